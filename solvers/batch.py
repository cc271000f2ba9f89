"""Batched evaluation of CasADi functions on numpy arrays, without Python loops.

:class:`BatchFunction` maps a CasADi function over a batch (``Function.map`` with
threads) and calls it through CasADi's buffer interface, so inputs and outputs are
numpy arrays shared with CasADi (no ``DM`` conversion). Inputs are ``(B, n_in)``
C-contiguous arrays; each output comes back as its nonzeros, ``(B, nnz_out)``;
:meth:`BatchFunction.dense` scatters a sparse output into ``(B, rows, cols)``.

Facts about the CasADi wheel this relies on: ``map(n, 'thread', t)`` needs an
explicit thread count (else one thread per element); the wheel has no OpenMP; CasADi
releases the GIL while it evaluates.
"""

from __future__ import annotations

import os

import casadi as ca
import numpy as np

__all__ = ["BatchFunction", "default_threads"]


def default_threads() -> int:
    """Threads for mapped evaluation: ``EPO_THREADS`` or the number of usable cores."""
    env = os.environ.get("EPO_THREADS")
    if env:
        return max(1, int(env))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


class BatchFunction:
    """Evaluate ``f`` on a batch: ``outs = bf(a0, a1, ...)`` with ``a_i`` of shape ``(B, n_i)``."""

    def __init__(self, f: ca.Function, threads: int | None = None):
        self.f = f
        self.threads = default_threads() if threads is None else max(1, int(threads))
        self._mapped: dict[int, tuple] = {}
        self._triplets: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for i in range(f.n_in()):
            if not f.sparsity_in(i).is_dense():
                raise ValueError(f"{f.name()}: input {f.name_in(i)} must be dense")

    def _get(self, B: int):
        if B not in self._mapped:
            if B == 1:
                m = self.f
            elif self.threads > 1:
                m = self.f.map(B, "thread", min(self.threads, B))
            else:
                m = self.f.map(B, "serial")
            buf, ev = m.buffer()
            self._mapped[B] = (m, buf, ev)
        return self._mapped[B]

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        f = self.f
        if len(args) != f.n_in():
            raise ValueError(f"{f.name()} takes {f.n_in()} inputs, got {len(args)}")
        B = args[0].shape[0]
        ins = []
        for i, a in enumerate(args):
            a = np.ascontiguousarray(a, dtype=np.float64)
            if a.shape != (B, f.nnz_in(i)):
                raise ValueError(
                    f"{f.name()}: input {f.name_in(i)} must have shape ({B}, {f.nnz_in(i)}), got {a.shape}"
                )
            ins.append(a)
        _, buf, ev = self._get(B)
        outs = [np.empty((B, f.nnz_out(i))) for i in range(f.n_out())]
        for i, a in enumerate(ins):
            buf.set_arg(i, memoryview(a))
        for i, o in enumerate(outs):
            buf.set_res(i, memoryview(o))
        ev()
        return outs

    def dense(self, index: int, nz: np.ndarray) -> np.ndarray:
        """Scatter nonzeros ``(B, nnz)`` of output ``index`` into ``(B, rows, cols)``."""
        if index not in self._triplets:
            rows, cols = self.f.sparsity_out(index).get_triplet()
            self._triplets[index] = (np.asarray(rows), np.asarray(cols))
        rows, cols = self._triplets[index]
        sp = self.f.sparsity_out(index)
        out = np.zeros((nz.shape[0], sp.size1(), sp.size2()))
        out[:, rows, cols] = nz
        return out
