"""Unprotected left turn with an oncoming vehicle, on highway-env (after the paper's CARLA
scenario, App. E): agent 0, the ego (SDV), turns left across the lane of agent 1, an
oncoming vehicle going straight.

Frame and road network (metres, mathematical frame: x east, y north, headings CCW from
+x). The ego's road runs north-south; the crossing road meets it at the origin. The ego
approaches from the south in lane 0 (next to the median, ``x = w/2``), turns left by the
geometry's ``angle`` on a circular arc of radius ``turn_radius`` into the crossing road's
lane 0 and drives on (lanes ``"ego_approach"``, ``"ego_turn"``, ``"ego_exit"``). The
oncoming vehicle comes from the north in one of the ``lanes`` southbound lanes (drawn per
episode) and goes straight (``"oncoming{i}_approach"``, ``"oncoming{i}_through"``). Every
lane is a highway-env ``StraightLane`` / ``CircularLane`` in a ``RoadNetwork`` built here,
so the geometry is a parameter (:class:`Intersection`, :data:`GEOMETRIES`); the same lanes,
sampled, are the world's :class:`scenarios.maps.RoadMap`.

Dynamics. The ego is a highway-env ``Vehicle`` (kinematic bicycle, one step of ``dt`` per
command ``(a, delta)``, stopping rather than reversing: exactly
``VehicleModel.highway().step``). The oncoming vehicle is a
highway-env ``IDMVehicle`` (IDM acceleration, lane-following steering, no lane change)
whose go / yield decision is ours:

Oncoming driver (hand-made, never the planner under test). Its character
(:class:`~scenarios.sim.common.Character`) is drawn per episode: aggressiveness ``g`` in
``U(aggressiveness)``, desired speed ``U(desired_speed) x`` speed limit, reaction time in
``U(reaction)`` (s). IDM parameters follow ``g``: time headway ``2 - g`` s, comfortable
acceleration ``2 + 2 g`` m/s^2. Every step, until it is committed (it passed its wait
point, or it is going and could no longer stop before it braking at 5 m/s^2), it looks at the ego as it was
``reaction`` s ago and applies :func:`~scenarios.sim.common.gap_decision`: it goes if the
ego already left the conflict zone or if it clears the zone itself (accelerating to its
desired speed) ``margin`` s before the ego (at constant speed) reaches it, where the margin
runs from ``margin[0]`` (``g = 0``, cautious) to ``margin[1]`` (``g = 1``, bold, negative:
it forces its way); otherwise it yields: IDM towards a virtual standing obstacle that stops
it at its wait point (half a length before the conflict zone or at the crossing road's
edge, whichever comes first, set back further where needed so that its centre is
``WAIT_CLEARANCE`` = 5 m, half its length + half the ego's width + 1.5 m, from the ego's
route: a waiting car never blocks the turn). A yielding car stops; it never reverses (its
acceleration is limited to what stops it within the step). An ego standing still before
the zone never reaches it, so the oncoming vehicle then goes; so does it once the ego (as
seen) has stood still for ``patience`` s with its body at least ``WAIT_GAP`` = 0.5 m from
the oncoming car's side of the lane, before crossing it (an ego waiting at the edge of the
zone: without this rule both would wait for each other). The oncoming car starts at its
desired speed, or at ``other_speed`` (a slow start: it then accelerates, and a
constant-velocity prediction is wrong). highway-env's IDM also brakes for the ego when the
ego is on its lane. The conflict zone is where the two routes' centre lines
are closer than 2.5 m (a vehicle width and a margin, less than any lane width, so adjacent
parallel lanes do not conflict); reach / clear times add half a vehicle length each side.

Tasks: the ego's :class:`~solvers.control.types.AgentTask` is its route (approach, turn,
exit) resampled to ``n_path`` points, with the smallest speed limit on it (the turn's,
``min(speed_limit, sqrt(3 R))``: 3 m/s^2 lateral acceleration) and its goal
``goal_distance`` m into the exit lane; the oncoming vehicle's is its lane with its desired
speed (:meth:`LeftTurnWorld.tasks`, the oracle's privilege).

Collisions: ``collision="rectangles"`` (default) is highway-env's crash flag (oriented 5 m x
2 m rectangles, ``Road.step``); ``"circles"``: the circles of ``radii`` overlap. The
world's ``radii`` do not change the rectangle test. The planners model each car as two
circles made from the world's ``footprint`` (5 m x 2 m, :mod:`solvers.control.plan`), and
use ``radius`` only without one; ``radius`` (default 1.75 m = (L/2 + W/2) / 2: two such
circles touch at 3.5 m, the centre distance at which two cars meeting at a right angle
touch) is the circle of ``collision="circles"``, of the metric ``min_distance`` and of the
passing order's reach. After a crash highway-env brakes the crashed vehicles to a stop.

Outcome (first terminal one sticks): ``collision``; ``off_road`` when the ego is more than
``off_road_margin`` beyond the edge of every lane; ``success`` when it has driven
``goal_distance`` along the exit lane after the turn; ``timeout`` after ``max_steps``.

Observations: the ego exactly; the oncoming vehicle's position with Gaussian noise and
dropouts (:class:`~scenarios.sim.common.Sensor`). Everything is drawn from generators
seeded by ``reset(seed)``: an episode is bit-identical for a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size
from solvers.control.types import AgentTask, Observation
from solvers.control.vehicle import VehicleModel

from ..maps import ConflictZone, RoadMap, project_to_polyline
from ._highway import LENGTH, WIDTH, HighwayWorld, hw
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
    ego_interval,
    gap_decision,
    seeds,
    time_to_cover,
    zone_times,
)

__all__ = ["Intersection", "GEOMETRIES", "LeftTurnOptions", "LeftTurnWorld"]

#: m, the least distance from a yielding car's centre to the ego's route centre line: half
#: its length + half the ego's width + 1.5 m, so the ego passes a waiting car with room
WAIT_CLEARANCE = LENGTH / 2 + WIDTH / 2 + 1.5
#: m, an ego standing still with its body this far from the oncoming car's side is waiting
WAIT_GAP = 0.5
IDM_OVERSHOOT = 1.0  # m, how far IDM (not reversing) stops past a standing obstacle's gap
BRAKE = 5.0  # m/s^2, the braking a committed driver would need (IDM's COMFORT_ACC_MIN)
LAT_ACC = 3.0  # m/s^2, lateral acceleration that sets the turn's speed limit
CLEARANCE = 2.5  # m, centre lines closer than this form the conflict zone (width 2 + 0.5)


@dataclass(frozen=True)
class Intersection:
    """Geometry of the left-turn intersection (see the module docstring)."""

    name: str = "custom"  #: label
    lane_width: float = 3.5  #: w (m), every lane
    lanes: int = 1  #: lanes per direction on the ego's road (ego in lane 0), 1 to 3
    cross_lanes: int = 1  #: lanes per direction on the crossing road, 1 to 3
    angle: float = 90.0  #: left-turn angle (deg): 90 = perpendicular crossing
    turn_radius: float = 10.0  #: radius of the ego's turn arc (m)
    speed_limit: float = 12.0  #: straight lanes (m/s); the turn: min(this, sqrt(3 R))
    approach: float = 80.0  #: length of the approach lanes (m)
    exit: float = 50.0  #: length of the exit lanes after the turn (m)

    def __post_init__(self):
        f = f"geometry[{self.name}]"
        check_number(f"{f}.lane_width", self.lane_width, lo=2.5, hi=5.0)
        for name in ("lanes", "cross_lanes"):
            object.__setattr__(
                self, name, check_size(f"{f}.{name}", getattr(self, name), 3, "lanes")
            )
        check_number(f"{f}.angle", self.angle, lo=45.0, hi=135.0)
        # the highway-env bicycle turns no tighter than (L/2) / sin(atan(tan(pi/4) / 2)) = 5.6 m
        check_number(f"{f}.turn_radius", self.turn_radius, lo=6.0, hi=50.0)
        check_number(f"{f}.speed_limit", self.speed_limit, lo=1.0, hi=40.0)
        check_number(f"{f}.approach", self.approach, lo=30.0)
        check_number(f"{f}.exit", self.exit, lo=20.0)


#: the named geometries: widths, turn angles, lane counts and radii all differ
GEOMETRIES: dict[str, Intersection] = {
    "g0": Intersection("g0", lane_width=3.5, lanes=1, cross_lanes=1, angle=90.0, turn_radius=10.0),
    "g1": Intersection(
        "g1", lane_width=3.0, lanes=1, cross_lanes=1, angle=70.0, turn_radius=12.0, speed_limit=11.0
    ),
    "g2": Intersection(
        "g2",
        lane_width=3.75,
        lanes=2,
        cross_lanes=2,
        angle=90.0,
        turn_radius=12.0,
        speed_limit=14.0,
    ),
    "g3": Intersection("g3", lane_width=3.25, lanes=2, cross_lanes=1, angle=115.0, turn_radius=9.0),
}


@dataclass(frozen=True)
class LeftTurnOptions:
    """Options of :class:`LeftTurnWorld` (frozen; unknown names are errors)."""

    geometry: str | Intersection = "g0"  #: a name of GEOMETRIES or an Intersection
    dt: float = 0.1  #: planning period = simulation step (s)
    max_steps: int = 150  #: timeout (steps), at most 100,000
    noise_std: float = 0.3  #: std of the position noise on other agents (m)
    dropout_prob: float = 0.0  #: fraction of an observed agent's positions lost (on average)
    dropout_burst: int = 3  #: length of a dropout (steps), at most 100,000
    ego_distance: tuple[float, float] = (12.0, 30.0)  #: ego centre to the conflict zone (m)
    ego_speed: tuple[float, float] = (3.0, 7.0)  #: initial ego speed (m/s)
    other_distance: tuple[float, float] = (20.0, 55.0)  #: oncoming centre to the zone (m)
    #: initial oncoming speed range (m/s); None: its desired speed. A slow start then
    #: accelerates (IDM) to the desired speed: a constant-velocity prediction misses that
    other_speed: tuple[float, float] | None = None
    aggressiveness: tuple[float, float] = (0.0, 1.0)  #: range of the oncoming character
    #: range, fraction of the speed limit, within [0.05, 1] (IDM never drives above the limit)
    desired_speed: tuple[float, float] = (0.7, 1.0)
    reaction: tuple[float, float] = (0.2, 1.0)  #: range of its reaction time (s)
    #: a fixed oncoming character (overrides the ranges); its desired speed (m/s) at most the
    #: geometry's speed limit
    character: Character | None = None
    margin: tuple[float, float] = (2.0, -1.0)  #: accepted time margin (s) at g = 0 and g = 1
    radius: float = 1.75  #: circle radius of each vehicle (m): collision="circles", metrics
    #: and planners without a footprint (module docstring)
    collision: str = "rectangles"  #: "rectangles" (highway-env's crash flag) or "circles"
    goal_distance: float = 15.0  #: success: driven this far along the exit lane (m)
    off_road_margin: float = 1.0  #: off_road: this far beyond every lane edge (m)
    n_path: int = 60  #: points of each AgentTask path (2 to 10,000)
    patience: float = 1.0  #: s the oncoming driver waits for an ego standing before the zone

    def __post_init__(self):
        p = "left-turn"
        g = self.geometry
        if isinstance(g, str):
            if g not in GEOMETRIES:
                raise SpecError(
                    f"{p}.geometry", f"unknown geometry {g!r}; valid: {', '.join(GEOMETRIES)}"
                )
        elif not isinstance(g, Intersection):
            raise SpecError(f"{p}.geometry", f"expected a name or an Intersection, got {g!r}")
        check_number(f"{p}.dt", self.dt, lo=0.01, hi=1.0)
        check_episode_sizes(self, p)
        burst = check_sensor(p, self.noise_std, self.dropout_prob, self.dropout_burst)
        object.__setattr__(self, "dropout_burst", burst)
        for name, lo, hi in (
            ("ego_distance", 0.0, None),
            ("ego_speed", 0.0, 30.0),
            ("other_distance", 0.0, None),
            ("aggressiveness", 0.0, 1.0),
            ("reaction", 0.0, 5.0),
            ("margin", -10.0, 10.0),
            ("other_speed", 0.0, 40.0),
        ):
            if getattr(self, name) is None and name == "other_speed":
                continue
            val = check_range(f"{p}.{name}", getattr(self, name), lo, hi, name != "margin")
            object.__setattr__(self, name, val)
        ds = check_speed_fraction(f"{p}.desired_speed", self.desired_speed)
        object.__setattr__(self, "desired_speed", ds)
        if self.character is not None and not isinstance(self.character, Character):
            raise SpecError(f"{p}.character", f"expected a Character, got {self.character!r}")
        if self.character is not None:
            limit = self.intersection.speed_limit
            if self.character.desired_speed > limit:
                raise SpecError(
                    f"{p}.character.desired_speed",
                    f"expected at most the speed limit of geometry {self.intersection.name!r}, "
                    f"{limit:g} m/s (IDM never drives faster), got {self.character.desired_speed:g}",
                )
        check_number(f"{p}.radius", self.radius, lo=0.0, lo_open=True)
        if self.collision not in ("rectangles", "circles"):
            raise SpecError(
                f"{p}.collision", f"expected 'rectangles' or 'circles', got {self.collision!r}"
            )
        check_number(f"{p}.goal_distance", self.goal_distance, lo=0.0)
        check_number(f"{p}.off_road_margin", self.off_road_margin, lo=0.0)
        check_number(f"{p}.patience", self.patience, lo=0.0)

    @property
    def intersection(self) -> Intersection:
        return GEOMETRIES[self.geometry] if isinstance(self.geometry, str) else self.geometry


def _unit(h: float) -> np.ndarray:
    return np.array([math.cos(h), math.sin(h)])


def build_network(geo: Intersection):
    """highway-env ``RoadNetwork`` of the intersection, the lane-id names of its lanes and
    the oncoming lanes' stop-line arc lengths (see the module docstring)."""
    H = hw()
    w, v = geo.lane_width, geo.speed_limit
    d_in = np.array([0.0, 1.0])
    h_out = math.pi / 2 + math.radians(geo.angle)
    d_out, r_out = _unit(h_out), np.array([math.sin(h_out), -math.cos(h_out)])
    cw = geo.cross_lanes * w
    # P: the ego lane (x = w/2) meets the exit lane (r_out . p = w/2)
    y_p = (w / 2 - r_out[0] * w / 2) / r_out[1]
    P = np.array([w / 2, y_p])
    R = geo.turn_radius
    delta = math.radians(geo.angle)
    T = R * math.tan(delta / 2)
    A, B = P - T * d_in, P + T * d_out
    C = A + R * np.array([-1.0, 0.0])
    net = H.RoadNetwork()
    names = {}

    def add(a, b, lane, name=None):
        net.add_lane(a, b, lane)
        if name:
            names[(a, b, len(net.graph[a][b]) - 1)] = name

    kw = dict(width=w, speed_limit=v)
    add("S0", "T", H.StraightLane(A - geo.approach * d_in, A, **kw), "ego_approach")
    v_turn = min(v, math.sqrt(LAT_ACC * R))
    add(
        "T",
        "X",
        H.CircularLane(C, R, 0.0, delta, clockwise=True, width=w, speed_limit=v_turn),
        "ego_turn",
    )
    t_b = float(d_out @ B)
    Lc = max(geo.approach, abs(t_b) + geo.exit)
    add("X", "W0", H.StraightLane(B, Lc * d_out + (w / 2) * r_out, **kw), "ego_exit")
    add("wb0_a", "X", H.StraightLane(-Lc * d_out + (w / 2) * r_out, B, **kw), "westbound0_in")
    for j in range(1, geo.cross_lanes):
        o = (w / 2 + j * w) * r_out
        add(f"wb{j}_a", f"wb{j}_b", H.StraightLane(-Lc * d_out + o, Lc * d_out + o, **kw))
    for j in range(geo.cross_lanes):
        o = -(w / 2 + j * w) * r_out
        add(f"eb{j}_a", f"eb{j}_b", H.StraightLane(Lc * d_out + o, -Lc * d_out + o, **kw))
    y_top = max(A[1] + geo.approach, 0.0)
    for i in range(1, geo.lanes):
        x = w / 2 + i * w
        add(f"nb{i}_a", f"nb{i}_b", H.StraightLane([x, A[1] - geo.approach], [x, y_top], **kw))
    stops = []
    for i in range(geo.lanes):
        x = -(w / 2 + i * w)
        # the crossing road's far edge (r_out . p = cw) on this lane: its stop line
        y_stop = (cw - r_out[0] * x) / r_out[1]
        top = np.array([x, y_stop + geo.approach])
        stop = np.array([x, y_stop])
        end = np.array([x, y_stop - 2 * cw / abs(math.sin(delta)) - geo.exit])
        add(f"sb{i}_a", f"sb{i}_s", H.StraightLane(top, stop, **kw), f"oncoming{i}_approach")
        add(f"sb{i}_s", f"sb{i}_b", H.StraightLane(stop, end, **kw), f"oncoming{i}_through")
        stops.append(geo.approach)
    return net, names, stops


class LeftTurnWorld(HighwayWorld):
    """The unprotected left turn as a :class:`solvers.control.types.World` (see the module
    docstring). ``LeftTurnWorld(geometry="g2", noise_std=0.5)`` or with a
    :class:`LeftTurnOptions`."""

    name = "left-turn"
    dataset_scenario = "left-turn"
    #: the map fields of a left-turn dataset scene (built by
    #: :func:`scenarios.left_turn.closed_loop_scene_fields`)
    scene_field_names = ("lanes", "paths", "vref", "goal_candidates")

    def __init__(self, options: LeftTurnOptions | None = None, **kw):
        if options is not None and kw:
            raise SpecError("left-turn", "give either options or keyword options, not both")
        self.options = (
            options if options is not None else build_options(LeftTurnOptions, "left-turn", kw)
        )
        o = self.options
        self.geometry = o.intersection
        self.dt = float(o.dt)
        self.max_steps = int(o.max_steps)
        self.vehicle = VehicleModel.highway()
        self.n_agents = 2
        self.radii = np.full(2, float(o.radius))
        self.network, names, self._stops = build_network(self.geometry)
        self.road_map = RoadMap.from_highway(self.network, step=0.5, names=names)
        self.ego_route_ids = ("ego_approach", "ego_turn", "ego_exit")
        self.ego_route = self.road_map.route(self.ego_route_ids)
        rm = self.road_map
        self._s_goal = rm.lane("ego_approach").length + rm.lane("ego_turn").length + o.goal_distance
        goal = rm.lane("ego_exit").point(o.goal_distance)
        self.ego_task = rm.task(self.ego_route_ids, n_points=o.n_path, radius=o.radius, goal=goal)
        self._zones = []
        for i, stop in enumerate(self._stops):
            route = rm.route((f"oncoming{i}_approach", f"oncoming{i}_through"))
            zone = rm.conflict_zone(self.ego_route, route, clearance=CLEARANCE)
            if zone is None:  # pragma: no cover - the turn always crosses the oncoming lanes
                raise SpecError("left-turn.geometry", f"the turn misses oncoming lane {i}")
            self._zones.append((route, zone, _wait_point(route, self.ego_route, zone, stop)))
        self.sensor = Sensor(1, o.noise_std, o.dropout_prob, o.dropout_burst)
        self.conflict: ConflictZone | None = None  # the episode's conflict zone (reset)
        #: "go" / "yield" overrides the oncoming driver's gap rule while it is not committed
        #: (demonstrations replay the other outcome, scenarios/left_turn.py); None: its rule
        self.forced_decision: str | None = None
        self._ready = False

    def conflict_zone(self) -> tuple[float, float] | None:
        """The ego's arc-length interval of :attr:`conflict` (the episode's zone, set by
        ``reset``; None before)."""
        return ego_interval(self.conflict)

    # ------------------------------------------------------------------ episode
    def reset(self, seed: int) -> Observation:
        H = hw()
        o = self.options
        g_scene, g_char, g_sense = seeds(seed, 3)
        geo = self.geometry
        self.lane_i = int(g_scene.integers(geo.lanes))
        self.other_route, self.conflict, self._s_wait = self._zones[self.lane_i]
        zone: ConflictZone = self.conflict
        d_e = float(g_scene.uniform(*o.ego_distance))
        v_e = float(g_scene.uniform(*o.ego_speed))
        d_o = float(g_scene.uniform(*o.other_distance))
        self.character = o.character or Character.draw(
            g_char,
            o.aggressiveness,
            tuple(f * geo.speed_limit for f in o.desired_speed),
            o.reaction,
        )
        ch = self.character
        app = (f"sb{self.lane_i}_a", f"sb{self.lane_i}_s", 0)
        self.road = H.Road(
            network=self.network, np_random=np.random.RandomState(int(g_scene.integers(2**31)))
        )
        v_o = min(ch.desired_speed, self.network.get_lane(app).speed_limit)
        if o.other_speed is not None:
            v_o = float(g_scene.uniform(*o.other_speed))
        s_e = max(zone.a[0] - LENGTH / 2 - d_e, 0.0)
        pe, he = _pose(self.ego_route, s_e)
        self.ego = H.Vehicle(self.road, pe, heading=he, speed=v_e)
        s_o = max(zone.b[0] - LENGTH / 2 - d_o, 0.0)
        po, ho = _pose(self.other_route, s_o)
        thr = (f"sb{self.lane_i}_s", f"sb{self.lane_i}_b", 0)
        drv = H.Driver(
            self.road,
            po,
            heading=ho,
            speed=v_o,
            target_lane_index=app,
            target_speed=ch.desired_speed,
            route=[app, thr],
            enable_lane_change=False,
            timer=0.0,
        )
        drv.TIME_WANTED = 2.0 - ch.aggressiveness
        drv.COMFORT_ACC_MAX = 2.0 + 2.0 * ch.aggressiveness
        self.driver = drv
        self.road.vehicles = [self.ego, drv]
        # IDM stops about a jam distance (DISTANCE_WANTED) behind a standing obstacle; without
        # reversing it overshoots that by up to about IDM_OVERSHOOT
        s_obstacle = self._s_wait + drv.DISTANCE_WANTED - IDM_OVERSHOOT
        self._stop_obstacle = H.Obstacle(
            self.road, _pose(self.other_route, s_obstacle, extend=True)[0]
        )
        self.sensor.reset(g_sense)
        self.t, self.k = 0.0, 0
        self.latch = Latch()
        self.committed = False
        self.decision = "go"
        self.decisions: list[str] = []
        self._ego_seen: list[tuple[float, float, float]] = []
        self._still = 0.0  # s the ego (as seen) has stood still clear of the oncoming lane
        self._ready = True
        self._decide()
        return self._observe()

    def step(self, command: np.ndarray) -> Observation:
        if not self._ready:
            raise SpecError("left-turn", "call reset(seed) before step(command)")
        u = check_command(command, "a, delta")
        self.ego.act({"acceleration": float(u[0]), "steering": float(u[1])})
        self.road.act()
        # a yielding car stops, it does not reverse (IDM overshoots its stop and backs up)
        acc = self.driver.action.get("acceleration", 0.0)
        self.driver.action["acceleration"] = max(acc, -max(self.driver.speed, 0.0) / self.dt)
        self.road.step(self.dt)
        self._stop_not_reverse()
        self.t = (self.k + 1) * self.dt
        self.k += 1
        self._check()
        self._decide()
        return self._observe()

    # ------------------------------------------------------------------ queries
    @property
    def vehicles(self) -> list:
        return [self.ego, self.driver]

    def tasks(self) -> list[AgentTask]:
        """The ego's task and the oncoming car's: its lane and the speed it drives when free,
        its desired speed within its lanes' limit (what IDM targets; a desired speed above
        the limit is refused when the options are made)."""
        rm = self.road_map
        i = self.lane_i
        ids = (f"oncoming{i}_approach", f"oncoming{i}_through")
        limit = min(rm.lane(j).speed_limit for j in ids)
        other = rm.task(
            ids,
            n_points=self.options.n_path,
            radius=self.options.radius,
            speed=min(self.character.desired_speed, limit),
        )
        return [self.ego_task, other]

    def info(self) -> dict:
        """The oncoming driver's hidden state (for metrics and tests, never for planners)."""
        return dict(
            decision=self.decision,
            committed=self.committed,
            character=self.character,
            lane=self.lane_i,
            geometry=self.geometry.name,
        )

    # ------------------------------------------------------------------ internals
    def _succeeded(self, position: np.ndarray) -> bool:
        """Past the goal along the route, within a lane width of it."""
        s, d = project_to_polyline(position[None], self.ego_route)
        return bool(s[0] >= self._s_goal - 1e-9 and d[0] <= self.geometry.lane_width)

    def _decide(self) -> None:
        """The oncoming driver's go / yield decision (module docstring)."""
        ch, drv, zone = self.character, self.driver, self.conflict
        s_e = self.progress()
        corners = _corners(self.ego.position, self.ego.heading)
        gap = float(project_to_polyline(corners, self.other_route)[1].min()) - WIDTH / 2
        self._ego_seen.append((s_e, float(self.ego.speed), gap))
        lag = int(round(ch.reaction / self.dt))
        s_seen, v_seen, gap_seen = self._ego_seen[max(0, len(self._ego_seen) - 1 - lag)]
        s_o = float(project_to_polyline(drv.position[None], self.other_route)[0][0])
        v_o = float(drv.speed)
        if not self.committed:
            dist = self._s_wait - s_o
            late = self.decision == "go" and v_o * v_o / (2 * BRAKE) > dist
            self.committed = dist <= 0.0 or late
        # an ego that stands still, its body at least WAIT_GAP from our side, before it
        # crossed our lane, is waiting for us (after ``patience`` s): we go
        waiting = v_seen <= 0.1 and gap_seen >= WAIT_GAP and s_seen < zone.a[1]
        self._still = self._still + self.dt if waiting else 0.0
        if not self.committed:
            t_e_reach, t_e_clear = zone_times(s_seen, v_seen, zone.a, LENGTH / 2)
            if self._still >= self.options.patience - 1e-9:
                t_e_reach = math.inf
            t_o_clear = time_to_cover(
                zone.b[1] + LENGTH / 2 - s_o, v_o, drv.COMFORT_ACC_MAX, ch.desired_speed
            )
            m = ch.margin(*self.options.margin)
            self.decision = "go" if gap_decision(t_o_clear, t_e_reach, t_e_clear, m) else "yield"
            if self.forced_decision in ("go", "yield"):
                self.decision = self.forced_decision
        drv.stop_obstacle = None if self.decision == "go" else self._stop_obstacle
        self.decisions.append(self.decision)


def _corners(position: np.ndarray, heading: float) -> np.ndarray:
    """The four corners ``(4, 2)`` of a LENGTH x WIDTH vehicle."""
    c, s = math.cos(heading), math.sin(heading)
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [LENGTH / 2, WIDTH / 2]
    return position + local @ np.array([[c, s], [-s, c]])


def _wait_point(route: np.ndarray, ego_route: np.ndarray, zone: ConflictZone, stop: float) -> float:
    """Arc length of the oncoming car's wait point on ``route``: half a length (and 0.5 m)
    before the conflict zone or the stop line, whichever comes first, and set back further
    if needed so that its centre is :data:`WAIT_CLEARANCE` from the ego's route."""
    s_max = min(stop, zone.b[0] - LENGTH / 2 - 0.5)
    s = np.arange(s_max, 0.0, -0.05)
    pts = np.stack([_pose(route, x)[0] for x in s])
    d = project_to_polyline(pts, ego_route)[1]
    ok = np.flatnonzero(d >= WAIT_CLEARANCE)
    return float(s[ok[0]]) if ok.size else 0.0


def _pose(route: np.ndarray, s: float, extend: bool = False) -> tuple[np.ndarray, float]:
    """Point and heading of a polyline at arc length ``s`` (``extend``: beyond its end along
    the last segment)."""
    seg = np.diff(route, axis=0)
    L = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(L)])
    k = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
    if not extend:
        s = min(s, cum[-1])
    p = route[k] + (s - cum[k]) / L[k] * seg[k]
    return p.astype(float), float(math.atan2(seg[k, 1], seg[k, 0]))
