"""The release's CSV tables: the columns read, the bounds of their cells and the one
validating reader of every table, :func:`read_table` (:mod:`scenarios.exid`, "Release
layout" and "Bounds")."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path as FilePath

import numpy as np

from epo_casadi.errors import SpecError, check_number, short_repr

from ..dataset import DatasetError

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


#: Bounds of the cells the reader uses (inclusive; :mod:`scenarios.exid`, "Bounds").
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
#: m: every track must come this close to a lane of its map (:mod:`scenarios.exid`, "Maps")
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
