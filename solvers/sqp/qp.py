"""The stage-structured QP of the SQP solver: one game, one constraint structure.

:class:`StagedQP` builds, once, the CasADi functions of the QP at the rolled-out iterate
(``P`` upper triangle, ``q``, ``A``, the energy, states and distances; the variables
``v = (dx, du)`` and the rows of :mod:`solvers.sqp`), the bounds' rows and OSQP's
problem; its methods are the QP's numbers at one point: the row bounds, the constraint
violation, the least-squares multipliers on the active set and the KKT test.
"""

from __future__ import annotations

import warnings

import casadi as ca
import numpy as np
import osqp
import scipy.sparse as sps
import scipy.sparse.linalg as spla

from epo_casadi.errors import SpecError
from epo_casadi.features import smooth_distance
from epo_casadi.game import PotentialGame

from ..codegen import BufferCall
from ..ipopt import agent_bounds
from ..lm import check_options
from .options import SQPOptions

__all__ = ["StagedQP"]

_ACTIVE = 1e-6  # a constraint this close to its bound at dv = 0 counts as active
_INF = 1e30  # OSQP's infinity (OSQP_INFTY)


def _bound_rows(game: PotentialGame, bounds, sizes, offsets, per_stage, first, field):
    """(flat indices, lower, upper) of the bounded entries, every stage from ``first``."""
    idx, lo_all, hi_all = [], [], []
    for i, lo, hi in agent_bounds(game, bounds, sizes, f"sqp.{field}"):
        comp = np.flatnonzero(np.isfinite(lo) | np.isfinite(hi))
        for k in range(first, per_stage):
            idx.append(int(offsets[i]) + k * sizes[i] + comp)
            lo_all.append(lo[comp])
            hi_all.append(hi[comp])
    if not idx:
        return np.zeros(0, int), np.zeros(0), np.zeros(0)
    return np.concatenate(idx), np.concatenate(lo_all), np.concatenate(hi_all)


def _csc(sp: ca.Sparsity, shape) -> sps.csc_matrix:
    """A scipy CSC matrix with CasADi's pattern ``sp`` (values 1; nonzeros in the same order)."""
    return sps.csc_matrix(
        (np.ones(sp.nnz()), np.asarray(sp.row()), np.asarray(sp.colind())), shape=shape
    )


class StagedQP:
    """The QP of one game and one :class:`SQPOptions` structure, with OSQP set up once.

    Attributes: ``n_v`` (QP variables), ``n_c`` (QP constraint rows), ``setups`` (OSQP
    set-ups so far), ``qp`` (the ``osqp.OSQP``, ``None`` before the first set-up).
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
        defect = _defects(game, x, u)
        v_sym = [x, u]
        Ddyn = ca.horzcat(ca.jacobian(defect, x)[:, xcols.tolist()], ca.jacobian(defect, u))
        dist = self._distances(game, x, opts)
        Ddist = ca.jacobian(dist, ca.vertcat(*v_sym))
        # reorder Ddist columns to v = (x[xcols], u)
        Ddist = ca.horzcat(
            Ddist[:, xcols.tolist()], Ddist[:, list(range(game.n_x, game.n_x + n_u))]
        )
        n_dyn = defect.shape[0]
        Sel_u = _selection(self.u_idx.size, n_dx + self.u_idx, self.n_v)
        Sel_x = _selection(self.x_idx.size, xpos[self.x_idx], self.n_v)
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
        self._functions(game, [x, u, p, reg], [P, q, A, E, r, dist, defect])
        self.P_sp, self.A_sp = self._lin.f.sparsity_out(0), self._lin.f.sparsity_out(2)
        self._P0 = _csc(self.P_sp, (self.n_v, self.n_v))
        self._A0 = _csc(self.A_sp, (self.n_c, self.n_v))
        self._costs = game.function("agent_costs")
        self._grad = game.function("gradient")
        self.qp: osqp.OSQP | None = None
        self.setups = 0

    def _distances(self, game: PotentialGame, x, opts: SQPOptions):
        """The pairwise distances of the hard collision constraints at stages ``k = 1..K``
        (an empty column without ``collision``); sets ``reach`` (``r_a + r_b + margin``
        per row) and ``pairs`` (``(a, b, k)`` per row)."""
        K = game.K
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
        return dist

    def _functions(self, game: PotentialGame, args: list, outs: list) -> None:
        """The QP's functions of ``(u, p, reg)`` and the merit's of ``(u, p)``: ``outs``
        (``P, q, A, E, r, dist, defect`` at the symbols ``args = (x, u, p, reg)``) with the
        rollout substituted for ``x``."""
        xr = game.symbols["x"]
        u_g, p_g = game.symbols["u"], game.symbols["p"]
        sub = ca.Function("sub", args, outs)
        P_r, q_r, A_r, E_r, r_r, d_r, _ = sub(xr, u_g, p_g, args[3])
        self._lin = BufferCall(
            ca.Function(
                "sqp_qp",
                [u_g, p_g, args[3]],
                [P_r, ca.densify(q_r), A_r, ca.densify(E_r), ca.densify(xr), ca.densify(d_r)],
                ["u", "p", "reg"],
                ["P", "q", "A", "E", "x", "dist"],
            )
        )
        self._merit = BufferCall(
            ca.Function(
                "sqp_merit",
                [u_g, p_g],
                [ca.densify(E_r), ca.densify(xr), ca.densify(d_r)],
                ["u", "p"],
                ["E", "x", "dist"],
            )
        )

    # ---- the QP's numbers at one point --------------------------------------------------------------------------
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


def _defects(game: PotentialGame, x, u):
    """The dynamics defects ``x_{k+1} - f(x_k, u_k)`` of every agent and stage (agent-major),
    each agent's own dynamics or its coupling's joint model (``game.agent_steps``)."""
    K = game.K
    defects = []
    Xs = [
        ca.reshape(x[int(game.xoff[i]) : int(game.xoff[i + 1])], game.nx[i], K + 1)
        for i in range(game.N)
    ]
    Us = [
        ca.reshape(u[int(game.uoff[i]) : int(game.uoff[i + 1])], game.nu[i], K)
        for i in range(game.N)
    ]
    nxt = [game.agent_steps([X[:, k] for X in Xs], [U[:, k] for U in Us]) for k in range(K)]
    for i in range(game.N):
        for k in range(K):
            defects.append(Xs[i][:, k + 1] - nxt[k][i])
    return ca.vertcat(*defects)


def _selection(n: int, cols: np.ndarray, n_v: int) -> ca.DM:
    """``(n, n_v)``: row ``j`` picks the QP variable ``cols[j]`` (a bound's row of ``A``)."""
    if not n:
        return ca.DM(0, n_v)
    return ca.DM(sps.csc_matrix((np.ones(n), (np.arange(n), cols)), shape=(n, n_v)))
