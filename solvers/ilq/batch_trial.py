"""The evaluations behind many starts at once (:class:`solvers.ilq.iteration.BatchSolve`).

:func:`batchable` says whether a solver and its options take the batched iteration (the
one-call trial in generated C, the residual line search). ``_batch_functions`` builds, once
per compiled solver, the trial over many starts (:class:`solvers.fast_ilq.CompiledWideTrial`
from :func:`solvers.fast_ilq.wide_trial`, else ``_MappedTrial``: the one-call trial one
start after the other) and the compiled rollout mapped over the starts. ``_Evaluation`` is
one round's evaluation of the running starts: their trials in one call, their
linearizations as :meth:`~solvers.ilq.iteration.SolveOnce.linearize` computes them.
``_exact_sums`` sums squares exactly rounded (numpy's longdouble), so a batched merit
equals the per-start one; ``_INIT`` ... ``_FINAL`` name what a start's pending evaluation
is for.
"""

from __future__ import annotations

import math
import weakref

import numpy as np

# --------------------------------------------------------------------------------------
# many starts at once
# --------------------------------------------------------------------------------------
# what a start's pending evaluation is for (BatchSolve.phase)
_INIT, _TRIAL, _RESET, _RELIN, _FINAL = range(5)
# (trial evaluation, mapped rollout) of a compiled solver, keyed by its CompiledTrial
_BATCH_FNS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def batchable(s, opts) -> bool:
    """Whether :class:`BatchSolve` applies to solver ``s`` with ``opts``: the one-call
    trial in generated C (``compiled=True``, the game's own costs) and the residual line
    search (after :meth:`solvers.ilq.ILQSolver.compile`)."""
    return (
        bool(opts.compiled)
        and opts.line_search == "residual"
        and s.kink_pins is None
        and s._ftrial is not None
    )


def _batch_functions(s):
    """The solver's one-call trial over many starts (:class:`solvers.fast_ilq.
    CompiledWideTrial`, else :class:`_MappedTrial`) and its compiled rollout mapped over
    the starts (:class:`solvers.batch.BatchFunction`); built once per compiled solver."""
    fns = _BATCH_FNS.get(s._ftrial)
    if fns is None:
        from .. import fast_ilq
        from ..batch import BatchFunction

        trial = fast_ilq.wide_trial(s) or _MappedTrial(s)
        fns = (trial, BatchFunction(s._croll.call.f))
        _BATCH_FNS[s._ftrial] = fns
    return fns


#: unit roundoff of numpy's longdouble (2^-64 with x87 extended precision)
_LD_U = float(np.finfo(np.longdouble).eps) / 2


def _exact_sums(x: np.ndarray) -> np.ndarray:
    """Row sums of ``x (m, n)`` (finite, >= 0) rounded once to float64, as ``math.fsum``.

    The rows are summed pairwise in numpy's longdouble (zeros padded to ``2^d`` columns,
    ``d`` levels of halves added): for terms >= 0 the result ``s`` is within ``d u S``
    of the exact sum ``S`` (``u`` the longdouble's unit roundoff), so where both ends of
    ``s -/+ 2 d u s`` round to the same float64, that float64 is the exactly rounded sum
    (rounding is monotone). The other rows (a sum near a rounding boundary, or no wider
    longdouble) take ``math.fsum``.
    """
    m, n = x.shape
    out = np.zeros(m)
    if not x.size:
        return out
    d = max(1, (n - 1).bit_length())
    s = np.zeros((m, 1 << d), dtype=np.longdouble)
    s[:, :n] = x
    for _ in range(d):
        h = s.shape[1] // 2
        s = s[:, :h] + s[:, h:]
    s = s[:, 0]
    e = s * np.longdouble(2 * d * _LD_U)
    lo, hi = (s - e).astype(np.float64), (s + e).astype(np.float64)
    sure = lo == hi
    out[sure] = lo[sure]
    for j in np.nonzero(~sure)[0]:
        out[j] = math.fsum(x[j].tolist())
    return out


class _MappedTrial:
    """The compiled one-call trial mapped over the starts (a
    :class:`solvers.batch.BatchFunction`), with the per-start stats of
    :class:`solvers.fast_ilq.CompiledWideTrial` from :func:`solvers.fast_ilq.trial_stats`."""

    def __init__(self, s):
        from ..batch import BatchFunction

        self.s, self.f = s, BatchFunction(s._ftrial.call)
        self._in: list = []

    def inputs(self, m: int) -> list[np.ndarray]:
        f = self.f.f
        self._in = [np.zeros((m, f.nnz_in(i))) for i in range(f.n_in())]
        return self._in

    def run(self, m: int) -> list[np.ndarray]:
        from ..fast_ilq import trial_stats

        X, U, PA, mu, r = self.f(*self._in)
        return [X, U, PA, mu, r, trial_stats(self.s, X, U, PA, r)]


class _Evaluation:
    """The one-call trials of the pending starts ``idx`` (``m`` of them), evaluated in one
    call for all, and their linearizations as :meth:`SolveOnce.linearize` computes them:
    ``X (m, K+1, nx)``, ``U``, ``PA``, ``mu``, ``r`` (residual rows), ``res``, ``merit``
    and ``good`` (a trial's trajectory is finite and inside the trust region)."""

    def __init__(self, bs: BatchSolve, idx: list[int]):  # noqa: F821 (solvers.ilq.iteration)
        s, opts = bs.s, bs.opts
        K, nx, nu, nxs, N = s.K, s.nx, s.nu, s.nxs, s.N
        ia = np.asarray(idx, dtype=np.intp)
        m, B = ia.size, bs.B
        trial = np.array([bs.phase[b] == _TRIAL for b in idx])
        i_x0, i_X, i_U, i_PA, i_eps, i_p, i_mu, i_d = bs.trial.inputs(m)
        np.take(bs.x0, ia, axis=0, out=i_x0)
        np.take(bs.X.reshape(B, -1), ia, axis=0, out=i_X)
        np.take(bs.U.reshape(B, -1), ia, axis=0, out=i_U)
        np.take(bs.PA.reshape(B, -1), ia, axis=0, out=i_PA)
        i_PA[~trial] = 0.0  # a linearization at (Xbar, Ubar): a rollout with P = 0, eps = 0
        i_eps[:, 0] = [bs.eps[b] if t else 0.0 for b, t in zip(idx, trial, strict=True)]
        np.take(bs.P, ia, axis=0, out=i_p)
        mu = i_mu[:, 0]
        mu[:] = [bs.mu_run[b] for b in idx]
        i_d.fill(bs.delta)
        Xr, P = i_X.reshape(m, K + 1, nx), i_p
        outs = bs.trial.run(m)
        self.X = outs[0].reshape(m, K + 1, nx)
        self.U = outs[1].reshape(m, K, nu)
        self.PA = outs[2].reshape(m, K, nu, nxs + 1)
        self.mu = outs[3].reshape(m, K, N)
        self.r = outs[4]
        st = outs[5]
        ok, self.good, res, asum, c_ok = (
            st[:, 0] != 0,
            st[:, 1] != 0,
            st[:, 2],
            st[:, 3],
            st[:, 4] != 0,
        )
        if opts.max_state_step < math.inf:
            step = np.max(np.abs(self.X - Xr), axis=(1, 2))
            self.good &= step <= opts.max_state_step
        used = ~trial | self.good  # the linearizations an iteration reads
        for j in np.nonzero(used & ~ok)[0]:  # a singular stage: as CompiledTrial does
            s._ftrial.quad(self.X[j], self.U[j], P[j])  # fills Lam and Phi
            self.PA[j], self.mu[j], ok[j] = s._numpy_backward(float(mu[j]), bs.delta)
            res[j], asum[j] = float(np.max(np.abs(self.PA[j][:, :, -1]))), math.nan
        # C = 1/2 member @ r2 is finite when r2 is and sums far below overflow; the
        # others as SolveOnce.linearize computes them
        for j in np.nonzero(used & ~c_ok)[0]:
            c_ok[j] = bool(np.isfinite(0.5 * (bs.member @ (self.r[j] * self.r[j]))).all())
        finite = ok & np.isfinite(res) & c_ok
        self.res = np.where(finite, res, math.inf)
        # merit RMS(a), with the exactly rounded sum of a*a (as SolveOnce.linearize)
        rows = np.nonzero(finite & used)[0]
        sums = asum[rows]
        redo = np.isnan(sums)
        if redo.any():
            a = self.PA[rows[redo]][..., -1].reshape(int(redo.sum()), -1)
            sums[redo] = _exact_sums(a * a)
        self.merit = np.full(m, math.inf)
        self.merit[rows] = np.sqrt(sums / (K * nu))
        # E = 1/2 |r|^2 per start (row sums equal numpy's sums of the single rows)
        self.E = 0.5 * np.sum(self.r * self.r, axis=1)
