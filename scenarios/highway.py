"""Generated highway interaction data in the exiD release layout, from highway-env.

The real exiD recordings cannot be downloaded here, so this module records traffic of
highway-env (1.12.1; reactive IDM / MOBIL vehicles) on highway entries and exits and writes
it **in the exiD file format** (``data/NN_tracks.csv``, ``NN_tracksMeta.csv``,
``NN_recordingMeta.csv`` and one lanelet2 map per location,
``maps/lanelet2/<id>_<name>.osm``), so that the very reader and extraction of
:mod:`scenarios.exid` run on it unchanged.

Locations (:data:`LOCATIONS`; "maps", one can be held out as the test map)
    ``0 onramp-2``: two lanes, an on-ramp with a 180 m acceleration lane, 100 km/h.
    ``1 offramp-3``: three lanes, an off-ramp with a 150 m deceleration lane, 120 km/h.
    ``2 onramp-3``: three lanes, an on-ramp with a 250 m acceleration lane, no limit.
    ``3 offramp-2``: two lanes, an off-ramp with a 120 m deceleration lane, no limit.
    Main lanes run along +x at ``y = -i w`` (lane 0 the left-most); the ramp is on the
    right: a straight ramp and a sine-shaped converging (diverging) lane join the
    auxiliary (acceleration / deceleration) lane, the extra right-most lane of the middle
    section. Each location has its own UTM origin (zone 32, around Cologne).

Traffic (per recording, seeded)
    highway-env ``IDMVehicle`` s (IDM longitudinal, MOBIL lane changes, highway-env's
    lane-following steering and kinematic bicycle) with one change (:func:`driver_class`):
    *mandatory* lane changes for the ramp traffic. On-ramp vehicles leave the acceleration
    lane towards the main road as soon as the gap is safe for them and their new follower
    (MOBIL's safety criterion with a braking limit that grows towards the lane's end) and
    brake for its end if they cannot; exiting vehicles move right lane by lane before the
    exit and take the deceleration lane (one not on it 40 m before its end misses the exit
    and drives on); a lane change that became unsafe while the vehicle is still on its own
    lane is called off. Through traffic may not enter the auxiliary lane;
    otherwise it changes lanes by MOBIL (discretionary). Randomized per vehicle: class
    (car 85 %, truck 15 %; trucks only in the two right-most lanes and on ramps), length
    and width (cars 4.2-5.2 x 1.75-2.0 m, trucks 10-16.5 x 2.5 m), desired speed (cars
    0.85-1.15 x the limit, capped at 45 m/s; trucks 22-25 m/s), IDM time headway
    (1.0-2.0 s), comfortable acceleration, jam distance (2-4 m; the IDM runs on bumper-to-bumper
    gaps, where highway-env's measures between centres), MOBIL politeness (0-0.5) and threshold
    (0.1-0.4 m/s^2). Vehicles enter at the upstream ends (Poisson arrivals, 900-1600
    veh/h/lane, ramps 500-1000 veh/h, 30 % of the main-road vehicles at an exit take it)
    with a free entry gap, and leave at the downstream ends. The road fills during
    ``warmup`` s before frame 0. Speeds never go below zero (braking ends at standstill).
    Crashes are detected with each vehicle's own length and width (highway-env's crash
    pre-check radius is set from them); a vehicle in a crash (rare) is removed at once (its
    track ends), as real data has none.

Recording (exiD layout, :mod:`scenarios.exid` docstring)
    ``frame_rate`` Hz (25, as exiD) = the simulation step. Positions and headings are the
    simulated ones; velocities and accelerations are the central differences of the
    recorded positions (as a tracker's would be), ``lon``/``lat`` components in the
    vehicle's frame; ``laneletId`` is highway-env's current lane (the nearest), also
    ``latLaneCenterOffset``, ``laneWidth``, ``lonLaneletPos``, ``laneletLength``,
    ``traveledDistance``, ``trackLifetime``. Maps: every highway-env lane is a lanelet
    whose left and right bounds are ways of nodes with ``lat`` / ``lon`` only (WGS84,
    inverse UTM of the local coordinates plus the origin); adjacent lanes share their
    boundary way; ``speed_limit`` tag in km/h where the location has a limit.

Limits (what real exiD has and this does not): no sensor noise or tracking errors (real
tracks are smoothed detections), no motorcycles, vans or buses, no curved main roads or
cloverleaf loops, no weaving sections with on- and off-ramp together, IDM/MOBIL drivers
(no cooperative yielding beyond MOBIL politeness, no forced merges at standstill beyond
waiting at the lane end), and highway-env's kinematic model for trucks as for cars.
On-ramp vehicles that find no gap wait at the end of the acceleration lane and queue behind
each other, bumper gaps of 2-4 m (docs/exid.md: the test map's scenes).

Deterministic for a seed: recording ``i`` uses ``SeedSequence(seed, spawn_key=(i,))``;
existing complete recordings are kept (a stopped run resumes).

Output folder (:func:`generate_raw`)
    One run at a time writes to a folder (its ``.lock``; a second run is refused at once),
    and the folder records its recipe in ``recipe.json`` (kind ``highway-raw``: the seed
    and every :class:`HighwayOptions` field but ``recordings``) before anything else is
    written. A rerun with the same recipe resumes; one with another seed, duration or
    option is refused naming the differing fields, so recordings of two recipes never mix.
    Recording ``i`` depends only on the recipe and ``i``, so a rerun with *more*
    ``recordings`` extends the set (the finished recordings are kept); one with fewer than
    the folder already holds is refused. A non-empty folder without ``recipe.json`` (files
    of something else, or of a version of epo that recorded no recipe) is refused.
    Every file is written atomically; a recording whose files cannot all be written
    (a full disk) leaves none of them.

Limits (checked before any work; :data:`MAX_RECORDINGS`, :data:`MAX_DURATION`,
:data:`MAX_WARMUP`, :data:`MAX_FRAMES`)
    at most 10,000 recordings, 3,600 s recorded per recording and 600 s of warm-up, and
    100,000 recorded frames per recording (``duration x frame_rate``: one recording is
    held in memory until it is written).
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import re
from dataclasses import dataclass, fields
from pathlib import Path as FilePath

import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size, short_repr

from .exid import latlon_from_utm
from .files import claim_output, ensure_dir, write_atomic

__all__ = [
    "Location",
    "LOCATIONS",
    "HighwayOptions",
    "build_network",
    "driver_class",
    "size_vehicle",
    "write_map",
    "record",
    "generate_raw",
    "raw_recipe",
    "MAX_RECORDINGS",
    "MAX_DURATION",
    "MAX_WARMUP",
    "MAX_FRAMES",
]

#: most recordings of one raw set (file names ``NN_*.csv``)
MAX_RECORDINGS = 10_000
#: most recorded seconds per recording (s)
MAX_DURATION = 3600.0
#: most simulated warm-up seconds before frame 0 (s)
MAX_WARMUP = 600.0
#: most recorded frames per recording (``duration x frame_rate``; held in memory)
MAX_FRAMES = 100_000

AMPLITUDE = 3.25  # m: half the lateral offset of the sine-shaped ramp lanes
ZONE = 32


@dataclass(frozen=True)
class Location:
    """One road geometry ("map")."""

    id: int
    name: str
    lanes: int  #: main lanes
    ramp: str  #: "on" or "off"
    lane_width: float  #: (m)
    speed_limit: float | None  #: (m/s); None: no limit (vehicles' speeds by their desire)
    aux_length: float  #: acceleration / deceleration lane (m)
    approach: float = 300.0  #: main road before the auxiliary lane (m)
    after: float = 250.0  #: main road after it (m)
    ramp_length: float = 150.0  #: straight ramp (m)
    bend: float = 80.0  #: sine-shaped converging / diverging lane (m)
    ramp_speed: float = 25.0  #: ramp speed limit (m/s)
    utm_origin: tuple[float, float] = (350000.0, 5645000.0)

    @property
    def limit(self) -> float:
        """Speed limit the lanes carry in highway-env (m/s): 130 km/h where none."""
        return self.speed_limit if self.speed_limit is not None else 130 / 3.6


LOCATIONS: dict[int, Location] = {
    0: Location(0, "onramp-2", 2, "on", 3.75, 100 / 3.6, 180.0, utm_origin=(351200.0, 5651400.0)),
    1: Location(1, "offramp-3", 3, "off", 3.5, 120 / 3.6, 150.0, utm_origin=(356800.0, 5640300.0)),
    2: Location(2, "onramp-3", 3, "on", 3.75, None, 250.0, utm_origin=(348400.0, 5633900.0)),
    3: Location(3, "offramp-2", 2, "off", 3.6, None, 120.0, utm_origin=(361700.0, 5646600.0)),
}


@dataclass(frozen=True)
class HighwayOptions:
    """Options of one generated raw set (frozen; unknown names are errors)."""

    recordings: int = 8  #: recordings, round-robin over ``locations``
    locations: tuple[int, ...] = (0, 1, 2, 3)
    duration: float = 120.0  #: recorded seconds per recording
    warmup: float = 30.0  #: simulated seconds before frame 0
    frame_rate: float = 25.0  #: Hz (exiD: 25)
    flow: tuple[float, float] = (0.25, 0.45)  #: main-road arrivals per lane (veh/s)
    ramp_flow: tuple[float, float] = (0.14, 0.28)  #: on-ramp arrivals (veh/s)
    exit_share: float = 0.3  #: share of main-road vehicles that take an off-ramp
    truck_share: float = 0.15

    def __post_init__(self):
        p = "highway"
        object.__setattr__(
            self,
            "recordings",
            check_size(f"{p}.recordings", self.recordings, MAX_RECORDINGS, "recordings of a set"),
        )
        locs = self.locations
        ids = sorted(LOCATIONS)
        if isinstance(locs, (str, bytes)) or not isinstance(locs, (list, tuple)):
            raise SpecError(
                f"{p}.locations",
                f"expected a list of location ids from {ids}, e.g. [0, 2], got {short_repr(locs)}",
            )
        bad = [
            x
            for x in locs
            if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x not in LOCATIONS
        ]
        if not locs or bad:
            raise SpecError(
                f"{p}.locations",
                f"expected a non-empty list of location ids from {ids}, got {short_repr(list(locs))}",
            )
        object.__setattr__(self, "locations", tuple(int(x) for x in locs))
        check_number(f"{p}.duration", self.duration, lo=1.0, hi=MAX_DURATION)
        check_number(f"{p}.warmup", self.warmup, lo=0.0, hi=MAX_WARMUP)
        check_number(f"{p}.frame_rate", self.frame_rate, lo=1.0, hi=100.0)
        frames = int(round(self.duration * self.frame_rate))
        check_size(
            f"{p}.duration",
            frames,
            MAX_FRAMES,
            f"recorded frames per recording, duration {self.duration:g} s x frame_rate "
            f"{self.frame_rate:g} Hz: memory",
        )
        for k in ("exit_share", "truck_share"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, hi=1.0)
        for k in ("flow", "ramp_flow"):
            v = getattr(self, k)
            ok = isinstance(v, (list, tuple)) and len(v) == 2
            ok = ok and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                for x in v
            )
            if not ok or not 0 <= v[0] <= v[1] <= 2:
                raise SpecError(
                    f"{p}.{k}",
                    f"expected [low, high] with 0 <= low <= high <= 2 veh/s, got {short_repr(v)}",
                )
            object.__setattr__(self, k, (float(v[0]), float(v[1])))


# --------------------------------------------------------------------------------------
# road network and map
# --------------------------------------------------------------------------------------
def build_network(loc: Location):
    """highway-env ``RoadNetwork`` of a location, its lanelet ids (lane index -> int) and the
    key positions ``(x_b, x_c)`` (start and end of the auxiliary lane)."""
    from .sim._highway import hw

    H = hw()
    w, v = loc.lane_width, loc.limit
    vr = min(loc.ramp_speed, v)
    x_b = loc.approach
    x_c = x_b + loc.aux_length
    x_d = x_c + loc.after
    net = H.RoadNetwork()
    for i in range(loc.lanes):
        y = -i * w
        for a, b, x0, x1 in (("a", "b", 0.0, x_b), ("b", "c", x_b, x_c), ("c", "d", x_c, x_d)):
            net.add_lane(a, b, H.StraightLane([x0, y], [x1, y], width=w, speed_limit=v))
    y_m = -loc.lanes * w
    net.add_lane("b", "c", H.StraightLane([x_b, y_m], [x_c, y_m], width=w, speed_limit=v))
    if loc.ramp == "on":
        y_r = y_m - 2 * AMPLITUDE
        x_k = x_b - loc.bend
        x_j = x_k - loc.ramp_length
        net.add_lane("j", "k", H.StraightLane([x_j, y_r], [x_k, y_r], width=w, speed_limit=vr))
        conv = H.SineLane(
            [x_k, y_r + AMPLITUDE], [x_b, y_r + AMPLITUDE], -AMPLITUDE, math.pi / loc.bend,
            math.pi / 2, width=w, speed_limit=v,
        )  # fmt: skip
        net.add_lane("k", "b", conv)
    else:
        x_e = x_c + loc.bend
        div = H.SineLane(
            [x_c, y_m - AMPLITUDE], [x_e, y_m - AMPLITUDE], AMPLITUDE, math.pi / loc.bend,
            math.pi / 2, width=w, speed_limit=vr,
        )  # fmt: skip
        net.add_lane("c", "e", div)
        y_e = y_m - 2 * AMPLITUDE
        net.add_lane(
            "e",
            "f",
            H.StraightLane([x_e, y_e], [x_e + loc.ramp_length, y_e], width=w, speed_limit=vr),
        )
    ids = {}
    for a, tos in net.graph.items():
        for b, group in tos.items():
            for i in range(len(group)):
                ids[(a, b, i)] = 1000 + len(ids)
    return net, ids, (x_b, x_c)


def write_map(loc: Location, path: str | os.PathLike) -> None:
    """The lanelet2 ``.osm`` map of a location (module docstring), written atomically."""
    net, ids, _ = build_network(loc)
    nodes: list[tuple[int, float, float]] = []
    ways: list[tuple[int, list[int], str]] = []
    rels: list[str] = []
    counter = [1]

    def new_id() -> int:
        counter[0] += 1
        return counter[0]

    def way(points: np.ndarray, subtype: str) -> int:
        refs = []
        for x, y in points:
            nid = new_id()
            nodes.append((nid, float(x), float(y)))
            refs.append(nid)
        wid = new_id()
        ways.append((wid, refs, subtype))
        return wid

    kmh = None if loc.speed_limit is None else round(loc.speed_limit * 3.6)
    for a, tos in net.graph.items():
        for b, group in tos.items():
            shared = None  # right bound of the previous lane of this edge
            for i, lane in enumerate(group):
                L = float(lane.length)
                n = max(
                    2, int(math.ceil(L / (2.5 if type(lane).__name__ == "SineLane" else 25.0))) + 1
                )
                s = np.linspace(0.0, L, n)
                hw_ = 0.5 * lane.width
                left = np.array([lane.position(x, hw_) for x in s])
                right = np.array([lane.position(x, -hw_) for x in s])
                lw = shared if shared is not None else way(left, "solid")
                rw = way(right, "solid" if i == len(group) - 1 else "dashed")
                shared = rw
                tags = {
                    "type": "lanelet",
                    "subtype": "road",
                    "location": "nonurban",
                    "one_way": "yes",
                }
                if kmh is not None and (a, b) not in (
                    ("j", "k"),
                    ("k", "b"),
                    ("c", "e"),
                    ("e", "f"),
                ):
                    tags["speed_limit"] = str(kmh)
                elif (a, b) in (("j", "k"), ("k", "b"), ("c", "e"), ("e", "f")):
                    tags["speed_limit"] = str(round(min(loc.ramp_speed, loc.limit) * 3.6))
                body = f'  <relation id="{ids[(a, b, i)]}" visible="true" version="1">\n'
                body += f'    <member type="way" ref="{lw}" role="left"/>\n'
                body += f'    <member type="way" ref="{rw}" role="right"/>\n'
                body += "".join(f'    <tag k="{k}" v="{v}"/>\n' for k, v in tags.items())
                rels.append(body + "  </relation>\n")
    xy = np.array([(x, y) for _, x, y in nodes])
    lat, lon = latlon_from_utm(xy[:, 0] + loc.utm_origin[0], xy[:, 1] + loc.utm_origin[1], ZONE)
    out = ['<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="epo highway">\n']
    for (nid, _, _), la, lo in zip(nodes, lat, lon, strict=True):
        out.append(
            f'  <node id="{nid}" visible="true" version="1" lat="{la:.11f}" lon="{lo:.11f}"/>\n'
        )
    for wid, refs, sub in ways:
        out.append(f'  <way id="{wid}" visible="true" version="1">\n')
        out.extend(f'    <nd ref="{r}"/>\n' for r in refs)
        out.append(
            f'    <tag k="type" v="line_thin"/>\n    <tag k="subtype" v="{sub}"/>\n  </way>\n'
        )
    out.extend(rels)
    out.append("</osm>\n")
    write_atomic(FilePath(path), "".join(out))


# --------------------------------------------------------------------------------------
# drivers
# --------------------------------------------------------------------------------------
@functools.cache
def driver_class():
    """highway-env's IDM/MOBIL vehicle with mandatory lane changes for ramp traffic
    (module docstring); built on first use (highway-env is imported lazily)."""
    from .sim._highway import hw

    H = hw()
    from highway_env import utils

    class RampDriver(H.Driver):
        """``want``: callable(vehicle) -> wanted lane number on the current edge or None;
        ``aux``: the auxiliary lane index (through traffic may not enter it);
        ``aux_end``: obstacle at its end (merging vehicles brake for it)."""

        want = None
        aux = None
        aux_end = None
        urgency = 0.0

        def change_lane_policy(self):
            if self.lane_index != self.target_lane_index:
                # a mandatory change still on its own lane is called off when it became
                # unsafe (a fast follower closed up); then highway-env's abort logic
                if self.want is not None and not self._safe(self.target_lane_index):
                    self.target_lane_index = self.lane_index
                    return None
                return H.IDMVehicle.change_lane_policy(self)
            on_aux = self.lane_index == self.aux
            self.stop_obstacle = self.aux_end if on_aux and self.aux_end is not None else None
            if not utils.do_every(self.LANE_CHANGE_DELAY, self.timer):
                return
            self.timer = 0
            cur = self.lane_index
            want = self.want(self) if self.want is not None else None
            if want is not None and want != cur[2]:
                cand = (cur[0], cur[1], cur[2] + (1 if want > cur[2] else -1))
                if cand[2] < len(self.road.network.graph[cur[0]][cur[1]]) and self._safe(cand):
                    self.target_lane_index = cand
                return
            if abs(self.speed) < 1:
                return
            for li in self.road.network.side_lanes(cur):
                if li == self.aux or not self.road.network.get_lane(li).is_reachable_from(
                    self.position
                ):
                    continue
                if self.mobil(li):
                    self.target_lane_index = li

        def acceleration(self, ego_vehicle, front_vehicle=None, rear_vehicle=None) -> float:
            # the IDM on bumper-to-bumper gaps: highway-env's free-road term, and the
            # interaction term -a (s* / s)^2 with s the gap between the bumpers (highway-env
            # uses the distance between the centres) and s* its desired gap (jam distance
            # DISTANCE_WANTED plus the speed terms), so that a queue stands DISTANCE_WANTED
            # apart behind cars and trucks alike
            acc = super().acceleration(ego_vehicle, None, rear_vehicle)
            if front_vehicle is None or ego_vehicle is None:
                return acc
            s = ego_vehicle.lane_distance_to(front_vehicle)
            s -= 0.5 * (ego_vehicle.LENGTH + front_vehicle.LENGTH)
            ratio = self.desired_gap(ego_vehicle, front_vehicle) / max(s, 0.1)
            return acc - self.COMFORT_ACC_MAX * ratio**2

        def step(self, dt: float) -> None:
            super().step(dt)
            if self.speed < 0.0:  # IDM braking ends at standstill: vehicles never reverse
                self.speed = 0.0

        def _safe(self, lane_index) -> bool:
            pre, fol = self.road.neighbour_vehicles(self, lane_index)
            b = self.LANE_CHANGE_MAX_BRAKING_IMPOSED * (1.0 + 0.75 * self.urgency)
            for other, ego, front in ((fol, fol, self), (pre, self, pre)):
                if other is None:
                    continue
                gap = abs(self.lane_distance_to(other)) - 0.5 * (self.LENGTH + other.LENGTH)
                if gap < 2.0 or self.acceleration(ego_vehicle=ego, front_vehicle=front) < -b:
                    return False
            return True

    return RampDriver


def size_vehicle(v, length: float, width: float) -> None:
    """Give a highway-env vehicle its length and width, and the crash pre-check its reach:
    highway-env caches ``diagonal`` at construction (from the class's 5 x 2 m), so a longer
    vehicle set afterwards would not be checked against vehicles beyond that reach."""
    v.LENGTH, v.WIDTH = float(length), float(width)
    v.diagonal = float(math.hypot(length, width))


# --------------------------------------------------------------------------------------
# one recording
# --------------------------------------------------------------------------------------
def record(loc: Location, opts: HighwayOptions, seed: np.random.SeedSequence, rid: int):
    """Simulate one recording: ``(tracks, tracks_meta, recording_meta)`` DataFrames in the
    exiD layout, and the number of crashes removed."""
    rec = _Recording(loc, opts, seed)
    rows, crashes = rec.run()
    return _frames(rows, rec.info, loc, opts, rid), crashes


class _Recording:
    """One simulated recording of ``loc``: the road, the entries and their flows, and the
    vehicles' own data (``info``: vehicle -> dict(id, cls, exit, prep, merge_at)); every
    random draw comes from one generator seeded by ``seed``, in simulation order."""

    def __init__(self, loc: Location, opts: HighwayOptions, seed: np.random.SeedSequence):
        from .sim._highway import hw

        H = hw()
        self.Driver = driver_class()
        self.loc, self.opts = loc, opts
        self.rng = rng = np.random.default_rng(seed)
        net, self.ids, (self.x_b, self.x_c) = build_network(loc)
        self.net = net
        self.road = H.Road(network=net, np_random=np.random.RandomState(int(rng.integers(2**31))))
        self.road.vehicles = []
        self.dt = 1.0 / opts.frame_rate
        self.nl = nl = loc.lanes
        self.aux = ("b", "c", nl)
        # merging vehicles brake for the end of the acceleration lane (a deceleration lane
        # continues into the exit: no end there)
        self.aux_end = None
        if loc.ramp == "on":
            self.aux_end = H.Obstacle(
                self.road, net.get_lane(self.aux).position(loc.aux_length, 0.0)
            )
        self.entries = [("a", "b", i) for i in range(nl)] + (
            [("j", "k", 0)] if loc.ramp == "on" else []
        )
        self.rates = [rng.uniform(*opts.flow) for _ in range(nl)]
        if loc.ramp == "on":
            self.rates.append(rng.uniform(*opts.ramp_flow))
        self.last_exit = ("e", "f") if loc.ramp == "off" else None
        self.info: dict = {}
        self.next_id = 1

    def want(self, v):
        """The lane vehicle ``v`` heads for (``None``: its own), and its urgency."""
        loc, nl, d = self.loc, self.nl, self.info[v]
        e, x = v.lane_index, v.position[0]
        if d["exit"]:
            if e[:2] == ("b", "c") and e[2] < nl and x > self.x_c - 40.0:  # missed the exit
                d["exit"], v.route = False, [("c", "d", None)]
                return None
            v.urgency = float(
                np.clip((x - self.x_b + d["prep"]) / (d["prep"] + loc.aux_length), 0, 1)
            )
            if e[:2] == ("a", "b") and x > self.x_b - d["prep"]:
                return nl - 1
            if e[:2] == ("b", "c"):
                return nl
            return None
        if e == self.aux and x > d["merge_at"]:
            v.urgency = float(np.clip((x - self.x_b) / loc.aux_length, 0.0, 1.0))
            return nl - 1
        return None

    def spawn(self, lane_index) -> None:
        """A new vehicle at the start of ``lane_index``, if the entry is free."""
        loc, opts, rng, road, nl = self.loc, self.opts, self.rng, self.road, self.nl
        lane = self.net.get_lane(lane_index)
        truck = lane_index[2] >= nl - 2 and rng.random() < opts.truck_share
        if truck:
            length, width, v0 = rng.uniform(10.0, 16.5), 2.5, rng.uniform(22.0, 25.0)
        else:
            length, width = rng.uniform(4.2, 5.2), rng.uniform(1.75, 2.0)
            v0 = min(rng.uniform(0.85, 1.15) * loc.limit, 45.0)
        # free entry: no vehicle within the first 2 s of the lane
        ahead = [
            u for u in road.vehicles
            if u.lane_index[:2] == lane_index[:2] and u.lane_index[2] == lane_index[2]
        ]  # fmt: skip
        s_min = min((lane.local_coordinates(u.position)[0] for u in ahead), default=np.inf)
        speed = min(v0, lane.speed_limit)
        if s_min < max(25.0, 2.0 * speed) + length:
            return
        if ahead:
            front = min(ahead, key=lambda u: lane.local_coordinates(u.position)[0])
            speed = min(speed, front.speed)
        route, exits = self._route(lane_index)
        v = self.Driver(
            road, lane.position(0.0, 0.0), heading=lane.heading_at(0.0), speed=speed,
            target_lane_index=lane_index, target_speed=v0, route=route,
            timer=float(rng.uniform(0.0, 1.0)),
        )  # fmt: skip
        size_vehicle(v, length, width)
        v.TIME_WANTED = float(rng.uniform(1.0, 2.0))
        v.COMFORT_ACC_MAX = float(rng.uniform(0.8, 1.5) if truck else rng.uniform(1.5, 3.0))
        v.DISTANCE_WANTED = float(rng.uniform(2.0, 4.0))  # bumper to bumper (acceleration)
        v.POLITENESS = float(rng.uniform(0.0, 0.5))
        v.LANE_CHANGE_MIN_ACC_GAIN = float(rng.uniform(0.1, 0.4))
        v.want, v.aux, v.aux_end = self.want, self.aux, self.aux_end
        self.info[v] = dict(
            id=self.next_id, cls="truck" if truck else "car", exit=exits,
            prep=float(rng.uniform(150.0, 280.0)),
            merge_at=self.x_b + float(rng.uniform(0.05, 0.4)) * loc.aux_length,
        )  # fmt: skip
        self.next_id += 1
        road.vehicles.append(v)

    def _route(self, lane_index) -> tuple[list, bool]:
        """The route of a vehicle entering at ``lane_index`` and whether it exits."""
        loc = self.loc
        if loc.ramp == "on" and lane_index[0] == "j":
            return [("j", "k", 0), ("k", "b", 0), ("b", "c", self.nl), ("c", "d", None)], False
        exits = loc.ramp == "off" and self.rng.random() < self.opts.exit_share
        tail = (
            [("b", "c", None), ("c", "e", 0), ("e", "f", 0)]
            if exits
            else [("b", "c", None), ("c", "d", None)]
        )
        return [lane_index, *tail], exits

    def done(self, v) -> bool:
        """Vehicle ``v`` has left the road (the end of the main road or the exit) or crashed."""
        lane = self.net.get_lane(v.lane_index)
        s = lane.local_coordinates(v.position)[0]
        end = v.lane_index[:2] in (("c", "d"), self.last_exit)
        return (end and s > lane.length - 2.0) or v.crashed

    def run(self) -> tuple[list, int]:
        """Warm up, then record every frame: the rows of the tracks and the crashes removed."""
        opts, road, dt, rng = self.opts, self.road, self.dt, self.rng
        n_warm = int(round(opts.warmup * opts.frame_rate))
        n_rec = int(round(opts.duration * opts.frame_rate))
        rows = []
        crashes = 0
        for k in range(-n_warm, n_rec):
            for lane_index, q in zip(self.entries, self.rates, strict=True):
                if rng.random() < q * dt:
                    self.spawn(lane_index)
            road.act()
            road.step(dt)
            gone = [v for v in road.vehicles if self.done(v)]
            crashes += sum(v.crashed for v in gone)
            for v in gone:
                road.vehicles.remove(v)
            if k < 0:
                continue
            for v in road.vehicles:
                lane = v.lane
                s, lat = lane.local_coordinates(v.position)
                rows.append(
                    (self.info[v]["id"], k, v.position[0], v.position[1], v.heading,
                     self.ids[v.lane_index], lat, lane.width_at(s), s, lane.length)
                )  # fmt: skip
        return rows, crashes


def _frames(rows, info, loc: Location, opts: HighwayOptions, rid: int):
    import pandas as pd

    cols = ["trackId", "frame", "x", "y", "h", "lanelet", "lat", "lw", "s", "ll"]
    df = pd.DataFrame(rows, columns=cols).sort_values(["trackId", "frame"], kind="stable")
    counts = df.groupby("trackId")["frame"].transform("size")
    df = df[counts >= 3].reset_index(drop=True)
    dt = 1.0 / opts.frame_rate
    tid = df["trackId"].to_numpy()
    x, y, h = (df[c].to_numpy(dtype=float) for c in ("x", "y", "h"))
    starts = np.flatnonzero(np.r_[True, tid[1:] != tid[:-1]])
    ends = np.r_[starts[1:], len(tid)]
    vx, vy, ax, ay, dist = (np.empty(len(tid)) for _ in range(5))
    for a, b in zip(starts, ends, strict=True):
        vx[a:b] = np.gradient(x[a:b], dt)
        vy[a:b] = np.gradient(y[a:b], dt)
        ax[a:b] = np.gradient(vx[a:b], dt)
        ay[a:b] = np.gradient(vy[a:b], dt)
        step = np.hypot(np.diff(x[a:b]), np.diff(y[a:b]))
        dist[a:b] = np.r_[0.0, np.cumsum(step)]
    c, s = np.cos(h), np.sin(h)
    by_id = {d["id"]: (d, v) for v, d in info.items()}
    first = df.groupby("trackId")["frame"].transform("min").to_numpy()
    length = np.array([by_id[t][1].LENGTH for t in tid])
    width = np.array([by_id[t][1].WIDTH for t in tid])
    tracks = pd.DataFrame(
        {
            "recordingId": rid,
            "trackId": tid,
            "frame": df["frame"].to_numpy(),
            "trackLifetime": df["frame"].to_numpy() - first,
            "xCenter": x,
            "yCenter": y,
            "heading": np.mod(np.degrees(h), 360.0),
            "width": width,
            "length": length,
            "xVelocity": vx,
            "yVelocity": vy,
            "xAcceleration": ax,
            "yAcceleration": ay,
            "lonVelocity": c * vx + s * vy,
            "latVelocity": -s * vx + c * vy,
            "lonAcceleration": c * ax + s * ay,
            "latAcceleration": -s * ax + c * ay,
            "traveledDistance": dist,
            "latLaneCenterOffset": df["lat"].to_numpy(),
            "laneWidth": df["lw"].to_numpy(),
            "laneletId": df["lanelet"].to_numpy(),
            "lonLaneletPos": df["s"].to_numpy(),
            "laneletLength": df["ll"].to_numpy(),
        }
    )
    g = tracks.groupby("trackId")
    meta = pd.DataFrame(
        {
            "recordingId": rid,
            "trackId": g["frame"].min().index.to_numpy(),
            "initialFrame": g["frame"].min().to_numpy(),
            "finalFrame": g["frame"].max().to_numpy(),
            "numFrames": g["frame"].size().to_numpy(),
            "width": g["width"].first().to_numpy(),
            "length": g["length"].first().to_numpy(),
            "class": [by_id[t][0]["cls"] for t in g["frame"].min().index],
        }
    )
    lat, lon = latlon_from_utm(*loc.utm_origin, ZONE)
    rec = pd.DataFrame(
        {
            "recordingId": [rid],
            "locationId": [loc.id],
            "frameRate": [opts.frame_rate],
            "speedLimit": [loc.speed_limit if loc.speed_limit is not None else -1.0],
            "weekday": ["monday"],
            "startTime": [8],
            "duration": [opts.duration],
            "numTracks": [len(meta)],
            "numVehicles": [len(meta)],
            "numVRUs": [0],
            "latLocation": [float(lat)],
            "lonLocation": [float(lon)],
            "xUtmOrigin": [loc.utm_origin[0]],
            "yUtmOrigin": [loc.utm_origin[1]],
            "orthoPxToMeter": [0.1],
        }
    )
    return tracks, meta, rec


_FILES = ("tracks", "tracksMeta", "recordingMeta")  # written in this order (meta last)


def _record_files(out: str, lid: int, opts: HighwayOptions, seed: int, i: int) -> tuple:
    """Simulate recording ``i`` at location ``lid`` and write its three CSV files atomically;
    ``(i, tracks, rows, crashes)``. One work unit of :func:`generate_raw` (a pool worker's).
    A recording whose files cannot all be written leaves none of them."""
    out = FilePath(out)
    (tracks, meta, rec), crashes = record(
        LOCATIONS[lid], opts, np.random.SeedSequence(int(seed), spawn_key=(i,)), i
    )
    paths = [out / "data" / f"{i:02d}_{n}.csv" for n in _FILES]
    try:
        for df, path in zip((tracks, meta, rec), paths, strict=True):
            write_atomic(path, df.to_csv(index=False, float_format="%.4f"))
    except BaseException:
        for path in paths:
            with contextlib.suppress(OSError):
                path.unlink()
        raise
    return i, len(meta), len(tracks), crashes


def raw_recipe(opts: HighwayOptions, seed: int) -> dict:
    """What ``recipe.json`` of a raw set records (module docstring): the seed and every
    option but ``recordings`` (a rerun with more recordings extends the set)."""
    d = {f.name: getattr(opts, f.name) for f in fields(opts) if f.name != "recordings"}
    return {"seed": int(seed), **{k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}}


_NAME = re.compile(r"(\d+)_(?:tracks|tracksMeta|recordingMeta)\.csv")


def _held(data: FilePath) -> int:
    """1 + the largest recording number with a file in ``data`` (0 when none)."""
    top = -1
    if data.is_dir():
        for f in data.iterdir():
            m = _NAME.fullmatch(f.name)
            if m:
                top = max(top, int(m.group(1)))
    return top + 1


def _pool(workers: int):
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from .dataset.engine import _single_threaded_children, _worker_init

    with _single_threaded_children():
        return ProcessPoolExecutor(
            max_workers=workers,
            mp_context=mp.get_context("spawn"),
            initializer=_worker_init,
            initargs=(os.getpid(),),
        )


def _run_pool(units, workers: int):
    """Results of ``_record_files(*u)`` for the lazy ``units``, ``workers`` at a time in
    worker processes (a bounded window in flight). Interrupted or failed: the recordings
    in flight are stopped at once (their files are never half-written) and the pool is
    shut down before the exception goes on, so no process or semaphore outlives it."""
    from concurrent.futures import FIRST_COMPLETED, wait

    from .dataset.engine import stop_pool

    ex = _pool(workers)
    finished = False
    flight: dict = {}  # future -> its unit
    try:
        for u in units:
            flight[ex.submit(_record_files, *u)] = u
            if len(flight) >= 2 * workers:
                break
        while flight:
            done, _ = wait(set(flight), return_when=FIRST_COMPLETED)
            for f in done:
                res = f.result()
                del flight[f]
                yield res
                nxt = next(units, None)
                if nxt is not None:
                    flight[ex.submit(_record_files, *nxt)] = nxt
        finished = True
    finally:
        if not finished:
            stop_pool(ex)
            for out, _, _, _, i in flight.values():  # stopped while writing: no part stays
                _discard_partial(FilePath(out), i)
        ex.shutdown(wait=True, cancel_futures=True)


def _discard_partial(out: FilePath, i: int) -> None:
    """Remove the files of recording ``i`` unless all three are there (and temporaries)."""
    data = out / "data"
    if all((data / f"{i:02d}_{n}.csv").is_file() for n in _FILES):
        return
    for f in [*data.glob(f"{i:02d}_*.csv"), *data.glob(f".{i:02d}_*.tmp")]:
        with contextlib.suppress(OSError):
            f.unlink()


def generate_raw(
    out: str | os.PathLike,
    opts: HighwayOptions,
    seed: int = 0,
    progress: bool = False,
    workers: int = 1,
) -> dict:
    """Write the raw set (module docstring) into ``out``: maps of the used locations and the
    recordings ``0 .. recordings - 1`` (existing complete ones are kept). ``workers`` > 1
    simulates that many recordings at a time in worker processes (the files are the same:
    recording ``i`` depends only on ``seed`` and ``i``; each is written atomically, so an
    interrupted run keeps every finished recording). The folder is locked for the whole
    run and records its recipe (:func:`raw_recipe`; module docstring, "Output folder"):
    a run with another recipe, or a second run at the same time, is refused
    (:class:`~epo_casadi.errors.SpecError`, :class:`scenarios.files.BusyError`). Returns
    counts: ``recordings``, ``written``, ``tracks``, ``rows``, ``crashes``, ``seconds``."""
    import time

    if not isinstance(opts, HighwayOptions):
        raise SpecError("opts", f"expected HighwayOptions, got {type(opts).__name__}")
    check_number("seed", seed, lo=0, integer=True)
    check_number("workers", workers, lo=1, integer=True)
    t0 = time.perf_counter()
    with claim_output(out, "highway-raw", raw_recipe(opts, seed), what="epo generate highway-raw"):
        out = FilePath(out)
        held = _held(out / "data")
        if held > opts.recordings:
            raise SpecError(
                "recordings",
                f"{out} already holds recordings 0 .. {held - 1}; ask for {held} or more to "
                f"resume or extend the set (got {opts.recordings}), or use another folder",
            )
        ensure_dir(out / "data")
        for tmp in [*out.glob("data/.*.tmp"), *out.glob("maps/lanelet2/.*.tmp")]:
            with contextlib.suppress(OSError):  # left by a killed run (we hold the lock)
                tmp.unlink()
        for lid in sorted(set(opts.locations)):
            loc = LOCATIONS[lid]
            write_map(loc, out / "maps" / "lanelet2" / f"{lid}_{loc.name}.osm")

        def complete(i: int) -> bool:
            return all((out / "data" / f"{i:02d}_{n}.csv").is_file() for n in _FILES)

        n_done = sum(1 for i in range(opts.recordings) if complete(i))
        n_todo = opts.recordings - n_done
        units = (
            (str(out), opts.locations[i % len(opts.locations)], opts, int(seed), i)
            for i in range(opts.recordings)
            if not complete(i)
        )
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=opts.recordings, unit="recording", desc=f"highway -> {out}")
            bar.update(n_done)
        stats = dict(recordings=opts.recordings, written=0, tracks=0, rows=0, crashes=0)
        try:
            if workers <= 1 or n_todo <= 1:
                results = (_record_files(*u) for u in units)
            else:
                results = _run_pool(units, min(workers, n_todo))
            try:
                for _, n_tracks, n_rows, crashes in results:
                    stats["written"] += 1
                    stats["tracks"] += n_tracks
                    stats["rows"] += n_rows
                    stats["crashes"] += crashes
                    if bar is not None:
                        bar.update(1)
            finally:
                results.close()  # stops the pool now, also after an interrupt
        finally:
            if bar is not None:
                bar.close()
    stats["seconds"] = time.perf_counter() - t0
    return stats
