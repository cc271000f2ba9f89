"""Generated-C quadratization for :mod:`solvers.ilq`: per-stage functions mapped over stages.

:class:`solvers.ilq.ILQSolver` quadratizes the players' costs and linearizes the dynamics
with one interpreted CasADi function over the whole trajectory (``ilq_quadratize``, about
1k SX instructions per stage). Compiling that function whole took tens of seconds and ran no
faster at ``-O0``. This module splits it into *stage functions* instead, found from the
graph itself, so it works for any stage-structured costs without knowing the features:

1. Every output nonzero belongs to one stage ``k`` (where :meth:`ILQSolver.quadratize`
   scatters it: ``L_ik``, ``Phi_k``). The sparsity of the outputs' Jacobian w.r.t. the
   trajectory gives the stages ``lo_k..hi_k`` each stage's outputs depend on (``k-1..k+1``
   with jerk terms: the residual rows of the next stage enter this stage's gradient).
2. Stage ``k``'s outputs become a function ``(z_lo..z_hi, p) -> out_k`` of its stage
   window (``z_j = (U_j, X_j)``, ``z_K = X_K``); its outputs are ordered by their place in
   the stage matrices. Stages whose functions serialize identically (same graph, same
   constants, same relative window) form one group: the middle stages are one group, the
   first and last stages a few more.
3. Each group's function is mapped over its stages (``Function.map``, ``p`` shared) and all
   groups are compiled into one library (:func:`solvers.codegen.compile_functions`,
   ``-O1``, cached on disk by the functions' serialization: by the game's structure, never
   by parameter values). A call gathers the stage windows with one numpy index per group.

The costs ``C`` and the energy ``E`` (needed once per linearization, for the result and the
finiteness test): with the game's own costs, the residual rows go out with the stage of the
latest variable they involve and numpy sums them, ``C_i = 1/2 |r_i|^2`` over player ``i``'s
terms, ``E = 1/2 |r|^2`` (the game's definitions; only the summation order differs, so they
agree to rounding). With custom costs they stay one interpreted function over the
trajectory (28k SX instructions, 0.08 ms, for 3 unicycles and K = 100).

When the split does not pay or cannot be made (a stage depends on stages more than
:data:`MAX_WINDOW` away, as with a custom cost that couples the whole trajectory, or more
than :data:`MAX_GROUPS` distinct stage functions), :func:`build` returns ``None`` and the
solver keeps the interpreted function; :attr:`ILQSolver.quad_backend` says which is used.
The arithmetic is the interpreted function's, operation for operation (the same SX graph),
so the stage matrices agree to rounding (tested in ``tests/test_ilq_fast.py``).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

__all__ = ["MAX_GROUPS", "MAX_WINDOW", "CompiledQuadratize", "build"]

#: Largest distance (in stages) between a stage and a stage its outputs depend on.
MAX_WINDOW = 2
#: Largest number of distinct stage functions (compile time grows with it).
MAX_GROUPS = 12


class CompiledQuadratize:
    """The quadratization as mapped, compiled stage functions (see the module docstring).

    ``__call__(X, U, p) -> (C, E)`` fills ``solver.Lam`` and ``solver.Phi`` like
    :meth:`solvers.ilq.ILQSolver.quadratize`.
    """

    def __init__(self, solver, groups, cost_fn, name: str, member=None, n_r: int = 0):
        from .codegen import BufferCall as _Call
        from .codegen import compile_functions

        self.s = solver
        funcs = [g["fn"] for g in groups]
        lib = compile_functions(funcs, name, optimize="-O1")
        self.groups = []
        for g in groups:
            self.groups.append((_Call(lib[g["fn"].name()]), g["win"], g["segments"]))
        self.costs = None if cost_fn is None else _Call(cost_fn)
        self.member = member  # (N, n_r) 0/1: residual row in one of player i's terms
        self.r = np.zeros(n_r)
        self.n_groups = len(groups)
        self.n_instructions = [int(g["n_instr"]) for g in groups]

    def __call__(self, X, U, p):
        s = self.s
        v = np.concatenate([np.asarray(U, float).reshape(-1), np.asarray(X, float).reshape(-1)])
        bufs = (s.Lam, s.Phi.reshape(-1), self.r)
        for call, win, segments in self.groups:
            out = call(v[win], p)[0].reshape(win.shape[0], -1)
            for b, lo, hi, tgt in segments:
                bufs[b][tgt] = out[:, lo:hi].reshape(-1)
        if self.costs is not None:
            C, E = self.costs(X, U, p)
            return C.copy(), float(E[0])
        r2 = self.r * self.r
        return 0.5 * (self.member @ r2), 0.5 * float(np.sum(r2))


def build(solver, Xs, Us, p, C, E, lamv, phi_out, r_traj) -> CompiledQuadratize | None:
    """Split ``solver``'s quadratization into stage groups and compile them (or ``None``)."""
    K, N, n, nu, nx = solver.K, solver.N, solver.n, solver.nu, solver.nx
    if K < 2:
        return None
    n_stage = K * N * n * n
    src, tgt = solver._lam_src, solver._lam_tgt
    # stage of every Lam entry and its place inside the stage's block
    t_stage = np.where(tgt < n_stage, tgt // (N * n * n), K)
    t_local = np.where(tgt < n_stage, tgt - t_stage * (N * n * n), tgt - n_stage)
    m_phi = solver._phi_pattern.size
    zvec = ca.vertcat(ca.vec(Us), ca.vec(Xs))  # = concat(U.ravel(), X.ravel()) numerically
    var_stage = np.concatenate([np.arange(K * nu) // nu, np.arange((K + 1) * nx) // nx])
    # dependencies of every output entry on the trajectory's stages (one sparsity pass)
    n_r = 0 if r_traj is None else r_traj.shape[0]
    allout = ca.vertcat(lamv, phi_out, *([r_traj] if n_r else []))
    rows, cols = (
        np.asarray(a, dtype=int) for a in ca.jacobian_sparsity(allout, zvec).get_triplet()
    )
    lo = np.full(allout.shape[0], K + 1)
    hi = np.full(allout.shape[0], -1)
    np.minimum.at(lo, rows, var_stage[cols])
    np.maximum.at(hi, rows, var_stage[cols])
    n_lam = lamv.shape[0]
    phi_rows = n_lam + np.arange(K * m_phi)
    # a residual row goes out with the latest stage it involves (stage 0 if none)
    r_stage = np.maximum(hi[n_lam + K * m_phi :], 0)
    groups: dict = {}
    for k in range(K + 1):
        sel = np.nonzero(t_stage == k)[0]
        sel = sel[np.argsort(t_local[sel], kind="stable")]
        rows_k = src[sel]
        rr = np.nonzero(r_stage == k)[0]
        phi_k = phi_rows[k * m_phi : (k + 1) * m_phi] if k < K else np.zeros(0, int)
        out_rows = np.concatenate([rows_k, phi_k, n_lam + K * m_phi + rr]).astype(int)
        dep_lo = int(lo[out_rows].min()) if out_rows.size else k
        dep_hi = int(hi[out_rows].max()) if out_rows.size else k
        dep_lo, dep_hi = min(dep_lo, k), max(dep_hi, k)
        if k - dep_lo > MAX_WINDOW or dep_hi - k > MAX_WINDOW:
            return None
        win = np.nonzero((var_stage >= dep_lo) & (var_stage <= dep_hi))[0]
        # variables in stage order (U_j, X_j) per stage of the window
        win = win[np.lexsort((win, var_stage[win]))]
        e = allout[out_rows.tolist()] if out_rows.size else ca.SX(0, 1)
        f = ca.Function("ilq_quad_stage", [zvec[win.tolist()], p], [e])
        # re-evaluated on fresh symbols: the serialization then no longer carries the
        # trajectory's symbol names, so stages with the same graph compare equal
        w_s, p_s = ca.SX.sym("w", win.size), ca.SX.sym("p", p.shape[0])
        f = ca.Function("ilq_quad_stage", [w_s, p_s], f.call([w_s, p_s]))
        key = (f.serialize(), t_local[sel].tobytes(), k < K, rr.size)
        grp = groups.get(key)
        if grp is None:
            if len(groups) >= MAX_GROUPS:
                return None
            grp = groups[key] = {"f": f, "ks": [], "wins": [], "n": (sel.size, phi_k.size)}
            grp["rr"] = []
        grp["ks"].append(k)
        grp["wins"].append(win)
        grp["rr"].append(rr)
    out = []
    for gi, grp in enumerate(groups.values()):
        ks = np.asarray(grp["ks"])
        m = ks.size
        f = grp["f"]
        fn = f.map(f"ilq_quad_{gi}", "serial", m, [1], [])
        sel0 = np.nonzero(t_stage == ks[0])[0]
        local = np.sort(t_local[sel0])
        base = np.where(ks < K, ks * (N * n * n), n_stage)
        nl, nph = grp["n"]
        segments = [(0, 0, nl, (base[:, None] + local[None, :]).reshape(-1).astype(np.intp))]
        if nph:
            tgt_p = solver._phi_tgt.reshape(K, m_phi)[ks].reshape(-1).astype(np.intp)
            segments.append((1, nl, nl + nph, tgt_p))
        nrr = grp["rr"][0].size
        if nrr:
            segments.append((2, nl + nph, nl + nph + nrr, np.stack(grp["rr"]).reshape(-1)))
        out.append(
            {
                "fn": fn,
                "win": np.stack(grp["wins"]).astype(np.intp),
                "segments": segments,
                "n_instr": f.n_instructions(),
            }
        )
    tag = f"ilq_quad_n{N}_k{K}"
    if n_r:
        g = solver.game
        member = np.zeros((N, n_r))
        for i, a in enumerate(g.agent_names):
            for t in g.terms:
                if a in t.agents:
                    member[i, t.rows] = 1.0
        return CompiledQuadratize(solver, out, None, tag, member, n_r)
    cost_fn = ca.Function("ilq_costs", [Xs, Us, p], [C, E], ["X", "U", "p"], ["C", "E"])
    return CompiledQuadratize(solver, out, cost_fn, tag)


class CompiledRollout:
    """The closed-loop rollout as one generated-C stage function folded over ``K`` stages.

    The stage is the body of :meth:`solvers.ilq.ILQSolver._build_rollout` (same SX
    operations): ``(x_k, dY_k), Xr_k, Ur_k, [P_k | a_k], eps -> (x_k+1, dY_k+1), U_k``.
    ``__call__`` has the signature of the interpreted ``ilq_rollout`` function.
    """

    def __init__(self, solver):
        from .codegen import BufferCall as _Call
        from .codegen import compile_functions

        K, nx, nu, nxs, na = solver.K, solver.nx, solver.nu, solver.nxs, solver.na
        s = ca.SX.sym("s", nx + na)
        xr, ur = ca.SX.sym("xr", nx), ca.SX.sym("ur", nu)
        pa_c = ca.SX.sym("pa", (nxs + 1) * nu)
        eps = ca.SX.sym("eps")
        x, dy = s[:nx], s[nx:]
        pa = ca.reshape(pa_c, nxs + 1, nu).T
        u = ur - ca.mtimes(pa[:, :nxs], ca.vertcat(x - xr, dy)) - eps * pa[:, nxs]
        dy_next = ca.vertcat(u - ur, x - xr)[solver.aug.tolist()] if na else ca.SX(0, 1)
        x_next = solver._joint_step(x, u)
        stage = ca.Function(
            "ilq_roll_stage", [s, xr, ur, pa_c, eps], [ca.vertcat(x_next, dy_next), u]
        )
        acc = stage.mapaccum("ilq_roll", K, [0], [0])
        acc = ca.Function("ilq_roll", acc.mx_in(), acc.call(acc.mx_in()))
        self.call = _Call(compile_functions([acc], "ilq_roll", optimize="-O1")["ilq_roll"])
        self.K, self.nx, self.na = K, nx, na

    def __call__(self, x0, Xr, Ur, PA, eps):
        K, nx, na = self.K, self.nx, self.na
        s0 = np.concatenate([np.asarray(x0, float), np.zeros(na)])
        S, U = self.call(s0, np.asarray(Xr)[:K], Ur, PA, np.full(K, float(eps)))
        X = np.empty((K + 1, nx))
        X[0] = x0
        X[1:] = S.reshape(K, nx + na)[:, :nx]
        return X, U
