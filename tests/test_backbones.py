"""Backbones (V-LSTM, VIBES, HiVT-M): shapes, gradients, masks that cannot leak, HiVT-M's
frame invariance, config validation, one training step per model kind and backbone."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from epo_casadi.errors import SpecError
from learning.backbones import BACKBONES, Encoder
from learning.data import SceneDataset
from learning.models import ModelConfig, build_model
from learning.train import PAPER_LOSS_WEIGHTS, compute_loss
from tests.test_models import TINY, synthetic_dataset

KINDS = ("epo", "sc", "vlstm", "tgl")


def _scene(B=3, H=5, N=4, L=3, P=6, seed=0) -> dict:
    g = torch.Generator().manual_seed(seed)
    hist = torch.zeros(B, H + 1, N, 4)
    hist[..., :2] = torch.randn(B, 1, N, 2, generator=g) * 5 + torch.cumsum(
        torch.randn(B, H + 1, N, 2, generator=g) * 0.5, 1
    )
    hist[..., 2] = 1.0
    hist[..., 3] = torch.randn(B, 1, N, generator=g)
    return {
        "history": hist,
        "lanes": torch.randn(B, L, P, 2, generator=g) * 5,
        "lanes_mask": torch.tensor([True, True, False]).expand(B, L).clone(),
    }


def _encoder(backbone: str) -> Encoder:
    torch.manual_seed(0)
    return Encoder(ModelConfig(backbone=backbone, **TINY)).eval()


@pytest.mark.parametrize("backbone", list(BACKBONES))
def test_forward_backward_shapes(backbone):
    enc = _encoder(backbone).train()
    sc = _scene()
    sc["history"].requires_grad_()
    z = enc(sc)
    assert z.shape == (3, 4, TINY["global_width"])
    z.square().sum().backward()
    assert torch.isfinite(sc["history"].grad).all() and sc["history"].grad.abs().sum() > 0
    for name, p in enc.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


@pytest.mark.parametrize("backbone", list(BACKBONES))
def test_masked_agents_steps_and_lanes_cannot_change_other_outputs(backbone):
    enc = _encoder(backbone)
    sc = _scene()
    sc["agents_mask"] = torch.tensor([True, True, False, True]).expand(3, 4).clone()
    hm = torch.ones(3, 6, 4, dtype=torch.bool)
    hm[:, :2, 1] = False  # agent 1's two oldest steps unobserved
    sc["history_mask"] = hm
    with torch.no_grad():
        z = enc(sc)
        other = {k: v.clone() for k, v in sc.items()}
        other["history"][:, :, 2] += torch.randn(3, 6, 4) * 10  # the absent agent
        other["history"][:, :2, 1, :2] += 7.0  # agent 1's masked steps
        other["lanes"][:, 2] += 9.0  # the masked lane
        z2 = enc(other)
    assert torch.equal(z[:, 2], torch.zeros_like(z[:, 2]))  # absent agent: zero feature
    torch.testing.assert_close(z2, z, rtol=0, atol=1e-5)
    # ...while an observed step of agent 1 does change the features
    with torch.no_grad():
        other["history"][:, 3, 1, :2] += 1.0
        assert (enc(other) - z).abs().max() > 1e-3


def test_all_true_masks_change_nothing():
    """Masks of all True give V-LSTM and VIBES the outputs of the unmasked encoders (to
    rounding: the origin is then a weighted mean)."""
    for backbone in ("vlstm", "vibes"):
        enc = _encoder(backbone)
        sc = _scene()
        with torch.no_grad():
            z = enc(sc)
            sc["agents_mask"] = torch.ones(3, 4, dtype=torch.bool)
            sc["history_mask"] = torch.ones(3, 6, 4, dtype=torch.bool)
            torch.testing.assert_close(enc(sc), z, rtol=0, atol=1e-6)


def test_hivt_local_encoding_is_invariant_to_rotating_and_translating_the_scene():
    enc = _encoder("hivt")
    sc = _scene()
    ang, shift = 0.9, torch.tensor([12.0, -4.0])
    R = torch.tensor([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
    moved = {k: v.clone() for k, v in sc.items()}
    moved["history"][..., :2] = sc["history"][..., :2] @ R.T + shift
    moved["history"][..., 3] = sc["history"][..., 3] + ang
    moved["lanes"] = sc["lanes"] @ R.T + shift
    with torch.no_grad():
        theta = sc["history"][:, -1, :, 3]
        loc = enc.local(sc["history"][..., :2], theta)
        loc2 = enc.local(moved["history"][..., :2], theta + ang)
        torch.testing.assert_close(loc2, loc, rtol=0, atol=1e-4)
        # as designed (paper App. F.1): pose and lanes enter in the scene frame, so the
        # global features see the rotation
        assert (enc(moved) - enc(sc)).abs().max() > 1e-3
        # a pure translation: the scene frame is centred on the agents, so nothing changes
        tr = {k: v.clone() for k, v in sc.items()}
        tr["history"][..., :2] += shift
        tr["lanes"] = tr["lanes"] + shift
        torch.testing.assert_close(enc(tr), enc(sc), rtol=0, atol=1e-4)


def test_backbone_config_is_validated():
    with pytest.raises(SpecError, match="model.backbone.*'hivt'"):
        ModelConfig(backbone="transformer")
    with pytest.raises(SpecError, match="model.heads.*hist_width 6"):
        ModelConfig(backbone="hivt", hist_width=6, heads=4, global_width=16)
    with pytest.raises(SpecError, match="model.kind"):
        ModelConfig(kind="tgl2")


@pytest.fixture(scope="module")
def tiny_rpi():
    with SceneDataset(synthetic_dataset(), "train") as ds:
        batch, game = ds.batch(np.arange(4)), ds.game
    # the synthetic RPI agents start at rest (constant histories): let them arrive moving,
    # so that every history-encoder weight sees a non-zero input (current states unchanged)
    H1 = batch["history"].shape[1]
    back = torch.arange(H1 - 1, -1, -1, dtype=torch.float32)[None, :, None]
    batch["history"][..., 0] -= 0.2 * back
    batch["history"][..., 1] -= 0.1 * back
    return batch, game


@pytest.mark.parametrize("backbone", list(BACKBONES))
@pytest.mark.parametrize("kind", KINDS)
def test_one_training_step_per_model_and_backbone(kind, backbone, tiny_rpi):
    batch, game = tiny_rpi
    torch.manual_seed(0)
    model = build_model(ModelConfig(kind=kind, backbone=backbone, **TINY), game)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    before = {n: p.detach().clone() for n, p in model.encoder.named_parameters()}
    parts = compute_loss(kind, model(batch), batch["gt"], PAPER_LOSS_WEIGHTS[kind])
    assert torch.isfinite(parts["loss"])
    opt.zero_grad()
    parts["loss"].backward()
    opt.step()
    assert all(torch.isfinite(p).all() for p in model.parameters())
    # the history encoder and the agent projection learn (RPI has no lanes: the map
    # stage of VIBES / HiVT-M gets no gradient there)
    hist = [n for n in before if n.split(".")[0] in ("lstm", "local", "pose", "agent_proj")]
    assert hist
    frozen = [
        n for n, p in model.encoder.named_parameters() if n in hist and torch.equal(before[n], p)
    ]
    assert not frozen, frozen
