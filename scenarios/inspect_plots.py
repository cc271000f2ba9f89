"""Figures of ``epo inspect`` (matplotlib, imported only inside these functions).

* :func:`plot_inspect_sparsity`: the Jacobian ``J = dr/du`` with every term's rows named
  (or the feature bands named, for many terms) and a legend, beside the Gauss-Newton
  Hessian pattern ``J^T J``.
* :func:`plot_solution_over_time`: with a solution, each term's value ``1/2 ||w c_k||^2``
  over time (one panel per feature, one line per term; active steps marked), then every
  agent's states and controls over time.

Both read :func:`epo_casadi.inspect.inspect_report`'s dict where they can, so the figures
show the numbers the text and ``--json`` show.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from epo_casadi.game import PotentialGame
from scenarios.plotting import _figure, _save, agent_colors

__all__ = ["plot_inspect_sparsity", "plot_solution_over_time"]

#: up to this many terms every row band of the spy image is labelled with its term
MAX_TERM_LABELS = 40
#: states and controls are drawn for the first this many agents
MAX_AGENT_ROWS = 8


def plot_inspect_sparsity(game: PotentialGame, path: str | Path | None = None, *, title=None):
    """Spy images of ``J`` (rows named by term, columns by agent) and of ``J^T J``."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from epo_casadi.inspect import hessian_pattern, jacobian_pattern, jacobian_sparsity

    pat = jacobian_pattern(game)
    H = hessian_pattern(game)
    sp = jacobian_sparsity(game)
    fig = _figure((12.0, 7.0))
    ax, axh = fig.subplots(1, 2, width_ratios=[1.1, 1.0])
    ax.imshow(pat, aspect="auto", cmap="Greys", interpolation="nearest")
    for t in game.terms[1:]:
        ax.axhline(t.rows.start - 0.5, lw=0.3, color="tab:blue", alpha=0.6)
    for off in game.uoff[1:-1]:
        ax.axvline(off - 0.5, lw=0.8, color="tab:red")
        axh.axvline(off - 0.5, lw=0.8, color="tab:red")
        axh.axhline(off - 0.5, lw=0.8, color="tab:red")
    mids = [(game.uoff[i] + game.uoff[i + 1]) / 2 for i in range(game.N)]
    if game.N <= 12:
        ax.set_xticks(mids, game.agent_names, fontsize=7)
    if len(game.terms) <= MAX_TERM_LABELS:
        ticks = [(t.rows.start + t.rows.stop - 1) / 2 for t in game.terms]
        names = [f"{t.index} {'-'.join(t.agents)}.{t.feature}" for t in game.terms]
    else:  # name the bands of consecutive terms with one feature
        ticks, names, start = [], [], 0
        terms = game.terms
        for j in range(1, len(terms) + 1):
            if j == len(terms) or (terms[j].kind, terms[j].feature) != (
                terms[start].kind,
                terms[start].feature,
            ):
                a, b = terms[start], terms[j - 1]
                ticks.append((a.rows.start + b.rows.stop - 1) / 2)
                names.append(f"{a.index}-{b.index} {a.kind} {a.feature}")
                start = j
    ax.set_yticks(ticks, names, fontsize=6 if len(names) > 20 else 7)
    ax.set_xlabel("controls u (agent-major, then time)")
    ax.set_title(
        title
        or f"J = dr/du: {sp['shape'][0]} x {sp['shape'][1]}, nnz {sp['nnz']} "
        f"(density {sp['density']:.3f})",
        fontsize=9,
    )
    axh.spy(H, markersize=0.3 if game.n_u > 200 else 1.0, color="black", aspect="auto")
    if game.N <= 12:
        axh.set_xticks(mids, game.agent_names, fontsize=7)
        axh.set_yticks(mids, game.agent_names, fontsize=7)
    axh.set_title(f"H = J^T J (Gauss-Newton) pattern: nnz {H.nnz}", fontsize=9)
    axh.set_xlabel("controls u")
    axh.set_ylabel("controls u")
    handles = [
        Patch(color="black", label="structural nonzero (may be nonzero)"),
        Patch(facecolor="white", edgecolor="grey", label="always zero"),
        Line2D([], [], color="tab:blue", lw=0.8, label="term boundary (rows)"),
        Line2D([], [], color="tab:red", lw=0.8, label="agent boundary (controls)"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=4, fontsize=8)
    return _save(fig, path)


def plot_solution_over_time(game: PotentialGame, report: dict, path: str | Path | None = None):
    """Each term's value over time (one panel per feature) and every agent's states and
    controls over time, from ``report["solution"]`` of :func:`inspect_report`."""
    sol = report["solution"]
    if sol is None:
        raise ValueError("the report has no solution; inspect with --solve or --result")
    terms = {r["index"]: r for r in report["terms"]}
    feats: dict[tuple[str, str], list[dict]] = {}
    for s in sol["terms"]:
        r = terms[s["index"]]
        feats.setdefault((r["kind"], r["feature"]), []).append(s)
    n_f = len(feats)
    agents = game.agent_names[:MAX_AGENT_ROWS]
    n_rows = -(-n_f // 3) + len(agents)
    fig = _figure((13.0, 2.4 * n_rows))
    gs = fig.add_gridspec(n_rows, 6)
    colors = agent_colors(game.N)
    t_x = np.arange(game.K + 1) * game.dt
    t_u = np.arange(game.K) * game.dt
    for j, ((kind, feat), ss) in enumerate(feats.items()):
        ax = fig.add_subplot(gs[j // 3, 2 * (j % 3) : 2 * (j % 3) + 2])
        many = len(ss) > 8
        for s in ss:
            r = terms[s["index"]]
            if s["energy_per_step"] is None:
                continue
            k = np.asarray(s["steps"])
            e = np.asarray(s["energy_per_step"])
            col = colors[game.agent_names.index(r["agents"][0])] if kind == "own" else None
            style = "o-" if len(k) == 1 or len(k) < game.K // 2 else "-"
            ax.plot(
                k * game.dt,
                e,
                style,
                ms=3,
                lw=0.6 if many else 1.2,
                color=col,
                label=None if many else "-".join(r["agents"]),
            )
            act = np.asarray(s["active_steps"])
            if kind == "pair" and act.size:
                ax.plot(act * game.dt, np.interp(act, k, e), "x", ms=4, color="tab:red")
        ax.set_title(f"{kind} {feat}: 1/2 ||w c_k||^2", fontsize=8)
        ax.set_xlabel("t (s)", fontsize=7)
        ax.tick_params(labelsize=7)
        if not many:
            ax.legend(fontsize=6)
    base = -(-n_f // 3)
    for i, a in enumerate(agents):
        X = np.asarray(sol["states"][a])
        U = np.asarray(sol["controls"][a])
        axx = fig.add_subplot(gs[base + i, 0:3])
        for c, n in enumerate(sol["state_names"][a]):
            axx.plot(t_x, X[:, c], label=n)
        axx.set_title(f"{a}: states", fontsize=8)
        axx.legend(fontsize=6, ncols=4)
        axx.tick_params(labelsize=7)
        axu = fig.add_subplot(gs[base + i, 3:6])
        for c, n in enumerate(sol["control_names"][a]):
            axu.step(t_u, U[:, c], where="post", label=n)
        axu.set_title(f"{a}: controls", fontsize=8)
        axu.legend(fontsize=6, ncols=4)
        axu.tick_params(labelsize=7)
    return _save(fig, path)
