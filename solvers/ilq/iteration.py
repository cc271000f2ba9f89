"""One iLQ solve: the iteration of :mod:`solvers.ilq`, step by step.

:class:`SolveOnce` holds the state of one solve (the current trajectory, its linearization,
the running regularization, the line search's memory and the kink continuation) and runs
the iteration: linearize and solve the LQ game (:meth:`SolveOnce.linearize`), try steps
along the feedback policy (:meth:`SolveOnce._line_search`), then accept one, raise the
regularization, or blend the kinks (:mod:`solvers.ilq.kinks`); at the tolerance, judge
it at the requested regularization and the exact kinks (:meth:`SolveOnce._at_tolerance`).

:class:`BatchSolve` runs the same iteration for many starts at once (:func:`solve_starts`,
what :func:`solvers.ilq.solve_ilq` uses for a compiled batch): one evaluation per round
for all running starts, each start's result the one :class:`SolveOnce` gives.

Modules. This module holds :class:`SolveOnce`, :class:`BatchSolve` and :func:`solve_starts`;
the pieces live beside it and every name stays importable from here:
:mod:`solvers.ilq.step_rules` (the regularization's limits, the secant of the first trial
step) and :mod:`solvers.ilq.batch_trial` (:func:`batchable`, the evaluations of a round).
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..codegen import BufferCall as _Call
from ..result import SolveResult, Status, StopReason
from ..stages import from_stages, to_stages
from . import kinks
from .batch_trial import _BATCH_FNS as _BATCH_FNS
from .batch_trial import _FINAL as _FINAL
from .batch_trial import _INIT as _INIT
from .batch_trial import _LD_U as _LD_U
from .batch_trial import _RELIN as _RELIN
from .batch_trial import _RESET as _RESET
from .batch_trial import _TRIAL as _TRIAL
from .batch_trial import _batch_functions as _batch_functions
from .batch_trial import _Evaluation as _Evaluation
from .batch_trial import _exact_sums as _exact_sums
from .batch_trial import _MappedTrial as _MappedTrial
from .batch_trial import batchable
from .step_rules import _ARMIJO as _ARMIJO
from .step_rules import _MAX_MU as _MAX_MU
from .step_rules import _MAX_RESETS as _MAX_RESETS
from .step_rules import _MIN_MU as _MIN_MU
from .step_rules import _MIN_STEP as _MIN_STEP
from .step_rules import _max as _max
from .step_rules import _secant_step as _secant_step

__all__ = ["BatchSolve", "SolveOnce", "batchable", "solve_starts"]


class SolveOnce:
    """One iLQ solve of problem ``p (n_p,)`` from ``u0 (n_u,)`` by the solver ``s``, at most
    ``max_iter`` iterations; ``backward`` is the Riccati recursion to use (compiled or
    numpy), ``t0`` the start of the wall time. :meth:`run` returns the result.

    The current linearization is ``C, E, PA, mu, res, merit`` (costs, energy, ``[P | a]``,
    shifts, ``max |a|`` and the merit ``RMS(a)``, both ``inf`` when not finite).
    """

    def __init__(self, s, p, u0, opts, backward, max_iter: int, t0: float):
        self.s, self.p, self.opts, self.backward = s, p, opts, backward
        self.max_iter, self.t0 = max_iter, t0
        _, Ubar = to_stages(s.game, None, u0)
        self.Xbar, self.Ubar = s.rollout(
            p,
            np.zeros((s.K + 1, s.nx)),
            Ubar,
            np.zeros((s.K, s.nu, s.nxs + 1)),
            0.0,
            opts.compiled,
        )
        self.mu0, self.delta = float(opts.regularization), float(opts.min_curvature)
        self.mu_run = self.mu0  # raised 10x when a pass fails, lowered after success
        # kink continuation (ILQOptions.kink_widths): off until the line search fails
        self.widths = list(opts.kink_widths)
        s.kink_width = 0.0
        self.continuation: list = []  # (iteration, width) at every change of the width
        self.it = 0
        self.on_kink = None  # (X, U, width, max |a|): converged while blended, kinks in band
        self.failed_width = 0.0
        self.take(self.relinearize(self.Xbar, self.Ubar))
        self.status = Status.MAX_ITER if math.isfinite(self.res) else Status.NONFINITE
        self.stop = StopReason.MAX_ITER if math.isfinite(self.res) else StopReason.NONFINITE
        self.hist_E, self.hist_res, self.steps = [self.E], [self.res], []
        self.merits = [self.merit]  # merits (RMS of a) at the current regularization
        self.eps_next = float(opts.step_size)  # first trial step of the next iteration
        self.max_mu = _max(self.mu)
        self.resets = 0
        self.rescue = False  # the secant step: only after a line search has failed

    # ---- linearization and regularization ---------------------------------------------
    def linearize(self, X, U, lin=None):
        """``(C, E, PA, mu, res, merit)`` at ``(X, U)`` with the running regularization;
        ``lin``: ``(C, E, PA, mu, ok)`` already computed by the one-call trial."""
        s, opts = self.s, self.opts
        if lin is not None:  # computed by the one-call trial (solvers.fast_ilq)
            C, E, PA, mu, ok = lin
        elif s._trial_fn(opts.compiled) is not None:
            C, E, PA, mu, ok = s._ftrial(self.p, X, U, None, 0.0, self.mu_run, self.delta)[2:]
        else:
            C, E = s.quadratize(X, U, self.p, opts.compiled)
            PA, mu, ok = self.backward(self.mu_run, self.delta)
        a = np.ascontiguousarray(PA[:, :, -1])  # gathered once (feed-forward terms)
        res = float(np.max(np.abs(a))) if s.K else 0.0
        finite = ok and math.isfinite(res) and bool(np.isfinite(C).all())
        # RMS of a; math.fsum is exactly rounded, so the merit (and every accept/reject
        # decision) does not depend on summation order, SIMD alignment or BLAS threads
        with np.errstate(over="ignore"):  # |a| > 1e154: an infinite merit
            a2 = (a * a).ravel().tolist()
        try:
            merit = math.sqrt(math.fsum(a2) / len(a2)) if a2 else 0.0
        except OverflowError:  # finite squares whose sum exceeds the float range
            merit = math.inf
        return C, E, PA, mu, res if finite else math.inf, merit if finite else math.inf

    def take(self, lin) -> None:
        """Make ``lin`` (from :meth:`linearize`) the current linearization."""
        self.C, self.E, self.PA, self.mu, self.res, self.merit = lin

    def bump(self) -> bool:
        """Raise the running regularization 10x; False at the cap."""
        if self.mu_run >= _MAX_MU:
            return False
        self.mu_run = max(10.0 * self.mu_run, _MIN_MU)
        return True

    def relinearize(self, X, U):
        """:meth:`linearize`, with more regularization until the pass is finite."""
        lin = self.linearize(X, U)
        while not math.isfinite(lin[4]) and self.bump():
            lin = self.linearize(X, U)
        return lin

    def set_width(self, w) -> None:
        """Blend the kinks over ``w`` from now on (``0``: exact kinks)."""
        self.s.kink_width = float(w)
        self.continuation.append((self.it, self.s.kink_width))

    # ---- the iteration -------------------------------------------------------------------
    def run(self) -> SolveResult:
        """Iterate until a stop, then the result (the kink report where it stopped on one)."""
        while self.status is Status.MAX_ITER:
            if self.res <= self.opts.tol:
                self._at_tolerance()
                continue
            if self.it >= self.max_iter:
                break
            self._iterate()
        self._unblend()
        kink_info = self._kink_report() if self.stop is StopReason.KINK else None
        return self._result(kink_info)

    def _at_tolerance(self) -> None:
        """``max |a| <= tol``: the next kink width, convergence, or the same trajectory at
        the requested regularization (stalled when it holds only with raised one)."""
        s, opts = self.s, self.opts
        if self.mu_run <= self.mu0 and s.kink_width > 0:
            # converged with blended kinks: the next (smaller) width, then the exact
            # kinks; a width whose band holds no kink argument changes nothing
            w = s.kink_width
            inside = s.kinks_within(self.Xbar, self.Ubar, self.p, w) > 0
            nxt = [v for v in self.widths if v < w] if inside else []
            if inside:  # a blended solution with kinks in its band
                self.on_kink = (self.Xbar, self.Ubar, w, self.res)
            self.set_width(nxt[0] if nxt else 0.0)
            if inside:
                self.take(self.relinearize(self.Xbar, self.Ubar))
                self.merits, self.eps_next = [self.merit], float(opts.step_size)
            return
        if self.mu_run <= self.mu0:  # the tolerance holds at the requested regularization
            self.status, self.stop = Status.CONVERGED, StopReason.TOL
            return
        # judged with the regularization the user asked for, never a raised one
        self.mu_run = self.mu0
        lin = self.linearize(self.Xbar, self.Ubar)
        self.resets += 1
        if not math.isfinite(lin[4]):
            self.status, self.stop = Status.STALLED, StopReason.SINGULAR
            return
        if lin[4] > opts.tol and self.resets > _MAX_RESETS:
            # the tolerance only holds with raised regularization: not a feedback
            # Nash point of the game that was asked for
            self.take(lin)
            self.status, self.stop = Status.STALLED, StopReason.REGULARIZED_ONLY
            return
        self.take(lin)
        self.merits = [self.merit]

    def _iterate(self) -> None:
        """One iteration: the line search, then the next linearization (or a stop)."""
        ref = max(self.merits[-self.opts.memory :])
        a_old = self.PA[:, :, -1]
        accepted = self._line_search(ref)
        self.it += 1
        if accepted is None:  # from now on the first trial step adapts (a secant)
            self.rescue = self.opts.adaptive_step
            nxt = self._no_step()
            if nxt is None:  # stopped
                return
        else:
            nxt = self._accept(accepted, a_old)
        self._record(*nxt)

    def _line_search(self, ref: float):
        """Trial steps ``eps`` from ``eps_next`` (times ``backtrack`` after each rejection):
        ``(X, U, lin, eps)`` of the first accepted one (``lin`` None without the residual
        line search), else None."""
        s, opts, p = self.s, self.opts, self.p
        eps = self.eps_next
        for _trial in range(opts.max_backtracks + 1):
            ft, flin = s._trial_fn(opts.compiled), None
            with np.errstate(all="ignore"):
                if ft is not None and opts.line_search == "residual":
                    Xn, Un, *flin = ft(
                        p, self.Xbar, self.Ubar, self.PA, eps, self.mu_run, self.delta
                    )
                else:
                    Xn, Un = s.rollout(p, self.Xbar, self.Ubar, self.PA, eps, opts.compiled)
                good = bool(np.isfinite(Xn).all() and np.isfinite(Un).all())
                if good and opts.max_state_step < math.inf:
                    good = float(np.max(np.abs(Xn - self.Xbar))) <= opts.max_state_step
            lin = None
            if good and opts.line_search == "residual":
                lin = self.linearize(Xn, Un, flin)
                good = lin[5] <= (1.0 - _ARMIJO * eps) * ref
            if good:
                return (Xn, Un, lin, eps)
            eps *= opts.backtrack
        return None

    def _no_step(self):
        """No trial passed: blend the kinks, stop on a kink, or raise the regularization.
        ``(lin, eps)`` to record, or None when the solve stops."""
        s, opts = self.s, self.opts
        if self.widths and not self.continuation and self.mu_run <= self.mu0 and s.has_kinks:
            # no usable step at the exact kinks: blend their curvature and go on
            self.set_width(self.widths[0])
            lin, eps = self.relinearize(self.Xbar, self.Ubar), 0.0
            self.merits, self.eps_next = [], float(opts.step_size)
            return lin, eps
        if self.on_kink is not None and self.mu_run <= self.mu0 and s.kink_width <= self.widths[-1]:
            # converged with the kinks blended (kinks inside the band), and at the last
            # width or the exact kinks no step passes: the solution sits on a kink, where
            # the one-sided curvatures give different gains (docs/ilq.md)
            self.failed_width = s.kink_width
            self.Xbar, self.Ubar = self.on_kink[0], self.on_kink[1]
            self.status, self.stop = Status.STALLED, StopReason.KINK
            return None
        # no usable step: more regularization, same trajectory
        if not self.bump():
            self.status, self.stop = Status.STALLED, StopReason.LINE_SEARCH
            if self.mu_run > self.mu0:  # report max |a| at the requested regularization
                self.mu_run = self.mu0
                lin = self.linearize(self.Xbar, self.Ubar)
                if math.isfinite(lin[4]):
                    self.take(lin)
            return None
        lin, eps = self.relinearize(self.Xbar, self.Ubar), 0.0
        self.merits = []
        self.eps_next = float(opts.step_size)
        return lin, eps

    def _accept(self, accepted, a_old):
        """Move to the accepted trial; lower a raised regularization. ``(lin, eps)``."""
        self.Xbar, self.Ubar, lin, eps = accepted
        self.eps_next = float(self.opts.step_size)
        if self.rescue and lin is not None and self.mu_run <= self.mu0:
            self.eps_next = _secant_step(a_old, lin[2][:, :, -1], eps, self.eps_next)
        if self.mu_run > self.mu0:  # success: lower the regularization again
            self.mu_run = self.mu_run / 10.0 if self.mu_run / 10.0 >= _MIN_MU else self.mu0
            self.mu_run = max(self.mu_run, self.mu0)
            self.merits = []
        if lin is None or not math.isfinite(lin[4]):
            lin = self.relinearize(self.Xbar, self.Ubar)
        return lin, eps

    def _record(self, lin, eps) -> None:
        """Make ``lin`` current and append it (and the step ``eps``) to the histories."""
        self.take(lin)
        self.merits.append(self.merit)
        self.steps.append(eps)
        self.hist_E.append(self.E)
        self.hist_res.append(self.res)
        self.max_mu = max(self.max_mu, _max(self.mu))
        if not math.isfinite(self.res):
            self.status, self.stop = Status.NONFINITE, StopReason.NONFINITE

    # ---- after the iteration ---------------------------------------------------------------
    def _unblend(self) -> None:
        """Stopped while blended: report ``max |a|`` at the exact kinks."""
        if self.s.kink_width > 0:
            self.set_width(0.0)
            self.mu_run = self.mu0
            lin = self.linearize(self.Xbar, self.Ubar)
            if math.isfinite(lin[4]):
                self.take(lin)

    def _kink_report(self) -> dict:
        """``info["kink_equilibrium"]``: the blended solution, reported (P, a, max |a|) at the
        exact kinks; then (``kink_equilibrium``) the search for an equilibrium on them."""
        s = self.s
        X1, U1, w, res_w = self.on_kink
        s.kink_width = w
        kink_info, sel = kinks.blend_report(s, X1, U1, self.p, w, res_w, self.failed_width)
        # the blended policy (passes the sampled feedback-Nash check on the family games)
        PAw = self.linearize(X1, U1)[2]
        kink_info["gains"] = PAw[:, :, : s.nx].copy()
        kink_info["gains_prev"] = PAw[:, :, s.nx : s.nxs].copy()
        kink_info["feedforward"] = PAw[:, :, s.nxs].copy()
        s.kink_width = 0.0
        self.take(self.linearize(X1, U1))
        kink_info["exact_stationarity"] = self.res
        kink_info["certified"] = False
        if self.opts.kink_equilibrium:  # an equilibrium on the kink (docs/ilq.md)
            self._certify_kinks(kink_info, U1, sel)
        return kink_info

    def _certify_kinks(self, kink_info: dict, U1, sel) -> None:
        """Search for an equilibrium on the kinks ``sel``; found, it is the solution."""
        opts = self.opts
        theta = np.clip([t for _, _, t in kink_info["kinks"]], 0.0, 1.0)
        eq = kinks.kink_equilibrium(self.s, self.p, U1, sel, theta, opts, self.backward)
        kink_info["equilibrium"] = kinks.kink_summary(eq, opts.tol)
        self.it += eq["iterations"]  # the pinned solves' iterations
        if eq["ok"]:
            kink_info["certified"] = True
            kink_info["message"] = kink_info["equilibrium"]["message"]
            self.Xbar, self.Ubar = eq["X"], eq["U"]
            self.C, self.E, self.PA = eq["C"], eq["E"], eq["PA"]
            self.mu, self.res = eq["mu"], eq["stationarity"]
            self.status, self.stop = Status.CONVERGED, StopReason.KINK_EQUILIBRIUM

    def _result(self, kink_info) -> SolveResult:
        """The :class:`solvers.result.SolveResult` at the current trajectory."""
        s, g, p, PA = self.s, self.s.game, self.p, self.PA
        x, u = from_stages(g, self.Xbar, self.Ubar)
        grad_norm = math.nan
        if not s.custom_costs:
            if s._grad is None:  # buffers bound once (a plain call converts to DM)
                s._grad = _Call(g.function("gradient"))
            grad_norm = float(np.max(np.abs(s._grad(u, p)[0]))) if g.n_u else 0.0
        return SolveResult(
            solver="ilq",
            controls=u,
            states=x,
            energy=np.float64(self.E),
            agent_costs=np.asarray(self.C, float).reshape(-1),
            status=self.status,
            iterations=np.int64(self.it),
            energy_history=np.asarray(self.hist_E, float),
            grad_norm=np.float64(grad_norm),
            wall_time=time.perf_counter() - self.t0,
            info={
                "gains": PA[:, :, : s.nx].copy(),
                "gains_prev": PA[:, :, s.nx : s.nxs].copy(),
                "prev_variables": s.aug.copy(),
                "feedforward": PA[:, :, s.nxs].copy(),
                "stationarity": self.res,
                "stop": self.stop,
                "residual_history": np.asarray(self.hist_res, float),
                "step_sizes": np.asarray(self.steps, float),
                "regularization": self.mu,
                "max_regularization": self.max_mu,
                "kink_continuation": self.continuation,
                "kink_equilibrium": kink_info,
                "hessian": s.hessian,
                "custom_costs": s.custom_costs,
                "backend": "compiled" if self.opts.compiled else "numpy",
                "options": self.opts,
            },
        )


def solve_starts(s, P: np.ndarray, U0: np.ndarray, opts) -> list[SolveResult]:
    """Solve problem ``P[b] (n_p,)`` from ``U0[b] (n_u,)`` for every ``b``: per start the
    result of ``s.solve(P[b], U0[b], opts)``.

    Where :func:`batchable`, all starts iterate together (:class:`BatchSolve`), the rare
    branches (kink blending, the restart from the open-loop equilibrium) per start; else
    one solve after the other. ``s``: the :class:`solvers.ilq.ILQSolver` of
    :func:`solvers.ilq.get_solver` for ``opts``.
    """
    if opts.compiled:
        s.compile()
    if P.shape[0] < 2 or not batchable(s, opts):
        return [s.solve(P[b], U0[b], opts) for b in range(P.shape[0])]
    t0 = time.perf_counter()
    runs = BatchSolve(s, P, U0, opts, s.backward, t0).run()
    out = []
    for b, run in enumerate(runs):
        res = s._solve_once(P[b], U0[b], opts, s.backward, opts.max_iter, t0, once=run)
        out.append(s._restart(res, P[b], U0[b], opts, s.backward, t0))
    return out


class BatchSolve:
    """The iteration of :class:`SolveOnce` for ``B`` starts at once: problems
    ``P (B, n_p)`` from ``U0 (B, n_u)``, each start with its own trajectory,
    regularization, step size, line-search memory and stop.

    Every round evaluates the pending trial (or linearization) of every running start in
    one mapped call of the compiled one-call trial (:class:`_Evaluation`), then moves each
    start on by the rules of :class:`SolveOnce` (line search, acceptance, regularization,
    judging at the tolerance) until its next evaluation or its stop. The numbers are the
    per-start solve's: the same compiled function on the same inputs, the same merit
    (exactly rounded), the same decisions. A start whose line search fails where
    :meth:`SolveOnce._no_step` would blend kinks continues alone from that point as a
    :class:`SolveOnce`. :meth:`run` returns per start a callable giving its result
    (``SolveOnce.run``). ``trial``: the evaluation of the trials (default: the solver's
    :class:`solvers.fast_ilq.CompiledWideTrial`, else :class:`_MappedTrial`).
    """

    def __init__(self, s, P, U0, opts, backward, t0: float, trial=None):
        self.s, self.opts, self.backward, self.t0 = s, opts, backward, t0
        self.trial, roll = _batch_functions(s)
        if trial is not None:  # another evaluation of the one-call trial (tests)
            self.trial = trial
        self.member = s._ftrial.quad.member
        K, nx, nu, nxs, na, N = s.K, s.nx, s.nu, s.nxs, s.na, s.N
        self.P = np.ascontiguousarray(P, dtype=float)
        B = self.B = self.P.shape[0]
        self.x0 = self.P[:, s._x0_idx]
        _, Ubar = to_stages(s.game, None, np.asarray(U0, float))
        # the starts' rollouts (SolveOnce.__init__): Xr = 0, P = 0, eps = 0
        S, U = roll(
            np.concatenate([self.x0, np.zeros((B, na))], axis=1),
            np.zeros((B, K * nx)),
            np.ascontiguousarray(Ubar).reshape(B, -1),
            np.zeros((B, K * nu * (nxs + 1))),
            np.zeros((B, K)),
        )
        self.X = np.empty((B, K + 1, nx))
        self.X[:, 0] = self.x0
        self.X[:, 1:] = S.reshape(B, K, nx + na)[:, :, :nx]
        self.U = U.reshape(B, K, nu).copy()
        # the current linearization per start
        self.PA = np.zeros((B, K, nu, nxs + 1))
        self.mu = np.zeros((B, K, N))
        self.r = np.zeros((B, self.member.shape[1]))
        self.E = [math.nan] * B
        self.res = [math.inf] * B
        self.merit = [math.inf] * B
        # the per-start state of SolveOnce
        self.mu0, self.delta = float(opts.regularization), float(opts.min_curvature)
        self.mu_run = [self.mu0] * B
        self.it = [0] * B
        self.status = [Status.MAX_ITER] * B
        self.stop = [StopReason.MAX_ITER] * B
        self.hist_E: list[list] = [[] for _ in range(B)]
        self.hist_res: list[list] = [[] for _ in range(B)]
        self.steps: list[list] = [[] for _ in range(B)]
        self.merits: list[list] = [[] for _ in range(B)]
        self.eps_next = [float(opts.step_size)] * B
        self.max_mu = [0.0] * B
        self.resets = [0] * B
        self.rescue = [False] * B
        # the pending evaluation: its phase, trial step, rejected trials, reference merit
        self.phase = [_INIT] * B
        self.eps = [0.0] * B
        self.trials = [0] * B
        self.ref = [math.inf] * B
        self.runs: list = [None] * B
        # takes and accepted trials of the current round: start -> row of the evaluation
        self._pending_lin: dict[int, int] = {}
        self._pending_xu: dict[int, int] = {}
        self._ev = None

    def run(self) -> list:
        """Iterate every start to its stop; per start a callable giving its result."""
        s = self.s
        s.kink_width = 0.0
        pending = list(range(self.B))
        while pending:
            # non-finite numbers are detected per start; numpy's warnings would repeat that
            with np.errstate(all="ignore"):
                ev = self._ev = _Evaluation(self, pending)
            pending = [b for j, b in enumerate(pending) if self._advance(b, j, ev)]
            self._flush(ev)
        for b in range(self.B):
            if self.runs[b] is None:
                self.runs[b] = self._once(b).run
        return self.runs

    # ---- one start ----------------------------------------------------------------------
    def _advance(self, b: int, j: int, ev: _Evaluation) -> bool:
        """Move start ``b`` on with its evaluation ``ev[j]``; True when it waits for the next."""
        opts, ph = self.opts, self.phase[b]
        res = float(ev.res[j])
        if ph == _INIT:  # SolveOnce.__init__: relinearize, then the histories
            if not math.isfinite(res) and self._bump(b):
                return True
            self._take(b, j, ev)
            fin = math.isfinite(res)
            self.status[b] = Status.MAX_ITER if fin else Status.NONFINITE
            self.stop[b] = StopReason.MAX_ITER if fin else StopReason.NONFINITE
            self.hist_E[b], self.hist_res[b] = [self.E[b]], [res]
            self.merits[b] = [self.merit[b]]
            self.max_mu[b] = _max(ev.mu[j])
            return self._loop(b)
        if ph == _RESET:  # SolveOnce._at_tolerance, after the linearization at mu0
            self.resets[b] += 1
            if not math.isfinite(res):
                self.status[b], self.stop[b] = Status.STALLED, StopReason.SINGULAR
                return False
            self._take(b, j, ev)
            if res > opts.tol and self.resets[b] > _MAX_RESETS:
                self.status[b], self.stop[b] = Status.STALLED, StopReason.REGULARIZED_ONLY
                return False
            self.merits[b] = [self.merit[b]]
            return self._loop(b)
        if ph == _TRIAL:  # SolveOnce._line_search
            eps = self.eps[b]
            if ev.good[j] and ev.merit[j] <= (1.0 - _ARMIJO * eps) * self.ref[b]:
                self.it[b] += 1
                self._accept(b, j, ev, eps)
                return self._loop(b)
            self.trials[b] += 1
            self.eps[b] = eps * opts.backtrack
            if self.trials[b] <= opts.max_backtracks:
                return True
            self.it[b] += 1  # SolveOnce._iterate, no trial passed: SolveOnce._no_step
            self.rescue[b] = opts.adaptive_step
            if self.mu_run[b] <= self.mu0 and opts.kink_widths and self.s.has_kinks:
                self._hand_off(b)
                return False
            if not self._bump(b):
                self.status[b], self.stop[b] = Status.STALLED, StopReason.LINE_SEARCH
                if self.mu_run[b] > self.mu0:  # max |a| at the requested regularization
                    self.mu_run[b] = self.mu0
                    self.phase[b] = _FINAL
                    return True
                return False
            self.phase[b] = _RELIN
            return True
        if ph == _RELIN:  # SolveOnce.relinearize after a raised regularization
            if not math.isfinite(res) and self._bump(b):
                return True
            self.merits[b] = []
            self.eps_next[b] = float(opts.step_size)
            self._record(b, j, ev, 0.0)
            return self._loop(b)
        if math.isfinite(res):  # _FINAL
            self._take(b, j, ev)
        return False

    def _loop(self, b: int) -> bool:
        """The top of :meth:`SolveOnce.run` for start ``b``: its stop, or its next
        evaluation (True)."""
        if self.status[b] is not Status.MAX_ITER:
            return False
        if self.res[b] <= self.opts.tol:  # SolveOnce._at_tolerance (the kinks are exact)
            if self.mu_run[b] <= self.mu0:
                self.status[b], self.stop[b] = Status.CONVERGED, StopReason.TOL
                return False
            self.mu_run[b] = self.mu0
            self.phase[b] = _RESET
            return True
        if self.it[b] >= self.opts.max_iter:
            return False
        self.ref[b] = max(self.merits[b][-self.opts.memory :])
        self.eps[b], self.trials[b] = self.eps_next[b], 0
        self.phase[b] = _TRIAL
        return True

    def _take(self, b, j, ev) -> None:
        """Make ``ev[j]`` start ``b``'s linearization (its arrays at :meth:`_flush`)."""
        self._pending_lin[b] = j
        self.E[b], self.res[b], self.merit[b] = float(ev.E[j]), float(ev.res[j]), float(ev.merit[j])

    def _flush(self, ev) -> None:
        """Copy the round's taken linearizations and accepted trajectories from ``ev``."""
        for pend, names in ((self._pending_lin, ("PA", "mu", "r")), (self._pending_xu, ("X", "U"))):
            if pend:
                bs, js = list(pend), list(pend.values())
                for name in names:
                    getattr(self, name)[bs] = getattr(ev, name)[js]
                pend.clear()

    def _bump(self, b) -> bool:
        if self.mu_run[b] >= _MAX_MU:
            return False
        self.mu_run[b] = max(10.0 * self.mu_run[b], _MIN_MU)
        return True

    def _accept(self, b, j, ev, eps) -> None:
        """:meth:`SolveOnce._accept` and :meth:`SolveOnce._record` of the trial ``ev[j]``."""
        opts = self.opts
        self._pending_xu[b] = j  # the trial's trajectory (copied at _flush)
        self.eps_next[b] = float(opts.step_size)
        if self.rescue[b] and self.mu_run[b] <= self.mu0:
            a_old, a_new = self.PA[b][:, :, -1], ev.PA[j][:, :, -1]
            self.eps_next[b] = _secant_step(a_old, a_new, eps, self.eps_next[b])
        if self.mu_run[b] > self.mu0:  # success: lower the regularization again
            mu = self.mu_run[b] / 10.0 if self.mu_run[b] / 10.0 >= _MIN_MU else self.mu0
            self.mu_run[b] = max(mu, self.mu0)
            self.merits[b] = []
        self._record(b, j, ev, eps)

    def _record(self, b, j, ev, eps) -> None:
        self._take(b, j, ev)
        self.merits[b].append(self.merit[b])
        self.steps[b].append(eps)
        self.hist_E[b].append(self.E[b])
        self.hist_res[b].append(self.res[b])
        self.max_mu[b] = max(self.max_mu[b], _max(ev.mu[j]))
        if not math.isfinite(self.res[b]):
            self.status[b], self.stop[b] = Status.NONFINITE, StopReason.NONFINITE

    def _once(self, b: int) -> SolveOnce:
        """Start ``b``'s state as a :class:`SolveOnce` (to continue it or read its result)."""
        s, opts = self.s, self.opts
        so = SolveOnce.__new__(SolveOnce)
        so.s, so.p, so.opts, so.backward = s, self.P[b], opts, self.backward
        so.max_iter, so.t0 = opts.max_iter, self.t0
        so.Xbar, so.Ubar = self.X[b].copy(), self.U[b].copy()
        so.mu0, so.delta, so.mu_run = self.mu0, self.delta, self.mu_run[b]
        so.widths, so.continuation = list(opts.kink_widths), []
        so.it, so.on_kink, so.failed_width = self.it[b], None, 0.0
        with np.errstate(over="ignore", invalid="ignore"):  # as non-finite as it is
            so.C, so.E = 0.5 * (self.member @ (self.r[b] * self.r[b])), self.E[b]
        so.PA, so.mu = self.PA[b].copy(), self.mu[b].copy()
        so.res, so.merit = self.res[b], self.merit[b]
        so.status, so.stop = self.status[b], self.stop[b]
        so.hist_E, so.hist_res, so.steps = self.hist_E[b], self.hist_res[b], self.steps[b]
        so.merits, so.eps_next, so.max_mu = self.merits[b], self.eps_next[b], self.max_mu[b]
        so.resets, so.rescue = self.resets[b], self.rescue[b]
        s.kink_width = 0.0
        return so

    def _hand_off(self, b: int) -> None:
        """Start ``b`` goes on alone (kink blending: :meth:`SolveOnce._no_step`), to its end
        now (the blend width is the solver's, one solve at a time)."""
        self._flush(self._ev)
        so = self._once(b)
        nxt = so._no_step()
        if nxt is not None:
            so._record(*nxt)
        result = so.run()
        self.runs[b] = lambda: result
