"""Spider (radar) plots of ours' predicted weights per mode, one panel per agent (as the spider plots of the paper, App. G.1).

:func:`weight_spider` runs a trained ours run on one sample and draws, for every agent, its
own-feature weights (goal, lane, vref, velocity, ...) and its mean pairwise (collision)
weight as one closed polygon per joint mode, labelled with the mode's probability. The
game's solution does not change when all weights of a mode are scaled together, so each
mode's weights are divided by their geometric mean over the whole scene before plotting,
and the radius is ``log10`` of that ratio: compare shapes and agents, not absolute sizes.
An agent's panel is titled "(lane changer)" when the sample's ``lane_change`` field (exiD
layout) flags it. ``epo show-weights`` is the command line of :func:`weight_spider`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from epo_casadi.errors import SpecError

from .evaluate import predict
from .show import MODE_COLORS, load_sample

__all__ = ["SpiderPlot", "agent_titles", "spider_weights", "weight_spider"]

#: radius of the smallest drawn weight: a polygon never touches the centre
MARGIN = 0.2


@dataclass(frozen=True)
class SpiderPlot:
    """What :func:`weight_spider` drew (``return_data=True``).

    ``weights[m, i, f]`` is :func:`spider_weights` of the sample's predicted parameters
    (mode ``m``, agent ``i``, axis ``axes[f]``); the radius drawn is ``weights - offset``.
    ``probs`` ``(M,)`` are the modes' scene probabilities (the legend's ``p``), ``titles`` the
    panel titles per agent, ``figure`` the matplotlib Figure written to ``path``.
    """

    path: Path
    weights: np.ndarray
    axes: list[str]
    probs: np.ndarray
    offset: float
    titles: list[str]
    figure: Any


def spider_weights(params: np.ndarray, game) -> tuple[np.ndarray, list[str]]:
    """``(M, N, F + 1)`` log10 weights normalized per mode, and the F + 1 axis names.

    ``params`` ``(M, n_p)`` one sample's game parameters; axes: the agent's own features in
    the game's order, then ``collision`` (the mean of the pairwise weights that involve the
    agent). Each mode is divided by the geometric mean of all its (own and pairwise) weights.
    """
    names = list(game.params.names)
    own, pair = list(game.params.group("w_own")), list(game.params.group("w_pair"))
    agents = list(game.agent_names)
    feats = [
        names[j][len(f"w.{agents[0]}.") :] for j in own if names[j].startswith(f"w.{agents[0]}.")
    ]
    M, N = params.shape[0], len(agents)
    w = np.empty((M, N, len(feats) + 1))
    for i, a in enumerate(agents):
        idx = [names.index(f"w.{a}.{f}") for f in feats]
        w[:, i, :-1] = params[:, idx]
        mine = [j for j in pair if a in names[j][2:].rsplit(".", 1)[0].split("-")]
        w[:, i, -1] = params[:, mine].mean(-1) if mine else np.nan
    allw = params[:, own + pair]
    gmean = np.exp(np.log(np.clip(allw, 1e-12, None)).mean(-1))  # (M,)
    return np.log10(np.clip(w, 1e-12, None) / gmean[:, None, None]), feats + ["collision"]


def agent_titles(sample: dict, agents: list[str]) -> list[str]:
    """Panel titles: the agent names, with " (lane changer)" for every agent the sample's
    ``lane_change`` field ``(N,)`` flags; no label when the dataset has no such field."""
    flags = np.zeros(len(agents), bool)
    if "lane_change" in sample:
        lc = np.asarray(sample["lane_change"]).reshape(-1).astype(bool)
        if lc.shape != flags.shape:
            raise SpecError(
                "lane_change", f"expected one flag per agent ({len(agents)}), got {lc.shape}"
            )
        flags = lc
    return [f"{a} (lane changer)" if f else str(a) for a, f in zip(agents, flags, strict=True)]


def weight_spider(
    run_dir: str | os.PathLike,
    data_dir: str | os.PathLike,
    index: int,
    out_png: str | os.PathLike,
    split: str = "test",
    checkpoint: str = "best",
    *,
    return_data: bool = False,
) -> Path | SpiderPlot:
    """Draw the spider plots of ours (``run_dir``) on sample ``index`` of ``split`` to ``out_png``.

    Returns the path written, or with ``return_data=True`` a :class:`SpiderPlot` (the plotted
    weights, offset, probabilities, titles and the Figure). Input errors as ``epo
    show-predictions`` (:func:`learning.show.load_sample`, :func:`learning.train.load_model`);
    a run that is not ours is refused with :class:`SpecError` naming ``run_dir``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from scenarios.plotting import save_figure

    from .train import load_model

    game, batch, raw, agents = load_sample(data_dir, split, index)
    titles = agent_titles(raw, agents)
    model, cfg, _ = load_model(run_dir, game, which=checkpoint)
    if cfg.model.kind != "epo":
        raise SpecError(
            "run_dir",
            f"expected a run of ours (kind 'epo'), got kind {cfg.model.kind!r} in {run_dir}",
        )
    with torch.no_grad():
        _, probs, out = predict(model, batch)
    w, axes = spider_weights(out["params"][0].double().numpy(), game)
    probs = probs[0].double().numpy()
    M, N, F = w.shape
    ang = np.linspace(0, 2 * np.pi, F, endpoint=False)
    lo, hi = np.nanmin(w) - MARGIN, np.nanmax(w) + MARGIN
    fig = Figure(figsize=(4.2 * N, 4.8))
    FigureCanvasAgg(fig)
    for i in range(N):
        ax = fig.add_subplot(1, N, i + 1, projection="polar")
        for m in np.argsort(-probs, kind="stable"):
            r = np.r_[w[m, i], w[m, i, :1]] - lo
            ax.plot(
                np.r_[ang, ang[:1]],
                r,
                "-",
                color=MODE_COLORS[m % len(MODE_COLORS)],
                lw=1.8,
                label=f"mode {m} (p={probs[m]:.2f})",
            )
        ax.set_xticks(ang)
        ax.set_xticklabels([a.replace("_", "\n") for a in axes], fontsize=7)
        ticks = np.arange(np.ceil(lo), np.floor(hi) + 1)
        ax.set_yticks(ticks - lo)
        ax.set_yticklabels([f"1e{int(t)}" for t in ticks], fontsize=6)
        ax.set_ylim(0, hi - lo)
        ax.set_title(titles[i], fontsize=10)
        if i == 0:
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(-0.35, 1.25))
    fig.suptitle(f"weights / geometric mean of the mode's weights, {split}[{index}]", fontsize=10)
    out_png = Path(out_png)
    save_figure(fig, out_png, "out", dpi=100, bbox_inches="tight")  # format from the suffix
    if not return_data:
        return out_png
    return SpiderPlot(out_png, w, axes, probs, float(lo), titles, fig)
