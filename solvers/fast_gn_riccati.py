"""The Riccati step of :class:`solvers.fast_gn.FusedGN` as CasADi functions.

``_FusedRiccati``, the base of :class:`~solvers.fast_gn.FusedGN`, reads one stage's
``H_k``, ``FG_k`` and factor from vectors of nonzeros and builds ``fused_solve``,
``fused_sweep`` and ``fused_diag``, unrolled over the stages (the interpreter) or staged
(``K`` calls of one stage function, for generated C), with the dense elimination of a large
stage in C (:data:`SCHUR_KERNEL_C`, :func:`schur_kernel_source`); :func:`_riccati_stage`,
:func:`_sweep_back`, :func:`_sweep_fwd` and :func:`_cholesky` are one stage's recursion,
sweeps and factor as SX. It relies on the attributes :class:`~solvers.fast_gn.FusedGN`
sets (``game``, ``layout``, ``_sp_H``, ``_fg``, ``_u_index``, ``schur_kernel``).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError


class _FusedRiccati:
    """The stage pieces and the Riccati step of :class:`~solvers.fast_gn.FusedGN`."""

    def _game_order(self) -> np.ndarray:
        """Permutation taking joint stage order (``k``, then joint control) to game order."""
        inv = np.empty_like(self._u_index)
        inv[self._u_index] = np.arange(self._u_index.size)
        return inv

    # stage pieces: one stage's H_k, FG_k and factor from vectors of nonzeros
    def _stage_H(self, v) -> ca.SX:
        return ca.tril2symm(ca.SX(self._sp_H[0], v))

    def _stage_FG(self, v) -> ca.SX:
        sp, const, vals = self._fg
        var = iter(ca.vertsplit(v)) if v.numel() else iter(())
        nzs = [ca.SX(c_val) if c else next(var) for c, c_val in zip(const, vals, strict=True)]
        return ca.SX(sp, ca.vertcat(*nzs)) if nzs else ca.SX(sp)

    def _pack(self, C: ca.SX, Y: ca.SX) -> ca.SX:
        """One stage's factor as a dense vector: lower ``C`` (column-major), then ``vec(Y)``."""
        m = self.layout.m
        low = [j * m + i for j in range(m) for i in range(j, m)]  # Sparsity.lower order
        return ca.vertcat(ca.densify(C).nz[low], ca.densify(ca.vec(Y)))

    def _unpack(self, v) -> tuple[ca.SX, ca.SX]:
        m, nz = self.layout.m, self.layout.nz
        nc = m * (m + 1) // 2
        return ca.SX(ca.Sparsity.lower(m), v[:nc]), ca.reshape(v[nc : nc + m * nz], m, nz)

    def _sizes(self) -> tuple[int, int, int, int]:
        """Nonzeros per stage of ``H`` (k < K), of ``H_K``, of ``FG`` (read) and of a factor."""
        m, nz = self.layout.m, self.layout.nz
        return (
            self._sp_H[0].nnz(),
            self._sp_H[1].nnz(),
            int((~self._fg[1]).sum()),
            m * (m + 1) // 2 + m * nz,
        )

    def _build_solve(self) -> tuple[ca.Function, ca.Function, ca.Function]:
        """``fused_solve``, ``fused_sweep`` and ``fused_diag`` as SX graphs unrolled over
        the stages (fastest in CasADi's interpreter)."""
        L = self.layout
        K, m, nz = L.K, L.m, L.nz
        nHu, nHK, nFv, nfac = self._sizes()
        Hin = ca.SX.sym("H", K * nHu + nHK)
        Fin = ca.SX.sym("FG", K * nFv)
        Din = ca.SX.sym("D", self.game.n_u)
        bin_ = ca.SX.sym("rhs", self.game.n_u)
        Hs = [self._stage_H(Hin[k * nHu : (k + 1) * nHu]) for k in range(K)]
        FGs = [self._stage_FG(Fin[k * nFv : (k + 1) * nFv]) for k in range(K)]
        PK = ca.tril2symm(ca.SX(self._sp_H[1], Hin[K * nHu :]))
        Dj = Din[self._u_index.tolist()]
        bj = bin_[self._u_index.tolist()]
        P = PK
        factor = [None] * K
        for k in range(K - 1, -1, -1):
            P, C, Y = _riccati_stage(P, Hs[k], FGs[k], Dj[k * m : (k + 1) * m], nz)
            factor[k] = (C, Y)
        du = self._sweeps(FGs, factor, bj)
        fac = ca.vertcat(*[self._pack(C, Y) for C, Y in factor])
        f_solve = ca.Function(
            "fused_solve",
            [Hin, Fin, Din, bin_],
            [du, fac],
            ["H", "FG", "D", "rhs"],
            ["du", "factor"],
        )
        # the same sweeps from a stored factorization (further right-hand sides)
        fin = ca.SX.sym("factor", K * nfac)
        sw = [self._unpack(fin[k * nfac : (k + 1) * nfac]) for k in range(K)]
        f_sweep = ca.Function(
            "fused_sweep",
            [fin, Fin, bin_],
            [self._sweeps(FGs, sw, bj)],
            ["factor", "FG", "rhs"],
            ["du"],
        )
        # diag(J'J): W_K = H_K,zz; M = H_k + FG'W FG; diag_k = diag(M_uu); W = M_zz
        W = PK
        dg = [None] * K
        for k in range(K - 1, -1, -1):
            M = Hs[k] + ca.mtimes(FGs[k].T, ca.mtimes(W, FGs[k]))
            dg[k] = ca.diag(M[nz:, nz:])
            W = ca.tril2symm(ca.tril(M[:nz, :nz]))
        f_diag = ca.Function(
            "fused_diag", [Hin, Fin], [ca.densify(ca.vertcat(*dg))], ["H", "FG"], ["diag"]
        )
        return f_solve, f_sweep, f_diag

    def _build_solve_staged(self) -> tuple[ca.Function, ca.Function, ca.Function]:
        """``fused_solve``, ``fused_sweep`` and ``fused_diag`` as MX graphs of ``K`` calls
        of small SX stage functions (the same arithmetic as :meth:`_build_solve`): the form
        to compile, since generated C of one stage compiles in a fraction of the time of
        the unrolled graph and calls cost nothing in C."""
        L = self.layout
        K, m, nz = L.K, L.m, L.nz
        nHu, nHK, nFv, nfac = self._sizes()
        nP = nz * (nz + 1) // 2
        lowz = [j * nz + i for j in range(nz) for i in range(j, nz)]

        def lower_nz(A):
            return ca.densify(A).nz[lowz]

        def sym_P(v):
            return ca.tril2symm(ca.SX(ca.Sparsity.lower(nz), v))

        Ps, Hk = ca.SX.sym("P", nP), ca.SX.sym("H", nHu)
        Fk, Dk = ca.SX.sym("FG", nFv), ca.SX.sym("D", m)
        if self.schur_kernel:
            f_ric = self._riccati_stage_kernel(Ps, Hk, Fk, Dk)
        else:
            Pn, C, Y = _riccati_stage(sym_P(Ps), self._stage_H(Hk), self._stage_FG(Fk), Dk, nz)
            f_ric = ca.Function(
                "fused_riccati_stage", [Ps, Hk, Fk, Dk], [lower_nz(Pn), self._pack(C, Y)]
            )
        HK = ca.SX.sym("HK", nHK)
        f_init = ca.Function(
            "fused_riccati_init", [HK], [lower_nz(ca.tril2symm(ca.SX(self._sp_H[1], HK)))]
        )
        fk, pv, bk = ca.SX.sym("factor", nfac), ca.SX.sym("pv", nz), ca.SX.sym("b", m)
        C, Y = self._unpack(fk)
        pvn, w = _sweep_back(pv, C, Y, self._stage_FG(Fk), bk, nz)
        f_back = ca.Function("fused_sweep_back", [pv, fk, Fk, bk], [ca.densify(pvn), ca.densify(w)])
        z, ws = ca.SX.sym("z", nz), ca.SX.sym("w", m)
        u, zn = _sweep_fwd(z, C, Y, ws, self._stage_FG(Fk))
        f_fwd = ca.Function("fused_sweep_fwd", [z, fk, Fk, ws], [ca.densify(u), ca.densify(zn)])

        Hin = ca.MX.sym("H", K * nHu + nHK)
        Fin = ca.MX.sym("FG", K * nFv)
        Din = ca.MX.sym("D", self.game.n_u)
        bin_ = ca.MX.sym("rhs", self.game.n_u)
        Dj = Din[self._u_index.tolist()]
        bj = bin_[self._u_index.tolist()]
        F = [Fin[k * nFv : (k + 1) * nFv] for k in range(K)]

        def sweeps(facs):
            pv = ca.MX.zeros(nz, 1)
            w = [None] * K
            for k in range(K - 1, -1, -1):
                pv, w[k] = f_back(pv, facs[k], F[k], bj[k * m : (k + 1) * m])
            z = ca.MX.zeros(nz, 1)
            us = []
            for k in range(K):
                uk, z = f_fwd(z, facs[k], F[k], w[k])
                us.append(uk)
            return ca.vertcat(*us)[self._game_order().tolist()]

        P = f_init(Hin[K * nHu :])
        facs = [None] * K
        for k in range(K - 1, -1, -1):
            P, facs[k] = f_ric(P, Hin[k * nHu : (k + 1) * nHu], F[k], Dj[k * m : (k + 1) * m])
        f_solve = ca.Function(
            "fused_solve",
            [Hin, Fin, Din, bin_],
            [sweeps(facs), ca.vertcat(*facs)],
            ["H", "FG", "D", "rhs"],
            ["du", "factor"],
        )
        fin = ca.MX.sym("factor", K * nfac)
        f_sweep = ca.Function(
            "fused_sweep",
            [fin, Fin, bin_],
            [sweeps([fin[k * nfac : (k + 1) * nfac] for k in range(K)])],
            ["factor", "FG", "rhs"],
            ["du"],
        )
        # diag(J'J): W_K = H_K,zz; M = H_k + FG'W FG; diag_k = diag(M_uu); W = M_zz
        Ws = ca.SX.sym("W", nP)
        FG = self._stage_FG(Fk)
        M = self._stage_H(Hk) + ca.mtimes(FG.T, ca.mtimes(sym_P(Ws), FG))
        f_dstage = ca.Function(
            "fused_diag_stage",
            [Ws, Hk, Fk],
            [lower_nz(ca.tril2symm(ca.tril(M[:nz, :nz]))), ca.densify(ca.diag(M[nz:, nz:]))],
        )
        W = f_init(Hin[K * nHu :])
        dg = [None] * K
        for k in range(K - 1, -1, -1):
            W, dg[k] = f_dstage(W, Hin[k * nHu : (k + 1) * nHu], F[k])
        f_diag = ca.Function("fused_diag", [Hin, Fin], [ca.vertcat(*dg)], ["H", "FG"], ["diag"])
        return f_solve, f_sweep, f_diag

    def _riccati_stage_kernel(self, Ps, Hk, Fk, Dk) -> ca.Function:
        """The Riccati step of :meth:`_build_solve_staged` with the dense elimination in C:
        ``Q = tril(H_k + FG_k' P FG_k) + diag(0, D)`` as an SX function (packed lower
        triangle), then :data:`SCHUR_KERNEL_C` (``P_k``, the packed factor ``(C_k, Y_k)``)
        through ``casadi.external``; its object file is linked into ``fused_solve``."""
        from .codegen import compile_kernel

        L = self.layout
        m, nz, d = L.m, L.nz, L.d
        P = ca.tril2symm(ca.SX(ca.Sparsity.lower(nz), Ps))
        FG = self._stage_FG(Fk)
        Q = ca.tril(self._stage_H(Hk) + ca.mtimes(FG.T, ca.mtimes(P, FG)))
        Q = Q + ca.diagcat(ca.SX(nz, nz), ca.diag(Dk))
        lowd = [j * d + i for j in range(d) for i in range(j, d)]
        f_q = ca.Function("fused_riccati_q", [Ps, Hk, Fk, Dk], [ca.densify(Q).nz[lowd]])
        name, src = schur_kernel_source(m, nz)
        so, obj = compile_kernel(src, name, self._cache_dir)
        self._kernel_objects = (obj,)
        kern = ca.external(name, str(so))
        args = [ca.MX.sym(n, a.shape[0]) for n, a in zip("PHFD", (Ps, Hk, Fk, Dk), strict=True)]
        return ca.Function("fused_riccati_stage", args, kern(f_q(*args)))

    def _sweeps(self, FGs: list, factor: list, bj: ca.SX) -> ca.SX:
        """``du`` (game order) from the stage factors ``(C_k, Y_k)`` and the right-hand side
        (see :func:`_sweep_back`, :func:`_sweep_fwd`)."""
        L = self.layout
        K, m, nz = L.K, L.m, L.nz
        pv = ca.SX.zeros(nz, 1)
        ws = [None] * K
        for k in range(K - 1, -1, -1):
            C, Y = factor[k]
            pv, ws[k] = _sweep_back(pv, C, Y, FGs[k], bj[k * m : (k + 1) * m], nz)
        z = ca.SX.zeros(nz, 1)
        us = []
        for k in range(K):
            C, Y = factor[k]
            uk, z = _sweep_fwd(z, C, Y, ws[k], FGs[k])
            us.append(uk)
        return ca.densify(ca.vertcat(*us)[self._game_order().tolist()])


#: The dense elimination of one Riccati stage in C (:meth:`FusedGN._riccati_stage_kernel`),
#: with the CasADi external-function interface; ``EPO_FN`` is replaced by the function's
#: name and ``EPO_M`` (controls), ``EPO_NZ`` (augmented state) are defined before it.
#: Input: the packed lower triangle (column-major) of ``Q`` (``d x d``, state first, the
#: damping already on the control diagonal). Outputs: the packed lower triangle of
#: ``P = Q_zz - Y'Y`` and the factor as :meth:`FusedGN._pack` orders it (lower ``C``, then
#: ``vec(Y)``), ``C C' = Q_uu`` (Cholesky), ``Y = C^{-1} Q_uz``. Each loop runs over
#: contiguous rows (``Y`` is held transposed), so ``-O3`` vectorizes it. With gcc 11 or
#: later on x86-64 Linux it is compiled twice, for the baseline and for ``x86-64-v3``
#: (AVX2, FMA), and the loader picks the one the CPU runs (``target_clones``), so a
#: shared cache stays portable (the AVX2 version is the faster: docs/bench_lm.md, "The
#: Riccati elimination in C").
SCHUR_KERNEL_C = r"""
#include <math.h>
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11 && defined(__x86_64__) && \
    defined(__linux__)
#define EPO_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define EPO_CLONES
#endif
#define EPO_D (EPO_M + EPO_NZ)
#define EPO_COL(n, j) ((j) * (n) - ((j) * ((j) - 1)) / 2) /* packed column offset */
static const long long int EPO_FN_sp[3][3] = {
    {EPO_D * (EPO_D + 1) / 2, 1, 1},
    {EPO_NZ * (EPO_NZ + 1) / 2, 1, 1},
    {EPO_M * (EPO_M + 1) / 2 + EPO_M * EPO_NZ, 1, 1}};
int EPO_FN_n_in(void) { return 1; }
int EPO_FN_n_out(void) { return 2; }
const long long int* EPO_FN_sparsity_in(long long int i) { return i == 0 ? EPO_FN_sp[0] : 0; }
const long long int* EPO_FN_sparsity_out(long long int i) {
  return i == 0 || i == 1 ? EPO_FN_sp[i + 1] : 0;
}
EPO_CLONES int EPO_FN(const double** arg, double** res, long long int* iw, double* w,
                      int mem) {
  const double* q = arg[0];
  double c[EPO_M][EPO_M];   /* c[j][i] = C(i, j), i >= j */
  double yt[EPO_M][EPO_NZ]; /* yt[i][a] = Y(i, a) */
  double col[EPO_NZ];
  int i, j, k, a, b;
  (void)iw;
  (void)w;
  (void)mem;
  for (j = 0; j < EPO_M; ++j) {
    const double* qj = q + EPO_COL(EPO_D, EPO_NZ + j) - (EPO_NZ + j);
    for (i = j; i < EPO_M; ++i) c[j][i] = qj[EPO_NZ + i];
  }
  for (a = 0; a < EPO_NZ; ++a) {
    const double* qa = q + EPO_COL(EPO_D, a) - a;
    for (i = 0; i < EPO_M; ++i) yt[i][a] = qa[EPO_NZ + i];
  }
  for (j = 0; j < EPO_M; ++j) { /* Cholesky, left-looking */
    for (k = 0; k < j; ++k) {
      double s = c[k][j];
      for (i = j; i < EPO_M; ++i) c[j][i] -= c[k][i] * s;
    }
    c[j][j] = sqrt(c[j][j]);
    for (i = j + 1; i < EPO_M; ++i) c[j][i] /= c[j][j];
  }
  for (i = 0; i < EPO_M; ++i) { /* Y = C^{-1} Q_uz, all columns at once */
    for (k = 0; k < i; ++k) {
      double s = c[k][i];
      for (a = 0; a < EPO_NZ; ++a) yt[i][a] -= yt[k][a] * s;
    }
    for (a = 0; a < EPO_NZ; ++a) yt[i][a] /= c[i][i];
  }
  for (b = 0; b < EPO_NZ; ++b) { /* P = Q_zz - Y'Y, column b from row b on */
    const double* qb = q + EPO_COL(EPO_D, b) - b;
    for (a = b; a < EPO_NZ; ++a) col[a] = qb[a];
    for (i = 0; i + 3 < EPO_M; i += 4) {
      double s0 = yt[i][b], s1 = yt[i + 1][b], s2 = yt[i + 2][b], s3 = yt[i + 3][b];
      for (a = b; a < EPO_NZ; ++a)
        col[a] -= yt[i][a] * s0 + yt[i + 1][a] * s1 + yt[i + 2][a] * s2 + yt[i + 3][a] * s3;
    }
    for (; i < EPO_M; ++i) {
      double s = yt[i][b];
      for (a = b; a < EPO_NZ; ++a) col[a] -= yt[i][a] * s;
    }
    if (res[0]) {
      double* pb = res[0] + EPO_COL(EPO_NZ, b) - b;
      for (a = b; a < EPO_NZ; ++a) pb[a] = col[a];
    }
  }
  if (res[1]) {
    double* f = res[1];
    for (j = 0; j < EPO_M; ++j)
      for (i = j; i < EPO_M; ++i) *f++ = c[j][i];
    for (a = 0; a < EPO_NZ; ++a)
      for (i = 0; i < EPO_M; ++i) *f++ = yt[i][a];
  }
  return 0;
}
"""


def schur_kernel_source(m: int, nz: int) -> tuple[str, str]:
    """Name and C source of :data:`SCHUR_KERNEL_C` for ``m`` controls and an augmented
    state of ``nz`` entries (sizes are compile-time constants, so loops vectorize)."""
    if min(m, nz) < 1:
        raise SpecError("schur_kernel", f"expected m, nz >= 1, got m = {m}, nz = {nz}")
    name = f"epo_schur_m{m}_nz{nz}"
    return name, f"#define EPO_M {m}\n#define EPO_NZ {nz}\n" + SCHUR_KERNEL_C.replace(
        "EPO_FN", name
    )


def _riccati_stage(P: ca.SX, H: ca.SX, FG: ca.SX, D: ca.SX, nz: int):
    """One stage of the backward Riccati recursion: ``(P_k, C_k, Y_k)`` from ``P_{k+1}``.

    ``Q = H_k + FG_k' P FG_k``; ``C C' = Q_uu + diag(D)`` (Cholesky); ``Y = C^{-1} Q_uz``;
    ``P_k = Q_zz - Y'Y``. Only lower triangles of the symmetric matrices are referenced, so
    the graph computes only those.
    """
    Q = ca.tril2symm(ca.tril(H + ca.mtimes(FG.T, ca.mtimes(P, FG))))
    C = _cholesky(Q[nz:, nz:] + ca.diag(D))
    Y = ca.solve(C, Q[nz:, :nz])
    return ca.tril2symm(ca.tril(Q[:nz, :nz] - ca.mtimes(Y.T, Y))), C, Y


def _sweep_back(pv: ca.SX, C: ca.SX, Y: ca.SX, FG: ca.SX, b: ca.SX, nz: int):
    """Backward sweep of a right-hand side: ``w = C^{-1} (b_k - G_k'pv)``,
    ``pv <- F_k'pv + Y'w`` (from ``pv = 0`` after the last stage)."""
    v = ca.mtimes(FG.T, pv)
    w = ca.solve(C, b - v[nz:])
    return v[:nz] + ca.mtimes(Y.T, w), w


def _sweep_fwd(z: ca.SX, C: ca.SX, Y: ca.SX, w: ca.SX, FG: ca.SX):
    """Forward sweep: ``u_k = C^{-T} (w_k - Y dz_k)``, ``dz_{k+1} = F_k dz_k + G_k u_k``
    (from ``dz_0 = 0``)."""
    u = ca.solve(C.T, w - ca.mtimes(Y, z))
    return u, ca.mtimes(FG, ca.vertcat(z, u))


def _cholesky(A: ca.SX) -> ca.SX:
    """Lower Cholesky factor of a small symmetric positive definite SX matrix."""
    n = A.size1()
    Lf = [[None] * n for _ in range(n)]
    for j in range(n):
        s = A[j, j]
        for q in range(j):
            s = s - Lf[j][q] * Lf[j][q]
        Lf[j][j] = ca.sqrt(s)
        for i in range(j + 1, n):
            s = A[i, j]
            for q in range(j):
                s = s - Lf[i][q] * Lf[j][q]
            Lf[i][j] = s / Lf[j][j]
    C = ca.SX(ca.Sparsity.lower(n))
    for j in range(n):
        for i in range(j, n):
            C[i, j] = Lf[i][j]
    return C
