"""Look inside a potential game: its energy terms, where the energy goes, and the
structure of its Jacobian. Text only (no plotting here; see ``scenarios.plotting``).

Everything reads :attr:`PotentialGame.terms` (one entry per residual block, see the
contract in :mod:`epo_casadi.game`) and the named functions ``term_energies``,
``agent_costs`` and ``jacobian``:

* :func:`term_rows` / :func:`term_table`: every term with its kind (own / pair), agents,
  feature, weight parameter and its default value, time steps, residual rows;
* :func:`energy_breakdown` / :func:`agent_breakdown` / :func:`breakdown_table`: per-term
  energy ``e_t = 1/2 ||r_t||^2`` and its share of ``E``, and per-agent costs ``C_i`` split
  into own and pair parts, at a joint strategy ``u`` and parameters ``p``;
* :func:`jacobian_sparsity` / :func:`jacobian_pattern` / :func:`spy_text`: the
  structural nonzeros of ``J = dr/du`` (``n_r x n_u``), in total, per term and per agent,
  and a text picture of which terms touch which agents' controls.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .errors import SpecError
from .game import PotentialGame, Term

__all__ = [
    "format_steps",
    "term_rows",
    "term_table",
    "energy_breakdown",
    "agent_breakdown",
    "breakdown_table",
    "jacobian_pattern",
    "jacobian_sparsity",
    "spy_text",
]


def format_steps(steps: Sequence[int]) -> str:
    """Compact time steps: ``"40"``, ``"1..40"``, ``"5,10,..,40"``, ``"0,3,7"``, ``"-"`` (none)."""
    s = [int(k) for k in steps]
    if not s:
        return "-"
    if len(s) == 1:
        return str(s[0])
    d = s[1] - s[0]
    if d > 0 and all(b - a == d for a, b in zip(s, s[1:], strict=False)):
        if d == 1:
            return f"{s[0]}..{s[-1]}"
        if len(s) == 2:
            return f"{s[0]},{s[1]}"
        return f"{s[0]},{s[1]},..,{s[-1]}"
    if len(s) <= 6:
        return ",".join(map(str, s))
    return ",".join(map(str, s[:3])) + ",..," + ",".join(map(str, s[-2:]))


def _check_game(game) -> PotentialGame:
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    return game


def _label(t: Term) -> str:
    return t.feature if t.feature == t.feature_type else f"{t.feature} ({t.feature_type})"


def term_rows(game: PotentialGame) -> list[dict]:
    """One dict per term: ``index, kind, agents, feature, feature_type, weight,
    weight_default, steps, n_steps, size, rows`` (``rows`` as ``(start, stop)``)."""
    game = _check_game(game)
    defaults = game.params.defaults()
    out = []
    for t in game.terms:
        out.append(
            {
                "index": t.index,
                "kind": t.kind,
                "agents": list(t.agents),
                "feature": t.feature,
                "feature_type": t.feature_type,
                "weight": t.weight,
                "weight_default": float(defaults[game.params[t.weight].start]),
                "steps": format_steps(t.steps),
                "n_steps": len(t.steps),
                "size": t.size,
                "rows": (t.rows.start, t.rows.stop),
            }
        )
    return out


def _table(
    header: Sequence[str], rows: Sequence[Sequence[str]], right: Sequence[bool]
) -> list[str]:
    widths = [
        max(len(h), *(len(r[c]) for r in rows)) if rows else len(h) for c, h in enumerate(header)
    ]

    def line(cells):
        return "  ".join(
            c.rjust(w) if r else c.ljust(w) for c, w, r in zip(cells, widths, right, strict=True)
        ).rstrip()

    return [line(header), line(["-" * w for w in widths]), *(line(r) for r in rows)]


def term_table(game: PotentialGame) -> str:
    """Text table of every energy term (see :func:`term_rows`), with a summary line."""
    rows = term_rows(game)
    header = [
        "#",
        "kind",
        "agents",
        "feature",
        "weight parameter",
        "default",
        "steps",
        "size",
        "rows",
    ]
    right = [True, False, False, False, False, True, False, True, False]
    body = [
        [
            str(r["index"]),
            r["kind"],
            "-".join(r["agents"]),
            r["feature"]
            if r["feature"] == r["feature_type"]
            else f"{r['feature']} ({r['feature_type']})",
            r["weight"],
            f"{r['weight_default']:g}",
            r["steps"],
            str(r["size"]),
            f"{r['rows'][0]}:{r['rows'][1]}",
        ]
        for r in rows
    ]
    g = game
    title = (
        f"{len(rows)} energy terms; N = {g.N} agents, K = {g.K} steps of {g.dt:g} s, "
        f"n_u = {g.n_u} controls, n_p = {g.n_p} parameters, n_r = {g.n_r} residuals"
    )
    return "\n".join([title, *_table(header, body, right)])


def _eval(game: PotentialGame, name: str, u, p) -> np.ndarray:
    U, P = game.check_inputs(u, p)
    if U.shape[0] != 1:
        raise SpecError("u/p", f"expected one problem, got a batch of {U.shape[0]}")
    return np.asarray(game.function(name)(U[0], P[0]), dtype=float).reshape(-1)


def energy_breakdown(game: PotentialGame, u: np.ndarray, p: np.ndarray) -> list[dict]:
    """Per-term energy at ``(u, p)``: the :func:`term_rows` fields plus ``energy``
    (``1/2 ||r_t||^2``) and ``share`` (``energy / E``; 0 when ``E = 0``)."""
    game = _check_game(game)
    e = _eval(game, "term_energies", u, p)
    total = float(e.sum())
    out = []
    for row, et in zip(term_rows(game), e, strict=True):
        row["energy"] = float(et)
        row["share"] = float(et / total) if total > 0 else 0.0
        out.append(row)
    return out


def agent_breakdown(game: PotentialGame, u: np.ndarray, p: np.ndarray) -> list[dict]:
    """Per-agent cost ``C_i`` at ``(u, p)``, split into ``own`` and ``pair`` energy.

    ``cost`` comes from the game's ``agent_costs`` function, ``own``/``pair`` from
    ``term_energies`` (``cost = own + pair``; pair terms count for both agents).
    """
    game = _check_game(game)
    e = _eval(game, "term_energies", u, p)
    C = _eval(game, "agent_costs", u, p)
    out = []
    for i, a in enumerate(game.agent_names):
        own = sum(float(e[t.index]) for t in game.terms if t.kind == "own" and a in t.agents)
        pair = sum(float(e[t.index]) for t in game.terms if t.kind == "pair" and a in t.agents)
        out.append({"agent": a, "cost": float(C[i]), "own": own, "pair": pair})
    return out


def breakdown_table(
    game: PotentialGame, u: np.ndarray, p: np.ndarray, top: int | None = None
) -> str:
    """Text tables: per-term energy and share (largest first; ``top`` rows if given),
    then per-agent costs."""
    rows = energy_breakdown(game, u, p)
    total = sum(r["energy"] for r in rows)
    order = sorted(rows, key=lambda r: -r["energy"])
    shown = order if top is None else order[:top]
    body = [
        [
            str(r["index"]),
            r["kind"],
            "-".join(r["agents"]),
            r["feature"]
            if r["feature"] == r["feature_type"]
            else f"{r['feature']} ({r['feature_type']})",
            f"{r['energy']:.6g}",
            f"{100 * r['share']:.1f}%",
        ]
        for r in shown
    ]
    lines = [f"energy E = {total:.6g} (sum of {len(rows)} terms, largest first)"]
    lines += _table(
        ["#", "kind", "agents", "feature", "energy", "share"],
        body,
        [True, False, False, False, True, True],
    )
    if len(shown) < len(rows):
        rest = sum(r["energy"] for r in order[len(shown) :])
        lines.append(f"... {len(rows) - len(shown)} more terms with {rest:.6g} in total")
    lines.append("")
    lines.append("agent costs C_i = own + pair (pair terms count for both agents)")
    ab = agent_breakdown(game, u, p)
    lines += _table(
        ["agent", "C_i", "own", "pair"],
        [[a["agent"], f"{a['cost']:.6g}", f"{a['own']:.6g}", f"{a['pair']:.6g}"] for a in ab],
        [False, True, True, True],
    )
    return "\n".join(lines)


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
    return _sparsity(game, jacobian_pattern(game))


def _sparsity(game: PotentialGame, pat: np.ndarray) -> dict:
    n_r, n_u = pat.shape
    nnz = int(pat.sum())
    return {
        "shape": (n_r, n_u),
        "nnz": nnz,
        "density": nnz / (n_r * n_u) if n_r * n_u else 0.0,
        "terms": [{"index": t.index, "nnz": int(pat[t.rows].sum())} for t in game.terms],
        "agents": [
            {"agent": a, "nnz": int(pat[:, game.uoff[i] : game.uoff[i + 1]].sum())}
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
    pat = jacobian_pattern(game)
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
        col = pat[t.rows].sum(axis=0)
        counts[nonempty] = np.add.reduceat(col, edges[:-1][nonempty])
        size = t.size * cell_w
        frac = np.divide(counts, size, out=np.zeros(width), where=size > 0)
        cells = [" " if f == 0 else "." if f <= 1 / 3 else ":" if f <= 2 / 3 else "#" for f in frac]
        lines.append(f"{lab:<{lw}} {''.join(cells)}")
    sp = _sparsity(game, pat)
    lines.append(
        f"J = dr/du: {sp['shape'][0]} x {sp['shape'][1]}, {sp['nnz']} structural nonzeros "
        f"(density {sp['density']:.3f}); columns: controls, agent-major then time"
    )
    return "\n".join(lines)
