"""The whole inspection of a game: :func:`inspect_report`, one JSON-ready dict (schema
``epo-inspect/1``: the energy convention, sizes, dynamics, parameters
(:func:`param_summary`), terms with formulas, sparsity and, with a solution, its energy),
and :func:`report_text`, the text of ``epo inspect`` made from it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..game import PotentialGame
from .formulas import dynamics_summary, term_formula
from .sparsity import SPY_LEGEND, hessian_sparsity, hessian_spy_text, jacobian_sparsity, spy_text
from .terms import _check_game, _eval, _table, agent_breakdown, format_steps, term_rows, term_series

#: The energy convention, stated once by every report.
ENERGY_CONVENTION = (
    "E(u, p) = 1/2 sum_t ||w_t c_t(u, p)||^2 = 1/2 ||r(u, p)||^2: each term t is its weight "
    "parameter w_t times its residual c_t, so the weight enters squared (doubling w_t "
    "multiplies the term's energy by 4)"
)

REPORT_FORMAT = "epo-inspect/1"


def game_sizes(game: PotentialGame) -> dict:
    """The sizes of ``game`` as JSON facts: ``N``, ``K``, ``dt``, ``n_u``, ``n_x``, ``n_p``,
    ``n_r`` (the ``sizes`` of the inspect report and of an export's manifest)."""
    return {
        "N": game.N,
        "K": game.K,
        "dt": game.dt,
        "n_u": game.n_u,
        "n_x": game.n_x,
        "n_p": game.n_p,
        "n_r": game.n_r,
    }


def param_summary(game: PotentialGame, p: np.ndarray | None = None) -> list[dict]:
    """Every block of the parameter vector: ``name, group, start, size, entries, values``
    (at ``p``; the defaults when ``p`` is None) and ``default``."""
    game = _check_game(game)
    P = game.params.defaults() if p is None else game.check_inputs(game.zero_controls(), p)[1][0]
    return [
        {
            "name": b.name,
            "group": b.group,
            "start": b.start,
            "size": b.size,
            "entries": list(b.entries),
            "values": [float(v) for v in P[b.slice]],
            "default": [float(v) for v in b.default],
        }
        for b in game.params.blocks
    ]


def _finite(v):
    return float(v) if np.isfinite(v) else None


def inspect_report(
    game: PotentialGame,
    p: np.ndarray | None = None,
    u: np.ndarray | None = None,
    *,
    source: str | None = None,
    hessian: bool = True,
) -> dict:
    """Everything :func:`report_text` prints, as one JSON-ready dict (schema
    ``epo-inspect/1``, documented in docs/gamefiles.md): the energy convention, sizes,
    dynamics, parameters (values at ``p``), terms with formulas, Jacobian and (``hessian``)
    Gauss-Newton Hessian sparsity, and with a solution ``u`` its energy per term, agent
    costs, each term's value over time, states and controls per agent."""
    game = _check_game(game)
    p = game.params.defaults() if p is None else np.asarray(p, dtype=float).reshape(-1)
    pv = param_summary(game, p)
    rows = term_rows(game)
    for row, t in zip(rows, game.terms, strict=True):
        row["weight_value"] = float(p[game.params[t.weight].start])
        row["step_list"] = [int(k) for k in t.steps]
        row["rows"] = list(row["rows"])
        row.update({k: v for k, v in term_formula(game, t).items() if k != "steps"})
    jac = jacobian_sparsity(game)
    jac["shape"] = list(jac["shape"])
    rep: dict = {
        "format": REPORT_FORMAT,
        "energy_convention": ENERGY_CONVENTION,
        "sizes": {**game_sizes(game), "terms": len(game.terms)},
        "agents": list(game.agent_names),
        "dynamics": dynamics_summary(game),
        "params": pv,
        "terms": rows,
        "jacobian": jac,
        "hessian": None,
        "solution": None,
    }
    if source is not None:
        rep["game"] = source
    if hessian:
        hs = hessian_sparsity(game)
        hs["shape"] = list(hs["shape"])
        rep["hessian"] = hs
    if u is not None:
        U, _ = game.check_inputs(u, p)
        u = U[0]
        e = _eval(game, "term_energies", p, u)
        total = float(e.sum())
        series = term_series(game, p=p, u=u)
        x = _eval(game, "rollout", p, u)
        X, Uc = game.split_states(x), game.split_controls(u)
        rep["solution"] = {
            "energy": _finite(total),
            "terms": [
                {
                    "index": s["index"],
                    "energy": _finite(et),
                    "share": float(et / total) if total > 0 else 0.0,
                    "steps": s["steps"],
                    "energy_per_step": s["energy"],
                    "active_steps": s["active"],
                }
                for s, et in zip(series, e, strict=True)
            ],
            "agent_costs": agent_breakdown(game, p=p, u=u),
            "states": {a: X[i].tolist() for i, a in enumerate(game.agent_names)},
            "controls": {a: Uc[i].tolist() for i, a in enumerate(game.agent_names)},
            "state_names": {a.name: list(a.dynamics.state_names) for a in game.agents},
            "control_names": {a.name: list(a.dynamics.control_names) for a in game.agents},
        }
    return rep


def _fmt_values(v: Sequence[float], limit: int = 8) -> str:
    s = [f"{x:.6g}" for x in v]
    if len(s) > limit:
        s = s[: limit - 2] + ["..."] + s[-1:]
    return s[0] if len(v) == 1 else "[" + ", ".join(s) + "]"


def report_text(game: PotentialGame, rep: dict, *, spy: bool = True, top: int | None = None) -> str:
    """The text of ``epo inspect`` from :func:`inspect_report`'s dict (same numbers)."""
    game = _check_game(game)
    sz = rep["sizes"]
    L = [
        f"{sz['terms']} energy terms; N = {sz['N']} agents, K = {sz['K']} steps of "
        f"{sz['dt']:g} s, n_u = {sz['n_u']} controls, n_p = {sz['n_p']} parameters, "
        f"n_r = {sz['n_r']} residuals",
        f"energy: {rep['energy_convention']}",
        "",
        "dynamics (x_{k+1} = f(x_k, u_k, dt), states and controls per agent in this order):",
    ]
    for g in rep["dynamics"]:
        ag = g["agents"]
        who = ", ".join(ag) if len(ag) <= 6 else f"{ag[0]}, ..., {ag[-1]} ({len(ag)} agents)"
        joint = " (coupled: one joint model steps these agents)" if g.get("coupled") else ""
        L.append(
            f"  {g['model']} [{who}]{joint}: states ({', '.join(g['states'])}), controls "
            f"({', '.join(g['controls'])}), integrator {g['integrator']}, dt = {g['dt']:g} s"
        )
        for s, e in g["update"].items():
            L.append(f"    {s}+ = {e}")
    L += ["", f"parameters p ({sz['n_p']} entries; value at p, and the default where it differs):"]
    L += _table(
        ["block", "group", "entries", "value"],
        [
            [
                b["name"],
                b["group"],
                f"{b['start']}:{b['start'] + b['size']}",
                _fmt_values(b["values"])
                + (
                    "" if b["values"] == b["default"] else f" (default {_fmt_values(b['default'])})"
                ),
            ]
            for b in rep["params"]
        ],
        [False, False, False, False],
    )
    L += ["", "terms (weight at p; r rows; formula of the weighted residual w * c, k over steps):"]
    body = [
        [
            str(r["index"]),
            r["kind"],
            "-".join(r["agents"]),
            _label_row(r),
            r["weight"],
            f"{r['weight_value']:g}",
            r["steps"],
            str(r["size"]),
            f"{r['rows'][0]}:{r['rows'][1]}",
        ]
        for r in rep["terms"]
    ]
    L += _table(
        ["#", "kind", "agents", "feature", "weight parameter", "value", "steps", "size", "rows"],
        body,
        [True, False, False, False, False, True, False, True, False],
    )
    L += ["", "formulas:"]
    for r in _distinct_formulas(rep["terms"]):
        L.append(f"  {r['index']:>3} {r['formula']}   ({r['steps_k']}{r['note']})")
    sol = rep["solution"]
    if sol is not None:
        L += ["", _solution_text(rep, top)]
    L.append("")
    jac = rep["jacobian"]
    if spy:
        L.append(spy_text(game))
        L.append(
            SPY_LEGEND + "; rows: terms (index agents.feature); columns: controls, "
            "'|name' where an agent's controls start"
        )
    else:
        L.append(
            f"J = dr/du: {jac['shape'][0]} x {jac['shape'][1]}, {jac['nnz']} structural nonzeros "
            f"(density {jac['density']:.3f})"
        )
    hs = rep["hessian"]
    if hs is not None:
        L.append("")
        L.append(
            f"H = J^T J (Gauss-Newton Hessian pattern): {hs['shape'][0]} x {hs['shape'][1]}, "
            f"{hs['nnz']} structural nonzeros (density {hs['density']:.3f}); blocks "
            "coupling two agents come from pair terms only"
        )
        if spy:
            L.append(hessian_spy_text(game))
            L.append(SPY_LEGEND + "; rows and columns: controls")
    return "\n".join(L)


def _label_row(r: dict) -> str:
    return (
        r["feature"]
        if r["feature"] == r["feature_type"]
        else f"{r['feature']} ({r['feature_type']})"
    )


def _distinct_formulas(terms: list[dict]) -> list[dict]:
    """One line per term, but pair terms with one formula up to the agents' names once."""
    out, seen = [], {}
    for r in terms:
        if r["kind"] == "pair":
            a, b = r["agents"]
            key = (r["feature"], r["residual"].replace(f"{a}.", "A.").replace(f"{b}.", "B."))
            if key in seen:
                seen[key]["n"] += 1
                continue
        d = {
            "index": r["index"],
            "formula": r["formula"],
            "steps_k": f"k = {r['steps']}",
            "note": "" if r["source"] == "formula()" else f"; residual {r['source']}",
            "n": 1,
        }
        out.append(d)
        if r["kind"] == "pair":
            seen[key] = d
    for d in out:
        if d["n"] > 1:
            d["note"] += f"; the same for {d['n'] - 1} more pairs"
    return out


def _solution_text(rep: dict, top: int | None) -> str:
    sol = rep["solution"]
    terms = {r["index"]: r for r in rep["terms"]}
    E = sol["energy"]
    rows = sorted(sol["terms"], key=lambda s: -(s["energy"] or 0.0))
    shown = rows if top is None else rows[:top]
    L = [
        f"energy E = {E:.6g} (sum of {len(rows)} terms, largest first)"
        if E is not None
        else "energy E = none (non-finite)"
    ]
    body = []
    for s in shown:
        r = terms[s["index"]]
        per = s["energy_per_step"]
        if per:
            kmax = s["steps"][int(np.argmax(per))]
            peak = f"{max(per):.6g} at k = {kmax}"
        else:
            peak = "-"
        body.append(
            [
                str(s["index"]),
                r["kind"],
                "-".join(r["agents"]),
                _label_row(r),
                "none" if s["energy"] is None else f"{s['energy']:.6g}",
                f"{100 * s['share']:.1f}%",
                format_steps(s["active_steps"]),
                peak,
            ]
        )
    L += _table(
        ["#", "kind", "agents", "feature", "energy", "share", "active steps", "peak"],
        body,
        [True, False, False, False, True, True, False, False],
    )
    if len(shown) < len(rows):
        rest = sum(s["energy"] or 0.0 for s in rows[len(shown) :])
        L.append(f"... {len(rows) - len(shown)} more terms with {rest:.6g} in total")
    L += ["", "agent costs C_i = own + pair (pair terms count for both agents)"]
    L += _table(
        ["agent", "C_i", "own", "pair"],
        [
            [a["agent"], f"{a['cost']:.6g}", f"{a['own']:.6g}", f"{a['pair']:.6g}"]
            for a in sol["agent_costs"]
        ],
        [False, True, True, True],
    )
    return "\n".join(L)
