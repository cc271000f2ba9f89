"""Scoring one predictor on a dataset: the piece training and evaluation share.

:func:`evaluate_model` runs a predictor over a :class:`learning.data.SceneDataset` and
averages :func:`learning.metrics.all_metrics` (:data:`METRICS`); :func:`predict` turns one
batch into positions and mode probabilities. :mod:`learning.train` (validation after each
epoch) and :mod:`learning.evaluate` (run directories, the table) both import it from here,
so neither of them imports the other for it.
"""

from __future__ import annotations

import math
import warnings

import torch

from .data import SceneDataset
from .metrics import all_metrics

__all__ = ["METRICS", "evaluate_model", "predict"]

METRICS = ("minADE", "minFDE", "minSADE", "minSFDE", "OR")


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
    (exiD layout; :func:`learning.metrics.overlap_rate_boxes`), else None (circles)."""
    if "length" not in batch or "width" not in batch:
        return None
    cur = batch["history"][:, -1]  # (B, N, 4): x, y, v, theta
    return {
        "length": batch["length"],
        "width": batch["width"],
        "start": cur[..., :2],
        "heading0": cur[..., 3],
    }


def evaluate_model(
    model: torch.nn.Module,
    data: SceneDataset,
    batch_size: int = 64,
    progress: bool = False,
) -> dict[str, float]:
    """Mean of every metric over ``data`` (and ``samples``); the model is put in eval mode.

    :data:`METRICS`; on data with vehicle sizes (:func:`boxes`) ``OR`` uses boxes and
    ``OR_circle`` is added (the circles of the game's radii). Every metric counts only the
    batch's real agents (``agents_mask``; the overlap rate only pairs of real agents): a
    sample's value is the mean over its real agents, then samples count alike."""
    radii = torch.tensor([a.radius for a in data.game.agents], dtype=torch.float32)
    was_training = model.training
    model.eval()
    sums = dict.fromkeys(METRICS, 0.0)
    n = 0
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(data), unit="sample", desc="evaluate", leave=False, dynamic_ncols=True)
    try:
        with torch.no_grad():
            for batch in data.batches(batch_size):
                pos, probs, _ = predict(model, batch)
                m = all_metrics(
                    pos.float(),
                    batch["gt"],
                    probs.float(),
                    radii,
                    mask=batch.get("agents_mask"),
                    boxes=boxes(batch),
                )
                for k in m.keys() - sums.keys():  # OR_circle with boxes
                    sums[k] = 0.0
                for k in m:
                    sums[k] += float(m[k].sum())
                n += pos.shape[0]
                if bar is not None:
                    bar.update(pos.shape[0])
    finally:
        if bar is not None:
            bar.close()
        model.train(was_training)
    if n == 0:  # e.g. an empty val split: say so instead of a silent "minADE nan"
        where = f"split {data.split!r} of {data.directory}" if hasattr(data, "split") else "data"
        warnings.warn(f"{where} has no samples: every metric is nan", stacklevel=2)
    out = {k: (sums[k] / n if n else math.nan) for k in sums}
    out["samples"] = n
    return out
