"""Prediction metrics of the paper (Sec. 5), marginal and joint.

Shapes (``B`` samples, ``M`` modes, ``N`` agents, ``T`` future steps):

- ``pred``: ``(B, M, N, T, 2)`` predicted positions;
- ``gt``: ``(B, N, T, 2)`` ground-truth positions;
- ``probs``: ``(B, M)`` joint mode probabilities, or ``(B, N, M)`` marginal ones;
- ``mask``: optional ``(B, N)`` boolean, True for agents that count.

Definitions (``d = ||pred - gt||_2`` per agent and step):

- ``minADE`` (marginal): per agent, the minimum over modes of the mean over time of ``d``,
  then averaged over agents;
- ``minFDE`` (marginal): the same at the last step;
- ``minSADE`` (joint): the minimum over modes of the mean over agents and time of ``d``;
- ``minSFDE`` (joint): the minimum over modes of the mean over agents of ``d`` at the last step;
- overlap rate ``OR``: share of samples whose most likely joint prediction has two agents'
  circles overlapping (``dist < r_i + r_j``) at some step.

Marginal models have one probability per agent and mode; their joint scenes are built
as the paper describes, by ordering each agent's modes by its marginal probability and
taking the ``m``-th most likely mode of every agent as joint mode ``m``
(:func:`marginal_to_joint`); the joint probability is the product of the agents'.

All functions return one value per sample (``(B,)``); average with ``.mean()``.
"""

from __future__ import annotations

import torch

__all__ = [
    "min_ade",
    "min_fde",
    "min_sade",
    "min_sfde",
    "overlap_rate",
    "marginal_to_joint",
    "all_metrics",
]


def _t(a) -> torch.Tensor:
    return a if isinstance(a, torch.Tensor) else torch.as_tensor(a)


def _check(pred, gt, mask):
    pred, gt = _t(pred), _t(gt)
    if pred.ndim != 5 or pred.shape[-1] != 2:
        raise ValueError(f"pred: expected shape (B, M, N, T, 2), got {tuple(pred.shape)}")
    if gt.shape != pred.shape[:1] + pred.shape[2:]:
        raise ValueError(
            f"gt: expected shape {tuple(pred.shape[:1] + pred.shape[2:])}, got {tuple(gt.shape)}"
        )
    if mask is None:
        mask = torch.ones(pred.shape[0], pred.shape[2], dtype=torch.bool, device=pred.device)
    mask = _t(mask).to(torch.bool)
    if mask.shape != (pred.shape[0], pred.shape[2]):
        raise ValueError(
            f"mask: expected shape {(pred.shape[0], pred.shape[2])}, got {tuple(mask.shape)}"
        )
    return pred, gt, mask


def _dist(pred, gt):
    return torch.linalg.vector_norm(pred - gt.unsqueeze(1), dim=-1)  # (B, M, N, T)


def agent_mean(v, mask=None):
    """Mean over agents (the last axis) of ``v`` ``(B, ..., N)``, counting only the agents
    of ``mask`` ``(B, N)`` (all agents without a mask)."""
    if mask is None:
        return v.mean(-1)
    m = mask.to(v.dtype)
    while m.ndim < v.ndim:
        m = m.unsqueeze(1)
    return (v * m).sum(-1) / m.sum(-1).clamp_min(1)


def min_ade(pred, gt, mask=None) -> torch.Tensor:
    pred, gt, mask = _check(pred, gt, mask)
    per_agent = _dist(pred, gt).mean(-1).min(dim=1).values  # (B, N)
    return agent_mean(per_agent, mask)


def min_fde(pred, gt, mask=None) -> torch.Tensor:
    pred, gt, mask = _check(pred, gt, mask)
    per_agent = _dist(pred, gt)[..., -1].min(dim=1).values
    return agent_mean(per_agent, mask)


def min_sade(pred, gt, mask=None) -> torch.Tensor:
    pred, gt, mask = _check(pred, gt, mask)
    return agent_mean(_dist(pred, gt).mean(-1), mask).min(dim=1).values


def min_sfde(pred, gt, mask=None) -> torch.Tensor:
    pred, gt, mask = _check(pred, gt, mask)
    return agent_mean(_dist(pred, gt)[..., -1], mask).min(dim=1).values


def overlap_rate(pred, probs, radii, mask=None) -> torch.Tensor:
    """1.0 for samples whose most likely joint mode has an overlap, else 0.0."""
    pred, probs = _t(pred), _t(probs)
    B, M, N = pred.shape[:3]
    if probs.shape != (B, M):
        raise ValueError(
            f"probs: expected joint probabilities of shape {(B, M)}, got {tuple(probs.shape)}"
        )
    radii = _t(radii).to(pred.dtype)
    radii = radii.expand(B, N) if radii.ndim == 1 else radii
    if mask is None:
        mask = torch.ones(B, N, dtype=torch.bool)
    best = pred[torch.arange(B), probs.argmax(dim=1)]  # (B, N, T, 2)
    d = torch.linalg.vector_norm(best[:, :, None] - best[:, None, :], dim=-1)  # (B, N, N, T)
    rr = radii[:, :, None] + radii[:, None, :]
    pair = mask[:, :, None] & mask[:, None, :] & ~torch.eye(N, dtype=torch.bool)[None]
    hit = (d < rr[..., None]).any(-1) & pair
    return hit.flatten(1).any(-1).to(pred.dtype)


def marginal_to_joint(pred, probs):
    """Joint scenes from per-agent modes ordered by marginal probability.

    ``pred`` ``(B, M, N, T, 2)`` holds agent ``i``'s ``m``-th mode at ``[:, m, i]``;
    ``probs`` ``(B, N, M)``. Returns the reordered ``pred`` (joint mode ``m`` = every agent's
    ``m``-th most likely mode) and joint probabilities ``(B, M)`` (products, normalized).
    """
    pred, probs = _t(pred), _t(probs)
    B, M, N = pred.shape[:3]
    if probs.shape != (B, N, M):
        raise ValueError(
            f"probs: expected marginal probabilities of shape {(B, N, M)}, got {tuple(probs.shape)}"
        )
    order = probs.argsort(dim=-1, descending=True)  # (B, N, M)
    idx = order.permute(0, 2, 1)  # (B, M, N): mode of agent n in joint mode m
    joint = torch.gather(pred, 1, idx[..., None, None].expand(B, M, N, *pred.shape[3:]))
    p = torch.gather(probs, 2, order).prod(dim=1)  # (B, M)
    return joint, p / p.sum(-1, keepdim=True).clamp_min(1e-12)


def all_metrics(pred, gt, probs, radii, mask=None) -> dict[str, torch.Tensor]:
    """Every metric per sample; ``probs`` joint ``(B, M)`` or marginal ``(B, N, M)``."""
    probs = _t(probs)
    marginal = {"minADE": min_ade(pred, gt, mask), "minFDE": min_fde(pred, gt, mask)}
    if probs.ndim == 3:
        pred, probs = marginal_to_joint(pred, probs)
    return {
        **marginal,
        "minSADE": min_sade(pred, gt, mask),
        "minSFDE": min_sfde(pred, gt, mask),
        "OR": overlap_rate(pred, probs, radii, mask),
    }
