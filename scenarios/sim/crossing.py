"""The robot-pedestrian crossing of RPI as a closed-loop world: our own small simulation.

highway-env simulates vehicles on lanes and has no pedestrians, and no other maintained
simulator we could depend on covers a robot and a free-walking pedestrian on the same
numerical footing, so this world is ~150 lines of numpy. The geometry is RPI's
(:mod:`scenarios.rpi`, :class:`~scenarios.rpi.RPIRecipe` defaults, drawn by
:meth:`~scenarios.rpi.RPIScenario.sample_config`): the robot (agent 0) goes from
``robot_start`` to ``robot_goal``; the pedestrian (agent 1) starts on the 3 m circle and
walks across it to a jittered opposite goal; radius 0.25 m each.

Robot: a unicycle ``(x, y, v, theta)``, command ``(a, omega)``, one explicit Euler step of
``dt`` (:class:`epo_casadi.dynamics.Unicycle`, ``VehicleModel("unicycle", no_reverse=True)``:
it stops rather than reverse, as the pedestrian, stepped by the same model, does).

Pedestrian (hand-made, never the planner under test): a unicycle with a seeded character
(:class:`~scenarios.sim.common.Character`: aggressiveness ``g``, desired walking speed,
reaction time). It steers towards its goal (turn rate ``2 x`` heading error, at most
2 rad/s), sidesteps a robot right ahead of it (head-on encounters, where no wait point
exists) and tracks a target speed with a 0.25 s time constant (acceleration in [-2, 1]
m/s^2). The target is its desired speed when it goes, slowing to stop 0.1 m from its goal, and when it yields
the speed that stops it at its wait point (``0.3`` m before the conflict zone, planned
with 1 m/s^2; once inside the zone it walks on). The
go / yield rule is the drivers' (:func:`~scenarios.sim.common.gap_decision` on the robot
seen ``reaction`` s ago, margin from ``margin[0]`` at ``g = 0`` to ``margin[1]`` at
``g = 1``); the conflict zone is where the two straight start-goal lines come closer than
``2 r + 0.25`` m (none: it always goes). A robot standing still inside that zone (e.g.
at its start, when the pedestrian's goal lies next to it) is waited for.

Outcome: ``collision`` when the circles overlap (``distance < r_0 + r_1``), ``success``
when the robot is within ``goal_tolerance`` of its goal, ``off_road`` when it is farther
than ``circle + off_road_margin`` from the centre, ``timeout`` after ``max_steps``.
Observation: the robot exactly, the pedestrian's position with Gaussian noise and dropouts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from epo_casadi.errors import SpecError, check_number
from solvers.control.types import AgentTask, Observation, WorldBase
from solvers.control.vehicle import VehicleModel

from ..maps import Lane, RoadMap, project_to_polyline
from ..rpi import RPIRecipe, RPIScenario
from .common import (
    Character,
    Latch,
    Sensor,
    build_options,
    check_command,
    check_episode_sizes,
    check_range,
    check_sensor,
    ego_interval,
    gap_decision,
    seeds,
    time_to_cover,
    zone_times,
)

__all__ = ["CrossingOptions", "CrossingWorld"]

_RPI = RPIRecipe(ground_truth="potential")  # the scene of the potential recipe (moving starts)
PED_TURN = 2.0  # rad/s, largest pedestrian turn rate
PED_ACC = (-2.0, 1.0)  # m/s^2, pedestrian acceleration range
PED_TAU = 0.25  # s, speed time constant
AT_GOAL = 0.1  # m, the pedestrian stops this close to its goal
WAIT_GAP = 0.3  # m, a yielding pedestrian stops this far before the conflict zone
AVOID = 3.0  # m, a robot closer than this ahead makes the pedestrian sidestep
YIELD_DEC = 1.0  # m/s^2, the deceleration its target speed profile plans when it yields


@dataclass(frozen=True)
class CrossingOptions:
    """Options of :class:`CrossingWorld` (frozen; unknown names are errors)."""

    dt: float = _RPI.dt  #: step (s)
    max_steps: int = 120  #: timeout (steps), at most 100,000
    noise_std: float = 0.05  #: std of the pedestrian's position noise (m)
    dropout_prob: float = 0.0  #: fraction of the pedestrian's positions lost (on average)
    dropout_burst: int = 3  #: length of a dropout (steps), at most 100,000
    robot_speed: float = _RPI.speed0[0]  #: robot's initial and desired speed (m/s)
    aggressiveness: tuple[float, float] = (0.0, 1.0)  #: range of the pedestrian character
    desired_speed: tuple[float, float] = (0.8, 1.4)  #: range of its walking speed (m/s)
    reaction: tuple[float, float] = (0.1, 0.5)  #: range of its reaction time (s)
    character: Character | None = None  #: a fixed pedestrian character
    margin: tuple[float, float] = (1.0, -0.5)  #: accepted time margin (s) at g = 0 and 1
    radius: float = _RPI.radius  #: radius of both agents (m)
    goal_tolerance: float = 0.3  #: success: robot this close to its goal (m)
    off_road_margin: float = 2.0  #: off_road: robot this far outside the 3 m circle (m)
    n_path: int = 40  #: points of each AgentTask path (2 to 10,000)

    def __post_init__(self):
        p = "crossing"
        check_number(f"{p}.dt", self.dt, lo=0.01, hi=1.0)
        check_episode_sizes(self, p)
        burst = check_sensor(p, self.noise_std, self.dropout_prob, self.dropout_burst)
        object.__setattr__(self, "dropout_burst", burst)
        check_number(f"{p}.robot_speed", self.robot_speed, lo=0.0, hi=_RPI.vmax[0])
        for name, lo, hi in (
            ("aggressiveness", 0.0, 1.0),
            ("desired_speed", 0.1, _RPI.vmax[1]),
            ("reaction", 0.0, 5.0),
            ("margin", -10.0, 10.0),
        ):
            val = check_range(f"{p}.{name}", getattr(self, name), lo, hi, name != "margin")
            object.__setattr__(self, name, val)
        if self.character is not None and not isinstance(self.character, Character):
            raise SpecError(f"{p}.character", f"expected a Character, got {self.character!r}")
        check_number(f"{p}.radius", self.radius, lo=0.0, lo_open=True)
        check_number(f"{p}.goal_tolerance", self.goal_tolerance, lo=0.0, lo_open=True)
        check_number(f"{p}.off_road_margin", self.off_road_margin, lo=0.0)


class CrossingWorld(WorldBase):
    """The RPI crossing as a :class:`solvers.control.types.World` (module docstring); it
    plays the scenes of the ``rpi`` datasets."""

    name = "crossing"
    dataset_scenario = "rpi"

    def __init__(self, options: CrossingOptions | None = None, **kw):
        if options is not None and kw:
            raise SpecError("crossing", "give either options or keyword options, not both")
        self.options = (
            options if options is not None else build_options(CrossingOptions, "crossing", kw)
        )
        o = self.options
        self.dt = float(o.dt)
        self.max_steps = int(o.max_steps)
        self.vehicle = VehicleModel(
            kind="unicycle", a_min=-_RPI.amax, a_max=_RPI.amax, steer_max=_RPI.wmax, no_reverse=True
        )
        self.n_agents = 2
        self.radii = np.full(2, float(o.radius))
        self._rpi = RPIScenario(_RPI)
        self.sensor = Sensor(1, o.noise_std, o.dropout_prob, o.dropout_burst)
        self.road_map: RoadMap | None = None  # the episode's two straight lanes (reset)
        self.ego_task: AgentTask | None = None  # the robot's task (reset)
        self.conflict = None  # where the two lanes meet (reset; None: they never do)
        self._ready = False

    def reset(self, seed: int) -> Observation:
        o = self.options
        g_scene, g_char, g_sense = seeds(seed, 3)
        cfg = self._rpi.sample_config(0, g_scene)
        self.x = np.array(cfg.x0, dtype=float)
        self.x[0, 2] = o.robot_speed
        self.goals = np.array(cfg.goals, dtype=float)
        self.character = o.character or Character.draw(
            g_char, o.aggressiveness, o.desired_speed, o.reaction
        )
        self.x[1, 2] = self.character.desired_speed
        lanes = [
            Lane("robot", np.stack([self.x[0, :2], self.goals[0]]), 1.0, max(o.robot_speed, 0.1)),
            Lane(
                "pedestrian",
                np.stack([self.x[1, :2], self.goals[1]]),
                1.0,
                self.character.desired_speed,
            ),
        ]
        self.road_map = RoadMap(tuple(lanes))
        self.routes = [ln.centre for ln in lanes]
        self.conflict = self.road_map.conflict_zone(
            "robot", "pedestrian", clearance=2 * o.radius + 0.25, step=0.05
        )
        self.ego_task = self.road_map.task(
            ("robot",), n_points=o.n_path, radius=o.radius, speed=o.robot_speed
        )
        self.sensor.reset(g_sense)
        self.t, self.k = 0.0, 0
        self.latch = Latch()
        self.decision = "go"
        self.decisions: list[str] = []
        self._seen: list[tuple[float, float]] = []
        self._ready = True
        self._decide()
        return self._observe()

    def step(self, command: np.ndarray) -> Observation:
        if not self._ready:
            raise SpecError("crossing", "call reset(seed) before step(command)")
        u = check_command(command, "a, omega")
        ped_u = self._pedestrian_command()
        self.x[0] = self.vehicle.step(self.x[0], u, self.dt)
        self.x[1] = self.vehicle.step(self.x[1], ped_u, self.dt)
        self.k += 1
        self.t = self.k * self.dt
        self._check()
        self._decide()
        return self._observe()

    def truth(self) -> np.ndarray:
        return self.x.copy()

    def tasks(self) -> list[AgentTask]:
        o = self.options
        ped = self.road_map.task(
            ("pedestrian",), n_points=o.n_path, radius=o.radius, speed=self.character.desired_speed
        )
        return [self.ego_task, ped]

    def outcome(self) -> str:
        return self.latch.value

    def conflict_zone(self) -> tuple[float, float] | None:
        """The robot's arc-length interval of :attr:`conflict` (None without one)."""
        return ego_interval(self.conflict)

    def info(self) -> dict:
        """The pedestrian's hidden state (metrics and tests, never planners)."""
        return dict(decision=self.decision, character=self.character)

    def set_state(self, agent: int, state: np.ndarray) -> None:
        """Place agent ``agent`` at ``(x, y, v, theta)`` (tests, hand-made situations)."""
        check_number("agent", agent, lo=0, hi=1, integer=True)
        self.x[agent] = np.asarray(state, dtype=float).reshape(4)

    # ------------------------------------------------------------------ internals
    def _observe(self) -> Observation:
        return Observation(
            t=self.t, ego=self.x[0].copy(), others=self.sensor.measure(self.x[1:, :2])
        )

    def _check(self) -> None:
        o = self.options
        if np.linalg.norm(self.x[0, :2] - self.x[1, :2]) < self.radii.sum():
            self.latch.set("collision")
        if np.linalg.norm(self.x[0, :2]) > _RPI.circle + o.off_road_margin:
            self.latch.set("off_road")
        if np.linalg.norm(self.x[0, :2] - self.goals[0]) <= o.goal_tolerance:
            self.latch.set("success")
        if self.k >= self.max_steps:
            self.latch.set("timeout")

    def _s(self, agent: int) -> float:
        return float(project_to_polyline(self.x[agent, None, :2], self.routes[agent])[0][0])

    def _decide(self) -> None:
        ch, zone = self.character, self.conflict
        self._seen.append((self._s(0), float(self.x[0, 2]), self.x[0, :2].copy()))
        lag = int(round(ch.reaction / self.dt))
        self._robot_seen = self._seen[max(0, len(self._seen) - 1 - lag)][2]
        if zone is None:
            self.decision = "go"
        else:
            s_r, v_r, _ = self._seen[max(0, len(self._seen) - 1 - lag)]
            s_p, v_p = self._s(1), float(self.x[1, 2])
            r = self.options.radius
            t_r_reach, t_r_clear = zone_times(s_r, v_r, zone.a, r)
            dist = zone.b[1] + r - s_p
            v_eff = max(v_p, 0.0)
            # own clear time: accelerating at PED_ACC[1] up to the desired speed
            t_p_clear = time_to_cover(dist, v_eff, PED_ACC[1], ch.desired_speed)
            passed = s_p >= zone.b[0]  # already in the zone: it walks on
            go = passed or gap_decision(
                t_p_clear, t_r_reach, t_r_clear, ch.margin(*self.options.margin)
            )
            self.decision = "go" if go else "yield"
        self.decisions.append(self.decision)

    def _pedestrian_command(self) -> np.ndarray:
        ch = self.character
        x = self.x[1]
        d = self.goals[1] - x[:2]
        dist_goal = float(np.linalg.norm(d))
        aim = math.atan2(d[1], d[0])
        # sidestep: a robot (as seen ``reaction`` s ago) less than AVOID m ahead and less than
        # 1 m to the side turns the walking direction away from it (to the right when dead
        # ahead), by up to 0.8 rad for a cautious and 0.4 rad for a bold pedestrian
        rel = self._robot_seen - x[:2]
        fwd = rel @ np.array([math.cos(x[3]), math.sin(x[3])])
        lat = rel @ np.array([-math.sin(x[3]), math.cos(x[3])])
        if 0.0 < fwd < AVOID and abs(lat) < 1.0:
            aim -= (0.8 - 0.4 * ch.aggressiveness) * (1.0 if lat >= 0.0 else -1.0)
        err = (aim - x[3] + math.pi) % (2 * math.pi) - math.pi
        at_goal = dist_goal < AT_GOAL
        omega = 0.0 if at_goal else float(np.clip(2.0 * err, -PED_TURN, PED_TURN))
        # slow down to stop at the goal, or at the wait point when yielding (YIELD_DEC)
        v_target = min(ch.desired_speed, math.sqrt(2.0 * YIELD_DEC * max(dist_goal - AT_GOAL, 0.0)))
        if self.decision == "yield":
            gap = self.conflict.b[0] - self.options.radius - WAIT_GAP - self._s(1)
            v_target = min(v_target, math.sqrt(2.0 * YIELD_DEC * max(gap, 0.0)))
        a = float(np.clip((v_target - x[2]) / PED_TAU, *PED_ACC))
        return np.array([a, omega])
