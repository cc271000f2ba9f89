"""Highway on-ramp merge on highway-env: agent 0, the ego, drives up an on-ramp and must
merge into the main road's right-most lane before the acceleration lane ends, among
reactive traffic.

Road network (metres, mathematical frame, traffic towards +x): ``lanes`` main lanes at
``y = 0, -w, ...`` (lane 0 the left-most) through nodes ``a -> b -> c -> d``; the ramp
(``"ramp"``, ``j -> k``, straight) joins through a converging sine lane
(``"ramp_converge"``, ``k -> b``) into the acceleration lane (``"merge_lane"``, the extra
lane of ``b -> c``, ``merge_length`` long), which ends at ``c``. highway-env lanes
(``StraightLane``, ``SineLane``) in a ``RoadNetwork`` built here; the same lanes, sampled,
are the world's :class:`scenarios.maps.RoadMap`.

Ego: a highway-env ``Vehicle`` (kinematic bicycle, command ``(a, delta)``, exactly
``VehicleModel.highway().step``). Its task path follows the ramp and the acceleration lane
and blends (smoothstep) into the right-most main lane between 20 % and 80 % of the
acceleration lane; its goal lies ``goal_distance`` m after the acceleration lane's end.

Traffic: ``traffic`` highway-env ``IDMVehicle`` s on the main lanes (IDM acceleration,
MOBIL lane changes, lane-following steering; the acceleration lane is ``forbidden`` to
them). Each has a seeded character (:class:`~scenarios.sim.common.Character`):
aggressiveness ``g`` sets the time headway ``2 - g`` s, comfortable acceleration
``2 + 2 g`` m/s^2 and MOBIL politeness ``1 - g``; its desired speed is drawn from
``desired_speed`` x speed limit. Vehicles are placed so that they reach the merge area
about when the ego does (arrival offsets ``U(-spread, spread)`` m, at least 15 m apart in
a lane), 70 % of them in the right-most lane. They react to the ego through IDM as soon
as it is in their lane (highway-env's ``neighbour_vehicles``).

Collision, outcome, observations: as :mod:`scenarios.sim.left_turn` (``collision`` =
highway-env's crash flag or circles; ``off_road`` past the end of the acceleration lane or
off every lane; ``success`` on a main lane past the goal; ``timeout``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size
from solvers.control.types import AgentTask, Observation
from solvers.control.vehicle import VehicleModel

from ..maps import RoadMap, resample_polyline
from ._highway import HighwayWorld, hw
from .common import (
    Character,
    Latch,
    Sensor,
    build_options,
    check_command,
    check_episode_sizes,
    check_range,
    check_sensor,
    check_speed_fraction,
    seeds,
)

__all__ = ["MergeOptions", "MergeWorld"]

AMPLITUDE = 3.25  # m, half the lateral offset of the ramp's converging sine lane


@dataclass(frozen=True)
class MergeOptions:
    """Options of :class:`MergeWorld` (frozen; unknown names are errors)."""

    lanes: int = 2  #: main lanes (1 to 4)
    lane_width: float = 4.0  #: w (m)
    speed_limit: float = 30.0  #: main road (m/s)
    ramp_length: float = 120.0  #: straight ramp (m)
    converge_length: float = 80.0  #: converging sine lane (m)
    merge_length: float = 80.0  #: acceleration lane (m)
    traffic: int = 4  #: IDM/MOBIL vehicles on the main road (0 to 20)
    dt: float = 0.1  #: planning period = simulation step (s)
    max_steps: int = 200  #: timeout (steps), at most 100,000
    noise_std: float = 0.3  #: std of the position noise on other agents (m)
    dropout_prob: float = 0.0  #: fraction of an observed agent's positions lost (on average)
    dropout_burst: int = 3  #: length of a dropout (steps), at most 100,000
    ego_start: tuple[float, float] = (40.0, 70.0)  #: ego's position on the ramp (m)
    ego_speed: tuple[float, float] = (18.0, 24.0)  #: initial ego speed (m/s)
    spread: float = 50.0  #: traffic arrival offsets U(-spread, spread) around the ego's (m)
    aggressiveness: tuple[float, float] = (0.0, 1.0)  #: range of the drivers' characters
    #: range, fraction of the speed limit (at most 1: IDM never drives above the limit)
    desired_speed: tuple[float, float] = (0.75, 0.95)
    radius: float = 2.5  #: circle radius of each vehicle (m): collision="circles", metrics;
    #: the planners use two circles per car from the footprint (5 m x 2 m) instead
    collision: str = "rectangles"  #: "rectangles" (highway-env's crash flag) or "circles"
    goal_distance: float = 40.0  #: success: this far past the end of the merge lane (m)
    off_road_margin: float = 1.0  #: off_road: this far beyond every lane edge (m)
    n_path: int = 80  #: points of each AgentTask path (2 to 10,000)

    def __post_init__(self):
        p = "merge"
        object.__setattr__(self, "lanes", check_size(f"{p}.lanes", self.lanes, 4, "lanes"))
        check_number(f"{p}.lane_width", self.lane_width, lo=2.5, hi=5.0)
        check_number(f"{p}.speed_limit", self.speed_limit, lo=5.0, hi=40.0)
        check_number(f"{p}.ramp_length", self.ramp_length, lo=20.0)
        check_number(f"{p}.converge_length", self.converge_length, lo=20.0)
        check_number(f"{p}.merge_length", self.merge_length, lo=20.0)
        object.__setattr__(
            self, "traffic", check_size(f"{p}.traffic", self.traffic, 20, "agents", lo=0)
        )
        check_number(f"{p}.dt", self.dt, lo=0.01, hi=1.0)
        check_episode_sizes(self, p)
        burst = check_sensor(p, self.noise_std, self.dropout_prob, self.dropout_burst)
        object.__setattr__(self, "dropout_burst", burst)
        for name, lo, hi in (
            ("ego_start", 0.0, self.ramp_length),
            ("ego_speed", 0.0, 40.0),
            ("aggressiveness", 0.0, 1.0),
        ):
            object.__setattr__(self, name, check_range(f"{p}.{name}", getattr(self, name), lo, hi))
        ds = check_speed_fraction(f"{p}.desired_speed", self.desired_speed)
        object.__setattr__(self, "desired_speed", ds)
        check_number(f"{p}.spread", self.spread, lo=0.0)
        check_number(f"{p}.radius", self.radius, lo=0.0, lo_open=True)
        if self.collision not in ("rectangles", "circles"):
            raise SpecError(
                f"{p}.collision", f"expected 'rectangles' or 'circles', got {self.collision!r}"
            )
        check_number(f"{p}.goal_distance", self.goal_distance, lo=0.0)
        check_number(f"{p}.off_road_margin", self.off_road_margin, lo=0.0)


def build_network(o: MergeOptions):
    """highway-env ``RoadNetwork`` of the merge and the lane-id names."""
    H = hw()
    w, v = o.lane_width, o.speed_limit
    x_b = o.ramp_length + o.converge_length
    x_c = x_b + o.merge_length
    x_d = x_c + o.goal_distance + 100.0
    net = H.RoadNetwork()
    names = {}
    for i in range(o.lanes):
        y = -i * w
        for a, b, x0, x1 in (("a", "b", 0.0, x_b), ("b", "c", x_b, x_c), ("c", "d", x_c, x_d)):
            net.add_lane(a, b, H.StraightLane([x0, y], [x1, y], width=w, speed_limit=v))
            names[(a, b, i)] = f"main{i}_{a}{b}"
    y_m = -o.lanes * w
    y_r = y_m - 2 * AMPLITUDE
    ramp = H.StraightLane([0.0, y_r], [o.ramp_length, y_r], width=w, speed_limit=v, forbidden=True)
    conv = H.SineLane(
        [o.ramp_length, y_r + AMPLITUDE],
        [x_b, y_r + AMPLITUDE],
        -AMPLITUDE,
        math.pi / o.converge_length,
        math.pi / 2,
        width=w,
        speed_limit=v,
        forbidden=True,
    )
    merge = H.StraightLane([x_b, y_m], [x_c, y_m], width=w, speed_limit=v, forbidden=True)
    net.add_lane("j", "k", ramp)
    net.add_lane("k", "b", conv)
    net.add_lane("b", "c", merge)
    names[("j", "k", 0)] = "ramp"
    names[("k", "b", 0)] = "ramp_converge"
    names[("b", "c", o.lanes)] = "merge_lane"
    return net, names, (x_b, x_c, y_m)


class MergeWorld(HighwayWorld):
    """The on-ramp merge as a :class:`solvers.control.types.World` (module docstring)."""

    name = "merge"
    dataset_scenario = "merge"

    def __init__(self, options: MergeOptions | None = None, **kw):
        if options is not None and kw:
            raise SpecError("merge", "give either options or keyword options, not both")
        self.options = options if options is not None else build_options(MergeOptions, "merge", kw)
        o = self.options
        self.dt = float(o.dt)
        self.max_steps = int(o.max_steps)
        self.vehicle = VehicleModel.highway()
        self.n_agents = 1 + o.traffic
        self.radii = np.full(self.n_agents, float(o.radius))
        self.network, names, (self._x_b, self._x_c, y_m) = build_network(o)
        self.road_map = RoadMap.from_highway(self.network, step=1.0, names=names)
        w = o.lane_width
        self._y_right = -(o.lanes - 1) * w
        rm = self.road_map
        head = rm.route(("ramp", "ramp_converge"))
        x = np.arange(self._x_b + 1.0, self._x_c + o.goal_distance + 10.0, 1.0)
        u = np.clip((x - self._x_b - 0.2 * o.merge_length) / (0.6 * o.merge_length), 0.0, 1.0)
        y = y_m + (self._y_right - y_m) * (3 * u**2 - 2 * u**3)
        self.ego_route = np.concatenate([head, np.stack([x, y], axis=1)])
        self._goal = np.array([self._x_c + o.goal_distance, self._y_right])
        self.ego_task = AgentTask(
            path=resample_polyline(self.ego_route, o.n_path),
            speed=float(o.speed_limit),
            goal=self._goal.copy(),
            radius=float(o.radius),
        )
        self.sensor = Sensor(o.traffic, o.noise_std, o.dropout_prob, o.dropout_burst)
        self._ready = False

    def reset(self, seed: int) -> Observation:
        H = hw()
        o = self.options
        g_scene, g_char, g_sense = seeds(seed, 3)
        self.road = H.Road(
            network=self.network, np_random=np.random.RandomState(int(g_scene.integers(2**31)))
        )
        s0 = float(g_scene.uniform(*o.ego_start))
        v0 = float(g_scene.uniform(*o.ego_speed))
        ramp = self.network.get_lane(("j", "k", 0))
        self.ego = H.Vehicle(self.road, ramp.position(s0, 0.0), heading=0.0, speed=v0)
        # the ego reaches the acceleration lane after about t_m seconds
        t_m = (self._x_b - s0) / max(v0, 1.0)
        n = o.traffic
        lane = np.where(g_scene.random(n) < 0.7, o.lanes - 1, g_scene.integers(o.lanes, size=n))
        offs = g_scene.uniform(-o.spread, o.spread, size=n)
        chars = [
            Character.draw(
                g_char,
                o.aggressiveness,
                tuple(f * o.speed_limit for f in o.desired_speed),
                (0.0, 0.0),
            )
            for _ in range(n)
        ]
        x0 = self._x_b + offs - np.array([c.desired_speed for c in chars]) * t_m
        # at least 15 m between vehicles of a lane (pushed backwards, in order)
        order = np.lexsort((-x0, lane))
        for a, b in zip(order[:-1], order[1:], strict=True):
            if lane[a] == lane[b] and x0[a] - x0[b] < 15.0:
                x0[b] = x0[a] - 15.0
        self.others = []
        for i in range(n):
            c = chars[i]
            li = ("a", "b", int(lane[i]))
            hl = self.network.get_lane(li)
            veh = H.IDMVehicle(
                self.road,
                hl.position(float(x0[i]), 0.0),
                heading=0.0,
                speed=c.desired_speed,
                target_lane_index=li,
                target_speed=c.desired_speed,
                route=[li, ("b", "c", None), ("c", "d", None)],
                timer=float(g_char.uniform(0.0, 1.0)),
            )
            veh.TIME_WANTED = 2.0 - c.aggressiveness
            veh.COMFORT_ACC_MAX = 2.0 + 2.0 * c.aggressiveness
            veh.POLITENESS = 1.0 - c.aggressiveness
            self.others.append(veh)
        self.characters = chars
        self.road.vehicles = [self.ego, *self.others]
        self.sensor.reset(g_sense)
        self.t, self.k = 0.0, 0
        self.latch = Latch()
        self._ready = True
        return self._observe()

    def step(self, command: np.ndarray) -> Observation:
        if not self._ready:
            raise SpecError("merge", "call reset(seed) before step(command)")
        u = check_command(command, "a, delta")
        self.ego.act({"acceleration": float(u[0]), "steering": float(u[1])})
        self.road.act()
        self.road.step(self.dt)
        self._stop_not_reverse()
        self.k += 1
        self.t = self.k * self.dt
        self._check()
        return self._observe()

    @property
    def vehicles(self) -> list:
        return [self.ego, *self.others]

    def tasks(self) -> list[AgentTask]:
        out = [self.ego_task]
        for veh, c in zip(self.others, self.characters, strict=True):
            i = veh.lane_index[2] if veh.lane_index[2] < self.options.lanes else 0
            ids = (f"main{i}_ab", f"main{i}_bc", f"main{i}_cd")
            out.append(
                self.road_map.task(
                    ids,
                    n_points=self.options.n_path,
                    radius=self.options.radius,
                    # what IDM targets: the desired speed within the lanes' limit
                    speed=min(c.desired_speed, min(self.road_map.lane(j).speed_limit for j in ids)),
                )
            )
        return out

    def info(self) -> dict:
        """The drivers' hidden characters (metrics and tests, never planners)."""
        return dict(characters=list(self.characters))

    def _succeeded(self, p: np.ndarray) -> bool:
        """On the main road past the goal."""
        o = self.options
        on_main = -(o.lanes - 0.5) * o.lane_width <= p[1] <= 0.5 * o.lane_width
        return bool(on_main and p[0] >= self._goal[0])
