"""Prediction metrics of the paper (Sec. 5), marginal and joint.

Shapes (``B`` samples, ``M`` modes, ``N`` agents, ``T`` future steps):

- ``pred``: ``(B, M, N, T, 2)`` predicted positions;
- ``gt``: ``(B, N, T, 2)`` ground-truth positions;
- ``probs``: ``(B, M)`` joint mode probabilities, or ``(B, N, M)`` marginal ones;
- ``mask``: optional ``(B, N)`` boolean, True for agents that count (the batch's
  ``agents_mask``: padded agents are False). Every mean over agents counts only the agents
  of ``mask``, the overlap rate only pairs of two such agents, and the joint scenes of
  marginal predictions only their probabilities; a padded agent's values, whatever they
  are (inf, NaN), change no metric.

Definitions (``d = ||pred - gt||_2`` per agent and step):

- ``minADE`` (marginal): per agent, the minimum over modes of the mean over time of ``d``,
  then averaged over agents;
- ``minFDE`` (marginal): the same at the last step;
- ``minSADE`` (joint): the minimum over modes of the mean over agents and time of ``d``;
- ``minSFDE`` (joint): the minimum over modes of the mean over agents of ``d`` at the last step;
- overlap rate ``OR``: share of samples whose most likely joint prediction has two agents
  overlapping at some step. Two definitions:

  * circles (:func:`overlap_rate`): ``dist < r_i + r_j``; ``radii`` ``(N,)`` or ``(B, N)``:
    :func:`learning.scoring.evaluate_model` passes each sample's ``radius`` where the
    dataset stores it and the game takes it as a parameter (``AgentSpec.radius_param``: the
    recorded-data readers, exiD with ``radius_per_agent``), else the radii of the game;
  * oriented boxes (:func:`overlap_rate_boxes`, Waymo / JFP style): each agent a
    ``length x width`` rectangle centred on its predicted position, heading along its
    predicted direction of motion; two agents overlap when their rectangles intersect
    (separating-axis test; touching is not an overlap).

  **Which one a table uses**: :func:`all_metrics` (and so ``epo evaluate`` / validation)
  reports ``OR`` with boxes when the batch gives each agent's length and width (exiD-layout
  and Waymo datasets, fields ``length`` and ``width``) and then also the circle OR as
  ``OR_circle``; datasets without those fields (RPI, left turn, ETH/UCY, CITR) get circles.
  ``epo evaluate`` writes the definition into its table header.

Focal-agent metrics (:func:`focal_errors`; the ETH/UCY benchmark's ADE / FDE, scored on
one agent per sample, the one in slot ``focal``):

- ``ADE_focal`` / ``FDE_focal``: the smallest, over the ``M`` modes, mean over time (or
  final-step) distance of the focal agent: "best of M" (best of 20 with ``M = 20``); the
  two minima are taken separately, as the benchmark does;
- ``ADE_focal_top1`` / ``FDE_focal_top1``: the focal agent's errors in the most likely mode:
  the argmax of the scene probabilities (joint models), or of the focal agent's own mode
  probabilities (marginal models); ties: the lower mode index.

A sample whose focal slot is not a real agent (``mask`` False) gets NaN there.

Marginal models have one probability per agent and mode; their joint scenes are built
as the paper describes, by ordering each agent's modes by its marginal probability and
taking the ``m``-th most likely mode of every agent as joint mode ``m``
(:func:`marginal_to_joint`); the joint probability is the product of the agents'.

All functions return one value per sample (``(B,)``); average with ``.mean()``.
"""

from __future__ import annotations

import math

import torch

__all__ = [
    "min_ade",
    "min_fde",
    "min_sade",
    "min_sfde",
    "overlap_rate",
    "overlap_rate_boxes",
    "box_hits",
    "box_overlap",
    "motion_headings",
    "marginal_to_joint",
    "focal_errors",
    "all_metrics",
    "FOCAL_METRICS",
]

#: the focal-agent metrics (:func:`focal_errors`)
FOCAL_METRICS = ("ADE_focal", "FDE_focal", "ADE_focal_top1", "FDE_focal_top1")


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
    m = _t(mask).to(device=v.device, dtype=torch.bool)
    while m.ndim < v.ndim:
        m = m.unsqueeze(1)
    zero = torch.zeros((), dtype=v.dtype, device=v.device)
    return torch.where(m, v, zero).sum(-1) / m.to(v.dtype).sum(-1).clamp_min(1)


def min_ade(pred, gt, mask=None) -> torch.Tensor:
    """Marginal minADE per sample, ``(B,)`` (metres, the units of the positions).

    For each agent the smallest, over the ``M`` modes, mean over the ``T`` steps of the
    distance ``||pred - gt||_2``; then the mean over the agents of ``mask`` (every agent
    without one; a sample with no agent in ``mask`` gives 0). Each agent picks its own
    best mode. ``pred`` ``(B, M, N, T, 2)``, ``gt`` ``(B, N, T, 2)``, ``mask`` ``(B, N)``
    boolean or ``None``; arrays or tensors; a wrong shape raises ``ValueError``.
    The paper's minADE (Sec. 5).
    """
    pred, gt, mask = _check(pred, gt, mask)
    per_agent = _dist(pred, gt).mean(-1).min(dim=1).values  # (B, N)
    return agent_mean(per_agent, mask)


def min_fde(pred, gt, mask=None) -> torch.Tensor:
    """Marginal minFDE per sample, ``(B,)`` (metres): :func:`min_ade` at the last step only.

    For each agent the smallest, over the modes, distance at step ``T - 1``; then the mean
    over the agents of ``mask``. Shapes and checks as :func:`min_ade`. The paper's minFDE
    (Sec. 5).
    """
    pred, gt, mask = _check(pred, gt, mask)
    per_agent = _dist(pred, gt)[..., -1].min(dim=1).values
    return agent_mean(per_agent, mask)


def min_sade(pred, gt, mask=None) -> torch.Tensor:
    """Joint (scene) minSADE per sample, ``(B,)`` (metres).

    For each mode the mean over the agents of ``mask`` and the ``T`` steps of the distance
    ``||pred - gt||_2``; then the smallest over the ``M`` modes, so one mode must fit every
    agent at once (``pred``'s modes are joint scenes; marginal predictions go through
    :func:`marginal_to_joint` first). Shapes and checks as :func:`min_ade`. The paper's
    minSADE (Sec. 5).
    """
    pred, gt, mask = _check(pred, gt, mask)
    return agent_mean(_dist(pred, gt).mean(-1), mask).min(dim=1).values


def min_sfde(pred, gt, mask=None) -> torch.Tensor:
    """Joint (scene) minSFDE per sample, ``(B,)`` (metres): :func:`min_sade` at the last
    step only (the mean over the agents of ``mask`` of the distance at step ``T - 1``, then
    the smallest over the modes). Shapes and checks as :func:`min_ade`. The paper's minSFDE
    (Sec. 5).
    """
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


def motion_headings(pos, start=None, heading0=None, min_step: float = 0.05) -> torch.Tensor:
    """Heading of each agent at each step from its direction of motion, ``(..., T)``.

    ``pos`` ``(..., T, 2)``; the heading at step ``t`` is the direction of
    ``pos[t] - pos[t - 1]`` (``pos[-1]`` = ``start`` ``(..., 2)``, the current position;
    without it ``2 pos[0] - pos[1]``, i.e. step 0 takes step 1's direction). Where an agent
    moves less than ``min_step`` metres in a step (nearly stopped) it keeps its last valid
    heading; before its first valid one, ``heading0`` ``(...)`` (the current heading; 0
    without it). No loop over steps: the last valid step comes from a running maximum.
    """
    pos = _t(pos)
    if pos.shape[-1] != 2 or pos.ndim < 2:
        raise ValueError(f"pos: expected shape (..., T, 2), got {tuple(pos.shape)}")
    T = pos.shape[-2]
    if start is None:
        start = 2 * pos[..., 0, :] - pos[..., min(1, T - 1), :]
    start = _t(start).to(pos.dtype)
    prev = torch.cat([start.unsqueeze(-2), pos[..., :-1, :]], dim=-2)
    d = pos - prev
    raw = torch.atan2(d[..., 1], d[..., 0])  # (..., T)
    valid = torch.linalg.vector_norm(d, dim=-1) >= min_step
    steps = torch.arange(T, device=pos.device).expand(valid.shape)
    last = torch.where(valid, steps, torch.full_like(steps, -1)).cummax(dim=-1).values
    held = torch.gather(raw, -1, last.clamp_min(0))
    h0 = torch.zeros(pos.shape[:-2], dtype=pos.dtype, device=pos.device)
    if heading0 is not None:
        h0 = h0 + _t(heading0).to(pos.dtype)
    return torch.where(last >= 0, held, h0.unsqueeze(-1).expand_as(held))


def box_overlap(c1, h1, l1, w1, c2, h2, l2, w2) -> torch.Tensor:
    """True where two oriented rectangles intersect (separating-axis test), broadcast.

    Centres ``c`` ``(..., 2)``, headings ``h`` (radians, along the length), lengths ``l``
    and widths ``w`` ``(...)``. Two convex polygons are disjoint iff some edge normal
    separates their projections; a rectangle has two: the four axes of the pair are
    tested at once. Touching (equal projections' extents) is not an overlap.
    """
    c1, c2 = _t(c1), _t(c2)
    h1, h2, l1, l2, w1, w2 = (_t(a).to(c1.dtype) for a in (h1, h2, l1, l2, w1, w2))
    u1 = torch.stack([torch.cos(h1), torch.sin(h1)], -1)
    v1 = torch.stack([-torch.sin(h1), torch.cos(h1)], -1)
    u2 = torch.stack([torch.cos(h2), torch.sin(h2)], -1)
    v2 = torch.stack([-torch.sin(h2), torch.cos(h2)], -1)
    axes = torch.stack(torch.broadcast_tensors(u1, v1, u2, v2), -2)  # (..., 4, 2)

    def proj(a, b):  # |a . b| over the axes
        return (a * b.unsqueeze(-2)).sum(-1).abs()

    gap = proj(axes, c2 - c1)
    r1 = 0.5 * l1.unsqueeze(-1) * proj(axes, u1) + 0.5 * w1.unsqueeze(-1) * proj(axes, v1)
    r2 = 0.5 * l2.unsqueeze(-1) * proj(axes, u2) + 0.5 * w2.unsqueeze(-1) * proj(axes, v2)
    return (gap < r1 + r2).all(-1)


def overlap_rate_boxes(
    pred, probs, length, width, start=None, heading0=None, mask=None, min_step: float = 0.05
) -> torch.Tensor:
    """1.0 for samples whose most likely joint mode has two intersecting vehicle boxes.

    ``length``, ``width`` ``(B, N)`` (or ``(N,)``) metres; ``start`` ``(B, N, 2)`` and
    ``heading0`` ``(B, N)`` the agents' current positions and headings (the box heading at
    each step is the predicted direction of motion, :func:`motion_headings`). Batched over
    samples, agent pairs and steps.
    """
    pred, probs = _t(pred), _t(probs)
    if pred.ndim != 5 or pred.shape[-1] != 2:
        raise ValueError(f"pred: expected shape (B, M, N, T, 2), got {tuple(pred.shape)}")
    B, M, N = pred.shape[:3]
    if probs.shape != (B, M):
        raise ValueError(
            f"probs: expected joint probabilities of shape {(B, M)}, got {tuple(probs.shape)}"
        )
    size = []
    for name, v in (("length", length), ("width", width)):
        v = _t(v).to(pred.dtype)
        if v.shape not in ((N,), (B, N)):
            raise ValueError(f"{name}: expected shape {(B, N)} or {(N,)}, got {tuple(v.shape)}")
        size.append(v.expand(B, N)[:, :, None])  # (B, N, 1): broadcast over steps
    L, W = size
    if mask is None:
        mask = torch.ones(B, N, dtype=torch.bool, device=pred.device)
    best = pred[torch.arange(B), probs.argmax(dim=1)]  # (B, N, T, 2)
    hit, _ = box_hits(best, L[..., 0], W[..., 0], start, heading0, min_step)  # (B, N, N, T)
    eye = torch.eye(N, dtype=torch.bool, device=pred.device)
    pair = mask[:, :, None] & mask[:, None, :] & ~eye[None]
    return (hit.any(-1) & pair).flatten(1).any(-1).to(pred.dtype)


def box_hits(
    pos, length, width, start=None, heading0=None, min_step: float = 0.05, grow=0.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Which agents' boxes intersect at each step: ``(B, N, N, T)`` (symmetric, the diagonal
    True), and the box headings ``(B, N, T)`` (:func:`motion_headings`).

    ``pos`` ``(B, N, T, 2)`` one joint trajectory per sample; ``length``, ``width`` ``(B, N)``;
    ``start``, ``heading0`` as in :func:`overlap_rate_boxes`; ``grow`` (a number or
    ``(B, N, N, T)``) is added to every box's length and width (clearance by bisection).
    """
    pos = _t(pos)
    h = motion_headings(pos, start, heading0, min_step)
    L = _t(length).to(pos.dtype)[..., None]  # (B, N, 1): broadcast over steps
    W = _t(width).to(pos.dtype)[..., None]
    a, b = (slice(None), slice(None), None), (slice(None), None, slice(None))
    hit = box_overlap(
        pos[a], h[a], L[a] + grow, W[a] + grow, pos[b], h[b], L[b] + grow, W[b] + grow
    )
    return hit, h


def marginal_to_joint(pred, probs, mask=None):
    """Joint scenes from per-agent modes ordered by marginal probability.

    ``pred`` ``(B, M, N, T, 2)`` holds agent ``i``'s ``m``-th mode at ``[:, m, i]``;
    ``probs`` ``(B, N, M)``. Returns the reordered ``pred`` (joint mode ``m`` = every agent's
    ``m``-th most likely mode) and joint probabilities ``(B, M)`` (products, normalized).
    ``mask`` ``(B, N)``: only the agents of ``mask`` enter the products (a padded agent's
    probabilities count as 1).
    """
    pred, probs = _t(pred), _t(probs)
    B, M, N = pred.shape[:3]
    if probs.shape != (B, N, M):
        raise ValueError(
            f"probs: expected marginal probabilities of shape {(B, N, M)}, got {tuple(probs.shape)}"
        )
    if mask is not None:
        m = _t(mask).to(device=probs.device, dtype=torch.bool)[..., None]
        probs = torch.where(m, probs, torch.ones((), dtype=probs.dtype, device=probs.device))
    order = probs.argsort(dim=-1, descending=True)  # (B, N, M)
    idx = order.permute(0, 2, 1)  # (B, M, N): mode of agent n in joint mode m
    joint = torch.gather(pred, 1, idx[..., None, None].expand(B, M, N, *pred.shape[3:]))
    p = torch.gather(probs, 2, order).prod(dim=1)  # (B, M)
    return joint, p / p.sum(-1, keepdim=True).clamp_min(1e-12)


def focal_errors(pred, gt, probs, focal: int = 0, mask=None) -> dict[str, torch.Tensor]:
    """The focal agent's errors per sample (module docstring): :data:`FOCAL_METRICS`, each
    ``(B,)`` metres. ``probs`` joint ``(B, M)`` (top-1: the scene probability's argmax) or
    marginal ``(B, N, M)`` (top-1: the focal agent's own argmax); ``pred`` ``(B, M, N, T, 2)``
    holds the modes as the model gives them (for marginal models agent ``i``'s ``m``-th mode
    at ``[:, m, i]``). ``mask`` ``(B, N)``: NaN where the focal slot is a pad."""
    pred, gt, mask = _check(pred, gt, mask)
    probs = _t(probs)
    B, M, N = pred.shape[:3]
    if isinstance(focal, bool) or not isinstance(focal, int) or not 0 <= focal < N:
        raise ValueError(f"focal: expected an agent slot in [0, {N}), got {focal!r}")
    if probs.shape == (B, N, M):
        top = probs[:, focal].argmax(dim=-1)
    elif probs.shape == (B, M):
        top = probs.argmax(dim=-1)
    else:
        raise ValueError(
            f"probs: expected shape {(B, M)} (joint) or {(B, N, M)} (marginal), "
            f"got {tuple(probs.shape)}"
        )
    d = torch.linalg.vector_norm(pred[:, :, focal] - gt[:, None, focal], dim=-1)  # (B, M, T)
    ade, fde = d.mean(-1), d[..., -1]
    rows = torch.arange(B, device=pred.device)
    out = {
        "ADE_focal": ade.min(dim=1).values,
        "FDE_focal": fde.min(dim=1).values,
        "ADE_focal_top1": ade[rows, top.to(pred.device)],
        "FDE_focal_top1": fde[rows, top.to(pred.device)],
    }
    real = mask[:, focal].to(pred.device)
    nan = torch.full((), math.nan, dtype=ade.dtype, device=ade.device)
    return {k: torch.where(real, v, nan) for k, v in out.items()}


def all_metrics(
    pred, gt, probs, radii, mask=None, boxes=None, focal: int | None = None
) -> dict[str, torch.Tensor]:
    """Every metric per sample; ``probs`` joint ``(B, M)`` or marginal ``(B, N, M)``.

    ``radii`` ``(N,)`` or ``(B, N)``: the circles of the overlap rate. ``boxes``: None
    (``OR`` with the circles of ``radii``), or a dict with ``length`` and ``width``
    ``(B, N)`` and optionally ``start`` ``(B, N, 2)`` and ``heading0`` ``(B, N)``
    (:func:`overlap_rate_boxes`): then ``OR`` is the box overlap rate and ``OR_circle``
    the circle one. ``focal``: an agent slot: adds :data:`FOCAL_METRICS`
    (:func:`focal_errors`).
    """
    probs = _t(probs)
    marginal = {"minADE": min_ade(pred, gt, mask), "minFDE": min_fde(pred, gt, mask)}
    if focal is not None:
        marginal.update(focal_errors(pred, gt, probs, focal, mask))
    if probs.ndim == 3:
        pred, probs = marginal_to_joint(pred, probs, mask)
    out = {
        **marginal,
        "minSADE": min_sade(pred, gt, mask),
        "minSFDE": min_sfde(pred, gt, mask),
        "OR": overlap_rate(pred, probs, radii, mask),
    }
    if boxes is not None:
        out["OR_circle"] = out["OR"]
        out["OR"] = overlap_rate_boxes(pred, probs, mask=mask, **boxes)
    return out
