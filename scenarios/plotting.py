"""Figures of games and solves (matplotlib, imported only inside these functions).

Figures are built with :class:`matplotlib.figure.Figure` directly (no ``pyplot``, no
global backend state): saving a PNG renders with Agg whatever backend is active, so
the functions work on headless machines and inside tests. Each function returns the
figure and writes it to ``path`` when one is given.

* :func:`plot_trajectories`: positions of every agent over the horizon, agent circles
  drawn to scale at a few time steps, initial positions, goals and reference paths.
* :func:`plot_modes`: the modes of a multi-modal solve side by side, each with its share.
* :func:`plot_energy_history`: energy per iteration of one or more solves (log scale).

The Jacobian's sparsity is drawn by :func:`scenarios.inspect_plots.plot_inspect_sparsity`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from epo_casadi.errors import SpecError, short_repr
from epo_casadi.game import PotentialGame

__all__ = [
    "plot_trajectories",
    "plot_modes",
    "plot_energy_history",
    "agent_colors",
    "image_formats",
    "check_image_path",
    "save_figure",
]

_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2")


def agent_colors(n: int) -> list[str]:
    """One distinct colour per agent (cycled after eight)."""
    return [_COLORS[i % len(_COLORS)] for i in range(n)]


def _figure(figsize):
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, dpi=110, layout="constrained")


def image_formats() -> list[str]:
    """The file name suffixes (without the dot) of the image formats matplotlib writes."""
    from matplotlib.backend_bases import FigureCanvasBase

    return sorted(FigureCanvasBase.get_supported_filetypes())


def check_image_path(path: str | Path, option: str = "path") -> Path:
    """``path`` as a :class:`Path` if its suffix names an image format matplotlib writes
    (no suffix: PNG); else :class:`SpecError` naming ``option`` and the formats. Commands
    call it on their figure options before any work."""
    path = Path(path)
    fmt = path.suffix.lstrip(".").lower()
    if fmt and fmt not in image_formats():
        raise SpecError(
            option,
            f"unknown image format {short_repr(path.suffix)} ({path.name!s:.80}); expected one "
            f"of {', '.join('.' + f for f in image_formats())}",
        )
    return path


def save_figure(fig, path: str | Path, field: str = "path", **savefig) -> Path:
    """Write ``fig`` to ``path`` atomically in the image format of its suffix (PNG without
    one): an unknown suffix is a :class:`SpecError` naming ``field``; a folder that cannot
    be written (read-only, a full disk) is one :class:`~epo_casadi.errors.OutputError` and
    leaves no partial file. ``savefig`` goes to matplotlib's ``savefig`` (``dpi``, ...)."""
    from scenarios.files import write_atomic

    path = check_image_path(path, field)
    fmt = path.suffix.lstrip(".").lower() or "png"
    write_atomic(path, lambda f: fig.savefig(f, format=fmt, **savefig))
    return path


def _save(fig, path):
    """Write ``fig`` to ``path`` (when given) with :func:`save_figure`; returns ``fig``."""
    if path is not None:
        save_figure(fig, path)
    return fig


#: positions farther than this (metres) from the origin are not drawn
_FAR = 1e9


def _drawable(pts: np.ndarray) -> np.ndarray:
    """``pts`` with NaN where an entry is not finite or beyond ``_FAR`` (a gap in a line)."""
    pts = np.array(pts, dtype=float)
    with np.errstate(invalid="ignore"):
        far = ~(np.abs(pts) <= _FAR)
    pts[np.broadcast_to(far.any(axis=-1, keepdims=True), pts.shape)] = np.nan
    return pts


def _snapshot_steps(K: int, n: int) -> list[int]:
    n = max(2, min(n, K + 1))
    return sorted({int(round(k)) for k in np.linspace(0, K, n)})


def plot_trajectories(
    game: PotentialGame,
    x: np.ndarray,
    p: np.ndarray | None = None,
    path: str | Path | None = None,
    *,
    title: str | None = None,
    snapshots: int = 5,
    others: Mapping[str, np.ndarray] | None = None,
    ax: Any = None,
):
    """Trajectory figure of one joint solution.

    ``x``: rolled-out states ``(n_x,)`` (:mod:`epo_casadi.game` layout); ``p``: the
    parameters used (default: the game's defaults), read for goals and paths. Each agent
    gets a line, a filled marker at its initial position, a star at its goal, its
    reference path dashed, and its circle (true radius) at ``snapshots`` time steps
    evenly spread over ``0..K`` with the step number written inside. ``others`` maps a
    label to another state vector drawn thin and dotted (e.g. a second solver).
    ``ax``: draw into an existing axes instead of a new figure.
    """
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    x = np.asarray(x, dtype=float).reshape(-1)
    if x.size != game.n_x:
        raise SpecError("x", f"expected {game.n_x} states (n_x), got {x.size}")
    p = game.params.defaults() if p is None else np.asarray(p, dtype=float).reshape(-1)
    blocks = game.params.unpack(p)
    # NaN/inf or absurdly far positions (a failed solve) are left out of the frame and not
    # drawn: matplotlib cannot place ticks on a 1e308 m axis
    pos = _drawable(game.positions(x))  # (N, K+1, 2)
    lo, hi = _frame(game, pos, blocks)
    fig = None
    if ax is None:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            aspect = (hi[1] - lo[1]) / (hi[0] - lo[0])
        aspect = float(aspect) if np.isfinite(aspect) and aspect > 0 else 1.0
        fig = _figure((8.0, float(np.clip(6.6 * aspect, 0.9, 7.0)) + 1.1))
        ax = fig.add_subplot(1, 1, 1)
    colors = agent_colors(game.N)
    steps = _snapshot_steps(game.K, snapshots)
    for i in range(game.N):
        _draw_agent(ax, game, i, colors[i], pos, blocks, steps)
    for label, xo in (others or {}).items():
        po = _drawable(game.positions(np.asarray(xo, dtype=float).reshape(-1)))
        for i in range(game.N):
            ax.plot(
                po[i, :, 0],
                po[i, :, 1],
                ls=":",
                lw=1.2,
                color=colors[i],
                zorder=3,
                label=label if i == 0 else None,
            )
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.set_title(
        title
        or f"{game.N} agents, K = {game.K}, dt = {game.dt:g} s "
        f"(o start, * goal, circles at k = {','.join(map(str, steps))})",
        fontsize=9,
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0.0)
    if fig is None:  # drawn into the caller's axes
        return _save(ax.figure, path)
    return _save(fig, path)


def _frame(game: PotentialGame, pos: np.ndarray, blocks: dict) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corner of the drawn area: trajectories and goals, a margin of the
    largest radius (paths may be long and are left out)."""
    pts = [pos.reshape(-1, 2)]
    for a in game.agents:
        if f"goal.{a.name}" in blocks:
            pts.append(blocks[f"goal.{a.name}"][None, :])
        elif a.goal is not None:
            pts.append(np.asarray(a.goal, dtype=float)[None, :])
    allp = _drawable(np.concatenate(pts))
    allp = allp[np.isfinite(allp).all(axis=1)]
    if not allp.size:
        allp = np.zeros((1, 2))
    r = max((a.radius for a in game.agents), default=0.0)
    r = r if r <= _FAR else 0.0
    return allp.min(axis=0) - r - 0.5, allp.max(axis=0) + r + 0.5


def _draw_agent(ax, game: PotentialGame, i: int, c, pos: np.ndarray, blocks: dict, steps) -> None:
    """Agent ``i`` in colour ``c``: its reference path, trajectory, circles at ``steps``
    with the step number, start marker and goal star."""
    from matplotlib.patches import Circle

    a = game.agents[i]
    if f"path.{a.name}" in blocks:
        poly = blocks[f"path.{a.name}"].reshape(-1, 2)
        ax.plot(poly[:, 0], poly[:, 1], ls="--", lw=1.0, color=c, alpha=0.45, zorder=1)
    ax.plot(pos[i, :, 0], pos[i, :, 1], "-", lw=1.8, color=c, zorder=3, label=a.name)
    for k in steps:
        if not np.all(np.isfinite(pos[i, k])) or not a.radius <= _FAR:
            continue
        alpha = 0.15 + 0.35 * k / max(game.K, 1)
        ax.add_patch(
            Circle(
                tuple(pos[i, k]),
                a.radius,
                facecolor=c,
                edgecolor=c,
                alpha=alpha,
                lw=1.0,
                zorder=2,
            )
        )
        if a.radius > 0:
            ax.annotate(
                str(k),
                tuple(pos[i, k]),
                ha="center",
                va="center",
                fontsize=6,
                color="black",
                zorder=4,
            )
    if np.all(np.isfinite(pos[i, 0])):
        ax.plot(*pos[i, 0], "o", ms=7, color=c, markeredgecolor="black", zorder=5)
    if f"goal.{a.name}" in blocks:
        g = blocks[f"goal.{a.name}"]
        ax.plot(g[0], g[1], "*", ms=14, color=c, markeredgecolor="black", zorder=5)
    elif a.goal is not None:
        ax.plot(a.goal[0], a.goal[1], "*", ms=14, color=c, markeredgecolor="black", zorder=5)


def plot_modes(
    game: PotentialGame,
    modes: Sequence[Any],
    p: np.ndarray | None = None,
    path: str | Path | None = None,
    *,
    title: str | None = None,
    max_modes: int = 6,
):
    """The modes of a multi-modal solve (:class:`solvers.multimodal.Mode`), one panel each.

    Panels follow the order of ``modes`` (largest share first), at most ``max_modes`` of
    them; each is a :func:`plot_trajectories` of the mode's medoid, titled with its share,
    energy and number of member solves. No mode (every solve dropped) gives one panel
    that says so.
    """
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    if isinstance(max_modes, bool) or not isinstance(max_modes, int) or max_modes < 1:
        raise SpecError("max_modes", f"expected an integer >= 1, got {max_modes!r}")
    shown = list(modes)[:max_modes]
    n = max(len(shown), 1)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig = _figure((5.2 * cols + 1.2, 4.4 * rows + 0.6))
    axes = [fig.add_subplot(rows, cols, i + 1) for i in range(n)]
    if not shown:
        axes[0].text(0.5, 0.5, "no mode: every solve was dropped", ha="center", va="center")
        axes[0].set_axis_off()
    for m, (ax, mode) in enumerate(zip(axes, shown, strict=False)):
        members = np.size(getattr(mode, "members", ()))
        plot_trajectories(
            game,
            mode.states,
            p,
            ax=ax,
            title=f"mode {m}: share {float(mode.share):.2f}, E = {float(mode.energy):.4g}, "
            f"{members} solves",
        )
    extra = len(modes) - len(shown)
    fig.suptitle(
        (title or f"{len(modes)} modes") + (f" ({extra} more not shown)" if extra > 0 else ""),
        fontsize=10,
    )
    return _save(fig, path)


def plot_energy_history(
    histories: Mapping[str, Sequence[float]] | Sequence[float],
    path: str | Path | None = None,
    *,
    title: str | None = None,
):
    """Energy per iteration (log scale) of one history or a mapping label -> history."""
    if not isinstance(histories, Mapping):
        histories = {"energy": histories}
    fig = _figure((6.0, 3.8))
    ax = fig.add_subplot(1, 1, 1)
    for label, h in histories.items():
        h = np.asarray([np.nan if v is None else v for v in np.ravel(h)], dtype=float)
        h = np.where(np.isfinite(h), np.maximum(h, 1e-300), np.nan)  # NaN/inf: a gap
        ax.plot(np.arange(h.size), h, "-o", ms=2.5, lw=1.4, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("energy E")
    ax.grid(True, which="both", lw=0.4, alpha=0.5)
    ax.set_title(title or "energy history", fontsize=9)
    ax.legend(fontsize=8)
    return _save(fig, path)
