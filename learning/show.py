"""The interpretability view (paper App., "Discussion of Interpretability"): one sample, predictions, weights.

:func:`show_predictions` draws, for one sample of a split, the observed history, the
ground truth, the dataset's other modes (thin grey), and every predicted joint mode with
its probability and its scene error (SADE to the ground truth). For ours it adds, per
agent and mode, the predicted weights of the agent's own energy features and the
pairwise (collision) weight as bars (log scale), with the weights of the game that
generated the sample as black markers. The game's solution is invariant to a common
scale of all weights, so compare ratios between features, not absolute heights.
Padded agents (the sample's ``agents_mask`` False) are not drawn: no history, truth,
prediction, goal or weight panel, and the view fits the real agents only.

Recorded data (a dataset with the ``origin`` field: the readers of :mod:`scenarios.real`)
is drawn over the real scene (:func:`_draw_recorded`): in the recording's world frame
(``frame="world"``, the origin added back; ``"scene"``: the sample's frame), the lane map
where the sample has ``lanes`` (Waymo; empty slots of ``lanes_mask`` left out), the other
recorded agents of the figure-only field ``others`` in grey (observed part solid, future
dotted; ETH/UCY, CITR), each real agent's history solid and its truth dashed, and every
predicted joint mode coloured by its probability (a colour bar; the most likely mode
thickest and named in the legend, with its decoded goals for ours). Ours' weight panels
then show the five most likely modes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from epo_casadi.errors import SpecError
from scenarios.dataset import SplitReader, check_index, read_manifest

from .baselines import ConstantVelocity
from .data import SceneDataset
from .evaluate import method_label, predict
from .metrics import marginal_to_joint

__all__ = ["show_predictions"]

AGENT_COLORS = ["black", "tab:purple", "tab:brown", "tab:olive"]
MODE_COLORS = ["tab:red", "tab:blue", "tab:orange", "tab:green", "tab:cyan", "tab:pink"]


def load_sample(data_dir: str | os.PathLike, split: str, index: int) -> tuple:
    """``(game, batch, raw, agents)`` of sample ``index`` of ``split``: the dataset's game,
    the sample as a batch of one, its stored fields as written (e.g. ``lane_change``) and the
    agents' display names (the manifest's ``meta.agents``, else the game's). A non-integer
    ``index`` is refused with :class:`SpecError`. Shared by the one-sample figures."""
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
        raise SpecError("index", f"expected an integer, got {index!r}")
    with SceneDataset(data_dir, split) as data:
        index = check_index(index, len(data), split)  # any size of integer: one line
        game, batch = data.game, data.batch([index])
    with SplitReader(data_dir, split) as r:
        raw = r[int(index)]
        agents = list(r.manifest.get("meta", {}).get("agents") or game.agent_names)
    return game, batch, raw, agents


def _model_of(run_dir, game, n_modes: int, checkpoint: str):
    """``(model, label, kind)``: a run's model, or the constant-velocity baseline (``"cv"``)."""
    if str(run_dir) == "cv" and not Path(run_dir).is_dir():
        return ConstantVelocity(game.K, n_modes), "CV", "cv"
    from .train import load_model

    model, cfg, _ = load_model(run_dir, game, which=checkpoint)
    return model, method_label(cfg.model, cfg), cfg.model.kind


def _real_agents(batch) -> np.ndarray:
    """Indices of the sample's real agents (``agents_mask`` True; every agent without it)."""
    N = batch["history"].shape[2]
    if "agents_mask" not in batch:
        return np.arange(N)
    return np.flatnonzero(batch["agents_mask"][0].numpy())


def _draw_scene(ax, game, batch, raw, agents, gt) -> None:
    """Lanes, histories, agent discs and given goals, the other dataset modes, the truth
    (real agents only)."""
    from matplotlib.patches import Circle

    hist = batch["history"][0].numpy()  # (H+1, N, 4)
    hvalid = batch["history_valid"][0].numpy()
    real = _real_agents(batch)
    # ---- map (scenes with lanes, e.g. exiD-format): lane polylines in light grey
    if "lanes" in batch:
        lanes = batch["lanes"][0].numpy()
        lmask = batch["lanes_mask"][0].numpy() if "lanes_mask" in batch else None
        keep = np.arange(len(lanes)) if lmask is None else np.flatnonzero(lmask)
        for n, k in enumerate(keep):
            ax.plot(*lanes[k].T, "-", color="0.88", lw=5, zorder=0, label=None if n else "lanes")
    # ---- trajectories
    for i in real:
        c = AGENT_COLORS[i % len(AGENT_COLORS)]
        ax.plot(hist[~hvalid, i, 0], hist[~hvalid, i, 1], ":", color=c, alpha=0.3)
        ax.plot(
            hist[hvalid, i, 0], hist[hvalid, i, 1], ":", color=c, lw=2, label=f"{agents[i]} history"
        )
        ax.add_patch(Circle(hist[-1, i, :2], game.agents[i].radius, fc="none", ec=c, lw=1.5))
        if "goals" in batch:
            ax.plot(
                *batch["goals"][0, i].numpy(),
                "*",
                color=c,
                ms=15,
                mec="white",
                label=f"{agents[i]} goal",
            )
    fut, valid = raw["future"], raw.get("mode_valid", np.ones(raw["future"].shape[0], bool))
    gt_mode = int(raw["gt_mode"]) if "gt_mode" in raw else 0
    for m in range(fut.shape[0]):
        if m == gt_mode or not valid[m]:
            continue
        for n, i in enumerate(real):
            xy = np.concatenate([hist[-1:, i, :2], fut[m, i, :, :2]])
            ax.plot(
                xy[:, 0],
                xy[:, 1],
                "-",
                color="0.6",
                lw=1,
                label="other dataset mode" if n == 0 and m == (1 if gt_mode == 0 else 0) else None,
            )
    for n, i in enumerate(real):
        xy = np.concatenate([hist[-1:, i, :2], gt[i]])
        ax.plot(
            xy[:, 0], xy[:, 1], "--", color="0.15", lw=2.5, label="ground truth" if n == 0 else None
        )


def _draw_modes(ax, out, pos, probs, hist, gt, real):
    """A goal decoder's goals and the predicted modes, most likely first, of the agents
    ``real``; returns their decoded goals ``(M, len(real), 2)`` or None."""
    M = pos.shape[0]
    decoded = None
    if isinstance(out, dict) and out.get("decoded_goals", False):  # a goal decoder's goals
        decoded = out["goals"][0].detach().numpy()[:, real]  # (M, n_real, 2)
        for m in range(M):
            ax.plot(
                decoded[m, :, 0],
                decoded[m, :, 1],
                "P",
                color=MODE_COLORS[m % len(MODE_COLORS)],
                ms=11,
                mec="k",
                label=f"mode {m} decoded goals",
            )
    order = np.argsort(-probs)
    for rank, m in enumerate(order):
        c = MODE_COLORS[m % len(MODE_COLORS)]
        sade = float(np.linalg.norm(pos[m, real] - gt[real], axis=-1).mean())
        for n, i in enumerate(real):
            xy = np.concatenate([hist[-1:, i, :2], pos[m, i]])
            ax.plot(
                xy[:, 0],
                xy[:, 1],
                "-",
                color=c,
                lw=2.5 if rank == 0 else 1.6,
                alpha=0.9,
                marker="os^v"[i % 4],
                markevery=[len(xy) - 1],
                ms=6,
                label=f"mode {m}: p={probs[m]:.2f}, SADE {sade:.2f} m" if n == 0 else None,
            )
    return decoded


def _fit_view(ax, pts: np.ndarray) -> None:
    """Equal-aspect limits around ``pts`` (a 3:1 view for an elongated scene), grid, labels."""
    lo, hi = pts.min(0), pts.max(0)
    mid, half = (lo + hi) / 2, np.full(2, max(float((hi - lo).max()) / 2, 1.0) + 0.5)
    narrow = int(np.argmin(hi - lo))
    if (hi - lo)[narrow] < (hi - lo).max() / 3:  # an elongated scene (highway): a 3:1 view
        half[narrow] = max((hi - lo)[narrow] / 2 + 0.5, half[narrow] / 3)
    ax.set_xlim(mid[0] - half[0], mid[0] + half[0])
    ax.set_ylim(mid[1] - half[1], mid[1] + half[1])
    ax.set_aspect("equal", adjustable="box")
    ax.grid(alpha=0.3)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def _draw_weights(fig, gs, out, game, raw, probs, agents, real, modes=None, colors=None) -> None:
    """Ours' predicted game weights per mode (one panel per real agent, one pairwise for the
    pairs of real agents), log scale, with the dataset game's weights where the sample
    stores them. ``modes``: the modes drawn (all without), ``colors``: a colour per mode
    (:data:`MODE_COLORS` without)."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    modes = list(range(len(probs))) if modes is None else [int(m) for m in modes]
    if colors is None:
        colors = [MODE_COLORS[m % len(MODE_COLORS)] for m in range(len(probs))]
    M = len(modes)
    p = out["params"][0].detach().numpy()  # (M, n_p)
    names = list(game.params.names)
    true = (
        np.asarray(raw["params"]) if "params" in raw and len(raw["params"]) == len(names) else None
    )
    own = game.params.group("w_own")
    pair = game.params.group("w_pair")
    from .masks import game_pairs

    panels = []
    for i, a in enumerate(game.agent_names):
        if i not in real:
            continue
        idx = [j for j in own if names[j].startswith(f"w.{a}.")]
        panels.append((f"{agents[i]}: own weights", idx, [names[j][len(f"w.{a}.") :] for j in idx]))
    pair = [j for j, (a, b) in zip(pair, game_pairs(game), strict=True) if a in real and b in real]
    if pair:  # no pair panel with a single real agent
        panels.append(("pairwise weights", pair, [names[j][2:] for j in pair]))
    width_max = max(len(idx) for _, idx, _ in panels)
    for row, (title, idx, ticks) in enumerate(panels):
        axw = fig.add_subplot(gs[row, 1])
        x = np.arange(len(idx))
        width = 0.8 / M
        for j, m in enumerate(modes):
            axw.bar(
                x + (j - (M - 1) / 2) * width,
                p[m, idx],
                width,
                color=colors[m],
                label=f"mode {m} (p={probs[m]:.2f})",
            )
        if true is not None:
            axw.plot(x, true[idx], "kx", ms=8, mew=2, label="dataset game")
        axw.set_yscale("log")
        axw.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axw.yaxis.set_minor_formatter(NullFormatter())
        axw.set_xlim(-0.6, width_max - 0.4)
        axw.set_xticks(x)
        axw.set_xticklabels(
            [t.replace("_", " ") for t in ticks], fontsize=8, rotation=20, ha="right"
        )
        axw.set_title(title, fontsize=10)
        axw.grid(alpha=0.3, axis="y")
        if row == 0:
            axw.legend(fontsize=7, ncol=M + 1, loc="lower left", bbox_to_anchor=(0, 1.12))


#: modes drawn in ours' weight panels of a recorded-data figure (the most likely ones)
RECORDED_WEIGHT_MODES = 5


def _sample_info(meta: dict, raw: dict) -> list[str]:
    """Where a recorded sample comes from, for the title: scene / clip / scenario, frame."""
    info = []
    for key, names in (("scene", "scenes"), ("clip", "clips"), ("scenario", "scenarios")):
        if key in raw and isinstance(meta.get(names), list):
            i = int(raw[key])
            if 0 <= i < len(meta[names]):
                info.append(f"{key} {meta[names][i]}")
    if "frame" in raw:
        info.append(f"frame {int(raw['frame'])}")
    return info


def _draw_recorded(ax, fig, game, batch, raw, agents, gt, pos, probs, out, offset):
    """The real scene of a recorded sample with the predicted modes (module docstring);
    returns ``(points to fit, colour per mode)``."""
    import matplotlib
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.patches import Circle

    hist = batch["history"][0].numpy()[..., :2] + offset  # (H+1, N, 2)
    H1 = hist.shape[0]
    real = _real_agents(batch)
    gt = gt + offset
    pos = pos + offset
    # ---- the lane map (Waymo)
    if "lanes" in batch:
        lanes = batch["lanes"][0].numpy() + offset
        lmask = batch["lanes_mask"][0].numpy() if "lanes_mask" in batch else None
        keep = np.arange(len(lanes)) if lmask is None else np.flatnonzero(lmask)
        for n, k in enumerate(keep):
            ax.plot(*lanes[k].T, "-", color="0.85", lw=4, zorder=0, label=None if n else "lanes")
    # ---- the other recorded agents (ETH/UCY, CITR): observed solid, future dotted
    if "others" in raw:
        o = np.asarray(raw["others"], np.float64) + offset  # (C, H+1+T, 2), NaN: absent
        seen = fut = False
        for c in range(o.shape[0]):
            a, b = o[c, :H1], o[c, H1 - 1 :]
            if np.isfinite(a).all(-1).any():
                ax.plot(
                    a[:, 0], a[:, 1], "-", color="0.55", lw=1.2, marker="o", ms=3,
                    markevery=[H1 - 1], zorder=1,
                    label=None if seen else "other recorded agents (observed)",
                )  # fmt: skip
                seen = True
            if np.isfinite(b).all(-1).any():
                ax.plot(
                    b[:, 0], b[:, 1], ":", color="0.7", lw=1.2, zorder=1,
                    label=None if fut else "other recorded agents (future)",
                )  # fmt: skip
                fut = True
    # ---- the modes, coloured by probability, the most likely last (on top)
    cmap = matplotlib.colormaps["plasma_r"]
    top = float(probs.max()) if probs.size else 1.0
    norm = Normalize(0.0, max(top, 1e-9))
    colors = [cmap(norm(float(p))) for p in probs]
    best = int(np.argmax(probs))  # ties: the lower mode, as the metrics' top-1
    order = [int(m) for m in np.argsort(probs, kind="stable") if m != best] + [best]
    for m in order:
        sade = float(np.linalg.norm(pos[m, real] - gt[real], axis=-1).mean())
        w = float(norm(float(probs[m])))
        if m == best:
            label = f"most likely mode {m}: p={probs[m]:.2f}, SADE {sade:.2f} m"
        else:
            label = "other modes (colour: probability)" if m == order[0] else None
        for n, i in enumerate(real):
            xy = np.concatenate([hist[-1:, i], pos[m, i]])
            ax.plot(
                xy[:, 0], xy[:, 1], "-", color=colors[m], lw=2.8 if m == best else 0.8 + 1.2 * w,
                alpha=1.0 if m == best else 0.35 + 0.5 * w, zorder=3 if m == best else 2,
                label=label if n == 0 else None,
            )  # fmt: skip
    sm = ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=ax, shrink=0.5, pad=0.02, label="mode probability")
    decoded = None
    if isinstance(out, dict) and out.get("decoded_goals", False):
        decoded = out["goals"][0].detach().numpy()[best, real] + offset  # (n_real, 2)
        ax.plot(
            decoded[:, 0], decoded[:, 1], "P", color=colors[best], ms=11, mec="k", zorder=4,
            label="most likely mode's decoded goals",
        )  # fmt: skip
    # ---- the agents: history solid, truth dashed, the circle of the sample's radius
    radius = raw.get("radius")
    for n, i in enumerate(real):
        c = AGENT_COLORS[i % len(AGENT_COLORS)]
        ax.plot(
            hist[:, i, 0],
            hist[:, i, 1],
            "-",
            color=c,
            lw=2.2,
            zorder=5,
            label=f"{agents[i]} history",
        )
        r = float(radius[i]) if radius is not None else float(game.agents[i].radius)
        ax.add_patch(Circle(hist[-1, i], max(r, 0.05), fc="none", ec=c, lw=1.5, zorder=5))
        xy = np.concatenate([hist[-1:, i], gt[i]])
        ax.plot(
            xy[:, 0], xy[:, 1], "--", color="0.1", lw=2.0, zorder=5,
            label="ground truth" if n == 0 else None,
        )  # fmt: skip
    pts = [hist[:, real].reshape(-1, 2), gt[real].reshape(-1, 2), pos[:, real].reshape(-1, 2)]
    if decoded is not None:
        pts.append(decoded.reshape(-1, 2))
    return np.concatenate(pts), colors


def show_predictions(
    run_dir: str | os.PathLike,
    data_dir: str | os.PathLike,
    index: int,
    out_png: str | os.PathLike,
    split: str = "test",
    checkpoint: str = "best",
    frame: str = "world",
) -> Path:
    """Draw sample ``index`` of ``split`` with the predictions of a run (or ``"cv"``) to
    ``out_png``. ``frame``: ``"world"`` or ``"scene"``, for recorded data (a dataset with
    ``origin``; module docstring)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if frame not in ("world", "scene"):
        raise SpecError("frame", f"expected 'world' or 'scene', got {frame!r}")
    game, batch, raw, agents = load_sample(data_dir, split, index)
    model, label, kind = _model_of(run_dir, game, int(raw["future"].shape[0]), checkpoint)
    with torch.no_grad():
        pos, probs, out = predict(model, batch)
    if probs.ndim == 3:
        pos, probs = marginal_to_joint(pos, probs, batch.get("agents_mask"))
    pos, probs = pos[0].numpy(), probs[0].numpy()  # (M, N, T, 2), (M,)
    gt = batch["gt"][0].numpy()  # (N, T, 2)
    hist = batch["history"][0].numpy()  # (H+1, N, 4)
    real = _real_agents(batch)  # padded agents are not drawn
    N = len(real)
    show_weights = kind == "epo"
    recorded = "origin" in raw

    fig = Figure(figsize=(14 if show_weights else 7.5, 8))
    FigureCanvasAgg(fig)
    gs = None
    if show_weights:
        gs = fig.add_gridspec(N + 1, 2, width_ratios=[1.25, 1], hspace=0.65, wspace=0.18)
        ax = fig.add_subplot(gs[:, 0])
    else:
        ax = fig.add_subplot(1, 1, 1)
    colors = wmodes = None
    if recorded:
        offset = np.asarray(raw["origin"], np.float64) if frame == "world" else np.zeros(2)
        pts, colors = _draw_recorded(ax, fig, game, batch, raw, agents, gt, pos, probs, out, offset)
        wmodes = np.argsort(-probs, kind="stable")[:RECORDED_WEIGHT_MODES]
        meta = read_manifest(data_dir).get("meta") or {}
        info = [f"{split}[{index}]", *_sample_info(meta, raw), f"{frame} frame"]
    else:
        _draw_scene(ax, game, batch, raw, agents, gt)
        given_goals = batch["goals"][0].numpy()[real] if "goals" in batch else None
        decoded = _draw_modes(ax, out, pos, probs, hist, gt, real)
        pts = np.concatenate(
            [
                hist[:, real, :2].reshape(-1, 2),
                gt[real].reshape(-1, 2),
                pos[:, real].reshape(-1, 2),
            ]
            + [g.reshape(-1, 2) for g in (given_goals, decoded) if g is not None]
        )
        info = [f"{split}[{index}]"]
        info += [f"{k} {int(raw[k])}" for k in ("main_game", "step") if k in raw]
    _fit_view(ax, pts)
    if recorded and frame == "world":
        ax.set_xlabel("x (m, recording frame)")
        ax.set_ylabel("y (m, recording frame)")
    below = -0.14 if recorded else -0.09  # under the axis label
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, below), ncol=2, framealpha=0.9)
    ax.set_title(f"{label}: " + ", ".join(info), fontsize=11)
    if show_weights:
        _draw_weights(fig, gs, out, game, raw, probs, agents, set(real.tolist()), wmodes, colors)
    from scenarios.plotting import save_figure

    return save_figure(fig, Path(out_png), "out_png", dpi=100, bbox_inches="tight")
