"""The exiD release layout: a reader for its recordings and lanelet2 maps, and the paper's
sample extraction (App. E "exiD", App. F.3) into the toolkit's dataset format.

Release layout (exiD v2, the levelXdata family shared with inD / rounD / uniD)
    ``DIR/data/NN_tracks.csv``, ``NN_tracksMeta.csv``, ``NN_recordingMeta.csv`` per
    recording ``NN`` (the three CSVs may also lie directly in ``DIR``), and one lanelet2
    map per location, ``DIR/maps/lanelet2/<locationId>_<name>.osm`` (or ``<locationId>.osm``;
    also looked for in ``DIR/maps`` and ``DIR``). The column names are those of the
    format documentation of the levelXdata datasets (ika, RWTH Aachen: "inD/rounD/uniD
    format 1.1", shared by exiD) and of ika's ``drone-dataset-tools`` reader
    (``src/tracks_import.py``: ``read_tracks`` / ``read_tracks_meta`` /
    ``read_recording_meta``); exiD adds the lane columns (``laneletId``,
    ``latLaneCenterOffset``, ``laneWidth``, ``lonLaneletPos``, ... , where a vehicle on
    two lanelets has ``"id1;id2"``). Columns read:

    ``NN_tracks.csv`` (one row per track and frame): ``recordingId, trackId, frame,
    xCenter, yCenter`` (m, local frame = UTM minus the recording's ``xUtmOrigin,
    yUtmOrigin``), ``heading`` (deg, counter-clockwise from +x), ``width, length`` (m),
    ``xVelocity, yVelocity`` (m/s), ``xAcceleration, yAcceleration`` (m/s^2),
    ``lonVelocity, latVelocity, lonAcceleration, latAcceleration``; optional
    ``laneletId`` (first id of a ``;`` list; empty or ``-1``: none; without the column
    the lanelet is found on the map).
    ``NN_tracksMeta.csv`` (one row per track): ``recordingId, trackId, initialFrame,
    finalFrame, numFrames, width, length, class``.
    ``NN_recordingMeta.csv`` (one row): ``recordingId, locationId, frameRate,
    xUtmOrigin, yUtmOrigin``; optional ``speedLimit`` (m/s; ``-1`` or missing: none),
    ``latLocation, lonLocation, duration, numTracks, ...``.

    Every problem is a :class:`~scenarios.dataset.DatasetError` whose ``where`` is
    ``<file>:<column>`` (a missing file or column, a cell with its line, a track whose row
    count differs from its ``numFrames``, a frame rate that does not divide the sampling
    step). Every table goes through one check, :func:`read_table` with the
    :class:`Column` s of :data:`TRACKS_TABLE`, :data:`TRACKS_META_TABLE`,
    :data:`RECORDING_META_TABLE`: each cell read must be a finite number (not ``nan``,
    ``inf``, text or empty) within its bounds, a whole number where an integer is meant.
    The columns not listed are not read. Then: recordingMeta has one row, the
    ``recordingId`` of every row is the file name's ``NN``, a track has one tracksMeta
    row and one tracks row per frame, its frames run from ``initialFrame`` to
    ``finalFrame`` without gaps, and ``laneletId`` holds ids (``id`` or ``id1;id2``, empty
    or ``-1``: none).

Bounds (inclusive; each a module constant)
    ``recordingId``, ``locationId``: integers 0 .. 32767 (:data:`MAX_ID`, stored as int16;
    also the ``NN`` of the file names); ``trackId``: 0 .. 2^31 - 1; frames (``frame``,
    ``initialFrame``, ``finalFrame``): 0 .. 10^7 (:data:`MAX_FRAME`), ``numFrames`` >= 1;
    ``xCenter``, ``yCenter``: within 10^6 m of the local origin (:data:`MAX_POSITION`);
    ``xUtmOrigin``, ``yUtmOrigin``: within 10^7 m (:data:`MAX_UTM`, the extent of UTM
    coordinates); ``heading``: -360 .. 360 deg; ``width``: (0, 10] m, ``length``: (0, 50]
    m (tracks and tracksMeta); every velocity component within 100 m/s
    (:data:`MAX_SPEED`), every acceleration component within 100 m/s^2
    (:data:`MAX_ACCELERATION`); ``frameRate``: 1 .. 1000 Hz; ``speedLimit``: -1 .. 100 m/s
    (<= 0: none); ``latLocation``: -90 .. 90, ``lonLocation``: -180 .. 180 deg. A
    recording of which the resampled arrays would exceed :data:`MAX_GRID_CELLS` tracks x
    samples is refused before they are built, and one of which no sample can be made
    (fewer than ``agents`` tracks span a scene's ``history + 1 + horizon`` samples: all
    tracks too short, a ``frameRate`` too high) is refused naming the recording.

Maps: a light OSM parse, not the ``lanelet2`` package
    ``lanelet2`` has wheels on PyPI (1.2.3, Linux x86-64 manylinux_2_31 only; none for
    macOS or Windows) and brings a compiled Boost stack; what the extraction needs of a
    map is small: every lanelet's left and right bound (``way`` s of ``node`` s), its
    centre line (the mean of the bounds resampled to the same arc fractions), width,
    speed limit, successors and left / right neighbours. That is ~150 lines of
    ``xml.etree`` here, runs everywhere the toolkit runs, and writes back trivially for the
    generator (:mod:`scenarios.highway`). Conventions of lanelet2's OSM format: a
    ``relation`` with ``type=lanelet`` and members ``left`` / ``right`` (ways); node
    positions from ``local_x`` / ``local_y`` tags when every node has them, else from
    ``lat`` / ``lon`` projected to UTM (WGS84, the zone of the recording's
    ``lonLocation`` or of the nodes, :func:`utm_from_latlon`) minus the recording's
    ``xUtmOrigin`` / ``yUtmOrigin``; left neighbour = the lanelet whose right bound is
    this one's left bound (the same way), successors = lanelets whose centre starts
    within 0.5 m of this one's end in a similar heading; the speed limit from the
    lanelet's ``speed_limit`` tag (km/h unless ``mph``), else a ``speed_limit``
    regulatory element it references (``sign_type`` ``de274-<kmh>`` or ``speed_limit``),
    else the recording's ``speedLimit``, else 130 km/h (the German advisory speed).
    Lanelets of subtype ``walkway``, ``crosswalk``, ``bicycle_lane``, ``stairs`` are left
    out. The result is a :class:`LaneletMap`: a :class:`scenarios.maps.RoadMap` (lane ids
    are the lanelet ids as strings) plus the neighbour relations.
    Checks: node ``lat`` within 90 deg, ``lon`` within 180 deg, ``local_x`` / ``local_y``
    within 10^7 m (all finite) and a finite UTM position; ids and references integers;
    a speed limit in (0, 500] km/h; a lanelet's bounds at most :data:`MAX_LANE_WIDTH`
    (30 m) apart on average. A map is used for a recording only if every track's first,
    middle and last position lies within :data:`MAP_DISTANCE` (200 m) of one of its
    lanelets (:func:`check_map_near`; the map of another location, lat/lon swapped or a
    wrong UTM origin put the lanes km away), and each lane of a sample (the agent's
    current lanelet and its neighbours, continued) passes within 200 m of its agent;
    otherwise the error names the map file and the distance.

Extraction (App. E, one work unit per recording)
    1. Resampling: every ``step = dt * frameRate`` frames (``dt = 0.2`` s, 5 frames at
       exiD's 25 Hz), on the global frame grid (``frame % step == 0``); a ``frameRate``
       that does not give an integer step is an error.
    2. Lane changes: a vehicle changes lane between two samples when its lanelet changes
       to one that is neither a successor nor a predecessor of the previous one (across
       lanes: a neighbour, or a jump over several). Where ``laneletId`` is missing, the
       lanelet is the one whose centre line is nearest within its half width.
    3. Scenes (``N = 4``): for every vehicle with a lane change at sample ``c``, every
       current sample ``t`` on the grid of ``stride`` samples such that the change lies in
       ``(t - H, t + T]`` and the vehicle exists from ``t - H`` to ``t + T``; its agents are
       that vehicle (agent 0) and the ``N - 1`` vehicles nearest to it at ``t`` (within
       ``neighbour_range``) that exist over the same window. A scene with fewer is
       skipped; the same set of agents at the same ``t`` is kept once. With
       ``max_scenes_per_recording`` > 0, that many scenes, evenly spread, are kept.
    4. Sample: history ``H + 1 = 10`` states (1.8 s), the future ``T = 20`` states (4 s),
       state ``(x, y, v, theta)``: ``xCenter, yCenter``, ``v = |(xVelocity, yVelocity)|``,
       ``theta = heading`` (rad, continuous per agent, the current one in ``(-pi, pi]``).
       Fixed global orientation (paper App. F: the origin is fixed), translated so that
       the scene's origin (the mean current position of its agents, in ``frame``) is 0.
    5. Modes: real data has one future: ``future`` ``(M = 5, N, T, 4)`` holds it in slot
       ``gt_mode = 0`` and copies it in the other slots with ``mode_valid`` False (the
       RPI / left-turn convention for unavailable modes).
    6. Map input: per agent, its current lane and its left and right neighbours (where one
       is missing, the current lane's boundary on that side, as the paper's goal decoder
       does), each a *corridor* (the lanelet continued through its straightest
       predecessors and successors) windowed from ``lane_behind`` m behind to
       ``lane_ahead`` m ahead of the agent (clamped to the corridor's ends, so every point
       lies on the map), resampled to ``P = lane_points``:
       ``lanes`` ``(3 N, P, 2)`` (agent-major: left, current, right). ``paths``
       ``(N, P, 2)``: the current lane (the game's lane feature), ``vref`` ``(N,)``: its
       speed limit. ``goal_candidates`` ``(N, G = 60, 2)``: ``G / 3`` points on each of
       the three from ``goal_near * v T dt`` to ``goal_far * v T dt + goal_margin`` m ahead
       of the agent (``goal_candidate_lane``: 0 left, 1 current, 2 right;
       ``goal_candidate_on_lane`` False on a boundary).
    7. Kept per agent: ``length``, ``width``, ``vehicle_class`` (index in
       :data:`CLASSES`), ``radius = length / 2`` (the paper's ``r = L / 2``),
       ``track_id``, ``lane_change`` (in the window); per sample ``recording``,
       ``location``, ``frame`` (current frame).

Splits (paper: the test set is a different map)
    Recordings of ``test_locations`` (default ``(0,)``, the paper's "map 0") are the test
    split; of the others, a seeded ``val_fraction`` of the recordings (at least one) is
    val, the rest train. No location is in test and in train / val.

Game (App. F.3, exiD): ``N = 4`` unicycles, ``K = T = 20``, ``dt = 0.2``; per agent the
terminal goal (the goal decoder's), ``lane`` (:class:`~epo_casadi.features.Path` on
``paths``), ``vref`` (:class:`~epo_casadi.features.ReferenceVelocity` on ``vref``),
velocity, acceleration, jerk, turn rate, turn acceleration; collision every 5th step.
Each agent's collision radius is a parameter of the game (``AgentSpec.radius_param``,
block ``radius.v<i>``, default ``radius`` = 2.5 m, ``L / 2`` of a 5 m car), and ours fills
it with the sample's ``L / 2`` (field ``radius``), the paper's ``r = L / 2``
(``radius_per_agent``; False: every agent has ``radius``, a number of the game. Datasets
written before this field existed keep that game: :func:`learning.data.dataset_game`).
"""

from __future__ import annotations

import hashlib
import math
import numbers
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from functools import cached_property
from pathlib import Path as FilePath

import numpy as np

from epo_casadi import (
    Acceleration,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    Jerk,
    Path,
    PotentialGame,
    ReferenceVelocity,
    TurnAcceleration,
    TurnRate,
    Velocity,
)
from epo_casadi.errors import SpecError, check_bool, check_number, check_size, short_repr

from .dataset import SPLITS, DatasetError, FieldSpec, Scenario
from .maps import Lane, RoadMap, arc_length, project_to_polyline, resample_at

__all__ = [
    "CLASSES",
    "TRACK_COLUMNS",
    "TRACKS_META_COLUMNS",
    "RECORDING_META_COLUMNS",
    "Recording",
    "LaneletMap",
    "ExidRecipe",
    "ExidScenario",
    "find_recordings",
    "read_recording",
    "read_lanelet_map",
    "read_table",
    "Column",
    "TRACKS_TABLE",
    "TRACKS_META_TABLE",
    "RECORDING_META_TABLE",
    "check_map_near",
    "map_distance",
    "find_map",
    "utm_from_latlon",
    "latlon_from_utm",
    "lane_changes",
]

#: vehicle classes (index stored in ``vehicle_class``); others map to the last entry
CLASSES = ("car", "van", "truck", "bus", "trailer", "motorcycle", "other")
TRACK_COLUMNS = (
    "recordingId",
    "trackId",
    "frame",
    "xCenter",
    "yCenter",
    "heading",
    "width",
    "length",
    "xVelocity",
    "yVelocity",
    "xAcceleration",
    "yAcceleration",
    "lonVelocity",
    "latVelocity",
    "lonAcceleration",
    "latAcceleration",
)
TRACKS_META_COLUMNS = (
    "recordingId",
    "trackId",
    "initialFrame",
    "finalFrame",
    "numFrames",
    "width",
    "length",
    "class",
)
RECORDING_META_COLUMNS = ("recordingId", "locationId", "frameRate", "xUtmOrigin", "yUtmOrigin")
DEFAULT_SPEED_LIMIT = 130 / 3.6  # m/s: German advisory speed where there is no limit
SKIP_SUBTYPES = {"walkway", "crosswalk", "bicycle_lane", "stairs"}


# --------------------------------------------------------------------------------------
# UTM (WGS84), Krueger series to n^3 (sub-millimetre within a zone)
# --------------------------------------------------------------------------------------
_A, _F = 6378137.0, 1 / 298.257223563
_N = _F / (2 - _F)
_AA = _A / (1 + _N) * (1 + _N**2 / 4 + _N**4 / 64)
_ALPHA = (
    _N / 2 - 2 * _N**2 / 3 + 5 * _N**3 / 16,
    13 * _N**2 / 48 - 3 * _N**3 / 5,
    61 * _N**3 / 240,
)
_BETA = (_N / 2 - 2 * _N**2 / 3 + 37 * _N**3 / 96, _N**2 / 48 + _N**3 / 15, 17 * _N**3 / 480)
_DELTA = (2 * _N - 2 * _N**2 / 3 - 2 * _N**3, 7 * _N**2 / 3 - 8 * _N**3 / 5, 56 * _N**3 / 15)
_E = 2 * math.sqrt(_N) / (1 + _N)
_K0, _E0 = 0.9996, 500000.0


def utm_zone(lon: float) -> int:
    """UTM zone (1..60) of a longitude in degrees."""
    return int((lon + 180.0) // 6.0) % 60 + 1


def utm_from_latlon(lat, lon, zone: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """UTM easting and northing (m, northern hemisphere) of WGS84 ``lat, lon`` (deg)."""
    lat, lon = np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)
    z = utm_zone(float(np.mean(lon))) if zone is None else int(zone)
    phi, lam = np.radians(lat), np.radians(lon - (6 * z - 183))
    t = np.sinh(np.arctanh(np.sin(phi)) - _E * np.arctanh(_E * np.sin(phi)))
    xi = np.arctan2(t, np.cos(lam))
    eta = np.arctanh(np.sin(lam) / np.sqrt(1 + t**2))
    E = eta + sum(a * np.cos(2 * j * xi) * np.sinh(2 * j * eta) for j, a in enumerate(_ALPHA, 1))
    N = xi + sum(a * np.sin(2 * j * xi) * np.cosh(2 * j * eta) for j, a in enumerate(_ALPHA, 1))
    return _E0 + _K0 * _AA * E, _K0 * _AA * N


def latlon_from_utm(easting, northing, zone: int) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 ``lat, lon`` (deg) of UTM coordinates (northern hemisphere) in ``zone``."""
    xi = np.asarray(northing, dtype=float) / (_K0 * _AA)
    eta = (np.asarray(easting, dtype=float) - _E0) / (_K0 * _AA)
    xi_ = xi - sum(b * np.sin(2 * j * xi) * np.cosh(2 * j * eta) for j, b in enumerate(_BETA, 1))
    eta_ = eta - sum(b * np.cos(2 * j * xi) * np.sinh(2 * j * eta) for j, b in enumerate(_BETA, 1))
    chi = np.arcsin(np.sin(xi_) / np.cosh(eta_))
    phi = chi + sum(d * np.sin(2 * j * chi) for j, d in enumerate(_DELTA, 1))
    lam = np.arctan2(np.sinh(eta_), np.cos(xi_))
    return np.degrees(phi), np.degrees(lam) + (6 * zone - 183)


# --------------------------------------------------------------------------------------
# CSV reading: one validating step for every table of the release
# --------------------------------------------------------------------------------------
#: Bounds of the cells the reader uses (inclusive; module docstring, "Bounds").
MAX_ID = 32767  #: recordingId, locationId (stored as int16)
MAX_TRACK_ID = 2**31 - 1  #: trackId (stored as int32)
MAX_FRAME = 10_000_000  #: frame numbers (4.6 days at 25 Hz)
MAX_POSITION = 1e6  #: m, |xCenter|, |yCenter| in the recording's local frame
MAX_UTM = 1e7  #: m, |xUtmOrigin|, |yUtmOrigin| (UTM eastings < 1e6, northings < 1e7)
MAX_SPEED = 100.0  #: m/s, every velocity component (360 km/h)
MAX_ACCELERATION = 100.0  #: m/s^2, every acceleration component (about 10 g)
MAX_LENGTH = 50.0  #: m, vehicle length (> 0)
MAX_WIDTH = 10.0  #: m, vehicle width (> 0)
FRAME_RATE = (1.0, 1000.0)  #: Hz
MAX_SPEED_LIMIT = 100.0  #: m/s, recordingMeta ``speedLimit`` (<= 0: none)
#: m: every track must come this close to a lane of its map (module docstring, "Maps")
MAP_DISTANCE = 200.0
#: m: the largest mean distance between a lanelet's left and right bounds
MAX_LANE_WIDTH = 30.0
#: tracks x samples of one recording on the ``dt`` grid (the resampled arrays' size)
MAX_GRID_CELLS = 50_000_000


@dataclass(frozen=True)
class Column:
    """A column of an external table and what each of its cells must be: a finite number
    in ``[lo, hi]`` (``lo`` exclusive with ``lo_open``), a whole number with ``integer``,
    or any text with ``text``. ``required=False``: the column may be absent (its cells are
    checked where it is present)."""

    name: str
    lo: float | None = None
    hi: float | None = None
    integer: bool = False
    lo_open: bool = False
    required: bool = True
    text: bool = False


def _num(name: str, bound: float, **kw) -> Column:
    return Column(name, -bound, bound, **kw)


def _size(name: str, hi: float) -> Column:
    return Column(name, 0.0, hi, lo_open=True)


#: ``NN_tracks.csv``
TRACKS_TABLE = (
    Column("recordingId", 0, MAX_ID, integer=True),
    Column("trackId", 0, MAX_TRACK_ID, integer=True),
    Column("frame", 0, MAX_FRAME, integer=True),
    _num("xCenter", MAX_POSITION),
    _num("yCenter", MAX_POSITION),
    Column("heading", -360.0, 360.0),
    _size("width", MAX_WIDTH),
    _size("length", MAX_LENGTH),
    *(_num(c, MAX_SPEED) for c in ("xVelocity", "yVelocity", "lonVelocity", "latVelocity")),
    *(
        _num(c, MAX_ACCELERATION)
        for c in ("xAcceleration", "yAcceleration", "lonAcceleration", "latAcceleration")
    ),
    Column("laneletId", required=False, text=True),
)
#: ``NN_tracksMeta.csv``
TRACKS_META_TABLE = (
    Column("recordingId", 0, MAX_ID, integer=True),
    Column("trackId", 0, MAX_TRACK_ID, integer=True),
    Column("initialFrame", 0, MAX_FRAME, integer=True),
    Column("finalFrame", 0, MAX_FRAME, integer=True),
    Column("numFrames", 1, MAX_FRAME + 1, integer=True),
    _size("width", MAX_WIDTH),
    _size("length", MAX_LENGTH),
    Column("class", text=True),
)
#: ``NN_recordingMeta.csv``
RECORDING_META_TABLE = (
    Column("recordingId", 0, MAX_ID, integer=True),
    Column("locationId", 0, MAX_ID, integer=True),
    Column("frameRate", *FRAME_RATE),
    _num("xUtmOrigin", MAX_UTM),
    _num("yUtmOrigin", MAX_UTM),
    Column("speedLimit", -1.0, MAX_SPEED_LIMIT, required=False),
    Column("latLocation", -90.0, 90.0, required=False),
    Column("lonLocation", -180.0, 180.0, required=False),
)


def read_table(path: str | FilePath, columns: Sequence[Column]) -> tuple[dict, np.ndarray]:
    """The cells of ``columns`` in the CSV at ``path``, each checked against its
    :class:`Column`: numeric columns as float arrays, text columns as stripped strings.
    Also returns each row's line number in the file (blank lines are skipped).

    The one check of every table the exiD reader reads: a missing file or column, a cell
    that is not a number (``nan``, text, empty), not finite, outside its bounds or not a
    whole number where one is expected is a :class:`~scenarios.dataset.DatasetError` at
    ``<file>:<column>`` naming the line and the value found.
    """
    import pandas as pd

    path = FilePath(path)
    if not path.is_file():
        raise DatasetError(str(path), "missing file")
    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=False, skip_blank_lines=False)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
        raise DatasetError(str(path), f"not a readable CSV ({str(e).strip()})") from None
    for c in columns:
        if c.required and c.name not in df.columns:
            raise DatasetError(
                f"{path}:{c.name}", f"missing column; the file has {', '.join(df.columns)}"
            )
    lines = np.arange(len(df)) + 2  # line 1 is the header
    blank = (df == "").all(axis=1).to_numpy() if len(df.columns) else np.ones(len(df), bool)
    df, lines = df[~blank], lines[~blank]
    if len(df) == 0:
        raise DatasetError(str(path), "no rows")
    out = {}
    for c in columns:
        if c.name not in df.columns:
            continue
        s = df[c.name].str.strip()
        if c.text:
            out[c.name] = s.to_numpy(dtype=str)
            continue
        v = pd.to_numeric(s, errors="coerce").to_numpy(dtype=float)
        bad = ~np.isfinite(v)
        if c.lo is not None:
            bad |= v <= c.lo if c.lo_open else v < c.lo
        if c.hi is not None:
            bad |= v > c.hi
        if c.integer:
            bad |= v != np.floor(v)
        if bad.any():
            i = int(np.argmax(bad))
            where, text = f"{path}:{c.name}", s.iloc[i]
            if np.isnan(v[i]):  # not a number at all
                what = "an empty value (truncated file?)" if text == "" else repr(text)
                raise DatasetError(where, f"expected a number, got {what} in line {lines[i]}")
            x = float(v[i])
            x = int(x) if c.integer and math.isfinite(x) and x.is_integer() else x
            try:
                check_number(where, x, lo=c.lo, hi=c.hi, lo_open=c.lo_open, integer=c.integer)
            except SpecError as e:
                raise DatasetError(where, f"{e.message} in line {lines[i]}") from None
            raise AssertionError(f"{where}: {text!r} passed check_number")  # pragma: no cover
        out[c.name] = v
    return out, lines


def _ids(column: np.ndarray, where: str, lines: np.ndarray) -> np.ndarray:
    """First id of each ``"a;b"`` entry; ``-1`` where empty or ``-1``. Anything else (text,
    an id of more than 18 digits) is refused naming its line."""
    first = np.array([str(x).split(";")[0].strip() for x in column], dtype=str)
    out = np.full(len(first), -1, dtype=np.int64)
    ok = np.char.isdigit(first) & (np.char.str_len(first) <= 18)
    bad = ~ok & ~np.isin(first, ["", "-1"])
    if bad.any():
        i = int(np.argmax(bad))
        raise DatasetError(
            where,
            f"expected a lanelet id ('id' or 'id1;id2'; empty or -1: none), got "
            f"{short_repr(str(column[i]))} in line {lines[i]}",
        )
    out[ok] = first[ok].astype(np.int64)
    return out


@dataclass(frozen=True, eq=False)
class Recording:
    """One recording: metadata and per-row track arrays, sorted by ``(trackId, frame)``.

    ``rows``: column name -> ``(R,)`` array (the :data:`TRACK_COLUMNS`, and ``laneletId``
    ``(R,)`` int, ``-1`` where unknown or absent); ``meta``: tracksMeta column ->
    ``(n_tracks,)`` array sorted by ``trackId``; ``start``: row offset of each track.
    """

    id: int
    location: int
    frame_rate: float
    speed_limit: float | None
    utm_origin: tuple[float, float]
    lonlat: tuple[float, float] | None
    rows: dict
    meta: dict
    start: np.ndarray
    files: tuple[str, str, str]

    @property
    def n_tracks(self) -> int:
        return len(self.meta["trackId"])


def find_recordings(raw: str | FilePath) -> dict[int, FilePath]:
    """Recording id -> directory of its CSVs, for every ``NN_recordingMeta.csv`` found in
    ``raw`` or ``raw/data`` (``NN`` from 00 to :data:`MAX_ID`, as ``recordingId`` is stored
    as int16)."""
    raw = FilePath(raw)
    if not raw.is_dir():
        raise DatasetError(str(raw), "no such directory (the exiD release: data/ and maps/)")
    out = {}
    for d in (raw, raw / "data"):
        if d.is_dir():
            for f in sorted(d.glob("*_recordingMeta.csv")):
                m = re.fullmatch(r"(\d+)_recordingMeta\.csv", f.name)
                if not m:
                    continue
                rid = int(m.group(1))
                if rid > MAX_ID or f"{rid:02d}" != m.group(1):
                    raise DatasetError(
                        str(f),
                        f"expected a recording number from 00 to {MAX_ID} (two or more "
                        f"digits, no extra leading zero) before _recordingMeta.csv, got "
                        f"{short_repr(m.group(1), 30)}",
                    )
                out.setdefault(rid, d)
    if not out:
        raise DatasetError(str(raw), "holds no NN_recordingMeta.csv (nor does its data/)")
    return dict(sorted(out.items()))


def _recording_meta(path: FilePath, rid: int) -> dict:
    """The one row of ``NN_recordingMeta.csv`` (recording ``rid``), checked."""
    m, lines = read_table(path, RECORDING_META_TABLE)
    if len(lines) != 1:
        raise DatasetError(
            str(path),
            f"expected one row (one recording), found {len(lines)} (lines "
            f"{', '.join(str(x) for x in lines[:3])}{', ...' if len(lines) > 3 else ''})",
        )
    rec = {k: float(m[k][0]) for k in RECORDING_META_COLUMNS}
    rec["recordingId"], rec["locationId"] = int(rec["recordingId"]), int(rec["locationId"])
    if rec["recordingId"] != rid:
        raise DatasetError(
            f"{path}:recordingId",
            f"expected {rid} (the recording of the file name), got {rec['recordingId']} "
            f"in line {lines[0]}",
        )
    sl = float(m["speedLimit"][0]) if "speedLimit" in m else -1.0
    rec["speedLimit"] = sl if sl > 0 else None
    lonlat = None
    if "latLocation" in m and "lonLocation" in m:
        lonlat = (float(m["lonLocation"][0]), float(m["latLocation"][0]))
    rec["lonlat"] = lonlat
    return rec


def _same_recording(path: FilePath, col: np.ndarray, lines: np.ndarray, rid: int) -> None:
    bad = np.flatnonzero(col != rid)
    if bad.size:
        i = int(bad[0])
        raise DatasetError(
            f"{path}:recordingId",
            f"expected {rid} (the recording of the file name), got {int(col[i])} "
            f"in line {lines[i]}",
        )


def read_recording(raw: str | FilePath, rid: int) -> Recording:
    """Recording ``rid`` of the release in ``raw`` (module docstring; errors name the file,
    the column and, for a cell, its line)."""
    dirs = find_recordings(raw)
    if rid not in dirs:
        raise DatasetError(str(raw), f"no recording {rid:02d}; found {sorted(dirs)}")
    d = dirs[rid]
    f_rec, f_meta, f_trk = (
        d / f"{rid:02d}_{n}.csv" for n in ("recordingMeta", "tracksMeta", "tracks")
    )
    rec = _recording_meta(f_rec, rid)
    meta, mlines = read_table(f_meta, TRACKS_META_TABLE)
    rows, lines = read_table(f_trk, TRACKS_TABLE)
    _same_recording(f_meta, meta["recordingId"], mlines, rid)
    _same_recording(f_trk, rows["recordingId"], lines, rid)
    meta["class"] = np.char.lower(meta["class"])
    n = len(lines)
    lanelet = (
        _ids(rows.pop("laneletId"), f"{f_trk}:laneletId", lines)
        if "laneletId" in rows
        else np.full(n, -1, np.int64)
    )
    # tracksMeta: one row per track
    mo = np.argsort(meta["trackId"], kind="stable")
    meta = {k: v[mo] for k, v in meta.items()}
    mlines = mlines[mo]
    mt = meta["trackId"].astype(np.int64)
    dup = np.flatnonzero(np.diff(mt) == 0)
    if dup.size:
        k = int(dup[0])
        raise DatasetError(
            f"{f_meta}:trackId",
            f"track {mt[k]} has two rows (lines {min(mlines[k], mlines[k + 1])} and "
            f"{max(mlines[k], mlines[k + 1])}); expected one row per track",
        )
    # tracks: one row per track and frame
    tid = rows["trackId"].astype(np.int64)
    order = np.lexsort((rows["frame"], tid))
    rows = {k: v[order] for k, v in rows.items()}
    rows["laneletId"] = lanelet[order]
    tid, lines = tid[order], lines[order]
    fr = rows["frame"].astype(np.int64)
    twice = np.flatnonzero((np.diff(tid) == 0) & (np.diff(fr) == 0))
    if twice.size:
        k = int(twice[0])
        a, b = sorted((int(lines[k]), int(lines[k + 1])))
        raise DatasetError(
            f"{f_trk}:frame",
            f"track {tid[k]} has frame {fr[k]} twice (lines {a} and {b}); expected one row "
            "per track and frame",
        )
    ids, start, counts = np.unique(tid, return_index=True, return_counts=True)
    if len(ids) != len(mt) or np.any(ids != mt):
        only_rows = sorted(set(ids.tolist()) - set(mt.tolist()))
        only_meta = sorted(set(mt.tolist()) - set(ids.tolist()))
        if only_rows:
            raise DatasetError(
                f"{f_trk}:trackId",
                f"track(s) {only_rows[:5]} have rows here but none in {f_meta.name}",
            )
        raise DatasetError(
            f"{f_trk}:trackId",
            f"track(s) {only_meta[:5]} of {f_meta.name} have no rows here (truncated file?)",
        )
    nf = meta["numFrames"].astype(np.int64)
    bad = np.flatnonzero(counts != nf)
    if bad.size:
        j = int(bad[0])
        raise DatasetError(
            f"{f_trk}:frame",
            f"track {int(ids[j])} has {int(counts[j])} rows, {f_meta.name} says numFrames "
            f"{int(nf[j])} (truncated file?)",
        )
    ok = (fr[start] == meta["initialFrame"]) & (fr[start + counts - 1] == meta["finalFrame"])
    gaps = np.diff(fr) != 1
    gaps[start[1:] - 1] = False
    if not ok.all() or gaps.any():
        if ok.all():  # the track of the first gap
            j = int(np.searchsorted(start, int(np.argmax(gaps)), side="right") - 1)
        else:
            j = int(np.argmin(ok))
        a, b = int(start[j]), int(start[j] + counts[j] - 1)
        raise DatasetError(
            f"{f_trk}:frame",
            f"track {int(ids[j])} has frames {int(fr[a])}..{int(fr[b])} with "
            f"{int(gaps[a:b].sum())} gap(s); {f_meta.name} says initialFrame "
            f"{int(meta['initialFrame'][j])}, finalFrame {int(meta['finalFrame'][j])}: "
            "expected every frame from initialFrame to finalFrame",
        )
    return Recording(
        id=int(rid),
        location=rec["locationId"],
        frame_rate=float(rec["frameRate"]),
        speed_limit=rec["speedLimit"],
        utm_origin=(rec["xUtmOrigin"], rec["yUtmOrigin"]),
        lonlat=rec["lonlat"],
        rows=rows,
        meta=meta,
        start=start.astype(np.int64),
        files=(str(f_trk), str(f_meta), str(f_rec)),
    )


# --------------------------------------------------------------------------------------
# lanelet2 maps
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LaneletMap:
    """A lanelet2 map as lanes: ``road_map`` (ids = lanelet ids as strings), ``left`` and
    ``right`` (lane id -> neighbour id or ``None``), ``predecessors``, ``path``."""

    road_map: RoadMap
    left: dict
    right: dict
    predecessors: dict
    path: str

    @cached_property
    def ids(self) -> tuple[str, ...]:
        return self.road_map.ids

    def locate(self, points: np.ndarray) -> np.ndarray:
        """Per point ``(Q, 2)``: id (int) of the lanelet whose centre line is nearest and
        within its half width, ``-1`` if none."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        best = np.full(len(pts), np.inf)
        out = np.full(len(pts), -1, dtype=np.int64)
        for ln in self.road_map.lanes:
            _, d = ln.project(pts)
            win = (d < best) & (d <= 0.5 * ln.width + 1e-6)
            best[win], out[win] = d[win], int(ln.id)
        return out


def map_distance(lmap: LaneletMap, rec: Recording) -> tuple[float, int, np.ndarray]:
    """How far the map's road is from the recording's tracks: the largest, over every
    track's first, middle and last position, of the distance to the nearest lanelet (its
    centre line less half its width; 0 on a lanelet). Returns ``(distance, trackId,
    position)`` of the farthest."""
    first = rec.start
    last = np.append(rec.start[1:], len(rec.rows["frame"])) - 1
    k = np.concatenate([first, (first + last) // 2, last])
    pts = np.stack([rec.rows["xCenter"][k], rec.rows["yCenter"][k]], axis=1)
    d = np.maximum(lmap.road_map.distance_to_road(pts), 0.0)
    i = int(np.argmax(d))
    tid = int(rec.meta["trackId"][i % rec.n_tracks])
    return float(d[i]), tid, pts[i]


def check_map_near(lmap: LaneletMap, rec: Recording, bound: float = MAP_DISTANCE) -> None:
    """Refuse a map whose road lies farther than ``bound`` metres from a track of ``rec``
    (:func:`map_distance`): the map of another location, lat/lon swapped, a wrong UTM
    origin."""
    d, tid, p = map_distance(lmap, rec)
    if not d <= bound:
        raise DatasetError(
            lmap.path,
            f"the map's lanes are {d:,.0f} m from track {tid} of recording {rec.id:02d} "
            f"(at x {p[0]:,.1f}, y {p[1]:,.1f} m); expected every track within {bound:g} m of "
            "a lanelet (the map of another location? lat/lon swapped? a wrong "
            "xUtmOrigin/yUtmOrigin?)",
        )


def find_map(raw: str | FilePath, location: int) -> FilePath:
    """The ``.osm`` map of ``location`` in the release (module docstring)."""
    raw = FilePath(raw)
    for d in (raw / "maps" / "lanelet2", raw / "maps", raw):
        if d.is_dir():
            hits = sorted(
                f
                for f in d.glob("*.osm")
                if re.fullmatch(rf"(location)?0*{location}(_.*)?\.osm", f.name)
            )
            if hits:
                return hits[0]
    raise DatasetError(
        str(raw / "maps" / "lanelet2"),
        f"no lanelet2 map {location}_<name>.osm for location {location}",
    )


def _speed(text: str, where: str) -> float | None:
    t = text.strip().lower()
    if t in ("", "none", "no", "-1", "unlimited"):
        return None
    m = re.fullmatch(r"(\d+(?:\.\d*)?|\.\d+)\s*(km/h|kmh|kph|mph)?", t)
    if not m or not 0 < float(m.group(1)) <= 500:
        raise DatasetError(
            where, f"expected a speed like '100' or '100 km/h' (0 to 500), got {short_repr(text)}"
        )
    v = float(m.group(1))
    return v * (0.44704 if m.group(2) == "mph" else 1 / 3.6)


def _osm_int(text, where: str, what: str) -> int:
    """An OSM id or reference (at most 18 digits, optionally signed)."""
    t = (text or "").strip()
    if not re.fullmatch(r"-?\d{1,18}", t):
        raise DatasetError(where, f"expected an integer {what}, got {short_repr(text)}")
    return int(t)


def _osm_float(text, where: str, what: str, bound: float) -> float:
    """A node coordinate: NaN where absent, else a finite number within ``bound``."""
    if text is None:
        return math.nan
    try:
        v = float(text)
    except ValueError:
        raise DatasetError(where, f"expected a number for {what}, got {short_repr(text)}") from None
    try:
        check_number(what, v, lo=-bound, hi=bound)
    except SpecError as e:
        raise DatasetError(where, f"{what}: {e.message}") from None
    return v


def read_lanelet_map(
    path: str | FilePath,
    utm_origin: tuple[float, float] | None = None,
    lonlat: tuple[float, float] | None = None,
    speed_limit: float | None = None,
) -> LaneletMap:
    """Lanes of a lanelet2 ``.osm`` map in the recordings' local frame (module docstring).

    ``utm_origin``: the recording's ``(xUtmOrigin, yUtmOrigin)``, needed when nodes have
    only ``lat`` / ``lon``; ``lonlat``: picks the UTM zone; ``speed_limit`` (m/s): for
    lanelets without one.
    """
    path = FilePath(path)
    if not path.is_file():
        raise DatasetError(str(path), "missing map file")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise DatasetError(str(path), f"not readable OSM XML ({e})") from None

    def tags(el) -> dict:
        return {t.get("k"): t.get("v", "") for t in el.findall("tag")}

    ids, lat, lon, lx, ly = [], [], [], [], []
    for nd in root.findall("node"):
        t = tags(nd)
        nid = _osm_int(nd.get("id"), f"{path}:node", "node id")
        where = f"{path}:node {nid}"
        ids.append(nid)
        lat.append(_osm_float(nd.get("lat"), where, "lat", 90.0))
        lon.append(_osm_float(nd.get("lon"), where, "lon", 180.0))
        lx.append(_osm_float(t.get("local_x"), where, "local_x", MAX_UTM))
        ly.append(_osm_float(t.get("local_y"), where, "local_y", MAX_UTM))
    lx, ly, lat, lon = map(np.asarray, (lx, ly, lat, lon))
    if len(ids) and np.all(np.isfinite(lx) & np.isfinite(ly)):
        xy = np.stack([lx, ly], axis=1)
    else:
        if not np.all(np.isfinite(lat) & np.isfinite(lon)):
            raise DatasetError(f"{path}:node", "every node needs lat/lon (or local_x/local_y tags)")
        if utm_origin is None:
            raise DatasetError(
                f"{path}:node",
                "nodes have lat/lon only: the recording's xUtmOrigin/yUtmOrigin are needed",
            )
        zone = utm_zone(lonlat[0]) if lonlat is not None else None
        with np.errstate(all="ignore"):
            e, n = utm_from_latlon(lat, lon, zone)
        xy = np.stack([e - utm_origin[0], n - utm_origin[1]], axis=1)
        bad = ~np.all(np.isfinite(xy), axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise DatasetError(
                f"{path}:node {ids[i]}",
                f"lat {lat[i]:g}, lon {lon[i]:g} has no UTM position (a pole?)",
            )
    node = dict(zip(ids, xy, strict=True))
    ways = {}
    for w in root.findall("way"):
        wid = _osm_int(w.get("id"), f"{path}:way", "way id")
        refs = [_osm_int(r.get("ref"), f"{path}:way {wid}", "nd ref") for r in w.findall("nd")]
        missing = [r for r in refs if r not in node]
        if missing:
            raise DatasetError(f"{path}:way", f"way {wid} refers to unknown node {missing[0]}")
        ways[wid] = np.array([node[r] for r in refs], dtype=float).reshape(-1, 2)
    regs = {}
    for r in root.findall("relation"):
        t = tags(r)
        if t.get("type") == "regulatory_element" and t.get("subtype") == "speed_limit":
            v = t.get("speed_limit") or re.sub(r"^de274-?", "", t.get("sign_type", ""))
            rid = _osm_int(r.get("id"), f"{path}:relation", "relation id")
            regs[rid] = _speed(v, f"{path}:relation {rid}.speed_limit")
    raw_lanes = []
    for r in root.findall("relation"):
        t = tags(r)
        if t.get("type") != "lanelet" or t.get("subtype", "road") in SKIP_SUBTYPES:
            continue
        rid = _osm_int(r.get("id"), f"{path}:relation", "relation id")
        mem = {
            m.get("role"): _osm_int(m.get("ref"), f"{path}:relation {rid}", "member ref")
            for m in r.findall("member")
            if m.get("role") in ("left", "right")
        }
        if set(mem) != {"left", "right"} or mem["left"] not in ways or mem["right"] not in ways:
            raise DatasetError(f"{path}:relation {rid}", "a lanelet needs a left and a right way")
        left, right = _dedupe(ways[mem["left"]]), _dedupe(ways[mem["right"]])
        if len(left) < 2 or len(right) < 2:
            raise DatasetError(f"{path}:relation {rid}", "a bound needs two distinct points")
        same = np.linalg.norm(left[0] - right[0]) + np.linalg.norm(left[-1] - right[-1])
        cross = np.linalg.norm(left[0] - right[-1]) + np.linalg.norm(left[-1] - right[0])
        if cross < same:
            left = left[::-1]
        n = max(len(left), len(right), 2) * 2
        lc = resample_at(left, np.linspace(0, arc_length(left)[-1], n))
        rc = resample_at(right, np.linspace(0, arc_length(right)[-1], n))
        centre = _dedupe(0.5 * (lc + rc))
        d = centre[-1] - centre[0]
        q = 0.5 * (lc[n // 2] - rc[n // 2])
        side = d[0] * q[1] - d[1] * q[0]
        if side < 0:  # the "left" bound lies on the right: the lanelet runs the other way
            centre, lc, rc = centre[::-1], rc[::-1], lc[::-1]
            mem = {"left": mem["right"], "right": mem["left"]}
        sl = None
        if "speed_limit" in t:
            sl = _speed(t["speed_limit"], f"{path}:relation {rid}.speed_limit")
        for m in r.findall("member"):
            ref = m.get("ref")
            if m.get("role") == "regulatory_element" and ref and ref.strip().isdigit():
                sl = sl if sl is not None else regs.get(int(ref))
        sl = sl if sl is not None else (speed_limit or DEFAULT_SPEED_LIMIT)
        width = float(np.mean(np.linalg.norm(lc - rc, axis=1)))
        if not width <= MAX_LANE_WIDTH:
            raise DatasetError(
                f"{path}:relation {rid}",
                f"the lanelet's left and right bounds lie {width:,.1f} m apart on average; "
                f"expected at most {MAX_LANE_WIDTH:g} m (a misplaced node?)",
            )
        raw_lanes.append((str(rid), centre, width, sl, mem["left"], mem["right"]))
    if not raw_lanes:
        raise DatasetError(f"{path}:relation", "no lanelet relations (type=lanelet)")
    # successors: a centre starting near this one's end, in a similar heading
    starts = np.array([c[0] for _, c, *_ in raw_lanes])
    ends = np.array([c[-1] for _, c, *_ in raw_lanes])
    h0 = np.array([_heading(c[:2]) for _, c, *_ in raw_lanes])
    h1 = np.array([_heading(c[-2:]) for _, c, *_ in raw_lanes])
    near = np.linalg.norm(ends[:, None] - starts[None], axis=2) < 0.5
    aligned = np.cos(h1[:, None] - h0[None]) > math.cos(math.radians(45))
    succ = near & aligned
    np.fill_diagonal(succ, False)
    by_left = {lw: i for i, (*_, lw, _rw) in enumerate(raw_lanes)}
    by_right = {rw: i for i, (*_, _lw, rw) in enumerate(raw_lanes)}
    lanes, left, right, pred = [], {}, {}, {}
    for i, (lid, centre, width, sl, lw, rw) in enumerate(raw_lanes):
        s = tuple(raw_lanes[j][0] for j in np.flatnonzero(succ[i]))
        lanes.append(Lane(lid, centre, width=width, speed_limit=sl, successors=s))
        j = by_right.get(lw)
        left[lid] = raw_lanes[j][0] if j is not None and j != i else None
        j = by_left.get(rw)
        right[lid] = raw_lanes[j][0] if j is not None and j != i else None
        pred[lid] = tuple(raw_lanes[j][0] for j in np.flatnonzero(succ[:, i]))
    return LaneletMap(RoadMap(tuple(lanes)), left, right, pred, str(path))


def _dedupe(p: np.ndarray) -> np.ndarray:
    if len(p) < 2:
        return p
    keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-6])
    return p[keep]


def _heading(seg: np.ndarray) -> float:
    d = seg[-1] - seg[0]
    return math.atan2(d[1], d[0])


# --------------------------------------------------------------------------------------
# lane changes
# --------------------------------------------------------------------------------------
def lane_changes(lanelets: np.ndarray, lmap: LaneletMap) -> np.ndarray:
    """``(n,)`` bool: True at sample ``k`` when the lanelet at ``k`` differs from the one at
    ``k - 1`` and neither is a successor of the other (both known, ``>= 0``)."""
    a, b = lanelets[:-1], lanelets[1:]
    out = np.zeros(len(lanelets), dtype=bool)
    cand = np.flatnonzero((a >= 0) & (b >= 0) & (a != b))
    rm = lmap.road_map
    for k in cand:
        sa, sb = str(int(a[k])), str(int(b[k]))
        if sa not in rm or sb not in rm:
            out[k + 1] = True
            continue
        if sb in rm.lane(sa).successors or sa in rm.lane(sb).successors:
            continue
        out[k + 1] = True
    return out


# --------------------------------------------------------------------------------------
# recipe and scenario
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExidRecipe:
    """Everything that defines an exiD-layout dataset (with the seed). Frozen; unknown keys
    fail. ``recordings`` (``[[id, location], ...]``) and ``raw_digest`` are filled from the
    raw directory by :meth:`ExidScenario.from_raw`."""

    recordings: tuple[tuple[int, int], ...] = ()  #: (recording id, location id) of each unit
    raw_digest: str = ""  #: sha256 of the raw files' names, sizes, metadata and maps
    agents: int = 4  #: N
    history: int = 9  #: H past samples (plus the current one): 1.8 s
    horizon: int = 20  #: T = K future samples: 4 s
    modes: int = 5  #: M future slots (one ground truth, the rest copies)
    dt: float = 0.2  #: resampling step (s)
    stride: int = 5  #: current samples of one lane changer's scenes are this many apart
    neighbour_range: float = 100.0  #: other agents within this distance at the current step (m)
    max_scenes_per_recording: int = 0  #: > 0: keep this many scenes, evenly spread
    test_locations: tuple[int, ...] = (0,)  #: locations (maps) of the test split
    val_fraction: float = 0.18  #: share of the other recordings in val (paper: 48745/255337)
    lane_points: int = 20  #: P, points of every lane / path polyline
    lane_behind: float = 20.0  #: lane windows start this far behind the agent (m)
    lane_ahead: float = 120.0  #: ... and end this far ahead (m)
    goal_points: int = 60  #: G (the paper's), G / 3 per lane
    goal_near: float = 0.3  #: candidates from goal_near * v * T * dt ahead ...
    goal_far: float = 1.4  #: ... to goal_far * v * T * dt + goal_margin ahead
    goal_margin: float = 10.0  #: (m)
    radius: float = 2.5  #: collision radius of every agent in the game (m): L / 2 of a 5 m car
    #: each agent's radius is a game parameter that the model sets to the sample's L / 2
    #: (the paper's r = L / 2); ``radius`` is then its default. False: ``radius`` for all
    radius_per_agent: bool = True
    collision_every: int = 5  #: the collision term every this many steps (paper: 5)
    w_goal: float = 1.0  #: default weights of the game (the network predicts them)
    w_lane: float = 1.0
    w_vref: float = 1.0
    w_vel: float = 0.1
    w_acc: float = 1.0
    w_jerk: float = 0.1
    w_turn: float = 1.0
    w_turnacc: float = 0.1
    w_collision: float = 10.0

    def __post_init__(self):
        p = "exid"
        try:
            recs = tuple((a, b) for a, b in self.recordings)
        except (TypeError, ValueError):
            raise SpecError(
                f"{p}.recordings", "expected [[recording id, location id], ...]"
            ) from None
        recs = tuple(
            (_id(f"{p}.recordings[{i}][0]", a), _id(f"{p}.recordings[{i}][1]", b))
            for i, (a, b) in enumerate(recs)
        )
        object.__setattr__(self, "recordings", recs)
        if isinstance(self.test_locations, (str, bytes)) or not isinstance(
            self.test_locations, (list, tuple)
        ):
            raise SpecError(
                f"{p}.test_locations",
                f"expected a list of location ids, got {self.test_locations!r}",
            )
        locs = tuple(_id(f"{p}.test_locations[{i}]", x) for i, x in enumerate(self.test_locations))
        object.__setattr__(self, "test_locations", locs)
        if not isinstance(self.raw_digest, str):
            raise SpecError(f"{p}.raw_digest", "expected a string")
        for k, lo, hi in (
            ("agents", 2, 32),
            ("history", 1, 1000),
            ("horizon", 2, 1000),
            ("modes", 1, 100),
            ("stride", 1, 10**6),
            ("max_scenes_per_recording", 0, 10**6),
            ("lane_points", 2, 1000),
            ("goal_points", 3, 3000),
            ("collision_every", 1, 1000),
        ):
            check_number(f"{p}.{k}", getattr(self, k), lo=lo, integer=True)
            check_size(f"{p}.{k}", getattr(self, k), hi, "the size of every sample", lo=lo)
        if self.goal_points % 3:
            raise SpecError(f"{p}.goal_points", f"expected a multiple of 3, got {self.goal_points}")
        check_number(f"{p}.dt", self.dt, lo=0.01, hi=2.0)
        check_number(f"{p}.val_fraction", self.val_fraction, lo=0.0, hi=0.9)
        for k in ("neighbour_range", "lane_ahead", "radius", "goal_far"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, lo_open=True)
        check_bool(f"{p}.radius_per_agent", self.radius_per_agent)
        for k in ("lane_behind", "goal_near", "goal_margin"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0)
        for f in fields(self):
            if f.name.startswith("w_"):
                check_number(f"{p}.{f.name}", getattr(self, f.name), lo=0.0)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["recordings"] = [list(r) for r in self.recordings]
        d["test_locations"] = list(self.test_locations)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ExidRecipe:
        if not isinstance(d, dict):
            raise SpecError("exid", f"expected a mapping of recipe fields, got {type(d).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise SpecError("exid", f"unknown recipe field(s) {unknown}; allowed: {sorted(names)}")
        return cls(**d)


def _id(field: str, x) -> int:
    """A recording or location id: an integer (numpy's too) in ``[0, MAX_ID]``."""
    if isinstance(x, numbers.Integral) and not isinstance(x, bool):
        x = int(x)
    return check_number(field, x, lo=0, hi=MAX_ID, integer=True)


def raw_digest(raw: str | FilePath, recordings: Sequence[int]) -> str:
    """sha256 over the names and sizes of the tracks files and the contents of the meta
    files and maps (a different raw set refuses to resume a dataset)."""
    raw = FilePath(raw)
    dirs = find_recordings(raw)
    h = hashlib.sha256()
    locs = set()
    for rid in recordings:
        d = dirs[rid]
        t = d / f"{rid:02d}_tracks.csv"
        h.update(f"{t.name}:{t.stat().st_size if t.exists() else -1}".encode())
        for n in ("tracksMeta", "recordingMeta"):
            f = d / f"{rid:02d}_{n}.csv"
            h.update(f.read_bytes() if f.exists() else b"-")
        locs.add(_recording_meta(d / f"{rid:02d}_recordingMeta.csv", rid)["locationId"])
    for loc in sorted(locs):
        h.update(find_map(raw, loc).read_bytes())
    return h.hexdigest()


class ExidScenario(Scenario):
    """Samples of the exiD layout (module docstring); one work unit per recording.
    Construct hooks: :meth:`agent_specs`, :meth:`game_spec`, :meth:`scenes`, :meth:`cut`."""

    name = "exid"
    pickled = ("recipe", "raw")

    def __init__(self, recipe: ExidRecipe | None = None, raw: str | FilePath | None = None):
        if recipe is not None and not isinstance(recipe, ExidRecipe):
            raise SpecError("recipe", f"expected an ExidRecipe, got {type(recipe).__name__}")
        self.recipe = recipe or ExidRecipe()
        self.raw = None if raw is None else FilePath(raw)

    @classmethod
    def from_raw(cls, raw: str | FilePath, **overrides) -> ExidScenario:
        """The scenario of every recording in ``raw`` (``overrides``: recipe fields; a
        ``recordings`` override given as ids selects recordings)."""
        dirs = find_recordings(raw)
        want = overrides.pop("recordings", None)
        ids = (
            sorted(dirs)
            if want is None
            else [int(r[0] if isinstance(r, (list, tuple)) else r) for r in want]
        )
        bad = [r for r in ids if r not in dirs]
        if bad:
            raise SpecError(
                "exid.recordings", f"no such recording(s) {bad} in {raw}; found {sorted(dirs)}"
            )
        recs = []
        for rid in ids:
            m = _recording_meta(dirs[rid] / f"{rid:02d}_recordingMeta.csv", rid)
            recs.append((rid, int(m["locationId"])))
        recipe = ExidRecipe.from_dict(
            {**overrides, "recordings": recs, "raw_digest": raw_digest(raw, ids)}
        )
        return cls(recipe, raw)

    # ---- Scenario interface ----------------------------------------------------------

    @property
    def n_units(self) -> int:
        return len(self.recipe.recordings)

    @property
    def units_per_shard(self) -> int:
        return 1

    def split_units(self, seed: int) -> dict[str, list[int]]:
        """By location (module docstring)."""
        r = self.recipe
        test = [i for i, (_, loc) in enumerate(r.recordings) if loc in r.test_locations]
        rest = [i for i, (_, loc) in enumerate(r.recordings) if loc not in r.test_locations]
        if not test or not rest:
            raise SpecError(
                "exid.test_locations",
                f"need recordings of a test location {list(r.test_locations)} and of another one; "
                f"locations present: {sorted({loc for _, loc in r.recordings})}",
            )
        out = {"train": list(rest), "val": [], "test": test}
        if len(rest) >= 2 and r.val_fraction > 0:
            rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0,)))
            nv = max(1, round(r.val_fraction * len(rest)))
            nv = min(nv, len(rest) - 1)
            val = sorted(int(rest[j]) for j in rng.permutation(len(rest))[:nv])
            out = {"train": [u for u in rest if u not in val], "val": val, "test": test}
        return {s: sorted(out[s]) for s in SPLITS}

    def schema(self) -> dict[str, FieldSpec]:
        r = self.recipe
        N, H, M, T, P, G = r.agents, r.history, r.modes, r.horizon, r.lane_points, r.goal_points
        return {
            "history": FieldSpec(
                (H + 1, N, 4), "float32", "states (x, y, v, theta) at t-H..t, scene frame"
            ),
            "history_valid": FieldSpec((H + 1,), "bool", "always True (complete windows only)"),
            "future": FieldSpec(
                (M, N, T, 4), "float32", "states at t+1..t+T; slot gt_mode: the recording"
            ),
            "mode_valid": FieldSpec((M,), "bool", "True only for the ground-truth slot"),
            "gt_mode": FieldSpec((), "int8", "slot of the recorded future (0)"),
            "lanes": FieldSpec(
                (3 * N, P, 2), "float32", "per agent: left, current, right lane windows"
            ),
            "paths": FieldSpec(
                (N, P, 2), "float32", "current lane window of each agent (game path)"
            ),
            "vref": FieldSpec((N,), "float32", "speed limit of each agent's lanelet (m/s)"),
            "goal_candidates": FieldSpec(
                (N, G, 2), "float32", "G/3 points on each of the three lanes"
            ),
            "goal_candidate_lane": FieldSpec((N, G), "int8", "0 left, 1 current, 2 right lane"),
            "goal_candidate_on_lane": FieldSpec(
                (N, G), "bool", "False: on a lane boundary (no neighbour)"
            ),
            "length": FieldSpec((N,), "float32", "vehicle length (m)"),
            "width": FieldSpec((N,), "float32", "vehicle width (m)"),
            "vehicle_class": FieldSpec((N,), "int8", "index in meta.classes"),
            "radius": FieldSpec((N,), "float32", "L / 2 (m), the paper's collision radius"),
            "track_id": FieldSpec((N,), "int32", "trackId in the recording"),
            "lane_change": FieldSpec((N,), "bool", "the agent changes lane in the window"),
            "recording": FieldSpec((), "int16", "recordingId"),
            "location": FieldSpec((), "int16", "locationId (map)"),
            "frame": FieldSpec((), "int64", "current frame in the recording"),
            "origin": FieldSpec((2,), "float64", "scene origin in the recording's local frame (m)"),
        }

    def meta(self) -> dict:
        r = self.recipe
        return {
            "state": ["x", "y", "v", "theta"],
            "classes": list(CLASSES),
            "agents": [f"v{i}" for i in range(r.agents)],
            "splits_by_location": {"test": list(r.test_locations)},
            "raw": None if self.raw is None else str(self.raw),
            "frame": "recording's local frame (UTM minus origin) translated by origin; not rotated",
            "param_names": list(self.game.params.names),
            "dt": r.dt,
            "units": "metres, seconds, radians",
        }

    # ---- the game ----------------------------------------------------------------------
    def agent_specs(self) -> list[AgentSpec]:
        """App. F.3 exiD features plus the goal term, per agent."""
        r = self.recipe
        out = []
        for i in range(r.agents):
            feats = [
                Goal(weight=r.w_goal),
                Path(weight=r.w_lane, points=r.lane_points, label="lane"),
                ReferenceVelocity(weight=r.w_vref, label="vref"),
                Velocity(weight=r.w_vel),
                Acceleration(weight=r.w_acc),
                Jerk(weight=r.w_jerk),
                TurnRate(weight=r.w_turn),
                TurnAcceleration(weight=r.w_turnacc),
            ]
            out.append(
                AgentSpec(
                    f"v{i}", "unicycle", feats, radius=r.radius, radius_param=r.radius_per_agent
                )
            )
        return out

    def game_spec(self) -> GameSpec:
        r = self.recipe
        return GameSpec(
            self.agent_specs(),
            [Collision(weight=r.w_collision, every=r.collision_every)],
            horizon=r.horizon,
            dt=r.dt,
        )

    @cached_property
    def game(self) -> PotentialGame:
        return PotentialGame(self.game_spec())

    # ---- extraction --------------------------------------------------------------------
    def load(self, rid: int) -> tuple[Recording, LaneletMap]:
        """Recording ``rid`` and its location's map."""
        if self.raw is None:
            raise SpecError(
                "exid.raw", "this scenario has no raw directory (ExidScenario.from_raw)"
            )
        rec = read_recording(self.raw, rid)
        lmap = read_lanelet_map(
            find_map(self.raw, rec.location), rec.utm_origin, rec.lonlat, rec.speed_limit
        )
        check_map_near(lmap, rec)
        return rec, lmap

    def resample(self, rec: Recording, lmap: LaneletMap) -> dict:
        """Per track, the samples on the ``dt`` grid: ``x`` ``(n_tracks, S, 4)`` states and
        ``lanelet`` ``(n_tracks, S)`` (NaN / -1 where the track does not exist),
        ``first`` / ``last`` sample index per track, ``grid`` frames ``(S,)`` (from the first
        grid frame of the recording), ``step`` frames per sample."""
        r = self.recipe
        step = r.dt * rec.frame_rate
        if abs(step - round(step)) > 1e-6 or round(step) < 1:
            raise DatasetError(
                f"{rec.files[2]}:frameRate",
                f"dt = {r.dt} s times frameRate {rec.frame_rate} is not a whole number of frames",
            )
        step = int(round(step))
        rows = rec.rows
        fr = rows["frame"].astype(np.int64)
        on = fr % step == 0
        tid = np.repeat(np.arange(rec.n_tracks), np.diff(np.append(rec.start, len(fr))))
        k0 = int(-(-fr.min() // step))  # the first grid frame is k0 * step
        S = max(int(fr.max() // step) - k0 + 1, 1)
        check_size(
            f"{rec.files[0]}:frame",
            rec.n_tracks * S,
            MAX_GRID_CELLS,
            f"memory: {rec.n_tracks} tracks x {S} samples of {r.dt} s from frame "
            f"{k0 * step} to {int(fr.max())}",
        )
        x = np.full((rec.n_tracks, S, 4), np.nan)
        lan = np.full((rec.n_tracks, S), -1, dtype=np.int64)
        j, k = tid[on], fr[on] // step - k0
        head = np.radians(rows["heading"][on])
        x[j, k] = np.stack(
            [
                rows["xCenter"][on],
                rows["yCenter"][on],
                np.hypot(rows["xVelocity"][on], rows["yVelocity"][on]),
                head,
            ],
            axis=1,
        )
        ll = rows["laneletId"][on].copy()
        unknown = ll < 0
        if unknown.any():
            ll[unknown] = lmap.locate(
                np.stack([rows["xCenter"][on][unknown], rows["yCenter"][on][unknown]], 1)
            )
        lan[j, k] = ll
        exists = np.isfinite(x[..., 0])
        first = np.where(exists.any(1), np.argmax(exists, 1), S)
        last = np.where(exists.any(1), S - 1 - np.argmax(exists[:, ::-1], 1), -1)
        # continuous headings per track
        th = x[..., 3]
        filled = np.where(exists, th, 0.0)
        filled = np.unwrap(filled, axis=1)
        x[..., 3] = np.where(exists, filled, np.nan)
        grid = (k0 + np.arange(S)) * step
        return {
            "x": x,
            "lanelet": lan,
            "first": first,
            "last": last,
            "grid": grid,
            "step": step,
        }

    def check_windows(self, rec: Recording, res: dict) -> None:
        """Refuse a recording of which no sample can be made: fewer than ``agents`` tracks
        span the ``history + 1 + horizon`` samples of a scene (all tracks too short for the
        window, or a ``frameRate`` that puts too few samples in each)."""
        r = self.recipe
        need = r.history + 1 + r.horizon
        span = np.maximum(res["last"] - res["first"] + 1, 0)
        n = int((span >= need).sum())
        if n < r.agents:
            raise DatasetError(
                rec.files[0],
                f"recording {rec.id:02d}: no sample can be made: a scene needs {r.agents} "
                f"tracks that each span {need} samples ({(need - 1) * r.dt:g} s), {n} do; "
                f"the longest spans {int(span.max(initial=0))} (a sample every "
                f"{res['step']} frames at frameRate {rec.frame_rate:g} Hz)",
            )

    def scenes(self, res: dict, lmap: LaneletMap) -> list[tuple[int, tuple[int, ...], np.ndarray]]:
        """``(t, agents, changes)`` of every scene (module docstring, step 3); ``changes``:
        per agent, a lane change in the window."""
        r = self.recipe
        H, T, N = r.history, r.horizon, r.agents
        x, lan, first, last = res["x"], res["lanelet"], res["first"], res["last"]
        lc = np.zeros(lan.shape, dtype=bool)
        for j in range(len(x)):
            if last[j] > first[j]:
                lc[j, first[j] : last[j] + 1] = lane_changes(lan[j, first[j] : last[j] + 1], lmap)
        out, seen = [], set()
        for i, c in zip(*np.nonzero(lc), strict=True):
            lo = max(c - T, first[i] + H)
            hi = min(c + H - 1, last[i] - T)
            t0 = -(-lo // r.stride) * r.stride
            for t in range(t0, hi + 1, r.stride):
                alive = (first <= t - H) & (last >= t + T)
                alive[i] = False
                cand = np.flatnonzero(alive)
                d = np.linalg.norm(x[cand, t, :2] - x[i, t, :2], axis=1)
                keep = d <= r.neighbour_range
                cand, d = cand[keep], d[keep]
                if len(cand) < N - 1:
                    continue
                agents = (int(i), *(int(a) for a in cand[np.argsort(d, kind="stable")[: N - 1]]))
                key = (t, tuple(sorted(agents)))
                if key in seen:
                    continue
                seen.add(key)
                win = lc[list(agents), t - H + 1 : t + T + 1].any(1)
                out.append((t, agents, win))
        out.sort(key=lambda s: (s[0], s[1]))
        m = r.max_scenes_per_recording
        if m and len(out) > m:
            pick = np.unique(np.linspace(0, len(out) - 1, m).round().astype(int))
            out = [out[k] for k in pick]
        return out

    def _corridor(self, lmap: LaneletMap, lid: str, cache: dict) -> tuple[np.ndarray, float]:
        """Centre polyline of ``lid`` continued through its straightest predecessors and
        successors (up to ``lane_behind`` / ``lane_ahead`` + 200 m), and the arc length at
        which ``lid`` starts on it."""
        if lid in cache:
            return cache[lid]
        rm, r = lmap.road_map, self.recipe
        lane = rm.lane(lid)
        parts, s0 = [lane.centre], 0.0
        cur, total = lane, 0.0
        seen = {lid}
        while total < r.lane_ahead + 200 and cur.successors:
            nxt = _straightest(rm, cur, cur.successors, forward=True)
            if nxt.id in seen:
                break
            seen.add(nxt.id)
            parts.append(nxt.centre)
            total += nxt.length
            cur = nxt
        cur, total = lane, 0.0
        while total < r.lane_behind + 200 and lmap.predecessors.get(cur.id):
            prv = _straightest(rm, cur, lmap.predecessors[cur.id], forward=False)
            if prv.id in seen:
                break
            seen.add(prv.id)
            parts.insert(0, prv.centre)
            s0 += prv.length
            total += prv.length
            cur = prv
        line = _dedupe(np.concatenate(parts))
        cache[lid] = (line, s0)
        return cache[lid]

    def cut(self, res: dict, rec: Recording, lmap: LaneletMap, scene, cache: dict) -> dict:
        """The sample of one scene (module docstring, steps 4-7)."""
        r = self.recipe
        H, T, N, M, P, G = r.history, r.horizon, r.agents, r.modes, r.lane_points, r.goal_points
        t, agents, changes = scene
        ag = list(agents)
        X = res["x"][ag, t - H : t + T + 1]  # (N, H+T+1, 4)
        origin = X[:, H, :2].mean(axis=0)
        X = X.copy()
        X[..., :2] -= origin
        cur = X[:, H, 3]
        X[..., 3] -= (2 * math.pi * np.ceil((cur - math.pi) / (2 * math.pi)))[:, None]
        hist = X[:, : H + 1].transpose(1, 0, 2)
        fut = np.repeat(X[None, :, H + 1 :], M, axis=0)
        lanes = np.empty((N, 3, P, 2))
        cands = np.empty((N, 3, G // 3, 2))
        on = np.ones((N, 3), dtype=bool)
        vref = np.empty(N)
        rm = lmap.road_map
        meta_tid = rec.meta["trackId"]
        for a, j in enumerate(ag):
            p = res["x"][j, t, :2]
            v = float(res["x"][j, t, 2])
            lid = int(res["lanelet"][j, t])
            if lid < 0 or str(lid) not in rm:
                lid = int(lmap.locate(p[None])[0])
            if lid < 0:  # off every lanelet: the nearest one
                lid = int(rm.ids[int(np.argmin([ln.project(p[None])[1][0] for ln in rm.lanes]))])
            sid = str(lid)
            lane = rm.lane(sid)
            vref[a] = lane.speed_limit
            span = v * T * r.dt
            ahead = np.linspace(r.goal_near * span, r.goal_far * span + r.goal_margin, G // 3)
            win = np.linspace(-r.lane_behind, r.lane_ahead, P)
            line, _ = self._corridor(lmap, sid, cache)
            s, dist = project_to_polyline(p[None], line)
            _check_near(lmap, sid, dist[0], rec, int(meta_tid[j]), int(res["grid"][t]))
            centre_w = _along(line, s[0] + win)
            centre_c = _along(line, s[0] + ahead)
            for side, nb, sign in ((0, lmap.left.get(sid), 1.0), (2, lmap.right.get(sid), -1.0)):
                if nb is not None:
                    nline, _ = self._corridor(lmap, nb, cache)
                    ns, dist = project_to_polyline(p[None], nline)
                    _check_near(lmap, nb, dist[0], rec, int(meta_tid[j]), int(res["grid"][t]))
                    lanes[a, side] = _along(nline, ns[0] + win)
                    cands[a, side] = _along(nline, ns[0] + ahead)
                else:
                    off = sign * 0.5 * lane.width
                    lanes[a, side] = _offset(line, s[0] + win, off)
                    cands[a, side] = _offset(line, s[0] + ahead, off)
                    on[a, side] = False
            lanes[a, 1], cands[a, 1] = centre_w, centre_c
        lanes -= origin
        cands -= origin
        meta = rec.meta
        length = meta["length"][ag]
        cls = [CLASSES.index(c) if c in CLASSES else len(CLASSES) - 1 for c in meta["class"][ag]]
        return {
            "history": hist,
            "history_valid": np.ones(H + 1, dtype=bool),
            "future": fut,
            "mode_valid": np.arange(M) == 0,
            "gt_mode": 0,
            "lanes": lanes.reshape(3 * N, P, 2),
            "paths": lanes[:, 1],
            "vref": vref,
            "goal_candidates": cands.reshape(N, G, 2),
            "goal_candidate_lane": np.repeat(np.arange(3), G // 3)[None].repeat(N, 0),
            "goal_candidate_on_lane": np.repeat(on, G // 3, axis=1),
            "length": length,
            "width": meta["width"][ag],
            "vehicle_class": np.array(cls),
            "radius": 0.5 * length,
            "track_id": meta["trackId"][ag].astype(np.int64),
            "lane_change": changes,
            "recording": rec.id,
            "location": rec.location,
            "frame": int(res["grid"][t]),
            "origin": origin,
        }

    def run_unit(self, index: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
        """Every sample of recording ``recordings[index]`` (deterministic; the seed does not
        enter)."""
        rid = self.recipe.recordings[index][0]
        rec, lmap = self.load(rid)
        res = self.resample(rec, lmap)
        self.check_windows(rec, res)
        cache: dict = {}
        rows = [self.cut(res, rec, lmap, sc, cache) for sc in self.scenes(res, lmap)]
        schema = self.schema()
        if not rows:
            return {k: np.zeros((0, *fs.shape), fs.dtype) for k, fs in schema.items()}
        return {
            k: np.stack([np.asarray(row[k]) for row in rows]).astype(fs.dtype)
            for k, fs in schema.items()
        }


def _check_near(lmap: LaneletMap, lid: str, d: float, rec: Recording, tid: int, frame: int):
    """Refuse a lane (corridor centre line) farther than :data:`MAP_DISTANCE` from its agent."""
    if not d <= MAP_DISTANCE:
        raise DatasetError(
            lmap.path,
            f"lanelet {lid} is {d:,.0f} m from track {tid} of recording {rec.id:02d} at frame "
            f"{frame}; expected the lanes of a sample within {MAP_DISTANCE:g} m of its agent",
        )


def _straightest(rm: RoadMap, cur: Lane, ids: Sequence[str], forward: bool) -> Lane:
    h = _heading(cur.centre[-2:] if forward else cur.centre[:2])
    best = max(
        (rm.lane(i) for i in ids),
        key=lambda ln: (
            math.cos(_heading(ln.centre[:2] if forward else ln.centre[-2:]) - h),
            ln.id,
        ),
    )
    return best


def _along(line: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points of ``line`` at arc lengths ``s``, clamped to its ends (so they stay on the map)."""
    return resample_at(line, np.asarray(s, dtype=float))


def _offset(line: np.ndarray, s: np.ndarray, off: float) -> np.ndarray:
    """Points at arc lengths ``s`` (clamped) shifted ``off`` metres to the left (negative:
    right)."""
    sa = arc_length(line)
    seg = np.diff(line, axis=0)
    s = np.clip(s, 0.0, sa[-1])
    k = np.clip(np.searchsorted(sa, s, side="right") - 1, 0, len(seg) - 1)
    d = seg[k] / np.linalg.norm(seg[k], axis=1, keepdims=True)
    return _along(line, s) + off * np.stack([-d[:, 1], d[:, 0]], axis=1)
