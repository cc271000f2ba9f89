"""One iLQ solve: the iteration of :mod:`solvers.ilq`, step by step.

:class:`SolveOnce` holds the state of one solve (the current trajectory, its linearization,
the running regularization, the line search's memory and the kink continuation) and runs
the iteration: linearize and solve the LQ game (:meth:`SolveOnce.linearize`), try steps
along the feedback policy (:meth:`SolveOnce._line_search`), then accept one, raise the
regularization, or blend the kinks (:mod:`solvers.ilq.kinks`); at the tolerance, judge
it at the requested regularization and the exact kinks (:meth:`SolveOnce._at_tolerance`).
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..codegen import BufferCall as _Call
from ..result import SolveResult, Status, StopReason
from ..stages import from_stages, to_stages
from . import kinks

__all__ = ["SolveOnce"]

_MAX_MU = 1e8  # largest global regularization the adaptive retries reach
_MIN_MU = 1e-4  # first raised regularization; below it, a lowered one returns to mu0
_MAX_RESETS = 2  # returns to the requested regularization before a solve is called stalled
_MIN_STEP = 1e-2  # smallest first trial step the secant predicts (relative to step_size)
_ARMIJO = 0.1  # sufficient decrease of the merit per unit step: (1 - c eps) x reference


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
        a2 = (a * a).ravel().tolist()
        merit = math.sqrt(math.fsum(a2) / len(a2)) if a2 else 0.0
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


def _secant_step(a_old, a_new, eps, cap):
    """First trial step of the next iteration from the last accepted one (a secant).

    Along the last direction the feed-forward went from ``a_old`` to ``a_new`` with step
    ``eps``; with ``rho = <a_new, a_old> / |a_old|^2`` the linear model
    ``a(e) = (1 - e (1 - rho) / eps) a_old`` vanishes at ``e = eps / (1 - rho)`` (at most
    ``cap``). An iteration that overshoots (``a`` flips sign: ``rho = -0.97`` gives about
    half a step) is damped; after a damped step the model is refitted (``rho ~ 0``: it
    fitted, keep the step; ``rho = 1/2``: twice the step). After a full step only a clear
    overshoot (``rho < -1/4``) damps, so an iteration that converges with full steps keeps
    them.
    """
    den = float(np.vdot(a_old, a_old))
    if not den > 0:
        return cap
    rho = float(np.vdot(a_new, a_old)) / den
    if not (math.isfinite(rho) and rho < 1.0) or (eps >= cap and rho >= -0.25):
        return cap
    return min(cap, max(_MIN_STEP * cap, eps / (1.0 - rho)))


def _max(a):
    a = np.asarray(a, float)
    m = float(a.max()) if a.size else 0.0
    if math.isfinite(m):  # the common case, without the masked copy
        return m
    a = a[np.isfinite(a)]
    return float(a.max()) if a.size else 0.0
