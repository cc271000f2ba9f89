"""Joint stage layout of a game's flat vectors (iLQ, the feedback-Nash check).

``to_stages`` maps the flat layout of the problem contract (:mod:`epo_casadi.game`: agent
after agent, stage after stage) to joint stage arrays ``X (..., K+1, nx)`` and
``U (..., K, nu)`` (every agent's states, then controls, at each stage); ``from_stages`` is
its inverse.
"""

from __future__ import annotations

import numpy as np

from epo_casadi.game import PotentialGame

__all__ = ["from_stages", "to_stages"]


def _stage_index(game: PotentialGame):
    """Index arrays: flat x -> (K+1, nx) and flat u -> (K, nu) (read-only, cached on the
    game: every solve converts its start and result)."""
    return game.cached(("ilq_stage_index",), lambda: _make_stage_index(game))


def _make_stage_index(game: PotentialGame):
    K = game.K
    xi = np.concatenate(
        [
            game.xoff[i] + np.arange(K + 1)[:, None] * game.nx[i] + np.arange(game.nx[i])[None]
            for i in range(game.N)
        ],
        axis=1,
    )
    ui = np.concatenate(
        [
            game.uoff[i] + np.arange(K)[:, None] * game.nu[i] + np.arange(game.nu[i])[None]
            for i in range(game.N)
        ],
        axis=1,
    )
    xi, ui = xi.astype(np.intp), ui.astype(np.intp)
    xi.setflags(write=False)
    ui.setflags(write=False)
    return xi, ui


def to_stages(game: PotentialGame, x: np.ndarray | None = None, u: np.ndarray | None = None):
    """Joint stage arrays ``X (..., K+1, nx)`` and ``U (..., K, nu)`` from flat ``x``, ``u``.

    Either argument may be ``None`` (then ``None`` is returned in its place).
    """
    xi, ui = _stage_index(game)
    X = None if x is None else np.asarray(x)[..., xi]
    U = None if u is None else np.asarray(u)[..., ui]
    return X, U


def from_stages(game: PotentialGame, X: np.ndarray | None = None, U: np.ndarray | None = None):
    """Inverse of :func:`to_stages`: flat ``x (..., n_x)`` and ``u (..., n_u)``."""
    xi, ui = _stage_index(game)
    x = u = None
    if X is not None:
        X = np.asarray(X)
        x = np.empty(X.shape[:-2] + (game.n_x,))
        x[..., xi] = X
    if U is not None:
        U = np.asarray(U)
        u = np.empty(U.shape[:-2] + (game.n_u,))
        u[..., ui] = U
    return x, u
