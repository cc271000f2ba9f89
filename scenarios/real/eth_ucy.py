"""ETH/UCY pedestrians: the benchmark's text files into the dataset format.

Files
    Whitespace-separated text, no header, one row ``frame ped x y`` per pedestrian and
    frame: ``frame`` and ``ped`` whole numbers (written as ``780`` or ``780.0``), ``x``,
    ``y`` in metres (the recording's world frame). Blank lines are skipped. Every row is
    checked (:func:`read_eth_ucy`): exactly four columns, finite numbers, ``frame`` a
    whole number in ``0 .. 10^9``, ``ped`` a whole number in ``0 .. 2^31 - 1`` (``-1``
    marks padding in a sample), ``|x|, |y| <= 10^4`` m, no pedestrian twice at one frame,
    every frame on the file's grid. A file over 64 MiB is refused before it is read. Each
    problem is one :class:`~scenarios.dataset.DatasetError` at ``<file>:<line>`` naming
    the column and the value found.

Frame step
    The grid step of a file is the most common frame difference of consecutive rows of
    one pedestrian (10 in every shipped file); every frame must lie on the grid
    ``first frame + k * step``. One grid step is ``dt`` seconds (0.4 s, the benchmark's
    convention; ``--dt`` overrides it). A pedestrian whose rows skip a grid step is cut
    there into pieces (:func:`scenarios.real.scenes.contiguous_pieces`); nothing is
    interpolated, and no scene spans a gap.

Scenes (:func:`scenarios.real.scenes.window_scenes`)
    Every pedestrian is a focal agent at every current frame at which it is recorded over
    the whole window (``history + 1`` observed and ``horizon`` future steps; 8 and 12 by
    default: 3.2 s and 4.8 s). The others are up to ``agents - 1`` pedestrians recorded over
    the same window, those of smallest closest approach to the focal pedestrian when both
    walk on at the constant velocity of their last two observed positions over the
    prediction window (observed positions only, so the future does not enter the choice;
    ties: the lower id). A scene with fewer recorded pedestrians is padded
    (``agents_mask``). Positions are relative to the focal pedestrian's current position
    (``origin``); speeds and headings are backward differences of positions. The focal
    pedestrian is slot 0 (``meta.focal_slot``: the benchmark's ADE / FDE are its errors).
    No ``length`` / ``width`` (no size is recorded: the overlap rate uses circles of
    ``radius``). ``others`` (figures only, ``context_agents`` of them): the nearest other
    pedestrians of the file over the window, NaN where not recorded
    (:mod:`scenarios.real.scenes`, "Context agents").

Scenes and splits
    Each file belongs to a scene: ``biwi_eth.txt`` eth, ``biwi_hotel.txt`` hotel,
    ``students001.txt`` and ``students003.txt`` univ, ``crowds_zara01.txt`` zara1,
    ``crowds_zara02.txt`` zara2, ``crowds_zara03.txt`` zara3, ``uni_examples.txt``
    uni_examples. Leave one scene out: every file of ``test_scene`` (one of
    :data:`SCENES`) is test; every other file is training, and the last ``val_fraction``
    of its frame span is validation (train: windows that end before the cut frame; val:
    windows that start at or after it; windows across the cut are dropped, so no
    recorded step is in two splits). zara3 and uni_examples are never test.

Other files
    :meth:`EthUcyScenario.from_raw` takes the benchmark's files found directly in the raw
    folder; other files there are ignored (a warning names them and the manifest lists
    them in ``meta.ignored_files``). A file of the same format under another name is used
    when the recipe names it: ``files`` ``[[name, scene], ...]`` (names relative to the raw
    folder) replaces the search; a scene label outside :data:`SCENES` is training only.
"""

from __future__ import annotations

import hashlib
import math
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from epo_casadi import PotentialGame
from epo_casadi.errors import SpecError, check_number, check_size, short_repr

from ..dataset import SPLITS, DatasetError, FieldSpec, RawScenario
from ..files import check_input_file
from .recipe import SceneRecipe
from .scenes import (
    Track,
    contiguous_pieces,
    crowd_game_spec,
    scene_schema,
    stack_scenes,
    window_scenes,
)

__all__ = [
    "SCENES",
    "KNOWN_FILES",
    "EthUcyFile",
    "EthUcyRecipe",
    "EthUcyScenario",
    "read_eth_ucy",
    "read_eth_ucy_file",
    "game_from_recipe",
]

#: the scenes of the leave-one-scene-out protocol (the possible test scenes)
SCENES = ("eth", "hotel", "univ", "zara1", "zara2")
#: file name -> scene of the benchmark's files (zara3 and uni_examples only ever train)
KNOWN_FILES = {
    "biwi_eth.txt": "eth",
    "biwi_hotel.txt": "hotel",
    "students001.txt": "univ",
    "students003.txt": "univ",
    "crowds_zara01.txt": "zara1",
    "crowds_zara02.txt": "zara2",
    "crowds_zara03.txt": "zara3",
    "uni_examples.txt": "uni_examples",
}
COLUMNS = ("frame", "ped", "x", "y")
MAX_FRAME = 10**9  #: frames 0 .. MAX_FRAME
MAX_PED = 2**31 - 1  #: pedestrian ids 0 .. MAX_PED (stored as int32 track_id)
MAX_POSITION = 1e4  #: m, |x| and |y|
MAX_FILES = 1000  #: files of one dataset
#: bytes of the samples one file (one work unit) may give at most: rows x bytes per sample
MAX_UNIT_BYTES = 4 * 2**30
#: the step note of the manifest (the data's README)
DT_NOTE = (
    "one row step is dt seconds; the benchmark (and published results) take 0.4 s for every "
    "file; with 0.4 s the median walking speed in biwi_eth is 2.45 m/s (0.5-1.3 m/s in the "
    "others), with 0.667 s 1.47 m/s, which matches the raw ETH annotation"
)
INTERACTION_RULE = (
    "the focal pedestrian plus up to agents - 1 others recorded over the whole window: those "
    "of smallest closest approach to the focal one over the current step and the horizon, "
    "both extrapolated at the constant velocity of their last two observed positions "
    "(observed positions only: no future leak); ties by the lower id; others farther than "
    "max_distance at their closest approach are left out"
)
CITATION = (
    "ETH: S. Pellegrini, A. Ess, K. Schindler, L. van Gool, 'You'll never walk alone: "
    "modeling social behavior for multi-target tracking', ICCV 2009. UCY: A. Lerner, "
    "Y. Chrysanthou, D. Lischinski, 'Crowds by example', Computer Graphics Forum "
    "(Eurographics) 2007."
)
_LABEL = re.compile(r"[A-Za-z0-9_.-]{1,64}")


# --------------------------------------------------------------------------------------
# the reader
# --------------------------------------------------------------------------------------
@dataclass
class EthUcyFile:
    """One file read and checked: its tracks (one per pedestrian, sorted by id; not yet
    split at gaps), its frame grid step and extent."""

    path: Path
    tracks: list[Track]
    step: int  #: frames between consecutive grid rows
    first: int  #: first frame
    last: int  #: last frame
    rows: int

    @property
    def pedestrians(self) -> int:
        return len(self.tracks)


def _where(path: Path, line: int) -> str:
    return f"{path}:{int(line)}"


def _col(j: int) -> str:
    return f"column {j + 1} ({COLUMNS[j]})" if j < len(COLUMNS) else f"column {j + 1}"


def _parse(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(values (n, 4) float64, line numbers (n,))`` of the rows of ``path``, every cell
    checked (module docstring)."""
    import pandas as pd

    check_input_file(path, str(path))
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        start = data.rfind(b"\n", 0, e.start) + 1
        col = len(data[start : e.start].split())
        col = col if data[e.start - 1 : e.start].isspace() or col == 0 else col - 1
        raise DatasetError(
            _where(path, line), f"{_col(col)}: not text (byte {data[e.start]:#04x} is not UTF-8)"
        ) from None
    raw_lines = text.split("\n")
    cells = [ln.split() for ln in raw_lines]
    ncol = np.fromiter((len(c) for c in cells), np.int64, len(cells))
    lines = np.flatnonzero(ncol > 0) + 1
    if lines.size == 0:
        raise DatasetError(_where(path, 1), "no rows (an empty file); expected 'frame ped x y'")
    bad = np.flatnonzero((ncol != 0) & (ncol != 4))
    if bad.size:
        i = int(bad[0])
        n = int(ncol[i])
        if n < 4:
            msg = f"{_col(n)}: missing; the row has {n} column(s), expected 4 (frame ped x y)"
            if i == len(cells) - 1 or not any(ncol[i + 1 :]):
                msg += " (truncated file?)"
        else:
            msg = f"{_col(4)}: unexpected; the row has {n} columns, expected 4 (frame ped x y)"
        raise DatasetError(_where(path, i + 1), msg)
    flat = np.array([x for c in cells if c for x in c], dtype=object)
    v = pd.to_numeric(pd.Series(flat), errors="coerce").to_numpy(np.float64).reshape(-1, 4)
    lo = np.array([0.0, 0.0, -MAX_POSITION, -MAX_POSITION])
    hi = np.array([MAX_FRAME, MAX_PED, MAX_POSITION, MAX_POSITION], np.float64)
    with np.errstate(invalid="ignore"):
        wrong = ~np.isfinite(v) | (v < lo) | (v > hi)
        wrong[:, :2] |= v[:, :2] != np.floor(v[:, :2])
    if wrong.any():
        k = int(np.argmax(wrong.ravel()))
        i, j = divmod(k, 4)
        text_cell, x = str(flat[k]), float(v[i, j])
        if not math.isfinite(x):
            what = "a finite number"
        elif j < 2 and x != math.floor(x):
            what = "a whole number"
        else:
            what = (
                f"a whole number in [0, {int(hi[j]):,}]"
                if j < 2
                else f"a number in [{lo[j]:g}, {hi[j]:g}] (metres)"
            )
            if j == 1 and x < 0:
                what += " (-1 marks padding in a sample)"
        raise DatasetError(
            _where(path, lines[i]), f"{_col(j)}: expected {what}, got {short_repr(text_cell)}"
        )
    return v, lines


def read_eth_ucy_file(path: str | Path) -> EthUcyFile:
    """The file at ``path`` read and checked (module docstring): tracks, grid step, extent."""
    path = Path(path)
    v, lines = _parse(path)
    frame = v[:, 0].astype(np.int64)
    ped = v[:, 1].astype(np.int64)
    order = np.lexsort((lines, frame, ped))
    f, p, ln = frame[order], ped[order], lines[order]
    same = p[1:] == p[:-1]
    dup = np.flatnonzero(same & (f[1:] == f[:-1]))
    if dup.size:
        k = dup[np.argmin(ln[dup + 1])]
        raise DatasetError(
            _where(path, ln[k + 1]),
            f"columns 1-2 (frame, ped): pedestrian {int(p[k])} at frame {int(f[k])} again "
            f"(first in line {int(ln[k])})",
        )
    d = np.diff(f)[same]
    if d.size == 0:
        raise DatasetError(
            str(path), "no pedestrian has two rows: the file's frame step cannot be found"
        )
    steps, counts = np.unique(d, return_counts=True)
    step = int(steps[np.argmax(counts)])
    first = int(frame.min())
    off = (frame - first) % step != 0
    if off.any():
        i = int(np.argmax(off))
        raise DatasetError(
            _where(path, lines[i]),
            f"{_col(0)}: frame {int(frame[i])} is off the file's grid (a row every {step} "
            f"frames from frame {first}, the most common step of a pedestrian's rows)",
        )
    xy = v[order, 2:4]
    cuts = np.flatnonzero(~same) + 1
    tracks = [
        Track(int(p[a]), f[a:b].copy(), xy[a:b].copy())
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(f)], strict=True)
    ]
    return EthUcyFile(path, tracks, step, first, int(frame.max()), int(len(f)))


def read_eth_ucy(path: str | Path) -> list[Track]:
    """The pedestrians of the ETH/UCY file at ``path``, one :class:`Track` per id (sorted
    by id, frames sorted; not split at gaps), every row checked (module docstring)."""
    return read_eth_ucy_file(path).tracks


def raw_digest(raw: str | Path, files: Sequence[str]) -> str:
    """sha256 over the names and contents of ``files`` (in ``raw``): a different raw set
    refuses to resume a dataset."""
    h = hashlib.sha256()
    for name in files:
        p = check_input_file(Path(raw) / name, str(Path(raw) / name))
        h.update(f"{name}\0".encode())
        h.update(p.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


# --------------------------------------------------------------------------------------
# the recipe
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EthUcyRecipe(SceneRecipe):
    """Everything that defines an ETH/UCY dataset (with the seed). ``files`` (``[[file,
    scene], ...]``) and ``raw_digest`` are filled from the raw folder by
    :meth:`EthUcyScenario.from_raw`; the window and game fields are
    :class:`~scenarios.real.recipe.SceneRecipe`'s (8 observed, 12 future steps at 0.4 s,
    N = 4, M = 20, radius 0.3 m)."""

    prefix = "eth_ucy"

    files: tuple[tuple[str, str], ...] = ()  #: (file name in the raw folder, scene) per file
    raw_digest: str = ""  #: sha256 of the files' names and contents
    test_scene: str = "eth"  #: the left-out scene (one of SCENES)
    val_fraction: float = 0.1  #: the last share of each training file's frame span is val
    #: figures only: the ``others`` field holds this many other pedestrians (0: no field)
    context_agents: int = 16

    def __post_init__(self):
        super().__post_init__()
        p = self.prefix
        if isinstance(self.files, (str, bytes)) or not isinstance(self.files, (list, tuple)):
            raise SpecError(f"{p}.files", f"expected [[file, scene], ...], got {self.files!r}")
        check_size(f"{p}.files", len(self.files), MAX_FILES, "files of one dataset", lo=0)
        out = []
        for i, e in enumerate(self.files):
            if (
                not isinstance(e, (list, tuple))
                or len(e) != 2
                or not all(isinstance(x, str) for x in e)
            ):
                raise SpecError(
                    f"{p}.files[{i}]", f"expected [file name, scene], got {short_repr(e)}"
                )
            name, scene = e
            q = Path(name)
            if not name or q.is_absolute() or ".." in q.parts or len(name.encode()) > 1000:
                raise SpecError(
                    f"{p}.files[{i}]", f"expected a file name inside the raw folder, got {name!r}"
                )
            if not _LABEL.fullmatch(scene):
                raise SpecError(
                    f"{p}.files[{i}]",
                    f"expected a scene label of letters, digits, '_', '.', '-' (1 to 64), "
                    f"got {short_repr(scene)}",
                )
            out.append((name, scene))
        names = [n for n, _ in out]
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            raise SpecError(f"{p}.files", f"a file named twice: {twice}")
        object.__setattr__(self, "files", tuple(out))
        if not isinstance(self.raw_digest, str):
            raise SpecError(f"{p}.raw_digest", "expected a string")
        if self.test_scene not in SCENES:
            raise SpecError(
                f"{p}.test_scene", f"expected one of {list(SCENES)}, got {self.test_scene!r}"
            )
        check_number(f"{p}.val_fraction", self.val_fraction, lo=0.0, hi=0.9)
        check_number(f"{p}.context_agents", self.context_agents, lo=0, hi=256, integer=True)

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["files"] = [list(f) for f in self.files]
        return d


def game_from_recipe(recipe: dict) -> PotentialGame:
    """The game of an ETH/UCY dataset (its manifest recipe): the crowd game
    (:func:`scenarios.real.scenes.crowd_game_spec`)."""
    return PotentialGame(crowd_game_spec(EthUcyRecipe.from_dict(recipe)))


# --------------------------------------------------------------------------------------
# the scenario
# --------------------------------------------------------------------------------------
def find_files(raw: str | Path) -> tuple[list[tuple[str, str]], list[str]]:
    """The benchmark's files directly in ``raw`` (``[name, scene]`` in :data:`KNOWN_FILES`
    order) and the names of the other files there."""
    raw = Path(raw)
    if not raw.is_dir():
        why = "does not exist" if not raw.exists() else "is not a folder"
        raise DatasetError(str(raw), f"the raw folder {why}")
    names = sorted(p.name for p in raw.iterdir() if p.is_file())
    found = [[n, s] for n, s in KNOWN_FILES.items() if n in names]
    return found, [n for n in names if n not in KNOWN_FILES]


class EthUcyScenario(RawScenario):
    """Samples of the ETH/UCY files (:mod:`scenarios.real.eth_ucy`); one work unit per test
    file and per training or validation part of a training file."""

    name = "eth-ucy"
    recipe_class = EthUcyRecipe

    @classmethod
    def from_raw(cls, raw: str | Path, **overrides) -> EthUcyScenario:
        """The scenario of the benchmark's files in ``raw`` (``overrides``: recipe fields; a
        ``files`` override ``[[name, scene], ...]`` names the files instead). Every file is
        read and checked here, before any work."""
        raw = Path(raw)
        if "files" in overrides:
            if not raw.is_dir():
                find_files(raw)  # the folder's own error
            files = overrides.pop("files")
        else:
            files, other = find_files(raw)
            if not files:
                raise DatasetError(
                    str(raw),
                    f"no ETH/UCY file ({', '.join(KNOWN_FILES)}) in this folder"
                    + (f"; it has {short_repr(other)}" if other else "")
                    + "; name files of this format with --set files=[[name,scene],...]",
                )
            if other:
                warnings.warn(
                    f"{raw}: ignoring {len(other)} file(s) that are not ETH/UCY benchmark files: "
                    f"{', '.join(other[:5])}{', ...' if len(other) > 5 else ''} (to use a file "
                    "of this format, name every file in --set files=[[name,scene],...]; "
                    "listed in the manifest's meta.ignored_files)",
                    stacklevel=2,
                )
        probe = EthUcyRecipe.from_dict({**overrides, "files": files})
        names = [n for n, _ in probe.files]
        recipe = EthUcyRecipe.from_dict(
            {**overrides, "files": probe.files, "raw_digest": raw_digest(raw, names)}
        )
        sc = cls(recipe, raw)
        sc.check()
        return sc

    def check(self) -> None:
        """Read every file (refusing a malformed one), and refuse a recipe of which no
        split can be made or a file whose samples would not fit in memory."""
        r = self.recipe
        self.split_units(0)
        per = sum(
            int(np.prod(fs.shape)) * np.dtype(fs.dtype).itemsize for fs in self.schema().values()
        )
        for i, (name, _) in enumerate(r.files):
            f = self.file(i)
            check_size(
                f"{self.raw / name}",
                f.rows * per,
                MAX_UNIT_BYTES,
                f"memory: up to {f.rows:,} samples of {per:,} bytes; split the file in time",
            )

    # ---- files and units ---------------------------------------------------------------
    def file(self, i: int) -> EthUcyFile:
        """File ``i`` of the recipe, read once per process."""
        cache = self.__dict__.setdefault("_files", {})
        if i not in cache:
            if self.raw is None:
                raise SpecError(
                    "eth_ucy.raw", "this scenario has no raw folder (EthUcyScenario.from_raw)"
                )
            cache[i] = read_eth_ucy_file(self.raw / self.recipe.files[i][0])
        return cache[i]

    @cached_property
    def scenes(self) -> list[str]:
        """Scene labels (the ``scene`` field indexes this list): :data:`SCENES`, then the
        other labels of the recipe's files in order."""
        out = list(SCENES)
        for _, s in self.recipe.files:
            if s not in out:
                out.append(s)
        return out

    @cached_property
    def units(self) -> list[tuple[int, str]]:
        """``(file index, part)`` per work unit: part ``"test"`` (a test-scene file, whole),
        ``"train"`` and ``"val"`` (a training file before and after its cut frame;
        ``"train"`` is the whole file when ``val_fraction`` is 0)."""
        r = self.recipe
        out = []
        for i, (_, scene) in enumerate(r.files):
            if scene == r.test_scene:
                out.append((i, "test"))
            else:
                out.append((i, "train"))
                if r.val_fraction > 0:
                    out.append((i, "val"))
        return out

    def cut_frame(self, f: EthUcyFile) -> int:
        """The first validation frame of a training file: its first frame plus ``1 -
        val_fraction`` of its frame span, rounded to the grid (half up)."""
        k = math.floor((1.0 - self.recipe.val_fraction) * (f.last - f.first) / f.step + 0.5)
        return f.first + k * f.step

    def frame_range(self, index: int) -> tuple[int, int]:
        """Frames ``[lo, hi)`` of unit ``index`` (every frame of a sample lies inside)."""
        fi, part = self.units[index]
        f = self.file(fi)
        if part == "test" or (part == "train" and self.recipe.val_fraction == 0):
            return f.first, f.last + 1
        c = self.cut_frame(f)
        return (f.first, c) if part == "train" else (c, f.last + 1)

    # ---- Scenario interface ------------------------------------------------------------
    @property
    def n_units(self) -> int:
        return len(self.units)

    @property
    def units_per_shard(self) -> int:
        return 1

    def split_units(self, seed: int) -> dict[str, list[int]]:
        """Leave one scene out: the files of ``test_scene`` are test, the other files'
        parts train and val (by construction; ``seed`` is not used)."""
        r = self.recipe
        out = {s: [u for u, (_, part) in enumerate(self.units) if part == s] for s in SPLITS}
        if not out["test"] or not out["train"]:
            present = sorted({s for _, s in r.files})
            raise SpecError(
                "eth_ucy.test_scene",
                f"need a file of the test scene {r.test_scene!r} and a file of another scene; "
                f"scenes present: {present}",
            )
        return out

    def schema(self) -> dict[str, FieldSpec]:
        r = self.recipe
        # no length / width: pedestrians have no recorded size (circles of `radius` instead)
        out = scene_schema(
            r.agents, r.history, r.horizon, r.modes, sizes=False, context=r.context_agents
        )
        out["scene"] = FieldSpec((), "int16", "index in meta.scenes")
        out["file"] = FieldSpec((), "int16", "index in meta.files (recipe.files)")
        return out

    def meta(self) -> dict:
        r = self.recipe
        files = []
        for i, (name, scene) in enumerate(r.files):
            f = self.file(i)
            role = "test" if scene == r.test_scene else "train"
            files.append(
                {
                    "file": name,
                    "scene": scene,
                    "role": role,
                    "rows": f.rows,
                    "pedestrians": f.pedestrians,
                    "frame_step": f.step,
                    "first_frame": f.first,
                    "last_frame": f.last,
                    "val_from_frame": (
                        self.cut_frame(f) if role == "train" and r.val_fraction > 0 else None
                    ),
                }
            )
        ignored = []
        if self.raw is not None and self.raw.is_dir():
            used = {n for n, _ in r.files}
            ignored = sorted(
                p.name for p in self.raw.iterdir() if p.is_file() and p.name not in used
            )
        return {
            "state": ["x", "y", "v", "theta"],
            "kinds": ["pedestrian"],
            "agents": [f"a{i}" for i in range(r.agents)],
            "focal_slot": 0,
            "scenes": self.scenes,
            "test_scene": r.test_scene,
            "files": files,
            "work_units": [
                [r.files[i][0], part, *self.frame_range(u)]
                for u, (i, part) in enumerate(self.units)
            ],
            "ignored_files": ignored,
            "raw": None if self.raw is None else str(self.raw),
            "dt": r.dt,
            "dt_note": DT_NOTE,
            "frame_steps": {n: self.file(i).step for i, (n, _) in enumerate(r.files)},
            "interaction_rule": INTERACTION_RULE,
            "frame": "the recording's world frame translated by origin (the focal pedestrian's "
            "current position); not rotated",
            "units": "metres, seconds, radians",
            "citation": CITATION,
        }

    def tracks(self, index: int) -> tuple[EthUcyFile, list[Track]]:
        """The file of unit ``index`` and its pieces without gaps inside the unit's frames."""
        fi, _ = self.units[index]
        f = self.file(fi)
        lo, hi = self.frame_range(index)
        pieces = []
        for t in f.tracks:
            keep = (t.frames >= lo) & (t.frames < hi)
            if keep.any():
                pieces += contiguous_pieces(Track(t.id, t.frames[keep], t.xy[keep]), f.step)
        return f, pieces

    def run_unit(self, index: int, seed) -> dict[str, np.ndarray]:
        r = self.recipe
        fi, _ = self.units[index]
        f, pieces = self.tracks(index)
        scenes = window_scenes(
            pieces,
            step=f.step,
            history=r.history,
            horizon=r.horizon,
            agents=r.agents,
            dt=r.dt,
            stride=r.stride,
            max_distance=r.max_distance,
            context=r.context_agents,
        )
        extra = {"scene": self.scenes.index(r.files[fi][1]), "file": fi}
        return stack_scenes(scenes, self.schema(), r.radius, extra=extra)
