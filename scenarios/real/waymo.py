"""Waymo Open Motion scenarios (TFRecord files of ``Scenario`` records) as a dataset.

Reading
    :func:`read_scenarios` reads TFRecord files (:mod:`scenarios.real.tfrecord`: the
    framing and its CRC-32C checks, no TensorFlow) and parses every payload with the
    ``protobuf`` package against the schema of :mod:`scenarios.real.waymo_schema` (the
    fields listed there; others are skipped). Each record is checked: it must have a
    ``scenario_id``, timestamps 0.1 s apart (10 Hz, within 0.02 s), tracks whose state count
    equals the timestamps', a ``current_time_index`` and ``sdc_track_index`` inside them,
    ``tracks_to_predict`` indices and ``objects_of_interest`` ids of its tracks, object
    types 0..4, and at every *valid* state finite values within bounds (positions within
    10^7 m, sizes within [0, 100] m, velocities within 200 m/s). Any problem is one
    :class:`~scenarios.dataset.DatasetError` naming ``<file>:record <i>`` and the field.

Agents: interacting pairs (the paper's Waymo setting, App. F)
    ``pairs="auto"`` (default): the ``objects_of_interest`` when the record lists at least
    two (the interactive split labels exactly two), else the ``tracks_to_predict``;
    ``"interest"`` / ``"predict"`` use only that list. Every pair of the listed tracks is a
    candidate (in list order), kept when both are of the recipe's ``types`` (default all of
    vehicle, pedestrian, cyclist; the paper keeps vehicles only: ``--set types=[vehicle]``)
    and both have ``valid`` states at every step of the window. A pair with an invalid step
    on the window's grid is skipped (never interpolated), and every skip is counted in the
    manifest's ``meta.skipped``. The choice reads the lists and the flags only, no
    positions. Slot 0 is the pair's vehicle when it has one vehicle, else the first in list
    order. With ``agents`` N > 2 the other N - 2 slots are the tracks of the kept types
    valid over the whole window chosen by :func:`scenarios.real.scenes.closest_approach`
    (observed positions only; padded and masked when there are fewer).

Window and units
    One scene per pair at the record's ``current_time_index`` c: ``history`` H past steps
    and the current one, ``horizon`` T future steps, ``step`` s grid steps (0.1 s) apart:
    states ``c - H s .. c + T s``. The defaults are the paper's: s = 1 (dt 0.1 s), H = 10
    (1 s of history plus the current step), T = 80 (8 s), M = 6 modes, collisions every 5th
    step. The game's horizon is T, so s = 5 (``--set step=5``: dt 0.5 s, H = 2, T = 16,
    collisions every step, the same 0.5 s apart) is a five times shorter game for quick
    runs. States: ``(x, y, v, theta)`` with the recorded centre, the speed
    ``|(velocity_x, velocity_y)|`` and the recorded heading, unwrapped over the window
    (the current one in [-pi, pi)). ``radius`` = length / 2 at the current step (the
    paper's r = L / 2), ``length`` and ``width`` the current box.

Scene frame
    ``origin`` is the slot-0 agent's current position in the record's frame; positions,
    lanes and goal candidates are relative to it. The axes stay the record's (no rotation).

Lanes (the map input)
    Every lane centre polyline (``MapFeature.lane``) is cut into pieces of equal arc length
    at most ``lane_piece`` metres (20 m), each resampled to ``lane_points`` P points (10);
    the ``lane_count`` L (128) pieces nearest to any recorded agent's current position
    within ``lane_range`` (150 m), nearest first, are ``lanes`` ``(L, P, 2)``; fewer fill
    the first slots and ``lanes_mask`` ``(L,)`` marks them, ``lane_id`` gives each piece's
    map feature id (-1: empty). ``speed_limit`` is the limit of the lane of each agent's
    nearest piece (m/s; 0 without lanes).

Goal candidates (no future)
    A pool of map points: every lane centre and crosswalk outline resampled every
    ``goal_spacing`` metres (2 m). For agent i at position p, speed v and heading theta,
    the pool points within R = ``goal_scale`` v T dt + ``goal_margin`` (1.5 v T dt + 10 m)
    of p, thinned to ``goal_points`` G (64) by farthest-point sampling that starts at the
    pool point nearest the constant-velocity end point p + v T dt (cos theta, sin theta).
    With fewer than G points in range all are taken and the rest are points of a Vogel
    spiral of radius R around p (``goal_candidates_on_map`` False). Only the current state
    enters. Padded slots are zeros.

Splits (by scenario: a scenario's pairs stay in one split)
    The scenarios of ``--raw`` files train; of ``--val`` files validate; of ``--test``
    files test (the paper: train on the official training split, test on the validation
    split). Without ``--test`` files, a seeded share ``test_fraction`` (0.1, at least one
    scenario) of the ``--raw`` scenarios tests; without ``--val`` files a seeded share
    ``val_fraction`` (0.1, at least one when three or more remain) of the rest validates.
    So the two scenarios of the Waymo test data run end to end (one trains, one tests, no
    validation). Fewer than one training and one test scenario is refused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size

from ..dataset import SPLITS, DatasetError, FieldSpec, Scenario
from ..maps import arc_length, resample_at
from .recipe import SceneRecipe
from .scenes import (
    Track,
    closest_approach,
    crowd_game_spec,
    scene_schema,
    select_agents,
    stack_scenes,
    window_scenes,
)
from .tfrecord import iter_records, read_record
from .waymo_schema import OBJECT_TYPES, scenario_class

__all__ = [
    "GRID_DT",
    "OBJECT_TYPES",
    "MapLine",
    "ScenarioRecord",
    "WaymoRecipe",
    "WaymoScenario",
    "draw_scenarios",
    "find_files",
    "game_from_recipe",
    "parse_scenario",
    "read_scenarios",
]

#: the recordings' step (s): Waymo Open Motion is sampled at 10 Hz
GRID_DT = 0.1
#: timestamps may differ from GRID_DT by this much (s)
DT_TOLERANCE = 0.02
#: bounds of one record (memory) and of a valid state's values
MAX_STEPS = 10_000
MAX_CELLS = 10**7  #: tracks x steps of one record
MAX_MAP_POINTS = 10**7
MAX_POSITION = 1e7  #: m
MAX_SIZE = 100.0  #: m (length, width, height)
MAX_SPEED = 200.0  #: m/s per velocity component
MAX_FILES = 100_000
MPH = 0.44704  #: m/s per mile per hour

#: state columns of :attr:`ScenarioRecord.states`
STATE_FIELDS = (
    "center_x",
    "center_y",
    "center_z",
    "length",
    "width",
    "height",
    "heading",
    "velocity_x",
    "velocity_y",
)
MAP_KINDS = ("lane", "road_line", "road_edge", "crosswalk")


# --------------------------------------------------------------------------------------
# records
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class MapLine:
    """One map feature: ``kind`` (``lane``, ``road_line``, ``road_edge``, ``crosswalk``),
    its enum ``type``, ``points`` ``(k, 3)`` (a crosswalk's polygon, closed implicitly) and
    for lanes the entry and exit lane ids and the speed limit (mph)."""

    id: int
    kind: str
    type: int
    points: np.ndarray
    entry: tuple[int, ...] = ()
    exit: tuple[int, ...] = ()
    speed_limit_mph: float = 0.0


@dataclass(frozen=True, eq=False)
class ScenarioRecord:
    """One parsed ``Scenario`` record (the fields of :mod:`scenarios.real.waymo_schema`)."""

    file: str
    index: int  #: record index in the file (from 0)
    offset: int  #: byte offset of the record
    scenario_id: str
    timestamps: np.ndarray  #: (S,) s
    current: int  #: current_time_index
    track_ids: np.ndarray  #: (n,) int64
    object_type: np.ndarray  #: (n,) int64 (OBJECT_TYPES)
    states: np.ndarray  #: (n, S, 9) float64, columns STATE_FIELDS
    valid: np.ndarray  #: (n, S) bool
    sdc: int  #: sdc_track_index
    interest: tuple[int, ...]  #: objects_of_interest (track ids)
    predict: tuple[tuple[int, int], ...]  #: tracks_to_predict (track index, difficulty)
    map: tuple[MapLine, ...] = ()

    @property
    def where(self) -> str:
        return f"{self.file}:record {self.index}"

    def lines(self, kind: str) -> list[MapLine]:
        return [m for m in self.map if m.kind == kind]


def _bad(where: str, field: str, message: str) -> DatasetError:
    return DatasetError(where, f"{field}: {message}")


def _message(payload: bytes, where: str):
    from google.protobuf.message import DecodeError

    try:
        return scenario_class().FromString(payload)
    except DecodeError as e:
        raise DatasetError(where, f"not a Waymo Scenario protocol buffer ({e})") from None


def _head(msg, where: str):
    """The checks of the fields every pass needs: id, timestamps, tracks, indices."""
    if not msg.scenario_id:
        raise DatasetError(where, "not a Waymo Scenario: no scenario_id")
    ts = np.asarray(msg.timestamps_seconds, np.float64)
    S = len(ts)
    if S < 2:
        raise _bad(where, "timestamps_seconds", f"expected at least 2 timestamps, got {S}")
    if S > MAX_STEPS:
        raise _bad(where, "timestamps_seconds", f"{S:,} steps is over the limit of {MAX_STEPS:,}")
    d = np.diff(ts)
    if not np.isfinite(ts).all() or not (np.abs(d - GRID_DT) <= DT_TOLERANCE).all():
        k = int(np.flatnonzero(~(np.abs(d - GRID_DT) <= DT_TOLERANCE))[0]) if len(d) else 0
        raise _bad(
            where,
            f"timestamps_seconds[{k + 1}]",
            f"expected steps of {GRID_DT} s (10 Hz, within {DT_TOLERANCE} s); "
            f"{ts[k]!r} -> {ts[k + 1]!r}",
        )
    n = len(msg.tracks)
    if n == 0:
        raise DatasetError(where, "not a Waymo Scenario: no tracks")
    if n * S > MAX_CELLS:
        raise _bad(where, "tracks", f"{n:,} tracks x {S} steps is over the limit of {MAX_CELLS:,}")
    c = msg.current_time_index
    if not 0 <= c < S:
        raise _bad(where, "current_time_index", f"expected 0 .. {S - 1}, got {c}")
    if not 0 <= msg.sdc_track_index < n:
        raise _bad(where, "sdc_track_index", f"expected 0 .. {n - 1}, got {msg.sdc_track_index}")
    ids = np.array([t.id for t in msg.tracks], np.int64)
    if len(np.unique(ids)) != n:
        srt = np.sort(ids)
        dup = int(srt[np.flatnonzero(np.diff(srt) == 0)[0]])
        raise _bad(where, "tracks.id", f"track id {dup} appears twice")
    types = np.array([t.object_type for t in msg.tracks], np.int64)
    bad = np.flatnonzero((types < 0) | (types >= len(OBJECT_TYPES)))
    if bad.size:
        raise _bad(
            where,
            f"tracks[{bad[0]}].object_type",
            f"expected 0 .. {len(OBJECT_TYPES) - 1} ({', '.join(OBJECT_TYPES)}), got {types[bad[0]]}",
        )
    for k, t in enumerate(msg.tracks):
        if len(t.states) != S:
            raise _bad(
                where,
                f"tracks[{k}].states",
                f"{len(t.states)} states, expected {S} (one per timestamp)",
            )
    pred = []
    for k, p in enumerate(msg.tracks_to_predict):
        if not 0 <= p.track_index < n:
            raise _bad(
                where,
                f"tracks_to_predict[{k}].track_index",
                f"expected 0 .. {n - 1}, got {p.track_index}",
            )
        pred.append((int(p.track_index), int(p.difficulty)))
    known = set(ids.tolist())
    for k, i in enumerate(msg.objects_of_interest):
        if i not in known:
            raise _bad(where, f"objects_of_interest[{k}]", f"no track has id {i}")
    return ts, ids, types, tuple(pred), tuple(int(i) for i in msg.objects_of_interest)


def _states(msg, rows: Iterable[int], where: str) -> tuple[np.ndarray, np.ndarray]:
    """``states`` ``(k, S, 9)`` and ``valid`` ``(k, S)`` of the tracks ``rows`` (checked at
    valid states)."""
    rows = list(rows)
    S = len(msg.timestamps_seconds)
    raw = [
        (
            s.center_x,
            s.center_y,
            s.center_z,
            s.length,
            s.width,
            s.height,
            s.heading,
            s.velocity_x,
            s.velocity_y,
            s.valid,
        )
        for k in rows
        for s in msg.tracks[k].states
    ]
    a = np.array(raw, np.float64).reshape(len(rows), S, len(STATE_FIELDS) + 1)
    st, va = a[..., :-1], a[..., -1] != 0
    v = st[va]  # (m, 9) valid states only
    bound = np.array([MAX_POSITION] * 3 + [MAX_SIZE] * 3 + [100.0] + [MAX_SPEED] * 2)
    lo = np.array([-MAX_POSITION] * 3 + [0.0] * 3 + [-100.0] + [-MAX_SPEED] * 2)
    ok = np.isfinite(v) & (v <= bound) & (v >= lo)
    if not ok.all():
        j, col = np.argwhere(~ok)[0]
        a, t = np.argwhere(va)[j]
        raise _bad(
            where,
            f"tracks[{rows[a]}].states[{t}].{STATE_FIELDS[col]}",
            f"expected a finite number in [{lo[col]:g}, {bound[col]:g}] at a valid state, "
            f"got {v[j, col]!r}",
        )
    return st, va


def _map(msg, where: str) -> tuple[MapLine, ...]:
    out = []
    total = 0
    for k, f in enumerate(msg.map_features):
        kind = f.WhichOneof("feature_data")
        if kind not in MAP_KINDS:
            continue
        m = getattr(f, kind)
        pts = m.polygon if kind == "crosswalk" else m.polyline
        total += len(pts)
        if total > MAX_MAP_POINTS:
            raise _bad(where, "map_features", f"over {MAX_MAP_POINTS:,} map points")
        xyz = np.array([(p.x, p.y, p.z) for p in pts], np.float64).reshape(-1, 3)
        if not (np.isfinite(xyz).all() and (np.abs(xyz) <= MAX_POSITION).all()):
            raise _bad(
                where,
                f"map_features[{k}].{kind}",
                f"expected finite points within {MAX_POSITION:g} m",
            )
        if kind == "lane":
            sl = float(m.speed_limit_mph)
            if not (math.isfinite(sl) and 0 <= sl <= 1000):
                raise _bad(where, f"map_features[{k}].lane.speed_limit_mph", f"got {sl!r}")
            out.append(
                MapLine(
                    int(f.id), kind, int(m.type), xyz, tuple(m.entry_lanes), tuple(m.exit_lanes), sl
                )
            )
        else:
            out.append(MapLine(int(f.id), kind, int(getattr(m, "type", 0)), xyz))
    return tuple(out)


def parse_scenario(payload: bytes, file: str = "<bytes>", index: int = 0, offset: int = 0):
    """The :class:`ScenarioRecord` of one ``Scenario`` payload (checked: module docstring)."""
    where = f"{file}:record {index}"
    msg = _message(payload, where)
    ts, ids, types, pred, interest = _head(msg, where)
    st, va = _states(msg, range(len(ids)), where)
    return ScenarioRecord(
        str(file),
        int(index),
        int(offset),
        str(msg.scenario_id),
        ts,
        int(msg.current_time_index),
        ids,
        types,
        st,
        va,
        int(msg.sdc_track_index),
        interest,
        pred,
        _map(msg, where),
    )


def find_files(paths: Sequence[str | os.PathLike], option: str = "--raw") -> list[Path]:
    """The TFRecord files of ``paths``: a file as given, a folder's regular files whose name
    contains ``tfrecord`` (sorted; the Waymo names are ``training.tfrecord-00000-of-01000``
    and the like). A missing path, an empty folder or a file given twice is refused."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if "tfrecord" in q.name and q.is_file())
            if not found:
                raise SpecError(option, f"no TFRecord files (names with 'tfrecord') in {p}")
            out += found
        else:
            from ..files import check_input_file

            out.append(check_input_file(p, option, max_bytes=None))
    seen: dict[str, Path] = {}
    for p in out:
        key = os.path.realpath(p)
        if key in seen:
            raise SpecError(option, f"{p} is given twice")
        seen[key] = p
    check_size(option, len(out), MAX_FILES, "TFRecord files of one dataset")
    return out


def _records(path: Path):
    n = 0
    for rec in iter_records(path):
        n += 1
        yield rec
    if n == 0:
        raise DatasetError(str(path), "no records: an empty file, not a TFRecord file of Scenarios")


def read_scenarios(files: Sequence[str | os.PathLike]) -> list[ScenarioRecord]:
    """Every ``Scenario`` record of ``files`` (files or folders, :func:`find_files`), parsed
    and checked; errors name the file and the record."""
    out = []
    for p in find_files(files, "files"):
        for rec in _records(p):
            out.append(parse_scenario(rec.payload, str(p), rec.index, rec.offset))
    return out


# --------------------------------------------------------------------------------------
# the recipe
# --------------------------------------------------------------------------------------
PAIR_RULES = ("auto", "interest", "predict")


@dataclass(frozen=True)
class WaymoRecipe(SceneRecipe):
    """Everything that defines a Waymo dataset (with the seed). ``history``, ``horizon``,
    ``dt`` and ``collision_every`` left at None follow ``step`` (the module docstring);
    ``files`` and ``raw_digest`` are filled by :meth:`WaymoScenario.from_raw`."""

    prefix = "waymo"

    agents: int = 2  #: N: the interacting pair (+ N - 2 nearest others)
    history: int | None = None  #: H past steps (None: 10 // step, 1 s)
    horizon: int | None = None  #: T future steps (None: 80 // step, 8 s)
    modes: int = 6  #: M (the paper's Waymo setting)
    dt: float | None = None  #: 0.1 s x step
    radius: float = 2.5  #: the game's default radius (m); samples set L / 2
    collision_every: int | None = None  #: None: every 0.5 s (5 // step, at least 1)
    step: int = 1  #: grid steps (0.1 s) per sample step
    pairs: str = "auto"  #: "auto", "interest" (objects_of_interest), "predict" (tracks_to_predict)
    types: tuple[str, ...] = ("vehicle", "pedestrian", "cyclist")  #: object types kept
    lane_count: int = 128  #: L lane pieces
    lane_points: int = 10  #: P points per piece
    lane_piece: float = 20.0  #: longest piece (m)
    lane_range: float = 150.0  #: pieces farther from every agent are left out (m)
    goal_points: int = 64  #: G goal candidates per agent
    goal_spacing: float = 2.0  #: spacing of the candidate pool along lanes and crosswalks (m)
    goal_scale: float = 1.5  #: candidate range: goal_scale * v * T * dt ...
    goal_margin: float = 10.0  #: ... + goal_margin (m)
    val_fraction: float = 0.1  #: seeded val share of the --raw scenarios (without --val)
    test_fraction: float = 0.1  #: seeded test share of the --raw scenarios (without --test)
    files: tuple[tuple[str, str], ...] = ()  #: (file name, "train" | "val" | "test")
    raw_digest: str = ""  #: sha256 of the files' names, sizes and the units read from them

    def __post_init__(self):
        p = self.prefix
        check_number(f"{p}.step", self.step, lo=1, hi=80, integer=True)
        s = self.step
        if self.dt is None:
            object.__setattr__(self, "dt", round(GRID_DT * s, 12))
        else:
            check_number(f"{p}.dt", self.dt, lo=0.01, hi=8.0)
            if abs(self.dt - GRID_DT * s) > 1e-9:
                raise SpecError(
                    f"{p}.dt",
                    f"is {GRID_DT} s x step (the recordings' 10 Hz) = {GRID_DT * s:g} s, "
                    f"got {self.dt}; set step instead",
                )
        for k, default in (("history", 10 // s), ("horizon", 80 // s)):
            if getattr(self, k) is None:
                object.__setattr__(self, k, max(default, 1 if k == "history" else 2))
        if self.collision_every is None:
            object.__setattr__(self, "collision_every", max(1, round(5 / s)))
        super().__post_init__()
        check_number(f"{p}.agents", self.agents, lo=2, integer=True)
        if self.stride != 1:
            raise SpecError(f"{p}.stride", "expected 1: one scene per pair, at current_time_index")
        if self.pairs not in PAIR_RULES:
            raise SpecError(f"{p}.pairs", f"expected one of {list(PAIR_RULES)}, got {self.pairs!r}")
        types = self.types
        if isinstance(types, str) or not isinstance(types, (list, tuple)) or not types:
            raise SpecError(
                f"{p}.types", f"expected a list of {list(OBJECT_TYPES[1:])}, got {types!r}"
            )
        for t in types:
            if t not in OBJECT_TYPES[1:]:
                raise SpecError(
                    f"{p}.types", f"expected names of {list(OBJECT_TYPES[1:])}, got {t!r}"
                )
        object.__setattr__(self, "types", tuple(dict.fromkeys(types)))
        for k, lo, hi in (
            ("lane_count", 1, 4096),
            ("lane_points", 2, 1000),
            ("goal_points", 1, 10000),
        ):
            check_number(f"{p}.{k}", getattr(self, k), lo=lo, integer=True)
            check_size(f"{p}.{k}", getattr(self, k), hi, "the size of every sample", lo=lo)
        for k in ("lane_piece", "lane_range", "goal_spacing", "goal_margin"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, lo_open=True, hi=1e6)
        check_number(f"{p}.goal_scale", self.goal_scale, lo=0.0, hi=100.0)
        for k in ("val_fraction", "test_fraction"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, hi=0.9)
        try:
            files = tuple((str(a), str(b)) for a, b in self.files)
        except (TypeError, ValueError):
            raise SpecError(f"{p}.files", "expected [[file name, split], ...]") from None
        for _name, split in files:
            if split not in SPLITS:
                raise SpecError(f"{p}.files", f"expected a split of {list(SPLITS)}, got {split!r}")
        object.__setattr__(self, "files", files)
        if not isinstance(self.raw_digest, str):
            raise SpecError(f"{p}.raw_digest", "expected a string")

    @property
    def span(self) -> tuple[int, int]:
        """Grid steps before and after the current one: ``(H s, T s)``."""
        return self.history * self.step, self.horizon * self.step

    def grid(self, current: int) -> np.ndarray:
        """Record step indices of a window at ``current``: ``(H + 1 + T,)``."""
        return current + self.step * np.arange(-self.history, self.horizon + 1)


def game_from_recipe(recipe: dict):
    """The game of a Waymo dataset from its manifest recipe (the crowd game, App. F.3)."""
    from epo_casadi import PotentialGame

    return PotentialGame(crowd_game_spec(WaymoRecipe.from_dict(recipe)))


# --------------------------------------------------------------------------------------
# the pair rule (lists and valid flags only)
# --------------------------------------------------------------------------------------
def _listed(r: WaymoRecipe, ids: np.ndarray, interest, pred) -> list[int]:
    """Track indices of the pair rule's list (order kept, duplicates dropped)."""
    by_id = {int(t): k for k, t in enumerate(ids)}
    inter = list(dict.fromkeys(by_id[i] for i in interest))
    predict = list(dict.fromkeys(k for k, _ in pred))
    if r.pairs == "interest" or (r.pairs == "auto" and len(inter) >= 2):
        return inter
    return predict


def _pairs(r: WaymoRecipe, where, ts, current, ids, types, valid_of, interest, pred):
    """``(pairs, skipped)``: the kept pairs (track indices, slot order) and the counts of
    skipped ones by reason (``type``, ``invalid``; ``no pair``: fewer than two listed)."""
    before, after = r.span
    S = len(ts)
    if current - before < 0 or current + after > S - 1:
        raise _bad(
            where,
            "current_time_index",
            f"the window needs {before} steps before and {after} after the current step "
            f"{current} (history {r.history} x step {r.step}, horizon {r.horizon} x step "
            f"{r.step}); the record has {S} steps",
        )
    listed = _listed(r, ids, interest, pred)
    skipped = {"type": 0, "invalid": 0, "no pair": 0}
    if len(listed) < 2:
        skipped["no pair"] = 1
        return [], skipped
    keep = {OBJECT_TYPES.index(t) for t in r.types}
    grid = r.grid(current)
    out = []
    for a, b in itertools.combinations(listed, 2):
        if int(types[a]) not in keep or int(types[b]) not in keep:
            skipped["type"] += 1
            continue
        if not (valid_of(a)[grid].all() and valid_of(b)[grid].all()):
            skipped["invalid"] += 1
            continue
        veh = [k for k in (a, b) if types[k] == 1]
        out.append((b, a) if veh == [b] else (a, b))
    return out, skipped


def _scan(r: WaymoRecipe, payload: bytes, where: str):
    """The pairs of one record, reading only the listed tracks' flags and types."""
    msg = _message(payload, where)
    ts, ids, types, pred, interest = _head(msg, where)
    cache: dict[int, np.ndarray] = {}

    def valid_of(k):
        if k not in cache:
            cache[k] = _states(msg, [k], where)[1][0]
        return cache[k]

    pairs, skipped = _pairs(
        r, where, ts, msg.current_time_index, ids, types, valid_of, interest, pred
    )
    return str(msg.scenario_id), pairs, skipped


# --------------------------------------------------------------------------------------
# map geometry
# --------------------------------------------------------------------------------------
def _dedupe(xy: np.ndarray) -> np.ndarray:
    if len(xy) < 2:
        return xy
    keep = np.r_[True, np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6]
    return xy[keep]


def lane_pieces(rec: ScenarioRecord, piece: float, points: int):
    """Every lane centre cut into equal pieces of at most ``piece`` m, each ``points``
    points: ``(pts (K, P, 2), lane index into rec.lines("lane") (K,))``."""
    pts, which = [], []
    for k, ln in enumerate(rec.lines("lane")):
        xy = _dedupe(ln.points[:, :2])
        if len(xy) < 2:
            continue
        total = float(arc_length(xy)[-1])
        n = max(1, math.ceil(total / piece - 1e-9))
        edges = np.linspace(0.0, total, n + 1)
        s = np.linspace(edges[:-1], edges[1:], points, axis=1)  # (n, P)
        pts.append(resample_at(xy, s.ravel()).reshape(n, points, 2))
        which += [k] * n
    if not pts:
        return np.zeros((0, points, 2)), np.zeros(0, np.int64)
    return np.concatenate(pts), np.array(which, np.int64)


def _distance_to_pieces(p: np.ndarray, pieces: np.ndarray) -> np.ndarray:
    """Distance ``(K,)`` of the point ``p`` ``(2,)`` to each piece ``(K, P, 2)``."""
    a, b = pieces[:, :-1], pieces[:, 1:]
    ab = b - a
    L2 = np.maximum((ab**2).sum(-1), 1e-18)
    t = np.clip(((p - a) * ab).sum(-1) / L2, 0.0, 1.0)
    d = np.linalg.norm(a + t[..., None] * ab - p, axis=-1)
    return d.min(axis=1)


def goal_pool(rec: ScenarioRecord, spacing: float) -> np.ndarray:
    """Points ``(Q, 2)`` every ``spacing`` m along the lane centres and crosswalk outlines."""
    out = []
    for ln in rec.map:
        if ln.kind not in ("lane", "crosswalk"):
            continue
        xy = ln.points[:, :2]
        if ln.kind == "crosswalk" and len(xy) >= 2:
            xy = np.concatenate([xy, xy[:1]])
        xy = _dedupe(xy)
        if len(xy) < 2:
            out.append(xy)
            continue
        total = float(arc_length(xy)[-1])
        out.append(resample_at(xy, np.arange(0.0, total + 1e-9, spacing)))
    return np.concatenate(out) if out else np.zeros((0, 2))


def _spiral(n: int, radius: float) -> np.ndarray:
    """``n`` points of a Vogel (golden-angle) spiral filling a disc of ``radius``."""
    k = np.arange(n) + 0.5
    r = radius * np.sqrt(k / max(n, 1))
    a = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def goal_candidates(
    pool: np.ndarray, p: np.ndarray, v: float, theta: float, reach: float, G: int, R: float
) -> tuple[np.ndarray, np.ndarray]:
    """``G`` candidates ``(G, 2)`` and their on-map flags for an agent at ``p`` (the module
    docstring; ``reach`` = v T dt, ``R`` the candidate range)."""
    near = pool[np.linalg.norm(pool - p, axis=1) <= R] if len(pool) else pool
    if len(near) >= G:
        end = p + reach * np.array([math.cos(theta), math.sin(theta)])
        j = int(np.argmin(np.linalg.norm(near - end, axis=1)))
        idx = [j]
        d = np.linalg.norm(near - near[j], axis=1)
        for _ in range(G - 1):
            j = int(np.argmax(d))
            idx.append(j)
            d = np.minimum(d, np.linalg.norm(near - near[j], axis=1))
        return near[idx], np.ones(G, bool)
    fill = p + _spiral(G - len(near), R)
    on = np.r_[np.ones(len(near), bool), np.zeros(G - len(near), bool)]
    return np.concatenate([near, fill]), on


# --------------------------------------------------------------------------------------
# the scenario
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Unit:
    scenario: int  #: index into WaymoScenario.scenarios
    tracks: tuple[int, int]  #: the pair's track indices, slot order


@dataclass(frozen=True)
class _Source:
    file: int  #: index into WaymoScenario.paths
    index: int  #: record index in the file
    offset: int
    scenario_id: str


class WaymoScenario(Scenario):
    """Samples of Waymo Open Motion records (module docstring); one work unit per pair."""

    name = "waymo"
    pickled = ("recipe", "paths", "scenarios", "units", "skipped")

    def __init__(
        self,
        recipe: WaymoRecipe | None = None,
        paths: Sequence[str] = (),
        scenarios: Sequence[_Source] = (),
        units: Sequence[_Unit] = (),
        skipped: dict | None = None,
    ):
        if recipe is not None and not isinstance(recipe, WaymoRecipe):
            raise SpecError("recipe", f"expected a WaymoRecipe, got {type(recipe).__name__}")
        self.recipe = recipe or WaymoRecipe()
        self.paths = tuple(str(p) for p in paths)
        self.scenarios = tuple(scenarios)
        self.units = tuple(units)
        self.skipped = dict(skipped or {})

    @classmethod
    def from_raw(
        cls,
        raw: Sequence[str | os.PathLike],
        val: Sequence[str | os.PathLike] = (),
        test: Sequence[str | os.PathLike] = (),
        **overrides,
    ) -> WaymoScenario:
        """The scenario of every record in the files (or folders) ``raw`` (train), ``val``
        and ``test``; ``overrides`` are recipe fields."""
        for k in ("files", "raw_digest"):
            if k in overrides:
                raise SpecError(f"--set {k}", "is read from --raw, --val and --test")
        recipe = WaymoRecipe.from_dict(overrides)
        tagged: list[tuple[Path, str]] = []
        for option, split, given in (
            ("--raw", "train", raw),
            ("--val", "val", val),
            ("--test", "test", test),
        ):
            if given:
                tagged += [(p, split) for p in find_files(given, option)]
        if not tagged:
            raise SpecError("--raw", "expected at least one TFRecord file")
        keys = [os.path.realpath(p) for p, _ in tagged]
        if len(set(keys)) != len(keys):
            dup = next(p for (p, _), k in zip(tagged, keys, strict=True) if keys.count(k) > 1)
            raise SpecError("--raw", f"{dup} is given twice (in --raw, --val or --test)")
        h = hashlib.sha256()
        sources, units = [], []
        skipped = {"type": 0, "invalid": 0, "no pair": 0}
        for fi, (path, split) in enumerate(tagged):
            h.update(f"{path.name}\0{split}\0{path.stat().st_size}\0".encode())
            for rec in _records(path):
                where = f"{path}:record {rec.index}"
                sid, pairs, sk = _scan(recipe, rec.payload, where)
                for k, v in sk.items():
                    skipped[k] += v
                h.update(f"{rec.offset}\0{sid}\0{pairs}\0".encode())
                if pairs:
                    units += [_Unit(len(sources), tuple(int(t) for t in pr)) for pr in pairs]
                    sources.append(_Source(fi, rec.index, rec.offset, sid))
        if not units:
            raise DatasetError(
                "--raw",
                f"no pair to make a sample of in {len(tagged)} file(s): {skipped['no pair']} "
                "record(s) list fewer than "
                f"two agents, {skipped['type']} pair(s) of other types than {list(recipe.types)}, "
                f"{skipped['invalid']} with invalid steps in the window",
            )
        recipe = dataclasses.replace(
            recipe,
            files=tuple((p.name, s) for p, s in tagged),
            raw_digest=h.hexdigest(),
        )
        return cls(recipe, [os.path.abspath(p) for p, _ in tagged], sources, units, skipped)

    # ---- Scenario interface ----------------------------------------------------------
    @property
    def n_units(self) -> int:
        return len(self.units)

    @property
    def units_per_shard(self) -> int:
        return 64

    def scenario_splits(self, seed: int) -> dict[str, list[int]]:
        """Split -> scenario indices (the module docstring, "Splits")."""
        r = self.recipe
        tags = [r.files[s.file][1] for s in self.scenarios]
        by = {s: [i for i, t in enumerate(tags) if t == s] for s in SPLITS}
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0,)))
        given = {t for _, t in r.files}
        train = list(by["train"])
        if "test" not in given and train:
            nt = min(max(1, round(r.test_fraction * len(train))), len(train) - 1)
            pick = set(rng.permutation(len(train))[:nt].tolist()) if nt > 0 else set()
            by["test"] = sorted(train[j] for j in pick)
            train = [u for j, u in enumerate(train) if j not in pick]
        if "val" not in given and r.val_fraction > 0 and len(train) >= 3:
            nv = min(max(1, round(r.val_fraction * len(train))), len(train) - 1)
            pick = set(rng.permutation(len(train))[:nv].tolist())
            by["val"] = sorted(train[j] for j in pick)
            train = [u for j, u in enumerate(train) if j not in pick]
        by["train"] = train
        if not by["train"] or not by["test"]:
            raise SpecError(
                "--raw",
                f"need scenarios with a pair for training and for testing; got "
                f"{len(by['train'])} train, {len(by['val'])} val, {len(by['test'])} test "
                "(give more --raw scenarios, or --test files)",
            )
        return {s: sorted(by[s]) for s in SPLITS}

    def split_units(self, seed: int) -> dict[str, list[int]]:
        """By scenario (:meth:`scenario_splits`): a scenario's pairs are in one split."""
        sc = self.scenario_splits(seed)
        where = {i: s for s, ids in sc.items() for i in ids}
        out: dict[str, list[int]] = {s: [] for s in SPLITS}
        for u, unit in enumerate(self.units):
            out[where[unit.scenario]].append(u)
        return out

    def schema(self) -> dict[str, FieldSpec]:
        r = self.recipe
        N, L, P, G = r.agents, r.lane_count, r.lane_points, r.goal_points
        out = scene_schema(N, r.history, r.horizon, r.modes)
        out["agent_kind"] = FieldSpec((N,), "int8", "Waymo object type, index in meta.kinds")
        out["radius"] = FieldSpec((N,), "float32", "length / 2 (m), the paper's r = L / 2")
        out["frame"] = FieldSpec((), "int64", "current_time_index of the record")
        out.update(
            {
                "lanes": FieldSpec((L, P, 2), "float32", "lane centre pieces nearest the agents"),
                "lanes_mask": FieldSpec((L,), "bool", "True: a lane piece; False: empty slot"),
                "lane_id": FieldSpec((L,), "int64", "map feature id of each piece (-1: empty)"),
                "goal_candidates": FieldSpec(
                    (N, G, 2), "float32", "map points near each agent (current state only)"
                ),
                "goal_candidates_on_map": FieldSpec(
                    (N, G), "bool", "False: a spiral point (too few map points in range)"
                ),
                "speed_limit": FieldSpec(
                    (N,), "float32", "limit of each agent's nearest lane (m/s)"
                ),
                "scenario": FieldSpec((), "int32", "index in meta.scenarios"),
            }
        )
        return out

    @cached_property
    def game(self):
        from epo_casadi import PotentialGame

        return PotentialGame(crowd_game_spec(self.recipe))

    def meta(self) -> dict:
        r = self.recipe
        return {
            "state": ["x", "y", "v", "theta"],
            "kinds": list(OBJECT_TYPES),
            "types": list(r.types),
            "agents": [f"a{i}" for i in range(r.agents)],
            "dt": r.dt,
            "step": r.step,
            "units": "metres, seconds, radians",
            "frame": "the record's frame translated by origin (the slot-0 agent's current "
            "position); not rotated",
            "pairs": r.pairs,
            "skipped": dict(self.skipped),
            "files": [[p, t] for p, (_, t) in zip(self.paths, r.files, strict=True)],
            "scenarios": [s.scenario_id for s in self.scenarios],
            "param_names": list(self.game.params.names),
            "source": "Waymo Open Motion Dataset (Waymo non-commercial licence)",
        }

    # ---- extraction --------------------------------------------------------------------
    def record(self, scenario: int) -> ScenarioRecord:
        """The parsed record of scenario index ``scenario`` (the last one is kept)."""
        cache = self.__dict__.get("_cache")
        if cache is not None and cache[0] == scenario:
            return cache[1]
        s = self.scenarios[scenario]
        path = self.paths[s.file]
        rec = parse_scenario(read_record(path, s.offset, s.index), path, s.index, s.offset)
        if rec.scenario_id != s.scenario_id:
            raise DatasetError(
                rec.where,
                f"scenario_id {rec.scenario_id!r}, expected {s.scenario_id!r}: the file changed "
                "since the dataset was planned",
            )
        extra = {
            "pieces": lane_pieces(rec, self.recipe.lane_piece, self.recipe.lane_points),
            "pool": goal_pool(rec, self.recipe.goal_spacing),
        }
        self.__dict__["_cache"] = (scenario, rec, extra)
        return rec

    def _extra(self) -> dict:
        return self.__dict__["_cache"][2]

    def agents_of(self, rec: ScenarioRecord, pair: tuple[int, int]) -> list[int]:
        """Track indices of a pair's scene: the pair, then up to N - 2 others (the module
        docstring), closest approach on observed positions only."""
        r = self.recipe
        out = list(pair)
        if r.agents <= 2:
            return out
        grid = r.grid(rec.current)
        H = r.history
        keep = np.isin(rec.object_type, [OBJECT_TYPES.index(t) for t in r.types])
        ok = rec.valid[:, grid].all(axis=1) & keep
        ok[list(pair)] = False
        cand = np.flatnonzero(ok)
        if cand.size == 0:
            return out
        obs = rec.states[:, grid[: H + 1], :2]
        scores = closest_approach(obs[pair[0]], obs[cand], r.horizon)
        pick = select_agents(scores, rec.track_ids[cand], r.agents - 2, r.max_distance)
        return out + [int(cand[j]) for j in pick]

    def cut(self, rec: ScenarioRecord, pair: tuple[int, int], scenario: int) -> dict:
        """The sample of one pair (every schema field)."""
        r = self.recipe
        H, T, N, s = r.history, r.horizon, r.agents, r.step
        grid = r.grid(rec.current)
        agents = self.agents_of(rec, pair)
        tracks = []
        for k in agents:
            st = rec.states[k, grid]
            head = np.unwrap(st[:, 6])
            head -= 2 * math.pi * math.floor((head[H] + math.pi) / (2 * math.pi))
            tracks.append(
                Track(
                    int(rec.track_ids[k]),
                    grid.astype(np.int64),
                    st[:, :2].copy(),
                    head,
                    np.hypot(st[:, 7], st[:, 8]),
                    int(rec.object_type[k]),
                    float(st[H, 3]),
                    float(st[H, 4]),
                )
            )
        ids = [t.id for t in tracks]
        (scene,) = window_scenes(
            tracks,
            step=s,
            history=H,
            horizon=T,
            agents=N,
            dt=r.dt,
            focal_ids=[ids[0]],
            candidate_ids=ids[1:],
        )
        # the slots in the pair's order (window_scenes orders the others by closest approach)
        order = [list(scene["track_id"]).index(i) for i in ids] + list(range(len(ids), N))
        for k in ("agents_mask", "track_id", "kind", "length", "width"):
            scene[k] = scene[k][order]
        scene["history"] = scene["history"][:, order]
        scene["gt"] = scene["gt"][order]
        base = scene_schema(N, H, T, r.modes)
        out = stack_scenes([scene], base, radius=0.0)
        out = {k: v[0] for k, v in out.items()}
        mask = out["agents_mask"]
        out["radius"] = np.where(mask, 0.5 * out["length"], 0.0).astype(np.float32)
        origin = scene["origin"]
        # lanes
        pieces, which = self._extra()["pieces"]
        L, P, G = r.lane_count, r.lane_points, r.goal_points
        cur = np.array([t.xy[H] for t in tracks])  # (k, 2) world frame
        lanes = np.zeros((L, P, 2))
        lmask = np.zeros(L, bool)
        lid = np.full(L, -1, np.int64)
        limit = np.zeros(N)
        lines = rec.lines("lane")
        if len(pieces):
            d = np.stack([_distance_to_pieces(p, pieces) for p in cur])  # (k, K)
            dmin = d.min(axis=0)
            inside = np.flatnonzero(dmin <= r.lane_range)
            sel = inside[np.lexsort((inside, dmin[inside]))][:L]
            lanes[: len(sel)] = pieces[sel] - origin
            lmask[: len(sel)] = True
            lid[: len(sel)] = [lines[which[j]].id for j in sel]
            for a in range(len(tracks)):
                limit[a] = lines[which[int(np.argmin(d[a]))]].speed_limit_mph * MPH
        # goal candidates
        pool = self._extra()["pool"]
        cand = np.zeros((N, G, 2))
        on = np.zeros((N, G), bool)
        for a, t in enumerate(tracks):
            v, th = float(t.speed[H]), float(t.heading[H])
            reach = v * T * r.dt
            c, o = goal_candidates(
                pool, t.xy[H], v, th, reach, G, r.goal_scale * reach + r.goal_margin
            )
            cand[a], on[a] = c - origin, o
        out.update(
            {
                "lanes": lanes.astype(np.float32),
                "lanes_mask": lmask,
                "lane_id": lid,
                "goal_candidates": cand.astype(np.float32),
                "goal_candidates_on_map": on,
                "speed_limit": limit.astype(np.float32),
                "scenario": np.int32(scenario),
                "frame": np.int64(rec.current),
            }
        )
        return out

    def run_unit(self, index: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
        """The sample of pair ``units[index]`` (deterministic; the seed does not enter)."""
        u = self.units[index]
        rec = self.record(u.scenario)
        row = self.cut(rec, u.tracks, u.scenario)
        return {k: np.asarray(row[k]).astype(fs.dtype)[None] for k, fs in self.schema().items()}


# --------------------------------------------------------------------------------------
# figures
# --------------------------------------------------------------------------------------
def draw_record(rec: ScenarioRecord, pairs: Sequence[tuple[int, ...]], recipe: WaymoRecipe, path):
    """One figure of a record: the map (lane centres, road lines, road edges, crosswalks),
    every other valid track's current position, and the agents of ``pairs`` (track index
    tuples): history solid, future dashed, current position marked. Written to ``path``."""
    from ..plotting import _figure, agent_colors, save_figure

    fig = _figure((8.0, 8.0))
    ax = fig.add_subplot(1, 1, 1)
    style = {
        "lane": {"color": "0.75", "lw": 0.8, "ls": "-"},
        "road_line": {"color": "0.55", "lw": 0.6, "ls": "--"},
        "road_edge": {"color": "0.1", "lw": 1.2, "ls": "-"},
    }
    for m in rec.map:
        xy = m.points[:, :2]
        if m.kind == "crosswalk":
            if len(xy) >= 3:
                ax.fill(*xy.T, color="#cfe3f7", ec="#7aa9d6", lw=0.6, zorder=0)
        elif len(xy) >= 2:
            ax.plot(*xy.T, zorder=1, **style[m.kind])
    grid = recipe.grid(rec.current)
    H = recipe.history
    chosen = list(dict.fromkeys(k for p in pairs for k in p))
    others = [k for k in range(len(rec.track_ids)) if k not in chosen and rec.valid[k, rec.current]]
    if others:
        ax.scatter(
            *rec.states[others, rec.current, :2].T,
            s=6,
            color="0.45",
            zorder=2,
            label="other tracks",
        )
    pts = []
    for c, k in zip(agent_colors(len(chosen)), chosen, strict=True):
        xy = rec.states[k, grid, :2]
        ok = rec.valid[k, grid]
        hist = np.where(ok[: H + 1, None], xy[: H + 1], np.nan)
        fut = np.where(ok[H:, None], xy[H:], np.nan)
        kind = OBJECT_TYPES[int(rec.object_type[k])]
        ax.plot(*hist.T, "-", color=c, lw=2.2, zorder=4)
        ax.plot(*fut.T, "--", color=c, lw=1.4, zorder=4)
        ax.plot(
            *xy[H],
            "o",
            color=c,
            ms=7,
            mec="k",
            zorder=5,
            label=f"track {rec.track_ids[k]} ({kind})",
        )
        pts.append(xy[ok])
    if pts:
        allp = np.concatenate(pts)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        mid, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2 + 20.0, 40.0)
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(
        f"scenario {rec.scenario_id}: history {H * recipe.dt:g} s (solid), future "
        f"{recipe.horizon * recipe.dt:g} s (dashed)",
        fontsize=9,
    )
    ax.legend(loc="upper right", fontsize=7)
    return save_figure(fig, path, "--draw")


def draw_scenarios(scenario: WaymoScenario, folder: str | os.PathLike) -> list[Path]:
    """One PNG per scenario of ``scenario`` (:func:`draw_record`) into ``folder``:
    ``<scenario_id>.png``."""
    from ..files import ensure_dir

    folder = ensure_dir(folder)
    pairs: dict[int, list] = {}
    for u in scenario.units:
        pairs.setdefault(u.scenario, []).append(u.tracks)
    out = []
    for si, prs in sorted(pairs.items()):
        rec = scenario.record(si)
        agents = [scenario.agents_of(rec, p) for p in prs]
        out.append(draw_record(rec, agents, scenario.recipe, folder / f"{rec.scenario_id}.png"))
    return out
