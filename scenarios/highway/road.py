"""The generator's locations and their roads: the :class:`Location` geometries
(:data:`LOCATIONS`), the highway-env road network of each (:func:`build_network`) and its
lanelet2 map in the exiD layout (:func:`write_map`). Geometry and map format:
:mod:`scenarios.highway`, "Locations" and "Recording"."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path as FilePath

import numpy as np

from ..exid import latlon_from_utm
from ..files import write_atomic

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


def build_network(loc: Location):
    """highway-env ``RoadNetwork`` of a location, its lanelet ids (lane index -> int) and the
    key positions ``(x_b, x_c)`` (start and end of the auxiliary lane)."""
    from ..sim._highway import hw

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
    """The lanelet2 ``.osm`` map of a location (:mod:`scenarios.highway`), written atomically."""
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
