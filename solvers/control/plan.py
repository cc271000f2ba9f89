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

Modules. This module holds the two planners; their pieces live beside it and every name
stays importable from here: :mod:`solvers.control.plan_options` (:class:`PlannerOptions`),
:mod:`solvers.control.plan_game` (the driving game, :func:`build_game`),
:mod:`solvers.control.plan_geometry` (rollout without reversing, footprints, lane windows,
:func:`passing_order`) and :mod:`solvers.control.plan_base` (the part both planners share).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError

from ..lm import solve_lm
from .plan_base import _GamePlanner, _PlanFailure, failed_plan
from .plan_game import _CV_TERMS as _CV_TERMS
from .plan_game import _FAR as _FAR
from .plan_game import _GAMES as _GAMES
from .plan_game import _OWN as _OWN
from .plan_game import FootprintCollision, build_game
from .plan_game import _circles as _circles
from .plan_game import agent_name as agent_name
from .plan_geometry import _SLOWING_DROP as _SLOWING_DROP
from .plan_geometry import _SLOWING_WINDOW as _SLOWING_WINDOW
from .plan_geometry import _project, inscribed_circles, passing_order, path_window, stop_not_reverse
from .plan_geometry import _resample as _resample
from .plan_geometry import _speed_change as _speed_change
from .plan_geometry import _straight as _straight
from .plan_options import MAX_HORIZON, PlannerOptions
from .plan_options import MAX_PATH_POINTS as MAX_PATH_POINTS
from .plan_options import MAX_STEPS as MAX_STEPS
from .plan_options import _have_compiler as _have_compiler
from .types import Plan, World

__all__ = [
    "PlannerOptions",
    "GameOracle",
    "ConstantVelocityPlanner",
    "FootprintCollision",
    "build_game",
    "inscribed_circles",
    "passing_order",
    "path_window",
    "stop_not_reverse",
    "failed_plan",
    "MAX_HORIZON",
]


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
