"""One simulated recording: the traffic of a location (arrivals, routes, vehicles drawn
per seed; :class:`_Recording`) and its frames as the three exiD tables (:func:`record`;
columns in :mod:`scenarios.highway`, "Recording")."""

from __future__ import annotations

import numpy as np

from ..exid import latlon_from_utm
from .drivers import driver_class, size_vehicle
from .options import HighwayOptions
from .road import ZONE, Location, build_network


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
        from ..sim._highway import hw

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
