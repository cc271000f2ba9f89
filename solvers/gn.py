"""The dense Gauss-Newton backend and the linearization every backend shares.

A *Gauss-Newton backend* gives :func:`solvers.lm.solve_lm` (and the differentiable layer)
three methods: ``linearize(U, P) -> Linearization``, ``energy(U, P)`` and
``solve(lin, damping, rhs, ellipsoidal)`` for ``(J'J + damping D) x = rhs``.
:class:`DenseGN` is the reference one: ``r`` and ``J`` of the whole batch from mapped
CasADi functions, batched Cholesky solves. The structured backends
(:mod:`solvers.structured`, :mod:`solvers.fast_gn`) fall back to it and return its
:class:`Linearization` from their ``dense()``.

This module sits below :mod:`solvers.lm`, :mod:`solvers.structured` and
:mod:`solvers.fast_gn`, so each of them imports it and none imports another for it.
Shapes follow :mod:`epo_casadi.game`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from epo_casadi.game import PotentialGame

from .batch import BatchFunction

__all__ = ["DenseGN", "Linearization"]


@dataclass
class Linearization:
    """What a backend knows at the current iterate of every problem."""

    r: np.ndarray  # (B, n_r)
    J: np.ndarray  # (B, n_r, n_u) dense Jacobian of r
    energy: np.ndarray  # (B,)
    gradient: np.ndarray  # (B, n_u) = J'r
    JtJ: np.ndarray  # (B, n_u, n_u)


class DenseGN:
    """Dense Gauss-Newton backend: ``r``, ``J`` by mapped CasADi, batched Cholesky solves."""

    def __init__(
        self, game: PotentialGame, threads: int | None = None, functions: dict | None = None
    ):
        self.game = game
        fn = functions or {}
        self.lm_terms = BatchFunction(fn.get("lm_terms") or game.function("lm_terms"), threads)
        self.energy_fn = BatchFunction(fn.get("energy") or game.function("energy"), threads)

    def linearize(self, U: np.ndarray, P: np.ndarray) -> Linearization:
        r, Jnz = self.lm_terms(U, P)
        J = Jnz.reshape(U.shape[0], self.game.n_u, self.game.n_r).transpose(0, 2, 1)
        g = np.einsum("bij,bi->bj", J, r)
        JtJ = np.matmul(J.transpose(0, 2, 1), J)
        return Linearization(r, J, 0.5 * np.einsum("bi,bi->b", r, r), g, JtJ)

    def energy(self, U: np.ndarray, P: np.ndarray) -> np.ndarray:
        return self.energy_fn(U, P)[0][:, 0]

    @staticmethod
    def solve(
        lin: Linearization, damping: np.ndarray, rhs: np.ndarray, ellipsoidal: bool = False
    ) -> np.ndarray:
        """Solve ``(J'J + damping D) x = rhs`` for every problem; ``rhs`` is ``(B, n_u)``."""
        A = lin.JtJ.copy()
        n = A.shape[-1]
        diag = np.einsum("bii->bi", A)
        d = np.where(diag > 1e-12, diag, 1e-12) if ellipsoidal else np.ones_like(diag)
        idx = np.arange(n)
        A[:, idx, idx] += damping[:, None] * d
        try:
            L = np.linalg.cholesky(A)
            y = np.linalg.solve(L, rhs[..., None])
            return np.linalg.solve(L.transpose(0, 2, 1), y)[..., 0]
        except np.linalg.LinAlgError:  # one bad problem must not fail the batch
            out = np.full_like(rhs, np.nan)
            for b in range(A.shape[0]):
                try:
                    out[b] = np.linalg.solve(A[b], rhs[b])
                except np.linalg.LinAlgError:
                    pass  # stays NaN: solve_lm marks the problem NONFINITE
            return out
