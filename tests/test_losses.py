"""Training objectives (learning/losses.py) on hand-made examples computed by hand.

Each example has modes whose errors differ so that the winning mode, the imitation value,
the cross-entropy target and the masking are all pinned down by numbers in the comments.
"""

from __future__ import annotations

import math

import pytest
import torch

from learning.losses import (
    LossWeights,
    goal_classification_loss,
    goal_loss,
    goal_regression_loss,
    marginal_loss,
    scene_loss,
)

LN = math.log
F64 = torch.float64


def _example():
    """pos (B=1, M=2, N=2, T=2, 2) and gt (1, 2, 2, 2) with offsets pos - gt:

    mode 0: agent 0 (1, 0), (0, 2)  -> squared 1, 4 (mean 2.5), norms 1, 2 (mean 1.5)
            agent 1 (0, 0), (0, 1)  -> squared 0, 1 (mean 0.5), norms 0, 1 (mean 0.5)
    mode 1: agent 0 (0, 0), (0, 0)  -> 0
            agent 1 (2, 0), (0, 2)  -> squared 4, 4 (mean 4),   norms 2, 2 (mean 2)
    Scene values (mean over agents of the squared means): mode 0 1.5, mode 1 2.0.
    """
    gt = torch.tensor([[[[0.0, 0.0], [1.0, 0.0]], [[3.0, 3.0], [3.0, 4.0]]]], dtype=F64)
    off = torch.tensor(
        [
            [[[1.0, 0.0], [0.0, 2.0]], [[0.0, 0.0], [0.0, 1.0]]],
            [[[0.0, 0.0], [0.0, 0.0]], [[2.0, 0.0], [0.0, 2.0]]],
        ],
        dtype=F64,
    )
    return gt[:, None] + off[None], gt


def test_scene_loss_picks_the_closest_scene_and_its_ce_target():
    pos, gt = _example()
    logits = torch.tensor([[0.0, LN(3.0)]], dtype=F64)  # softmax (1/4, 3/4)
    out = scene_loss(pos, logits, gt)
    assert out["imitation"].item() == pytest.approx(1.5, abs=1e-12)  # mode 0, not 2.0
    assert out["probability"].item() == pytest.approx(LN(4.0), abs=1e-12)  # target: mode 0
    assert out["loss"].item() == pytest.approx(1.5 + 0.1 * LN(4.0), abs=1e-12)
    w = LossWeights(imitation=2.0, goal=7.0, probability=0.5)  # the goal weight plays no part
    assert scene_loss(pos, logits, gt, w)["loss"].item() == pytest.approx(
        3.0 + 0.5 * LN(4.0), abs=1e-12
    )


def test_scene_loss_mask_changes_the_winner():
    pos, gt = _example()
    logits = torch.tensor([[0.0, LN(3.0)]], dtype=F64)
    # only agent 0: mode 0 2.5, mode 1 0: mode 1 wins, CE target 1: -ln(3/4)
    out = scene_loss(pos, logits, gt, mask=torch.tensor([[True, False]]))
    assert out["imitation"].item() == pytest.approx(0.0, abs=1e-12)
    assert out["probability"].item() == pytest.approx(LN(4 / 3), abs=1e-12)


def test_scene_loss_batch_mean_and_gradient_only_through_the_winner():
    pos, gt = _example()
    # sample 1: the modes swapped, so its winner is mode 1; values are batch means
    pos2 = torch.cat([pos, pos.flip(1)]).requires_grad_()
    gt2 = torch.cat([gt, gt])
    logits = torch.tensor([[0.0, LN(3.0)], [0.0, LN(3.0)]], dtype=F64)
    out = scene_loss(pos2, logits, gt2)
    assert out["imitation"].item() == pytest.approx(1.5, abs=1e-12)
    assert out["probability"].item() == pytest.approx((LN(4.0) + LN(4 / 3)) / 2, abs=1e-12)
    (g,) = torch.autograd.grad(out["imitation"], pos2)
    assert g[0, 1].abs().sum() == 0 and g[1, 0].abs().sum() == 0  # losing modes get nothing
    assert g[0, 0].abs().sum() > 0 and g[1, 1].abs().sum() > 0


def test_marginal_loss_per_agent_mode_and_targets():
    pos, gt = _example()
    # agent 0 logits (0, ln 3): target mode 1 -> CE ln(4/3); agent 1 logits (0, 0): target
    # mode 0 -> CE ln 2. ADE (norms): agent 0 best 0 (mode 1), agent 1 best 0.5 (mode 0).
    logits = torch.tensor([[[0.0, LN(3.0)], [0.0, 0.0]]], dtype=F64)
    out = marginal_loss(pos, logits, gt)
    assert out["imitation"].item() == pytest.approx(0.25, abs=1e-12)
    cls = (LN(4 / 3) + LN(2.0)) / 2
    assert out["probability"].item() == pytest.approx(cls, abs=1e-12)
    assert out["loss"].item() == pytest.approx(0.25 + cls, abs=1e-12)  # default lambda_3 = 1
    masked = marginal_loss(pos, logits, gt, mask=torch.tensor([[False, True]]))
    assert masked["imitation"].item() == pytest.approx(0.5, abs=1e-12)
    assert masked["probability"].item() == pytest.approx(LN(2.0), abs=1e-12)


def test_goal_classification_target_and_candidate_mask():
    cands = torch.tensor([[[[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]]] * 2], dtype=F64)  # (1, 2, 3, 2)
    final = torch.tensor([[[0.9, 0.1], [4.0, 4.5]]], dtype=F64)  # nearest: 1 and 2
    logits = torch.tensor([[[LN(2.0), 0.0, 0.0]] * 2], dtype=F64)  # softmax (1/2, 1/4, 1/4)
    assert goal_classification_loss(logits, cands, final).item() == pytest.approx(
        LN(4.0), abs=1e-12
    )
    # candidate 1 masked for agent 0: its target becomes candidate 0 (CE ln 2)
    cmask = torch.tensor([[[True, False, True], [True, True, True]]])
    assert goal_classification_loss(logits, cands, final, cmask).item() == pytest.approx(
        (LN(2.0) + LN(4.0)) / 2, abs=1e-12
    )
    agent_mask = torch.tensor([[True, False]])
    assert goal_classification_loss(logits, cands, final, cmask, agent_mask).item() == (
        pytest.approx(LN(2.0), abs=1e-12)
    )


def test_goal_regression_and_dispatch():
    final = torch.tensor([[[1.0, 2.0], [-3.0, 0.5]]], dtype=F64)  # (B=1, N=2, 2)
    offsets = torch.tensor(
        [[[[1.0, 0.0], [0.0, 3.0]], [[2.0, 0.0], [0.0, 0.0]]]], dtype=F64
    )  # (B=1, M=2, N=2, 2); squared errors: mode 0 (1, 9), mode 1 (4, 0)
    goals = final[:, None] + offsets
    assert goal_regression_loss(goals, final).item() == pytest.approx(2.0, abs=1e-12)
    assert goal_regression_loss(goals, final, torch.tensor([[True, False]])).item() == (
        pytest.approx(1.0, abs=1e-12)
    )
    gt = torch.zeros(1, 2, 5, 2, dtype=F64)
    gt[:, :, -1] = final  # goal_loss reads the last step of gt
    gt[:, :, :-1] = 9.0
    assert goal_loss({"decoded_goals": False, "goals": goals}, gt) is None
    assert goal_loss({"goals": goals}, gt) is None
    assert goal_loss({"decoded_goals": True, "goals": goals}, gt).item() == pytest.approx(2.0)
    cands = torch.tensor([[[[0.0, 0.0], [9.0, 9.0]]] * 2], dtype=F64)
    out = {
        "decoded_goals": True,
        "goals": goals,
        "goal_logits": torch.zeros(1, 2, 2, dtype=F64),
        "goal_candidates": cands,
    }
    assert goal_loss(out, gt).item() == pytest.approx(LN(2.0), abs=1e-12)


def test_loss_weight_defaults_are_the_papers():
    """lambda_1, lambda_2, lambda_3 = 1, 0.1, 0.1 (paper Sec. 4.3); marginal: lambda_3 = 1."""
    w = LossWeights()
    assert (w.imitation, w.goal, w.probability) == (1.0, 0.1, 0.1)


def test_masked_means_count_every_kept_agent_of_the_batch():
    pos, gt = _example()
    pos2, gt2 = torch.cat([pos, pos]), torch.cat([gt, gt])
    logits = torch.tensor([[[0.0, LN(3.0)], [0.0, 0.0]]] * 2, dtype=F64)
    mask = torch.tensor([[True, True], [False, True]])  # 3 kept (sample, agent) entries
    out = marginal_loss(pos2, logits, gt2, mask=mask)
    # ADE of the closest mode: agent 0 -> 0, agent 1 -> 0.5; kept: 0, 0.5, 0.5
    assert out["imitation"].item() == pytest.approx(1.0 / 3, abs=1e-12)
    cls = (LN(4 / 3) + 2 * LN(2.0)) / 3
    assert out["probability"].item() == pytest.approx(cls, abs=1e-12)


def test_marginal_loss_with_more_modes_than_agents():
    """M = 3 modes, N = 2 agents (the mode and agent axes cannot be confused): a third mode
    10 m off changes nothing."""
    pos, gt = _example()
    pos3 = torch.cat([pos, pos[:, :1] + 10.0], dim=1)
    logits = torch.tensor([[[0.0, LN(3.0), -50.0], [0.0, 0.0, -50.0]]], dtype=F64)
    out = marginal_loss(pos3, logits, gt)
    assert out["imitation"].item() == pytest.approx(0.25, abs=1e-12)
    assert out["probability"].item() == pytest.approx((LN(4 / 3) + LN(2.0)) / 2, abs=1e-12)
    scene = scene_loss(pos3, logits[:, 0], gt)
    assert scene["imitation"].item() == pytest.approx(1.5, abs=1e-12)
