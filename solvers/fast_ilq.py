"""Generated C for :mod:`solvers.ilq` (``compiled=True``): stage functions, one call per trial.

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
3. Each group's function is mapped over its stages (``Function.map``, ``p`` shared). A
   call gathers the stage windows with one numpy index per group.

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

One call per line-search trial (:class:`CompiledTrial`, the game's own costs): the
closed-loop rollout (:class:`CompiledRollout`), the stage groups on its windows, one index
table from their outputs to the Riccati fold's inputs (what the numpy scatter into
``Lam``/``Phi`` and the gather of ``CompiledRiccati.backward`` did) and the fold itself, as
one generated MX function around the same compiled SX functions: the separate calls'
numbers bit for bit, with Python once per trial instead of five calls with numpy glue.

Many starts at once (:class:`CompiledWideTrial`, built on the first batched solve by
:func:`wide_trial`): the one-call trial's SX stage functions written again on vectors of
:data:`WIDE_LANES` starts (:func:`wide_function_source`: one C statement per SX
instruction, GCC vector extensions, FMA contraction off, library functions lane by lane)
and its data movement as C around them (:func:`wide_trial_source`), compiled by
:func:`solvers.codegen.compile_kernel`; each lane equals the scalar trial bit for bit.

:func:`compile_solver` compiles all of it into one library per game structure
(``ilq_n<N>_k<K>_<cpu>``, cached on disk by the functions' serialization, never by
parameter values) with :data:`OPTIMIZE`: ``-O3`` vector code for this CPU, FMA contraction
off, so the numbers equal ``-O1``'s bit for bit (docs/ilq.md, "Benchmark").
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from .codegen import BufferCall as _Call

__all__ = [
    "MAX_GROUPS",
    "MAX_WINDOW",
    "OPTIMIZE",
    "WIDE_LANES",
    "CompiledQuadratize",
    "CompiledRollout",
    "CompiledTrial",
    "CompiledWideTrial",
    "WideUnsupported",
    "build",
    "compile_solver",
    "trial_stats",
    "wide_function_external",
    "wide_function_source",
    "wide_trial",
    "wide_trial_source",
]

#: Largest distance (in stages) between a stage and a stage its outputs depend on.
MAX_WINDOW = 2
#: Largest number of distinct stage functions (compile time grows with it).
MAX_GROUPS = 12
#: gcc flags of the iLQ library (:func:`compile_solver`): vector code for this CPU at
#: ``-O3``, without FMA contraction, so the numbers equal ``-O1``'s bit for bit. The
#: library's name carries the CPU (:func:`_cpu_tag`): a cache shared by several machines
#: never loads it on another CPU. A compiler that rejects the flags gets ``-O1``.
OPTIMIZE = "-O3 -march=native -ffp-contract=off -fno-math-errno"


def _cpu_tag() -> str:
    """A short hash of this CPU's model and instruction-set flags (``/proc/cpuinfo``)."""
    import hashlib
    import platform

    info = platform.machine() + platform.processor()
    try:
        with open("/proc/cpuinfo") as fh:
            lines = fh.read().split("\n\n")[0].splitlines()
        info += "".join(ln for ln in lines if ln.split(":")[0].strip() in ("model name", "flags"))
    except OSError:
        pass
    return hashlib.sha256(info.encode()).hexdigest()[:8]


class CompiledQuadratize:
    """The quadratization as mapped, compiled stage functions (see the module docstring).

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


def compile_solver(solver, optimize: str | None = None, trial: bool = True) -> None:
    """Build and compile every generated-C path of ``solver`` as one library.

    Sets ``solver._compiled`` (the Riccati fold), ``_croll`` (the rollout), ``_cquad`` (the
    stage-split quadratization, or ``None``: :func:`build`) and ``_ftrial``
    (:class:`CompiledTrial`, with the game's own costs only, else ``None``). One library
    ``ilq_n<N>_k<K>_<cpu>``, compiled with ``optimize`` (default :data:`OPTIMIZE`; ``-O1``
    when the compiler rejects it) and cached on disk by the functions' serialization.
    ``trial=False`` leaves the one-call trial out (the separate calls: a benchmark's
    reference, ``bench/bench_ilq.py``).
    """
    from .codegen import CompilerError, compile_functions

    ric = solver.riccati_fold()  # the solver's own Riccati fold, not compiled yet
    quad = build(solver, *solver._quad_sym)
    roll = CompiledRollout(solver)
    funcs = [ric.acc, roll.fn] + ([] if quad is None else quad.fns)
    ftrial = None
    if trial and quad is not None and quad.costs is None:
        ftrial = CompiledTrial(solver, quad, roll, ric)
        funcs.append(ftrial.fn)
    name = f"ilq_n{solver.N}_k{solver.K}"
    try:
        lib = compile_functions(funcs, f"{name}_{_cpu_tag()}", optimize=optimize or OPTIMIZE)
    except CompilerError:  # a compiler without these flags: the portable -O1 build
        lib = compile_functions(funcs, name, optimize="-O1")
    for part in (ric, roll, quad, ftrial):
        if part is not None:
            part.attach(lib)
    solver._compiled, solver._croll, solver._cquad, solver._ftrial = ric, roll, quad, ftrial
    solver.quad_backend = "interpreted" if quad is None else "compiled"


# --------------------------------------------------------------------------------------
# several starts at once: the one-call trial on vectors of starts
# --------------------------------------------------------------------------------------
#: starts one call of :class:`CompiledWideTrial` evaluates together: 8 doubles fill one
#: AVX-512 register (two AVX2 or four SSE2 ones)
WIDE_LANES = 8

# C of each SX operation on vectors of WIDE_LANES doubles (GCC vector extensions), as
# CasADi's generated C writes it for one double (casadi_sq(x) = x*x, (2.*x), (1./x), ...):
# arithmetic on whole vectors; comparisons and logic as masks (-1 or 0 per lane) turned
# into 1.0 or 0.0; library functions lane by lane (the same libm calls)
_WIDE_ARITH = {
    "ADD": "{a}+{b}",
    "SUB": "{a}-{b}",
    "MUL": "{a}*{b}",
    "DIV": "{a}/{b}",
    "NEG": "-{a}",
    "SQ": "{a}*{a}",
    "TWICE": "2.*{a}",
    "INV": "1./{a}",
    "ASSIGN": "{a}",
}
_WIDE_MASK = {
    "LT": "{a}<{b}",
    "LE": "{a}<={b}",
    "EQ": "{a}=={b}",
    "NE": "{a}!={b}",
    "NOT": "{a}==0",
    "AND": "({a}!=0)&({b}!=0)",
    "OR": "({a}!=0)|({b}!=0)",
}
# selections on whole vectors: fabs clears the sign bit; fmax and fmin as glibc's x86-64
# fmax/fmin (maxsd/minsd: the second argument on ties and for a NaN first one, the first
# for a NaN second one), elsewhere glibc's functions lane by lane (EPO_SELECT)
_WIDE_SELECT = {
    "FABS": "(vd)((vl){a} & ~(vl)(-zero))",
    "FMAX": "EPO_FMAX({a},{b})",
    "FMIN": "EPO_FMIN({a},{b})",
}
_WIDE_LIB = {
    "SQRT": "sqrt({a})",
    "SIGN": "({a}<0 ? -1 : {a}>0 ? 1 : {a})",
    "SIN": "sin({a})",
    "COS": "cos({a})",
    "TAN": "tan({a})",
    "ASIN": "asin({a})",
    "ACOS": "acos({a})",
    "ATAN": "atan({a})",
    "ATAN2": "atan2({a},{b})",
    "SINH": "sinh({a})",
    "COSH": "cosh({a})",
    "TANH": "tanh({a})",
    "ASINH": "asinh({a})",
    "ACOSH": "acosh({a})",
    "ATANH": "atanh({a})",
    "EXP": "exp({a})",
    "LOG": "log({a})",
    "POW": "pow({a},{b})",
    "CONSTPOW": "pow({a},{b})",
    "FLOOR": "floor({a})",
    "CEIL": "ceil({a})",
    "FMOD": "fmod({a},{b})",
    "REMAINDER": "remainder({a},{b})",
    "COPYSIGN": "copysign({a},{b})",
    "ERF": "erf({a})",
}
_OP_NAMES = {getattr(ca, k): k[3:] for k in dir(ca) if k.startswith("OP_")}


def _c_double(v: float) -> str:
    """``v`` as an exact C literal (hexadecimal; INFINITY, NAN)."""
    v = float(v)
    if math.isnan(v):
        return "NAN"
    if math.isinf(v):
        return "INFINITY" if v > 0 else "(-INFINITY)"
    return f"({v.hex()})"


class WideUnsupported(ValueError):
    """An SX operation or a sparsity that :func:`wide_function_source` does not write."""


def _sincos_pairs(f: ca.Function, code: list[str]) -> dict[int, str]:
    """Statements for the SIN and COS instructions of ``f`` that take the same value (no
    write to its work variable between them): the first computes both lane by lane with
    ``sincos`` (as gcc does for the scalar code) into a temporary, the second copies it."""
    out: dict[int, str] = {}
    n = len(code)
    for k in range(n):
        if code[k] not in ("SIN", "COS") or k in out:
            continue
        a, o1 = f.instruction_input(k)[0], f.instruction_output(k)[0]
        if o1 == a:  # the value is overwritten by the first one
            continue
        want = "COS" if code[k] == "SIN" else "SIN"
        for q in range(k + 1, n):
            if q not in out and code[q] == want and f.instruction_input(q)[0] == a:
                o2 = f.instruction_output(q)[0]
                first, second = ("s", "c") if code[k] == "SIN" else ("c", "s")
                out[k] = f"  EPO_SINCOS(w{a}, s{k}, c{k}); w{o1} = {first}{k};"
                out[q] = f"  w{o2} = {second}{k};"
                break
            if code[q] != "OUTPUT" and f.instruction_output(q)[0] == a:
                break  # the value was overwritten
    return out


def wide_function_source(f: ca.Function, name: str, indexed=()) -> str:
    """C of the SX function ``f`` on :data:`WIDE_LANES` lanes at once: ``static void
    name(const vd* const* in, const int* const* ix, vd* const* out)``, every input and
    output as vectors ``vd`` of its nonzeros (outputs as all their entries, structural
    zeros written as 0); an input ``i`` in ``indexed`` is read through its index table,
    nonzero ``j`` at ``in[i][ix[i][j]]`` (a gather without a copy).

    One C statement per instruction of ``f`` in ``f``'s order, each lane computing what
    CasADi's generated C computes for one double (:data:`_WIDE_ARITH` and the tables
    beside it), so with FMA contraction off every lane equals ``f``'s compiled code bit
    for bit. :class:`WideUnsupported` for an operation outside the tables or a sparse input.
    """
    if not f.is_a("SXFunction"):
        raise WideUnsupported(f"{f.name()}: not an SX function")
    for i in range(f.n_in()):
        if not f.sparsity_in(i).is_dense():
            raise WideUnsupported(f"{f.name()}: input {i} is sparse")
    rows = []  # per output: entry (column-major) of each nonzero
    body = []
    for i in range(f.n_out()):
        sp = f.sparsity_out(i)
        r, c = (np.asarray(v, dtype=int) for v in sp.get_triplet())
        ent = c * sp.size1() + r
        rows.append(ent)
        for e in sorted(set(range(sp.numel())) - set(ent.tolist())):
            body.append(f"  out[{i}][{e}] = zero;")
    W = WIDE_LANES
    code = [_OP_NAMES.get(f.instruction_id(k), "?") for k in range(f.n_instructions())]
    pairs = _sincos_pairs(f, code)
    for k in range(f.n_instructions()):
        op = code[k]
        ins, outs = f.instruction_input(k), f.instruction_output(k)
        if k in pairs:  # sin and cos of the same value: one sincos, the second kept
            body.append(pairs[k])
            continue
        if op == "INPUT":
            j = f"ix[{ins[0]}][{ins[1]}]" if ins[0] in indexed else str(ins[1])
            body.append(f"  w{outs[0]} = in[{ins[0]}][{j}];")
            continue
        if op == "OUTPUT":
            body.append(f"  out[{outs[0]}][{rows[outs[0]][outs[1]]}] = w{ins[0]};")
            continue
        o = f"w{outs[0]}"
        if op == "CONST":
            body.append(f"  {o} = zero + {_c_double(f.instruction_constant(k))};")
            continue
        a = f"w{ins[0]}"
        b = f"w{ins[1]}" if len(ins) > 1 else None
        if op in _WIDE_ARITH:
            body.append(f"  {o} = " + _WIDE_ARITH[op].format(a=a, b=b) + ";")
        elif op in _WIDE_MASK:
            body.append(f"  {o} = (vd)((" + _WIDE_MASK[op].format(a=a, b=b) + ") & one);")
        elif op in _WIDE_SELECT:
            body.append(f"  {o} = " + _WIDE_SELECT[op].format(a=a, b=b) + ";")
        elif op == "IF_ELSE_ZERO":  # (a ? b : 0)
            body.append(f"  {o} = (vd)(({a}!=0) & (vl){b});")
        elif op in _WIDE_LIB:
            e = _WIDE_LIB[op].format(a=f"{a}[l]", b=f"{b}[l]" if b else None)
            body.append(f"  {{ vd t; for (l = 0; l < {W}; ++l) t[l] = {e}; {o} = t; }}")
        else:
            raise WideUnsupported(f"{f.name()}: operation {op}")
    n = max(f.sz_w(), 1)
    head = [
        f"static EPO_CLONES void {name}(const vd* const* in, const int* const* ix, "
        "vd* const* out) {",
        "  const vd zero = {0};",
        "  const vl one = (vl)(zero + 1.0);",
        "  vd " + ", ".join(f"w{j}" for j in range(n)) + ";",
        "  int l;",
        "  (void)l;",
        "  (void)one;",
        "  (void)ix;",
    ]
    return "\n".join(head + body + ["}"])


_WIDE_HEAD = r"""
#define _GNU_SOURCE
#include <float.h>
#include <math.h>
#include <stdint.h>
#pragma GCC optimize("fp-contract=off")
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11 && defined(__x86_64__) && \
    defined(__linux__)
#define EPO_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define EPO_CLONES
#endif
typedef double vd __attribute__((vector_size(8 * EPO_W)));
typedef long long vl __attribute__((vector_size(8 * EPO_W)));
static inline vd epo_pick(vl m, vd a, vd b) { return (vd)(((vl)a & m) | ((vl)b & ~m)); }
#if defined(__x86_64__) && defined(__GLIBC__)
#define EPO_FMAX(a, b) epo_pick(((a) > (b)) | ((b) != (b)), (a), (b))
#define EPO_FMIN(a, b) epo_pick(((a) < (b)) | ((b) != (b)), (a), (b))
#else
static inline vd epo_fmax(vd a, vd b) {
  int l;
  for (l = 0; l < EPO_W; ++l) a[l] = fmax(a[l], b[l]);
  return a;
}
static inline vd epo_fmin(vd a, vd b) {
  int l;
  for (l = 0; l < EPO_W; ++l) a[l] = fmin(a[l], b[l]);
  return a;
}
#define EPO_FMAX(a, b) epo_fmax((a), (b))
#define EPO_FMIN(a, b) epo_fmin((a), (b))
#endif
#if defined(__GLIBC__)
#define EPO_SINCOS1(x, s, c) sincos((x), &(s), &(c))
#else
#define EPO_SINCOS1(x, s, c) ((s) = sin(x), (c) = cos(x))
#endif
/* s = sin(x), c = cos(x) lane by lane (declares s and c) */
#define EPO_SINCOS(x, s, c)                  \
  vd s, c;                                   \
  for (l = 0; l < EPO_W; ++l) {              \
    double s_, c_;                           \
    EPO_SINCOS1((x)[l], s_, c_);             \
    s[l] = s_;                               \
    c[l] = c_;                               \
  }
"""

# the driver: one call evaluates EPO_W starts (inputs and outputs start after start, as
# CompiledTrial's function has them); every intermediate array holds vectors of starts
_WIDE_DRIVER = r"""
#if EPO_W == 8
typedef long long vi __attribute__((vector_size(64)));
/* the 8 x 8 block r[i][j] -> r[j][i] (three rounds of shuffles) */
static inline void tr8(vd* r) {
  const vi lo1 = {0, 8, 2, 10, 4, 12, 6, 14}, hi1 = {1, 9, 3, 11, 5, 13, 7, 15};
  const vi lo2 = {0, 1, 8, 9, 4, 5, 12, 13}, hi2 = {2, 3, 10, 11, 6, 7, 14, 15};
  const vi lo3 = {0, 1, 2, 3, 8, 9, 10, 11}, hi3 = {4, 5, 6, 7, 12, 13, 14, 15};
  vd t[8], u[8];
  int i;
  for (i = 0; i < 8; i += 2) {
    t[i] = __builtin_shuffle(r[i], r[i + 1], lo1);
    t[i + 1] = __builtin_shuffle(r[i], r[i + 1], hi1);
  }
  for (i = 0; i < 8; i += 4) {
    u[i] = __builtin_shuffle(t[i], t[i + 2], lo2);
    u[i + 2] = __builtin_shuffle(t[i], t[i + 2], hi2);
    u[i + 1] = __builtin_shuffle(t[i + 1], t[i + 3], lo2);
    u[i + 3] = __builtin_shuffle(t[i + 1], t[i + 3], hi2);
  }
  for (i = 0; i < 4; ++i) {
    r[i] = __builtin_shuffle(u[i], u[i + 4], lo3);
    r[i + 4] = __builtin_shuffle(u[i], u[i + 4], hi3);
  }
}
#endif
/* starts one after the other (src[l n + j]) -> vectors of starts (dst[j][l]) */
static EPO_CLONES void pack(const double* src, vd* dst, int n) {
  double* d = (double*)dst;
  int j = 0, l;
  if (!src) {
    for (j = 0; j < n * EPO_W; ++j) d[j] = 0.0;
    return;
  }
#if EPO_W == 8
  for (; j + 8 <= n; j += 8) {
    vd r[8];
    for (l = 0; l < 8; ++l) __builtin_memcpy(&r[l], src + l * n + j, sizeof(vd));
    tr8(r);
    for (l = 0; l < 8; ++l) dst[j + l] = r[l];
  }
#endif
  for (l = 0; l < EPO_W; ++l)
    for (int q = j; q < n; ++q) d[q * EPO_W + l] = src[l * n + q];
}
/* the inverse of pack, into rows of length stride from column at */
static EPO_CLONES void unpack(const vd* src, double* dst, int n, int stride, int at) {
  const double* s = (const double*)src;
  int j = 0, l;
  if (!dst) return;
#if EPO_W == 8
  for (; j + 8 <= n; j += 8) {
    vd r[8];
    for (l = 0; l < 8; ++l) r[l] = src[j + l];
    tr8(r);
    for (l = 0; l < 8; ++l) __builtin_memcpy(dst + l * stride + at + j, &r[l], sizeof(vd));
  }
#endif
  for (l = 0; l < EPO_W; ++l)
    for (int q = j; q < n; ++q) dst[l * stride + at + q] = s[q * EPO_W + l];
}
static EPO_CLONES void gather(const vd* all, const int* idx, vd* dst, int n) {
  int j;
  for (j = 0; j < n; ++j) dst[j] = all[idx[j]];
}
/* per start (solvers.ilq.iteration._Evaluation reads them): PA finite; X, U finite;
   max |a| (NaN if one is); sum of a*a exactly rounded (pairwise in long double, kept
   where both ends of its error bound round to the same double, else NaN); r*r finite
   and summing below 1e300 */
static EPO_CLONES void stats(const vd* PAr, const vd* V, const vd* ALL, double* st) {
  const vd zero = {0};
  const vl one = (vl)(zero == zero);
  const vd nan = zero + NAN;
  vl ok = one, good = one, isnan = (vl)zero, cok = one;
  vd r = zero, sq = zero, v;
  int j, i, k, l, h;
  for (j = 0; j < EPO_K * EPO_NPA; ++j) ok &= (PAr[j] - PAr[j]) == zero;
  for (j = 0; j < EPO_NV; ++j) good &= (V[j] - V[j]) == zero;
  for (k = 0; k < EPO_K; ++k)
    for (i = 0; i < EPO_NU; ++i) {
      v = (vd)((vl)PAr[k * EPO_NPA + i * (EPO_NXS + 1) + EPO_NXS] & ~(vl)(-zero));
      isnan |= v != v;
      r = epo_pick(v > r, v, r);
    }
  r = epo_pick(isnan, nan, r);
  for (j = 0; j < EPO_NR; ++j) {
    v = ALL[epo_tr[j]] * ALL[epo_tr[j]];
    cok &= (v - v) == zero;
    sq += v;
  }
  cok &= sq < zero + 1e300;
  for (l = 0; l < EPO_W; ++l) {
    long double b[EPO_NA2], e;
    double lo = NAN, hi = 0.0;
    if (ok[l]) {
      for (k = 0; k < EPO_K; ++k)
        for (i = 0; i < EPO_NU; ++i) {
          double a = PAr[k * EPO_NPA + i * (EPO_NXS + 1) + EPO_NXS][l];
          b[k * EPO_NU + i] = a * a;
        }
      for (j = EPO_K * EPO_NU; j < EPO_NA2; ++j) b[j] = 0.0L;
      for (h = EPO_NA2 / 2; h >= 1; h /= 2)
        for (i = 0; i < h; ++i) b[i] += b[i + h];
      e = b[0] * (long double)(EPO_DEPTH * LDBL_EPSILON);
      lo = (double)(b[0] - e);
      hi = (double)(b[0] + e);
      if (!(lo == hi)) lo = NAN;
    }
    st[l * 5 + 0] = ok[l] ? 1.0 : 0.0;
    st[l * 5 + 1] = good[l] ? 1.0 : 0.0;
    st[l * 5 + 2] = r[l];
    st[l * 5 + 3] = lo;
    st[l * 5 + 4] = cok[l] ? 1.0 : 0.0;
  }
}
static const long long int EPO_FN_sp_in[8][3] = EPO_SP_IN;
static const long long int EPO_FN_sp_out[6][3] = EPO_SP_OUT;
int EPO_FN_n_in(void) { return 8; }
int EPO_FN_n_out(void) { return 6; }
const long long int* EPO_FN_sparsity_in(long long int i) {
  return i >= 0 && i < 8 ? EPO_FN_sp_in[i] : 0;
}
const long long int* EPO_FN_sparsity_out(long long int i) {
  return i >= 0 && i < 6 ? EPO_FN_sp_out[i] : 0;
}
int EPO_FN_work(long long int* sz_arg, long long int* sz_res, long long int* sz_iw,
                long long int* sz_w) {
  if (sz_arg) *sz_arg = 8;
  if (sz_res) *sz_res = 6;
  if (sz_iw) *sz_iw = 0;
  if (sz_w) *sz_w = (long long int)EPO_NWORK * EPO_W + EPO_W;
  return 0;
}
EPO_CLONES int EPO_FN(const double** arg, double** res, long long int* iw, double* w,
                      int mem) {
  vd* wk = (vd*)(((uintptr_t)w + 8 * EPO_W - 1) & ~(uintptr_t)(8 * EPO_W - 1));
  vd *x0 = wk, *Xr = x0 + EPO_NX, *Ur = Xr + (EPO_K + 1) * EPO_NX;
  vd *PA = Ur + EPO_K * EPO_NU, *eps = PA + EPO_K * EPO_NPA, *p = eps + 1;
  vd *mu0 = p + EPO_NP, *del = mu0 + 1, *S = del + 1, *S2 = S + EPO_NS;
  vd *V = S2 + EPO_NS, *ALL = V + EPO_NV, *Z = ALL + EPO_NALL, *Z2 = Z + EPO_NZC;
  vd *PAr = Z2 + EPO_NZC, *mur = PAr + EPO_K * EPO_NPA, *lam = mur + EPO_K * EPO_N;
  vd *phi = lam + EPO_NLAM, *tmp = phi + EPO_NPHI, *sw;
  const vd zero = {0};
  int j, k, l;
  (void)iw;
  (void)mem;
  pack(arg[0], x0, EPO_NX);
  pack(arg[1], Xr, (EPO_K + 1) * EPO_NX);
  pack(arg[2], Ur, EPO_K * EPO_NU);
  pack(arg[3], PA, EPO_K * EPO_NPA);
  pack(arg[4], eps, 1);
  pack(arg[5], p, EPO_NP);
  pack(arg[6], mu0, 1);
  pack(arg[7], del, 1);
  /* closed-loop rollout: s = (x, dY), v = (vec(U), vec(X)) */
  for (j = 0; j < EPO_NX; ++j) S[j] = V[EPO_K * EPO_NU + j] = x0[j];
  for (j = EPO_NX; j < EPO_NS; ++j) S[j] = zero;
  for (k = 0; k < EPO_K; ++k) {
    const vd* in[5] = {S, Xr + k * EPO_NX, Ur + k * EPO_NU, PA + k * EPO_NPA, eps};
    vd* out[2] = {S2, V + k * EPO_NU};
    epo_roll(in, 0, out);
    for (j = 0; j < EPO_NX; ++j) V[EPO_K * EPO_NU + (k + 1) * EPO_NX + j] = S2[j];
    sw = S, S = S2, S2 = sw;
  }
  /* stage functions of the quadratization on their windows of v */
EPO_GROUPS
  ALL[EPO_NALL - 1] = zero;
  /* coupled Riccati recursion, stage K-1 first (PAr, mur: in stage order) */
  gather(ALL, epo_tz, Z, EPO_NZC);
  for (k = 0; k < EPO_K; ++k) {
    const vd* in[5] = {Z, ALL, ALL, mu0, del};
    const int* ix[5] = {0, epo_tlam + k * EPO_NLAM, epo_tphi + k * EPO_NPHI, 0, 0};
    vd* out[3] = {Z2, PAr + (EPO_K - 1 - k) * EPO_NPA, mur + (EPO_K - 1 - k) * EPO_N};
    epo_riccati(in, ix, out);
    sw = Z, Z = Z2, Z2 = sw;
  }
  unpack(V + EPO_K * EPO_NU, res[0], (EPO_K + 1) * EPO_NX, (EPO_K + 1) * EPO_NX, 0);
  unpack(V, res[1], EPO_K * EPO_NU, EPO_K * EPO_NU, 0);
  unpack(PAr, res[2], EPO_K * EPO_NPA, EPO_K * EPO_NPA, 0);
  unpack(mur, res[3], EPO_K * EPO_N, EPO_K * EPO_N, 0);
  gather(ALL, epo_tr, tmp, EPO_NR);
  unpack(tmp, res[4], EPO_NR, EPO_NR, 0);
  if (res[5]) stats(PAr, V, ALL, res[5]);
  (void)l;
  return 0;
}
"""


def wide_function_external(f: ca.Function, name: str) -> str:
    """C of a ``casadi.external`` function evaluating the SX function ``f`` (dense
    outputs) on :data:`WIDE_LANES` lanes: every input and output holds the lanes one after
    the other (``(WIDE_LANES, nnz)``), lane ``l`` computing ``f`` on its own numbers bit for
    bit (:func:`wide_function_source`; the per-operation check of ``tests/test_ilq_batch.py``)."""
    n_in, n_out = f.n_in(), f.n_out()
    for i in range(n_out):
        if not f.sparsity_out(i).is_dense():
            raise WideUnsupported(f"{f.name()}: output {i} is sparse")
    W = WIDE_LANES
    sz_in = [f.nnz_in(i) for i in range(n_in)]
    sz_out = [f.nnz_out(i) for i in range(n_out)]
    sp = lambda szs: "{" + ",".join(f"{{{k * W},1,1}}" for k in szs) + "}"  # noqa: E731
    body = [
        f"static const long long int {name}_spi[{n_in}][3] = {sp(sz_in)};",
        f"static const long long int {name}_spo[{n_out}][3] = {sp(sz_out)};",
        f"int {name}_n_in(void) {{ return {n_in}; }}",
        f"int {name}_n_out(void) {{ return {n_out}; }}",
        f"const long long int* {name}_sparsity_in(long long int i) {{ return {name}_spi[i]; }}",
        f"const long long int* {name}_sparsity_out(long long int i) {{ return {name}_spo[i]; }}",
        f"int {name}(const double** arg, double** res, long long int* iw, double* w, int mem) {{",
        f"  vd in_[{max(sum(sz_in), 1)}], out_[{max(sum(sz_out), 1)}];",
        f"  const vd* in[{max(n_in, 1)}];",
        f"  vd* out[{max(n_out, 1)}];",
        "  int i, j, l;",
        "  (void)iw, (void)w, (void)mem;",
    ]
    off = 0
    for i, k in enumerate(sz_in):
        body.append(f"  in[{i}] = in_ + {off};")
        body.append(f"  for (j = 0; j < {k}; ++j) for (l = 0; l < {W}; ++l)")
        body.append(f"    in_[{off} + j][l] = arg[{i}] ? arg[{i}][l * {k} + j] : 0.0;")
        off += k
    off = 0
    for i, _ in enumerate(sz_out):
        body.append(f"  out[{i}] = out_ + {off};")
        off += sz_out[i]
    body.append(f"  {name}_f(in, 0, out);")
    off = 0
    for i, k in enumerate(sz_out):
        body.append(f"  if (res[{i}]) for (j = 0; j < {k}; ++j) for (l = 0; l < {W}; ++l)")
        body.append(f"    res[{i}][l * {k} + j] = out_[{off} + j][l];")
        off += k
    body += ["  (void)i;", "  return 0;", "}"]
    head = f"#define EPO_W {W}\n" + _WIDE_HEAD
    return head + wide_function_source(f, f"{name}_f") + "\n" + "\n".join(body) + "\n"


def _c_ints(name: str, values) -> str:
    v = np.asarray(values, dtype=np.int64).reshape(-1)
    body = ",".join(str(int(x)) for x in v) if v.size else "0"
    return f"static const int {name}[{max(v.size, 1)}] = {{{body}}};"


def wide_trial_source(trial: CompiledTrial, name: str) -> str:
    """C of :class:`CompiledWideTrial` for the one-call trial ``trial``: its stage
    functions on :data:`WIDE_LANES` starts (:func:`wide_function_source`) and the data
    movement of its graph (rollout fold, stage windows, the index tables into the
    Riccati fold and the outputs), as a ``casadi.external`` function whose inputs and
    outputs are ``trial.fn``'s for :data:`WIDE_LANES` starts, one after the other.
    :class:`WideUnsupported` where it cannot be written."""
    s, quad, lay = trial.s, trial.quad, trial.layout
    f = trial.fn
    for i in range(f.n_out()):
        if not f.sparsity_out(i).is_dense():
            raise WideUnsupported(f"ilq_trial: output {f.name_out(i)} is sparse")
    K, N, nx, nu, nxs, na = s.K, s.N, s.nx, s.nu, s.nxs, s.na
    npa = (nxs + 1) * nu
    g = lay["gathers"]
    parts = [
        wide_function_source(trial.roll.stage, "epo_roll"),
        wide_function_source(trial.ric.stage, "epo_riccati", indexed=(1, 2)),
    ]
    calls, max_win = [], 1
    for gi, (stage, (win, _), off) in enumerate(
        zip(quad.stages, quad.spec, lay["offsets"], strict=True)
    ):
        parts.append(wide_function_source(stage, f"epo_quad{gi}", indexed=(0,)))
        parts.append(_c_ints(f"epo_win{gi}", win))
        m, w = win.shape
        n_out = stage.numel_out(0)
        max_win = max(max_win, w)
        calls.append(
            f"  for (k = 0; k < {m}; ++k) {{\n"
            f"    const vd* in[2] = {{V, p}};\n"
            f"    const int* ix[2] = {{epo_win{gi} + k * {w}, 0}};\n"
            f"    vd* out[1] = {{ALL + {off} + k * {n_out}}};\n"
            f"    epo_quad{gi}(in, ix, out);\n"
            "  }"
        )
    tables = [
        _c_ints("epo_tz", g["Z"]),
        _c_ints("epo_tlam", g["lam"]),
        _c_ints("epo_tphi", g["phi"]),
        _c_ints("epo_tr", g["r"]),
    ]
    n_lam, n_phi = g["lam"].size // K, g["phi"].size // K
    sizes = {
        "EPO_W": WIDE_LANES,
        "EPO_K": K,
        "EPO_N": N,
        "EPO_NX": nx,
        "EPO_NU": nu,
        "EPO_NS": nx + na,
        "EPO_NPA": npa,
        "EPO_NP": s.game.n_p,
        "EPO_NV": K * nu + (K + 1) * nx,
        "EPO_NALL": lay["n_all"],
        "EPO_NZC": g["Z"].size,
        "EPO_NLAM": n_lam,
        "EPO_NPHI": n_phi,
        "EPO_NR": g["r"].size,
        "EPO_NXS": nxs,
        # the exact sum of a*a: 2^depth >= K nu terms, bound 2 depth u (u = LDBL_EPSILON/2)
        "EPO_NA2": 1 << max(1, (K * nu - 1).bit_length()),
        "EPO_DEPTH": max(1, (K * nu - 1).bit_length()),
    }
    tmp_n = max(max_win, g["r"].size)
    sizes["EPO_NWORK"] = (
        nx
        + (K + 1) * nx
        + K * nu
        + K * npa
        + 1
        + s.game.n_p
        + 2
        + 2 * (nx + na)
        + sizes["EPO_NV"]
        + lay["n_all"]
        + 2 * g["Z"].size
        + K * npa
        + K * N
        + n_lam
        + n_phi
        + tmp_n
    )
    sp_in = [[f.nnz_in(i) * WIDE_LANES, 1, 1] for i in range(f.n_in())]
    sp_out = [[f.nnz_out(i) * WIDE_LANES, 1, 1] for i in range(f.n_out())]
    sp_out.append([5 * WIDE_LANES, 1, 1])  # the per-start stats
    defs = "".join(f"#define {k} {v}\n" for k, v in sizes.items())
    arr = lambda rows: "{" + ",".join("{" + ",".join(map(str, r)) + "}" for r in rows) + "}"  # noqa: E731
    driver = (
        _WIDE_DRIVER.replace("EPO_GROUPS", "\n".join(calls))
        .replace("EPO_SP_IN", arr(sp_in))
        .replace("EPO_SP_OUT", arr(sp_out))
        .replace("EPO_FN", name)
    )
    return defs + _WIDE_HEAD + "\n".join(parts + tables) + driver


class CompiledWideTrial:
    """:class:`CompiledTrial` for many starts: ``__call__(*inputs)`` with every input
    ``(m, nnz)`` (``m`` starts, ``trial.fn``'s inputs one row each) returns its outputs
    ``(m, nnz)``, as :class:`solvers.batch.BatchFunction` of ``trial.fn`` does, bit for
    bit, and per start ``(ok, good, res, asum, c_ok)`` (:func:`trial_stats`), evaluating
    :data:`WIDE_LANES` starts per call of the kernel
    (:func:`wide_trial_source`, compiled by :func:`solvers.codegen.compile_kernel`; ``m``
    is padded to a multiple). :func:`wide_trial` builds it."""

    def __init__(self, trial: CompiledTrial):
        from .batch import default_threads
        from .codegen import compile_kernel

        s = trial.s
        name = f"epo_ilq_wide_n{s.N}_k{s.K}"
        src = wide_trial_source(trial, name)
        so, _ = compile_kernel(src, name)
        self.fn = ca.external(name, str(so))
        self.threads = default_threads()
        self.sizes_in = [trial.fn.nnz_in(i) for i in range(trial.fn.n_in())]
        self.sizes_out = [trial.fn.nnz_out(i) for i in range(trial.fn.n_out())] + [5]
        self._bound: dict[int, tuple] = {}

    def _buffers(self, m: int):
        """``(evaluate, inputs, outputs)`` for ``m`` starts: the kernel mapped over
        ``ceil(m / WIDE_LANES)`` calls, bound once to arrays of that many lanes (lanes
        past ``m`` hold earlier numbers; their outputs are not read)."""
        c = max(1, -(-m // WIDE_LANES))
        b = self._bound.get(c)
        if b is None:
            f = self.fn
            if c > 1:
                th = min(self.threads, c)
                f = f.map(c, "thread", th) if th > 1 else f.map(c, "serial")
            buf, ev = f.buffer()
            n = c * WIDE_LANES
            ins = [np.zeros((n, k)) for k in self.sizes_in]
            outs = [np.zeros((n, k)) for k in self.sizes_out]
            for i, a in enumerate(ins):
                buf.set_arg(i, memoryview(a))
            for i, o in enumerate(outs):
                buf.set_res(i, memoryview(o))
            b = self._bound[c] = (ev, ins, outs, buf)
        return b

    def inputs(self, m: int) -> list[np.ndarray]:
        """The input arrays ``(m, nnz)`` of the next :meth:`run` of ``m`` starts, to fill."""
        return [a[:m] for a in self._buffers(m)[1]]

    def run(self, m: int) -> list[np.ndarray]:
        """Evaluate the ``m`` starts of :meth:`inputs`: the outputs ``(m, nnz)`` (views of
        arrays the next run overwrites)."""
        ev, _, outs, _ = self._buffers(m)
        ev()
        return [o[:m] for o in outs]

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        m = np.shape(args[0])[0]
        for a, dst in zip(args, self.inputs(m), strict=True):
            dst[:] = np.reshape(a, dst.shape)
        return [o.copy() for o in self.run(m)]


def wide_trial(solver) -> CompiledWideTrial | None:
    """The :class:`CompiledWideTrial` of a compiled ``solver`` (built and compiled on first
    use, then kept on its one-call trial), or ``None`` where it cannot be written or
    compiled (:class:`WideUnsupported`, a compiler error): then the mapped scalar trial."""
    from .codegen import CompilerError

    ft = solver._ftrial
    if ft is None:
        return None
    if ft.wide is None:
        try:
            ft.wide = CompiledWideTrial(ft)
        except (WideUnsupported, CompilerError):
            ft.wide = False
    return ft.wide or None


def trial_stats(solver, X, U, PA, r) -> np.ndarray:
    """Per start of the one-call trial's outputs ``(m, nnz)``: ``(ok, good, res, asum,
    c_ok)`` as :class:`CompiledWideTrial` computes them in C: ``PA`` finite, ``X`` and
    ``U`` finite, ``max |a|`` (NaN where one is), ``asum`` NaN (the exact sum of ``a*a`` is
    left to the caller), ``r*r`` finite and summing below ``1e300``: ``(m, 5)``."""
    m = X.shape[0]
    st = np.empty((m, 5))
    with np.errstate(all="ignore"):
        st[:, 0] = np.isfinite(PA).all(axis=1)
        st[:, 1] = np.isfinite(X).all(axis=1) & np.isfinite(U).all(axis=1)
        a = PA.reshape(m, solver.K * solver.nu, solver.nxs + 1)[:, :, -1]
        st[:, 2] = np.max(np.abs(a), axis=1)
        st[:, 3] = np.nan
        r2 = r * r
        st[:, 4] = np.isfinite(r2).all(axis=1) & (np.sum(r2, axis=1) < 1e300)
    return st
