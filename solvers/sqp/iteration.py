"""One problem's SQP iteration on a :class:`~solvers.sqp.qp.StagedQP`, step by step.

:class:`SQPRun` holds the state of one solve (the iterate, the merit's penalty ``nu``, the
regularization ``mu``, the QP's multipliers and the histories) and runs the iteration of
:mod:`solvers.sqp`: linearize and solve the QP (:meth:`SQPRun._solve_qp`), test the
first-order conditions at the current point (:meth:`SQPRun._kkt_test`), undo a step
taken below the energy's resolution that made the KKT error worse
(:meth:`SQPRun._revert`), and take a step (:meth:`SQPRun._step`: the step below the
energy's resolution, or the line search on the merit and the adaptation of ``mu``).
"""

from __future__ import annotations

import math

import numpy as np
import osqp

from ..result import Status, StopReason
from .options import SQPOptions
from .qp import StagedQP

__all__ = ["SQPRun"]

_RHO0 = 0.1  # OSQP's default initial rho
_MU_MIN = 1e-6  # smallest mu after a poor step
_MU_MAX = 1e8  # mu beyond which no step is tried any more (stalled)
_FINE = 1e-9  # relative predicted decrease below which a failed line search
# hands the step to the KKT test


class SQPRun:
    """The SQP iteration of problem ``p (n_p,)`` from ``u (n_u,)`` (changed in place) on
    the QP ``qp`` with options ``o``; :meth:`run` returns the per-problem record."""

    def __init__(self, qp: StagedQP, u: np.ndarray, p: np.ndarray, o: SQPOptions):
        self.s, self.p, self.o = qp, p, o
        if qp._radius_param and qp.pairs:  # each problem's radii (radius.<agent> in p)
            r = qp.game.radii(p)
            ij = np.array([(a, b) for a, b, _ in qp.pairs])
            qp.reach = r[ij[:, 0]] + r[ij[:, 1]] + qp._margin
        if qp.u_idx.size:  # start inside the control bounds (a box: projection is exact)
            u[qp.u_idx] = np.clip(u[qp.u_idx], qp.u_lo, qp.u_hi)
        self.u = u
        self.nu_pen = float(o.merit_penalty)
        self.mu = float(o.regularization)  # adapted like LM's damping (see solvers.sqp)
        self.mu_hist: list = []
        self.fine = None  # (point, KKT error) before a step taken below the energy's resolution
        self.hist: list = []
        self.kkt_hist: list = []
        self.alphas: list = []
        self.qp_iters: list = []
        self.polish_hist: list = []
        self.status, self.stop, self.qp_status = Status.MAX_ITER, StopReason.MAX_ITER, ""
        self.kkt = dict(stationarity=math.inf, violation=math.inf, complementarity=math.inf)
        self.y = np.zeros(qp.n_c)
        self.it = 0

    def run(self) -> dict:
        """Iterate until a status is reached; the record :func:`solvers.sqp.solver._stack`
        stacks."""
        s, o = self.s, self.o
        while True:
            Px, q, Ax, E, x, d = (a.copy() for a in s._lin(self.u, self.p, self.mu))
            E = float(E[0])
            self.hist.append(E)
            if not (math.isfinite(E) and np.isfinite(x).all() and np.isfinite(q).all()):
                self.status, self.stop = Status.NONFINITE, StopReason.NONFINITE
                break
            lo, hi = s._bounds(self.u, x, d)
            v = self._solve_qp(Px, q, Ax, lo, hi)
            if v is None:
                break
            viol1, measure = self._kkt_test(q, Ax, lo, hi, x, d)
            if measure is None:
                break
            if self.fine is not None and measure >= self.fine[1]:
                if self._revert():
                    break
                continue
            self.fine = None
            if self.it >= o.max_iter:
                break
            if self._step(v, q, Px, E, viol1, measure):
                break
        return self._record()

    def _solve_qp(self, Px, q, Ax, lo, hi) -> np.ndarray | None:
        """Set OSQP up (first QP) or update and warm-start it, and solve; the QP's solution
        ``v``, or ``None`` with the status set where OSQP fails."""
        s, o = self.s, self.o
        if s.qp is None:
            s._setup(Px, q, Ax, lo, hi)
        else:
            s.qp.update(q=q, l=lo, u=hi, Px=Px, Ax=Ax)
            if self.it == 0:
                s.qp.update_settings(
                    eps_abs=o.eps_abs,
                    eps_rel=o.eps_rel,
                    max_iter=o.qp_max_iter,
                    polishing=o.polish,
                )
                s.qp.update_settings(rho=_RHO0)  # the adapted rho fits the last QP
        sol = s.qp.solve(raise_error=False)
        self.qp_status = qp_status = str(sol.info.status)
        self.polish_hist.append(int(sol.info.status_polish))
        self.qp_iters.append(int(sol.info.iter))
        sv = sol.info.status_val
        S = osqp.SolverStatus
        if sv in (
            S.OSQP_PRIMAL_INFEASIBLE,
            S.OSQP_PRIMAL_INFEASIBLE_INACCURATE,
            S.OSQP_DUAL_INFEASIBLE,
            S.OSQP_DUAL_INFEASIBLE_INACCURATE,
        ):
            self.status, self.stop = Status.INFEASIBLE, f"qp {qp_status}"
            return None
        if sv not in (S.OSQP_SOLVED, S.OSQP_SOLVED_INACCURATE, S.OSQP_MAX_ITER_REACHED):
            self.status, self.stop = Status.FAILED, f"qp {qp_status}"
            return None
        v, self.y = np.asarray(sol.x, float), np.asarray(sol.y, float)
        if not (np.isfinite(v).all() and np.isfinite(self.y).all()):
            self.status, self.stop = Status.NONFINITE, f"qp {qp_status} (non-finite solution)"
            return None
        return v

    def _kkt_test(self, q, Ax, lo, hi, x, d) -> tuple[float, float | None]:
        """The first-order test at the current point (``dv = 0``), multipliers refined on
        the QP's active set: ``(l1 violation, KKT error)``, the error ``None`` (status
        ``CONVERGED``) where the test holds."""
        s, o = self.s, self.o
        self.y = s._multipliers(q, Ax, self.y, lo, hi)
        viol1, viol_inf = s._violation(self.u, x, d)
        kkt = self.kkt = s._kkt(q, Ax, self.y, lo, hi)
        kkt["violation"] = viol_inf
        self.kkt_hist.append(max(kkt["stationarity"], kkt["complementarity"]))
        if (
            kkt["stationarity"] <= o.tol
            and kkt["complementarity"] <= o.tol
            and viol_inf <= o.feas_tol
        ):
            self.status, self.stop = Status.CONVERGED, StopReason.KKT
            return viol1, None
        return viol1, max(kkt["stationarity"], kkt["complementarity"], viol_inf)

    def _revert(self) -> bool:
        """A step taken below the energy's resolution made the KKT error worse: back to the
        previous point with more regularization. True where the solve stops here."""
        self.u, self.fine, self.mu = self.fine[0], None, max(10.0 * self.mu, _MU_MIN)
        self.it += 1
        if self.mu > _MU_MAX or self.it >= self.o.max_iter:
            self.status, self.stop = (
                (Status.STALLED, StopReason.NO_DESCENT)
                if self.mu > _MU_MAX
                else (Status.MAX_ITER, StopReason.MAX_ITER)
            )
            return True
        return False

    def _step(self, v, q, Px, E: float, viol1: float, measure: float) -> bool:
        """Take the QP's step ``du`` (part of ``v``): judged by the line search on the l1
        merit, or, below the energy's resolution, by the next KKT test. True where the
        solve stops here (negligible step, failed line search)."""
        s, o, u = self.s, self.o, self.u
        du = v[s.xcols.size :]
        # l1 merit: penalty above the inequality multipliers
        y_in = np.abs(self.y[s.n_dyn :])
        if y_in.size:
            self.nu_pen = max(self.nu_pen, 1.1 * float(y_in.max()))
        nu_pen = self.nu_pen
        phi = E + nu_pen * viol1
        dphi = float(q @ v) - nu_pen * viol1  # q'v = g'du: the QP's dx follows du
        Pm = s._P0.copy()
        Pm.data = Px
        vPv = float(2.0 * v @ (Pm @ v) - Pm.diagonal() @ (v * v))
        self.it += 1
        if np.max(np.abs(du), initial=0.0) <= o.step_tol * (1 + np.max(np.abs(u), initial=0.0)):
            self.status, self.stop = Status.STALLED, StopReason.STEP_TOL
            return True
        if -dphi <= _FINE * (1 + abs(phi)):
            # the predicted decrease drowns in the rounding of E (or nearly): the line
            # search cannot judge the step; take it and judge it by the KKT error at
            # the next point (reverted, with more regularization, if that is worse)
            self.fine = (u.copy(), measure)
            u = u + du
            if s.u_idx.size:
                u[s.u_idx] = np.clip(u[s.u_idx], s.u_lo, s.u_hi)
            self.u = u
            self.alphas.append(1.0)
            self.mu_hist.append(self.mu)
            return False
        found = self._line_search(du, phi, dphi)
        if found is None:
            self.status, self.stop = Status.STALLED, StopReason.LINE_SEARCH
            return True
        alpha, phi_t, u_try = found
        # the QP model's predicted decrease against the actual one: adapt mu
        pred = -alpha * dphi - 0.5 * alpha * alpha * vPv
        ratio = (phi - phi_t) / pred if pred > 0 else 0.0
        if alpha < 1.0 or ratio < 0.25:
            self.mu = max(10.0 * self.mu, _MU_MIN)
        elif ratio > 0.75:
            self.mu = max(self.mu / 10.0, float(o.regularization))
        self.mu_hist.append(self.mu)
        self.alphas.append(alpha)
        u = u_try
        if s.u_idx.size:  # rounding only: the QP's du keeps u inside the box
            u[s.u_idx] = np.clip(u[s.u_idx], s.u_lo, s.u_hi)
        self.u = u
        return False

    def _line_search(self, du, phi: float, dphi: float):
        """Backtracking (Armijo) on the merit along ``du``: ``(alpha, merit, point)`` of the
        accepted trial, ``None`` where none of ``max_backtracks + 1`` trials is."""
        s, o, u = self.s, self.o, self.u
        alpha = 1.0
        for _ in range(o.max_backtracks + 1):
            u_try = u + alpha * du
            E_t, x_t, d_t = s._eval_merit(u_try, self.p)
            if math.isfinite(E_t) and np.isfinite(x_t).all():
                phi_t = E_t + self.nu_pen * s._violation(u_try, x_t, d_t)[0]
                if phi_t <= phi + o.armijo * alpha * dphi:
                    return alpha, phi_t, u_try
            alpha *= o.backtrack
        return None

    def _record(self) -> dict:
        return dict(
            u=self.u,
            p=self.p,
            status=self.status,
            stop=self.stop,
            iter=self.it,
            history=self.hist,
            qp_status=self.qp_status,
            kkt=self.kkt,
            kkt_history=self.kkt_hist,
            step_sizes=self.alphas,
            qp_iterations=self.qp_iters,
            merit_penalty=self.nu_pen,
            polish=self.polish_hist,
            mu=self.mu_hist,
            y=self.y,
        )
