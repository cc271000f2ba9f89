"""A sampled check that a feedback policy is a (local) feedback Nash equilibrium.

The iLQ solver (:mod:`solvers.ilq`) returns a feedback policy, one per stage
``k = 0..K-1``, for the joint stage vectors of :func:`solvers.stages.to_stages`::

    U_k(X) = U*_k - P_k (X_k - X*_k) - Q_k (Y_k - Y*_k) - a_k

(``P = info["gains"]``, ``a = info["feedforward"]``, ``Q = info["gains_prev"]``). With
costs that couple consecutive stages (``jerk``, ``turn_acceleration``) the policy also
reacts to the carried variables ``Y_k = (U_{k-1}, X_{k-1})[info["prev_variables"]]``
(``Y_0 - Y*_0 = 0``); without ``Q`` the check tests a different policy than iLQ's.

A feedback Nash equilibrium is a set of policies from which no player lowers its own cost
``C_i`` (:mod:`epo_casadi.game`) by changing *its own* policy while the others keep
theirs (feedback included: the others react to the deviation through their gains). The
open-loop certificate (:mod:`solvers.nash`) is the wrong test for it: it holds the others'
*controls* fixed, not their policies.

:func:`feedback_nash_check` perturbs each player's policy, its rows of the gains ``P_k``
(and of ``Q_k`` when given) and of the feed-forward ``a_k`` together, along ``n_random``
random directions (unit RMS entries, seeded) and ``n_coordinate`` coordinate directions
(one feed-forward entry of one stage), each with both signs and every step in ``scales``; rolls the closed loop out
from the game's initial states with the nonlinear dynamics; and evaluates every player's
cost. The largest decrease of the deviating player's own cost is its *gain*; the check
passes when every player's gain is ``<= tol (1 + |C_i|)``.

It is a sampled, **local** test: a passing check says that none of the tried deviations
helps (a gradient of size ``g`` along a direction shows as a gain of about ``scale |g|``); it
does not prove optimality, and it cannot see a better response behind a barrier (passing
another player on the other side). A policy shifted away from the equilibrium fails it.

Verdicts (:class:`solvers.result.Verdict`), per player and overall: ``fails`` when a
deviation lowers the player's cost by more than the tolerance, or its cost under the
policies is not finite; ``unknown`` when no deviation could be evaluated (none tried, or
every deviated rollout non-finite); ``passes`` otherwise. ``ok`` is "every player passes".

Global check (``global_starts = K``). From one initial state, the best a player can do
against the others' *fixed policies* is the best open-loop control sequence (the system
is deterministic, so any policy of the player is one sequence here). For each player the
check minimizes its own closed-loop cost over that sequence with IPOPT (the others react
through their gains ``P``, ``Q``; exact Hessian up to ``exact_hessian_max`` controls, else
L-BFGS) from ``K`` starts: zero controls, then seeded normal draws times
``global_scale``. A start that lowers the player's cost by more than the tolerance fails
it, whether or not that solve converged; starts that find nothing leave the verdict as
the sampled check found it. The starts run one after the other.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError, check_number
from epo_casadi.game import PotentialGame

from .lm import check_options
from .result import Verdict, combine_verdicts
from .stages import to_stages

__all__ = [
    "FeedbackNashOptions",
    "FeedbackNashCheck",
    "feedback_nash_check",
    "check_ilq_result",
]


@dataclass(frozen=True)
class FeedbackNashOptions:
    """How many deviations to try, how far, and the tolerance on a player's gain."""

    n_random: int = 8  #: random directions per player (gains and feed-forward together)
    n_coordinate: int = 4  #: coordinate directions per player (one feed-forward entry each)
    scales: tuple[float, ...] = (1e-3, 1e-2)  #: step sizes along every direction (both signs)
    tol: float = 1e-6  #: a player fails when its cost drops by more than tol (1 + |C_i|)
    seed: int = 0  #: seed of the random directions
    global_starts: int = 0  #: best responses against the others' policies from this many starts
    global_scale: float = 1.0  #: standard deviation of the drawn starts (control units)
    global_seed: int = 0  #: seed of the drawn starts
    max_iter: int = 300  #: IPOPT iterations per global best response
    exact_hessian_max: int = 200  #: exact Hessian up to this many controls per player, then L-BFGS

    def __post_init__(self):
        for name in (
            "n_random",
            "n_coordinate",
            "seed",
            "global_starts",
            "global_seed",
            "max_iter",
            "exact_hessian_max",
        ):
            check_number(f"feedback_nash.{name}", getattr(self, name), lo=0, integer=True)
        check_number("feedback_nash.tol", self.tol, lo=0, lo_open=True)
        check_number("feedback_nash.global_scale", self.global_scale, lo=0, lo_open=True)
        try:
            scales = tuple(float(s) for s in self.scales)
        except (TypeError, ValueError):
            raise SpecError("feedback_nash.scales", "expected a list of numbers > 0") from None
        if not scales:
            raise SpecError("feedback_nash.scales", "expected at least one step size")
        for s in scales:
            check_number("feedback_nash.scales", s, lo=0, lo_open=True)
        object.__setattr__(self, "scales", scales)


@dataclass(frozen=True)
class FeedbackNashCheck:
    """Result of :func:`feedback_nash_check`.

    ``costs``: ``C_i`` under the given policies ``(N,)``; ``gain``: the largest decrease of
    ``C_i`` found by player ``i``'s own deviations ``(N,)`` (``<= 0``: none helped; the
    global best responses included when run); ``ok_agent``: per player, verdict
    ``passes``; ``trials``: sampled deviations tried per player; ``time_s``: wall time;
    ``verdicts`` / ``verdict``: per player and overall (module docstring); ``reasons``:
    why a player fails or is unknown (``""`` where it passes); ``decided_by``: the test
    that decided each player's verdict; ``global_starts``: starts of the global check per
    player (0: local only); ``global_gain``: the largest decrease the global best
    responses found ``(N,)`` (NaN without them).
    """

    kind: ClassVar[str] = "feedback"

    ok: bool
    costs: np.ndarray
    gain: np.ndarray
    ok_agent: np.ndarray
    trials: int
    tol: float
    time_s: float
    verdicts: tuple[Verdict, ...] = ()
    verdict: Verdict = Verdict.PASSES
    reasons: tuple[str, ...] = ()
    decided_by: tuple[str, ...] = ()
    global_starts: int = 0
    global_gain: np.ndarray | None = None

    @property
    def max_relative_gain(self) -> float:
        return float(np.max(self.gain / (1.0 + np.abs(self.costs)))) if self.gain.size else 0.0

    def scope(self) -> str:
        """What the check searched: ``local, sampled`` or with ``K global starts``."""
        k = self.global_starts
        if not k:
            return "LOCAL, sampled policy deviations"
        return f"sampled policy deviations + {k} global start{'s' if k > 1 else ''} per player"

    def summary(self) -> str:
        state = {"passes": "passes", "fails": "FAILS", "unknown": "UNKNOWN"}[str(self.verdict)]
        per = ", ".join(f"{g:.3g}" for g in self.gain)
        lines = [
            f"feedback Nash check {state} ({self.scope()}): largest own-cost decrease per "
            f"player [{per}] ({self.trials} deviations each, tol {self.tol:g} (1 + |C_i|), "
            f"{self.time_s:.2f} s)"
        ]
        if not self.global_starts:
            lines.append(
                "  certifies a LOCAL feedback equilibrium: a better response in another "
                "basin is not excluded (global_starts > 0 searches for one)"
            )
        for i, r in enumerate(self.reasons):
            if r:
                lines.append(f"  player {i}: {r}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready dictionary (non-finite numbers as None)."""

        def nums(a):
            if a is None:
                return None
            return [float(x) if np.isfinite(x) else None for x in np.asarray(a, float).ravel()]

        return {
            "kind": self.kind,
            "ok": bool(self.ok),
            "verdict": str(self.verdict),
            "verdicts": [str(v) for v in self.verdicts],
            "reasons": list(self.reasons),
            "decided_by": list(self.decided_by),
            "costs": nums(self.costs),
            "gain": nums(self.gain),
            "ok_agent": [bool(x) for x in self.ok_agent],
            "trials": int(self.trials),
            "tol": float(self.tol),
            "global_starts": int(self.global_starts),
            "global_gain": nums(self.global_gain),
            "time_s": float(self.time_s),
        }


def _loop(game: PotentialGame, prev: tuple[int, ...], player: int | None):
    """Symbols and costs of the closed loop (see :func:`_closed_loop`); with ``player``,
    that player's controls are a free sequence ``W (nu_i, K)`` instead of its policy."""
    K = game.K
    nx, nu = int(sum(game.nx)), int(sum(game.nu))
    na = len(prev)
    xo = np.concatenate([[0], np.cumsum(game.nx)]).astype(int)
    uo = np.concatenate([[0], np.cumsum(game.nu)]).astype(int)
    p = ca.SX.sym("p", game.n_p)
    Xr = ca.SX.sym("Xr", nx, K + 1)
    Ur = ca.SX.sym("Ur", nu, K)
    Pg = ca.SX.sym("P", nu * nx, K)
    a = ca.SX.sym("a", nu, K)
    Qg = ca.SX.sym("Q", nu * na, K)
    W = ca.SX.sym("W", 0 if player is None else int(game.nu[player]), K)
    x = ca.vertcat(
        *[
            p[game.params[f"x0.{n}"].start : game.params[f"x0.{n}"].start + game.nx[i]]
            for i, n in enumerate(game.agent_names)
        ]
    )
    xs, us = [x], []
    dy = ca.SX.zeros(na)  # Y_k - Y*_k, none at k = 0
    for k in range(K):
        Pk = ca.reshape(Pg[:, k], nx, nu).T  # row-major (nu, nx)
        u = Ur[:, k] - ca.mtimes(Pk, x - Xr[:, k]) - a[:, k]
        if na:
            Qk = ca.reshape(Qg[:, k], na, nu).T  # row-major (nu, na)
            u = u - ca.mtimes(Qk, dy)
        if player is not None:  # the deviating player plays its own sequence
            lo, hi = int(uo[player]), int(uo[player + 1])
            u = ca.vertcat(u[:lo], W[:, k], u[hi:])
        if na:
            dy = ca.vertcat(u - Ur[:, k], x - Xr[:, k])[list(prev)]
        x = game.stage_step(x, u)  # own dynamics, or a coupling's joint model
        xs.append(x)
        us.append(u)
    # flat game layout (agent-major, then time)
    xf = ca.vertcat(*[ca.vertcat(*[xk[xo[i] : xo[i + 1]] for xk in xs]) for i in range(game.N)])
    uf = ca.vertcat(*[ca.vertcat(*[uk[uo[i] : uo[i + 1]] for uk in us]) for i in range(game.N)])
    C = game.function("traj_agent_costs")(xf, uf, p)
    return W, [p, Xr, Ur, Pg, a, Qg], C


def _closed_loop(game: PotentialGame, prev: tuple[int, ...] = ()) -> ca.Function:
    """``(p, Xr (nx, K+1), Ur (nu, K), P (nu*nx, K), a (nu, K), Q (nu*na, K)) -> C (N)``: the
    closed loop from the game's initial states, rolled out with the nonlinear dynamics, and
    its costs. ``prev``: positions in ``(U_{k-1}, X_{k-1})`` of the carried variables ``Y_k``
    (``na = len(prev)``; their deviation is zero at ``k = 0``)."""

    def build():
        _, ins, C = _loop(game, prev, None)
        return ca.Function("closed_loop_costs", ins, [C])

    return game.cached(("feedback_nash_closed_loop", tuple(prev)), build)


def _best_response_nlp(game: PotentialGame, prev: tuple[int, ...], i: int, opts) -> ca.Function:
    """IPOPT on player ``i``'s closed-loop cost over its own control sequence ``W``
    (``x = vec(W)``, time-major), the others on their policies; NLP parameters: the
    closed loop's inputs, each flattened column-major and stacked."""
    exact = int(game.nu[i]) * game.K <= opts.exact_hessian_max

    def build():
        W, ins, C = _loop(game, prev, i)
        par = ca.vertcat(*[ca.vec(v) for v in ins])
        nlp_opts = {
            "print_time": False,
            "error_on_fail": False,
            "show_eval_warnings": False,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "ipopt.max_iter": opts.max_iter,
            "ipopt.tol": 1e-10,
            "ipopt.nlp_scaling_method": "none",
        }
        if not exact:
            nlp_opts["ipopt.hessian_approximation"] = "limited-memory"
        return ca.nlpsol(
            f"feedback_best_response_{i}", "ipopt", {"x": ca.vec(W), "p": par, "f": C[i]}, nlp_opts
        )

    key = ("feedback_nash_best_response", tuple(prev), i, opts.max_iter, exact)
    return game.cached(key, build)


def _sampled_gains(game, costs, base, P, a, Q, opts):
    """``(gain, evaluated, trials)``: per player the largest drop of its own cost over the
    sampled deviations of its rows of the policy (``-inf`` where none had a finite cost),
    how many deviations had a finite cost, and the number of rollouts."""
    K, N = game.K, game.N
    uo = np.concatenate([[0], np.cumsum(game.nu)]).astype(int)
    rng = np.random.default_rng(opts.seed)
    gain = np.full(N, -np.inf)
    evaluated = np.zeros(N, dtype=int)  # deviations with a finite cost, per player
    trials, na = 0, Q.shape[2]
    for i in range(N):
        rows = slice(int(uo[i]), int(uo[i + 1]))
        dirs = []
        for _ in range(opts.n_random):
            dP, da, dQ = np.zeros_like(P), np.zeros_like(a), np.zeros_like(Q)
            dP[:, rows] = rng.standard_normal(P[:, rows].shape)
            da[:, rows] = rng.standard_normal(a[:, rows].shape)
            if na:  # drawn after P and a: without Q the directions are as before
                dQ[:, rows] = rng.standard_normal(Q[:, rows].shape)
            dirs.append((dP, da, dQ))
        for _ in range(opts.n_coordinate):
            dP, da, dQ = np.zeros_like(P), np.zeros_like(a), np.zeros_like(Q)
            da[rng.integers(K), int(uo[i]) + rng.integers(game.nu[i])] = 1.0
            dirs.append((dP, da, dQ))
        for dP, da, dQ in dirs:
            for s in opts.scales:
                for sign in (1.0, -1.0):
                    c = costs(P + sign * s * dP, a + sign * s * da, Q + sign * s * dQ)
                    trials += 1
                    drop = base[i] - c[i] if np.isfinite(c[i]) else -np.inf
                    evaluated[i] += bool(np.isfinite(c[i]))
                    gain[i] = max(gain[i], drop)
    return gain, evaluated, trials


def _policy_inputs(game, gains, feedforward, gains_prev, prev_variables):
    """``(P, a, Q, prev)``: the policy's arrays of :func:`feedback_nash_check`, their
    shapes checked (one :class:`SpecError` naming the argument)."""
    K, nx, nu = game.K, int(sum(game.nx)), int(sum(game.nu))
    P = np.asarray(gains, float)
    a = np.asarray(feedforward, float)
    if P.shape != (K, nu, nx) or a.shape != (K, nu):
        raise SpecError(
            "gains/feedforward",
            f"expected shapes ({K}, {nu}, {nx}) and ({K}, {nu}), got {P.shape} and {a.shape}",
        )
    if (gains_prev is None) != (prev_variables is None):
        raise SpecError("gains_prev/prev_variables", "expected both or neither")
    prev = np.zeros(0, int) if prev_variables is None else np.asarray(prev_variables)
    if prev.ndim != 1 or (prev.size and not np.issubdtype(prev.dtype, np.integer)):
        raise SpecError("prev_variables", f"expected a 1-d array of integers, got {prev!r}")
    if prev.size and (prev.min() < 0 or prev.max() >= nu + nx):
        raise SpecError("prev_variables", f"expected positions in 0..{nu + nx - 1}")
    na = int(prev.size)
    Q = np.zeros((K, nu, 0)) if gains_prev is None else np.asarray(gains_prev, float)
    if Q.shape != (K, nu, na):
        raise SpecError("gains_prev", f"expected shape ({K}, {nu}, {na}), got {Q.shape}")
    return P, a, Q, prev


def _agent_verdict(base_i, gain_i, limit_i, glob_i, glob_by_i, evaluated_i, global_starts):
    """``(verdict, reason, decided_by)`` of one player (:func:`feedback_nash_check`): from
    its cost under the policies, the largest sampled drop, its limit, the global best
    responses' drop and source, and how many deviations had a finite cost."""
    if not np.isfinite(base_i):
        verdict = Verdict.FAILS
        reason = "the cost under the policies is not finite"
        by = "finite values"
    elif gain_i > limit_i:
        verdict = Verdict.FAILS
        reason = (
            f"a sampled deviation of its own policy lowers C_i by {gain_i:.3g} > tol "
            f"(1 + |C_i|) = {limit_i:.3g}"
        )
        by = "sampled policy deviation"
    elif np.isfinite(glob_i) and glob_i > limit_i:
        verdict = Verdict.FAILS
        reason = (
            f"a best response against the others' policies ({glob_by_i}) lowers C_i by "
            f"{glob_i:.3g} > tol (1 + |C_i|) = {limit_i:.3g}"
        )
        by = glob_by_i
    elif evaluated_i == 0 and not np.isfinite(glob_i):
        verdict = Verdict.UNKNOWN
        reason = (
            "no deviation could be evaluated (none tried, or every deviated rollout is "
            "not finite): no evidence either way"
        )
        by = "none"
    else:
        verdict = Verdict.PASSES
        reason = ""
        by = "sampled policy deviations" + (
            f" + {global_starts} global starts" if global_starts else ""
        )
    return verdict, reason, by


def feedback_nash_check(
    game: PotentialGame,
    p: np.ndarray,
    states: np.ndarray,
    controls: np.ndarray,
    gains: np.ndarray,
    feedforward: np.ndarray,
    options: FeedbackNashOptions | dict | None = None,
    gains_prev: np.ndarray | None = None,
    prev_variables: np.ndarray | None = None,
) -> FeedbackNashCheck:
    """Check the policy ``U_k(X) = U*_k - P_k (X - X*_k) - Q_k (Y_k - Y*_k) - a_k`` (module
    docstring).

    ``states`` ``(n_x,)`` and ``controls`` ``(n_u,)``: the trajectory ``(X*, U*)`` in the
    flat game layout; ``gains`` ``(K, nu, nx)`` and ``feedforward`` ``(K, nu)`` in the
    joint stage layout of :func:`solvers.stages.to_stages` (an iLQ result's
    ``info["gains"]`` and ``info["feedforward"]``). ``gains_prev`` ``(K, nu, na)`` and
    ``prev_variables`` ``(na,)``: the gains ``Q`` on the carried variables
    ``Y_k = (U_{k-1}, X_{k-1})[prev_variables]`` (``Y_0 - Y*_0 = 0``; an iLQ result's
    ``info["gains_prev"]`` and ``info["prev_variables"]``); both or neither (``None``: no
    ``Q`` term). One problem at a time.
    """
    opts = check_options(FeedbackNashOptions, options, "feedback_nash")
    t0 = time.perf_counter()
    K, N = game.K, game.N
    nx, nu = int(sum(game.nx)), int(sum(game.nu))
    P, a, Q, prev = _policy_inputs(game, gains, feedforward, gains_prev, prev_variables)
    na = int(prev.size)
    X, U = to_stages(game, np.asarray(states, float), np.asarray(controls, float))
    f = _closed_loop(game, tuple(int(v) for v in prev))
    p = np.asarray(p, float).reshape(-1)
    Xr, Ur = X.T, U.T

    def costs(Pm, am, Qm):
        Pf, Qf = Pm.reshape(K, nu * nx).T, Qm.reshape(K, nu * na).T
        return np.asarray(f(p, Xr, Ur, Pf, am.T, Qf), float).ravel()

    base = costs(P, a, Q)
    gain, evaluated, trials = _sampled_gains(game, costs, base, P, a, Q, opts)
    gain = np.where(np.isfinite(gain), gain, 0.0)
    limit = opts.tol * (1.0 + np.abs(base))
    glob = np.full(N, np.nan)
    glob_by = [""] * N
    if opts.global_starts:
        par = np.concatenate(
            [
                np.ravel(v, order="F")
                for v in (p, Xr, Ur, P.reshape(K, nu * nx).T, a.T, Q.reshape(K, nu * na).T)
            ]
        )
        for i in range(N):
            if np.isfinite(base[i]):
                glob[i], glob_by[i] = _global_best_responses(
                    game, tuple(int(v) for v in prev), i, par, base[i], limit[i], opts
                )
    verdicts, reasons, decided = [], [], []
    for i in range(N):
        v, why, by = _agent_verdict(
            base[i], gain[i], limit[i], glob[i], glob_by[i], evaluated[i], opts.global_starts
        )
        verdicts.append(v)
        reasons.append(why)
        decided.append(by)
    if opts.global_starts:
        gain = np.where(np.isfinite(glob), np.maximum(gain, glob), gain)
    ok_agent = np.array([v is Verdict.PASSES for v in verdicts], dtype=bool)
    verdict = combine_verdicts(verdicts)
    return FeedbackNashCheck(
        ok=verdict is Verdict.PASSES,
        costs=base,
        gain=gain,
        ok_agent=ok_agent,
        trials=trials // max(N, 1),
        tol=opts.tol,
        time_s=time.perf_counter() - t0,
        verdicts=tuple(verdicts),
        verdict=verdict,
        reasons=tuple(reasons),
        decided_by=tuple(decided),
        global_starts=opts.global_starts,
        global_gain=glob if opts.global_starts else None,
    )


def _global_best_responses(game, prev, i, par, base_i, limit_i, opts) -> tuple[float, str]:
    """Player ``i``'s best responses (its own control sequence, the others on their
    policies) from ``global_starts`` starts: the largest decrease of ``C_i`` found and the
    start that found it; stops at the first decrease above ``limit_i``."""
    solver = _best_response_nlp(game, prev, i, opts)
    n = int(game.nu[i]) * game.K
    rng = np.random.default_rng([opts.global_seed, i])
    best, by = -np.inf, ""
    for s in range(opts.global_starts):
        x0 = np.zeros(n) if s == 0 else opts.global_scale * rng.standard_normal(n)
        sol = solver(x0=x0, p=par)
        st = str(solver.stats().get("return_status", "unknown"))
        c = float(sol["f"])
        drop = base_i - c if np.isfinite(c) else -np.inf
        if drop > best:
            where = "zero controls" if s == 0 else "seeded draw"
            best, by = drop, f"global start {s} ({where}), ipopt: {st}"
        if best > limit_i:
            break
    return (best if np.isfinite(best) else np.nan), by


def check_ilq_result(
    game: PotentialGame,
    p: np.ndarray,
    result,
    options: FeedbackNashOptions | dict | None = None,
) -> FeedbackNashCheck:
    """:func:`feedback_nash_check` of the policy a :func:`solvers.ilq.solve_ilq` result
    holds: its trajectory, ``info["gains"]``, ``info["feedforward"]`` and, for games with
    lagged variables, ``info["gains_prev"]`` / ``info["prev_variables"]``."""
    info = result.info
    return feedback_nash_check(
        game,
        p,
        result.states,
        result.controls,
        info["gains"],
        info["feedforward"],
        options,
        gains_prev=info.get("gains_prev"),
        prev_variables=info.get("prev_variables"),
    )
