"""The part the two planners of :mod:`solvers.control.plan` share.

``_GamePlanner``: the driving game of a world (:func:`~solvers.control.plan_game.build_game`),
its parameter slices, the agents' initial states, lane windows, speeds and radii as game
parameters, the warm start, the rollout without reversing, the plan's assembly and
:meth:`~_GamePlanner.plan`, which never raises (a failure is :func:`failed_plan`,
``Plan(ok=False, message=...)``). Each planner supplies ``_solve``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from epo_casadi.errors import SpecError, short_repr
from epo_casadi.game import PotentialGame

from .plan_game import _CV_TERMS, _FAR, agent_name, build_game
from .plan_geometry import _speed_change, _straight, path_window, stop_not_reverse
from .plan_options import PlannerOptions
from .types import AgentTask, Estimate, Observation, Plan, World, world_member


def failed_plan(t0: float, dt: float, horizon: int, message: str, **info) -> Plan:
    """A plan that says it failed: NaN states and controls, ``ok=False``."""
    nan = np.full((horizon, 4), np.nan)
    return Plan(t0, dt, nan, np.full((horizon, 2), np.nan), ok=False, message=message, info=info)


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
        """The ego's plan for this period; never raises (a failure is ``ok=False``, see
        :mod:`solvers.control.plan`: also for a missing or malformed ``obs`` or ``est``)."""
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
        except Exception as e:  # noqa: BLE001 - plan() never raises (solvers.control.plan)
            self._u = None
            plan = failed_plan(t, self.dt, K, f"{self.name}: {type(e).__name__}: {e}")
        plan.info["solve_ms"] = (time.perf_counter() - t0) * 1e3
        return plan

    def _solve(self, obs, ego, others) -> Plan:  # pragma: no cover - abstract
        raise NotImplementedError


class _PlanFailure(Exception):
    pass
