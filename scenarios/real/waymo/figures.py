"""Figures of Waymo records: the map, the other tracks and the agents of each scene
(:func:`draw_record`), one PNG per scenario of a dataset (:func:`draw_scenarios`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..waymo_schema import OBJECT_TYPES
from .recipe import WaymoRecipe
from .records import ScenarioRecord
from .scenario import WaymoScenario


def draw_record(rec: ScenarioRecord, pairs: Sequence[tuple[int, ...]], recipe: WaymoRecipe, path):
    """One figure of a record: the map (lane centres, road lines, road edges, crosswalks),
    every other valid track's current position, and the agents of ``pairs`` (track index
    tuples): history solid, future dashed, current position marked. Written to ``path``."""
    from ...plotting import _figure, agent_colors, save_figure

    fig = _figure((8.0, 8.0))
    ax = fig.add_subplot(1, 1, 1)
    style = {
        "lane": {"color": "0.75", "lw": 0.8, "ls": "-"},
        "road_line": {"color": "0.55", "lw": 0.6, "ls": "--"},
        "road_edge": {"color": "0.1", "lw": 1.2, "ls": "-"},
    }
    for m in rec.map:
        xy = m.points[:, :2]
        if m.kind == "crosswalk":
            if len(xy) >= 3:
                ax.fill(*xy.T, color="#cfe3f7", ec="#7aa9d6", lw=0.6, zorder=0)
        elif len(xy) >= 2:
            ax.plot(*xy.T, zorder=1, **style[m.kind])
    grid = recipe.grid(rec.current)
    H = recipe.history
    chosen = list(dict.fromkeys(k for p in pairs for k in p))
    others = [k for k in range(len(rec.track_ids)) if k not in chosen and rec.valid[k, rec.current]]
    if others:
        ax.scatter(
            *rec.states[others, rec.current, :2].T,
            s=6,
            color="0.45",
            zorder=2,
            label="other tracks",
        )
    pts = []
    for c, k in zip(agent_colors(len(chosen)), chosen, strict=True):
        xy = rec.states[k, grid, :2]
        ok = rec.valid[k, grid]
        hist = np.where(ok[: H + 1, None], xy[: H + 1], np.nan)
        fut = np.where(ok[H:, None], xy[H:], np.nan)
        kind = OBJECT_TYPES[int(rec.object_type[k])]
        ax.plot(*hist.T, "-", color=c, lw=2.2, zorder=4)
        ax.plot(*fut.T, "--", color=c, lw=1.4, zorder=4)
        ax.plot(
            *xy[H],
            "o",
            color=c,
            ms=7,
            mec="k",
            zorder=5,
            label=f"track {rec.track_ids[k]} ({kind})",
        )
        pts.append(xy[ok])
    if pts:
        allp = np.concatenate(pts)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        mid, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2 + 20.0, 40.0)
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(
        f"scenario {rec.scenario_id}: history {H * recipe.dt:g} s (solid), future "
        f"{recipe.horizon * recipe.dt:g} s (dashed)",
        fontsize=9,
    )
    ax.legend(loc="upper right", fontsize=7)
    return save_figure(fig, path, "--draw")


def draw_scenarios(scenario: WaymoScenario, folder: str | os.PathLike) -> list[Path]:
    """One PNG per scenario of ``scenario`` (:func:`draw_record`) into ``folder``:
    ``<scenario_id>.png``."""
    from ...files import ensure_dir

    folder = ensure_dir(folder)
    pairs: dict[int, list] = {}
    for u in scenario.units:
        pairs.setdefault(u.scenario, []).append(u.tracks)
    out = []
    for si, prs in sorted(pairs.items()):
        rec = scenario.record(si)
        agents = [scenario.agents_of(rec, p) for p in prs]
        out.append(draw_record(rec, agents, scenario.recipe, folder / f"{rec.scenario_id}.png"))
    return out
