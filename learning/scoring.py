"""Scoring one predictor on a dataset: the piece training and evaluation share.

:func:`score_samples` runs a predictor over a :class:`learning.data.SceneDataset` and gives
:func:`learning.metrics.all_metrics` per sample; :func:`mean_metrics` averages them (over
the whole split or a subset of its samples); :func:`evaluate_model` is the two in one
(:data:`METRICS`). :func:`predict` turns one batch into positions and mode probabilities.
:mod:`learning.train` (validation after each epoch) and :mod:`learning.evaluate` (run
directories, the table) both import it from here, so neither of them imports the other
for it.

Initial strategies: a model whose output has ``init_pos`` (ours: the rollout of the
learned initialization ``U_init``, before the game layer's ``S`` steps) is scored on it as
well, with the same metric functions, mask and scene probabilities (the model's, computed
from the optimized modes: they rank the initial modes for ``OR`` and the top-1 focal
errors); those values are the metrics' names with the prefix :data:`INIT_PREFIX`
(``init_minSADE``, ...). A model without ``init_pos`` (the baselines) has none.

The overlap rate's shapes (:func:`overlap_shapes`): oriented boxes where the dataset stores
``length`` and ``width`` (:func:`boxes`; then the circles are ``OR_circle``), circles
otherwise. The circles' radii are each sample's ``radius`` where the dataset stores it and
the game takes the radius as a parameter (``AgentSpec.radius_param``: the model's game then
uses the same radius), else the radii of the game (:func:`sample_radii`).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from .data import SceneDataset
from .metrics import FOCAL_METRICS, all_metrics

__all__ = [
    "INIT_PREFIX",
    "METRICS",
    "FOCAL_METRICS",
    "evaluate_model",
    "mean_metrics",
    "overlap_shapes",
    "predict",
    "sample_radii",
    "score_samples",
]

METRICS = ("minADE", "minFDE", "minSADE", "minSFDE", "OR")
#: prefix of the metrics of a model's initial strategies (output ``init_pos``)
INIT_PREFIX = "init_"


def predict(model: torch.nn.Module, batch: dict) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """``(pos, probs, out)`` of a predictor on a batch: probabilities joint ``(B, M)`` or marginal ``(B, N, M)``."""
    out = model(batch)
    if "marginal_logits" in out:
        probs = torch.softmax(out["marginal_logits"], dim=-1)
    else:
        probs = torch.softmax(out["logits"], dim=-1)
    return out["pos"], probs, out


def boxes(batch: dict) -> dict | None:
    """Vehicle boxes for the overlap rate when the batch has ``length`` and ``width``
    (exiD layout, Waymo; :func:`learning.metrics.overlap_rate_boxes`), else None (circles)."""
    if "length" not in batch or "width" not in batch:
        return None
    cur = batch["history"][:, -1]  # (B, N, 4): x, y, v, theta
    return {
        "length": batch["length"],
        "width": batch["width"],
        "start": cur[..., :2],
        "heading0": cur[..., 3],
    }


def sample_radii(data: SceneDataset) -> bool:
    """True when the circles of the overlap rate are each sample's ``radius``: the dataset
    stores the field and every agent of its game takes its radius as a parameter
    (``radius.<agent>``, ``AgentSpec.radius_param``); False: the game's radii."""
    if "radius" not in data.fields:
        return False
    game = data.game
    return all(f"radius.{a}" in game.params for a in game.agent_names)


def overlap_shapes(data: SceneDataset) -> tuple[bool, str]:
    """``(boxes, circles)``: whether ``OR`` uses vehicle boxes (the dataset stores ``length``
    and ``width``), and where the circles' radii come from, in the words of the table
    header: ``"the sample radii (field radius)"`` or ``"the game's radii"``."""
    box = "length" in data.fields and "width" in data.fields
    circles = "the sample radii (field radius)" if sample_radii(data) else "the game's radii"
    return box, circles


def score_samples(
    model: torch.nn.Module,
    data: SceneDataset,
    batch_size: int = 64,
    progress: bool = False,
    focal: int | None = None,
) -> dict[str, np.ndarray]:
    """Every metric of every sample of ``data``, in sample order: ``{name: (n,) float64}``
    (:data:`METRICS`, ``OR_circle`` on data with vehicle sizes, :data:`FOCAL_METRICS` with
    ``focal``, an agent slot; NaN where that slot is a pad; each also with the prefix
    :data:`INIT_PREFIX` for a model whose output has ``init_pos``, module docstring). The
    model is put in eval mode.
    Every metric counts only the batch's real agents (``agents_mask``; the overlap rate only
    pairs of real agents)."""
    game_radii = torch.tensor([a.radius for a in data.game.agents], dtype=torch.float32)
    per_sample = sample_radii(data)
    was_training = model.training
    model.eval()
    parts: dict[str, list[np.ndarray]] = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(data), unit="sample", desc="evaluate", leave=False, dynamic_ncols=True)
    try:
        with torch.no_grad():
            for batch in data.batches(batch_size):
                pos, probs, out = predict(model, batch)
                scored = [("", pos)]
                if out.get("init_pos") is not None:
                    scored.append((INIT_PREFIX, out["init_pos"]))
                for prefix, p in scored:
                    m = all_metrics(
                        p.float(),
                        batch["gt"],
                        probs.float(),
                        batch["radius"] if per_sample else game_radii,
                        mask=batch.get("agents_mask"),
                        boxes=boxes(batch),
                        focal=focal,
                    )
                    for k, v in m.items():
                        parts.setdefault(prefix + k, []).append(v.double().cpu().numpy())
                if bar is not None:
                    bar.update(pos.shape[0])
    finally:
        if bar is not None:
            bar.close()
        model.train(was_training)
    if not parts:
        names = METRICS + (FOCAL_METRICS if focal is not None else ())
        return {k: np.zeros(0) for k in names}
    return {k: np.concatenate(v) for k, v in parts.items()}


def mean_metrics(per: dict[str, np.ndarray], select: np.ndarray | None = None) -> dict:
    """Means of :func:`score_samples`' values over the samples ``select`` (a boolean mask
    or indices; all without), and ``samples``, their count. A focal metric averages the
    samples whose focal slot is a real agent (its value is not NaN); every other metric
    averages every sample (a NaN prediction shows as NaN). No sample: NaN."""
    out = {}
    n = 0
    for k, v in per.items():
        v = v if select is None else v[select]
        n = v.size
        if k.removeprefix(INIT_PREFIX) in FOCAL_METRICS:
            ok = ~np.isnan(v)
            out[k] = float(v[ok].mean()) if ok.any() else math.nan
        else:
            out[k] = float(v.mean()) if v.size else math.nan
    out["samples"] = int(n)
    return out


def evaluate_model(
    model: torch.nn.Module,
    data: SceneDataset,
    batch_size: int = 64,
    progress: bool = False,
    focal: int | None = None,
) -> dict[str, float]:
    """Mean of every metric over ``data`` (and ``samples``); the model is put in eval mode.

    :data:`METRICS`; on data with vehicle sizes (:func:`boxes`) ``OR`` uses boxes and
    ``OR_circle`` is added (circles: :func:`sample_radii`); with ``focal`` (an agent slot)
    :data:`FOCAL_METRICS`. Every metric counts only the batch's real agents
    (``agents_mask``; the overlap rate only pairs of real agents): a sample's value is the
    mean over its real agents, then samples count alike. A model with initial strategies
    (ours) also gets each metric of them, prefixed :data:`INIT_PREFIX`."""
    per = score_samples(model, data, batch_size, progress, focal)
    out = mean_metrics(per)
    if out["samples"] == 0:  # e.g. an empty val split: say so instead of a silent "minADE nan"
        where = f"split {data.split!r} of {data.directory}" if hasattr(data, "split") else "data"
        warnings.warn(f"{where} has no samples: every metric is nan", stacklevel=2)
    return out
