"""Figures of closed-loop episodes (matplotlib, imported only inside these functions).

As in :mod:`scenarios.plotting`, figures are :class:`matplotlib.figure.Figure` objects
rendered with Agg (no ``pyplot``, no global backend), so they work headless and in tests.

* :func:`plot_episode`: the map's lanes, every agent's driven trajectory and, at a few
  instants, the agents (circles to scale) with the planner's predicted joint modes and
  their probabilities; beside it the speeds over time with the fallback steps marked.
* :func:`animate_episode`: the same scene as an animated GIF (one frame per period or
  every few periods), predicted modes drawn at every frame.
* :func:`plot_latency_histogram`: planning latency (ms) of all steps with its p50 / p99 and
  the planning period.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .closed_loop import EpisodeLog
from .plotting import _figure, _save, agent_colors

__all__ = ["plot_episode", "animate_episode", "plot_latency_histogram"]


def _frame(log: EpisodeLog, margin: float = 8.0):
    pos = log.truth[:, :, :2].reshape(-1, 2)
    pos = pos[np.all(np.isfinite(pos), axis=1)]
    if not pos.size:
        pos = np.zeros((1, 2))
    return pos.min(axis=0) - margin, pos.max(axis=0) + margin


def _draw_map(ax, log: EpisodeLog) -> None:
    for c, w in zip(log.lanes, log.lane_widths, strict=True):
        ax.plot(
            c[:, 0],
            c[:, 1],
            "-",
            color="0.82",
            lw=max(1.0, 2.2 * w),
            zorder=0,
            solid_capstyle="butt",
        )
    for c in log.lanes:
        ax.plot(c[:, 0], c[:, 1], "--", color="white", lw=0.6, zorder=0.5)
    if not log.lanes:  # no map: the agents' paths
        for p in log.paths:
            ax.plot(p[:, 0], p[:, 1], "--", color="0.6", lw=0.8, zorder=0.5)


def _draw_instant(ax, log: EpisodeLog, k: int, colors, label_modes: bool = True) -> list:
    from matplotlib.patches import Circle

    artists = []
    x = log.truth[k]
    for i in range(x.shape[0]):
        artists.append(
            ax.add_patch(
                Circle(
                    tuple(x[i, :2]),
                    log.radii[i],
                    facecolor=colors[i],
                    edgecolor="black",
                    alpha=0.35,
                    lw=0.8,
                    zorder=3,
                )
            )
        )
    if k >= len(log.t):
        return artists
    preds, probs = log.predictions[k], log.probabilities[k]  # (M, N, K, 4), (M,)
    for m in range(preds.shape[0]):
        if not np.any(np.isfinite(preds[m])):
            continue
        w = probs[m] if np.isfinite(probs[m]) else np.nan
        lw = 0.8 + 2.2 * (w if np.isfinite(w) else 0.5)
        for i in range(preds.shape[1]):
            pts = np.concatenate([x[i : i + 1, :2], preds[m, i, :, :2]])
            (ln,) = ax.plot(
                pts[:, 0], pts[:, 1], ls=(0, (3, 1.5)), color=colors[i], lw=lw, alpha=0.85, zorder=4
            )
            artists.append(ln)
        if label_modes and np.isfinite(w):
            end = preds[m, 0, -1, :2]
            artists.append(
                ax.annotate(
                    f"m{m} p={w:.2f}",
                    tuple(end),
                    fontsize=6,
                    color=colors[0],
                    zorder=6,
                    xytext=(2, 2),
                    textcoords="offset points",
                )
            )
    if not log.plan_ok[k]:
        artists.append(
            ax.annotate(
                "fallback",
                tuple(x[0, :2]),
                fontsize=7,
                color="red",
                zorder=6,
                xytext=(4, -8),
                textcoords="offset points",
            )
        )
    return artists


def _title(log: EpisodeLog, title: str | None) -> str:
    return title or f"closed loop, {len(log.t)} steps of {log.dt:g} s"


def plot_episode(
    log: EpisodeLog,
    path: str | Path | None = None,
    *,
    instants: int = 4,
    title: str | None = None,
):
    """Episode figure (see the module docstring); returns the figure, saved to ``path``."""
    fig = _figure((11.0, 5.6))
    gs = fig.add_gridspec(1, 2, width_ratios=(2.2, 1.0))
    ax = fig.add_subplot(gs[0, 0])
    colors = agent_colors(log.truth.shape[1])
    _draw_map(ax, log)
    T = len(log.t)
    for i in range(log.truth.shape[1]):
        xy = log.truth[:, i, :2]
        ax.plot(
            xy[:, 0],
            xy[:, 1],
            "-",
            color=colors[i],
            lw=1.6,
            zorder=2,
            label="ego" if i == 0 else f"agent {i}",
        )
        ax.plot(*xy[0], "o", color=colors[i], markeredgecolor="black", ms=6, zorder=5)
    steps = sorted({int(round(s)) for s in np.linspace(0, max(T - 1, 0), max(instants, 1))})
    for k in steps:
        _draw_instant(ax, log, k, colors)
        ax.annotate(
            f"t={log.t[k]:.1f}s" if T else "",
            tuple(log.truth[k, 0, :2]),
            fontsize=6,
            ha="center",
            va="center",
            zorder=7,
        )
    lo, hi = _frame(log)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, lw=0.3, alpha=0.4)
    ax.legend(loc="best", fontsize=7)
    ax.set_title(_title(log, title) + " (dashed: predicted modes, width ~ probability)", fontsize=8)
    sp = fig.add_subplot(gs[0, 1])
    tt = np.arange(log.truth.shape[0]) * log.dt
    for i in range(log.truth.shape[1]):
        sp.plot(
            tt, log.truth[:, i, 2], color=colors[i], lw=1.4, label="ego" if i == 0 else f"agent {i}"
        )
    fb = np.flatnonzero(log.fallback)
    if fb.size:
        sp.plot(log.t[fb], log.truth[fb, 0, 2], "x", color="red", ms=5, label="fallback")
    sp.set_xlabel("t [s]")
    sp.set_ylabel("speed [m/s]")
    sp.grid(True, lw=0.3, alpha=0.5)
    sp.legend(fontsize=7)
    return _save(fig, path)


def animate_episode(
    log: EpisodeLog,
    path: str | Path,
    *,
    every: int = 1,
    fps: int | None = None,
    max_frames: int = 75,
    title: str | None = None,
) -> Path:
    """Write an animated GIF of the episode to ``path`` (Pillow writer); returns the path.

    One frame every ``every`` periods (raised so there are at most ``max_frames``);
    ``fps`` defaults to real time (``1 / (every dt)``)."""
    from matplotlib.animation import FuncAnimation, PillowWriter

    T = log.truth.shape[0]
    every = max(int(every), int(np.ceil(T / max(max_frames, 1))), 1)
    frames = list(range(0, T, every))
    fps = fps or max(1, int(round(1.0 / (every * log.dt))))
    fig = _figure((6.4, 5.4))
    ax = fig.add_subplot(1, 1, 1)
    colors = agent_colors(log.truth.shape[1])
    _draw_map(ax, log)
    lo, hi = _frame(log)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    trails = [ax.plot([], [], "-", color=c, lw=1.4, zorder=2)[0] for c in colors]
    dynamic: list = []

    def draw(k):
        for a in dynamic:
            a.remove()
        dynamic.clear()
        for i, ln in enumerate(trails):
            ln.set_data(log.truth[: k + 1, i, 0], log.truth[: k + 1, i, 1])
        dynamic.extend(_draw_instant(ax, log, k, colors))
        ax.set_title(f"{_title(log, title)}: t = {k * log.dt:.1f} s", fontsize=8)
        return trails + dynamic

    anim = FuncAnimation(fig, draw, frames=frames, blit=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.gif")
    anim.save(tmp, writer=PillowWriter(fps=fps), dpi=80)
    tmp.replace(path)
    return path


def plot_latency_histogram(
    plan_ms: Sequence[float] | np.ndarray,
    dt: float,
    path: str | Path | None = None,
    *,
    title: str | None = None,
):
    """Histogram of planning latencies (ms) with p50, p99 and the period ``dt`` marked."""
    a = np.asarray(plan_ms, dtype=float).reshape(-1)
    a = a[np.isfinite(a)]
    fig = _figure((6.0, 3.6))
    ax = fig.add_subplot(1, 1, 1)
    if a.size:
        hi = max(float(a.max()), dt * 1e3) * 1.05
        ax.hist(a, bins=np.linspace(0.0, hi, 50), color="#1f77b4", alpha=0.8)
        p50, p99 = np.percentile(a, [50, 99])
        ax.axvline(p50, color="black", lw=1.0, ls="--", label=f"p50 {p50:.1f} ms")
        ax.axvline(p99, color="black", lw=1.0, ls=":", label=f"p99 {p99:.1f} ms")
    ax.axvline(dt * 1e3, color="red", lw=1.2, label=f"period {dt * 1e3:.0f} ms")
    ax.set_xlabel("planning time per step [ms]")
    ax.set_ylabel("steps")
    ax.set_title(title or f"planning latency, {a.size} steps", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, lw=0.3, alpha=0.5)
    return _save(fig, path)
