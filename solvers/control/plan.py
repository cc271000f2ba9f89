"""Planners without a network: the game oracle and the constant-velocity planner.

Both implement :class:`solvers.control.types.Planner` and plan on the same energy, the
paper's driving features (App. F.3, CARLA) for every agent on the unicycle of
:mod:`epo_casadi.dynamics`::

    path               distance to the agent's lane centre line (a polyline parameter)
    reference_velocity speed - the lane's speed (a vref parameter)
    velocity, acceleration, jerk, turn_rate, turn_acceleration   (running costs)
    velocity_bound     max(0, -v): no reversing (a soft term; the hard rule is below)
    collision          max(0, r_i + r_j + margin - distance), every pair, every step

:class:`GameOracle`
    The game solver itself in receding horizon with every agent's *true* task
    (``world.tasks()``: path and speed): the N-agent potential game is minimized by
    Levenberg-Marquardt (:func:`solvers.solve_lm`) each period, warm-started from the
    previous solution shifted by one step. The ego's initial state is exact, the others'
    come from the :class:`~solvers.control.types.Estimate`. Which equilibrium it follows is
    the *commit logic* below.

:class:`ConstantVelocityPlanner`
    What a planner without a game does: the others are predicted at constant velocity from
    the estimate (a unicycle with zero controls is exactly that) and the ego minimizes the
    same energy over its own controls only, the others' controls fixed at zero. In a
    potential game this is the ego's best response: the terms that change with the ego's
    controls are those of its own cost ``C_0``. The reduced problem (the game's energy
    with the others' controls as parameters) is built once in CasADi and solved by IPOPT,
    with the ego's speeds ``v_k = v_0 + dt (a_0 + ... + a_{k-1}) >= 0`` as hard (linear)
    constraints.

No reversing (hard). Every plan and every prediction a planner returns has ``v >= 0`` at
every step, exactly: the controls of each agent are rolled out with the acceleration that
would take the speed below zero raised to the one that stops it within the step
(:func:`stop_not_reverse`, the rule of ``VehicleModel(no_reverse=True)``); the CV planner's
IPOPT solution satisfies it already (its constraint), the oracle's LM solution (LM has no
constraints; the soft ``velocity_bound`` keeps it from relying on reversing) is projected
so. A plan's ``controls`` are the projected ones, so its states remain their rollout.

Footprints. A world with a ``footprint`` ``(length, width)`` (the cars of the highway-env
worlds, :func:`~solvers.control.types.world_member`) gives every agent two circles of radius
``width / 2`` centred ``+-(length - width) / 2`` along its heading: the stadium inscribed in
the car's rectangle, whose corners stick out by ``(sqrt 2 - 1) width / 2`` (0.41 m for a
2 m wide car), less than the default ``collision_margin`` of 1 m, so a plan that keeps the
margin between the circles keeps the rectangles apart. The collision term is then
:class:`FootprintCollision` (the four circle pairs of two agents, every step). A world
without one keeps a circle of its ``radii`` per agent (the built-in ``collision`` term).
Two cars nose to nose touch at ``length`` between centres, side by side in lanes 3.5 m
apart they are ``3.5 - width`` apart: one circle that covers the car (radius 2.7 m for
5 m x 2 m) makes passing cars look like colliding ones, one of 1.75 m lets a plan drive
into a waiting car's nose. Every radius is a parameter of the game (``radius.<agent>``),
so one game serves every period.

Tracks that have not converged (``Estimate.converged`` False): the agent is predicted at
constant velocity (a straight path along its estimated heading at its estimated speed as
its task, and, in the oracle's game, its acceleration and turn-rate weights multiplied by
``hold_weight`` so that it keeps that velocity rather than yield), its radius grown
by ``unconverged_inflation``, and the oracle neither forms nor changes a commitment while
one is unconverged: it follows the lowest-energy equilibrium that lets the others go first
where one exists (``plan.info["converged"]``).

Commit logic (oracle, in a world with a conflict zone, ``world.conflict_zone()``). Each
period's equilibria (one per start: the warm start, "ego first", "others first") are
classified by :func:`passing_order` (who enters the ego's stretch ``[s_in, s_out]`` of the
zone first in the predicted joint future: ``"ego"``, ``"other"`` or ``"none"``, no one
within the horizon). The oracle commits to an order and keeps it (the lowest-energy
equilibrium of that order, or of ``"none"``) unless an equilibrium of the other order is
lower by a margin, with hysteresis that leans to the safe side: from "other first" to "ego
first" only for one lower by ``switch_margin (1 + |E|)`` (0.3: the energies of the two
orders jump by 20-40 % from one period to the next with the estimate's noise, far more than
a 2 % margin) and at least ``commit_time`` s after the last switch; from "ego first" to
"other first" (yielding) for one lower by ``yield_margin (1 + |E|)`` (0.02), at once: a
driver who turns out not to yield is given way while the ego can still stop. The ego's
*stop line* (:meth:`GameOracle.stop_line`) keeps its front ``stop_gap`` m before ``s_in``
(where the centre lines come within 2.5 m), so a waiting ego's nose stays out of the other
lane. A plan that lets another agent go first stops there: where its ego would pass the
line, its accelerations are capped by the constant deceleration that stops it at the line,
``-v^2 / (2 d)`` (``plan.info["stop_line"]``), so a yielding ego does not creep into the
zone. Once the ego can no longer stop before the line with ``stop_deceleration``, or is past
it, and until its rear has left the zone, it is committed to going first: only equilibria
in which it goes first are taken (the lowest-energy one; if no start gives one, its last
plan shifted by a step, else the plan that progresses furthest with its braking removed,
``plan.info["no_braking"]``), so it never re-yields inside the zone (``plan.info``:
``phase`` free / committed / clear, ``order``, ``committed``, ``switched``). Without a
conflict zone the warm-started equilibrium is kept unless another is lower by
``yield_margin (1 + |E|)``.

Yielding drivers. The oracle knows each agent's task, but not what the agent does about the
ego: an agent whose converged estimate is slower than ``stopped_speed`` is predicted by its
observed state, not by its lane's desired speed (which would predict a car waiting for the
ego to drive through it): its own estimated speed is its speed reference and its
acceleration and turn-rate weights are multiplied by ``hold_weight``, so that in the game it
stays stopped (or goes as slowly as it goes) rather than drive off to make room for the ego;
once it moves faster, its desired speed is its reference again. An agent braking to yield
(below half its desired speed, its estimated speed fell by more than 0.5 m/s over the last
0.5 s of the estimate's history, measured at both ends; held until it speeds up by as much
or reaches half its desired speed, so the noise of the speed estimate does not toggle it)
gets 0 as speed reference, with the ordinary weights: it is predicted to stop, not to speed
up again to its desired speed.

The game is built once per structure (number of agents, footprint, ``dt``, options) and
cached: a new episode or a new step only changes parameters (initial states, the path
windows, the speeds, the radii, the weights). Paths enter as a window of ``path_points``
vertices resampled along each agent's lane from just behind it to beyond what it can reach
within the horizon.

Failures (an observation or estimate that is missing or of the wrong kind or shape, a
non-finite input, a solver that fails or returns non-finite values, an exception inside a
solve, :meth:`plan` before :meth:`reset`) give ``Plan(ok=False, message=...)`` (NaN states of
the horizon's length, ``t0`` the observation's time or NaN when it has none); :meth:`plan`
never raises. Option errors are :class:`~epo_casadi.errors.SpecError` when the options are
made, sizes bounded (:data:`MAX_HORIZON` and the limits in :class:`PlannerOptions`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields
from typing import ClassVar

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size, short_repr
from epo_casadi.features import PairFeature, smooth_distance
from epo_casadi.game import AgentSpec, GameSpec, PotentialGame

from ..lm import LMOptions, solve_lm
from .types import AgentTask, Estimate, Observation, Plan, World, world_member

__all__ = [
    "PlannerOptions",
    "GameOracle",
    "ConstantVelocityPlanner",
    "FootprintCollision",
    "build_game",
    "footprint_circles",
    "passing_order",
    "path_window",
    "stop_not_reverse",
    "failed_plan",
    "MAX_HORIZON",
]

#: most planning steps (a game of N agents has 2 N K unknowns and is rebuilt per K)
MAX_HORIZON = 1000
#: most lane-window vertices per agent (parameters of the game)
MAX_PATH_POINTS = 1000
#: most LM steps per period / of a cold start, and IPOPT iterations per plan
MAX_STEPS = 100_000

#: (feature type, option holding its weight), the order of the residual blocks
_OWN = (
    ("path", "w_path"),
    ("reference_velocity", "w_vref"),
    ("velocity", "w_velocity"),
    ("acceleration", "w_acceleration"),
    ("jerk", "w_jerk"),
    ("turn_rate", "w_turn_rate"),
    ("turn_acceleration", "w_turn_acceleration"),
    ("velocity_bound", "w_reverse"),
)
#: the own terms whose weights keep an unconverged agent at constant velocity (oracle)
_CV_TERMS = ("acceleration", "turn_rate")


@dataclass(frozen=True)
class PlannerOptions:
    """Horizon, energy weights and solver settings of the game oracle and the CV planner.

    The defaults give a 3 s horizon at the world's ``dt`` and a plan within a period
    (``epo simulate`` measures it: the real-time factor in the summary).
    """

    horizon: int = 30  #: planning steps K (of the world's dt), 2 to MAX_HORIZON (1000)
    path_points: int = 10  #: vertices of each agent's lane window (a fixed parameter size),
    #: 2 to 1000
    path_behind: float = 3.0  #: metres of lane kept behind an agent's projection
    path_ahead: float = 10.0  #: metres of lane beyond max(v, speed) * horizon
    w_path: float = 5.0  #: weight of the distance to the lane centre line
    w_vref: float = 0.6  #: weight of speed - lane speed
    w_velocity: float = 0.05  #: weight of the speed itself
    w_acceleration: float = 0.5  #: weight of the acceleration
    w_jerk: float = 0.05  #: weight of the jerk
    w_turn_rate: float = 1.0  #: weight of the turn rate
    w_turn_acceleration: float = 0.1  #: weight of the turn acceleration
    w_reverse: float = 5.0  #: weight of max(0, -v) (soft; the plans never reverse anyway)
    w_collision: float = 50.0  #: weight of the collision penetration
    collision_margin: float = 1.0  #: metres added to r_i + r_j in the collision feature
    steps: int = 10  #: LM steps per period (warm-started), at most 100,000
    start_acceleration: float = 2.0  #: oracle: |a| of the "ego first" / "others first" starts
    switch_margin: float = 0.3  #: oracle: switch from letting another agent go first to going
    #: first only for an equilibrium this fraction of (1 + |E|) lower
    yield_margin: float = 0.02  #: oracle: the same for switching to letting it go first (the
    #: safe direction), and to leave the warm-started equilibrium without a conflict zone
    commit_time: float = 1.0  #: oracle: least time (s) after a switch before going first
    stop_gap: float = 0.5  #: oracle: m from the ego's front at its stop line to the zone
    stop_deceleration: float = 4.0  #: oracle: m/s^2; the ego is committed to going first
    #: once it cannot stop before its stop line with it
    stopped_speed: float = 1.0  #: oracle: m/s; a converged agent slower than this gets its
    #: estimated speed as speed reference (it waits), not its lane's desired speed
    unconverged_inflation: float = 1.0  #: m added to the radius of an unconverged track
    hold_weight: float = 100.0  #: oracle: factor on the acceleration and turn-rate weights
    #: of an agent predicted to keep its velocity (an unconverged track, a stopped agent)
    temperature: float = 1.0  #: oracle: mode weights exp(-(E - E_min) / temperature)
    first_steps: int = 100  #: LM steps of a cold start (first period, after a failure), at
    #: most 100,000
    gtol: float = 1e-6  #: LM gradient tolerance (stops early once met)
    backend: str = "fused"  #: LM Gauss-Newton backend: "fused" (one problem at a time is its
    #: strength; equal to "structured" to 1e-12), "structured" or "dense"
    compiled: bool | None = None  #: the backend as generated C; None: when a C compiler is
    #: found (solvers.codegen.find_compiler), else interpreted
    ipopt_max_iter: int = 100  #: IPOPT iterations of the CV planner's best response (at most
    #: 100,000)
    ipopt_tol: float = 1e-8  #: IPOPT tolerance of the CV planner

    def __post_init__(self):
        sizes = (
            ("horizon", MAX_HORIZON, "game size", 2),
            ("path_points", MAX_PATH_POINTS, "game size", 2),
            ("steps", MAX_STEPS, "planning time", 1),
            ("first_steps", MAX_STEPS, "planning time", 1),
            ("ipopt_max_iter", MAX_STEPS, "planning time", 1),
        )
        for name, limit, what, lo in sizes:
            v = check_size(f"planner.{name}", getattr(self, name), limit, what, lo=lo)
            object.__setattr__(self, name, v)
        for f in fields(self):
            if f.name.startswith("w_") or f.name in ("path_behind", "path_ahead"):
                check_number(f"planner.{f.name}", getattr(self, f.name), lo=0)
        for name in (
            "collision_margin",
            "gtol",
            "start_acceleration",
            "switch_margin",
            "yield_margin",
            "commit_time",
            "stop_gap",
            "stopped_speed",
            "unconverged_inflation",
        ):
            check_number(f"planner.{name}", getattr(self, name), lo=0)
        check_number("planner.stop_deceleration", self.stop_deceleration, lo=0, lo_open=True)
        check_number("planner.hold_weight", self.hold_weight, lo=1)
        check_number("planner.temperature", self.temperature, lo=0, lo_open=True)
        check_number("planner.ipopt_tol", self.ipopt_tol, lo=0, lo_open=True)
        if self.backend not in ("fused", "structured", "dense"):
            raise SpecError(
                "planner.backend",
                f"expected 'fused', 'structured' or 'dense', got {self.backend!r}",
            )
        if self.compiled is not None and not isinstance(self.compiled, bool):
            raise SpecError(
                "planner.compiled", f"expected true, false or null, got {self.compiled!r}"
            )

    @classmethod
    def from_dict(cls, values: dict | None) -> PlannerOptions:
        """Options from a mapping; an unknown key is an error naming the allowed ones."""
        from ..lm import check_options

        return check_options(cls, values, "planner")

    def lm(self, steps: int) -> LMOptions:
        return LMOptions(
            steps=steps,
            gtol=self.gtol,
            ftol=0.0,
            backend=self.backend,
            compiled=_have_compiler() if self.compiled is None else self.compiled,
            threads=1,
        )


def _have_compiler() -> bool:
    from ..codegen import CompilerError, find_compiler

    try:
        find_compiler()
    except CompilerError:
        return False
    return True


def failed_plan(t0: float, dt: float, horizon: int, message: str, **info) -> Plan:
    """A plan that says it failed: NaN states and controls, ``ok=False``."""
    nan = np.full((horizon, 4), np.nan)
    return Plan(t0, dt, nan, np.full((horizon, 2), np.nan), ok=False, message=message, info=info)


# --------------------------------------------------------------------------------------
# geometry shared by the planners and their checks
# --------------------------------------------------------------------------------------
def stop_not_reverse(x0: np.ndarray, U: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The unicycle rollout of controls ``U`` ``(K, 2)`` from ``x0`` ``(4,)`` (explicit
    Euler, as :class:`epo_casadi.dynamics.Unicycle`) in which no speed goes below zero:
    where ``v_k + a_k dt < 0`` the acceleration becomes ``-v_k / dt`` and ``v_{k+1} = 0``
    exactly (a negative ``v_0`` is brought to zero in the first step). Returns the states
    ``(K, 4)`` after each step and the controls that produce them."""
    U = np.array(U, dtype=np.float64, copy=True)
    X = np.empty((len(U), 4))
    x, y, v, th = (float(c) for c in x0)
    for k in range(len(U)):  # sequential by nature: each clamp depends on the speed so far
        a, w = U[k]
        v_next = v + a * dt
        if v_next < 0.0:
            U[k, 0], v_next = -v / dt, 0.0
        x, y, th = x + v * math.cos(th) * dt, y + v * math.sin(th) * dt, th + w * dt
        v = v_next
        X[k] = x, y, v, th
    return X, U


def footprint_circles(footprint) -> tuple[float, float]:
    """``(offset, radius)`` of the planners' two circles of a ``(length, width)`` car:
    centres ``+-(length - width) / 2`` along the heading, radius ``width / 2`` (the stadium
    inscribed in its rectangle, module docstring)."""
    try:
        length, width = (float(v) for v in footprint)
    except (TypeError, ValueError):
        raise SpecError(
            "world.footprint", f"expected (length, width) in m, got {short_repr(footprint)}"
        ) from None
    check_number("world.footprint.width", width, lo=0, lo_open=True)
    check_number("world.footprint.length", length, lo=width)
    return 0.5 * (length - width), 0.5 * width


@dataclass(frozen=True)
class FootprintCollision(PairFeature):
    """Collision avoidance of two cars, each two circles at ``+-offset`` along its heading:
    ``max(0, r_i + r_j + margin - dist(c_i, c_j))`` for the four pairs of circles ``c_i``,
    ``c_j`` (front and rear of each), four rows per step ``k = 1..K`` (m).

    ``r_i`` are the agents' radii (the game's ``radius.<agent>`` parameters, the width's
    half), the heading is the state's ``theta`` (unicycle). Symmetric in ``(i, j)``; with
    ``offset = 0`` the four rows are the built-in ``collision`` row four times. Fields:
    ``label``, ``weight``, ``pairs`` (:class:`~epo_casadi.features.PairFeature`),
    ``margin`` (m, >= 0) and ``offset`` (m, >= 0).
    """

    kind: ClassVar[str] = "footprint_collision"
    margin: float = 0.0
    offset: float = 0.0

    def __post_init__(self):
        check_number("footprint_collision.margin", self.margin, lo=0)
        check_number("footprint_collision.offset", self.offset, lo=0)
        check_number("footprint_collision.weight", self.weight, lo=0)

    def steps(self, K: int) -> list[int]:
        return list(range(1, K + 1))

    def residual(self, a, b):
        reach = a.radius + b.radius + float(self.margin)
        d = float(self.offset)
        rows = []
        for k in self.steps(a.K):
            ca_ = _circles(a.X[:, k], d)
            cb = _circles(b.X[:, k], d)
            rows += [ca.fmax(0, reach - smooth_distance(p, q)) for p in ca_ for q in cb]
        return ca.vertcat(*rows)


def _circles(x, d: float) -> list:
    """The centres of a unicycle state's two circles (symbolic)."""
    u = ca.vertcat(ca.cos(x[3]), ca.sin(x[3]))
    return [x[0:2] + d * u, x[0:2] - d * u]


#: s of estimated history over which a speed drop says an agent is braking, and that drop
#: (m/s): 1 m/s^2 sustained for half a second
_SLOWING_WINDOW, _SLOWING_DROP = 0.5, 0.5


def _speed_change(est, n: int, dt: float) -> np.ndarray:
    """``(n,)`` each agent's estimated speed now minus ``_SLOWING_WINDOW`` s ago from
    ``est.history`` (0 where either row is not backed by a measurement, or without such a
    history)."""
    out = np.zeros(n)
    lag = int(round(_SLOWING_WINDOW / dt))
    try:
        h = np.asarray(getattr(est, "history", None), dtype=float)
        valid = np.asarray(getattr(est, "valid", None), dtype=bool)
    except (TypeError, ValueError):
        return out
    if h.ndim != 3 or h.shape[:1] != (n,) or h.shape[1] <= lag or valid.shape != h.shape[:2]:
        return out
    with np.errstate(invalid="ignore"):
        change = h[:, -1, 2] - h[:, -1 - lag, 2]
    ok = valid[:, -1] & valid[:, -1 - lag] & np.isfinite(change)
    return np.where(ok, change, 0.0)


def _project(points: np.ndarray, line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length along ``line`` ``(P, 2)`` of the closest point and the distance, per point
    of ``points`` ``(Q, 2)``."""
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    a, ab = line[:-1], np.diff(line, axis=0)
    L2 = np.maximum(np.einsum("sj,sj->s", ab, ab), 1e-18)
    t = np.clip(np.einsum("qsj,sj->qs", pts[:, None] - a[None], ab) / L2, 0.0, 1.0)
    d = np.linalg.norm(pts[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)
    k = np.argmin(d, axis=1)
    rows = np.arange(len(pts))
    cum = np.concatenate([[0.0], np.cumsum(np.sqrt(L2))])
    return cum[k] + t[rows, k] * np.sqrt(L2[k]), d[rows, k]


def _resample(line: np.ndarray, s: np.ndarray) -> np.ndarray:
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    return np.stack([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])], axis=-1)


def passing_order(
    ego: np.ndarray, other: np.ndarray, path: np.ndarray, zone: tuple[float, float], reach: float
) -> str:
    """Who enters the ego's stretch ``[s_in, s_out]`` of ``path`` first in a joint future:
    ``ego`` / ``other`` ``(K+1, >=2)`` positions (the current state first). The ego *enters*
    at its first position whose arc length along ``path`` is at least ``s_in``; the other
    agent *occupies* the zone at its first position closer than ``reach`` to the stretch.
    ``"ego"`` when the ego enters before the other occupies it (or enters while the other
    never does), ``"other"`` when the other is there first or at the same step (an ego that
    waits beyond the horizon included), ``"none"`` when neither reaches it."""
    s_in, s_out = zone
    s_e = _project(ego[:, :2], path)[0]
    enter = np.flatnonzero(s_e >= s_in)
    stretch = _resample(path, np.linspace(s_in, s_out, max(int((s_out - s_in) / 0.25), 2)))
    occ = np.flatnonzero(_project(other[:, :2], stretch)[1] < reach)
    if occ.size == 0:
        return "ego" if enter.size else "none"
    return "ego" if enter.size and enter[0] < occ[0] else "other"


# --------------------------------------------------------------------------------------
# the game
# --------------------------------------------------------------------------------------
_GAMES: dict[tuple, PotentialGame] = {}
_FAR = 1e3  # metres: where an agent without an estimate is parked


def agent_name(i: int) -> str:
    return "ego" if i == 0 else f"a{i}"


def build_game(radii, dt: float, options: PlannerOptions, footprint=None) -> PotentialGame:
    """The driving game of ``len(radii)`` unicycles (cached per structure in the process).

    Agent ``0`` is ``"ego"``, the others ``"a1"``, ``"a2"``, ...; parameters as in
    :mod:`epo_casadi.game` (``x0.<agent>``, ``vref.<agent>``, ``path.<agent>``,
    ``radius.<agent>``). ``footprint``: ``(length, width)`` of every agent (two circles
    each, :class:`FootprintCollision`; the radii default to half the width), or None (one
    circle of ``radii`` each, the built-in ``collision``).
    """
    radii = tuple(float(r) for r in np.asarray(radii, dtype=float).reshape(-1))
    offset = None
    if footprint is not None:
        offset, r = footprint_circles(footprint)
        radii = (r,) * len(radii)
    key = (radii, float(dt), options, offset)
    game = _GAMES.get(key)
    if game is not None:
        return game
    P = options.path_points
    feats = []
    for kind, w in _OWN:
        f = {"type": kind, "weight": float(getattr(options, w))}
        if kind == "path":
            f["points"] = P
        if kind == "velocity_bound":
            f["lower"], f["upper"] = 0.0, math.inf
        feats.append(f)
    agents = [
        AgentSpec(
            name=agent_name(i), dynamics="unicycle", features=feats, radius=r, radius_param=True
        )
        for i, r in enumerate(radii)
    ]
    margin = float(options.collision_margin)
    if offset is None:
        pair = {"type": "collision", "weight": float(options.w_collision), "margin": margin}
    else:
        pair = FootprintCollision(weight=float(options.w_collision), margin=margin, offset=offset)
    spec = GameSpec(
        agents, pair_features=[pair] if len(radii) > 1 else [], horizon=options.horizon, dt=dt
    )
    game = _GAMES[key] = PotentialGame(spec)
    return game


def path_window(
    path: np.ndarray, point: np.ndarray, behind: float, ahead: float, n: int
) -> np.ndarray:
    """``n`` points equally spaced along ``path`` from ``behind`` metres before the
    projection of ``point`` to ``ahead`` metres after it, ``(n, 2)``.

    Beyond its ends the polyline is extended along its first and last segments, so a
    window near the end of a lane stays straight instead of folding back.
    """
    pts = np.asarray(path, dtype=float).reshape(-1, 2)
    seg = np.diff(pts, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    keep = length > 1e-9
    if not keep.any():
        raise SpecError("task.path", "expected a polyline with two distinct points")
    pts = np.concatenate([pts[:1], pts[1:][keep]])
    seg, length = seg[keep], length[keep]
    cum = np.concatenate([[0.0], np.cumsum(length)])
    q = np.asarray(point, dtype=float)[:2]
    t = np.clip(np.einsum("sc,sc->s", q - pts[:-1], seg) / length**2, 0.0, 1.0)
    d = np.hypot(*(pts[:-1] + t[:, None] * seg - q).T)
    j = int(np.argmin(d))
    s0 = cum[j] + t[j] * length[j]
    s = np.linspace(s0 - behind, s0 + ahead, n)
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    tt = (s - cum[idx]) / length[idx]
    return pts[idx] + tt[:, None] * seg[idx]


def _straight(state: np.ndarray, behind: float, ahead: float, n: int) -> np.ndarray:
    """A straight path through the position along the heading (constant velocity)."""
    s = np.linspace(-behind, ahead, n)
    c, si = math.cos(state[3]), math.sin(state[3])
    return state[:2] + s[:, None] * np.array([c, si])


class _GamePlanner:
    """Shared part of the oracle and the CV planner: game, parameters, plan assembly."""

    name = "game"

    def __init__(self, options: PlannerOptions | dict | None = None):
        self.options = (
            options if isinstance(options, PlannerOptions) else PlannerOptions.from_dict(options)
        )
        self.game: PotentialGame | None = None
        self.dt = 0.1
        self.last_params: np.ndarray | None = None
        self.last_u0: np.ndarray | None = None

    def reset(self, world: World) -> None:
        radii = np.asarray(world.radii, dtype=float).reshape(-1)
        if radii.size != world.n_agents:
            raise SpecError("world.radii", f"expected {world.n_agents} radii, got {radii.size}")
        self.dt = float(world.dt)
        self.footprint = world_member(world, "footprint")
        self.game = build_game(radii, self.dt, self.options, self.footprint)
        self.ego_task: AgentTask = world.ego_task
        self.zone = world_member(world, "conflict_zone")()
        self._u: np.ndarray | None = None  # previous solution (warm start)
        g = self.game
        self._base = g.default_params()
        self._sl = {
            (kind, i): g.params[f"{kind}.{agent_name(i)}"].slice
            for i in range(g.N)
            for kind in ("x0", "vref", "path", "radius")
        }
        self._radius = np.array([self._base[self._sl[("radius", i)]][0] for i in range(g.N)])
        self._world_radii = radii  # the circles the world states (the passing order's reach)
        self._w_cv = {
            i: [g.params[f"w.{agent_name(i)}.{t}"].start for t in _CV_TERMS] for i in range(g.N)
        }
        #: the ego's reach ahead of its centre (half its length, or its radius)
        self._front = 0.5 * float(self.footprint[0]) if self.footprint else self._radius[0]
        self.last_params = self.last_u0 = None
        self._absent = np.zeros(0, dtype=int)
        self._unconverged = np.zeros(0, dtype=int)
        pairs = [
            (b.start, b.name.split(".")[1].split("-"))
            for b in g.params.blocks
            if b.group == "w_pair"
        ]
        self._pair_w = {
            i: np.array([st for st, ab in pairs if agent_name(i) in ab], dtype=int)
            for i in range(1, g.N)
        }

    def _base_params(self) -> np.ndarray:
        p = self._base.copy()
        for i in self._absent:
            p[self._pair_w[int(i)]] = 0.0
        for i in self._unconverged:
            p[self._sl[("radius", int(i))]] = (
                self._radius[int(i)] + self.options.unconverged_inflation
            )
        return p

    def _window(self, path, state, speed):
        o = self.options
        ahead = max(float(state[2]), float(speed), 0.0) * o.horizon * self.dt + o.path_ahead
        return path_window(path, state, o.path_behind, ahead, o.path_points)

    def _cv_path(self, state):
        o = self.options
        ahead = max(float(state[2]), 0.0) * o.horizon * self.dt + o.path_ahead
        return _straight(state, o.path_behind, ahead, o.path_points)

    def _set_agent(self, p, i, state, path_pts, speed):
        p[self._sl[("x0", i)]] = state
        p[self._sl[("vref", i)]] = speed
        p[self._sl[("path", i)]] = path_pts.reshape(-1)

    def _warm_start(self) -> np.ndarray | None:
        """The previous solution shifted by one step (last control repeated), or None."""
        if self._u is None:
            return None
        parts = self.game.split_controls(self._u)
        return self.game.join_controls([np.concatenate([a[1:], a[-1:]]) for a in parts])

    def _no_reverse(self, u: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every agent's controls of ``u`` rolled out without reversing
        (:func:`stop_not_reverse`): the joint controls and the states ``(N, K, 4)``."""
        g = self.game
        parts, states = [], []
        for i, a in enumerate(g.split_controls(u)):
            X, U = stop_not_reverse(p[self._sl[("x0", i)]], a, self.dt)
            parts.append(U)
            states.append(X)
        return g.join_controls(parts), np.stack(states)

    def _assemble(self, obs: Observation, u: np.ndarray, states: np.ndarray, info: dict) -> Plan:
        """The plan of joint controls ``u`` and their states ``(N, K, 4)`` (no reversing)."""
        controls = self.game.split_controls(u)[0]
        if not (np.all(np.isfinite(states)) and np.all(np.isfinite(controls))):
            self._u = None
            return failed_plan(obs.t, self.dt, self.game.K, f"{self.name}: non-finite plan", **info)
        self._u = u
        return Plan(
            t0=float(obs.t),
            dt=self.dt,
            states=states[0].copy(),
            controls=controls.copy(),
            predictions=states[None],
            probabilities=np.ones(1),
            info=info,
        )

    def plan(self, obs: Observation, est: Estimate) -> Plan:
        """The ego's plan for this period; never raises (a failure is ``ok=False``, see the
        module docstring: also for a missing or malformed ``obs`` or ``est``)."""
        K = self.options.horizon
        t = getattr(obs, "t", math.nan)
        try:
            t = float(t)
        except (TypeError, ValueError):
            t = math.nan
        if self.game is None:
            return failed_plan(t, self.dt, K, f"{self.name}: plan() before reset()")
        t0 = time.perf_counter()
        try:
            if not math.isfinite(t):
                raise _PlanFailure(
                    f"expected an Observation with a finite time t, got {short_repr(obs)}"
                )
            if not isinstance(getattr(est, "states", None), np.ndarray | list | tuple):
                raise _PlanFailure(f"expected an Estimate, got {type(est).__name__}")
            ego = np.asarray(obs.ego, dtype=float).reshape(4)
            others = np.asarray(est.states, dtype=float).reshape(self.game.N - 1, 4).copy()
            self._speed_change = _speed_change(est, len(others), self.dt)
            if not np.all(np.isfinite(ego)):
                raise _PlanFailure("the ego state is not finite")
            ego = ego.copy()
            ego[2] = max(ego[2], 0.0)  # the plan starts from a car that does not reverse
            others[:, 2] = np.maximum(others[:, 2], 0.0)
            # an agent without a finite estimate (never observed yet) is left out: placed
            # far away with its collision weights set to zero
            seen = np.all(np.isfinite(others), axis=1)
            self._absent = np.flatnonzero(~seen) + 1
            conv = getattr(est, "converged", None)
            conv = np.ones(len(others), bool) if conv is None else np.asarray(conv, bool)
            conv = conv.reshape(-1) if conv.size == len(others) else np.ones(len(others), bool)
            self._unconverged = np.flatnonzero(seen & ~conv) + 1
            for i in self._absent:
                others[i - 1] = [ego[0] + _FAR * i, ego[1] + _FAR, 0.0, 0.0]
            with np.errstate(all="ignore"):
                plan = self._solve(obs, ego, others)
            if self._absent.size:
                plan.info["absent"] = self._absent.tolist()
            plan.info["converged"] = not self._unconverged.size
        except _PlanFailure as e:
            self._u = None
            plan = failed_plan(t, self.dt, K, f"{self.name}: {e}")
        except Exception as e:  # noqa: BLE001 - plan() never raises (module docstring)
            self._u = None
            plan = failed_plan(t, self.dt, K, f"{self.name}: {type(e).__name__}: {e}")
        plan.info["solve_ms"] = (time.perf_counter() - t0) * 1e3
        return plan

    def _solve(self, obs, ego, others) -> Plan:  # pragma: no cover - abstract
        raise NotImplementedError


class _PlanFailure(Exception):
    pass


class GameOracle(_GamePlanner):
    """The potential game in receding horizon with every agent's true task and the commit
    logic of the module docstring. ``options``: :class:`PlannerOptions` or a dict of its
    fields."""

    name = "oracle"

    def reset(self, world: World) -> None:
        super().reset(world)
        tasks = list(world.tasks())
        if len(tasks) != self.game.N:
            raise SpecError("world.tasks", f"expected {self.game.N} tasks, got {len(tasks)}")
        self.tasks = tasks
        self._order: str | None = None  # the committed passing order (commit logic)
        self._yielding: set[int] = set()  # agents seen braking to yield (params)
        self._switched_at = -math.inf  # when the committed order last changed (s)

    def params(self, ego: np.ndarray, others: np.ndarray) -> np.ndarray:
        """The game's parameter vector for these initial states: the true tasks, the
        estimated speed as the reference of a stopped agent, constant velocity for an
        unconverged one (module docstring)."""
        o = self.options
        p = self._base_params()
        self._set_agent(p, 0, ego, self._window(self.tasks[0].path, ego, self.tasks[0].speed),
                        self.tasks[0].speed)  # fmt: skip
        for i, (state, task) in enumerate(zip(others, self.tasks[1:], strict=True), start=1):
            hold = i in self._unconverged or (i not in self._absent and state[2] < o.stopped_speed)
            if i in self._unconverged:
                self._set_agent(p, i, state, self._cv_path(state), state[2])
            elif hold:  # it waits: predicted to keep going as slowly as it goes
                self._set_agent(p, i, state, self._window(task.path, state, state[2]), state[2])
            elif self._is_yielding(i, state[2], task.speed):  # braking to yield
                self._set_agent(p, i, state, self._window(task.path, state, 0.0), 0.0)
            else:
                self._set_agent(p, i, state, self._window(task.path, state, task.speed), task.speed)
            if hold:
                for j in self._w_cv[i]:
                    p[j] *= o.hold_weight
        return p

    def _is_yielding(self, i: int, speed: float, desired: float) -> bool:
        """Agent ``i`` is braking to yield (module docstring): set once its speed fell by
        more than ``_SLOWING_DROP`` over ``_SLOWING_WINDOW`` while below half its desired
        speed, held until it speeds up by as much or reaches half its desired speed."""
        change = self._speed_change[i - 1]
        if speed >= 0.5 * desired or change > _SLOWING_DROP:
            self._yielding.discard(i)
        elif change < -_SLOWING_DROP:
            self._yielding.add(i)
        return i in self._yielding

    def starts(self, ego: np.ndarray) -> np.ndarray:
        """Initial strategies ``(B, n_u)``: the previous solution shifted (if any), then
        "ego first" (the ego accelerates, the others brake) and "others first" (the
        reverse), each for the first half of the horizon."""
        g, o = self.game, self.options
        K, half = g.K, g.K // 2
        out = []
        warm = self._warm_start()
        out.append(g.zero_controls() if warm is None else warm)
        for sign in (1.0, -1.0):
            parts = []
            for i in range(g.N):
                a = np.zeros((K, 2))
                a[:half, 0] = (sign if i == 0 else -sign) * o.start_acceleration
                parts.append(a)
            out.append(g.join_controls(parts))
        return np.stack(out)

    # ---------------------------------------------------------------- commit logic
    def stop_line(self) -> float:
        """Arc length of the ego's stop line along its path: its centre there keeps its front
        (half its length, or its radius) ``stop_gap`` m before the zone's ``s_in``."""
        return self.zone[0] - self._front - self.options.stop_gap

    def phase(self, ego: np.ndarray) -> str:
        """``"free"`` (it can still stop before its stop line), ``"committed"`` (it cannot,
        or its front is past the line, and its rear has not left the zone) or ``"clear"``
        (past the zone, or no zone)."""
        if self.zone is None:
            return "clear"
        s_in, s_out = self.zone
        s = float(_project(ego[None, :2], self.ego_task.path)[0][0])
        if s - self._front >= s_out:
            return "clear"
        stop_line = self.stop_line()
        braking = max(float(ego[2]), 0.0) ** 2 / (2.0 * self.options.stop_deceleration)
        return "committed" if s + braking > stop_line else "free"

    def _stop_at_line(self, ego, cand, p):
        """A yielding plan whose ego would pass its stop line, with the ego's accelerations
        capped by the constant deceleration that stops it there, ``-v^2 / (2 d)`` (``d`` the
        arc length left to the line; at once when none is left); None when it stops before
        the line anyway."""
        u, states = cand
        path = self.ego_task.path
        line = self.stop_line()
        if _project(states[0, :, :2], path)[0].max() <= line:
            return None
        g = self.game
        parts = g.split_controls(u)
        d = line - float(_project(ego[None, :2], path)[0][0])
        v = max(float(ego[2]), 0.0)
        brake = -v * v / (2.0 * d) if d > 1e-3 else -v / self.dt
        a = parts[0].copy()
        a[:, 0] = np.minimum(a[:, 0], brake)
        X, a = stop_not_reverse(ego, a, self.dt)
        parts[0] = a
        states = states.copy()
        states[0] = X
        return g.join_controls(parts), states

    def order(self, ego: np.ndarray, states: np.ndarray) -> str:
        """The passing order of a joint future ``(N, K, 4)`` from ``ego`` and this period's
        estimates: ``"ego"`` if the ego goes first against every other agent, ``"other"``
        if any goes first, ``"none"`` if nobody reaches the zone (:func:`passing_order`,
        with the world's ``radii`` as reach: the classification
        :func:`scenarios.closed_loop.metrics.passing_orders` makes from the log); ``"none"``
        without a zone."""
        if self.zone is None:
            return "none"
        e = np.concatenate([ego[None, :2], states[0, :, :2]])
        orders = set()
        for j in range(1, len(states)):
            if j in self._absent:
                continue
            reach = self._world_radii[0] + self._world_radii[j]
            pts = np.concatenate([self._others[j - 1, None, :2], states[j, :, :2]])
            orders.add(passing_order(e, pts, self.ego_task.path, self.zone, reach))
        if "other" in orders:
            return "other"
        return "ego" if "ego" in orders else "none"

    def _choose(self, t, ego, E, orders, progress, warm, warm_order) -> tuple[int, str, bool]:
        """The candidate to follow: its index (-1: the warm start itself, unsolved), the
        phase and whether the order switched."""
        o = self.options
        phase = self.phase(ego)
        best = int(np.argmax(E <= E.min() + 1e-9 * (1.0 + abs(E.min()))))
        ok = np.isfinite(E)
        if phase == "committed":  # it goes first: never re-yields before leaving the zone
            going = [m for m in range(len(E)) if ok[m] and orders[m] in ("ego", "none")]
            pick = min(going, key=lambda m: E[m]) if going else int(np.nanargmax(progress))
            if not going and warm_order == "ego":
                pick = -1  # no start goes first: the committed plan, shifted, goes on
            switched = self._order not in (None, "ego")
            self._order = "ego"
            return pick, phase, switched
        if self.zone is None or phase == "clear":
            # without a zone: keep the warm-started equilibrium unless another is clearly lower
            if warm and ok[0] and E[best] > E[0] - o.yield_margin * (1.0 + abs(E[0])):
                best = 0
            return best, phase, False
        committed = self._order
        if self._unconverged.size:  # no commitment on a track that has not converged:
            yielding = [m for m in range(len(E)) if ok[m] and orders[m] == "other"]
            return (min(yielding, key=lambda m: E[m]) if yielding else best), phase, False
        if committed is None:
            if orders[best] != "none":
                self._order, self._switched_at = orders[best], t
            return best, phase, False
        same = [m for m in range(len(E)) if ok[m] and orders[m] in (committed, "none")]
        other = [m for m in range(len(E)) if ok[m] and orders[m] not in (committed, "none")]
        keep = min(same, key=lambda m: E[m]) if same else None
        alt = min(other, key=lambda m: E[m]) if other else None
        if keep is None:
            pick = alt
        elif alt is None:
            pick = keep
        else:
            if orders[alt] == "other":  # yielding is the safe direction: a small margin
                pick = alt if E[alt] < E[keep] - o.yield_margin * (1.0 + abs(E[keep])) else keep
            else:  # going first: clearly lower, and not right after a switch
                lower = E[alt] < E[keep] - o.switch_margin * (1.0 + abs(E[keep]))
                settled = t - self._switched_at >= o.commit_time - 1e-9
                pick = alt if lower and settled else keep
        switched = pick is not None and orders[pick] not in (committed, "none")
        if switched:
            self._order, self._switched_at = orders[pick], t
        return (best if pick is None else pick), phase, switched

    def _solve(self, obs, ego, others) -> Plan:
        g, o = self.game, self.options
        p = self.params(ego, others)
        self._others = others
        warm = self._u is not None
        U0 = self.starts(ego)
        B = U0.shape[0]
        steps = o.steps if warm else o.first_steps
        res = solve_lm(g, np.broadcast_to(p, (B, g.n_p)), U0, o.lm(steps))
        ok = np.asarray(res.ok, dtype=bool) & np.isfinite(res.energy)
        info = {
            "status": [s.value for s in res.status],
            "iterations": res.iterations.tolist(),
            "energies": res.energy.tolist(),
        }
        if not ok.any():
            self._u = None
            self._order = None
            return failed_plan(obs.t, self.dt, g.K, f"oracle: LM {res.message}", **info)
        E = np.where(ok, res.energy, np.inf)
        # every candidate without reversing, and who goes first in it
        cands = [self._no_reverse(res.controls[m], p) if ok[m] else None for m in range(B)]
        orders = [self.order(ego, c[1]) if c is not None else "none" for c in cands]
        prog = np.array(
            [
                _project(c[1][0, -1:, :2], self.ego_task.path)[0][0] if c is not None else -np.inf
                for c in cands
            ]
        )
        held = self._no_reverse(U0[0], p) if warm else None
        held_order = self.order(ego, held[1]) if warm else "none"
        best, phase, switched = self._choose(float(obs.t), ego, E, orders, prog, warm, held_order)
        if best < 0:  # the committed plan shifted by one step, as it is
            cands.append(held)
            orders.append(held_order)
            E = np.append(E, float(g.function("energy")(held[0], p)))
            ok = np.append(ok, bool(np.isfinite(E[-1])))
            best, B = B, B + 1
        if phase == "committed" and orders[best] == "other":  # nothing goes first: go on
            parts = g.split_controls(cands[best][0])
            parts[0] = parts[0].copy()
            parts[0][:, 0] = np.maximum(parts[0][:, 0], 0.0)  # no braking inside the zone
            cands[best] = self._no_reverse(g.join_controls(parts), p)
            orders[best] = self.order(ego, cands[best][1])
            info["no_braking"] = True
        if phase == "free" and orders[best] == "other":  # yielding: stop at the stop line
            stopped = self._stop_at_line(ego, cands[best], p)
            if stopped is not None:
                cands[best] = stopped
                info["stop_line"] = True
        self.last_params, self.last_u0 = p, (U0[best] if best < len(U0) else U0[0])
        info.update(
            mode=best,  # B (one past the starts): the committed plan shifted, unsolved
            energy=float(E[best]),
            orders=orders,
            order=orders[best],
            committed=self._order,
            phase=phase,
            switched=switched,
        )
        modes = [m for m in range(B) if ok[m] or m == best]
        keep = []  # drop starts that converged to the same equilibrium
        for m in sorted(modes, key=lambda m: (m != best, E[m])):
            if all(np.max(np.abs(cands[m][0] - cands[j][0])) > 1e-3 for j in keep):
                keep.append(m)
        Ek = np.where(np.isfinite(E[keep]), E[keep], np.nanmax(np.where(ok, E, -np.inf)) + 1e3)
        w = np.exp(-(Ek - Ek.min()) / o.temperature)
        plan = self._assemble(obs, cands[best][0], cands[best][1], info)
        if not plan.ok:
            self._order = None
            return plan
        preds = np.stack([cands[m][1] for m in keep])
        return Plan(
            plan.t0,
            plan.dt,
            plan.states,
            plan.controls,
            predictions=preds,
            probabilities=w / w.sum(),
            info=info,
        )


class ConstantVelocityPlanner(_GamePlanner):
    """Constant-velocity predictions of the others and the ego's best response to them on
    the same energy (see the module docstring); IPOPT on the reduced problem with the
    ego's speeds kept >= 0 as constraints."""

    name = "cv"

    def reset(self, world: World) -> None:
        super().reset(world)
        self._nlp = self.game.cached(("cv_best_response", self.options), self._build_nlp)

    def _build_nlp(self):
        g = self.game
        n_e = int(g.uoff[1])
        ue = ca.SX.sym("ue", n_e)
        uo = ca.SX.sym("uo", g.n_u - n_e)
        p = ca.SX.sym("p", g.n_p)
        E = g.function("energy")(ca.vertcat(ue, uo), p)
        v0 = p[g.params["x0.ego"].start + 2]
        # the ego's speeds after each step: linear in its accelerations (every 2nd control)
        speeds = v0 + g.dt * ca.cumsum(ue[0::2])
        o = self.options
        opts = {
            "print_time": False,
            "error_on_fail": False,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "ipopt.max_iter": o.ipopt_max_iter,
            "ipopt.tol": o.ipopt_tol,
        }
        return ca.nlpsol(
            "cv_best_response",
            "ipopt",
            {"x": ue, "p": ca.vertcat(p, uo), "f": E, "g": speeds},
            opts,
        )

    def params(self, ego: np.ndarray, others: np.ndarray) -> np.ndarray:
        """Parameters: the ego's true task; each other agent on a straight line along its
        heading at its current speed (its own terms do not change the ego's best response)."""
        p = self._base_params()
        task = self.ego_task
        self._set_agent(p, 0, ego, self._window(task.path, ego, task.speed), task.speed)
        for i, s in enumerate(others, start=1):
            self._set_agent(p, i, s, self._cv_path(s), s[2])
        return p

    def _solve(self, obs, ego, others) -> Plan:
        g = self.game
        n_e = int(g.uoff[1])
        p = self.params(ego, others)
        u0 = self._warm_start()
        ue0 = np.zeros(n_e) if u0 is None else u0[:n_e]
        self.last_params, self.last_u0 = p, np.concatenate([ue0, np.zeros(g.n_u - n_e)])
        try:
            sol = self._nlp(
                x0=ue0, p=np.concatenate([p, np.zeros(g.n_u - n_e)]), lbg=0.0, ubg=np.inf
            )
        except RuntimeError as e:
            raise _PlanFailure(f"IPOPT: {str(e).splitlines()[0]}") from None
        st = self._nlp.stats()
        status = str(st.get("return_status", "unknown"))
        info = {"status": status, "iterations": int(st.get("iter_count", 0))}
        if status not in ("Solve_Succeeded", "Solved_To_Acceptable_Level"):
            if status != "Maximum_Iterations_Exceeded":
                self._u = None
                return failed_plan(obs.t, self.dt, g.K, f"cv: IPOPT {status}", **info)
        u = np.concatenate([np.asarray(sol["x"], dtype=float).reshape(-1), np.zeros(g.n_u - n_e)])
        info["energy"] = float(sol["f"])
        u, states = self._no_reverse(u, p)  # IPOPT's tolerance: speeds of -1e-9 become 0
        return self._assemble(obs, u, states, info)
