"""Gauss-Newton SQP on OSQP: the potential game with hard constraints.

Shapes and index order follow the contract in :mod:`epo_casadi.game`. The problem is ::

    min_u  E(u, p) = 1/2 ||r(u, p)||^2
    s.t.   lower_i <= u_{i,k} <= upper_i                (control_bounds, every k = 0..K-1)
           lower_i <= x_{i,k} <= upper_i                (state_bounds, every k = 1..K)
           |pos_a(x_{a,k}) - pos_b(x_{b,k})| >= r_a + r_b + margin
                                                        (collision=True: every pair, k = 1..K)

with the bounds in the shapes of :class:`solvers.ipopt.IpoptOptions` and the distance the
collision feature's (``epo_casadi.features.smooth_distance``). The soft terms of the game
(the collision penalty included) stay in ``E``.

One iteration, at the rolled-out iterate ``(x(u), u)``
    The QP is *stage-structured* (sparse): its variables are ``v = (dx, du)`` with ``dx``
    every state entry of stages ``k = 1..K`` (``dx_0 = 0``), and ::

        min_v  1/2 v' (G'G + mu_u) v + (G'r)' v         G = [R_x  R_u]: the partial Jacobian
        s.t.   dx_{k+1} = A_k dx_k + B_k du_k            of traj_residual(x, u, p)
               lower - u <= du <= upper - u
               lower - x <= dx <= upper - x
               d + D v >= r_a + r_b + margin             (the linearized distances)

    Eliminating ``dx`` gives the Gauss-Newton step of single shooting,
    ``min 1/2 ||r + J du||^2`` with ``J = R_x dx/du + R_u``, so without constraints the
    step is LM's with damping ``regularization``; kept in stage form, ``G'G`` and the
    constraint matrix are sparse (banded in time) where the condensed ``J'J`` is dense.
    The QP's structure (the sparsity of ``P`` and ``A``) depends only on the game and the
    options, so OSQP is set up **once** per :class:`SQPSolver` and every later QP, in this
    solve and in later calls, is an ``update(q, l, u, Px, Ax)`` of the same object,
    warm-started from the previous QP's primal and dual solution.

Step and merit
    ``u <- u + alpha du`` (rolled out again: the iterate stays dynamically feasible), with
    ``alpha`` from a backtracking (Armijo) line search on the l1 merit
    ``phi(u) = E(u) + nu * viol(u)``, ``viol`` the sum of all constraint violations and
    ``nu >= 1.1 max |y|`` (QP multipliers of the inequality rows, raised when needed).
    The regularization ``mu_u`` of the controls' block adapts like LM's damping: x10
    after a shortened step or a poor ratio of actual to predicted decrease, /10 (down to
    ``regularization``) after a good one; plain Gauss-Newton can diverge slowly near a
    minimizer with large residuals, the damped step does not. Where the predicted decrease
    is below what ``E`` resolves (``1e-9`` relative), the full step is taken and judged by
    the KKT error at the next point instead: if that is larger, the step is undone and
    ``mu_u`` raised (``stalled`` once it passes ``1e8``).

Statuses
    * ``CONVERGED``: the first-order (KKT) test holds: ``max |q + A'y| <= tol`` (the
      stationarity of the Lagrangian in ``v``, with the QP's multipliers ``y``),
      ``viol_inf <= feas_tol`` and complementarity ``max |y_j| slack_j <= tol``.
    * ``INFEASIBLE``: OSQP reports the QP primal or dual infeasible; OSQP's reason is
      ``info["qp_status"]`` and part of ``info["stop"]``.
    * ``MAX_ITER``: ``max_iter`` iterations without meeting the test.
    * ``STALLED``: the line search finds no decrease of the merit (or the step is
      negligible) while the KKT test fails.
    * ``NONFINITE``: NaN or inf in the energy, states or the QP's solution; ``FAILED``:
      another OSQP failure (non-convex, unsolved, interrupted). A QP stopped at OSQP's
      iteration limit still gives a step (``info["qp_status"]`` says so); the line search
      and the KKT test judge it.

A batch ``(B, n)`` is solved problem by problem (a loop) with the same OSQP object and
returned as one batched result, like :func:`solvers.ipopt.solve_ipopt`.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import casadi as ca
import numpy as np
import osqp
import scipy.sparse as sps
import scipy.sparse.linalg as spla

from epo_casadi.errors import SpecError, check_bool, check_number
from epo_casadi.features import smooth_distance
from epo_casadi.game import PotentialGame

from .ipopt import Bounds, _normalize_bounds
from .lm import MAX_STEPS, check_options
from .result import SolveResult, Status, demote_nonfinite

__all__ = ["SQPOptions", "SQPSolver", "solve_sqp"]

_RHO0 = 0.1  # OSQP's default initial rho
_ACTIVE = 1e-6  # a constraint this close to its bound at dv = 0 counts as active
_MU_MIN = 1e-6  # smallest mu after a poor step
_MU_MAX = 1e8  # mu beyond which no step is tried any more (stalled)
_FINE = 1e-9  # relative predicted decrease below which a failed line search
# hands the step to the KKT test
_ROUND = 1e-14  # merit changes below this (relative) are rounding
_INF = 1e30  # OSQP's infinity (OSQP_INFTY)


@dataclass(frozen=True)
class SQPOptions:
    """Options of :func:`solve_sqp` (defaults: a tight solve without hard constraints).

    ``control_bounds`` / ``state_bounds``: as in :class:`solvers.ipopt.IpoptOptions`
    (``{agent: (lower list, upper list)}``, ``None``/``inf`` for no bound).
    """

    max_iter: int = 200  #: SQP iterations (QP solves with an accepted step)
    tol: float = 1e-7  #: KKT tolerance: stationarity and complementarity (inf-norms)
    feas_tol: float = 1e-7  #: largest constraint violation at a converged point
    control_bounds: Bounds | dict | None = None  #: hard bounds on u_{i,k}, per agent
    state_bounds: Bounds | dict | None = None  #: hard bounds on x_{i,k}, k = 1..K, per agent
    collision: bool = False  #: hard distance constraints for every pair at every step k = 1..K
    collision_margin: float = 0.0  #: safety distance (m) added to r_a + r_b in the constraint
    regularization: float = 1e-9  #: smallest mu_u on the controls' diagonal of the QP Hessian
    merit_penalty: float = 1.0  #: initial nu of the l1 merit (raised to 1.1 max |y|)
    armijo: float = 1e-4  #: sufficient-decrease factor of the line search
    backtrack: float = 0.5  #: factor on alpha after a rejected trial
    max_backtracks: int = 30  #: trials before the line search gives up (status stalled)
    step_tol: float = 1e-13  #: a step max|alpha du| <= step_tol (1 + max|u|) is negligible
    eps_abs: float = 1e-7  #: OSQP absolute tolerance
    eps_rel: float = 1e-7  #: OSQP relative tolerance
    qp_max_iter: int = 20000  #: OSQP iterations per QP
    polish: bool = True  #: OSQP solution polishing (an exact active-set step)

    def __post_init__(self):
        for name in ("max_iter", "max_backtracks", "qp_max_iter"):
            check_number(f"sqp.{name}", getattr(self, name), lo=0, hi=MAX_STEPS, integer=True)
        for name in ("tol", "feas_tol", "eps_abs", "eps_rel", "armijo", "merit_penalty"):
            check_number(f"sqp.{name}", getattr(self, name), lo=0, lo_open=True)
        for name in ("regularization", "collision_margin", "step_tol"):
            check_number(f"sqp.{name}", getattr(self, name), lo=0)
        check_number("sqp.backtrack", self.backtrack, lo=0, hi=1, lo_open=True)
        if self.backtrack >= 1:
            raise SpecError("sqp.backtrack", f"expected 0 < backtrack < 1, got {self.backtrack}")
        if self.armijo >= 0.5:
            raise SpecError("sqp.armijo", f"expected 0 < armijo < 0.5, got {self.armijo}")
        check_bool("sqp.collision", self.collision)
        check_bool("sqp.polish", self.polish)
        object.__setattr__(
            self, "control_bounds", _normalize_bounds(self.control_bounds, "sqp.control_bounds")
        )
        object.__setattr__(
            self, "state_bounds", _normalize_bounds(self.state_bounds, "sqp.state_bounds")
        )

    def structure(self) -> tuple:
        """What decides the QP's sparsity (and the CasADi functions): the cache key."""
        return (self.control_bounds, self.state_bounds, self.collision, self.collision_margin)


def _bound_rows(game: PotentialGame, bounds, sizes, offsets, per_stage, first, field):
    """(flat indices, lower, upper) of the bounded entries, every stage from ``first``."""
    names = game.agent_names
    idx, lo_all, hi_all = [], [], []
    for name, lo, hi in bounds or ():
        where = f"sqp.{field}[{name!r}]"
        if name not in names:
            raise SpecError(where, f"unknown agent; expected one of {names}")
        i = names.index(name)
        if len(lo) != sizes[i]:
            raise SpecError(
                where, f"expected {sizes[i]} entries per list for agent {name!r}, got {len(lo)}"
            )
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        comp = np.flatnonzero(np.isfinite(lo) | np.isfinite(hi))
        for k in range(first, per_stage):
            idx.append(int(offsets[i]) + k * sizes[i] + comp)
            lo_all.append(lo[comp])
            hi_all.append(hi[comp])
    if not idx:
        return np.zeros(0, int), np.zeros(0), np.zeros(0)
    return np.concatenate(idx), np.concatenate(lo_all), np.concatenate(hi_all)


class _Buffered:
    """A ``casadi.Function`` called on numpy arrays through its buffer interface; every
    output comes back as its nonzeros (the order of its CSC sparsity)."""

    def __init__(self, f: ca.Function):
        self.f = f
        self.buf, self.ev = f.buffer()
        self.outs = [np.empty(f.nnz_out(i)) for i in range(f.n_out())]
        for i, o in enumerate(self.outs):
            self.buf.set_res(i, memoryview(o))
        self._ins: list = [None] * f.n_in()

    def __call__(self, *args) -> list[np.ndarray]:
        for i, a in enumerate(args):
            a = np.ascontiguousarray(a, dtype=np.float64).reshape(-1)
            if a.size != self.f.nnz_in(i):
                raise ValueError(f"{self.f.name()}: input {i} needs {self.f.nnz_in(i)} numbers")
            self._ins[i] = a  # kept alive while CasADi reads it
            self.buf.set_arg(i, memoryview(a))
        self.ev()
        return self.outs


def _csc(sp: ca.Sparsity, shape) -> sps.csc_matrix:
    """A scipy CSC matrix with CasADi's pattern ``sp`` (values 1; nonzeros in the same order)."""
    return sps.csc_matrix(
        (np.ones(sp.nnz()), np.asarray(sp.row()), np.asarray(sp.colind())), shape=shape
    )


class SQPSolver:
    """The SQP of one game and one :class:`SQPOptions` structure; OSQP set up once.

    ``solver.solve(p, u0, options)`` solves one problem or a batch (a loop). Attributes:
    ``n_v`` (QP variables), ``n_c`` (QP constraint rows), ``setups`` (OSQP set-ups so far:
    1 after the first solve, whatever the number of solves), ``qp`` (the ``osqp.OSQP``).
    """

    def __init__(self, game: PotentialGame, options: SQPOptions | dict | None = None):
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        self.game = game
        self.options = opts = check_options(SQPOptions, options, "sqp")
        K = game.K
        u = ca.SX.sym("u", game.n_u)
        p = ca.SX.sym("p", game.n_p)
        x = ca.SX.sym("x", game.n_x)
        reg = ca.SX.sym("reg")
        # state entries of stages 1..K: the QP's dx (flat x order)
        xcols = np.concatenate(
            [int(game.xoff[i]) + np.arange(game.nx[i], (K + 1) * game.nx[i]) for i in range(game.N)]
        ).astype(int)
        self.xcols = xcols
        n_dx, n_u = xcols.size, game.n_u
        self.n_v = n_dx + n_u
        # bounds: entries of u (flat) and of x (flat, stages 1..K)
        self.u_idx, self.u_lo, self.u_hi = _bound_rows(
            game, opts.control_bounds, game.nu, game.uoff, K, 0, "control_bounds"
        )
        self.x_idx, self.x_lo, self.x_hi = _bound_rows(
            game, opts.state_bounds, game.nx, game.xoff, K + 1, 1, "state_bounds"
        )
        xpos = np.full(game.n_x, -1)
        xpos[xcols] = np.arange(n_dx)
        # symbolic pieces at (x, u, p); x is substituted by the rollout below
        r = game.function("traj_residual")(x, u, p)
        Jx = ca.jacobian(r, x)[:, xcols.tolist()]
        G = ca.horzcat(Jx, ca.jacobian(r, u))
        defects = []
        Xs = [
            ca.reshape(x[int(game.xoff[i]) : int(game.xoff[i + 1])], game.nx[i], K + 1)
            for i in range(game.N)
        ]
        Us = [
            ca.reshape(u[int(game.uoff[i]) : int(game.uoff[i + 1])], game.nu[i], K)
            for i in range(game.N)
        ]
        # each agent's own dynamics, or its coupling's joint model (game.agent_steps)
        nxt = [game.agent_steps([X[:, k] for X in Xs], [U[:, k] for U in Us]) for k in range(K)]
        for i in range(game.N):
            for k in range(K):
                defects.append(Xs[i][:, k + 1] - nxt[k][i])
        defect = ca.vertcat(*defects)
        v_sym = [x, u]
        Ddyn = ca.horzcat(ca.jacobian(defect, x)[:, xcols.tolist()], ca.jacobian(defect, u))
        dists, reach, pairs = [], [], []
        radii = game.radii()  # the defaults; a game with radius parameters: set per solve
        if opts.collision:
            for a in range(game.N):
                for b in range(a + 1, game.N):
                    da, db = game.agents[a].dynamics, game.agents[b].dynamics
                    rr = radii[a] + radii[b] + opts.collision_margin
                    for k in range(1, K + 1):
                        xa = x[
                            int(game.xoff[a]) + k * game.nx[a] : int(game.xoff[a])
                            + (k + 1) * game.nx[a]
                        ]
                        xb = x[
                            int(game.xoff[b]) + k * game.nx[b] : int(game.xoff[b])
                            + (k + 1) * game.nx[b]
                        ]
                        dists.append(smooth_distance(da.position(xa), db.position(xb)))
                        reach.append(rr)
                        pairs.append((a, b, k))
        dist = ca.vertcat(*dists) if dists else ca.SX(0, 1)
        self.reach = np.asarray(reach, float)
        self.pairs = pairs
        self._radius_param = any(ag.radius_param for ag in game.agents)
        self._margin = float(opts.collision_margin)
        Ddist = ca.jacobian(dist, ca.vertcat(*v_sym))
        # reorder Ddist columns to v = (x[xcols], u)
        Ddist = ca.horzcat(
            Ddist[:, xcols.tolist()], Ddist[:, list(range(game.n_x, game.n_x + n_u))]
        )
        n_dyn = defect.shape[0]
        Sel_u = (
            ca.DM(
                sps.csc_matrix(
                    (np.ones(self.u_idx.size), (np.arange(self.u_idx.size), n_dx + self.u_idx)),
                    shape=(self.u_idx.size, self.n_v),
                )
            )
            if self.u_idx.size
            else ca.DM(0, self.n_v)
        )
        Sel_x = (
            ca.DM(
                sps.csc_matrix(
                    (np.ones(self.x_idx.size), (np.arange(self.x_idx.size), xpos[self.x_idx])),
                    shape=(self.x_idx.size, self.n_v),
                )
            )
            if self.x_idx.size
            else ca.DM(0, self.n_v)
        )
        A = ca.vertcat(Ddyn, ca.SX(Sel_u), ca.SX(Sel_x), Ddist)
        self.n_dyn, self.n_c = n_dyn, A.shape[0]
        self.rows_u = slice(n_dyn, n_dyn + self.u_idx.size)
        self.rows_x = slice(self.rows_u.stop, self.rows_u.stop + self.x_idx.size)
        self.rows_d = slice(self.rows_x.stop, self.n_c)
        H = ca.mtimes(G.T, G)
        H = H + ca.diag(ca.vertcat(ca.SX(n_dx, 1), reg * ca.SX.ones(n_u)))
        P = ca.triu(H)
        q = ca.mtimes(G.T, r)
        E = 0.5 * ca.sumsqr(r)
        # substitute the rollout: every function takes (u, p)
        xr = game.symbols["x"]
        u_g, p_g = game.symbols["u"], game.symbols["p"]
        sub = ca.Function("sub", [x, u, p, reg], [P, q, A, E, r, dist, defect])
        P_r, q_r, A_r, E_r, r_r, d_r, _ = sub(xr, u_g, p_g, reg)
        self._lin = _Buffered(
            ca.Function(
                "sqp_qp",
                [u_g, p_g, reg],
                [P_r, ca.densify(q_r), A_r, ca.densify(E_r), ca.densify(xr), ca.densify(d_r)],
                ["u", "p", "reg"],
                ["P", "q", "A", "E", "x", "dist"],
            )
        )
        self._merit = _Buffered(
            ca.Function(
                "sqp_merit",
                [u_g, p_g],
                [ca.densify(E_r), ca.densify(xr), ca.densify(d_r)],
                ["u", "p"],
                ["E", "x", "dist"],
            )
        )
        self.P_sp, self.A_sp = self._lin.f.sparsity_out(0), self._lin.f.sparsity_out(2)
        self._P0 = _csc(self.P_sp, (self.n_v, self.n_v))
        self._A0 = _csc(self.A_sp, (self.n_c, self.n_v))
        self._costs = game.function("agent_costs")
        self._grad = game.function("gradient")
        self.qp: osqp.OSQP | None = None
        self.setups = 0

    def prepare(self, p: np.ndarray, u0: np.ndarray | None = None) -> SQPSolver:
        """Evaluate the QP's functions once at ``(u0, p)`` and set OSQP up (if not yet):
        the whole first-call cost, so that a timed solve afterwards is the solve alone."""
        g = self.game
        U0, P = g.check_inputs(g.zero_controls() if u0 is None else u0, p)
        u = U0[0].copy()
        if self.u_idx.size:
            u[self.u_idx] = np.clip(u[self.u_idx], self.u_lo, self.u_hi)
        Px, q, Ax, _E, x, d = (a.copy() for a in self._lin(u, P[0], self.options.regularization))
        self._eval_merit(u, P[0])
        if self.qp is None:
            self._setup(Px, q, Ax, *self._bounds(u, x, d))
        return self

    # ---- numbers --------------------------------------------------------------------------
    def _setup(self, Px, q, Ax, lo, hi):
        o = self.options
        P = self._P0.copy()
        P.data = Px
        A = self._A0.copy()
        A.data = Ax
        self.qp = osqp.OSQP()
        self.qp.setup(
            P,
            q,
            A,
            lo,
            hi,
            eps_abs=o.eps_abs,
            eps_rel=o.eps_rel,
            eps_prim_inf=1e-9,
            eps_dual_inf=1e-9,
            max_iter=o.qp_max_iter,
            polishing=o.polish,
            warm_starting=True,
            verbose=False,
        )
        self.setups += 1

    def _violation(self, u, x, d) -> tuple[float, float]:
        """(l1, inf) norms of the constraint violation at ``(x, u)``."""
        parts = [
            np.maximum(self.u_lo - u[self.u_idx], 0.0),
            np.maximum(u[self.u_idx] - self.u_hi, 0.0),
            np.maximum(self.x_lo - x[self.x_idx], 0.0),
            np.maximum(x[self.x_idx] - self.x_hi, 0.0),
            np.maximum(self.reach - d, 0.0),
        ]
        v = np.concatenate(parts)
        if v.size == 0:
            return 0.0, 0.0
        return float(v.sum()), float(v.max())

    def _bounds(self, u, x, d):
        lo = np.concatenate(
            [
                np.zeros(self.n_dyn),
                self.u_lo - u[self.u_idx],
                self.x_lo - x[self.x_idx],
                self.reach - d,
            ]
        )
        hi = np.concatenate(
            [
                np.zeros(self.n_dyn),
                self.u_hi - u[self.u_idx],
                self.x_hi - x[self.x_idx],
                np.full(d.size, np.inf),
            ]
        )
        return np.clip(lo, -_INF, _INF), np.clip(hi, -_INF, _INF)

    def _multipliers(self, q, Ax, y, lo, hi):
        """Least-squares multipliers ``min |q + A_a' y_a|`` on the active set ``a`` of the
        QP (the dynamics rows and the rows with a non-zero OSQP multiplier whose constraint
        is active, within ``_ACTIVE``, at ``dv = 0``): OSQP's own are accurate to its
        tolerance only, these to rounding. OSQP's are kept if the system is singular."""
        A = self._A0.copy()
        A.data = Ax
        near = np.minimum(np.abs(lo), np.abs(hi)) <= _ACTIVE
        act = np.union1d(np.arange(self.n_dyn), np.flatnonzero((y != 0) & near))
        Aa = A.tocsr()[act]
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", spla.MatrixRankWarning)
                ya = spla.spsolve((Aa @ Aa.T).tocsc(), -(Aa @ q))
        except (spla.MatrixRankWarning, RuntimeError, ValueError):
            return y
        if not np.all(np.isfinite(ya)):
            return y
        out = np.zeros_like(y)
        out[act] = ya
        return out

    def _kkt(self, q, Ax, y, lo, hi) -> dict:
        """Stationarity ``|q + A'y|_inf`` and complementarity (with the multipliers' signs:
        ``y < 0`` at a lower, ``y > 0`` at an upper bound) at ``dv = 0``."""
        A = self._A0.copy()
        A.data = Ax
        grad_l = q + A.T @ y
        yi, loi, hii = y[self.n_dyn :], lo[self.n_dyn :], hi[self.n_dyn :]
        # slack of the side a multiplier pushes against; the wrong side counts fully
        comp = np.where(
            yi < 0, -yi * np.minimum(np.abs(loi), _INF), yi * np.minimum(np.abs(hii), _INF)
        )
        return dict(
            stationarity=float(np.max(np.abs(grad_l))) if grad_l.size else 0.0,
            complementarity=float(np.max(comp)) if comp.size else 0.0,
        )

    def _eval_merit(self, u, p):
        E, x, d = self._merit(u, p)
        return float(E[0]), x.copy(), d.copy()

    # ---- the solve ------------------------------------------------------------------------
    def solve(
        self, p: np.ndarray, u0: np.ndarray | None = None, options: SQPOptions | dict | None = None
    ) -> SolveResult:
        """Solve for ``p`` (``(n_p,)`` or ``(B, n_p)``) from ``u0`` (zeros if None).

        ``options`` may change the numbers (tolerances, line search, OSQP tolerances) but
        not the structure (bounds, collision) this solver was built for.
        """
        opts = check_options(SQPOptions, options, "sqp") if options is not None else self.options
        if opts.structure() != self.options.structure():
            raise SpecError(
                "sqp",
                "these options change the QP's structure (bounds or collision); "
                "use solve_sqp or a new SQPSolver",
            )
        game = self.game
        t0 = time.perf_counter()
        single = np.ndim(p) == 1 and (u0 is None or np.ndim(u0) == 1)
        U0, P = game.check_inputs(game.zero_controls() if u0 is None else u0, p)
        with np.errstate(over="ignore", invalid="ignore"):
            runs = [self._solve_one(U0[b].copy(), P[b], opts) for b in range(U0.shape[0])]
        res = _stack(game, runs, time.perf_counter() - t0, opts)
        return res[0] if single else res

    def _solve_one(self, u: np.ndarray, p: np.ndarray, o: SQPOptions) -> dict:
        if self._radius_param and self.pairs:  # each problem's radii (radius.<agent> in p)
            r = self.game.radii(p)
            ij = np.array([(a, b) for a, b, _ in self.pairs])
            self.reach = r[ij[:, 0]] + r[ij[:, 1]] + self._margin
        if self.u_idx.size:  # start inside the control bounds (a box: projection is exact)
            u[self.u_idx] = np.clip(u[self.u_idx], self.u_lo, self.u_hi)
        nu_pen = float(o.merit_penalty)
        mu = float(o.regularization)  # adapted like LM's damping (see the module docstring)
        mu_hist = []
        fine = None  # (point, KKT error) before a step taken below the energy's resolution
        hist, kkt_hist, alphas, qp_iters, polish_hist = [], [], [], [], []
        status, stop, qp_status = Status.MAX_ITER, "max_iter", ""
        kkt = dict(stationarity=math.inf, violation=math.inf, complementarity=math.inf)
        y = np.zeros(self.n_c)
        it = 0
        while True:
            Px, q, Ax, E, x, d = (a.copy() for a in self._lin(u, p, mu))
            E = float(E[0])
            hist.append(E)
            if not (math.isfinite(E) and np.isfinite(x).all() and np.isfinite(q).all()):
                status, stop = Status.NONFINITE, "nonfinite"
                break
            lo, hi = self._bounds(u, x, d)
            if self.qp is None:
                self._setup(Px, q, Ax, lo, hi)
            else:
                self.qp.update(q=q, l=lo, u=hi, Px=Px, Ax=Ax)
                if it == 0:
                    self.qp.update_settings(
                        eps_abs=o.eps_abs,
                        eps_rel=o.eps_rel,
                        max_iter=o.qp_max_iter,
                        polishing=o.polish,
                    )
                    self.qp.update_settings(rho=_RHO0)  # the adapted rho fits the last QP
            sol = self.qp.solve(raise_error=False)
            qp_status = str(sol.info.status)
            polish_hist.append(int(sol.info.status_polish))
            qp_iters.append(int(sol.info.iter))
            sv = sol.info.status_val
            S = osqp.SolverStatus
            if sv in (
                S.OSQP_PRIMAL_INFEASIBLE,
                S.OSQP_PRIMAL_INFEASIBLE_INACCURATE,
                S.OSQP_DUAL_INFEASIBLE,
                S.OSQP_DUAL_INFEASIBLE_INACCURATE,
            ):
                status, stop = Status.INFEASIBLE, f"qp {qp_status}"
                break
            if sv not in (S.OSQP_SOLVED, S.OSQP_SOLVED_INACCURATE, S.OSQP_MAX_ITER_REACHED):
                status, stop = Status.FAILED, f"qp {qp_status}"
                break
            v, y = np.asarray(sol.x, float), np.asarray(sol.y, float)
            if not (np.isfinite(v).all() and np.isfinite(y).all()):
                status, stop = Status.NONFINITE, f"qp {qp_status} (non-finite solution)"
                break
            # first-order test at the current point (dv = 0), multipliers refined on the
            # QP's active set
            y = self._multipliers(q, Ax, y, lo, hi)
            viol1, viol_inf = self._violation(u, x, d)
            kkt = self._kkt(q, Ax, y, lo, hi)
            kkt["violation"] = viol_inf
            kkt_hist.append(max(kkt["stationarity"], kkt["complementarity"]))
            if (
                kkt["stationarity"] <= o.tol
                and kkt["complementarity"] <= o.tol
                and viol_inf <= o.feas_tol
            ):
                status, stop = Status.CONVERGED, "kkt"
                break
            measure = max(kkt["stationarity"], kkt["complementarity"], viol_inf)
            if fine is not None and measure >= fine[1]:
                # a step taken below the energy's resolution made the KKT error worse:
                # back to the previous point with more regularization
                u, fine, mu = fine[0], None, max(10.0 * mu, _MU_MIN)
                it += 1
                if mu > _MU_MAX or it >= o.max_iter:
                    status, stop = (
                        (Status.STALLED, "no_descent")
                        if mu > _MU_MAX
                        else (Status.MAX_ITER, "max_iter")
                    )
                    break
                continue
            fine = None
            if it >= o.max_iter:
                break
            du = v[self.xcols.size :]
            # l1 merit: penalty above the inequality multipliers
            y_in = np.abs(y[self.n_dyn :])
            if y_in.size:
                nu_pen = max(nu_pen, 1.1 * float(y_in.max()))
            phi = E + nu_pen * viol1
            dphi = float(q @ v) - nu_pen * viol1  # q'v = g'du: the QP's dx follows du
            Pm = self._P0.copy()
            Pm.data = Px
            vPv = float(2.0 * v @ (Pm @ v) - Pm.diagonal() @ (v * v))
            it += 1
            if np.max(np.abs(du), initial=0.0) <= o.step_tol * (1 + np.max(np.abs(u), initial=0.0)):
                status, stop = Status.STALLED, "step_tol"
                break
            if -dphi <= _FINE * (1 + abs(phi)):
                # the predicted decrease drowns in the rounding of E (or nearly): the line
                # search cannot judge the step; take it and judge it by the KKT error at
                # the next point (reverted, with more regularization, if that is worse)
                fine = (u.copy(), measure)
                u = u + du
                if self.u_idx.size:
                    u[self.u_idx] = np.clip(u[self.u_idx], self.u_lo, self.u_hi)
                alphas.append(1.0)
                mu_hist.append(mu)
                continue
            alpha, accepted = 1.0, False
            for _ in range(o.max_backtracks + 1):
                u_try = u + alpha * du
                E_t, x_t, d_t = self._eval_merit(u_try, p)
                if math.isfinite(E_t) and np.isfinite(x_t).all():
                    phi_t = E_t + nu_pen * self._violation(u_try, x_t, d_t)[0]
                    if phi_t <= phi + o.armijo * alpha * dphi:
                        accepted = True
                        break
                alpha *= o.backtrack
            if not accepted:
                status, stop = Status.STALLED, "line_search"
                break
            # the QP model's predicted decrease against the actual one: adapt mu
            pred = -alpha * dphi - 0.5 * alpha * alpha * vPv
            ratio = (phi - phi_t) / pred if pred > 0 else 0.0
            if alpha < 1.0 or ratio < 0.25:
                mu = max(10.0 * mu, _MU_MIN)
            elif ratio > 0.75:
                mu = max(mu / 10.0, float(o.regularization))
            mu_hist.append(mu)
            alphas.append(alpha)
            u = u_try
            if self.u_idx.size:  # rounding only: the QP's du keeps u inside the box
                u[self.u_idx] = np.clip(u[self.u_idx], self.u_lo, self.u_hi)
        return dict(
            u=u,
            p=p,
            status=status,
            stop=stop,
            iter=it,
            history=hist,
            qp_status=qp_status,
            kkt=kkt,
            kkt_history=kkt_hist,
            step_sizes=alphas,
            qp_iterations=qp_iters,
            merit_penalty=nu_pen,
            polish=polish_hist,
            mu=mu_hist,
            y=y,
        )


def _stack(game: PotentialGame, runs: list[dict], wall: float, opts: SQPOptions) -> SolveResult:
    B = len(runs)
    U = np.stack([r["u"] for r in runs])
    Pm = np.stack([r["p"] for r in runs])
    X = np.empty((B, game.n_x))
    E = np.empty(B)
    C = np.empty((B, game.N))
    G = np.empty((B, game.n_u))
    roll = game.function("rollout")
    for b in range(B):  # one problem at a time, like the solve itself
        X[b] = np.asarray(roll(U[b], Pm[b])).ravel()
        E[b] = float(game.function("energy")(U[b], Pm[b]))
        C[b] = np.asarray(game.function("agent_costs")(U[b], Pm[b])).ravel()
        G[b] = np.asarray(game.function("gradient")(U[b], Pm[b])).ravel()
    status = np.empty(B, dtype=object)
    status[:] = [r["status"] for r in runs]
    status = demote_nonfinite(status, E[:, None], X, C, U)
    S = max(max(len(r["history"]) for r in runs), 1)
    hist = np.empty((S, B))
    for b, r in enumerate(runs):
        h = list(r["history"]) or [E[b]]
        hist[:, b] = h + [h[-1]] * (S - len(h))
    kkt = {k: np.array([r["kkt"][k] for r in runs]) for k in runs[0]["kkt"]}
    return SolveResult(
        solver="sqp",
        controls=U,
        states=X,
        energy=E,
        agent_costs=C,
        status=status,
        iterations=np.array([r["iter"] for r in runs], dtype=int),
        energy_history=hist,
        grad_norm=np.max(np.abs(G), axis=1) if game.n_u else np.zeros(B),
        wall_time=wall,
        info={
            "stop": np.array([r["stop"] for r in runs], dtype=object),
            "qp_status": np.array([r["qp_status"] for r in runs], dtype=object),
            "kkt_stationarity": kkt["stationarity"],
            "max_violation": kkt["violation"],
            "kkt_complementarity": kkt["complementarity"],
            "kkt_history": _per_problem(runs, "kkt_history"),
            "step_sizes": _per_problem(runs, "step_sizes"),
            "qp_iterations": _per_problem(runs, "qp_iterations"),
            "qp_polish": _per_problem(runs, "polish"),
            "regularization_history": _per_problem(runs, "mu"),
            "merit_penalty": np.array([r["merit_penalty"] for r in runs]),
            "multipliers": np.stack([r["y"] for r in runs]),
            "options": opts,
        },
    )


def _per_problem(runs: list[dict], key: str) -> np.ndarray:
    """``(B,)`` object array of per-problem arrays (``result[b]`` picks one)."""
    out = np.empty(len(runs), dtype=object)
    for b, r in enumerate(runs):
        out[b] = np.asarray(r[key], dtype=float)
    return out


def _solver_for(game: PotentialGame, opts: SQPOptions) -> SQPSolver:
    return game.cached(("sqp", opts.structure()), lambda: SQPSolver(game, opts))


def solve_sqp(
    game: PotentialGame,
    p: np.ndarray,
    u0: np.ndarray | None = None,
    options: SQPOptions | dict | None = None,
) -> SolveResult:
    """Minimize the potential of ``game`` under hard constraints by Gauss-Newton SQP (OSQP).

    ``p``: ``(n_p,)`` or ``(B, n_p)`` (the same argument name and order as every solver); ``u0``: ``(n_u,)`` or ``(B, n_u)`` (zeros if
    None). ``options``: :class:`SQPOptions` or a dict of its fields (unknown keys raise
    :class:`~epo_casadi.errors.SpecError`). The solver (CasADi functions and the OSQP
    object) is built once per game and constraint structure and reused by later calls,
    which update and warm-start the same QP. See the module docstring for the statuses.
    """
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    opts = check_options(SQPOptions, options, "sqp")
    return _solver_for(game, opts).solve(p, u0, opts)
