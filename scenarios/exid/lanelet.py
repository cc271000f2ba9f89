"""Lanelet2 maps: a light OSM parse into lanes with their neighbours, the map's distance to
a recording's tracks, and lane changes on it (:mod:`scenarios.exid`, "Maps" and
"Extraction", step 2)."""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path as FilePath

import numpy as np

from epo_casadi.errors import SpecError, check_number, short_repr

from ..dataset import DatasetError
from ..maps import Lane, RoadMap, arc_length, resample_at
from .recording import Recording
from .tables import MAP_DISTANCE, MAX_LANE_WIDTH, MAX_UTM
from .utm import utm_from_latlon, utm_zone

DEFAULT_SPEED_LIMIT = 130 / 3.6  # m/s: German advisory speed where there is no limit
SKIP_SUBTYPES = {"walkway", "crosswalk", "bicycle_lane", "stairs"}


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
    """The ``.osm`` map of ``location`` in the release (:mod:`scenarios.exid`)."""
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
    """Lanes of a lanelet2 ``.osm`` map in the recordings' local frame
    (:mod:`scenarios.exid`).

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
    node = _node_positions(root, path, utm_origin, lonlat)
    ways = _ways(root, path, node)
    regs = _speed_regulations(root, path)
    raw_lanes = []
    for r in root.findall("relation"):
        t = _tags(r)
        if t.get("type") != "lanelet" or t.get("subtype", "road") in SKIP_SUBTYPES:
            continue
        raw_lanes.append(_lanelet(r, t, path, ways, regs, speed_limit))
    if not raw_lanes:
        raise DatasetError(f"{path}:relation", "no lanelet relations (type=lanelet)")
    return _linked(raw_lanes, path)


def _tags(el) -> dict:
    """The ``tag`` children of an OSM element as ``k -> v``."""
    return {t.get("k"): t.get("v", "") for t in el.findall("tag")}


def _node_positions(
    root, path: FilePath, utm_origin: tuple[float, float] | None, lonlat
) -> dict[int, np.ndarray]:
    """Node id -> position in the recording's local frame: ``local_x`` / ``local_y`` when
    every node has them, else ``lat`` / ``lon`` in UTM minus ``utm_origin``."""
    ids, lat, lon, lx, ly = [], [], [], [], []
    for nd in root.findall("node"):
        t = _tags(nd)
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
    return dict(zip(ids, xy, strict=True))


def _ways(root, path: FilePath, node: dict) -> dict[int, np.ndarray]:
    """Way id -> its nodes' positions ``(n, 2)``; a reference to an unknown node is refused."""
    ways = {}
    for w in root.findall("way"):
        wid = _osm_int(w.get("id"), f"{path}:way", "way id")
        refs = [_osm_int(r.get("ref"), f"{path}:way {wid}", "nd ref") for r in w.findall("nd")]
        missing = [r for r in refs if r not in node]
        if missing:
            raise DatasetError(f"{path}:way", f"way {wid} refers to unknown node {missing[0]}")
        ways[wid] = np.array([node[r] for r in refs], dtype=float).reshape(-1, 2)
    return ways


def _speed_regulations(root, path: FilePath) -> dict[int, float | None]:
    """Relation id -> speed (m/s) of every ``speed_limit`` regulatory element."""
    regs = {}
    for r in root.findall("relation"):
        t = _tags(r)
        if t.get("type") == "regulatory_element" and t.get("subtype") == "speed_limit":
            v = t.get("speed_limit") or re.sub(r"^de274-?", "", t.get("sign_type", ""))
            rid = _osm_int(r.get("id"), f"{path}:relation", "relation id")
            regs[rid] = _speed(v, f"{path}:relation {rid}.speed_limit")
    return regs


def _lanelet(r, t: dict, path: FilePath, ways: dict, regs: dict, speed_limit) -> tuple:
    """One lanelet relation as ``(id, centre, width, speed limit, left way, right way)``:
    the bounds oriented along the lanelet's direction, left on the left."""
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
    return (str(rid), centre, width, sl, mem["left"], mem["right"])


def _linked(raw_lanes: list[tuple], path: FilePath) -> LaneletMap:
    """The map of the lanelets ``raw_lanes`` (:func:`_lanelet`) with their relations:
    successors (a centre starting near this one's end, in a similar heading),
    predecessors, and left / right neighbours (sharing a bound)."""
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
