"""The LQ game step: the coupled Riccati recursion of one iteration (:mod:`solvers.ilq`, step 2).

Player ``i``'s stage matrices ``L_ik`` (``s.Lam``) and the dynamics ``Phi_k`` (``s.Phi``),
filled by the quadratization (:mod:`solvers.ilq.quadratize`), give the feedback Nash
equilibrium of the LQ game: gains ``P_k``, feed-forward terms ``a_k`` and the shift added
to each player's own block (the "Regularization" of :mod:`solvers.ilq`). Two
implementations with the same algebra: :func:`backward` in numpy (the reference) and
:class:`CompiledRiccati`, one generated-C stage function folded over the horizon. ``s`` is
the :class:`solvers.ilq.ILQSolver` whose arrays they read.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..codegen import BufferCall as _Call

__all__ = ["CompiledRiccati", "backward", "build_indices", "own_shift"]


def build_indices(s) -> None:
    """The numpy recursion's index arrays, set on ``s``: ``_row_p``, ``_row_r`` (the rows
    ``u_i`` of every player's ``T_i``), ``_own_diag`` (the own blocks' diagonals),
    ``_Psi``, ``_term`` (the ``(x, 1)`` rows of the terminal stage) and ``_own2`` (flat
    indices of the own 2x2 blocks, or ``None``)."""
    N, nu, nx, n = s.N, s.nu, s.nxs, s.n
    owner = np.concatenate([np.full(s.game.nu[i], i) for i in range(N)]).astype(np.intp)
    s._row_p, s._row_r = owner, np.arange(nu, dtype=np.intp)
    s._own_diag = (owner, np.arange(nu, dtype=np.intp), np.arange(nu, dtype=np.intp))
    s._Psi = np.zeros((n, nx + 1))
    s._Psi[nu:, :] = np.eye(nx + 1)
    s._term = np.r_[nu + np.arange(nx), n - 1].astype(np.intp)
    # own 2x2 blocks (every agent with two controls): flat indices of h00, h11, h01, h10
    s._own2 = None
    if all(m == 2 for m in s.game.nu):
        u0 = s.uo[:-1]
        base = np.arange(N) * n * n
        s._own2 = np.stack(
            [
                base + u0 * n + u0,
                base + (u0 + 1) * n + u0 + 1,
                base + u0 * n + u0 + 1,
                base + (u0 + 1) * n + u0,
            ]
        ).astype(np.intp)


def own_shift(s, T, delta):
    """Shift per player so that its own block ``T_i[u_i, u_i]`` has pivots >= delta.

    ``0`` when the ``LDL'`` pivots are all ``>= delta``, else ``max(delta - g, delta)``
    with ``g`` the Gershgorin lower bound of the block's eigenvalues.
    """
    if s._own2 is not None:  # closed-form pivots of 2x2 blocks
        h00, h11, h01, h10 = T.reshape(-1)[s._own2]
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = (h00 >= delta) & (h11 - h01 * h10 / h00 >= delta)
        if ok.all():
            return None
        gersh = np.minimum(h00 - np.abs(h01), h11 - np.abs(h10))
        return np.where(ok, 0.0, _shift(gersh, delta))
    mu = np.zeros(s.N)
    for i in range(s.N):
        own = slice(s.uo[i], s.uo[i + 1])
        H = T[i, own, own]
        if not _pivots_ok(H, delta):
            d = np.diag(H)
            gersh = np.min(d - (np.sum(np.abs(H), axis=1) - np.abs(d))) if d.size else 0.0
            mu[i] = _shift(gersh, delta)
    return mu if mu.any() else None


def backward(s, mu0: float, delta: float):
    """Coupled Riccati recursion on ``s.Lam``/``s.Phi`` in numpy.

    Returns ``(PA, mu, ok)``: ``PA (K, nu, nx+1)`` holds ``[P_k | a_k]``, ``mu (K, N)``
    the shift added to each player's own block (``mu0`` included), ``ok`` False when
    a stage could not be solved (non-finite numbers).
    """
    K, N, nu, nx, n = s.K, s.N, s.nu, s.nxs, s.n
    Lam = s.Lam[: K * N * n * n].reshape(K, N, n, n)
    LamK = s.Lam[K * N * n * n :].reshape(N, n, n)
    t = s._term
    Z = LamK[:, t[:, None], t[None, :]]
    PA = np.empty((K, nu, nx + 1))
    mus = np.full((K, N), float(mu0))
    Psi = s._Psi
    od, rp, rr = s._own_diag, s._row_p, s._row_r
    ok = True
    with np.errstate(all="ignore"):
        for k in range(K - 1, -1, -1):
            Ph = s.Phi[k]
            T = Ph.T @ (Z @ Ph)
            T += Lam[k]
            if mu0:
                T[od] += mu0
            mu = s._own_shift(T, delta)
            if mu is not None:
                T[od] += mu[rp]
                mus[k] += mu
            extra = 0.0
            for _ in range(20):  # singular coupled system: shift every own block more
                rows = T[rp, rr]
                try:
                    pa = np.linalg.solve(rows[:, :nu], rows[:, nu:])
                    if np.isfinite(pa).all():
                        break
                except np.linalg.LinAlgError:
                    pass
                step = max(10.0 * extra, delta, 1e-8)
                T[od] += step - extra
                extra = step
            else:
                ok = False
                break
            mus[k] += extra
            PA[k] = pa
            Psi[:nu] = -pa
            Z = Psi.T @ (T @ Psi)
        if ok and not np.isfinite(Z).all():
            ok = False
    return PA, mus, ok


def _shift(g, delta):
    """Shift of an own block with Gershgorin bound ``g`` that failed the pivot test.

    ``delta - g`` lifts the smallest eigenvalue to ``>= delta``; negative curvature is
    mirrored on top (``+ |g|``), so a concave direction gets curvature of its own size
    instead of a near-singular ``delta`` (which would give gains of order ``1/delta``).
    """
    return np.maximum(delta - g, delta) + np.maximum(-g, 0.0)


def _pivots_ok(H, delta):
    try:
        L = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        return False
    return bool(np.min(np.diag(L)) ** 2 >= delta) if L.size else True


class CompiledRiccati:
    """The backward recursion as one generated-C function: a stage folded over ``K`` stages.

    The stage function does the numpy recursion's algebra in CasADi SX with the structural
    zeros of ``L_ik`` and ``Phi_k`` (union pattern over stages) and the same own-block shift
    (closed ``LDL'`` pivots, Gershgorin). The symmetric products ``T_i = L_ik + Phi' Z Phi``
    and ``Z_ik = Psi' T_i Psi`` are computed on their upper triangle and mirrored
    (:func:`_sym_product`; the instruction counts are in docs/ilq.md). A stage whose
    coupled system is singular is not retried inside; the caller sees non-finite gains
    and the numpy recursion (``s._numpy_backward``) takes over. ``s``: the
    :class:`solvers.ilq.ILQSolver`; ``compile_now``: compile the fold here, else
    :func:`solvers.fast_ilq.compile_solver` compiles it with the rest (:meth:`attach`).
    """

    def __init__(self, s, compile_now: bool = True):
        from ..codegen import compile_functions

        self.s = s
        K, N, nu, nx, n = s.K, s.N, s.nu, s.nxs, s.n
        # union pattern of the stage matrices L_ik (k < K), per player
        lt = s._lam_tgt[s._lam_tgt < K * N * n * n]
        rem = lt % (N * n * n)
        pats = []
        for i in range(N):
            e = np.unique(rem[(rem // (n * n)) == i] % (n * n))
            r, c = e // n, e % n
            order = np.lexsort((r, c))  # column-major, CasADi's nonzero order
            pats.append((r[order], c[order]))
        self._lam_cols = np.concatenate(
            [i * n * n + r * n + c for i, (r, c) in enumerate(pats)]
        ).astype(np.intp)
        pr = s._phi_pattern // n
        pc = s._phi_pattern % n
        order = np.lexsort((pr, pc))
        # entries of Phi_k equal to 1 at every stage (the identity in A_k of the built-in
        # models) are numbers in the stage function, not inputs: a product with 1 is
        # exact, so nothing changes by a bit (14.0k instead of 14.7k instructions for 3
        # unicycles)
        one = _ones_at_every_stage(s._quad_sym[6], K, s._phi_pattern.size)[order]
        self._phi_cols = s._phi_pattern[order][~one].astype(np.intp)
        pr, pc = pr[order], pc[order]

        Zin = ca.SX.sym("Z", nx + 1, N * (nx + 1))
        lam = ca.SX.sym("lam", self._lam_cols.size)
        phi = ca.SX.sym("phi", self._phi_cols.size)
        mu0 = ca.SX.sym("mu0")
        delta = ca.SX.sym("delta")
        Ph = ca.SX(ca.Sparsity.triplet(nx + 1, n, pr[~one].tolist(), pc[~one].tolist()), phi)
        ones_r = [s.nx + m for m in range(s.na)] + [nx] + pr[one].tolist()
        ones_c = [int(c) for c in s.aug] + [n - 1] + pc[one].tolist()
        Ph = Ph + ca.SX(ca.Sparsity.triplet(nx + 1, n, ones_r, ones_c), ca.SX.ones(len(ones_r)))
        Ts, off, mus = [], 0, []
        for i, (r, c) in enumerate(pats):
            L = ca.SX(ca.Sparsity.triplet(n, n, r.tolist(), c.tolist()), lam[off : off + r.size])
            off += r.size
            Z = Zin[:, i * (nx + 1) : (i + 1) * (nx + 1)]
            T = L + _sym_product(Ph, ca.mtimes(Z, Ph))
            s0, s1 = int(s.uo[i]), int(s.uo[i + 1])
            H = T[s0:s1, s0:s1] + mu0 * ca.SX.eye(s1 - s0)
            piv = _ldl_pivots(H)
            ok = piv[0] >= delta
            for d in piv[1:]:
                ok = ca.logic_and(ok, d >= delta)
            gersh = _gershgorin(H)
            mu = ca.if_else(ok, 0, ca.fmax(delta - gersh, delta) + ca.fmax(-gersh, 0))
            mus.append(mu0 + mu)
            D = ca.SX(n, n)
            D[s0:s1, s0:s1] = (mu0 + mu) * ca.SX.eye(s1 - s0)
            Ts.append(T + D)
        rows = ca.vertcat(*[Ts[i][int(s.uo[i]) : int(s.uo[i + 1]), :] for i in range(N)])
        PA = ca.solve(rows[:, :nu], rows[:, nu:])
        Psi = ca.vertcat(-PA, ca.SX.eye(nx + 1))
        Zout = []
        for T in Ts:
            Zout.append(_sym_product(Psi, ca.mtimes(T, Psi)))
        stage = ca.Function(
            "ilq_riccati_stage",
            [Zin, lam, phi, mu0, delta],
            [ca.horzcat(*Zout), ca.vec(PA.T), ca.vertcat(*mus)],
        )
        self.stage = stage  # one stage (solvers.fast_ilq: the same SX over a batch of starts)
        self.n_instructions = stage.n_instructions()
        # The fold over K stages is a loop in the generated C around one stage function, so
        # compile time does not grow with K (the library is cached per structure, K included:
        # folding a K-independent compiled stage in CasADi's VM cost 0.8 us more per stage)
        acc = stage.mapaccum("ilq_riccati", K)  # CasADi may nest and rename it for large K
        self.acc = ca.Function("ilq_riccati", acc.mx_in(), acc.call(acc.mx_in()))
        self.call = None
        if compile_now:  # else solvers.fast_ilq.compile_solver compiles it with the rest
            self.attach(compile_functions([self.acc], "ilq_riccati", optimize="-O1"))

    def attach(self, lib: dict) -> None:
        """Use the compiled fold ``lib['ilq_riccati']``."""
        self.call = _Call(lib["ilq_riccati"])

    def backward(self, mu0, delta):
        """:func:`backward` by the compiled fold: ``(PA, mu, ok)``."""
        s = self.s
        K, N, nu, nx, n = s.K, s.N, s.nu, s.nxs, s.n
        Lam = s.Lam[: K * N * n * n].reshape(K, N * n * n)
        LamK = s.Lam[K * N * n * n :].reshape(N, n, n)
        t = s._term
        Z = LamK[:, t[:, None], t[None, :]]  # (N, nx+1, nx+1) -> column-major (nx+1, N(nx+1))
        Zc = np.ascontiguousarray(Z.transpose(0, 2, 1)).reshape(-1)
        lam = Lam[::-1][:, self._lam_cols]
        phi = s.Phi.reshape(K, -1)[::-1][:, self._phi_cols]
        _, PA, mu = self.call(Zc, lam, phi, np.full(K, float(mu0)), np.full(K, float(delta)))
        PA = PA.reshape(K, nu, nx + 1)[::-1].copy()
        mu = mu.reshape(K, N)[::-1].copy()
        ok = bool(np.isfinite(PA).all())
        if not ok:  # singular stage: the numpy recursion retries with larger shifts
            return s._numpy_backward(mu0, delta)
        return PA, mu, ok


def _ones_at_every_stage(phi_out, K: int, m: int) -> np.ndarray:
    """Which of the ``m`` trajectory-dependent entries of ``Phi_k`` are the constant 1 at
    every stage ``k`` of ``phi_out`` (``K m`` SX entries, stage-major)."""
    return np.array(
        [all(phi_out[k * m + j].is_one() for k in range(K)) for j in range(m)], dtype=bool
    )


def _sym_product(A, B):
    """``A' B`` for a product known to be symmetric: the upper triangle, mirrored.

    Every entry ``a <= b`` is one dot product of columns; ``(b, a)`` reuses it, so the
    stage function does about half the work of ``mtimes(A.T, B)`` (and ``Z`` and ``T`` are
    exactly symmetric).
    """
    m = A.shape[1]
    out = ca.SX(m, m)
    for a in range(m):
        for b in range(a, m):
            v = ca.dot(A[:, a], B[:, b])
            out[a, b] = v
            if a != b:
                out[b, a] = v
    return out


def _ldl_pivots(H):
    """Pivots of the ``LDL'`` factorization (no pivoting) of a small symmetric SX matrix."""
    m = H.shape[0]
    A = [[H[i, j] for j in range(m)] for i in range(m)]
    piv = []
    for j in range(m):
        d = A[j][j]
        piv.append(d)
        for i in range(j + 1, m):
            f = A[i][j] / d
            for c in range(j + 1, m):
                A[i][c] = A[i][c] - f * A[j][c]
    return piv


def _gershgorin(H):
    m = H.shape[0]
    lows = []
    for i in range(m):
        off = 0
        for j in range(m):
            if j != i:
                off = off + ca.fabs(H[i, j])
        lows.append(H[i, i] - off)
    g = lows[0]
    for v in lows[1:]:
        g = ca.fmin(g, v)
    return g
