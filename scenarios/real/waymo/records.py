"""Reading Waymo Open Motion TFRecord files and parsing each ``Scenario`` record into plain
arrays (:class:`ScenarioRecord`, :class:`MapLine`), every field checked (the rules are in
the package docstring, :mod:`scenarios.real.waymo`, "Reading"); the bounds of one record."""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from epo_casadi.errors import SpecError, check_size

from ...dataset import DatasetError
from ..tfrecord import iter_records
from ..waymo_schema import OBJECT_TYPES, scenario_class

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
            from ...files import check_input_file

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
