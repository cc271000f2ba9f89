"""Recordings of the release: finding them, and reading one with every check of its three
tables against each other (:mod:`scenarios.exid`, "Release layout")."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path as FilePath

import numpy as np

from epo_casadi.errors import short_repr

from ..dataset import DatasetError
from .tables import (
    MAX_ID,
    RECORDING_META_COLUMNS,
    RECORDING_META_TABLE,
    TRACKS_META_TABLE,
    TRACKS_TABLE,
    _ids,
    read_table,
)


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
    """Recording ``rid`` of the release in ``raw`` (:mod:`scenarios.exid`; errors name the
    file, the column and, for a cell, its line)."""
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
    meta = _one_row_per_track(f_meta, meta, mlines)
    rows = _one_row_per_frame(f_trk, rows, lanelet, lines)
    start = _check_frames(f_trk, f_meta, rows, meta)
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


def _one_row_per_track(f_meta: FilePath, meta: dict, mlines: np.ndarray) -> dict:
    """tracksMeta sorted by ``trackId``; a track with two rows is refused."""
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
    return meta


def _one_row_per_frame(f_trk: FilePath, rows: dict, lanelet: np.ndarray, lines: np.ndarray) -> dict:
    """The tracks' rows (and ``laneletId``) sorted by ``(trackId, frame)``; a track with
    one frame twice is refused (naming both lines)."""
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
    return rows


def _check_frames(f_trk: FilePath, f_meta: FilePath, rows: dict, meta: dict) -> np.ndarray:
    """Row offset of each track in the sorted ``rows``, after checking them against
    tracksMeta: the same tracks, ``numFrames`` rows each, every frame from
    ``initialFrame`` to ``finalFrame``."""
    tid = rows["trackId"].astype(np.int64)
    fr = rows["frame"].astype(np.int64)
    mt = meta["trackId"].astype(np.int64)
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
    return start
