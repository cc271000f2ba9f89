"""The SDV's strategy of the most likely mode (paper Sec. 4.3): selection, rollout, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from epo_casadi.errors import SpecError
from learning import plan, sdv_strategy
from learning.models import ModelConfig, build_model
from tests.test_models import TINY, scene_batch


def _unicycle(x0: np.ndarray, U: np.ndarray, dt: float) -> np.ndarray:
    """Hand-written explicit Euler unicycle (paper App. F.2), one step at a time."""
    x, out = x0.astype(np.float64).copy(), []
    for a, w in U:
        px, py, v, th = x
        x = np.array([px + dt * v * np.cos(th), py + dt * v * np.sin(th), v + dt * a, th + dt * w])
        out.append(x)
    return np.array(out)


def test_the_most_likely_mode_is_selected():
    B, M, N, K = 3, 2, 2, 4
    U = torch.arange(B * M * N * K * 2, dtype=torch.float32).reshape(B, M, N, K, 2)
    X = torch.randn(B, M, N, K, 4)
    logits = torch.tensor([[0.0, 5.0], [3.0, 0.0], [1.0, 1.0]])  # modes 1, 0, tie -> 0
    p = sdv_strategy({"controls": U, "states": X, "logits": logits}, agent=1)
    assert p.mode.tolist() == [1, 0, 0] and p.agent == 1
    for b, m in enumerate([1, 0, 0]):
        assert torch.equal(p.controls[b], U[b, m, 1]) and torch.equal(p.states[b], X[b, m, 1])
    e5 = float(np.exp(5.0))
    want = torch.tensor([e5 / (1 + e5), np.exp(3.0) / (1 + np.exp(3.0)), 0.5])
    torch.testing.assert_close(p.probability, want.float())
    assert torch.equal(p.first_control, U[torch.arange(B), p.mode, 1, 0])


@pytest.mark.parametrize("kind", ["epo", "sc"])
def test_the_plan_rolls_out_from_the_current_state(kind):
    batch, game = scene_batch(3)
    torch.manual_seed(0)
    model = build_model(ModelConfig(kind=kind, **TINY), game)
    model.train()
    p = plan(model, batch, agent=0)
    assert model.training  # restored
    assert p.controls.shape == (3, game.K, 2) and p.states.shape == (3, game.K, 4)
    x0 = batch["history"][:, -1, 0].numpy()
    for b in range(3):
        ref = _unicycle(x0[b], p.controls[b].double().numpy(), game.dt)
        np.testing.assert_allclose(p.states[b].double().numpy(), ref, atol=2e-4)
    with torch.no_grad():
        model.eval()
        out = model(batch)
    torch.testing.assert_close(p.controls, out["controls"][torch.arange(3), p.mode, 0])


def test_errors_name_the_field():
    batch, game = scene_batch(2)
    out = build_model(ModelConfig(kind="vlstm", **TINY), game)(batch)
    with pytest.raises(SpecError) as e:
        sdv_strategy(out)
    assert e.value.field == "model"
    U = torch.zeros(1, 2, 2, 3, 2)
    ok = {"controls": U, "states": torch.zeros(1, 2, 2, 3, 4), "logits": torch.zeros(1, 2)}
    for bad in (2, -1, True, 0.0):
        with pytest.raises(SpecError) as e:
            sdv_strategy(ok, agent=bad)
        assert e.value.field == "agent"
