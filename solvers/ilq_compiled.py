"""The compiled stage functions of :mod:`solvers.fast_ilq` and the one-call trial.

:func:`build` splits the solver's interpreted quadratization into stage functions found from
the graph (:class:`CompiledQuadratize`; ``None`` where the split does not pay or cannot be
made: :data:`MAX_WINDOW`, :data:`MAX_GROUPS`), :class:`CompiledRollout` is the closed-loop
rollout as one function, and :class:`CompiledTrial` joins rollout, stage groups and the
Riccati fold into one generated call per line-search trial. They are compiled into the
solver's library by :func:`solvers.fast_ilq.compile_solver`; the method is described in
:mod:`solvers.fast_ilq`.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .codegen import BufferCall as _Call

#: Largest distance (in stages) between a stage and a stage its outputs depend on.
MAX_WINDOW = 2
#: Largest number of distinct stage functions (compile time grows with it).
MAX_GROUPS = 12


class CompiledQuadratize:
    """The quadratization as mapped, compiled stage functions (see :mod:`solvers.fast_ilq`).

    ``__call__(X, U, p) -> (C, E)`` fills ``solver.Lam`` and ``solver.Phi`` like
    :meth:`solvers.ilq.ILQSolver.quadratize`.
    """

    def __init__(self, solver, groups, cost_fn, member=None, n_r: int = 0):
        self.s = solver
        self.fns = [g["fn"] for g in groups]  # mapped stage functions (compiled by attach)
        self.stages = [g["stage"] for g in groups]  # the same, one stage (CompiledWideTrial)
        self.spec = [(g["win"], g["segments"]) for g in groups]
        self.groups = []
        self.costs = None if cost_fn is None else _Call(cost_fn)
        self.member = member  # (N, n_r) 0/1: residual row in one of player i's terms
        self.r = np.zeros(n_r)
        self.n_r = n_r
        self.n_groups = len(groups)
        self.n_instructions = [int(g["n_instr"]) for g in groups]

    def attach(self, lib: dict) -> None:
        """Use the compiled stage functions of ``lib`` (:func:`compile_solver`)."""
        self.groups = [
            (_Call(lib[f.name()]), win, seg)
            for f, (win, seg) in zip(self.fns, self.spec, strict=True)
        ]

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
    """Split ``solver``'s quadratization into stage groups (or ``None``), not compiled yet:
    :func:`compile_solver` compiles them with the rest and attaches the library."""
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
                "stage": f,
                "win": np.stack(grp["wins"]).astype(np.intp),
                "segments": segments,
                "n_instr": f.n_instructions(),
            }
        )
    if n_r:
        g = solver.game
        member = np.zeros((N, n_r))
        for i, a in enumerate(g.agent_names):
            for t in g.terms:
                if a in t.agents:
                    member[i, t.rows] = 1.0
        return CompiledQuadratize(solver, out, None, member, n_r)
    cost_fn = ca.Function("ilq_costs", [Xs, Us, p], [C, E], ["X", "U", "p"], ["C", "E"])
    return CompiledQuadratize(solver, out, cost_fn)


class CompiledRollout:
    """The closed-loop rollout as one generated-C stage function folded over ``K`` stages.

    The stage is the body of :func:`solvers.ilq.rollout.build_rollout` (same SX
    operations): ``(x_k, dY_k), Xr_k, Ur_k, [P_k | a_k], eps -> (x_k+1, dY_k+1), U_k``.
    ``__call__`` has the signature of the interpreted ``ilq_rollout`` function.
    """

    def __init__(self, solver):
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
        self.stage = stage  # one stage (CompiledWideTrial: the same SX on several starts)
        acc = stage.mapaccum("ilq_roll", K, [0], [0])
        self.fn = ca.Function("ilq_roll", acc.mx_in(), acc.call(acc.mx_in()))
        self.call = None
        self.K, self.nx, self.na = K, nx, na

    def attach(self, lib: dict) -> None:
        """Use the compiled fold of ``lib`` (:func:`compile_solver`)."""
        self.call = _Call(lib["ilq_roll"])

    def __call__(self, x0, Xr, Ur, PA, eps):
        K, nx, na = self.K, self.nx, self.na
        s0 = np.concatenate([np.asarray(x0, float), np.zeros(na)])
        S, U = self.call(s0, np.asarray(Xr)[:K], Ur, PA, np.full(K, float(eps)))
        X = np.empty((K + 1, nx))
        X[0] = x0
        X[1:] = S.reshape(K, nx + na)[:, :nx]
        return X, U


class CompiledTrial:
    """One step of the iteration as one generated-C call: rollout, quadratization, Riccati.

    ``(x0, Xr, Ur, PA, eps, p, mu0, delta) -> (X, U, PA', mu', r)``: the closed-loop rollout
    from ``(Xr, Ur)`` with ``[P | a]`` and step ``eps`` (:class:`CompiledRollout`), the stage
    functions of :class:`CompiledQuadratize` on its windows, their outputs gathered into the
    Riccati fold's inputs (the numpy scatter into ``Lam``/``Phi`` and the gather of
    :meth:`solvers.ilq.riccati.CompiledRiccati.backward`, as one index table), the fold, and the
    residual rows ``r``. The same compiled functions on the same numbers as the separate
    calls, so the results are bit-identical to them; Python makes one call per line-search
    trial instead of five. ``PA = 0, eps = 0`` linearizes at ``(Xr, Ur)`` itself (the
    rollout then reproduces ``Xr`` from ``x0`` and ``Ur``). Game costs only (the residual
    rows give ``C`` and ``E``).
    """

    def __init__(self, solver, quad: CompiledQuadratize, roll: CompiledRollout, ric):
        s = solver
        K, N, n, nx, nu, nxs, na = s.K, s.N, s.n, s.nx, s.nu, s.nxs, s.na
        self.s, self.quad = s, quad
        x0 = ca.MX.sym("x0", nx)
        Xr, Ur = ca.MX.sym("Xr", nx, K + 1), ca.MX.sym("Ur", nu, K)
        PA = ca.MX.sym("PA", (nxs + 1) * nu, K)
        eps, p = ca.MX.sym("eps"), ca.MX.sym("p", s.game.n_p)
        mu0, delta = ca.MX.sym("mu0"), ca.MX.sym("delta")
        S, U = roll.fn(ca.vertcat(x0, ca.MX.zeros(na)), Xr[:, :K], Ur, PA, ca.repmat(eps, 1, K))
        X = ca.horzcat(x0, S[:nx, :])
        v = ca.vertcat(ca.vec(U), ca.vec(X))  # = concat(U.ravel(), X.ravel()) numerically
        # every written entry of Lam, Phi and r -> its place in the stacked group outputs
        lam_pos = np.full(s.Lam.size, -1, dtype=np.intp)
        phi_pos = np.full(s.Phi.size, -1, dtype=np.intp)
        r_pos = np.full(quad.n_r, -1, dtype=np.intp)
        dest = (lam_pos, phi_pos, r_pos)
        outs, off, offsets = [], 0, []
        for fn, (win, segments) in zip(quad.fns, quad.spec, strict=True):
            offsets.append(off)
            m, w = win.shape
            out = fn(ca.reshape(v[win.reshape(-1).tolist()], w, m), p)  # (n_out, m)
            n_out = out.shape[0]
            outs.append(ca.vec(out))
            for b, lo, hi, tgt in segments:
                pos = off + (np.arange(m)[:, None] * n_out + np.arange(lo, hi)[None, :])
                dest[b][tgt] = pos.reshape(-1)  # later writes win, as in the numpy scatter
            off += m * n_out
        zero = off  # a zero appended: entries no stage function writes stay zero in Lam
        allout = ca.vertcat(*outs, ca.MX.zeros(1))

        gathers = {}  # Riccati and output input -> position in allout (CompiledWideTrial)

        def take(pos, key):
            pos = gathers[key] = np.where(pos < 0, zero, pos).reshape(-1)
            return allout[pos.tolist()]

        m1, n_stage = nxs + 1, K * N * n * n
        t = s._term
        # terminal values Z_iK = Lam_K[(x, 1), (x, 1)], column-major per player
        zi = n_stage + (np.arange(N)[:, None, None] * n + t[None, None, :]) * n + t[None, :, None]
        Zc = ca.reshape(take(lam_pos[zi], "Z"), m1, N * m1)
        rev = np.arange(K - 1, -1, -1)
        lam_idx = rev[:, None] * (N * n * n) + ric._lam_cols[None]
        lam = ca.reshape(take(lam_pos[lam_idx], "lam"), -1, K)
        phi_idx = rev[:, None] * (m1 * n) + ric._phi_cols[None]
        phi = ca.reshape(take(phi_pos[phi_idx], "phi"), -1, K)
        _, PAr, mur = ric.acc(Zc, lam, phi, ca.repmat(mu0, 1, K), ca.repmat(delta, 1, K))
        PAo, muo = PAr[:, rev.tolist()], mur[:, rev.tolist()]
        r = take(r_pos, "r") if quad.n_r else ca.MX(0, 1)
        # the graph's data movement, for the same arithmetic on several starts at once
        self.layout = {"gathers": gathers, "offsets": offsets, "n_all": zero + 1}
        self.roll, self.ric = roll, ric
        self.wide = None  # CompiledWideTrial after compile_solver, where it applies
        self.fn = ca.Function(
            "ilq_trial",
            [x0, Xr, Ur, PA, eps, p, mu0, delta],
            [X, U, PAo, muo, r],
            ["x0", "Xr", "Ur", "PA", "eps", "p", "mu0", "delta"],
            ["X", "U", "PA_out", "mu", "r"],
        )
        self.call = None

    def attach(self, lib: dict) -> None:
        """Use the compiled function of ``lib`` (:func:`compile_solver`): its buffers are
        bound once to preallocated arrays (a call copies the inputs in, no allocation)."""
        f = self.call = lib["ilq_trial"]
        self._buf, self._ev = f.buffer()
        self._in = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
        self._out = [np.empty(f.nnz_out(i)) for i in range(f.n_out())]
        for i, a in enumerate(self._in):
            self._buf.set_arg(i, memoryview(a))
        for i, o in enumerate(self._out):
            self._buf.set_res(i, memoryview(o))

    def __call__(self, p, Xr, Ur, PA, eps, mu0, delta):
        """``(X, U, C, E, PA, mu, ok)``: the trial trajectory and the linearization there,
        as :meth:`solvers.ilq.ILQSolver.rollout`, ``quadratize`` and ``backward`` give them.
        ``PA = None``: linearize at ``(Xr, Ur)`` (a rollout of ``Ur``)."""
        s = self.s
        K, nx, nu = s.K, s.nx, s.nu
        i_x0, i_X, i_U, i_PA, i_eps, i_p, i_mu, i_d = self._in
        np.take(p, s._x0_idx, out=i_x0)
        i_X[:] = Xr.reshape(-1)
        i_U[:] = Ur.reshape(-1)
        if PA is None:
            i_PA.fill(0.0)
            i_eps[0] = 0.0
        else:
            i_PA[:] = PA.reshape(-1)
            i_eps[0] = eps
        i_p[:] = p
        i_mu[0], i_d[0] = mu0, delta
        self._ev()
        o_X, o_U, o_PA, o_mu, r = self._out
        X = o_X.reshape(K + 1, nx).copy()
        U = o_U.reshape(K, nu).copy()
        PAo = o_PA.reshape(K, nu, s.nxs + 1).copy()
        mu = o_mu.reshape(K, s.N).copy()
        r2 = r * r
        C, E = 0.5 * (self.quad.member @ r2), 0.5 * float(np.sum(r2))
        ok = bool(np.isfinite(PAo).all())
        if not ok:  # singular stage: as CompiledRiccati.backward, numpy with larger shifts
            self.quad(X, U, p)  # fills Lam and Phi
            PAo, mu, ok = s._numpy_backward(mu0, delta)
        return X, U, C, E, PAo, mu, ok
