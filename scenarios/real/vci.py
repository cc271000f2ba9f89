"""Vehicle-crowd clips in the layout of the CITR dataset (D. Yang et al., "Top-view
Trajectories: A Pedestrian Dataset of Vehicle-Crowd Interaction from Controlled Experiments
and Crowded Campus", IEEE IV 2019, arXiv:1902.00487) into the dataset format: scenes of a
vehicle and the pedestrians that interact with it most.

Clips
    A clip is a pair of CSV files found by name anywhere under the raw folder:
    ``<clip>_traj_ped_filtered.csv`` (required) and ``<clip>_traj_veh_filtered.csv`` (optional:
    a clip without it has no vehicle and makes no scene). A vehicle file without its
    pedestrian file is refused. Clips are ordered by their path relative to the raw folder
    (without the suffix), e.g. ``vci_back/back_interaction_01``. The experiment type of a
    clip is the name of the folder that holds its files; a clip directly in the raw folder
    takes the type of :data:`EXPERIMENT_TYPES` whose prefix its name starts with (the CITR
    names: ``back_interaction`` -> ``vci_back``, ``front_interaction`` -> ``vci_front``,
    ``bidirection_normal_driving`` -> ``vci_lat_bi``, ``unidirection_normal_driving`` and
    ``unidirection_yeild`` -> ``vci_lat_uni``, ``bidirection_no_vehicle`` -> ``p2p_bi``,
    ``unidirection_no_vehicle`` -> ``p2p_uni``), else its name without a trailing ``_<digits>``
    (``crossing_03`` -> ``crossing``). Both layouts of the CITR release thus give the same types.

Files
    CSV with a header (names stripped of spaces; other columns are not read, ``label`` neither).
    Pedestrians: ``id, frame, x_est, y_est, vx_est, vy_est``; vehicles: ``id, frame, x_est,
    y_est, psi_est, vel_est`` (Kalman-filtered estimates: metres in the recording's ground
    frame, m/s, radians). Every cell read must be a finite number: ``id`` a whole number in
    ``[0, 2^31 - 1]``, ``frame`` a whole number in ``[0, 10^7]``, ``|x|, |y| <= 10^4`` m,
    ``|vx|, |vy|, |vel| <= 100`` m/s, ``|psi| <= 1000`` rad; one ``(id, frame)`` per row. Rows
    may come in any order. Each file is at most 64 MiB. Every file is checked when the
    scenario is made (:meth:`VciScenario.from_raw`), before any work starts; every problem is
    one error naming the file, the column and the line. A file may hold several vehicles (or pedestrians): the ``id``
    tells them apart.

Resampling
    The files carry frame numbers, not times: a row's time is ``frame / fps`` (``fps`` a recipe
    field, default 29.97, the CITR videos'). A clip's grid starts at its first frame ``f0``
    (over both files): step ``k`` is at frame ``u_k = f0 + k dt fps``, time ``u_k / fps``. A
    track is cut into runs of rows at most ``max_frame_gap`` frames apart (default 1: any
    missing frame ends a run); each run is sampled at the grid steps inside it by linear
    interpolation between its two neighbouring rows, never across a gap (a run is a
    :class:`~scenarios.real.scenes.Track` on integer grid steps; runs of the same id are
    separate pieces, so no window spans a gap). Interpolated per step: ``x, y``; pedestrians
    ``vx, vy``, from which speed ``|(vx, vy)|`` and heading ``atan2(vy, vx)`` (unwrapped along
    the run); vehicles ``psi_est`` (unwrapped along the run at the recorded rate before
    interpolating) and ``vel_est``. The states ``(x, y, v, theta)`` are these recorded speeds
    and headings, not differences of positions.

Scenes (:func:`scenarios.real.scenes.window_scenes`, grid step 1)
    One scene per vehicle and current grid step at which the vehicle's run covers ``history``
    steps before and ``horizon`` after (every ``stride``-th step). Slot 0 is the vehicle; the
    other ``agents - 1`` slots are the pedestrians whose runs cover the same window, ranked by
    the closest-approach rule of :mod:`scenarios.real.scenes` on observed positions only
    (ties: the lower id); fewer pedestrians are padded (``agents_mask`` False). Other vehicles
    of the clip are not candidates unless ``vehicle_candidates`` (each vehicle is the focal
    agent of its own scenes). Positions are relative to the vehicle's current position
    (``origin``); the axes are those of the recording. ``track_id`` is the id in its file,
    ``agent_kind`` tells which file (:data:`KINDS`); ``radius``: ``radius`` for pedestrians
    (0.3 m), ``vehicle_radius`` for vehicles (1.1 m, half the golf cart's 2.2 m length: 1 m
    front bumper to centre, 1.2 m centre to rear bumper, width 1.2 m, as the CITR README
    measures it). No ``length`` / ``width`` fields (the pedestrians have no recorded size,
    so the overlap rate uses circles of ``radius``); the cart's size is ``meta.vehicle_size``.
    The vehicle is slot 0 (``meta.focal_slot``). ``others`` (figures only,
    ``context_agents`` of them): the nearest other agents of the clip over the window, NaN
    where not recorded (:mod:`scenarios.real.scenes`, "Context agents").

Splits (by clip)
    Per experiment type with a vehicle (sorted by name, one seeded generator for all): its
    ``n`` clips with a vehicle file are permuted; ``max(1, round(test_fraction n))`` go to
    test, ``max(1, round(val_fraction n))`` to validation, the rest (at least one) to train. A
    type with fewer than three such clips (two when a fraction is 0) goes to train whole
    (``meta.train_only_types``).
    Clips without a vehicle (no samples) are in train.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass, fields
from pathlib import Path as FilePath
from pathlib import PurePosixPath

import numpy as np

from epo_casadi import PotentialGame
from epo_casadi.errors import SpecError, check_bool, check_number, check_size, short_repr

from ..dataset import SPLITS, DatasetError, FieldSpec, RawScenario
from ..files import check_input_file
from .recipe import SceneRecipe
from .scenes import Track, crowd_game_spec, scene_schema, stack_scenes, window_scenes

__all__ = [
    "KINDS",
    "EXPERIMENT_TYPES",
    "PED_SUFFIX",
    "VEH_SUFFIX",
    "read_vci_pedestrians",
    "read_vci_vehicles",
    "find_clips",
    "experiment_type",
    "clip_tracks",
    "raw_digest",
    "VciRecipe",
    "VciScenario",
    "game_from_recipe",
]

#: agent kinds (index stored in ``agent_kind``)
KINDS = ("pedestrian", "vehicle")
PED_SUFFIX = "_traj_ped_filtered.csv"
VEH_SUFFIX = "_traj_veh_filtered.csv"
#: experiment type of a clip lying directly in the raw folder: the first prefix its name
#: starts with (the CITR clip names; the folder names of the CITR release)
EXPERIMENT_TYPES = (
    ("back_interaction", "vci_back"),
    ("front_interaction", "vci_front"),
    ("bidirection_normal_driving", "vci_lat_bi"),
    ("unidirection_normal_driving", "vci_lat_uni"),
    ("unidirection_yeild", "vci_lat_uni"),
    ("unidirection_yield", "vci_lat_uni"),
    ("bidirection_no_vehicle", "p2p_bi"),
    ("unidirection_no_vehicle", "p2p_uni"),
)

MAX_ID = 2**31 - 1  #: ids (stored as int32)
MAX_FRAME = 10_000_000  #: frame numbers (3.9 days at 29.97 Hz)
MAX_POSITION = 1e4  #: m, |x_est|, |y_est|
MAX_SPEED = 100.0  #: m/s, |vx_est|, |vy_est|, |vel_est|
MAX_HEADING = 1e3  #: rad, |psi_est|
MAX_CLIPS = 10_000  #: clips of one raw folder
MAX_GRID_CELLS = 50_000_000  #: resampled steps of all tracks of one clip
MAX_UNIT_BYTES = 2**31  #: the scenes of one clip in memory

# (column, bound, integer): numbers in [-bound, bound] ([0, bound] for the integer ones)
_PED = (
    ("id", MAX_ID, True),
    ("frame", MAX_FRAME, True),
    ("x_est", MAX_POSITION, False),
    ("y_est", MAX_POSITION, False),
    ("vx_est", MAX_SPEED, False),
    ("vy_est", MAX_SPEED, False),
)
_VEH = (
    ("id", MAX_ID, True),
    ("frame", MAX_FRAME, True),
    ("x_est", MAX_POSITION, False),
    ("y_est", MAX_POSITION, False),
    ("psi_est", MAX_HEADING, False),
    ("vel_est", MAX_SPEED, False),
)


# --------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------
def _read(path, columns) -> dict[str, np.ndarray]:
    """The checked cells of ``columns`` of the CSV at ``path``, rows sorted by (id, frame);
    ``line``: each row's line in the file."""
    import pandas as pd

    path = check_input_file(path, str(path))
    try:
        df = pd.read_csv(
            path, dtype=str, keep_default_na=False, skip_blank_lines=False, encoding="utf-8-sig"
        )
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, ValueError) as e:
        msg = " ".join(str(e).split())
        raise DatasetError(str(path), f"not a readable CSV ({short_repr(msg, 200)})") from None
    names = [str(c).strip() for c in df.columns]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DatasetError(f"{path}:{dup[0]}", "the header names this column twice (line 1)")
    df.columns = names
    for c, _, _ in columns:
        if c not in names:
            have = ", ".join(short_repr(n, 30) for n in names[:12])
            raise DatasetError(f"{path}:{c}", f"missing column (line 1 has {have})")
    lines = np.arange(len(df), dtype=np.int64) + 2  # line 1 is the header
    blank = (df == "").all(axis=1).to_numpy()
    df, lines = df[~blank], lines[~blank]
    if len(df) == 0:
        raise DatasetError(str(path), "no rows below the header")
    out = {}
    for c, bound, integer in columns:
        s = df[c].str.strip()
        v = pd.to_numeric(s, errors="coerce").to_numpy(dtype=float)
        lo = 0.0 if integer else -bound
        bad = ~np.isfinite(v) | (v < lo) | (v > bound)
        if integer:
            bad |= v != np.floor(v)
        if bad.any():
            i = int(np.argmax(bad))
            where, text = f"{path}:{c}", s.iloc[i]
            if text == "":
                got = "an empty value (a truncated line?)"
            elif not np.isfinite(v[i]):
                got = short_repr(text, 40)
            else:
                kind = "a whole number" if integer else "a number"
                raise DatasetError(
                    where, f"expected {kind} in [{lo:g}, {bound:g}], got {text} in line {lines[i]}"
                )
            kind = "a whole number" if integer else "a finite number"
            raise DatasetError(where, f"expected {kind}, got {got} in line {lines[i]}")
        out[c] = v
    ids, frames = out["id"].astype(np.int64), out["frame"].astype(np.int64)
    order = np.lexsort((lines, frames, ids))
    ids, frames = ids[order], frames[order]
    dup = (np.diff(ids) == 0) & (np.diff(frames) == 0)
    if dup.any():
        j = int(np.argmax(dup))
        a, b = sorted((int(lines[order[j]]), int(lines[order[j + 1]])))
        raise DatasetError(
            f"{path}:frame",
            f"id {ids[j]} has frame {frames[j]} twice (line {a} and line {b}); expected one "
            "row per id and frame",
        )
    res = {k: v[order] for k, v in out.items()}
    res["id"], res["frame"], res["line"] = ids, frames, lines[order]
    return res


def read_vci_pedestrians(path: str | FilePath) -> dict[str, np.ndarray]:
    """The rows of a ``<clip>_traj_ped_filtered.csv``, checked (module docstring) and sorted by
    (id, frame): ``id``, ``frame`` (int64), ``x``, ``y``, ``vx``, ``vy`` (float64), ``line``."""
    r = _read(path, _PED)
    return {
        "id": r["id"],
        "frame": r["frame"],
        "x": r["x_est"],
        "y": r["y_est"],
        "vx": r["vx_est"],
        "vy": r["vy_est"],
        "line": r["line"],
    }


def read_vci_vehicles(path: str | FilePath) -> dict[str, np.ndarray]:
    """The rows of a ``<clip>_traj_veh_filtered.csv``, checked (module docstring) and sorted by
    (id, frame): ``id``, ``frame`` (int64), ``x``, ``y``, ``psi`` (rad), ``vel`` (m/s),
    ``line``."""
    r = _read(path, _VEH)
    return {
        "id": r["id"],
        "frame": r["frame"],
        "x": r["x_est"],
        "y": r["y_est"],
        "psi": r["psi_est"],
        "vel": r["vel_est"],
        "line": r["line"],
    }


def experiment_type(clip: str) -> str:
    """The experiment type of a clip path relative to the raw folder (module docstring)."""
    p = PurePosixPath(clip)
    if len(p.parts) > 1:
        return p.parent.name
    for prefix, typ in EXPERIMENT_TYPES:
        if p.name.startswith(prefix):
            return typ
    return re.sub(r"_\d+$", "", p.name) or p.name


def find_clips(raw: str | FilePath) -> list[tuple[str, str, bool]]:
    """``(clip, experiment type, has a vehicle file)`` of every clip under ``raw``, sorted by
    the clip's path relative to ``raw`` (without the file suffix)."""
    raw = FilePath(raw)
    if not raw.is_dir():
        why = "is a file, expected a folder" if raw.exists() else "no such folder"
        raise DatasetError(str(raw), f"{why} (of clips <clip>{PED_SUFFIX}, <clip>{VEH_SUFFIX})")
    ped = {
        f.relative_to(raw).as_posix()[: -len(PED_SUFFIX)]
        for f in raw.rglob(f"*{PED_SUFFIX}")
        if f.name != PED_SUFFIX
    }
    veh = {
        f.relative_to(raw).as_posix()[: -len(VEH_SUFFIX)]
        for f in raw.rglob(f"*{VEH_SUFFIX}")
        if f.name != VEH_SUFFIX
    }
    lone = sorted(veh - ped)
    if lone:
        raise DatasetError(
            str(raw / f"{lone[0]}{VEH_SUFFIX}"),
            f"a vehicle file without its pedestrian file {FilePath(lone[0]).name}{PED_SUFFIX}",
        )
    if not ped:
        raise DatasetError(
            str(raw), f"holds no clip (no file named <clip>{PED_SUFFIX} in it or below it)"
        )
    check_size(f"{raw}:clips", len(ped), MAX_CLIPS, "clips of one raw folder")
    return [(c, experiment_type(c), c in veh) for c in sorted(ped)]


def raw_digest(raw: str | FilePath, clips) -> str:
    """sha256 over the clips' names and the bytes of their files (a different raw set
    refuses to resume a dataset)."""
    raw = FilePath(raw)
    h = hashlib.sha256()
    for c in clips:
        name, has_veh = c[0], c[2]
        for suffix in (PED_SUFFIX, VEH_SUFFIX) if has_veh else (PED_SUFFIX,):
            f = check_input_file(raw / f"{name}{suffix}", str(raw / f"{name}{suffix}"))
            data = f.read_bytes()
            h.update(f"{name}{suffix}:{len(data)}:".encode())
            h.update(data)
    return h.hexdigest()


# --------------------------------------------------------------------------------------
# resampling
# --------------------------------------------------------------------------------------
def _runs(ids: np.ndarray, frames: np.ndarray, max_gap: int) -> list[tuple[int, int]]:
    """``(lo, hi)`` row ranges of the runs of rows sorted by (id, frame)."""
    brk = (np.diff(ids) != 0) | (np.diff(frames) > max_gap)
    lo = np.r_[0, np.flatnonzero(brk) + 1]
    hi = np.r_[lo[1:], ids.size]
    return list(zip(lo.tolist(), hi.tolist(), strict=True))


def _grid(frames: np.ndarray, f0: int, step: float) -> np.ndarray:
    """The grid steps ``k`` whose frame ``f0 + k step`` lies within ``frames[0] .. frames[-1]``."""
    k_lo = math.ceil((frames[0] - f0) / step - 1e-9)
    k_hi = math.floor((frames[-1] - f0) / step + 1e-9)
    return np.arange(k_lo, k_hi + 1, dtype=np.int64)


def clip_tracks(
    ped: dict[str, np.ndarray],
    veh: dict[str, np.ndarray] | None,
    *,
    fps: float,
    dt: float,
    max_frame_gap: int = 1,
    vehicle_length: float = 0.0,
    vehicle_width: float = 0.0,
    where: str = "clip",
) -> tuple[list[Track], int]:
    """The runs of a clip's tracks resampled on its grid (module docstring, "Resampling"),
    and the grid's first frame ``f0``. Each run is a :class:`Track` on grid steps
    (``frames`` = ``k``) whose ``id`` is ``2 id + kind`` (kind 0 pedestrian, 1 vehicle, so
    the ids of the two files never meet; ``id >> 1`` is the file's id)."""
    tables = [(0, ped)] + ([] if veh is None else [(1, veh)])
    f0 = int(min(int(t["frame"].min()) for _, t in tables))
    step = float(dt) * float(fps)  # frames per grid step
    runs = [
        (kind, t, lo, hi)
        for kind, t in tables
        for lo, hi in _runs(t["id"], t["frame"], max_frame_gap)
    ]
    cells = sum((t["frame"][hi - 1] - t["frame"][lo]) / step + 1 for _, t, lo, hi in runs)
    check_size(
        f"{where}:frame",
        int(min(cells, 1e18)),
        MAX_GRID_CELLS,
        f"memory: resampled steps of the clip's tracks at dt {dt:g} s and {fps:g} frames/s",
        lo=0,
    )
    out = []
    for kind, t, lo, hi in runs:
        fr = t["frame"][lo:hi]
        k = _grid(fr, f0, step)
        if k.size == 0:
            continue
        u = f0 + k * step
        x, y = np.interp(u, fr, t["x"][lo:hi]), np.interp(u, fr, t["y"][lo:hi])
        if kind == 0:
            vx, vy = np.interp(u, fr, t["vx"][lo:hi]), np.interp(u, fr, t["vy"][lo:hi])
            speed, heading = np.hypot(vx, vy), np.unwrap(np.arctan2(vy, vx))
            length = width = 0.0
        else:
            heading = np.interp(u, fr, np.unwrap(t["psi"][lo:hi]))
            speed = np.interp(u, fr, t["vel"][lo:hi])
            length, width = vehicle_length, vehicle_width
        out.append(
            Track(
                int(t["id"][lo]) * 2 + kind,
                k,
                np.stack([x, y], axis=1),
                heading,
                speed,
                kind,
                float(length),
                float(width),
            )
        )
    return out, f0


# --------------------------------------------------------------------------------------
# recipe
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VciRecipe(SceneRecipe):
    """Everything that defines a vehicle-crowd dataset (with the seed); the fields of
    :class:`~scenarios.real.recipe.SceneRecipe` plus the reader's. ``clips`` and
    ``raw_digest`` are filled from the raw folder by :meth:`VciScenario.from_raw`. The clips
    are 5-14 s long, so the default window is short: 1 s observed (``history`` 5 steps plus
    the current one) and 3 s predicted (``horizon`` 15) at ``dt`` 0.2 s."""

    prefix = "vci"

    #: ``(clip, experiment type, has a vehicle file)`` of each unit; clip: its path relative
    #: to the raw folder without the file suffix
    clips: tuple[tuple[str, str, bool], ...] = ()
    raw_digest: str = ""  #: sha256 of the clips' names and files
    fps: float = 29.97  #: frames per second of the recordings (the files carry frames only)
    agents: int = 4  #: N: the vehicle and N - 1 pedestrians
    history: int = 5  #: H past steps (plus the current one): 1 s
    horizon: int = 15  #: T future steps: 3 s
    modes: int = 6  #: M future slots (slot 0 the recording)
    dt: float = 0.2  #: resampling step (s)
    radius: float = 0.3  #: collision radius of a pedestrian (m); the game's default radius
    vehicle_radius: float = 1.1  #: collision radius of a vehicle (m): half the golf cart's length
    vehicle_length: float = 2.2  #: m, the golf cart (CITR README: 1 m + 1.2 m from the centre)
    vehicle_width: float = 1.2  #: m, the golf cart (CITR README)
    vehicle_candidates: bool = False  #: other vehicles compete with pedestrians for the slots
    max_frame_gap: int = 1  #: rows further apart than this many frames end a run (a gap)
    val_fraction: float = 0.2  #: share of each experiment type's vehicle clips in val
    test_fraction: float = 0.2  #: ... and in test
    #: figures only: the ``others`` field holds this many other agents of the clip (0: none)
    context_agents: int = 16

    def __post_init__(self):
        super().__post_init__()
        p = self.prefix
        if isinstance(self.clips, (str, bytes)) or not isinstance(self.clips, (list, tuple)):
            raise SpecError(f"{p}.clips", "expected [[clip, experiment type, has vehicle], ...]")
        check_size(f"{p}.clips", len(self.clips), MAX_CLIPS, "clips of one dataset", lo=0)
        clips = []
        for i, c in enumerate(self.clips):
            if isinstance(c, (str, bytes)) or not isinstance(c, (list, tuple)) or len(c) != 3:
                raise SpecError(
                    f"{p}.clips[{i}]",
                    f"expected [clip, experiment type, has vehicle], got {short_repr(c)}",
                )
            name, typ, veh = c
            if not isinstance(name, str) or not name or len(name) > 4096:
                raise SpecError(
                    f"{p}.clips[{i}][0]", f"expected a clip path, got {short_repr(name)}"
                )
            pp = PurePosixPath(name)
            if pp.is_absolute() or ".." in pp.parts or "\\" in name:
                raise SpecError(
                    f"{p}.clips[{i}][0]",
                    f"expected a path relative to the raw folder, got {short_repr(name)}",
                )
            if not isinstance(typ, str) or not typ:
                raise SpecError(
                    f"{p}.clips[{i}][1]", f"expected a type name, got {short_repr(typ)}"
                )
            check_bool(f"{p}.clips[{i}][2]", veh)
            clips.append((name, typ, veh))
        if len({c[0] for c in clips}) != len(clips):
            raise SpecError(f"{p}.clips", "a clip is listed twice")
        object.__setattr__(self, "clips", tuple(clips))
        if not isinstance(self.raw_digest, str):
            raise SpecError(f"{p}.raw_digest", "expected a string")
        check_number(f"{p}.fps", self.fps, lo=0.1, hi=1000.0)
        check_number(f"{p}.max_frame_gap", self.max_frame_gap, lo=1, hi=1000, integer=True)
        for k in ("vehicle_radius", "vehicle_length", "vehicle_width"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, lo_open=True, hi=100.0)
        check_bool(f"{p}.vehicle_candidates", self.vehicle_candidates)
        for k in ("val_fraction", "test_fraction"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, hi=0.5)
        check_number(f"{p}.context_agents", self.context_agents, lo=0, hi=256, integer=True)

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["clips"] = [list(c) for c in self.clips]
        return d


# --------------------------------------------------------------------------------------
# scenario
# --------------------------------------------------------------------------------------
class VciScenario(RawScenario):
    """Scenes of vehicle-crowd clips (module docstring); one work unit per clip."""

    name = "vci"
    recipe_class = VciRecipe

    @classmethod
    def from_raw(cls, raw: str | FilePath, **overrides) -> VciScenario:
        """The scenario of every clip under ``raw`` (``overrides``: recipe fields; a ``clips``
        override given as clip paths selects clips). Every file of the chosen clips is read
        and checked here, so a malformed one is refused before any work starts."""
        found = find_clips(raw)
        want = overrides.pop("clips", None)
        if want is not None:
            if isinstance(want, (str, bytes)) or not isinstance(want, (list, tuple)):
                raise SpecError(
                    "vci.clips", f"expected a list of clip paths, got {short_repr(want)}"
                )
            names = [w[0] if isinstance(w, (list, tuple)) and w else w for w in want]
            by_name = {c[0]: c for c in found}
            bad = [n for n in names if not isinstance(n, str) or n not in by_name]
            if bad:
                raise SpecError(
                    "vci.clips",
                    f"no such clip(s) {short_repr(bad)} under {raw}; found "
                    f"{short_repr([c[0] for c in found])}",
                )
            found = [by_name[n] for n in sorted(set(names))]
        for name, _, has_veh in found:  # every file checked before any work starts
            read_vci_pedestrians(FilePath(raw) / f"{name}{PED_SUFFIX}")
            if has_veh:
                read_vci_vehicles(FilePath(raw) / f"{name}{VEH_SUFFIX}")
        if not any(c[2] for c in found):
            raise DatasetError(
                str(raw), f"no clip has a vehicle file (<clip>{VEH_SUFFIX}): no scene can be made"
            )
        recipe = VciRecipe.from_dict(
            {**overrides, "clips": [list(c) for c in found], "raw_digest": raw_digest(raw, found)}
        )
        return cls(recipe, raw)

    # ---- Scenario interface ----------------------------------------------------------
    @property
    def n_units(self) -> int:
        return len(self.recipe.clips)

    @property
    def units_per_shard(self) -> int:
        return 1

    def _types(self) -> tuple[dict[str, list[int]], list[str]]:
        """Vehicle clips by experiment type (types with a vehicle only) and the types that
        go to train whole (fewer clips than the splits need)."""
        r = self.recipe
        by_type: dict[str, list[int]] = {}
        for i, (_, typ, veh) in enumerate(r.clips):
            if veh:
                by_type.setdefault(typ, []).append(i)
        need = 1 + (r.val_fraction > 0) + (r.test_fraction > 0)
        train_only = sorted(t for t, u in by_type.items() if len(u) < need)
        return dict(sorted(by_type.items())), train_only

    def split_units(self, seed: int) -> dict[str, list[int]]:
        """By clip, within each experiment type with a vehicle (module docstring, "Splits")."""
        r = self.recipe
        by_type, train_only = self._types()
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0,)))
        out: dict[str, list[int]] = {s: [] for s in SPLITS}
        placed: set[int] = set()
        for typ, units in by_type.items():
            n = len(units)
            perm = [units[j] for j in rng.permutation(n)]
            placed.update(units)
            if typ in train_only:
                out["train"] += units
                continue
            nv = max(1, round(r.val_fraction * n)) if r.val_fraction > 0 else 0
            nt = max(1, round(r.test_fraction * n)) if r.test_fraction > 0 else 0
            while nv + nt > n - 1:  # keep a training clip
                if nv > nt or (nv == nt and nv > 1 and r.val_fraction <= r.test_fraction):
                    nv -= 1
                else:
                    nt -= 1
            out["test"] += perm[:nt]
            out["val"] += perm[nt : nt + nv]
            out["train"] += perm[nt + nv :]
        out["train"] += [i for i in range(self.n_units) if i not in placed]
        return {s: sorted(int(i) for i in out[s]) for s in SPLITS}

    def schema(self) -> dict[str, FieldSpec]:
        r = self.recipe
        # no length / width: the pedestrians have no recorded size (circles of `radius`
        # instead; the cart's size is in meta.vehicle_size)
        s = scene_schema(
            r.agents, r.history, r.horizon, r.modes, sizes=False, context=r.context_agents
        )
        s["frame"] = FieldSpec((), "int64", "video frame nearest the current step (time * fps)")
        s["time"] = FieldSpec(
            (), "float64", "time of the current step in the clip: frame / fps (s)"
        )
        s["clip"] = FieldSpec((), "int32", "index of the clip in meta.clips")
        return s

    def meta(self) -> dict:
        r = self.recipe
        by_type, train_only = self._types()
        return {
            "state": ["x", "y", "v", "theta"],
            "kinds": list(KINDS),
            "agents": [f"a{i}" for i in range(r.agents)],
            "slots": "slot 0 the vehicle, then pedestrians by closest approach (observed part)",
            "focal_slot": 0,
            "vehicle_size": {"length": r.vehicle_length, "width": r.vehicle_width},
            "clips": [c[0] for c in r.clips],
            "clip_types": [c[1] for c in r.clips],
            "clip_has_vehicle": [c[2] for c in r.clips],
            "experiment_types": sorted({c[1] for c in r.clips}),
            "types_with_vehicle": list(by_type),
            "train_only_types": train_only,
            "splits": "by clip within each experiment type with a vehicle",
            "fps": r.fps,
            "dt": r.dt,
            "frames_per_step": r.dt * r.fps,
            "raw": None if self.raw is None else str(self.raw),
            "frame": "recording's ground frame translated by origin (the vehicle's current "
            "position); not rotated",
            "units": "metres, seconds, radians",
        }

    # ---- extraction --------------------------------------------------------------------
    def tracks(self, index: int) -> tuple[list[Track], int]:
        """The resampled runs of clip ``index`` and its grid's first frame (:func:`clip_tracks`)."""
        r = self.recipe
        if self.raw is None:
            raise SpecError("vci.raw", "this scenario has no raw folder (VciScenario.from_raw)")
        name, _, has_veh = r.clips[index]
        ped = read_vci_pedestrians(self.raw / f"{name}{PED_SUFFIX}")
        veh = read_vci_vehicles(self.raw / f"{name}{VEH_SUFFIX}") if has_veh else None
        return clip_tracks(
            ped,
            veh,
            fps=r.fps,
            dt=r.dt,
            max_frame_gap=r.max_frame_gap,
            vehicle_length=r.vehicle_length,
            vehicle_width=r.vehicle_width,
            where=str(self.raw / f"{name}{PED_SUFFIX}"),
        )

    def run_unit(self, index: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
        """Every scene of clip ``clips[index]`` (deterministic; the seed does not enter); none
        for a clip without a vehicle."""
        r = self.recipe
        schema = self.schema()
        base = {k: v for k, v in schema.items() if k != "time"}
        if not r.clips[index][2]:
            return stack_scenes([], schema, 0.0)
        tracks, f0 = self.tracks(index)
        veh = sorted({t.id for t in tracks if t.kind == 1})
        span = r.history + r.horizon
        n = sum(max(0, t.frames.size - span + r.stride - 1) // r.stride for t in tracks if t.kind)
        per = (span + 1) * r.agents * 4 * 8 + r.modes * r.horizon * r.agents * 4 * 4
        per += r.context_agents * (span + 1) * 2 * 8
        check_size(
            f"{self.raw / r.clips[index][0]}{PED_SUFFIX}:frame",
            n * per,
            MAX_UNIT_BYTES,
            f"memory: {n:,} scenes of {per:,} bytes from one clip (fewer: a larger dt or stride)",
            lo=0,
        )
        cand = sorted({t.id for t in tracks if t.kind == 0 or r.vehicle_candidates})
        scenes = window_scenes(
            tracks,
            step=1,
            history=r.history,
            horizon=r.horizon,
            agents=r.agents,
            dt=r.dt,
            stride=r.stride,
            max_distance=r.max_distance,
            focal_ids=veh,
            candidate_ids=cand,
            context=r.context_agents,
        )
        step = r.dt * r.fps
        times = []
        for s in scenes:
            u = f0 + s["frame"] * step
            times.append(u / r.fps)
            s["frame"] = int(round(u))
            s["track_id"] = np.where(s["agents_mask"], s["track_id"] >> 1, -1)
        out = stack_scenes(scenes, base, np.array([r.radius, r.vehicle_radius]), {"clip": index})
        out["time"] = np.asarray(times, np.float64)
        return {k: out[k] for k in schema}


def game_from_recipe(recipe: dict) -> PotentialGame:
    """The game of a vci dataset (its manifest's recipe): the crowd game of
    :func:`scenarios.real.scenes.crowd_game_spec`."""
    return PotentialGame(crowd_game_spec(VciRecipe.from_dict(recipe)))
