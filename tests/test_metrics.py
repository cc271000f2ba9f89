"""Metrics on hand-made examples whose values are computed by hand in the comments."""

import pytest
import torch

from learning.metrics import (
    all_metrics,
    marginal_to_joint,
    min_ade,
    min_fde,
    min_sade,
    min_sfde,
    overlap_rate,
)


def _example():
    gt = torch.tensor([[[[0.0, 0.0], [1.0, 0.0]], [[0.0, 5.0], [0.0, 4.0]]]])  # (1, N=2, T=2, 2)
    m0 = torch.tensor(
        [[[0.0, 1.0], [1.0, 1.0]], [[0.0, 5.0], [0.0, 4.0]]]
    )  # agent 0 off by 1, agent 1 exact
    m1 = torch.tensor(
        [[[0.0, 0.0], [1.0, 0.0]], [[3.0, 5.0], [4.0, 4.0]]]
    )  # agent 0 exact, agent 1 off by 3, 4
    return torch.stack([m0, m1])[None], gt  # pred (1, M=2, N=2, T=2, 2)


def test_marginal_metrics_pick_the_best_mode_per_agent():
    pred, gt = _example()
    assert min_ade(pred, gt).item() == pytest.approx(0.0)  # each agent has an exact mode
    assert min_fde(pred, gt).item() == pytest.approx(0.0)


def test_joint_metrics_pick_the_best_scene():
    pred, gt = _example()
    # scene 0: mean(1, 1, 0, 0) = 0.5; scene 1: mean(0, 0, 3, 4) = 1.75
    assert min_sade(pred, gt).item() == pytest.approx(0.5)
    # final step: scene 0: mean(1, 0) = 0.5; scene 1: mean(0, 4) = 2
    assert min_sfde(pred, gt).item() == pytest.approx(0.5)


def test_mask_drops_agents():
    pred, gt = _example()
    mask = torch.tensor([[True, False]])
    # only agent 0: scene 1 is exact
    assert min_sade(pred, gt, mask).item() == pytest.approx(0.0)
    assert min_ade(pred, gt, mask).item() == pytest.approx(0.0)
    mask = torch.tensor([[False, True]])
    assert min_sfde(pred, gt, mask).item() == pytest.approx(0.0)


def test_overlap_rate_uses_the_most_likely_scene():
    pred, gt = _example()
    pred = pred.clone()
    pred[0, 1, 1, 0] = torch.tensor([0.3, 0.0])  # scene 1: agent 1 starts 0.3 m from agent 0
    radii = torch.tensor([0.25, 0.25])  # 0.3 < 0.5: overlap in scene 1 only
    assert overlap_rate(pred, torch.tensor([[0.3, 0.7]]), radii).item() == 1.0
    assert overlap_rate(pred, torch.tensor([[0.7, 0.3]]), radii).item() == 0.0
    assert overlap_rate(pred, torch.tensor([[0.3, 0.7]]), torch.tensor([0.1, 0.1])).item() == 0.0


def test_marginal_to_joint_orders_by_probability():
    pred, gt = _example()
    probs = torch.tensor([[[0.2, 0.8], [0.6, 0.4]]])  # agent 0 prefers mode 1, agent 1 mode 0
    joint, p = marginal_to_joint(pred, probs)
    torch.testing.assert_close(joint[0, 0, 0], pred[0, 1, 0])
    torch.testing.assert_close(joint[0, 0, 1], pred[0, 0, 1])
    torch.testing.assert_close(p, torch.tensor([[0.48 / 0.56, 0.08 / 0.56]]))
    # the most likely joint scene is exact for both agents
    assert min_sade(joint[:, :1], gt).item() == pytest.approx(0.0)
    m = all_metrics(pred, gt, probs, torch.tensor([0.25, 0.25]))
    assert m["minSADE"].item() == pytest.approx(0.0) and m["minADE"].item() == pytest.approx(0.0)


def test_shape_errors_name_the_input():
    pred, gt = _example()
    with pytest.raises(ValueError, match="gt"):
        min_ade(pred, gt[:, :1])
    with pytest.raises(ValueError, match="pred"):
        min_ade(pred[0], gt)
    with pytest.raises(ValueError, match="probs"):
        overlap_rate(pred, torch.ones(1, 3), torch.ones(2))
