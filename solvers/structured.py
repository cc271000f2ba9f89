"""Structured Gauss-Newton backend: the exact LM step by a Riccati recursion over stages.

Shapes and index order follow the contract in :mod:`epo_casadi.game`. The backend has the
interface of :class:`solvers.lm.DenseGN` (``linearize``, ``energy``, ``solve``) and solves
the same system ``(J'J + lambda D) du = rhs`` (``D = I`` or ``diag(J'J)``) for every problem
of a batch, without forming the ``n_u x n_u`` matrix.

Why it is exact
    In single shooting the states are a function of the controls, ``x_{k+1} = f(x_k, u_k)``,
    so ``J = R_x dx/du + R_u`` with ``R_x, R_u`` the *partial* Jacobians of
    ``traj_residual(x, u, p)``. Writing ``dx`` as a variable with the linearized dynamics
    ``dx_{k+1} = A_k dx_k + B_k du_k``, ``dx_0 = 0``, gives

        1/2 du'(J'J + lambda D)du - rhs'du = 1/2 ||R_x dx + R_u du||^2 + lambda/2 du'D du - rhs'du,

    an LQ problem over stages whose minimizer is the solution of the system above. Every
    residual row is assigned to the last stage ``h`` it touches; a row that also touches
    earlier stages (``jerk``: ``u_k, u_{k+1}``; ``turn_acceleration`` of a bicycle:
    ``x_k, u_k, x_{k+1}, u_{k+1}``) is kept exact by augmenting the state with the lagged
    components it needs, ``z_k = (x_k, x_{k-1}[S^x_1], ..., u_{k-1}[S^u_1], ...)``. Stages,
    lags and components come from the sparsity of the Jacobian of
    ``game.function('traj_residual')`` wrt ``x`` and ``u``, never from feature names.
    The backward Riccati recursion factors the system once per damping; a solve with any
    right-hand side is a backward and a forward sweep. Ellipsoidal damping uses the exact
    ``diag(J'J)``, from the backward recursion ``W_k = C_k'C_k + F_k'W_{k+1}F_k``,
    ``diag(J'J)_k = diag(D_k'D_k + G_k'W_{k+1}G_k)``.

Cost
    Per problem and step ``O(K (nz + m)^3)`` with ``nz`` the augmented state size and ``m``
    the joint control size, against ``O(n_r n_u^2 + n_u^3)`` for the dense path. The sweeps
    are loops over stages, vectorized over the batch with numpy (no loop over problems).
    When the augmented state makes the recursion costlier than the dense solve (rows that
    couple many stages), the backend falls back to :class:`DenseGN` and says why in
    :attr:`StructuredGN.fallback`.

What is evaluated
    One CasADi function per batch (``structured_terms(u, p) -> (r, Jr, Jf)``: the residual,
    the nonzeros of the partial Jacobian of ``traj_residual`` at the rollout and those of
    the per-agent dynamics Jacobians), interpreted or, with ``compiled=True``, as generated
    C (:mod:`solvers.codegen`). Stage Hessians ``R_k'R_k`` and ``J'r`` are formed in numpy
    from these nonzeros with precomputed sparse index maps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.sparse as sps

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame

from .batch import BatchFunction
from .gn import DenseGN, Linearization

__all__ = ["StageLayout", "StructuredGN", "StructuredLinearization", "stage_layout"]


# --------------------------------------------------------------------------------------
# Stage structure from sparsity
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StageLayout:
    """Stage structure of a game's Gauss-Newton system (see the module docstring).

    ``n``, ``m``: joint state and control sizes of one stage (agents in order, each
    agent's components in order). ``x_lags[l-1]``, ``u_lags[l-1]``: joint components of
    ``x_{k-l}``, ``u_{k-l}`` kept in the augmented state ``z_k`` (``nz`` entries: ``x_k``,
    then the state lags, then the control lags). ``row_stage``: stage of every residual
    row (``-1``: the row does not depend on ``u``). ``coupled_rows``: rows that touch more
    than one stage.
    """

    K: int
    n: int
    m: int
    x_lags: tuple[tuple[int, ...], ...]
    u_lags: tuple[tuple[int, ...], ...]
    row_stage: np.ndarray
    coupled_rows: int

    @property
    def nz(self) -> int:
        return self.n + sum(map(len, self.x_lags)) + sum(map(len, self.u_lags))

    @property
    def d(self) -> int:
        return self.nz + self.m

    def z_index(self, kind: str, lag: int, comp: int) -> int:
        """Position in the stage vector ``[z_k; u_k]`` of component ``comp`` of
        ``x_{k-lag}`` (``kind='x'``) or ``u_{k-lag}`` (``kind='u'``)."""
        if kind == "x":
            if lag == 0:
                return comp
            off = self.n + sum(len(s) for s in self.x_lags[: lag - 1])
            return off + self.x_lags[lag - 1].index(comp)
        if lag == 0:
            return self.nz + comp
        off = self.n + sum(map(len, self.x_lags)) + sum(len(s) for s in self.u_lags[: lag - 1])
        return off + self.u_lags[lag - 1].index(comp)


def _var_columns(game: PotentialGame):
    """Variables ``v = [x_{.,k>=1}; u]``: for each, (kind, stage, joint component), game index."""
    xc = np.concatenate([[0], np.cumsum(game.nx)]).astype(int)
    uc = np.concatenate([[0], np.cumsum(game.nu)]).astype(int)
    kind, stage, comp, xsel = [], [], [], []
    for i in range(game.N):
        for k in range(1, game.K + 1):
            for c in range(game.nx[i]):
                kind.append(0)
                stage.append(k)
                comp.append(xc[i] + c)
                xsel.append(int(game.xoff[i]) + k * game.nx[i] + c)
    for i in range(game.N):
        for k in range(game.K):
            for c in range(game.nu[i]):
                kind.append(1)
                stage.append(k)
                comp.append(uc[i] + c)
    return np.array(kind), np.array(stage), np.array(comp), np.array(xsel, dtype=int)


def stage_layout(game: PotentialGame, jac_sparsity: ca.Sparsity | None = None) -> StageLayout:
    """Derive the stage structure from the sparsity of ``d traj_residual / d[x_{k>=1}; u]``."""
    kind, stage, comp, xsel = _var_columns(game)
    if jac_sparsity is None:
        x = ca.SX.sym("x", game.n_x)
        u = ca.SX.sym("u", game.n_u)
        p = ca.SX.sym("p", game.n_p)
        r = game.function("traj_residual")(x, u, p)
        jac_sparsity = ca.jacobian(r, ca.vertcat(x[xsel.tolist()], u)).sparsity()
    rows, cols = (np.asarray(a, dtype=int) for a in jac_sparsity.get_triplet())
    n_r = jac_sparsity.size1()
    row_stage = np.full(n_r, -1, dtype=int)
    if rows.size:
        np.maximum.at(row_stage, rows, stage[cols])
    lag = row_stage[rows] - stage[cols]
    Lx = int(lag[kind[cols] == 0].max(initial=0))
    Lu = int(lag[kind[cols] == 1].max(initial=0))

    def lag_sets(kd, L):
        sets, acc = [], set()
        for ell in range(L, 0, -1):  # closure: S_l contains S_{l+1}
            acc |= set(comp[cols][(kind[cols] == kd) & (lag == ell)].tolist())
            sets.append(tuple(sorted(acc)))
        return tuple(reversed(sets))

    smin = np.full(n_r, game.K + 1, dtype=int)
    if rows.size:
        np.minimum.at(smin, rows, stage[cols])
    coupled = int(np.sum((row_stage >= 0) & (smin < row_stage)))
    return StageLayout(
        K=game.K,
        n=int(sum(game.nx)),
        m=int(sum(game.nu)),
        x_lags=lag_sets(0, Lx),
        u_lags=lag_sets(1, Lu),
        row_stage=row_stage,
        coupled_rows=coupled,
    )


# --------------------------------------------------------------------------------------
# Linearization
# --------------------------------------------------------------------------------------
@dataclass
class StageLinearization:
    """What a stage-wise Gauss-Newton backend knows at the current iterate of every problem
    (the fields and accessors :class:`StructuredLinearization` and
    :class:`solvers.fast_gn.FusedLinearization` share; each adds its ``diag_jtj``).

    ``r`` ``(B, n_r)``, ``energy`` ``(B,)``, ``gradient`` ``(B, n_u) = J'r`` as in
    :class:`solvers.lm.Linearization`; ``H`` and ``FG`` the stage blocks and augmented
    dynamics in the backend's own layout; ``U``, ``P`` the iterate. ``J`` and ``JtJ`` are
    dense and computed on first access only (for code that needs them, e.g.
    :func:`solvers.lm._merge`); the solve never uses them.
    """

    r: np.ndarray
    energy: np.ndarray
    gradient: np.ndarray
    H: np.ndarray
    FG: np.ndarray
    U: np.ndarray
    P: np.ndarray
    backend: object = field(repr=False)
    _diag: np.ndarray | None = field(default=None, repr=False)
    _factor: tuple | None = field(default=None, repr=False)
    _dense: Linearization | None = field(default=None, repr=False)

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

    def select(self, other: StageLinearization, take_other: np.ndarray) -> StageLinearization:
        """A copy with the problems where ``take_other`` is true taken from ``other``."""
        return type(self)(
            *(
                np.where(_bcast(take_other, a), b, a)
                for a, b in (
                    (self.r, other.r),
                    (self.energy, other.energy),
                    (self.gradient, other.gradient),
                    (self.H, other.H),
                    (self.FG, other.FG),
                    (self.U, other.U),
                    (self.P, other.P),
                )
            ),
            backend=self.backend,
        )


@dataclass
class StructuredLinearization(StageLinearization):
    """What :class:`StructuredGN` knows (:class:`StageLinearization`): ``H``
    ``(B, K+1, d, d)`` stage Gauss-Newton blocks ``R_k'R_k`` over ``[z_k; u_k]``; ``FG``
    ``(B, K, nz, d)`` the augmented dynamics ``[F_k, G_k]``."""

    def diag_jtj(self) -> np.ndarray:
        """``diag(J'J)`` as ``(B, K, m)`` joint stage controls (exact, cached)."""
        if self._diag is None:
            self._diag = self.backend._diag_jtj(self)
        return self._diag


def check_stage_game(game) -> None:
    """Stage-wise backends need a :class:`PotentialGame` with per-agent stage dynamics."""
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    if getattr(game, "coupled", False):
        raise SpecError("game", "coupled dynamics: use the dense backend (LM picks it)")


def _bcast(mask, a):
    return mask.reshape(mask.shape + (1,) * (a.ndim - 1))


# --------------------------------------------------------------------------------------
# Backend
# --------------------------------------------------------------------------------------
class StructuredGN:
    """Structured Gauss-Newton backend (see the module docstring).

    ``threads``: threads of the mapped CasADi evaluation (None: ``EPO_THREADS`` or all
    cores). ``compiled``: evaluate generated C (:func:`solvers.codegen.compile_functions`,
    cached on disk) instead of CasADi's interpreter; ``cache_dir`` overrides the cache
    folder. After construction :attr:`fallback` is ``None``, or a sentence saying why the
    backend delegates to :class:`solvers.lm.DenseGN`.
    """

    def __init__(
        self,
        game: PotentialGame,
        threads: int | None = None,
        compiled: bool = False,
        cache_dir: str | None = None,
    ):
        check_stage_game(game)
        self.game = game
        self.threads = threads
        self.compiled = bool(compiled)
        self.fallback: str | None = None
        fn_terms, sp_r, sp_f = self._build_terms()
        self.layout = L = stage_layout(game, sp_r)
        self._dense_be: DenseGN | None = None
        cost_riccati = (L.K + 1) * (4 * L.nz**2 * L.d + 2 * L.d**3)
        cost_dense = game.n_r * game.n_u**2 + game.n_u**3 / 3
        if cost_riccati > cost_dense:
            span = max(len(L.x_lags), len(L.u_lags)) + 1
            self.fallback = (
                f"a Riccati recursion over {L.K} stages with an augmented state of {L.nz} entries "
                f"(residual rows span up to {span} stages) costs more flops than the dense solve "
                f"with n_u = {game.n_u}; using DenseGN (same steps, interpreted CasADi)"
            )
            self._energy = BatchFunction(game.function("energy"), threads)
            return
        fn_energy = game.function("energy")
        if self.compiled:
            from .codegen import compile_functions

            cf = compile_functions(
                [fn_terms, fn_energy], f"epo_structured_n{game.N}_k{game.K}", cache_dir
            )
            fn_terms, fn_energy = cf[fn_terms.name()], cf[fn_energy.name()]
        self._energy = BatchFunction(fn_energy, threads)
        self._terms = BatchFunction(fn_terms, threads)
        self._build_maps(sp_r, sp_f)

    # ---- symbolic -------------------------------------------------------------------
    def _build_terms(self):
        g = self.game
        x = ca.SX.sym("x", g.n_x)
        u = ca.SX.sym("u", g.n_u)
        p = ca.SX.sym("p", g.n_p)
        _, _, _, xsel = _var_columns(g)
        r = g.function("traj_residual")(x, u, p)
        Jr = ca.jacobian(r, ca.vertcat(x[xsel.tolist()], u))
        steps = []
        for i, a in enumerate(g.agents):
            X = x[int(g.xoff[i]) : int(g.xoff[i + 1])]
            U = u[int(g.uoff[i]) : int(g.uoff[i + 1])]
            nx, nu = g.nx[i], g.nu[i]
            for k in range(g.K):
                steps.append(
                    a.dynamics.step(X[k * nx : (k + 1) * nx], U[k * nu : (k + 1) * nu], g.dt)
                )
        Jf = ca.jacobian(ca.vertcat(*steps), ca.vertcat(x, u))
        partial = ca.Function("structured_partials", [x, u, p], [r, Jr, Jf])
        xr = g.function("rollout")(u, p)
        outs = partial(xr, u, p)
        fn = ca.Function("structured_terms", [u, p], outs, ["u", "p"], ["r", "Jr", "Jf"])
        return fn, Jr.sparsity(), Jf.sparsity()

    # ---- index maps -------------------------------------------------------------------
    def _build_maps(self, sp_r: ca.Sparsity, sp_f: ca.Sparsity):
        g, L = self.game, self.layout
        K, m, nz, d = L.K, L.m, L.nz, L.d
        kind, stage, comp, _ = _var_columns(g)
        # controls: joint stage order -> game index
        uc = np.concatenate([[0], np.cumsum(g.nu)]).astype(int)
        u_index = np.zeros((K, m), dtype=int)
        for i in range(g.N):
            for k in range(K):
                for c in range(g.nu[i]):
                    u_index[k, uc[i] + c] = int(g.uoff[i]) + k * g.nu[i] + c
        self._u_index = u_index.reshape(-1)
        # residual Jacobian nonzeros -> (stage, local column)
        rows, cols = (np.asarray(a, dtype=int) for a in sp_r.get_triplet())
        h = L.row_stage[rows]
        lag = h - stage[cols]
        local = np.array(
            [
                L.z_index("x" if kd == 0 else "u", int(lg), int(c))
                for kd, lg, c in zip(kind[cols], lag, comp[cols], strict=True)
            ],
            dtype=int,
        )
        nnz = rows.size
        # Hessian blocks: products of nonzero pairs of the same row
        order = np.argsort(rows, kind="stable")
        ia, ib, tgt_a, tgt_b = [], [], [], []
        bounds = np.searchsorted(rows[order], np.arange(sp_r.size1() + 1))
        for row in range(sp_r.size1()):
            idx = order[bounds[row] : bounds[row + 1]]
            for s, a in enumerate(idx):
                for b in idx[s:]:
                    base = h[a] * d * d
                    ia.append(a)
                    ib.append(b)
                    tgt_a.append(base + local[a] * d + local[b])
                    tgt_b.append(base + local[b] * d + local[a])
        ia, ib = np.array(ia, dtype=int), np.array(ib, dtype=int)
        tgt_a, tgt_b = np.array(tgt_a, dtype=int), np.array(tgt_b, dtype=int)
        npair = ia.size
        off = tgt_a != tgt_b
        pr = np.concatenate([np.arange(npair), np.arange(npair)[off]])
        tg = np.concatenate([tgt_a, tgt_b[off]])
        self._pair_a, self._pair_b = ia, ib
        # S_H: npair x ((K+1) d d), so that H_flat = products @ S_H
        self._SH = sps.csr_matrix((np.ones(pr.size), (pr, tg)), shape=(npair, (K + 1) * d * d))
        # J'r stage terms: c_flat = (Jnz * r[rows]) @ S_g
        self._nz_rows = rows
        self._Sg = sps.csr_matrix(
            (np.ones(nnz), (np.arange(nnz), h * d + local)), shape=(nnz, (K + 1) * d)
        )
        # augmented dynamics [F_k, G_k]: constant shifts + dynamics Jacobian nonzeros
        FG0 = np.zeros((K, nz, d))
        for ell, s in enumerate(L.x_lags, 1):  # x_{k+1-l} at stage k+1 is x_{k-(l-1)} at k
            for cc in s:
                FG0[:, L.z_index("x", ell, cc), L.z_index("x", ell - 1, cc)] = 1.0
        for ell, s in enumerate(L.u_lags, 1):  # same for the control lags
            for cc in s:
                FG0[:, self._uz(ell, cc), self._uz(ell - 1, cc)] = 1.0
        self._FG0 = FG0 if FG0.any() else None
        frow, fcol = (np.asarray(a, dtype=int) for a in sp_f.get_triplet())
        xc = np.concatenate([[0], np.cumsum(g.nx)]).astype(int)
        srow = np.concatenate([[0], np.cumsum([K * nx for nx in g.nx])]).astype(int)
        fidx = np.empty(frow.size, dtype=int)
        for q, (fr, fc) in enumerate(zip(frow, fcol, strict=True)):
            i = int(np.searchsorted(srow, fr, side="right") - 1)
            k, c_out = divmod(fr - srow[i], g.nx[i])
            if fc < g.n_x:
                j = int(np.searchsorted(g.xoff, fc, side="right") - 1)
                kk, c_in = divmod(fc - int(g.xoff[j]), g.nx[j])
                col = xc[j] + c_in
            else:
                fu = fc - g.n_x
                j = int(np.searchsorted(g.uoff, fu, side="right") - 1)
                kk, c_in = divmod(fu - int(g.uoff[j]), g.nu[j])
                col = nz + uc[j] + c_in
            if kk != k:
                raise SpecError("dynamics", "a step of the dynamics reads another time step")
            fidx[q] = (k * nz + xc[i] + c_out) * d + col
        self._FG_idx = fidx

    def _uz(self, lag: int, comp: int) -> int:
        return self.layout.z_index("u", lag, comp)

    @property
    def dense_backend(self) -> DenseGN:
        """The :class:`DenseGN` of the same game (built on first use)."""
        if self._dense_be is None:
            self._dense_be = DenseGN(self.game, threads=self.threads)
        return self._dense_be

    # ---- backend interface -----------------------------------------------------------
    def linearize(self, U: np.ndarray, P: np.ndarray):
        """Residual, energy, ``J'r`` and stage blocks for every problem."""
        if self.fallback:
            return self.dense_backend.linearize(U, P)
        L = self.layout
        K, nz, d = L.K, L.nz, L.d
        B = U.shape[0]
        r, Jnz, Jfnz = self._terms(U, P)
        prod = Jnz[:, self._pair_a] * Jnz[:, self._pair_b]
        H = np.asarray(prod @ self._SH).reshape(B, K + 1, d, d)
        c = np.asarray((Jnz * r[:, self._nz_rows]) @ self._Sg).reshape(B, K + 1, d)
        if self._FG0 is None:  # no lags: F_k, G_k are the dynamics Jacobians only
            FG = np.zeros((B, K, nz, d))
        else:
            FG = np.empty((B, K, nz, d))
            FG[:] = self._FG0
        FG.reshape(B, -1)[:, self._FG_idx] = Jfnz
        # J'r by the adjoint sweep: lam_K = c_z,K; g_k = c_u,k + G_k'lam_{k+1}; lam_k = c_z,k + F_k'lam_{k+1}
        gk = np.empty((B, K, L.m))
        lam = c[:, K, :nz]
        FGt = FG.transpose(0, 1, 3, 2)
        for k in range(K - 1, -1, -1):
            v = (FGt[:, k] @ lam[:, :, None])[:, :, 0]
            gk[:, k] = c[:, k, nz:] + v[:, nz:]
            lam = c[:, k, :nz] + v[:, :nz]
        grad = np.empty((B, self.game.n_u))
        grad[:, self._u_index] = gk.reshape(B, -1)
        E = 0.5 * np.einsum("bi,bi->b", r, r)
        return StructuredLinearization(r, E, grad, H, FG, U.copy(), P.copy(), backend=self)

    def energy(self, U: np.ndarray, P: np.ndarray) -> np.ndarray:
        return self._energy(U, P)[0][:, 0]

    def solve(
        self, lin, damping: np.ndarray, rhs: np.ndarray, ellipsoidal: bool = False
    ) -> np.ndarray:
        """Solve ``(J'J + damping D) x = rhs`` for every problem; ``rhs`` is ``(B, n_u)``.

        ``D = I``, or ``diag(J'J)`` (clamped below at ``1e-12``) with ``ellipsoidal``. The
        Riccati factorization is cached on ``lin`` for the last ``(damping, ellipsoidal)``,
        so further right-hand sides (a backward pass) cost two sweeps.
        """
        B = lin.r.shape[0]
        damping = np.broadcast_to(np.asarray(damping, dtype=float), (B,))
        rhs = np.asarray(rhs, dtype=float)
        if rhs.shape != (B, self.game.n_u):
            raise SpecError("rhs", f"expected shape ({B}, {self.game.n_u}), got {rhs.shape}")
        if not isinstance(lin, StructuredLinearization):
            return DenseGN.solve(lin, np.ascontiguousarray(damping), rhs, ellipsoidal)
        L = self.layout
        K, nz, m = L.K, L.nz, L.m
        key = (damping.tobytes(), bool(ellipsoidal))
        if lin._factor is None or lin._factor[0] != key:
            lin._factor = (key, self._factorize(lin, damping, ellipsoidal))
        Qinv, Kg, QzuT = lin._factor[1]
        b = rhs[:, self._u_index].reshape(B, K, m)
        FG = lin.FG
        FGt = FG.transpose(0, 1, 3, 2)
        dff = np.empty((B, K, m))
        pv = np.zeros((B, nz))
        for k in range(K - 1, -1, -1):
            v = (FGt[:, k] @ pv[:, :, None])[:, :, 0]
            dk = -(Qinv[:, k] @ (v[:, nz:] - b[:, k])[:, :, None])
            dff[:, k] = dk[:, :, 0]
            pv = v[:, :nz] + (QzuT[:, k] @ dk)[:, :, 0]
        out = np.empty((B, K, m))
        zu = np.zeros((B, nz + m, 1))
        for k in range(K):
            zu[:, nz:] = Kg[:, k] @ zu[:, :nz] + dff[:, k, :, None]
            out[:, k] = zu[:, nz:, 0]
            if k + 1 < K:
                zu[:, :nz] = FG[:, k] @ zu
        x = np.empty((B, self.game.n_u))
        x[:, self._u_index] = out.reshape(B, -1)
        return x

    # ---- numerics ---------------------------------------------------------------------
    def _factorize(self, lin: StructuredLinearization, damping: np.ndarray, ellipsoidal: bool):
        L = self.layout
        K, nz, m = L.K, L.nz, L.m
        B = lin.r.shape[0]
        if ellipsoidal:
            Dg = lin.diag_jtj()
            Dg = np.where(Dg > 1e-12, Dg, 1e-12) * damping[:, None, None]
        else:
            Dg = np.broadcast_to(damping[:, None, None], (B, K, m))
        H, FG = lin.H, lin.FG
        FGt = FG.transpose(0, 1, 3, 2)
        Qinv = np.empty((B, K, m, m))
        Kg = np.empty((B, K, m, nz))
        QzuT = np.empty((B, K, nz, m))
        P = H[:, K, :nz, :nz]
        d = nz + m
        for k in range(K - 1, -1, -1):
            Q = H[:, k] + FGt[:, k] @ (P @ FG[:, k])
            Q.reshape(B, d * d)[:, nz * (d + 1) :: d + 1] += Dg[:, k]  # view of the u diagonal
            qi = _spd_inverse(Q[:, nz:, nz:])
            Qinv[:, k] = qi
            Qzu = Q[:, :nz, nz:]
            QzuT[:, k] = Qzu
            Kk = -(qi @ Q[:, nz:, :nz])
            Kg[:, k] = Kk
            P = Q[:, :nz, :nz] + Qzu @ Kk
            P = 0.5 * (P + P.transpose(0, 2, 1))
        return Qinv, Kg, QzuT

    def _diag_jtj(self, lin: StructuredLinearization) -> np.ndarray:
        L = self.layout
        K, nz, m = L.K, L.nz, L.m
        B = lin.r.shape[0]
        H, FG = lin.H, lin.FG
        FGt = FG.transpose(0, 1, 3, 2)
        D = np.empty((B, K, m))
        W = H[:, K, :nz, :nz]
        d = nz + m
        for k in range(K - 1, -1, -1):
            M = H[:, k] + FGt[:, k] @ (W @ FG[:, k])
            D[:, k] = M.reshape(B, d * d)[:, nz * (d + 1) :: d + 1]
            W = M[:, :nz, :nz]
        return D


def _spd_inverse(A: np.ndarray) -> np.ndarray:
    """Inverse of a batch of symmetric positive definite matrices.

    numpy's batched ``inv`` (LU with partial pivoting) is the fastest batched LAPACK call
    numpy offers for small matrices and is backward stable on SPD input; a singular
    matrix (zero damping and a rank-deficient ``J``) raises ``LinAlgError`` like the
    dense backend's solve.
    """
    return np.linalg.inv(A)
