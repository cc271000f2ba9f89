"""The structure of a potential game's derivatives: the structural nonzeros of the
Jacobian ``J = dr/du`` (:func:`jacobian_pattern`, :func:`jacobian_sparsity`) and of the
Gauss-Newton Hessian ``J^T J`` (:func:`hessian_pattern`, :func:`hessian_sparsity`), in
total, per term and per agent, and their text pictures (:func:`spy_text`,
:func:`hessian_spy_text`, :data:`SPY_LEGEND`)."""

from __future__ import annotations

import numpy as np

from ..errors import SpecError
from ..game import PotentialGame
from .terms import _check_game

#: What the characters of the text spy pictures mean.
SPY_LEGEND = (
    "legend: each cell is a block of entries; ' ' no structural nonzero, '.' up to 1/3 of "
    "the block's entries, ':' up to 2/3, '#' more"
)


def jacobian_pattern(game: PotentialGame) -> np.ndarray:
    """Boolean ``(n_r, n_u)`` array of the structural nonzeros of ``J = dr/du``."""
    game = _check_game(game)
    sp = game.jacobian_sparsity()
    rows, cols = sp.get_triplet()
    out = np.zeros((game.n_r, game.n_u), dtype=bool)
    out[np.asarray(rows, dtype=int), np.asarray(cols, dtype=int)] = True
    return out


def jacobian_sparsity(game: PotentialGame) -> dict:
    """Structural sparsity of ``J = dr/du``.

    Keys: ``shape`` ``(n_r, n_u)``, ``nnz``, ``density`` (``nnz / (n_r n_u)``),
    ``terms`` (per term: ``index``, ``nnz``), ``agents`` (per agent: ``agent``, ``nnz`` in
    its control columns). Structural means "may be nonzero": a soft bound or collision
    term that is inactive at some ``u`` still counts.
    """
    return _sparsity(_check_game(game))


def _sparsity(game: PotentialGame) -> dict:
    A = _jacobian_csr(game)
    n_r, n_u = A.shape
    nnz = int(A.nnz)
    row_nnz = np.concatenate([[0], np.cumsum(np.diff(A.indptr))])
    col_nnz = np.concatenate([[0], np.cumsum(np.bincount(A.indices, minlength=n_u))])
    return {
        "shape": (n_r, n_u),
        "nnz": nnz,
        "density": nnz / (n_r * n_u) if n_r * n_u else 0.0,
        "terms": [
            {"index": t.index, "nnz": int(row_nnz[t.rows.stop] - row_nnz[t.rows.start])}
            for t in game.terms
        ],
        "agents": [
            {"agent": a, "nnz": int(col_nnz[game.uoff[i + 1]] - col_nnz[game.uoff[i]])}
            for i, a in enumerate(game.agent_names)
        ],
    }


def spy_text(game: PotentialGame, width: int = 60) -> str:
    """A text spy of ``J`` with one line per term and ``width`` column cells.

    Each cell covers a range of controls; its character is the share of nonzeros in
    that (term rows x control columns) block: ``' '`` none, ``.`` up to a third, ``:``
    up to two thirds, ``#`` more. The header marks where each agent's controls start.
    """
    game = _check_game(game)
    if not isinstance(width, int) or width < 4:
        raise SpecError("width", f"expected an integer >= 4, got {width!r}")
    A = _jacobian_csr(game)
    n_u = game.n_u
    width = max(1, min(width, n_u))
    edges = np.linspace(0, n_u, width + 1).round().astype(int)
    labels = [f"{t.index:>3d} {'-'.join(t.agents)}.{t.feature}" for t in game.terms]
    lw = max((len(s) for s in labels), default=0)
    head = [" "] * width
    for i, a in enumerate(game.agent_names):
        c = int(np.searchsorted(edges, game.uoff[i], side="right") - 1)
        txt = "|" + a
        for j, ch in enumerate(txt):
            if c + j < width and (j == 0 or head[c + j] == " "):
                head[c + j] = ch
    lines = [f"{'term':<{lw}} {''.join(head)}"]
    cell_w = np.diff(edges)
    nonempty = cell_w > 0
    for t, lab in zip(game.terms, labels, strict=True):
        # share of nonzeros per (term rows x cell columns) block, one numpy pass per term
        counts = np.zeros(width)
        col = np.asarray(A[t.rows.start : t.rows.stop].sum(axis=0)).ravel()
        counts[nonempty] = np.add.reduceat(col, edges[:-1][nonempty])
        size = t.size * cell_w
        frac = np.divide(counts, size, out=np.zeros(width), where=size > 0)
        cells = [" " if f == 0 else "." if f <= 1 / 3 else ":" if f <= 2 / 3 else "#" for f in frac]
        lines.append(f"{lab:<{lw}} {''.join(cells)}")
    sp = _sparsity(game)
    lines.append(
        f"J = dr/du: {sp['shape'][0]} x {sp['shape'][1]}, {sp['nnz']} structural nonzeros "
        f"(density {sp['density']:.3f}); columns: controls, agent-major then time"
    )
    return "\n".join(lines)


def _jacobian_csr(game: PotentialGame):
    """The pattern of ``J`` as a boolean CSR matrix (kept with the game: many readers)."""

    def build():
        import scipy.sparse as sps

        rows, cols = game.jacobian_sparsity().get_triplet()
        data = np.ones(len(rows), dtype=bool)
        return sps.csr_matrix((data, (rows, cols)), shape=(game.n_r, game.n_u))

    return game.cached(("inspect", "jacobian_csr"), build)


def hessian_pattern(game: PotentialGame):
    """Structural pattern of the Gauss-Newton Hessian ``J^T J`` (``n_u x n_u``), from the
    pattern of ``J``: entry ``(a, b)`` may be nonzero iff some residual row depends on both
    controls ``a`` and ``b``. A ``scipy.sparse`` CSR boolean matrix (50 agents: 15 million
    entries, a few seconds). The exact Hessian adds second derivatives of the residuals,
    which couple only controls that already share a row, so its pattern lies inside this one.
    """
    game = _check_game(game)

    def build():
        A = _jacobian_csr(game)
        H = (A.T @ A).tocsr()
        H.eliminate_zeros()
        return H

    return game.cached(("inspect", "gn_hessian_pattern"), build)


def hessian_sparsity(game: PotentialGame, H=None) -> dict:
    """``shape``, ``nnz``, ``density`` of :func:`hessian_pattern` and ``agent_blocks``: the
    nonzeros of each ``(agent_i, agent_j)`` block (``N x N`` list, row and column order of
    :attr:`PotentialGame.agent_names`)."""
    game = _check_game(game)
    H = hessian_pattern(game) if H is None else H
    n = game.n_u
    coo = H.tocoo()
    ai = np.searchsorted(game.uoff, coo.row, side="right") - 1
    aj = np.searchsorted(game.uoff, coo.col, side="right") - 1
    blocks = np.zeros((game.N, game.N), dtype=np.int64)
    np.add.at(blocks, (ai, aj), 1)
    nnz = int(H.nnz)
    return {
        "kind": "Gauss-Newton J^T J",
        "shape": (n, n),
        "nnz": nnz,
        "density": nnz / (n * n) if n else 0.0,
        "agent_blocks": blocks.tolist(),
    }


def _cell_edges(n: int, width: int) -> np.ndarray:
    width = max(1, min(width, n))
    return np.linspace(0, n, width + 1).round().astype(int)


def hessian_spy_text(game: PotentialGame, width: int = 24, H=None) -> str:
    """A text spy of the Gauss-Newton Hessian pattern (``width x width`` cells; characters
    as in :data:`SPY_LEGEND`); ``|name`` marks where an agent's controls start."""
    game = _check_game(game)
    if not isinstance(width, int) or width < 4:
        raise SpecError("width", f"expected an integer >= 4, got {width!r}")
    H = hessian_pattern(game) if H is None else H
    edges = _cell_edges(game.n_u, width)
    w = len(edges) - 1
    coo = H.tocoo()
    ci = np.searchsorted(edges, coo.row, side="right") - 1
    cj = np.searchsorted(edges, coo.col, side="right") - 1
    counts = np.zeros((w, w))
    np.add.at(counts, (ci, cj), 1)
    sizes = np.outer(np.diff(edges), np.diff(edges))
    frac = np.divide(counts, sizes, out=np.zeros((w, w)), where=sizes > 0)
    starts = {
        int(np.searchsorted(edges, game.uoff[i], side="right") - 1): a
        for i, a in enumerate(game.agent_names)
    }
    head = [" "] * w
    for c, a in starts.items():
        for j, ch in enumerate("|" + a):
            if c + j < w and (j == 0 or head[c + j] == " "):
                head[c + j] = ch
    lw = max((len(a) for a in game.agent_names), default=0) + 1
    lines = [f"{'':<{lw}} {''.join(head)}"]
    for r in range(w):
        lab = ("|" + starts[r]) if r in starts else ""
        cells = "".join(
            " " if f == 0 else "." if f <= 1 / 3 else ":" if f <= 2 / 3 else "#" for f in frac[r]
        )
        lines.append(f"{lab:<{lw}} {cells}")
    return "\n".join(lines)
