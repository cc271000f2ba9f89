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
are generated C (:func:`solvers.codegen.compile_libraries`, one library per function,
compiled in parallel, cached on disk by a hash of their serialization, i.e. by the game's
structure, never by parameter values: ``p`` is an input; ``fused_sweep`` and
``fused_diag`` are compiled when first used). For C, ``fused_solve`` and ``fused_sweep``
take a staged form with the same arithmetic: ``K`` calls of one small SX function per stage
(Riccati step, backward sweep, forward sweep; stage blocks are exchanged in one pattern
for all stages), which compiles at ``-O1`` in a fraction of the time of the unrolled graph,
while the interpreter runs the unrolled graph, where a call per stage would cost more
than the stage's arithmetic.
From stage size :data:`SCHUR_KERNEL_MIN_STAGE_SIZE` on, the dense part of the Riccati step
(Cholesky factor of the control block, ``Y``, the Schur complement ``P``) is hand-written C
with loops the compiler vectorizes (:data:`SCHUR_KERNEL_C`, linked into ``fused_solve``),
and only ``Q = H_k + FG_k' P FG_k`` stays an SX function of the stage.
When the stage functions below have more than :data:`STAGED_MIN_INSTRUCTIONS` SX
instructions in all (three or more unicycles at K = 40, two from K = 47; the left-turn
game, with lanes: 188k in one graph), ``fused_linearize`` and ``energy`` are staged: each
stage's outputs (its residual rows, ``H_k``, ``c_k``, ``FG_k``) become one SX function of
the window of stages they depend on, stages with the same function form a group mapped over
its stages (three groups for the crossing and left-turn games: first, middle, terminal),
the rollout is the game's and ``J'r`` is the adjoint sweep as ``K`` calls of one stage
function (:func:`_staged_linearize`). Staging cuts the compile time several-fold at a
cost of a few percent in the step; the two-unicycle RPI game keeps the one graph, whose
step is faster there (compile times and step costs of both forms: docs/bench_lm.md,
"Scaling with N and K, twelve agents, first compile"). Steps equal the interpreted
structured and dense backends up to rounding (the Riccati solve uses a Cholesky factor where
:class:`StructuredGN` inverts; tested to 1e-12); the staged linearization gives the
one-graph numbers bit for bit (the same SX operations per stage).

Cost
    The unrolled graph grows with ``K (nz + m)^3`` scalar instructions, which generated C
    runs several times faster than CasADi's SX virtual machine. With generated C the step
    is several times cheaper than :class:`StructuredGN` with generated C, in a batch and,
    up to eight agents, more so for one problem; interpreted it is cheaper for one problem
    and dearer in a large batch (numpy amortizes its per-stage calls over the batch, the SX
    interpreter does not). At twelve agents (d = 72) the Riccati stage as unrolled SX has
    101k instructions and takes most of the step; the C elimination
    (:data:`SCHUR_KERNEL_MIN_STAGE_SIZE`) leaves 12k of them in SX. The measurements, with
    their commands (``bench/bench_lm.py``, crossing game, K = 40, per path, agent count
    and batch size), are in docs/bench_lm.md, a summary in docs/benchmarks.md ("One LM
    step"). Above :data:`MAX_STAGE_SIZE` (interpreted) or
    :data:`MAX_STAGE_SIZE_COMPILED` (generated C), or when :class:`StructuredGN` itself
    falls back to the dense solve (short horizons, rows coupling many stages), the backend
    delegates to :class:`StructuredGN` and says why in :attr:`FusedGN.fallback`.

A zero damping with a rank-deficient ``J`` gives a zero pivot, so the step is NaN/inf
and :func:`solvers.lm.solve_lm` marks that problem ``NONFINITE`` (the numpy backends raise
or return NaN for it).

Modules. This module holds :class:`FusedGN`, its limits and the staged linearization; the
Riccati step lives beside it and every name stays importable from here:
:mod:`solvers.fast_gn_riccati` (the stage pieces, ``fused_solve``, ``fused_sweep`` and
``fused_diag`` as SX, and the C elimination :data:`SCHUR_KERNEL_C`).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame

from .batch import BatchFunction
from .fast_gn_riccati import SCHUR_KERNEL_C, _FusedRiccati, schur_kernel_source
from .fast_gn_riccati import _cholesky as _cholesky
from .fast_gn_riccati import _riccati_stage as _riccati_stage
from .fast_gn_riccati import _sweep_back as _sweep_back
from .fast_gn_riccati import _sweep_fwd as _sweep_fwd
from .gn import DenseGN
from .structured import (
    StageLayout,
    StageLinearization,
    StructuredGN,
    _var_columns,
    check_stage_game,
    stage_layout,
)

__all__ = [
    "MAX_STAGE_GROUPS",
    "MAX_STAGE_SIZE",
    "MAX_STAGE_SIZE_COMPILED",
    "SCHUR_KERNEL_C",
    "SCHUR_KERNEL_MIN_STAGE_SIZE",
    "STAGED_MIN_INSTRUCTIONS",
    "FusedGN",
    "schur_kernel_source",
    "FusedLinearization",
]

#: Largest stage size ``d = nz + m`` (augmented state + joint controls) the fused backend
#: builds (4 unicycles: 24, the largest measured). The unrolled graphs it builds for the
#: interpreter grow like ``K d^3`` instructions (204k for ``fused_solve`` at d = 24,
#: K = 40; build time and memory follow), so above this size :class:`FusedGN` delegates
#: to :class:`StructuredGN`.
MAX_STAGE_SIZE = 24
#: The same limit with ``compiled=True``, where only the staged graphs are built (one SX
#: function per stage): 12 unicycles (d = 72), the largest measured, whose Riccati step
#: has 101k SX instructions (d = 48: 32k), the largest part of the compile time (measured
#: in docs/bench_lm.md); with the C elimination (:data:`SCHUR_KERNEL_MIN_STAGE_SIZE`) its
#: SX part has 12k.
MAX_STAGE_SIZE_COMPILED = 72
#: The compiled backend uses the staged linearization when its stage functions have more
#: SX instructions than this, summed over the stages (about 0.89 of the one-graph
#: ``fused_linearize``, which is then not built). The one graph's compile time grows with
#: its instruction count and the staged form compiles in a fraction of it, at a small cost
#: per step: four unicycles at K = 20 (14.4k staged, 16k in one graph) are staged, while
#: the two-unicycle RPI game (K = 40: 10.9k staged, 12.3k in one graph) keeps the one
#: graph, faster per step in a batch (compile times and steps: docs/bench_lm.md, "Scaling
#: with N and K, twelve agents, first compile").
STAGED_MIN_INSTRUCTIONS = 12_500
#: Largest number of distinct stage functions of the staged linearization (compile time
#: grows with it); a game with more falls back to the one-graph ``fused_linearize``.
MAX_STAGE_GROUPS = 12
#: From this stage size ``d = nz + m`` on, the compiled Riccati step eliminates the
#: stage's controls (Cholesky factor of ``Q_uu + diag(D)``, ``Y = C^{-1} Q_uz``,
#: ``P = Q_zz - Y'Y``: the dense part, about 90 % of the stage's instructions) in the
#: hand-written C loops of :data:`SCHUR_KERNEL_C` (``-O3``, vectorized) instead of the
#: unrolled SX graph; ``Q`` itself stays SX (it exploits the block-diagonal dynamics).
#: The kernel makes the step slower at d = 12 (two unicycles), faster from d = 24 on, the
#: more so the larger the stage (measured in docs/bench_lm.md, "The Riccati elimination
#: in C").
SCHUR_KERNEL_MIN_STAGE_SIZE = 24


@dataclass
class FusedLinearization(StageLinearization):
    """What :class:`FusedGN` knows at the current iterate of every problem: the fields of
    :class:`solvers.structured.StageLinearization`, where ``H`` and ``FG`` hold
    the structural nonzeros of the stage blocks ``R_k'R_k`` and of the augmented dynamics,
    ``(B, nnz)`` each, as inputs of ``fused_solve``; ``backend`` is the :class:`FusedGN`.
    """

    def diag_jtj(self) -> np.ndarray:
        """``diag(J'J)`` as ``(B, K, m)`` joint stage controls (exact, cached)."""
        if self._diag is None:
            L = self.backend.layout
            d = self.backend._diag(self.H, self.FG)[0]
            self._diag = d.reshape(-1, L.K, L.m)
        return self._diag


class FusedGN(_FusedRiccati):
    """Fused Gauss-Newton backend (see the module docstring).

    ``threads``: threads of the mapped CasADi evaluation (None: ``EPO_THREADS`` or all
    cores). ``compiled``: generated C instead of CasADi's interpreter (needs a C compiler;
    compiled once per game structure and cached in ``cache_dir``). After construction
    :attr:`fallback` is ``None``, or a sentence saying why the backend delegates to
    :class:`solvers.structured.StructuredGN` (:attr:`delegate`). ``schur_kernel``
    (``compiled=True`` only): the Riccati step's dense elimination in hand-written C
    (:data:`SCHUR_KERNEL_C`) instead of unrolled SX; ``None`` chooses by stage size
    (:data:`SCHUR_KERNEL_MIN_STAGE_SIZE`). The numbers agree to rounding (1e-15).
    """

    def __init__(
        self,
        game: PotentialGame,
        threads: int | None = None,
        compiled: bool = False,
        cache_dir: str | None = None,
        schur_kernel: bool | None = None,
    ):
        check_stage_game(game)
        if schur_kernel not in (None, True, False):
            raise SpecError("schur_kernel", f"expected None, True or False, got {schur_kernel!r}")
        if schur_kernel and not compiled:
            raise SpecError("schur_kernel", "the C kernel needs compiled=True")
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
        limit = MAX_STAGE_SIZE_COMPILED if self.compiled else MAX_STAGE_SIZE
        if L.d > limit:
            self.fallback = f"stage size nz + m = {L.d} > {limit}" + (
                " (compiled)"
                if self.compiled
                else ": the unrolled Riccati graph (~K d^3 instructions) is slower than "
                "StructuredGN's numpy recursion; compiled=True allows up to "
                f"{MAX_STAGE_SIZE_COMPILED}"
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
        #: whether the compiled Riccati step runs the hand-written C elimination
        self.schur_kernel = (
            self.compiled and L.d >= SCHUR_KERNEL_MIN_STAGE_SIZE
            if schur_kernel is None
            else bool(schur_kernel)
        )
        self._kernel_objects: tuple = ()
        f_energy = game.function("energy")
        #: distinct stage functions of the staged linearization (0: the one-graph function)
        self.stage_groups = 0
        staged = self.compiled and self._build_linearize(x, u, p, r, Jr, staged=True)
        if staged and staged[3] > STAGED_MIN_INSTRUCTIONS:
            f_lin, f_energy, self.stage_groups = staged[:3]
        else:
            f_lin = self._build_linearize(x, u, p, r, Jr)
        self._cache_dir = cache_dir
        self._later: dict[str, ca.Function] = {}
        if self.compiled:
            # staged graphs only (the unrolled ones grow like K d^3 and are not needed)
            f_solve, f_sweep, f_diag = self._build_solve_staged()
            from .codegen import compile_libraries

            # one library per function (compile_functions picks -O1 or -O0 by each one's
            # size), compiled in parallel; fused_sweep (the layer's backward pass) and
            # fused_diag (ellipsoidal damping) only when first used
            tag = f"n{game.N}_k{game.K}"
            fs = [f_lin, f_solve, f_energy]
            objs = {"fused_solve": self._kernel_objects}  # the kernel's callers link it
            libs = compile_libraries(
                [([f], f"epo_{f.name()}_{tag}", objs.get(f.name(), ())) for f in fs], cache_dir
            )
            f_lin, f_solve, f_energy = (lib[f.name()] for lib, f in zip(libs, fs, strict=True))
            self._later = {"sweep": f_sweep, "diag": f_diag}
        else:
            f_solve, f_sweep, f_diag = self._build_solve()
            self._sweep_fn = BatchFunction(f_sweep, threads)
            self._diag_fn = BatchFunction(f_diag, threads)
        self._lin = BatchFunction(f_lin, threads)
        self._solve = BatchFunction(f_solve, threads)
        self._energy = BatchFunction(f_energy, threads)

    def _compiled_later(self, key: str) -> BatchFunction:
        """``fused_sweep`` or ``fused_diag`` as generated C, compiled (or loaded from the
        cache) on first use."""
        from .codegen import compile_functions

        f = self._later[key]
        lib = compile_functions(
            [f], f"epo_{f.name()}_n{self.game.N}_k{self.game.K}", self._cache_dir
        )
        return BatchFunction(lib[f.name()], self.threads)

    @property
    def _sweep(self) -> BatchFunction:
        if getattr(self, "_sweep_fn", None) is None:
            self._sweep_fn = self._compiled_later("sweep")
        return self._sweep_fn

    @property
    def _diag(self) -> BatchFunction:
        if getattr(self, "_diag_fn", None) is None:
            self._diag_fn = self._compiled_later("diag")
        return self._diag_fn

    # ---- symbolic -------------------------------------------------------------------
    def _build_linearize(self, x, u, p, r, Jr, staged: bool = False):
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
        # Stage blocks go out in one pattern for all stages k < K (the union of their lower
        # triangles; explicit zeros where a stage has none), so that one stage function can
        # read any stage; the terminal block H_K,zz has its own pattern.
        spHu = ca.tril(Hs[0]).sparsity()
        for hk in Hs[1:K]:
            spHu = spHu + ca.tril(hk).sparsity()
        spHK = ca.tril(Hs[K][:nz, :nz]).sparsity()
        # FG_k in one pattern too; an entry that is the same constant in every stage
        # (shifts, identities, dt) is built into the solve functions instead of read
        spF = FGs[0].sparsity()
        for fk in FGs[1:]:
            spF = spF + fk.sparsity()
        proj = [ca.project(fk, spF) for fk in FGs]
        const = np.ones(spF.nnz(), dtype=bool)
        vals = np.zeros(spF.nnz())
        for i in range(spF.nnz()):
            es = [pk.nz[i] for pk in proj]
            if all(e.is_constant() for e in es) and len({float(e) for e in es}) == 1:
                vals[i] = float(es[0])
            else:
                const[i] = False
        self._sp_H = (spHu, spHK)
        self._fg = (spF, const, vals)
        var = np.flatnonzero(~const).tolist()
        H_out = ca.vertcat(
            *[ca.project(ca.tril(hk), spHu).nz[:] for hk in Hs[:K]],
            ca.tril(Hs[K][:nz, :nz]).nz[:] if spHK.nnz() else ca.SX(0, 1),
        )
        FG_out = ca.vertcat(*[pk.nz[var] for pk in proj]) if var else ca.SX(0, 1)
        # J'r by the adjoint sweep over stages
        gk = [None] * K
        lam = cs[K][:nz]
        for k in range(K - 1, -1, -1):
            v = ca.mtimes(FGs[k].T, lam)
            gk[k] = cs[k][nz:] + v[nz:]
            lam = cs[k][:nz] + v[:nz]
        grad = ca.vertcat(*gk)[self._game_order().tolist()]
        if staged:
            # per stage: its residual rows, tril(H_k) in its pattern, c_k and FG_k's nonzeros
            row_k = np.maximum(L.row_stage, 0)
            parts = []
            for k in range(K + 1):
                rk = np.flatnonzero(row_k == k)
                pk = [ca.densify(r[rk.tolist()]) if rk.size else ca.SX(0, 1)]
                if k < K:
                    pk += [
                        ca.densify(ca.project(ca.tril(Hs[k]), spHu).nz[:]),
                        ca.densify(cs[k]),
                        ca.densify(proj[k].nz[var]) if var else ca.SX(0, 1),
                    ]
                else:
                    pk += [
                        ca.densify(ca.tril(Hs[K][:nz, :nz]).nz[:]) if spHK.nnz() else ca.SX(0, 1),
                        ca.densify(cs[K][:nz]),
                    ]
                parts.append((rk, pk))
            return _staged_linearize(self, x, u, p, parts)
        outs = [
            ca.densify(r),
            0.5 * ca.sumsqr(r),
            ca.densify(grad),
            ca.densify(H_out),
            ca.densify(FG_out),
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


def _staged_linearize(be: FusedGN, x, u, p, parts):
    """``fused_linearize`` and ``energy`` as MX graphs of mapped stage functions, or ``None``.

    ``parts[k] = (rows_k, [r_k, H_k, c_k, FG_k])``: stage ``k``'s residual rows and its
    outputs as SX expressions of the whole trajectory. Each stage's outputs become a
    function of the window of stages they depend on (``z_j = (x_j, u_j)``, ``p`` shared);
    stages whose functions serialize identically form one group, mapped over its stages
    (a loop in C). The rollout is the game's, ``E = 1/2 |r|^2`` in the game's row order and
    ``J'r`` by the adjoint sweep as ``K`` calls of one stage function: the arithmetic of
    the one-graph function, operation for operation, so the numbers agree to rounding.
    """
    g, L = be.game, be.layout
    K, nz, d = L.K, L.nz, L.d
    # stage of every entry of z = [x; u] (game order, agent-major)
    zst = np.zeros(g.n_x + g.n_u, dtype=int)
    for i in range(g.N):
        nx, nu = g.nx[i], g.nu[i]
        xo = int(g.xoff[i])
        zst[xo : xo + (K + 1) * nx] = np.arange((K + 1) * nx) // nx
        uo = g.n_x + int(g.uoff[i])
        zst[uo : uo + K * nu] = np.arange(K * nu) // nu
    z = ca.vertcat(x, u)
    outs = [ca.vertcat(*pk) for _, pk in parts]
    allout = ca.vertcat(*outs)
    rows, cols = (np.asarray(a, dtype=int) for a in ca.jacobian_sparsity(allout, z).get_triplet())
    lo = np.full(allout.shape[0], K + 1)
    hi = np.full(allout.shape[0], -1)
    np.minimum.at(lo, rows, zst[cols])
    np.maximum.at(hi, rows, zst[cols])
    sizes = [[int(e.shape[0]) for e in pk] for _, pk in parts]
    groups: dict = {}
    off = 0
    for k, e in enumerate(outs):
        ne = int(e.shape[0])
        a = int(lo[off : off + ne].min(initial=k))
        b = int(hi[off : off + ne].max(initial=k))
        off += ne
        a, b = min(a, k), max(b, k)
        win = np.flatnonzero((zst >= a) & (zst <= b))
        win = win[np.lexsort((win, zst[win]))]
        w_s, p_s = ca.SX.sym("w", win.size), ca.SX.sym("p", g.n_p)
        try:
            f = ca.Function("s", [z[win.tolist()], p], [e])
        except RuntimeError:  # depends on a stage outside its window (not by derivative)
            return None
        e_s = ca.cse(f.call([w_s, p_s])[0])
        f = ca.Function("s", [w_s, p_s], [e_s])
        key = (f.serialize(), tuple(sizes[k]))
        grp = groups.get(key)
        if grp is None:
            if len(groups) >= MAX_STAGE_GROUPS:
                return None
            grp = groups[key] = {"w": w_s, "p": p_s, "e": e_s, "ks": [], "wins": []}
            grp["n"] = f.n_instructions()
        grp["ks"].append(k)
        grp["wins"].append(win)
    # MX graph: rollout, windows, mapped groups, then index maps into the outputs
    U, P = ca.MX.sym("u", g.n_u), ca.MX.sym("p", g.n_p)
    Z = ca.vertcat(g.function("rollout")(U, P), U)
    blocks_lin, blocks_r = [], []
    where = [None] * (K + 1)  # stage k -> (group's flat offset, member j, e length)
    base_lin = base_r = 0
    for gi, grp in enumerate(groups.values()):
        ks, wins = grp["ks"], np.stack(grp["wins"])
        m, w = wins.shape
        ne = int(grp["e"].shape[0])
        nr = sizes[ks[0]][0]
        f = ca.Function(f"fused_lin_stage{gi}", [grp["w"], grp["p"]], [grp["e"]])
        fr = ca.Function(f"fused_res_stage{gi}", [grp["w"], grp["p"]], [grp["e"][:nr]])
        Wz = ca.reshape(Z[wins.reshape(-1).tolist()], w, m)
        blocks_lin.append(ca.vec(f.map(f"fused_lin_map{gi}", "serial", m, [1], [])(Wz, P)))
        if nr:
            blocks_r.append(ca.vec(fr.map(f"fused_res_map{gi}", "serial", m, [1], [])(Wz, P)))
        for j, k in enumerate(ks):
            where[k] = (base_lin + j * ne, base_r + j * nr)
        base_lin += m * ne
        base_r += m * nr
    V = ca.vertcat(*blocks_lin)
    R = ca.vertcat(*blocks_r) if blocks_r else ca.MX(0, 1)
    n_r = g.n_r
    r_lin, r_res = np.empty(n_r, dtype=int), np.empty(n_r, dtype=int)
    H_idx, c_idx, F_idx = [], [], []
    for k, (rk, _) in enumerate(parts):
        o, orr = where[k]
        sz = sizes[k]
        r_lin[rk] = o + np.arange(sz[0])
        r_res[rk] = orr + np.arange(sz[0])
        o += sz[0]
        H_idx.append(o + np.arange(sz[1]))
        o += sz[1]
        c_idx.append(o + np.arange(sz[2]))
        o += sz[2]
        if k < K:
            F_idx.append(o + np.arange(sz[3]))

    def take(vec, idx):
        idx = np.concatenate(idx) if isinstance(idx, list) else idx
        return vec[idx.tolist()] if idx.size else ca.MX(0, 1)

    r = take(V, r_lin)
    H = take(V, H_idx)
    FGv = take(V, F_idx)
    # J'r by the adjoint sweep: lam_K = c_K; g_k = c_k,u + G_k' lam; lam_k = c_k,z + F_k' lam
    nFv = be._sizes()[2]
    lam_s, c_s, F_s = ca.SX.sym("lam", nz), ca.SX.sym("c", d), ca.SX.sym("FG", nFv)
    v = ca.mtimes(be._stage_FG(F_s).T, lam_s)
    f_adj = ca.Function(
        "fused_adjoint_stage",
        [lam_s, c_s, F_s],
        [ca.densify(c_s[:nz] + v[:nz]), ca.densify(c_s[nz:] + v[nz:])],
    )
    lam = take(V, c_idx[K])
    gk = [None] * K
    for k in range(K - 1, -1, -1):
        lam, gk[k] = f_adj(lam, take(V, c_idx[k]), FGv[k * nFv : (k + 1) * nFv])
    grad = ca.vertcat(*gk)[be._game_order().tolist()]
    f_lin = ca.Function(
        "fused_linearize",
        [U, P],
        [r, 0.5 * ca.sumsqr(r), grad, H, FGv],
        ["u", "p"],
        ["r", "E", "g", "H", "FG"],
    )
    rr = take(R, r_res)
    f_energy = ca.Function("energy", [U, P], [0.5 * ca.sumsqr(rr)], ["u", "p"], ["E"])
    n_instr = sum(grp["n"] * len(grp["ks"]) for grp in groups.values())
    return f_lin, f_energy, len(groups), n_instr
