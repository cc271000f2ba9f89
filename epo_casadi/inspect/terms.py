"""The terms of a potential game and where its energy goes: every term with its kind,
agents, feature, weight and steps (:func:`term_rows`, :func:`term_table`), per-term and
per-agent energy at ``(p, u)`` (:func:`energy_breakdown`, :func:`agent_breakdown`,
:func:`breakdown_table`) and each term's value per time step (:func:`term_series`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import SpecError
from ..game import PotentialGame, Term


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


def _eval(game: PotentialGame, name: str, p, u) -> np.ndarray:
    U, P = game.check_inputs(u, p)
    if U.shape[0] != 1:
        raise SpecError("u/p", f"expected one problem, got a batch of {U.shape[0]}")
    return np.asarray(game.function(name)(U[0], P[0]), dtype=float).reshape(-1)


def energy_breakdown(game: PotentialGame, p: np.ndarray, u: np.ndarray) -> list[dict]:
    """Per-term energy at parameters ``p`` and strategy ``u``: the :func:`term_rows` fields
    plus ``energy`` (``1/2 ||r_t||^2``) and ``share`` (``energy / E``; 0 when ``E = 0``)."""
    game = _check_game(game)
    e = _eval(game, "term_energies", p, u)
    total = float(e.sum())
    out = []
    for row, et in zip(term_rows(game), e, strict=True):
        row["energy"] = float(et)
        row["share"] = float(et / total) if total > 0 else 0.0
        out.append(row)
    return out


def agent_breakdown(game: PotentialGame, p: np.ndarray, u: np.ndarray) -> list[dict]:
    """Per-agent cost ``C_i`` at ``(p, u)``, split into ``own`` and ``pair`` energy.

    ``cost`` comes from the game's ``agent_costs`` function, ``own``/``pair`` from
    ``term_energies`` (``cost = own + pair``; pair terms count for both agents).
    """
    game = _check_game(game)
    e = _eval(game, "term_energies", p, u)
    C = _eval(game, "agent_costs", p, u)
    out = []
    for i, a in enumerate(game.agent_names):
        own = sum(float(e[t.index]) for t in game.terms if t.kind == "own" and a in t.agents)
        pair = sum(float(e[t.index]) for t in game.terms if t.kind == "pair" and a in t.agents)
        out.append({"agent": a, "cost": float(C[i]), "own": own, "pair": pair})
    return out


def breakdown_table(
    game: PotentialGame, p: np.ndarray, u: np.ndarray, top: int | None = None
) -> str:
    """Text tables: per-term energy and share (largest first; ``top`` rows if given),
    then per-agent costs."""
    rows = energy_breakdown(game, p=p, u=u)
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
    ab = agent_breakdown(game, p=p, u=u)
    lines += _table(
        ["agent", "C_i", "own", "pair"],
        [[a["agent"], f"{a['cost']:.6g}", f"{a['own']:.6g}", f"{a['pair']:.6g}"] for a in ab],
        [False, True, True, True],
    )
    return "\n".join(lines)


def term_series(game: PotentialGame, p: np.ndarray, u: np.ndarray) -> list[dict]:
    """Each term's value over time at ``(p, u)``: ``index``, ``steps`` (the time steps, a
    list), ``energy`` (per step ``1/2 ||w c_k||^2``; ``None`` when the term's rows do not
    split evenly over its steps), ``active`` (steps with a nonzero value) and ``total``."""
    game = _check_game(game)
    r = _eval(game, "residual", p, u)
    out = []
    for t in game.terms:
        rr = r[t.rows]
        n = len(t.steps)
        if n and rr.size % n == 0:
            e = 0.5 * np.sum(rr.reshape(n, -1) ** 2, axis=1)
            per = [float(v) for v in e]
            active = [int(k) for k, v in zip(t.steps, e, strict=True) if v > 0]
        else:
            per, active = None, [int(k) for k in t.steps] if np.any(rr != 0) else []
        out.append(
            {
                "index": t.index,
                "steps": [int(k) for k in t.steps],
                "energy": per,
                "active": active,
                "total": float(0.5 * rr @ rr),
            }
        )
    return out
