"""Training objectives (paper Sec. 4.3 and App. F.4).

``L = lambda_1 L_imit + lambda_2 L_goal + lambda_3 L_prob`` with the paper's weights
``(1, 0.1, 0.1)`` for ours. ``L_imit`` is the minSADE loss: the joint mode closest to
the ground truth. Its reduction over the ``K`` future steps (:data:`IMITATION_REDUCTIONS`,
``imitation_reduction``) is ``"mean"`` by default,
``min_m 1/N sum_i mean_t ||x^m_{i,t} - x^GT_{i,t}||^2`` (averaged over steps so that its
scale does not depend on the horizon), or ``"sum"``,
``min_m 1/N sum_i sum_t ||x^m_{i,t} - x^GT_{i,t}||^2``: the paper's form (App. F.4), the
squared norm of the whole trajectory difference, ``K`` times the mean (so its weight
against ``L_goal`` and ``L_prob`` is ``K`` times larger; the closest mode is the same).
``L_prob`` is the cross entropy of the scene
probabilities with that closest mode as the target. ``L_goal`` (:func:`goal_loss`, only for
ours with a goal decoder; in RPI the goals are given and it is zero): the cross entropy of
each agent's goal distribution with the candidate closest to its ground-truth final
position as the target, averaged over agents (App. F.4, Eq. (11)); or, for regressed
goals, the minSFDE-style ``min_m 1/N sum_i ||g^m_i - x_GT,i,T||^2`` (App. F.4, Waymo). The SC baseline uses ``L_imit + L_prob`` (paper Sec. 5); the
marginal V-LSTM uses per-agent minADE plus a per-agent classification loss (with
``"sum"`` the per-step distances are summed over the steps instead).

Shapes follow :mod:`learning.metrics`: ``pos`` ``(B, M, N, T, 2)``, ``gt`` ``(B, N, T, 2)``.

``mask`` ``(B, N)`` bool (the batch's ``agents_mask``): every per-agent term is averaged over
the agents of ``mask`` only. A padded agent's (False) predictions, ground truth, logits and
candidates are replaced by zeros with ``torch.where`` before any arithmetic, so no value of a
pad (inf, NaN) reaches the loss or its gradient. A mask with every agent True is the same as
no mask: the numbers are those computed without one.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from epo_casadi.errors import SpecError

from .masks import active, where_agents
from .metrics import agent_mean

__all__ = [
    "IMITATION_REDUCTIONS",
    "LossWeights",
    "scene_loss",
    "marginal_loss",
    "goal_loss",
    "goal_classification_loss",
    "goal_regression_loss",
]


@dataclass(frozen=True)
class LossWeights:
    """The scaling factors of ``L = lambda_1 L_imit + lambda_2 L_goal + lambda_3 L_prob``.

    ``imitation`` (``lambda_1``), ``goal`` (``lambda_2``, used only by a model with a goal
    decoder) and ``probability`` (``lambda_3``), plain numbers. The defaults ``(1, 0.1,
    0.1)`` are the paper's (Sec. 4.3; values in App. F.4); :func:`marginal_loss` defaults
    to ``probability=1``.
    """

    imitation: float = 1.0  #: lambda_1
    goal: float = 0.1  #: lambda_2 (used by a goal decoder; RPI gives the goals)
    probability: float = 0.1  #: lambda_3


#: how the imitation loss reduces its per-step terms over the future steps
IMITATION_REDUCTIONS = ("mean", "sum")


def _over_time(v: torch.Tensor, reduction: str) -> torch.Tensor:
    """``v`` ``(..., T)`` reduced over its last (time) axis: ``"mean"`` or ``"sum"``."""
    if reduction == "mean":
        return v.mean(-1)
    if reduction == "sum":
        return v.sum(-1)
    raise SpecError(
        "imitation_reduction", f"expected one of {list(IMITATION_REDUCTIONS)}, got {reduction!r}"
    )


def _masked_mean(v: torch.Tensor, mask) -> torch.Tensor:
    """Mean of per-agent values ``v`` ``(B, N)`` over the batch and the agents of ``mask``."""
    if mask is None:
        return v.mean()
    m = mask.to(torch.bool)
    return torch.where(m, v, torch.zeros((), dtype=v.dtype)).sum() / m.sum().clamp_min(1)


def _real(mask, *pairs):
    """``(mask or None, tensors)``: ``mask`` as :func:`learning.masks.active` (None without a
    pad), and each ``(tensor, agent_dim)`` of ``pairs`` with zeros on the padded agents."""
    mask = active(mask)
    if mask is None:
        return None, [t for t, _ in pairs]
    return mask, [where_agents(mask, t, 0.0, agent_dim=d) for t, d in pairs]


def scene_loss(
    pos,
    logits,
    gt,
    weights: LossWeights = LossWeights(),
    mask=None,
    imitation_reduction: str = "mean",
) -> dict[str, torch.Tensor]:
    """Joint (scene-level) loss; returns the total and its parts (means over the batch).

    ``imitation_reduction``: the squared distances of the ``T`` steps averaged (``"mean"``)
    or summed (``"sum"``, the paper's ``||x^m_i - x_GT||^2``) per agent."""
    mask, (pos, gt) = _real(mask, (pos, 2), (gt, 1))
    sq = _over_time(((pos - gt[:, None]) ** 2).sum(-1), imitation_reduction)  # (B, M, N)
    per_mode = agent_mean(sq, mask)  # (B, M)
    best = per_mode.argmin(dim=1)
    imit = per_mode.gather(1, best[:, None]).mean()
    prob = F.cross_entropy(logits, best)
    total = weights.imitation * imit + weights.probability * prob
    return {"loss": total, "imitation": imit, "probability": prob}


def marginal_loss(
    pos,
    logits,
    gt,
    weights: LossWeights = LossWeights(probability=1.0),
    mask=None,
    imitation_reduction: str = "mean",
) -> dict[str, torch.Tensor]:
    """Marginal loss: per agent the closest mode's ADE, plus classification of that mode.

    ``logits`` are per agent, ``(B, N, M)``. ``imitation_reduction``: the distances of the
    ``T`` steps averaged (``"mean"``, the ADE) or summed (``"sum"``).
    """
    mask, (pos, gt, logits) = _real(mask, (pos, 2), (gt, 1), (logits, 1))
    d = torch.linalg.vector_norm(pos - gt[:, None], dim=-1)
    ade = _over_time(d, imitation_reduction)  # (B, M, N)
    best = ade.argmin(dim=1)  # (B, N)
    imit_agent = ade.gather(1, best[:, None]).squeeze(1)  # (B, N)
    ce = F.cross_entropy(
        logits.reshape(-1, logits.shape[-1]), best.reshape(-1), reduction="none"
    ).reshape(best.shape)
    imit, cls = _masked_mean(imit_agent, mask), _masked_mean(ce, mask)
    total = weights.imitation * imit + weights.probability * cls
    return {"loss": total, "imitation": imit, "probability": cls}


def goal_classification_loss(logits, candidates, gt_final, cand_mask=None, mask=None):
    """Cross entropy of per-agent goal logits ``(B, N, G)`` with the candidate closest to
    the ground-truth final position ``gt_final`` ``(B, N, 2)`` as the target; mean over agents.

    ``candidates`` ``(B, N, G, 2)``; masked candidates (``cand_mask`` False) are never targets.
    """
    mask, (logits, candidates, gt_final) = _real(mask, (logits, 1), (candidates, 1), (gt_final, 1))
    if mask is not None and cand_mask is not None:
        cand_mask = cand_mask.bool() | ~mask[:, :, None]
    d = torch.linalg.vector_norm(candidates - gt_final[:, :, None], dim=-1)  # (B, N, G)
    if cand_mask is not None:
        d = d.masked_fill(~cand_mask.bool(), torch.inf)
    target = d.argmin(-1)  # (B, N)
    ce = F.cross_entropy(
        logits.reshape(-1, logits.shape[-1]), target.reshape(-1), reduction="none"
    ).reshape(target.shape)
    return _masked_mean(ce, mask)


def goal_regression_loss(goals, gt_final, mask=None):
    """``min_m 1/N sum_i ||g^m_i - x_GT,i,T||^2`` for goals ``(B, M, N, 2)``; mean over the batch."""
    mask, (goals, gt_final) = _real(mask, (goals, 2), (gt_final, 1))
    sq = ((goals - gt_final[:, None]) ** 2).sum(-1)  # (B, M, N)
    return agent_mean(sq, mask).min(dim=1).values.mean()


def goal_loss(out: dict, gt, mask=None) -> torch.Tensor | None:
    """The goal loss of a model output (``gt`` ``(B, N, T, 2)``), or ``None`` without a goal decoder.

    An output with ``goal_logits`` gets :func:`goal_classification_loss`; one with decoded
    ``goals`` but no logits (``"regress"``) gets :func:`goal_regression_loss`. Given goals
    (``decoded_goals`` False or absent) have no loss.
    """
    if not out.get("decoded_goals", False):
        return None
    final = gt[:, :, -1]
    if "goal_logits" in out:
        return goal_classification_loss(
            out["goal_logits"], out["goal_candidates"], final, out.get("goal_candidates_mask"), mask
        )
    return goal_regression_loss(out["goals"], final, mask)
