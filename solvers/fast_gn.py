"""Fused Gauss-Newton backend: the whole structured LM step as generated CasADi code.

Shapes and index order follow the contract in :mod:`epo_casadi.game`. The backend has the
interface of :class:`solvers.lm.DenseGN` (``linearize``, ``solve``, ``energy``) and computes
the same step as :class:`solvers.structured.StructuredGN` (the same LQ problem over stages,
the same stage layout, read from the sparsity of ``traj_residual``: see that module's
docstring for why it is exact), but Python runs once per batch and call instead of once
per stage: every stage loop lives inside CasADi SX functions, built once per game
and mapped over the batch (:class:`solvers.batch.BatchFunction`, ``map`` with threads).

``fused_linearize(u, p) -> (r, E, g, H, FG)``
    The rollout, the residual, the *stage-wise* partial Jacobians (rows of
    ``d traj_residual / d[x, u]`` per stage and the per-agent dynamics Jacobians ``A_k``,
    ``B_k``, never the dense ``J``), the stage Gauss-Newton blocks ``H_k = R_k'R_k`` and the
    augmented dynamics ``FG_k = [F_k, G_k]`` as their structural nonzeros, and ``J'r`` by
    the adjoint sweep over stages. The symbolic products exploit the structural zeros of
    ``R_k`` and ``FG_k`` (block-diagonal dynamics across agents).
``fused_solve(H, FG, D, rhs) -> (du, factor)``
    ``(J'J + diag(D)) du = rhs``: the backward Riccati recursion (a Cholesky factor of each
    stage's control block), the backward sweep of the right-hand side and the forward
    rollout of the LQ solution, unrolled over the ``K`` stages. ``D`` is the damping per
    control (``lambda`` or ``lambda diag(J'J)``), so identity and ellipsoidal damping share it.
    ``factor`` (each stage's ``C_k``, ``Y_k``) is kept on the linearization, and
    ``fused_sweep(factor, FG, rhs) -> du`` solves with further right-hand sides.
``fused_diag(H, FG) -> diag(J'J)``
    The exact diagonal by the backward recursion of :class:`~solvers.structured.StructuredGN`
    (ellipsoidal damping and :func:`solvers.lm.residual_cosine` only).

The trial energy is the game's ``energy`` function. With ``compiled=True`` the functions
are generated C (:func:`solvers.codegen.compile_functions`, cached on disk by a hash of
their serialization, i.e. by the game's structure, never by parameter values: ``p`` is an
input). Steps equal the interpreted structured and dense backends up to rounding (the
Riccati solve uses a Cholesky factor where :class:`StructuredGN` inverts; tested to 1e-12).

Cost
    The unrolled graph grows with ``K (nz + m)^3`` scalar instructions; CasADi's SX virtual
    machine runs about 3 ns per instruction, generated C at ``-O1`` about 0.4 ns. Measured
    (``bench/bench_lm.py``, crossing game, K = 40, CPU per problem and step): for two agents
    generated C is 4.5x faster than :class:`StructuredGN` with generated C in a batch of 64
    and 7x for one problem; interpreted it is 4 to 5x faster for one problem and about 10 %
    slower in a batch of 64 (numpy amortizes its per-stage calls over the batch). Above
    :data:`MAX_STAGE_SIZE`, or when :class:`StructuredGN` itself falls back to the dense solve
    (short horizons, rows coupling many stages), the backend delegates to
    :class:`StructuredGN` and says why in :attr:`FusedGN.fallback`.

A zero damping with a rank-deficient ``J`` gives a zero pivot, so the step is NaN/inf
and :func:`solvers.lm.solve_lm` marks that problem ``NONFINITE`` (the numpy backends raise
or return NaN for it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame

from .batch import BatchFunction
from .gn import DenseGN, Linearization
from .structured import StageLayout, StructuredGN, _var_columns, stage_layout

__all__ = ["MAX_STAGE_SIZE", "FusedGN", "FusedLinearization"]

#: Largest stage size ``d = nz + m`` (augmented state + joint controls) the fused backend
#: builds (4 unicycles: 24). The unrolled graph grows like ``K d^3`` instructions (204k for
#: ``fused_solve`` at d = 24, K = 40), its generated C is compiled at ``-O0`` above
#: :data:`solvers.codegen.AUTO_O1_LIMIT`, and in a batch it is then no faster than the numpy
#: recursion, so above this size :class:`FusedGN` delegates to :class:`StructuredGN`.
MAX_STAGE_SIZE = 24


@dataclass
class FusedLinearization:
    """What :class:`FusedGN` knows at the current iterate of every problem.

    ``r`` ``(B, n_r)``, ``energy`` ``(B,)``, ``gradient`` ``(B, n_u) = J'r`` as in
    :class:`solvers.lm.Linearization`; ``H`` and ``FG`` the structural nonzeros of the
    stage blocks ``R_k'R_k`` and of the augmented dynamics, ``(B, nnz)`` each, as inputs of
    ``fused_solve``. ``J`` and ``JtJ`` are dense and computed on first access only.
    """

    r: np.ndarray
    energy: np.ndarray
    gradient: np.ndarray
    H: np.ndarray
    FG: np.ndarray
    U: np.ndarray
    P: np.ndarray
    backend: FusedGN = field(repr=False)
    _diag: np.ndarray | None = field(default=None, repr=False)
    _factor: tuple | None = field(default=None, repr=False)
    _dense: Linearization | None = field(default=None, repr=False)

    def diag_jtj(self) -> np.ndarray:
        """``diag(J'J)`` as ``(B, K, m)`` joint stage controls (exact, cached)."""
        if self._diag is None:
            L = self.backend.layout
            d = self.backend._diag(self.H, self.FG)[0]
            self._diag = d.reshape(-1, L.K, L.m)
        return self._diag

    def dense(self) -> Linearization:
        """The dense :class:`solvers.lm.Linearization` at the same iterate (slow, cached)."""
        if self._dense is None:
            self._dense = self.backend.dense_backend.linearize(self.U, self.P)
        return self._dense

    @property
    def J(self) -> np.ndarray:
        return self.dense().J

    @property
    def JtJ(self) -> np.ndarray:
        return self.dense().JtJ

    def select(self, other: FusedLinearization, take_other: np.ndarray) -> FusedLinearization:
        """A copy with the problems where ``take_other`` is true taken from ``other``."""
        m = take_other[:, None]
        return FusedLinearization(
            np.where(m, other.r, self.r),
            np.where(take_other, other.energy, self.energy),
            np.where(m, other.gradient, self.gradient),
            np.where(m, other.H, self.H),
            np.where(m, other.FG, self.FG),
            np.where(m, other.U, self.U),
            np.where(m, other.P, self.P),
            backend=self.backend,
        )


class FusedGN:
    """Fused Gauss-Newton backend (see the module docstring).

    ``threads``: threads of the mapped CasADi evaluation (None: ``EPO_THREADS`` or all
    cores). ``compiled``: generated C instead of CasADi's interpreter (needs a C compiler;
    compiled once per game structure and cached in ``cache_dir``). After construction
    :attr:`fallback` is ``None``, or a sentence saying why the backend delegates to
    :class:`solvers.structured.StructuredGN` (:attr:`delegate`).
    """

    def __init__(
        self,
        game: PotentialGame,
        threads: int | None = None,
        compiled: bool = False,
        cache_dir: str | None = None,
    ):
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        if getattr(game, "coupled", False):  # per-agent stage dynamics only
            raise SpecError("game", "coupled dynamics: use the dense backend (LM picks it)")
        self.game = game
        self.threads = threads
        self.compiled = bool(compiled)
        self.fallback: str | None = None
        self.delegate: StructuredGN | None = None
        self._dense_be: DenseGN | None = None
        x = ca.SX.sym("x", game.n_x)
        u = ca.SX.sym("u", game.n_u)
        p = ca.SX.sym("p", game.n_p)
        _, _, _, xsel = _var_columns(game)
        r = game.function("traj_residual")(x, u, p)
        Jr = ca.jacobian(r, ca.vertcat(x[xsel.tolist()], u))
        self.layout = L = stage_layout(game, Jr.sparsity())
        if L.d > MAX_STAGE_SIZE:
            self.fallback = (
                f"stage size nz + m = {L.d} > {MAX_STAGE_SIZE}: the unrolled Riccati graph "
                f"(~K d^3 instructions) is slower than StructuredGN's numpy recursion"
            )
        elif (L.K + 1) * (
            4 * L.nz**2 * L.d + 2 * L.d**3
        ) > game.n_r * game.n_u**2 + game.n_u**3 / 3:
            self.fallback = (  # the rule of StructuredGN, which then uses the dense solve
                f"a Riccati recursion over {L.K} stages with an augmented state of {L.nz} "
                f"entries costs more flops than the dense solve with n_u = {game.n_u}"
            )
        if self.fallback:
            self.delegate = StructuredGN(
                game, threads=threads, compiled=compiled, cache_dir=cache_dir
            )
            self._u_index = getattr(self.delegate, "_u_index", None)
            return
        self._u_index = _joint_u_index(game, L)
        f_lin = self._build_linearize(x, u, p, r, Jr)
        f_solve, f_sweep, f_diag = self._build_solve()
        f_energy = game.function("energy")
        if self.compiled:
            from .codegen import compile_functions

            # one library per function: compile_functions picks -O1 or -O0 by size, and
            # each of these stays under the -O1 limit where their sum would not
            fs = [f_lin, f_solve, f_sweep, f_energy]
            f_lin, f_solve, f_sweep, f_energy = (
                compile_functions([f], f"epo_{f.name()}_n{game.N}_k{game.K}", cache_dir)[f.name()]
                for f in fs
            )
        self._lin = BatchFunction(f_lin, threads)
        self._solve = BatchFunction(f_solve, threads)
        self._sweep = BatchFunction(f_sweep, threads)
        self._diag = BatchFunction(f_diag, threads)
        self._energy = BatchFunction(f_energy, threads)

    # ---- symbolic -------------------------------------------------------------------
    def _build_linearize(self, x, u, p, r, Jr) -> ca.Function:
        g, L = self.game, self.layout
        K, nz, d = L.K, L.nz, L.d
        kind, stage, comp, _ = _var_columns(g)
        rows, cols = (np.asarray(a, dtype=int) for a in Jr.sparsity().get_triplet())
        h = L.row_stage[rows]
        lag = h - stage[cols]
        local = np.array(
            [
                L.z_index("x" if kd == 0 else "u", int(lg), int(c))
                for kd, lg, c in zip(kind[cols], lag, comp[cols], strict=True)
            ],
            dtype=int,
        )
        # stage blocks H_k = R_k'R_k and c_k = R_k'r_k from the nonzeros of each stage's rows
        Hs, cs = [], []
        for k in range(K + 1):
            idx = np.flatnonzero(h == k)
            srows = np.unique(rows[idx])
            if srows.size == 0:
                Hs.append(ca.SX(d, d))
                cs.append(ca.SX(d, 1))
                continue
            lr = np.searchsorted(srows, rows[idx])
            Rk = ca.SX.triplet(lr.tolist(), local[idx].tolist(), Jr.nz[idx.tolist()], srows.size, d)
            Hs.append(ca.mtimes(Rk.T, Rk))
            cs.append(ca.mtimes(Rk.T, r[srows.tolist()]))
        # augmented dynamics FG_k = [F_k, G_k]: per-agent A_k, B_k and the lag shifts
        xc = np.concatenate([[0], np.cumsum(g.nx)]).astype(int)
        uc = np.concatenate([[0], np.cumsum(g.nu)]).astype(int)
        FGs = []
        for k in range(K):
            FG = ca.SX(nz, d)
            for i, a in enumerate(g.agents):
                nx, nu = g.nx[i], g.nu[i]
                X = x[int(g.xoff[i]) + k * nx : int(g.xoff[i]) + (k + 1) * nx]
                U = u[int(g.uoff[i]) + k * nu : int(g.uoff[i]) + (k + 1) * nu]
                f = a.dynamics.step(X, U, g.dt)
                FG[xc[i] : xc[i + 1], xc[i] : xc[i + 1]] = ca.jacobian(f, X)
                FG[xc[i] : xc[i + 1], nz + uc[i] : nz + uc[i + 1]] = ca.jacobian(f, U)
            for ell, s in enumerate(L.x_lags, 1):  # x_{k+1-l} at stage k+1 is x_{k-(l-1)}
                for cc in s:
                    FG[L.z_index("x", ell, cc), L.z_index("x", ell - 1, cc)] = 1.0
            for ell, s in enumerate(L.u_lags, 1):
                for cc in s:
                    FG[L.z_index("u", ell, cc), L.z_index("u", ell - 1, cc)] = 1.0
            FGs.append(FG)
        # H_k is symmetric: only its lower triangle goes out (and is read by fused_solve)
        self._sp_H = [ca.tril(hk).sparsity() for hk in Hs]
        # constant nonzeros of FG_k (shifts, identities, dt) are built into fused_solve
        self._fg = []
        fg_var = []
        for fk in FGs:
            nzs = [fk.nz[i] for i in range(fk.nnz())]
            const = np.array([e.is_constant() for e in nzs], dtype=bool)
            vals = np.array([float(e) if c else 0.0 for e, c in zip(nzs, const, strict=True)])
            self._fg.append((fk.sparsity(), const, vals))
            fg_var.extend(e for e, c in zip(nzs, const, strict=True) if not c)
        # J'r by the adjoint sweep over stages
        gk = [None] * K
        lam = cs[K][:nz]
        for k in range(K - 1, -1, -1):
            v = ca.mtimes(FGs[k].T, lam)
            gk[k] = cs[k][nz:] + v[nz:]
            lam = cs[k][:nz] + v[:nz]
        grad = ca.vertcat(*gk)[self._game_order().tolist()]
        outs = [
            ca.densify(r),
            0.5 * ca.sumsqr(r),
            ca.densify(grad),
            _nz([ca.tril(hk) for hk in Hs]),
            ca.vertcat(*fg_var) if fg_var else ca.SX(0, 1),
        ]
        partial = ca.Function("fused_partials", [x, u, p], ca.cse(outs))
        xr = g.function("rollout")(u, p)
        return ca.Function(
            "fused_linearize",
            [u, p],
            partial(xr, u, p),
            ["u", "p"],
            ["r", "E", "g", "H", "FG"],
        )

    def _game_order(self) -> np.ndarray:
        """Permutation taking joint stage order (``k``, then joint control) to game order."""
        inv = np.empty_like(self._u_index)
        inv[self._u_index] = np.arange(self._u_index.size)
        return inv

    def _build_solve(self) -> tuple[ca.Function, ca.Function, ca.Function]:
        L = self.layout
        K, m, nz = L.K, L.m, L.nz
        nH = sum(sp.nnz() for sp in self._sp_H)
        nF = sum(int((~c).sum()) for _, c, _ in self._fg)
        Hin = ca.SX.sym("H", nH)
        Fin = ca.SX.sym("FG", nF)
        Din = ca.SX.sym("D", self.game.n_u)
        bin_ = ca.SX.sym("rhs", self.game.n_u)
        Hs, off = [], 0
        for sp in self._sp_H:
            Hs.append(ca.tril2symm(ca.SX(sp, Hin[off : off + sp.nnz()])))
            off += sp.nnz()
        FGs, off = [], 0
        for sp, const, vals in self._fg:
            nv = int((~const).sum())
            var = iter(ca.vertsplit(Fin[off : off + nv])) if nv else iter(())
            off += nv
            nzs = [ca.SX(v) if c else next(var) for c, v in zip(const, vals, strict=True)]
            FGs.append(ca.SX(sp, ca.vertcat(*nzs)) if nzs else ca.SX(sp))
        Dj = Din[self._u_index.tolist()]
        bj = bin_[self._u_index.tolist()]
        # Riccati recursion with C C' = Q_uu (Cholesky) and Y = C^{-1} Q_uz per stage:
        # P <- Q_zz - Y'Y. Only lower triangles of the symmetric matrices are referenced,
        # so the graph computes only those.
        P = Hs[K][:nz, :nz]
        factor = [None] * K
        for k in range(K - 1, -1, -1):
            FG = FGs[k]
            Q = ca.tril2symm(ca.tril(Hs[k] + ca.mtimes(FG.T, ca.mtimes(P, FG))))
            C = _cholesky(Q[nz:, nz:] + ca.diag(Dj[k * m : (k + 1) * m]))
            Y = ca.solve(C, Q[nz:, :nz])
            factor[k] = (C, Y)
            P = ca.tril2symm(ca.tril(Q[:nz, :nz] - ca.mtimes(Y.T, Y)))
        du = self._sweeps(FGs, factor, bj)
        low = [j * m + i for j in range(m) for i in range(j, m)]  # Sparsity.lower order
        fac = ca.vertcat(
            *[ca.vertcat(ca.densify(C).nz[low], ca.densify(ca.vec(Y))) for C, Y in factor]
        )
        f_solve = ca.Function(
            "fused_solve",
            [Hin, Fin, Din, bin_],
            [du, fac],
            ["H", "FG", "D", "rhs"],
            ["du", "factor"],
        )
        # the same sweeps from a stored factorization (further right-hand sides)
        fin = ca.SX.sym("factor", fac.numel())
        sw, off = [], 0
        nc = m * (m + 1) // 2
        for _ in range(K):
            C = ca.SX(ca.Sparsity.lower(m), fin[off : off + nc])
            Y = ca.reshape(fin[off + nc : off + nc + m * nz], m, nz)
            sw.append((C, Y))
            off += nc + m * nz
        f_sweep = ca.Function(
            "fused_sweep",
            [fin, Fin, bin_],
            [self._sweeps(FGs, sw, bj)],
            ["factor", "FG", "rhs"],
            ["du"],
        )
        # diag(J'J): W_K = H_K,zz; M = H_k + FG'W FG; diag_k = diag(M_uu); W = M_zz
        W = Hs[K][:nz, :nz]
        dg = [None] * K
        for k in range(K - 1, -1, -1):
            M = Hs[k] + ca.mtimes(FGs[k].T, ca.mtimes(W, FGs[k]))
            dg[k] = ca.diag(M[nz:, nz:])
            W = ca.tril2symm(ca.tril(M[:nz, :nz]))
        f_diag = ca.Function(
            "fused_diag", [Hin, Fin], [ca.densify(ca.vertcat(*dg))], ["H", "FG"], ["diag"]
        )
        return f_solve, f_sweep, f_diag

    def _sweeps(self, FGs: list, factor: list, bj: ca.SX) -> ca.SX:
        """``du`` (game order) from the stage factors ``(C_k, Y_k)`` and the right-hand side.

        Backward: ``w_k = C_k^{-1} (b_k - G_k'pv)``, ``pv <- F_k'pv + Y_k'w_k`` from
        ``pv = 0``; forward from ``dz_0 = 0``: ``u_k = C_k^{-T} (w_k - Y_k dz_k)``,
        ``dz_{k+1} = F_k dz_k + G_k u_k``.
        """
        L = self.layout
        K, m, nz = L.K, L.m, L.nz
        pv = ca.SX.zeros(nz, 1)
        ws = [None] * K
        for k in range(K - 1, -1, -1):
            C, Y = factor[k]
            v = ca.mtimes(FGs[k].T, pv)
            ws[k] = ca.solve(C, bj[k * m : (k + 1) * m] - v[nz:])
            pv = v[:nz] + ca.mtimes(Y.T, ws[k])
        z = ca.SX.zeros(nz, 1)
        us = []
        for k in range(K):
            C, Y = factor[k]
            uk = ca.solve(C.T, ws[k] - ca.mtimes(Y, z))
            us.append(uk)
            if k + 1 < K:
                z = ca.mtimes(FGs[k], ca.vertcat(z, uk))
        return ca.densify(ca.vertcat(*us)[self._game_order().tolist()])

    @property
    def dense_backend(self) -> DenseGN:
        """The :class:`DenseGN` of the same game (built on first use)."""
        if self._dense_be is None:
            self._dense_be = DenseGN(self.game, threads=self.threads)
        return self._dense_be

    # ---- backend interface -----------------------------------------------------------
    def linearize(self, U: np.ndarray, P: np.ndarray):
        """Residual, energy, ``J'r`` and stage blocks for every problem (one CasADi call)."""
        if self.delegate is not None:
            return self.delegate.linearize(U, P)
        r, E, g, H, FG = self._lin(U, P)
        return FusedLinearization(r, E[:, 0], g, H, FG, U.copy(), P.copy(), backend=self)

    def energy(self, U: np.ndarray, P: np.ndarray) -> np.ndarray:
        if self.delegate is not None:
            return self.delegate.energy(U, P)
        return self._energy(U, P)[0][:, 0]

    def solve(
        self, lin, damping: np.ndarray, rhs: np.ndarray, ellipsoidal: bool = False
    ) -> np.ndarray:
        """Solve ``(J'J + damping D) x = rhs`` for every problem; ``rhs`` is ``(B, n_u)``.

        ``D = I``, or ``diag(J'J)`` (clamped below at ``1e-12``) with ``ellipsoidal``. One
        CasADi call factors and solves; the factorization is kept on ``lin`` for the last
        ``(damping, ellipsoidal)``, so further right-hand sides (the layer's backward pass)
        cost the two sweeps only (``fused_sweep``).
        """
        if self.delegate is not None or not isinstance(lin, FusedLinearization):
            be = self.delegate if self.delegate is not None else DenseGN
            B = lin.r.shape[0]
            damping = np.broadcast_to(np.asarray(damping, dtype=float), (B,))
            return be.solve(lin, np.ascontiguousarray(damping), rhs, ellipsoidal)
        B = lin.r.shape[0]
        damping = np.broadcast_to(np.asarray(damping, dtype=float), (B,))
        rhs = np.asarray(rhs, dtype=float)
        if rhs.shape != (B, self.game.n_u):
            raise SpecError("rhs", f"expected shape ({B}, {self.game.n_u}), got {rhs.shape}")
        if ellipsoidal:
            Dg = lin.diag_jtj().reshape(B, -1)
            D = np.empty((B, self.game.n_u))
            D[:, self._u_index] = np.where(Dg > 1e-12, Dg, 1e-12) * damping[:, None]
        else:
            D = np.repeat(damping[:, None], self.game.n_u, axis=1)
        key = (damping.tobytes(), bool(ellipsoidal))
        if lin._factor is not None and lin._factor[0] == key:
            return self._sweep(lin._factor[1], lin.FG, rhs)[0]
        du, fac = self._solve(lin.H, lin.FG, D, rhs)
        lin._factor = (key, fac)
        return du


def _joint_u_index(game: PotentialGame, L: StageLayout) -> np.ndarray:
    """Game index of every control in joint stage order (``k``, then joint component)."""
    uc = np.concatenate([[0], np.cumsum(game.nu)]).astype(int)
    out = np.zeros((L.K, L.m), dtype=int)
    for i in range(game.N):
        k = np.arange(L.K)[:, None]
        c = np.arange(game.nu[i])[None, :]
        out[:, uc[i] : uc[i + 1]] = int(game.uoff[i]) + k * game.nu[i] + c
    return out.reshape(-1)


def _nz(blocks: list) -> ca.SX:
    """The structural nonzeros of every block, concatenated (column-major per block)."""
    parts = [b.nz[:] for b in blocks if b.nnz()]
    return ca.vertcat(*parts) if parts else ca.SX(0, 1)


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
