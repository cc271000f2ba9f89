"""Spider (radar) plots of ours' predicted weights per mode, one panel per agent (paper Fig. 3c).

:func:`weight_spider` runs a trained ours run on one sample and draws, for every agent, its
own-feature weights (goal, lane, vref, velocity, ...) and its mean pairwise (collision)
weight as one closed polygon per joint mode, labelled with the mode's probability. The
game's solution does not change when all weights of a mode are scaled together, so each
mode's weights are divided by their geometric mean over the whole scene before plotting,
and the radius is ``log10`` of that ratio: compare shapes and agents, not absolute sizes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from epo_casadi.errors import SpecError

from .evaluate import predict
from .show import load_sample

__all__ = ["spider_weights", "weight_spider"]

MODE_COLORS = ["tab:red", "tab:blue", "tab:orange", "tab:green", "tab:cyan", "tab:pink"]


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


def weight_spider(
    run_dir: str | os.PathLike,
    data_dir: str | os.PathLike,
    index: int,
    out_png: str | os.PathLike,
    split: str = "test",
    checkpoint: str = "best",
) -> Path:
    """Draw the spider plots of ours (``run_dir``) on sample ``index`` of ``split`` to ``out_png``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from .train import load_model

    game, batch = load_sample(data_dir, split, index)
    model, cfg, _ = load_model(run_dir, game, which=checkpoint)
    if cfg.model.kind != "epo":
        raise SpecError("run_dir", f"expected a run of ours (kind 'epo'), got {cfg.model.kind!r}")
    with torch.no_grad():
        _, probs, out = predict(model, batch)
    w, axes = spider_weights(out["params"][0].double().numpy(), game)
    probs = probs[0].numpy()
    M, N, F = w.shape
    ang = np.linspace(0, 2 * np.pi, F, endpoint=False)
    lo, hi = np.nanmin(w) - 0.2, np.nanmax(w) + 0.2
    fig = Figure(figsize=(4.2 * N, 4.8))
    FigureCanvasAgg(fig)
    for i in range(N):
        ax = fig.add_subplot(1, N, i + 1, projection="polar")
        for m in np.argsort(-probs):
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
        ax.set_title(f"{game.agent_names[i]}" + (" (lane changer)" if i == 0 else ""), fontsize=10)
        if i == 0:
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(-0.35, 1.25))
    fig.suptitle(f"weights / geometric mean of the mode's weights, {split}[{index}]", fontsize=10)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=100, bbox_inches="tight")
    return out_png
