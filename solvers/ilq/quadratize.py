"""The per-stage linearization and quadratization of one iteration (:mod:`solvers.ilq`, step 1).

:func:`build_quadratize` builds, once per solver, the CasADi function ``ilq_quadratize``
``(X, U, p) -> (C, E, lam_nz, phi_nz)``: the players' costs, the potential, the nonzeros
of every player's stage matrices ``L_ik`` (gradient and Hessian blocks of ``C_i``, exact or
Gauss-Newton) and of the dynamics Jacobians ``Phi_k = [[B_k, A_k, 0], [0, 0, 1]]``, with
the index tables that scatter them into the solver's ``Lam`` and ``Phi``
(:meth:`solvers.ilq.ILQSolver.quadratize`). Costs that couple consecutive stages make the
earlier stage's variables extra states ``Y_k`` (:attr:`solvers.ilq.ILQSolver.aug`), so the
Hessian blocks between stage ``k-1`` and ``k`` are kept at stage ``k``.

``s`` is the :class:`solvers.ilq.ILQSolver` being built (its game, costs, Hessian mode and
stage offsets are set).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..codegen import BufferCall as _Call

__all__ = ["build_quadratize", "lam_index"]


def build_quadratize(s) -> None:
    """Build ``s.quad`` and the layout it fills.

    Sets on ``s``: ``aug``, ``na``, ``nxs``, ``n`` (the Riccati state ``(X_k, Y_k)`` and the
    stage vector ``(U_k, X_k, Y_k, 1)``), ``dropped_cross_stage``, ``quad`` and its scatter
    tables ``_lam_src``/``_lam_tgt`` (into ``Lam``), ``_phi_pattern``/``_phi_tgt`` (into
    ``Phi``), the symbolic pieces ``_quad_sym`` (:mod:`solvers.fast_ilq`) and ``_blend_sym``
    (:func:`solvers.ilq.kinks.build_kink_quad`), and the work arrays ``Lam`` and ``Phi``.
    """
    g, K, N, nx, nu = s.game, s.K, s.N, s.nx, s.nu
    Xs, Us, p, x_flat, u_flat, C, z, stage_of, pos_in = _trajectory_symbols(s)
    grads, hessians, player_rows = _player_curvature(s, x_flat, u_flat, p, C, z)
    # Hessian entries between consecutive stages (jerk, turn_acceleration): the earlier
    # stage's variables they involve are carried into the next stage as extra states Y
    prev = _carried_variables(stage_of, pos_in, hessians)
    s.aug = prev  # positions in (U_k, X_k) of the carried variables Y_{k+1}
    s.na = int(prev.size)
    s.nxs = nx + s.na  # Riccati state (X_k, Y_k)
    s.n = n = nu + s.nxs + 1
    ypos = np.full(nu + nx, -1)
    ypos[prev] = nu + nx + np.arange(s.na)
    n_stage = K * N * n * n
    outs, src, tgt, hess_sel = _stage_entries(s, grads, hessians, stage_of, pos_in, ypos)
    phi_out = _dynamics_jacobians(s, Xs, Us)
    r_traj = None
    if s.custom_costs:
        E = ca.SX(np.nan)
    else:
        r_traj = g.function("traj_residual")(x_flat, u_flat, p)
        E = 0.5 * ca.sumsqr(r_traj)
    s.quad = _Call(
        ca.Function(
            "ilq_quadratize",
            [Xs, Us, p],
            [C, E, ca.vertcat(*outs), phi_out],
            ["X", "U", "p"],
            ["C", "E", "lam_nz", "phi_nz"],
        )
    )
    s._lam_src = np.concatenate(src).astype(np.intp)
    s._lam_tgt = np.concatenate(tgt).astype(np.intp)
    # the symbolic pieces, for the compiled stage-split quadratization (solvers.fast_ilq)
    s._quad_sym = (Xs, Us, p, C, E, ca.vertcat(*outs), phi_out, r_traj)
    # for the quadratization with blended kinks, built when a solve first needs it
    s._blend_sym = (Xs, Us, p, x_flat, u_flat, z, C, E, grads, player_rows, hess_sel)
    s._blend_sym += (phi_out,)
    s.Lam = np.zeros(n_stage + N * n * n)  # stages 0..K-1, then the terminal stage
    s.Phi = np.zeros((K, s.nxs + 1, n))
    s.Phi[:, s.nxs, n - 1] = 1.0
    s.Phi[:, nx + np.arange(s.na), prev] = 1.0  # Y_{k+1} = (U_k, X_k)[aug]


def _trajectory_symbols(s):
    """The trajectory as SX symbols ``X (nx, K+1)``, ``U (nu, K)``, ``p``; its flat game
    layout; the costs ``C``; the stage-major variables ``z`` and, per entry of ``z``, its
    stage and its position in ``(U_k, X_k)``."""
    g, K, N, nx, nu = s.game, s.K, s.N, s.nx, s.nu
    Xs = ca.SX.sym("X", nx, K + 1)
    Us = ca.SX.sym("U", nu, K)
    p = ca.SX.sym("p", g.n_p)
    x_flat = ca.vertcat(*[ca.vec(Xs[s.xo[i] : s.xo[i + 1], :]) for i in range(N)])
    u_flat = ca.vertcat(*[ca.vec(Us[s.uo[i] : s.uo[i + 1], :]) for i in range(N)])
    C = ca.reshape(s.costs(x_flat, u_flat, p), N, 1)
    # stage-major variables z = (U_0, X_0, U_1, X_1, ..., U_{K-1}, X_{K-1}, X_K)
    zs = []
    for k in range(K):
        zs += [Us[:, k], Xs[:, k]]
    zs.append(Xs[:, K])
    z = ca.vertcat(*zs)
    stage_of = np.concatenate([np.full(nu + nx, k) for k in range(K)] + [np.full(nx, K)]).astype(
        int
    )
    pos_in = np.concatenate([np.arange(nu + nx) for _ in range(K)] + [nu + np.arange(nx)]).astype(
        int
    )
    return Xs, Us, p, x_flat, u_flat, C, z, stage_of, pos_in


def _player_curvature(s, x_flat, u_flat, p, C, z):
    """Per player: the gradient of ``C_i`` w.r.t. ``z``, its Hessian (``s.hessian``) with the
    triplet of its sparsity, and (Gauss-Newton) the residual rows of its terms."""
    g, N = s.game, s.N
    r_all = g.function("traj_residual")(x_flat, u_flat, p) if s.hessian == "gauss_newton" else None
    grads, hessians, player_rows = [], [], []
    for i in range(N):
        if s.hessian == "gauss_newton":
            rows_i = [
                r
                for t in g.terms
                if g.agent_names[i] in t.agents
                for r in range(t.rows.start, t.rows.stop)
            ]
            ri = r_all[rows_i] if rows_i else ca.SX(0, 1)
            J = ca.jacobian(ri, z)
            H, grad = ca.mtimes(J.T, J), ca.mtimes(J.T, ri)
            player_rows.append(rows_i)
        else:
            H, grad = ca.hessian(C[i], z)
        rows, cols = (np.asarray(v, dtype=int) for v in H.sparsity().get_triplet())
        grads.append(grad)
        hessians.append((H, rows, cols))
    return grads, hessians, player_rows


def _carried_variables(stage_of, pos_in, hessians) -> np.ndarray:
    """Positions in ``(U_k, X_k)`` of the variables some Hessian entry couples with the next
    stage (sorted, unique)."""
    lag = [stage_of[r] - stage_of[c] for _, r, c in hessians]
    return np.unique(
        np.concatenate(
            [pos_in[c[d == 1]] for (_, r, c), d in zip(hessians, lag, strict=True)] + [[]]
        )
    ).astype(int)


def _stage_entries(s, grads, hessians, stage_of, pos_in, ypos):
    """The outputs ``lam_nz`` (per player: its gradient, then its Hessian nonzeros within a
    stage or between consecutive stages) and where they go in ``s.Lam``: ``(outs, src, tgt,
    hess_sel)``. Counts the dropped entries in ``s.dropped_cross_stage``."""
    K, N, n = s.K, s.N, s.n
    nz = stage_of.size
    n_stage = K * N * n * n
    outs, src, tgt, hess_sel = [], [], [], []
    off = 0
    s.dropped_cross_stage = 0
    for i, (grad, (H, rows, cols)) in enumerate(zip(grads, hessians, strict=True)):
        # gradient -> last row and last column of player i's stage matrices
        outs.append(ca.densify(grad))
        for a_, b_ in ((pos_in, np.full(nz, n - 1)), (np.full(nz, n - 1), pos_in)):
            src.append(off + np.arange(nz))
            tgt.append(lam_index(s, stage_of, i, a_, b_, n_stage))
        off += nz
        # Hessian nonzeros inside a stage block, and between a stage and the one before
        # it (placed at stage k against Y_k); blocks further apart are dropped
        d = stage_of[rows] - stage_of[cols]
        sel = np.nonzero(np.abs(d) <= 1)[0]
        outs.append(H.nz[sel.tolist()] if sel.size else ca.SX(0, 1))
        hess_sel.append((H.sparsity(), sel))
        rs, cs, ds = rows[sel], cols[sel], d[sel]
        ka = np.maximum(stage_of[rs], stage_of[cs])
        pa = np.where(ds == -1, ypos[pos_in[rs]], pos_in[rs])
        pb = np.where(ds == 1, ypos[pos_in[cs]], pos_in[cs])
        src.append(off + np.arange(sel.size))
        tgt.append(lam_index(s, ka, i, pa, pb, n_stage))
        off += sel.size
        s.dropped_cross_stage += int(rows.size - sel.size)
    return outs, src, tgt, hess_sel


def _dynamics_jacobians(s, Xs, Us):
    """The nonzeros of ``B_k`` and ``A_k`` at every stage (``Function.map`` over stages,
    stage-major): the output ``phi_nz``. Sets ``s._phi_pattern`` (the flat entries of one
    ``Phi_k`` that change with the trajectory) and ``s._phi_tgt`` (their places in
    ``s.Phi``)."""
    K, nx, nu, n = s.K, s.nx, s.nu, s.n
    # dynamics Jacobians per stage, packed into Phi[k] = [[B_k, A_k, 0], [0, 0, 1]]
    xk, uk = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
    nxt = s._joint_step(xk, uk)
    Ja, Jb = ca.jacobian(nxt, xk), ca.jacobian(nxt, uk)
    lin = ca.Function("ilq_lin", [xk, uk], [Ja, Jb])
    A_all, B_all = (lin.map(K) if K > 1 else lin)(Xs[:, :K], Us)
    ra, cA = (np.asarray(v, dtype=int) for v in Ja.sparsity().get_triplet())
    rb, cB = (np.asarray(v, dtype=int) for v in Jb.sparsity().get_triplet())
    # nonzeros of a mapped output are stage-major (each stage's column block in turn)
    A_nz = ca.reshape(A_all.nz[:], Ja.nnz(), K)
    B_nz = ca.reshape(B_all.nz[:], Jb.nnz(), K)
    phi_out = ca.vec(ca.vertcat(B_nz, A_nz))
    stage0 = np.concatenate([rb * n + cB, ra * n + nu + cA])
    s._phi_pattern = stage0  # flat entries of one Phi[k] that change with the trajectory
    s._phi_tgt = (
        (np.arange(K)[:, None] * ((s.nxs + 1) * n) + stage0[None]).reshape(-1).astype(np.intp)
    )
    return phi_out


def lam_index(s, k, i, a, b, n_stage):
    """Flat index into ``s.Lam`` of entry ``(a, b)`` of player ``i`` at stage ``k``.

    Stages ``k < K`` fill ``(K, N, n, n)``; stage ``K`` fills the terminal ``(N, n, n)``
    block after it (its ``(x, 1)`` rows and columns, same positions as other stages).
    """
    n, N = s.n, s.N
    k = np.asarray(k)
    return np.where(k < s.K, ((k * N + i) * n + a) * n + b, n_stage + (i * n + a) * n + b)
