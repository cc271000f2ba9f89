"""Planners without a network: the game oracle and the constant-velocity planner.

Both implement :class:`solvers.control.types.Planner` and plan on the same energy, the
paper's driving features (App. F.3, CARLA) for every agent on the unicycle of
:mod:`epo_casadi.dynamics`::

    path               distance to the agent's lane centre line (a polyline parameter)
    reference_velocity speed - the lane's speed (a vref parameter)
    velocity, acceleration, jerk, turn_rate, turn_acceleration   (running costs)
    velocity_bound     max(0, -v): no reversing (a soft bound, not in the paper's list)
    collision          max(0, r_i + r_j + margin - distance), every pair, every step

:class:`GameOracle`
    The game solver itself in receding horizon with every agent's *true* task
    (``world.tasks()``: path and speed): the N-agent potential game is minimized by
    Levenberg-Marquardt (:func:`solvers.solve_lm`) each period, warm-started from the
    previous solution shifted by one step. The ego's initial state is exact, the others'
    come from the :class:`~solvers.control.types.Estimate`.

:class:`ConstantVelocityPlanner`
    What a planner without a game does: the others are predicted at constant velocity from
    the estimate (a unicycle with zero controls is exactly that) and the ego minimizes the
    same energy over its own controls only, the others' controls fixed at zero. In a
    potential game this is the ego's best response: the terms that change with the ego's
    controls are those of its own cost ``C_0``. The reduced problem (the game's energy
    with the others' controls as parameters) is built once in CasADi and solved by IPOPT.

The game is built once per structure (number of agents, radii, ``dt``, options) and
cached: a new episode or a new step only changes parameters (initial states, the path
windows, the speeds). Paths enter as a window of ``path_points`` vertices resampled along
each agent's lane from just behind it to beyond what it can reach within the horizon.

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

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size, short_repr
from epo_casadi.game import AgentSpec, GameSpec, PotentialGame

from ..lm import LMOptions, solve_lm
from .types import AgentTask, Estimate, Observation, Plan, World

__all__ = [
    "PlannerOptions",
    "GameOracle",
    "ConstantVelocityPlanner",
    "build_game",
    "path_window",
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
    w_reverse: float = 5.0  #: weight of max(0, -v) (no reversing)
    w_collision: float = 50.0  #: weight of the collision penetration
    collision_margin: float = 1.0  #: metres added to r_i + r_j in the collision feature
    steps: int = 10  #: LM steps per period (warm-started), at most 100,000
    start_acceleration: float = 2.0  #: oracle: |a| of the "ego first" / "others first" starts
    switch_margin: float = 0.02  #: oracle: leave the warm-started mode if another is this
    #: fraction of (1 + E) lower
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
        check_number("planner.collision_margin", self.collision_margin, lo=0)
        check_number("planner.gtol", self.gtol, lo=0)
        check_number("planner.start_acceleration", self.start_acceleration, lo=0)
        check_number("planner.switch_margin", self.switch_margin, lo=0)
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
# the game
# --------------------------------------------------------------------------------------
_GAMES: dict[tuple, PotentialGame] = {}
_FAR = 1e3  # metres: where an agent without an estimate is parked


def agent_name(i: int) -> str:
    return "ego" if i == 0 else f"a{i}"


def build_game(radii, dt: float, options: PlannerOptions) -> PotentialGame:
    """The driving game of ``len(radii)`` unicycles (cached per structure in the process).

    Agent ``0`` is ``"ego"``, the others ``"a1"``, ``"a2"``, ...; parameters as in
    :mod:`epo_casadi.game` (``x0.<agent>``, ``vref.<agent>``, ``path.<agent>``).
    """
    radii = tuple(float(r) for r in np.asarray(radii, dtype=float).reshape(-1))
    key = (radii, float(dt), options)
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
        AgentSpec(name=agent_name(i), dynamics="unicycle", features=feats, radius=r)
        for i, r in enumerate(radii)
    ]
    pair = {
        "type": "collision",
        "weight": float(options.w_collision),
        "margin": float(options.collision_margin),
    }
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
        self.game = build_game(radii, self.dt, self.options)
        self.ego_task: AgentTask = world.ego_task
        self._u: np.ndarray | None = None  # previous solution (warm start)
        g = self.game
        self._base = g.default_params()
        self._sl = {
            (kind, i): g.params[f"{kind}.{agent_name(i)}"].slice
            for i in range(g.N)
            for kind in ("x0", "vref", "path")
        }
        self.last_params = self.last_u0 = None
        self._absent = np.zeros(0, dtype=int)
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
        return p

    def _window(self, path, state, speed):
        o = self.options
        ahead = max(float(state[2]), float(speed), 0.0) * o.horizon * self.dt + o.path_ahead
        return path_window(path, state, o.path_behind, ahead, o.path_points)

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

    def _assemble(self, obs: Observation, u: np.ndarray, x: np.ndarray, info: dict) -> Plan:
        g = self.game
        states = np.stack(g.split_states(x))[:, 1:]  # (N, K, 4): x_1..x_K
        controls = g.split_controls(u)[0]
        if not (np.all(np.isfinite(states)) and np.all(np.isfinite(controls))):
            self._u = None
            return failed_plan(obs.t, self.dt, g.K, f"{self.name}: non-finite plan", **info)
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
            others = np.asarray(est.states, dtype=float).reshape(self.game.N - 1, 4)
            if not np.all(np.isfinite(ego)):
                raise _PlanFailure("the ego state is not finite")
            # an agent without a finite estimate (never observed yet) is left out: placed
            # far away with its collision weights set to zero
            self._absent = np.flatnonzero(~np.all(np.isfinite(others), axis=1)) + 1
            if self._absent.size:
                others = others.copy()
                for i in self._absent:
                    others[i - 1] = [ego[0] + _FAR * i, ego[1] + _FAR, 0.0, 0.0]
            with np.errstate(all="ignore"):
                plan = self._solve(obs, ego, others)
            if self._absent.size:
                plan.info["absent"] = self._absent.tolist()
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
    """The potential game in receding horizon with every agent's true task (see the
    module docstring). ``options``: :class:`PlannerOptions` or a dict of its fields."""

    name = "oracle"

    def reset(self, world: World) -> None:
        super().reset(world)
        tasks = list(world.tasks())
        if len(tasks) != self.game.N:
            raise SpecError("world.tasks", f"expected {self.game.N} tasks, got {len(tasks)}")
        self.tasks = tasks

    def params(self, ego: np.ndarray, others: np.ndarray) -> np.ndarray:
        """The game's parameter vector for these initial states (true tasks)."""
        p = self._base_params()
        for i, (state, task) in enumerate(zip([ego, *others], self.tasks, strict=True)):
            self._set_agent(p, i, state, self._window(task.path, state, task.speed), task.speed)
        return p

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

    def _solve(self, obs, ego, others) -> Plan:
        g, o = self.game, self.options
        p = self.params(ego, others)
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
            return failed_plan(obs.t, self.dt, g.K, f"oracle: LM {res.message}", **info)
        E = np.where(ok, res.energy, np.inf)
        # the first start whose energy is the lowest up to rounding: equal equilibria reached
        # from several starts pick the same one whatever the backend's summation order
        best = int(np.argmax(E <= E.min() + 1e-9 * (1.0 + abs(E.min()))))
        # hysteresis: keep the warm-started equilibrium unless another is clearly lower
        if warm and ok[0] and E[best] > E[0] - o.switch_margin * (1.0 + abs(E[0])):
            best = 0
        self.last_params, self.last_u0 = p, U0[best]
        info.update(mode=best, energy=float(E[best]))
        modes = [m for m in range(B) if ok[m]]
        keep = []  # drop starts that converged to the same equilibrium
        for m in sorted(modes, key=lambda m: (m != best, E[m])):
            if all(np.max(np.abs(res.controls[m] - res.controls[j])) > 1e-3 for j in keep):
                keep.append(m)
        w = np.exp(-(E[keep] - E[keep].min()) / o.temperature)
        plan = self._assemble(obs, res.controls[best], res.states[best], info)
        if not plan.ok:
            return plan
        preds = np.stack([np.stack(g.split_states(res.states[m]))[:, 1:] for m in keep])
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
    the same energy (see the module docstring); IPOPT on the reduced problem."""

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
            "cv_best_response", "ipopt", {"x": ue, "p": ca.vertcat(p, uo), "f": E}, opts
        )

    def params(self, ego: np.ndarray, others: np.ndarray) -> np.ndarray:
        """Parameters: the ego's true task; each other agent on a straight line along its
        heading at its current speed (its own terms do not change the ego's best response)."""
        o = self.options
        p = self._base_params()
        task = self.ego_task
        self._set_agent(p, 0, ego, self._window(task.path, ego, task.speed), task.speed)
        for i, s in enumerate(others, start=1):
            ahead = max(float(s[2]), 0.0) * o.horizon * self.dt + o.path_ahead
            self._set_agent(p, i, s, _straight(s, o.path_behind, ahead, o.path_points), s[2])
        return p

    def _solve(self, obs, ego, others) -> Plan:
        g = self.game
        n_e = int(g.uoff[1])
        p = self.params(ego, others)
        u0 = self._warm_start()
        ue0 = np.zeros(n_e) if u0 is None else u0[:n_e]
        self.last_params, self.last_u0 = p, np.concatenate([ue0, np.zeros(g.n_u - n_e)])
        try:
            sol = self._nlp(x0=ue0, p=np.concatenate([p, np.zeros(g.n_u - n_e)]))
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
        x = np.asarray(g.function("rollout")(u, p), dtype=float).reshape(-1)
        return self._assemble(obs, u, x, info)
