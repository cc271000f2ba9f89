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


# --------------------------------------------------------------------------------------
# Non-zero values by hand: T = 3, different errors per step, agents preferring different modes
# --------------------------------------------------------------------------------------
_UNIT = torch.tensor(
    [0.6, 0.8], dtype=torch.float64
)  # a unit vector off the axes: the norm is Euclidean


def _errors_example():
    """(pred, gt) with known per-step errors ``d[m][i]`` (metres) along ``_UNIT``.

    mode 0: agent 0 ``(1, 2, 4)`` (mean 7/3, final 4), agent 1 ``(3, 0, 0)`` (mean 1, final 0);
    mode 1: agent 0 ``(2, 2, 2)`` (mean 2, final 2),   agent 1 ``(0, 1, 5)`` (mean 2, final 5).
    """
    gt = torch.tensor(
        [[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], [[0.0, 5.0], [0.0, 4.0], [0.0, 3.0]]],
        dtype=torch.float64,
    )[None]  # (1, N=2, T=3, 2)
    d = torch.tensor(
        [[[1.0, 2.0, 4.0], [3.0, 0.0, 0.0]], [[2.0, 2.0, 2.0], [0.0, 1.0, 5.0]]],
        dtype=torch.float64,
    )  # (M, N, T)
    pred = gt[:, None] + d[None, ..., None] * _UNIT.to(torch.float64)
    return pred, gt


def test_marginal_metrics_by_hand():
    pred, gt = _errors_example()
    # agent 0: min(7/3, 2) = 2 (mode 1); agent 1: min(1, 2) = 1 (mode 0)
    assert min_ade(pred, gt).item() == pytest.approx(1.5, abs=1e-12)
    # final step: agent 0: min(4, 2) = 2; agent 1: min(0, 5) = 0 (step 0 would give 0.5)
    assert min_fde(pred, gt).item() == pytest.approx(1.0, abs=1e-12)


def test_joint_metrics_by_hand():
    pred, gt = _errors_example()
    # scene 0: mean(7/3, 1) = 5/3; scene 1: mean(2, 2) = 2
    assert min_sade(pred, gt).item() == pytest.approx(5 / 3, abs=1e-12)
    # scene 0: mean(4, 0) = 2; scene 1: mean(2, 5) = 3.5
    assert min_sfde(pred, gt).item() == pytest.approx(2.0, abs=1e-12)


def test_masked_metrics_by_hand_per_sample():
    pred, gt = _errors_example()
    pred, gt = pred.repeat(2, 1, 1, 1, 1), gt.repeat(2, 1, 1, 1)
    mask = torch.tensor([[True, False], [False, True]])  # sample 0: agent 0, sample 1: agent 1
    expect = {
        min_ade: [2.0, 1.0],
        min_fde: [2.0, 0.0],
        min_sade: [2.0, 1.0],  # min(7/3, 2); min(1, 2)
        min_sfde: [2.0, 0.0],  # min(4, 2); min(0, 5)
    }
    for fn, values in expect.items():
        torch.testing.assert_close(
            fn(pred, gt, mask), torch.tensor(values, dtype=torch.float64), rtol=0, atol=1e-12
        )


def test_all_metrics_joint_and_marginal_by_hand():
    pred, gt = _errors_example()
    radii = torch.tensor([0.25, 0.25])
    m = all_metrics(pred, gt, torch.tensor([[0.9, 0.1]]), radii)
    expect = {"minADE": 1.5, "minFDE": 1.0, "minSADE": 5 / 3, "minSFDE": 2.0, "OR": 0.0}
    assert {k: pytest.approx(v, abs=1e-12) for k, v in expect.items()} == {
        k: v.item() for k, v in m.items()
    }
    # marginal probabilities: agent 0 prefers mode 1, agent 1 mode 0: joint scene 0 takes
    # agent 0's mode 1 and agent 1's mode 0: errors (2, 2, 2) and (3, 0, 0): SADE 1.5, SFDE 1
    m = all_metrics(pred, gt, torch.tensor([[[0.3, 0.7], [0.8, 0.2]]]), radii)
    assert m["minSADE"].item() == pytest.approx(1.5, abs=1e-12)
    assert m["minSFDE"].item() == pytest.approx(1.0, abs=1e-12)
    assert m["minADE"].item() == pytest.approx(1.5, abs=1e-12)  # marginal: order-free


def _three_agents(gap01=3.0, gap02=0.3):
    """Scene of three agents at T = 3 steps; agent 2 is ``gap02`` from agent 0 at step 1
    only, agent 1 is ``gap01`` from agent 0 throughout. One mode."""
    base = torch.zeros(3, 3, 2, dtype=torch.float64)
    base[0, :, 0] = torch.tensor([0.0, 1.0, 2.0])
    base[1] = base[0] + torch.tensor([0.0, gap01], dtype=torch.float64)
    base[2] = base[0] + torch.tensor([0.0, 10.0], dtype=torch.float64)
    base[2, 1] = base[0, 1] + torch.tensor([gap02, 0.0], dtype=torch.float64)
    return base[None, None]  # (B=1, M=1, N=3, T=3, 2)


def test_overlap_rate_mask_matters():
    pred = _three_agents()
    probs = torch.ones(1, 1)
    radii = torch.tensor([0.25, 0.25, 0.25])
    assert overlap_rate(pred, probs, radii).item() == 1.0  # 0 and 2 overlap at step 1 only
    assert overlap_rate(pred, probs, radii, torch.tensor([[True, True, False]])).item() == 0.0
    assert overlap_rate(pred, probs, radii, torch.tensor([[True, False, True]])).item() == 1.0
    assert overlap_rate(pred, probs, radii, torch.tensor([[False, True, True]])).item() == 0.0
    # per-sample radii (B, N): only agent 2's radius shrinks below the gap
    assert overlap_rate(pred, probs, torch.tensor([[0.25, 0.25, 0.04]])).item() == 0.0
    # an overlap between two kept agents counts, whatever the masked one does
    pred = _three_agents(gap01=0.4, gap02=5.0)
    assert overlap_rate(pred, probs, radii, torch.tensor([[True, True, False]])).item() == 1.0


def test_overlap_is_strict_at_touching_circles():
    probs, radii = torch.ones(1, 1), torch.tensor([0.25, 0.25, 0.25])
    touching = overlap_rate(_three_agents(gap02=0.5), probs, radii)  # dist == r_0 + r_2
    assert touching.item() == 0.0
    assert overlap_rate(_three_agents(gap02=0.5 - 1e-9), probs, radii).item() == 1.0


# --------------------------------------------------------------------------------------
# Properties (hypothesis): invariances and orderings of the metrics
# --------------------------------------------------------------------------------------
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_SETTINGS = settings(max_examples=25, deadline=None, derandomize=True, database=None)


@st.composite
def scenes(draw):
    B, M, N, T = (draw(st.integers(1, n)) for n in (3, 4, 3, 5))
    seed = draw(st.integers(0, 2**31 - 1))
    g = torch.Generator().manual_seed(seed)
    pred = torch.randn(B, M, N, T, 2, generator=g, dtype=torch.float64) * 3
    gt = torch.randn(B, N, T, 2, generator=g, dtype=torch.float64) * 3
    mask = torch.rand(B, N, generator=g) < 0.7
    mask[:, 0] = True  # at least one agent counts
    probs = torch.softmax(torch.randn(B, M, generator=g, dtype=torch.float64), -1)
    return pred, gt, mask, probs


def _distance_metrics(pred, gt, mask):
    return torch.stack([f(pred, gt, mask) for f in (min_ade, min_fde, min_sade, min_sfde)])


@_SETTINGS
@given(scenes(), st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(-3.2, 3.2))
def test_metrics_invariant_under_rigid_motion(scene, tx, ty, angle):
    pred, gt, mask, probs = scene
    a = torch.tensor(angle, dtype=torch.float64)
    c, s = torch.cos(a), torch.sin(a)
    R = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    shift = torch.tensor([tx, ty], dtype=torch.float64)
    pred2, gt2 = pred @ R.T + shift, gt @ R.T + shift
    torch.testing.assert_close(
        _distance_metrics(pred2, gt2, mask), _distance_metrics(pred, gt, mask), rtol=1e-9, atol=1e-9
    )
    radii = torch.full((pred.shape[2],), 0.8)
    assert torch.equal(
        overlap_rate(pred2, probs, radii, mask), overlap_rate(pred, probs, radii, mask)
    ) or _near_touching(pred, probs, radii)


def _near_touching(pred, probs, radii):
    """True when some pair's distance is within round-off of r_i + r_j (OR may flip)."""
    best = pred[torch.arange(pred.shape[0]), probs.argmax(1)]
    d = torch.linalg.vector_norm(best[:, :, None] - best[:, None, :], dim=-1)
    rr = radii[:, None] + radii[None, :]
    return bool(((d - rr[None, :, :, None]).abs() < 1e-6).any())


@_SETTINGS
@given(scenes(), st.randoms(use_true_random=False))
def test_metrics_invariant_under_mode_and_agent_permutation(scene, rnd):
    pred, gt, mask, probs = scene
    M, N = pred.shape[1], pred.shape[2]
    pm = torch.tensor(rnd.sample(range(M), M))
    pn = torch.tensor(rnd.sample(range(N), N))
    ref = _distance_metrics(pred, gt, mask)
    torch.testing.assert_close(_distance_metrics(pred[:, pm], gt, mask), ref)
    torch.testing.assert_close(
        _distance_metrics(pred[:, :, pn], gt[:, pn], mask[:, pn]), ref, rtol=1e-12, atol=1e-12
    )
    radii = torch.linspace(0.2, 1.5, N, dtype=torch.float64)
    orate = overlap_rate(pred, probs, radii, mask)
    assert torch.equal(overlap_rate(pred[:, pm], probs[:, pm], radii, mask), orate)
    assert torch.equal(overlap_rate(pred[:, :, pn], probs, radii[pn], mask[:, pn]), orate)


@_SETTINGS
@given(scenes(), st.floats(0.0, 50.0))
def test_metric_orderings_and_scaling(scene, scale):
    pred, gt, mask, _ = scene
    ade, fde, sade, sfde = _distance_metrics(pred, gt, mask)
    # the joint minimum is over whole scenes: never below the per-agent minimum
    assert (sade >= ade - 1e-12).all() and (sfde >= fde - 1e-12).all()
    # with one mode there is nothing to choose: marginal == joint
    one = _distance_metrics(pred[:, :1], gt, mask)
    torch.testing.assert_close(one[0], one[2])
    torch.testing.assert_close(one[1], one[3])
    # distances are homogeneous of degree one
    torch.testing.assert_close(
        _distance_metrics(pred * scale, gt * scale, mask),
        scale * torch.stack([ade, fde, sade, sfde]),
        rtol=1e-9,
        atol=1e-9,
    )
    # a perfect mode added anywhere makes every distance metric 0
    perfect = torch.cat([pred, gt[:, None]], dim=1)
    assert (_distance_metrics(perfect, gt, mask) == 0).all()


def test_marginal_to_joint_batch_probabilities():
    """Each sample's joint probabilities are normalized over its own modes."""
    pred, _ = _example()
    pred = pred.repeat(3, 1, 1, 1, 1)
    probs = torch.tensor(
        [[[0.2, 0.8], [0.6, 0.4]], [[0.5, 0.5], [0.9, 0.1]], [[0.7, 0.3], [0.3, 0.7]]]
    )
    _, p = marginal_to_joint(pred, probs)
    # sorted products: (0.8 0.6, 0.2 0.4), (0.5 0.9, 0.5 0.1), (0.7 0.7, 0.3 0.3)
    raw = torch.tensor([[0.48, 0.08], [0.45, 0.05], [0.49, 0.09]])
    torch.testing.assert_close(p, raw / raw.sum(1, keepdim=True))
