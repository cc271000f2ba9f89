"""A certificate that a joint strategy is an open-loop Nash equilibrium: local by default.

An open-loop Nash equilibrium (OLNE, paper Def. 3.1) is a joint strategy ``u*`` with
``C_i(u*) <= C_i(u_i, u*_{-i})`` for every agent ``i`` and every ``u_i``. The agent costs
``C_i`` are those of :mod:`epo_casadi.game` (own terms of ``i`` plus the pair terms that
involve ``i``). For each agent, :func:`nash_certificate` measures

* **stationarity** ``s_i = |dC_i/du_i (u, p)|_inf``, from the game's ``pseudo_gradient``
  function: first-order optimality of agent ``i``'s problem with the others fixed;
* **best-response gap** ``gap_i = C_i(u) - min_{u_i} C_i(u_i, u_{-i})``, where the minimum
  is a *local* solve of agent ``i``'s own problem (the others' controls fixed),
  warm-started at the given ``u_i``. The gap is ``>= 0`` by construction: when the
  solve ends above ``C_i(u)`` the given ``u_i`` is its own best known response.

Tolerances. Both tests are relative to a *bounded* scale
``S_i = 1 + min(|C_i|, scale_cap)``: ``s_i <= stat_tol S_i`` and ``gap_i <= gap_tol S_i``.
The cap keeps a huge cost from excusing a huge gradient (a failed solve with
``C_i = 2e204`` and ``s_i = 3e103`` passes a plain relative test).

Verdicts (:class:`solvers.result.Verdict`), per agent and overall
    * ``fails`` on evidence only: stationarity above its tolerance, a cost or gradient
      that is not finite, or a best response that **found** a lower ``C_i`` (a gap above
      the tolerance, whether or not that solve converged);
    * ``unknown`` when no best-response method finished (iteration cap, IPOPT's
      ``Search_Direction_Becomes_Too_Small``, L-BFGS stopping early, ...) and none showed
      a gap: a solve that stopped early is no evidence either way;
    * ``passes`` otherwise. The overall verdict is ``fails`` if an agent fails, else
      ``unknown`` if one is unknown, else ``passes``; :attr:`NashCertificate.ok` is
      "every agent passes".

Best responses, in order until one decides (:attr:`NashCertificate.decided_by` names it)
    1. IPOPT on ``C_i`` over ``u_i``, warm-started at the candidate, without objective
       scaling (``nlp_scaling_method none``: the tolerance is on ``C_i`` itself), with the
       exact Hessian for agents with ``n_i <= exact_hessian_max`` controls, else L-BFGS;
    2. when it stops without converging and without a gap, and the agent passes its
       stationarity test (else it fails anyway; ``fallback=True``):
       Levenberg-Marquardt on the agent's own residual rows (``C_i = 1/2 ||r_i||^2``, the
       rows of its own terms and of the pair terms that involve it), from the better of
       the candidate and the point IPOPT reached; it converges when
       ``|dC_i/du_i|_inf <= tol S_i``. Where it stops short of that (its decreases fall
       below round-off, its iteration cap), a Newton test at its point decides: the
       Hessian of ``C_i`` by central differences of the game's ``pseudo_gradient``
       positive definite, the Newton step small and its predicted decrease below
       ``gap_tol S_i / 100``.

    3. second order, for agents with the exact Hessian: a best response that finished at
       (or started from) a stationary point may sit on a saddle of ``C_i`` (IPOPT,
       warm-started at a stationary point, stops there). The smallest eigenvalue of the
       exact ``d^2 C_i / du_i^2`` at the point decides: above ``-stat_tol S_i`` the
       point is a local minimum of ``C_i``; below it, steps of growing length along the
       eigenvector (both signs) look for a lower ``C_i``: one that lowers it by more than
       the gap tolerance fails the agent, none leaves it ``unknown`` (a saddle without a
       found improvement is no evidence of a minimum).

    Agents with ``n_i > best_response_max`` get the stationarity test only (their
    verdict rests on it; the table says so), as do all with ``best_response=False``.

Local and global
    By default this is a **local** certificate: a small gap says that no agent can improve
    by a unilateral deviation that a descent method finds from the current point; it does
    not exclude a better response in another basin of the non-convex ``C_i`` (e.g. passing
    another agent on the other side). ``global_starts = K`` adds, per agent, best
    responses (IPOPT, then the fallback) from ``K`` more starts, the others' controls
    fixed: zero controls, then ``K - 1`` seeded normal draws times ``global_scale``. A
    start that finds a lower cost fails the agent; starts that find nothing leave the
    verdict as the local check found it (a sampled search, not a proof). The starts run one
    after the other. Bounds are not taken into account: the certificate is for the
    unconstrained (soft-penalty) game of the paper.

Cost. Each agent's best-response NLP is built once per game and options (parameters:
``p`` and the others' controls) and cached. Its Hessian decides the cost: an exact Hessian
of a single-shooting problem is dense and its symbolic build grows quickly with the
agent's control count ``n_i = K nu_i`` (1 s at ``n_i = 200``, 8 s at 400, minutes at
1,000). So agents with ``n_i <= exact_hessian_max`` get the exact Hessian, larger ones a
limited-memory (L-BFGS) Hessian that needs only the gradient, and agents with
``n_i > best_response_max`` get the stationarity test only; the table says which. The
fallback's residual Jacobian is built only when the fallback runs.
:attr:`NashCertificate.time_s` is the certificate's own wall time, and long checks show a
progress bar on a terminal (tqdm).

For a potential game every local minimizer of ``E`` passes (Theorem 1); a strategy
perturbed for one agent fails on that agent. For a game with coupled dynamics a minimizer
of ``E`` is in general not an equilibrium, and the certificate fails it.

Modules. This module holds the checker and its entry point; the options and the result live in
:mod:`solvers.nash_types` (:class:`NashOptions`, :class:`NashCertificate`) and stay importable
from here.
"""

from __future__ import annotations

import time
from dataclasses import replace

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame

from .codegen import BufferCall
from .lm import check_options
from .nash_types import CONVERGED as CONVERGED
from .nash_types import METHOD_NAMES as METHOD_NAMES
from .nash_types import NashCertificate as NashCertificate
from .nash_types import NashOptions as NashOptions
from .nash_types import _Attempt as _Attempt
from .result import Verdict, combine_verdicts

__all__ = ["NashOptions", "NashCertificate", "NashChecker", "nash_certificate"]


class NashChecker:
    """Best-response NLPs of every agent of one game, built once (see the module doc)."""

    def __init__(self, game: PotentialGame, options: NashOptions | dict | None = None):
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        self.game = game
        self.options = check_options(NashOptions, options, "nash")
        self._costs = game.function("agent_costs")
        self._pg = game.function("pseudo_gradient")
        self._br: dict[int, ca.Function] = {}
        self._lm: dict[int, ca.Function] = {}
        self._hess: dict[int, ca.Function] = {}
        self._calls: dict[int, BufferCall] = {}  # the residual functions, on numpy buffers
        self._pg_call: BufferCall | None = None

    def method(self, i: int) -> str:
        """How agent ``i``'s best response is found: ``exact``, ``l-bfgs``, ``off``, ``too large``."""
        n = int(self.game.uoff[i + 1] - self.game.uoff[i])
        o = self.options
        if not o.best_response or n == 0:
            return "off"
        if n > o.best_response_max:
            return "too large"
        return "exact" if n <= o.exact_hessian_max else "l-bfgs"

    def _agent_symbols(self, i: int):
        """``(u_i, [p; u_{-i}], u)`` symbols of agent ``i``'s problem."""
        g = self.game
        a, b = int(g.uoff[i]), int(g.uoff[i + 1])
        ui = ca.SX.sym("u_i", b - a)
        uo = ca.SX.sym("u_others", g.n_u - (b - a))
        p = ca.SX.sym("p", g.n_p)
        return ui, ca.vertcat(p, uo), p, ca.vertcat(uo[:a], ui, uo[a:])

    def best_response_nlp(self, i: int) -> ca.Function:
        """IPOPT solver of agent ``i``: ``x = u_i``, ``p = [p; u_{-i}]``, ``f = C_i``."""
        if i not in self._br:
            ui, par, p, u = self._agent_symbols(i)
            Ci = self._costs(u, p)[i]
            opts = {
                "print_time": False,
                "error_on_fail": False,
                "show_eval_warnings": False,
                "ipopt.print_level": 0,
                "ipopt.sb": "yes",
                "ipopt.max_iter": self.options.max_iter,
                "ipopt.tol": self.options.tol,
                # the tolerance is on C_i itself: no gradient-based objective scaling
                "ipopt.nlp_scaling_method": "none",
            }
            if self.method(i) == "l-bfgs":
                opts["ipopt.hessian_approximation"] = "limited-memory"
            self._br[i] = ca.nlpsol(
                f"best_response_{i}", "ipopt", {"x": ui, "p": par, "f": Ci}, opts
            )
        return self._br[i]

    def residual_function(self, i: int) -> ca.Function:
        """``(u_i, [p; u_{-i}]) -> (r_i, J_i)``: agent ``i``'s own residual rows (its own
        terms and the pair terms that involve it; ``C_i = 1/2 ||r_i||^2``) and their dense
        Jacobian in ``u_i``, for the fallback's Levenberg-Marquardt."""
        if i not in self._lm:
            g = self.game
            ui, par, p, u = self._agent_symbols(i)
            name = g.agent_names[i]
            rows = [
                k for t in g.terms if name in t.agents for k in range(t.rows.start, t.rows.stop)
            ]
            r = g.function("residual")(u, p)[rows] if rows else ca.SX(0, 1)
            J = ca.densify(ca.jacobian(r, ui))
            self._lm[i] = ca.Function(
                f"agent_residual_{i}", [ui, par], [r, J], ["u_i", "p"], ["r", "J"]
            )
        return self._lm[i]

    def own_hessian(self, i: int) -> ca.Function:
        """``(u_i, [p; u_{-i}]) -> H``: the exact Hessian of ``C_i`` in agent ``i``'s
        controls (dense; for the second-order test of agents with the exact Hessian)."""
        if i not in self._hess:
            ui, par, p, u = self._agent_symbols(i)
            Ci = self._costs(u, p)[i]
            H = ca.densify(ca.hessian(Ci, ui)[0])
            self._hess[i] = ca.Function(f"own_hessian_{i}", [ui, par], [H], ["u_i", "p"], ["H"])
        return self._hess[i]

    def _curvature_attempt(self, i: int, u, p, x, Ci, tol_i, scale_i) -> _Attempt | None:
        """The second-order test at agent ``i``'s controls ``x`` (module docstring, step
        3): None when the exact own Hessian there has no eigenvalue below
        ``-stat_tol S_i``; else the best point of the steps along its eigenvector, as a
        ``curvature`` attempt that converged only if it shows no saddle."""
        g = self.game
        a, b = int(g.uoff[i]), int(g.uoff[i + 1])
        others = np.concatenate([u[:a], u[b:]])
        with np.errstate(all="ignore"):
            H = np.asarray(self.own_hessian(i)(x, np.concatenate([p, others])), dtype=float)
        if not np.all(np.isfinite(H)):
            return None
        w, V = np.linalg.eigh(0.5 * (H + H.T))
        if not w[0] < -self.options.stat_tol * scale_i:
            return None
        v = V[:, 0]
        best_c, best_x = self._cost(i, u, p, x), x
        for t in np.geomspace(1e-3, 1e2, 11):
            for sgn in (1.0, -1.0):
                xt = x + sgn * t * v
                c = self._cost(i, u, p, xt)
                if np.isfinite(c) and c < best_c:
                    best_c, best_x = c, xt
        status = f"own Hessian eigenvalue {w[0]:.3g} < 0 (a saddle of C_i)"
        return _Attempt("curvature", status, False, best_c, best_x)

    def certify(self, p: np.ndarray, u: np.ndarray) -> NashCertificate:
        """Certificate for one problem: ``p`` ``(n_p,)``, ``u`` ``(n_u,)`` (the order of
        :func:`nash_certificate`).

        Non-finite ``u`` or ``p`` give a failing certificate (not an exception): every
        solver status, including ``nonfinite``, has one.
        """
        t0 = time.perf_counter()
        g = self.game
        u = np.asarray(u, dtype=float)
        p = np.asarray(p, dtype=float)
        finite_in = bool(np.all(np.isfinite(u)) and np.all(np.isfinite(p)))
        U, P = g.check_inputs(np.nan_to_num(u), np.nan_to_num(p))  # shapes only
        if U.shape[0] != 1:
            raise SpecError(
                "u/p", f"expected one problem, got a batch of {U.shape[0]}; certify each"
            )
        u, p = u.reshape(-1), p.reshape(-1)
        o = self.options
        methods = tuple(self.method(i) for i in range(g.N))
        C, stat = self._stationarity(u, p, finite_in)
        finite = np.isfinite(C) & np.isfinite(stat)
        scale = 1.0 + np.minimum(np.abs(np.nan_to_num(C, nan=np.inf)), o.scale_cap)
        stat_ok = finite & (stat <= o.stat_tol * scale)
        br = C.copy()
        gap_ok = finite.copy()
        glob = np.full(g.N, np.nan)
        statuses, reasons, verdicts, decided = [], [], [], []
        todo = [i for i in range(g.N) if finite[i] and methods[i] in ("exact", "l-bfgs")]
        bar = self._progress(todo)
        for i in range(g.N):
            why = self._first_order_reasons(i, finite_in, finite, stat_ok, stat, scale)
            fails = bool(why)
            by = "" if finite[i] else "finite values"
            if finite[i] and not stat_ok[i]:
                by = "stationarity"
            if i not in todo:
                statuses.append("skipped")
                reasons.append("; ".join(why))
                verdicts.append(Verdict.FAILS if fails else Verdict.PASSES)
                decided.append(by or "stationarity only")
                continue
            status, verdict, by, br[i], gap_ok[i], glob[i] = self._judge_agent(
                i, u, p, C[i], scale[i], fails, why, by
            )
            statuses.append(status)
            verdicts.append(verdict)
            reasons.append("; ".join(why))
            decided.append(by)
            bar.update(1)
        bar.close()
        with np.errstate(invalid="ignore"):
            gap = C - br  # NaN where C_i is not finite
        verdict = combine_verdicts(verdicts)
        return NashCertificate(
            agents=tuple(g.agent_names),
            costs=C,
            stationarity=stat,
            best_response_costs=br,
            best_response_gap=gap,
            relative_gap=gap / scale,
            best_response_status=tuple(statuses),
            best_response_method=methods,
            stat_ok=stat_ok,
            gap_ok=gap_ok,
            reasons=tuple(reasons),
            ok=verdict is Verdict.PASSES,
            time_s=time.perf_counter() - t0,
            options=o,
            verdicts=tuple(verdicts),
            verdict=verdict,
            decided_by=tuple(decided),
            global_best_costs=glob,
        )

    def _judge_agent(self, i, u, p, Ci, scale_i, fails, why, by):
        """Agent ``i``'s best-response verdict (:meth:`certify`): ``(status, verdict,
        decided_by, best_response_cost, gap_ok, global_best_cost)``; the reasons it finds are
        appended to ``why``. ``fails``/``by``: what the first-order checks already decided."""
        o = self.options
        br_i, gap_ok_i, glob_i = Ci, True, np.nan
        tol_i = o.gap_tol * scale_i
        local = self._local_attempts(i, u, p, Ci, tol_i, scale_i, fallback=not fails)
        found = [t for t in local if Ci - t.cost > tol_i]
        finished = [t for t in local if t.converged]
        searched = o.global_starts and not (found or fails)  # else already failing
        starts = self._global_attempts(i, u, p, Ci, tol_i, scale_i) if searched else []
        if starts:
            glob_i = min((c for _, t in starts if np.isfinite(c := t.cost)), default=np.nan)
        costs = [t.cost for t in local] + [t.cost for _, t in starts]
        finite_costs = [c for c in costs if np.isfinite(c)]
        if finite_costs:
            br_i = min(Ci, *finite_costs)
        gap_i = Ci - br_i
        found_global = [(s, t) for s, t in starts if Ci - t.cost > tol_i]
        if found or found_global:
            gap_ok_i = False
            fails = True
            if found:
                src = found[0].label
            else:
                s, t = found_global[0]
                src = (
                    f"global start {s} ({'zero controls' if s == 0 else 'seeded draw'}), {t.label}"
                )
            why.append(
                f"a best response ({src}) lowers C_i by {gap_i:.3g} > gap_tol x (1 + "
                f"min(|C_i|, scale_cap)) = {tol_i:.3g}"
            )
            by = by or src
        if fails:
            verdict = Verdict.FAILS
        elif finished:
            verdict = Verdict.PASSES
            by = finished[0].label
        else:
            gap_ok_i = False
            verdict = Verdict.UNKNOWN
            tried = "; ".join(t.label for t in local)
            why.append(
                f"best-response solve did not converge ({tried}) and found no gap: the "
                "gap is unknown"
            )
            by = "none (no best response finished)"
        return local[0].status, verdict, by, br_i, gap_ok_i, glob_i

    def _local_attempts(self, i, u, p, Ci, tol_i, scale_i, fallback=True) -> list[_Attempt]:
        """Best responses from the candidate until one finishes or finds a gap: IPOPT,
        then (options ``fallback`` and ``fallback``: the agent does not already fail on
        stationarity) LM from the better of the candidate and IPOPT's point."""
        a, b = int(self.game.uoff[i]), int(self.game.uoff[i + 1])
        first = self._best_response(i, u, p, u[a:b])
        out = [first]
        if Ci - first.cost > tol_i:
            return out
        if not first.converged and self.options.fallback and fallback:
            start = first.controls if np.isfinite(first.cost) and first.cost <= Ci else u[a:b]
            out.append(self._lm_best_response(i, u, p, start, scale_i))
        done = [t for t in out if t.converged]
        if done and self.method(i) == "exact" and not Ci - min(t.cost for t in out) > tol_i:
            saddle = self._curvature_attempt(i, u, p, done[0].controls, Ci, tol_i, scale_i)
            if saddle is not None:  # no local minimum: the finished solves decide nothing
                out = [replace(t, converged=False) for t in out] + [saddle]
        return out

    def _global_attempts(self, i, u, p, Ci, tol_i, scale_i) -> list[tuple[int, _Attempt]]:
        """Best responses from ``global_starts`` starts (zero controls, then seeded draws),
        the fallback after a start that stops early; stops at the first improvement."""
        o = self.options
        a, b = int(self.game.uoff[i]), int(self.game.uoff[i + 1])
        rng = np.random.default_rng([o.global_seed, i])
        out = []
        for s in range(o.global_starts):
            x0 = np.zeros(b - a) if s == 0 else o.global_scale * rng.standard_normal(b - a)
            t = self._best_response(i, u, p, x0)
            if not t.converged and not Ci - t.cost > tol_i and o.fallback:
                start = t.controls if np.all(np.isfinite(t.controls)) else x0
                lm = self._lm_best_response(i, u, p, start, scale_i, newton=False)
                if not np.isfinite(t.cost) or lm.cost < t.cost:
                    t = lm
            out.append((s, t))
            if Ci - t.cost > tol_i:
                break
        return out

    def _stationarity(self, u, p, finite_in: bool) -> tuple[np.ndarray, np.ndarray]:
        """Each agent's cost ``C_i`` and stationarity ``max |dC_i/du_i|`` (``(N,)`` each;
        NaN where not finite or where the inputs are not)."""
        g = self.game
        if not finite_in:
            return np.full(g.N, np.nan), np.full(g.N, np.nan)
        with np.errstate(all="ignore"):
            C = np.asarray(self._costs(u, p), dtype=float).reshape(-1)
            pg = np.asarray(self._pg(u, p), dtype=float).reshape(-1)
        stat = np.array(
            [np.max(np.abs(pg[g.uoff[i] : g.uoff[i + 1]]), initial=0.0) for i in range(g.N)]
        )
        stat[[not np.all(np.isfinite(pg[g.uoff[i] : g.uoff[i + 1]])) for i in range(g.N)]] = np.nan
        return C, stat

    def _progress(self, todo: list[int]):
        """A progress bar over the best-response solves, shown for large problems only."""
        g = self.game
        work = sum(int(g.uoff[i + 1] - g.uoff[i]) for i in todo) * (1 + self.options.global_starts)
        from tqdm.auto import tqdm

        return tqdm(
            total=len(todo),
            desc="Nash certificate: best responses",
            unit="agent",
            disable=None if work >= 400 else True,
            leave=False,
        )

    def _first_order_reasons(self, i, finite_in, finite, stat_ok, stat, scale) -> list[str]:
        """Why agent ``i`` fails the first-order test (empty where it passes)."""
        why = []
        if not finite_in:
            why.append("the controls or parameters are not finite")
        elif not finite[i]:
            why.append("the cost or its gradient is not finite")
        elif not stat_ok[i]:
            why.append(
                f"stationarity {stat[i]:.3g} > stat_tol x (1 + min(|C_i|, scale_cap)) "
                f"= {self.options.stat_tol * scale[i]:.3g}"
            )
        return why

    def _cost(self, i: int, u, p, ui) -> float:
        """``C_i`` with agent ``i``'s controls replaced by ``ui`` (NaN if not finite)."""
        g = self.game
        a, b = int(g.uoff[i]), int(g.uoff[i + 1])
        with np.errstate(all="ignore"):
            c = float(self._costs(np.concatenate([u[:a], ui, u[b:]]), p)[i])
        return c if np.isfinite(c) else np.nan

    def _best_response(self, i: int, u, p, x0) -> _Attempt:
        """IPOPT on agent ``i``'s cost from ``x0`` (its controls), the others' ``u_{-i}``
        fixed."""
        g = self.game
        a, b = int(g.uoff[i]), int(g.uoff[i + 1])
        solver = self.best_response_nlp(i)
        others = np.concatenate([u[:a], u[b:]])
        sol = solver(x0=x0, p=np.concatenate([p, others]))
        st = str(solver.stats().get("return_status", "unknown"))
        ui = np.asarray(sol["x"], dtype=float).reshape(-1)
        return _Attempt(self.method(i), st, st in CONVERGED, self._cost(i, u, p, ui), ui)

    def _lm_best_response(self, i: int, u, p, x0, scale_i: float, newton=True) -> _Attempt:
        """Levenberg-Marquardt on agent ``i``'s residual rows from ``x0``: converged when
        ``|J_i'r_i|_inf <= tol S_i``; it stops after ``max_iter`` iterations, when no step
        lowers ``C_i`` (``max_damping``) or after three steps in a row that lower it by at
        most ``gap_tol S_i / 100`` (``small_decrease``); the Newton test decides then
        (``newton=False``: a search for an improvement only, as from a global start)."""
        o = self.options
        g = self.game
        a, b = int(g.uoff[i]), int(g.uoff[i + 1])
        if i not in self._calls:
            self._calls[i] = BufferCall(self.residual_function(i))
        f = self._calls[i]
        par = np.concatenate([p, u[:a], u[b:]])
        n = b - a

        def lin(x):
            with np.errstate(all="ignore"):
                r, J = f(x, par)
            r, J = r.copy(), J.reshape(n, -1).T.copy()  # J: dense, column-major
            return r, J, 0.5 * float(r @ r)

        if self._pg_call is None:
            self._pg_call = BufferCall(self._pg)
        pg = self._pg_call

        def own_gradient(x):
            with np.errstate(all="ignore"):
                return pg(np.concatenate([u[:a], x, u[b:]]), p)[0][a:b].copy()

        gtol = o.tol * scale_i
        x = np.asarray(x0, float).copy()
        r, J, c = lin(x)
        if not (np.isfinite(c) and np.all(np.isfinite(J))):
            return _Attempt("lm", "nonfinite", False, np.nan, x)
        lam, stop, small = 1e-6, "max_iter", 0
        negligible = 1e-2 * o.gap_tol * scale_i  # a decrease far below the gap tolerance
        for it in range(o.max_iter + 1):
            grad = J.T @ r
            if np.max(np.abs(grad), initial=0.0) <= gtol:
                stop = "gtol"
                break
            if it == o.max_iter:
                break
            H = J.T @ J
            h = max(1.0, float(np.max(np.diag(H), initial=0.0)))
            while lam <= 1e10:
                try:
                    d = np.linalg.solve(H + lam * h * np.eye(x.size), -grad)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                rn, Jn, cn = lin(x + d)
                if np.isfinite(cn) and cn < c:
                    small = small + 1 if c - cn <= negligible else 0
                    x, r, J, c = x + d, rn, Jn, cn
                    lam = max(lam / 10, 1e-12)
                    break
                lam *= 10
            else:
                stop = "max_damping"  # no step lowers C_i
                break
            if small >= 3:  # three steps in a row gained next to nothing
                stop = "small_decrease"
                break
        converged = stop == "gtol"
        if not converged and newton:  # e.g. decreases below round-off: the Newton model decides
            converged, why = self._newton_test(own_gradient, x, o.gap_tol * scale_i)
            stop = f"{stop}; {why}"
        return _Attempt("lm", stop, converged, self._cost(i, u, p, x), x)

    @staticmethod
    def _newton_test(grad, x, gap_tol_i: float) -> tuple[bool, str]:
        """Whether the Newton model of ``C_i`` at ``x`` shows no decrease worth the gap
        tolerance: the Hessian by central differences of the gradient ``dC_i/du_i``
        (``2 n_i`` evaluations of the game's ``pseudo_gradient``) positive definite, the
        Newton step small (``<= 1e-2 (1 + |x|_inf)``) and its predicted decrease
        ``g'H^{-1}g / 2 <= 1e-2 gap_tol S_i``."""
        n = x.size
        g0 = grad(x)
        H = np.empty((n, n))
        for j in range(n):
            h = 1e-5 * (1.0 + abs(x[j]))
            e = np.zeros(n)
            e[j] = h
            H[:, j] = (grad(x + e) - grad(x - e)) / (2 * h)
        H = 0.5 * (H + H.T)
        if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g0))):
            return False, "Newton test: not finite"
        w, V = np.linalg.eigh(H)
        if w[0] <= 1e-10 * max(1.0, abs(w[-1])):
            return False, f"Newton test: Hessian not positive definite (eigenvalue {w[0]:.2g})"
        d = V @ ((V.T @ g0) / w)
        pred = 0.5 * float(g0 @ d)
        if np.max(np.abs(d)) > 1e-2 * (1.0 + np.max(np.abs(x))) or pred > 1e-2 * gap_tol_i:
            return False, f"Newton test: predicted decrease {pred:.2g}"
        return True, f"Newton test passes (predicted decrease {pred:.2g})"


def nash_certificate(
    game: PotentialGame,
    p: np.ndarray,
    u: np.ndarray,
    options: NashOptions | dict | None = None,
) -> NashCertificate:
    """Open-loop Nash certificate of the joint strategy ``u`` (``(n_u,)``) for ``p``
    (``(n_p,)``): local by default, with ``global_starts`` more starts per agent on request.

    Arguments in the solvers' order ``(game, p, u)`` (or as keywords ``p=``, ``u=``). See
    the module docstring for what is measured, the tolerances, the three verdicts and what
    "local" means. ``options``: :class:`NashOptions` or a dict of its
    fields (unknown keys raise :class:`~epo_casadi.errors.SpecError`).
    """
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    t0 = time.perf_counter()
    opts = check_options(NashOptions, options, "nash")
    cert = game.cached(("nash", opts), lambda: NashChecker(game, opts)).certify(p=p, u=u)
    return replace(cert, time_s=time.perf_counter() - t0)  # with the first use's build
