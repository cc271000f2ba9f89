"""Goal decoder (paper Sec. 4.1, App. F.1, F.4): candidates, top-M goals, losses, datasets without goals."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from epo_casadi.errors import SpecError
from learning.data import SceneDataset
from learning.losses import goal_classification_loss, goal_regression_loss
from learning.models import ModelConfig, build_model, goal_candidates
from learning.show import show_predictions
from learning.train import PAPER_LOSS_WEIGHTS, TrainConfig, compute_loss, torch_threads, train
from scenarios.dataset import DatasetError
from tests.test_models import TINY, scene_batch, synthetic_dataset


# ----------------------------------------------------------------------------- candidates
def test_generated_candidates_are_a_polar_grid_in_the_heading_frame():
    hist = torch.zeros(1, 3, 2, 4)
    hist[0, -1, 0] = torch.tensor([1.0, 2.0, 0.7, 0.0])  # heading 0
    hist[0, -1, 1] = torch.tensor([-3.0, 0.5, 0.0, math.pi / 2])  # heading +90 deg
    cfg = ModelConfig(goal_decoder="candidates", goal_rings=5, goal_angles=12, goal_range=5.0)
    cand, mask = goal_candidates({"history": hist}, cfg)
    assert cand.shape == (1, 2, 60, 2) and mask.all()
    # index ring * angles + angle; ring r has radius (r + 1) m, angle a is a * 30 deg off the heading
    torch.testing.assert_close(cand[0, 0, 0], torch.tensor([2.0, 2.0]))  # 1 m ahead
    torch.testing.assert_close(cand[0, 0, 4 * 12 + 3], torch.tensor([1.0, 7.0]))  # 5 m, +90 deg
    torch.testing.assert_close(cand[0, 0, 1 * 12 + 6], torch.tensor([-1.0, 2.0]))  # 2 m behind
    torch.testing.assert_close(cand[0, 1, 2 * 12], torch.tensor([-3.0, 3.5]))  # 3 m ahead (+y)
    dist = torch.linalg.vector_norm(cand[0] - hist[0, -1, :, None, :2], dim=-1)
    torch.testing.assert_close(
        dist.reshape(2, 5, 12), torch.arange(1.0, 6.0)[None, :, None].expand(2, 5, 12)
    )


def test_scene_candidates_and_lane_points_take_precedence():
    hist = torch.zeros(2, 3, 2, 4)
    cfg = ModelConfig(goal_decoder="candidates")
    own = torch.randn(2, 2, 7, 2)
    cmask = torch.rand(2, 2, 7) > 0.3
    cand, mask = goal_candidates(
        {"history": hist, "goal_candidates": own, "goal_candidates_mask": cmask}, cfg
    )
    assert torch.equal(cand, own) and torch.equal(mask, cmask)
    lanes = torch.randn(2, 3, 4, 2)
    lmask = torch.tensor([[True, False, True], [True, True, True]])
    cand, mask = goal_candidates({"history": hist, "lanes": lanes, "lanes_mask": lmask}, cfg)
    assert cand.shape == (2, 2, 12, 2)
    torch.testing.assert_close(cand[0, 1, 4:8], lanes[0, 1])  # lane 1's points, for every agent
    assert not mask[0, :, 4:8].any() and mask[0, :, :4].all() and mask[1].all()
    with pytest.raises(SpecError, match="goal_candidates"):
        goal_candidates({"history": hist, "goal_candidates": torch.zeros(2, 3, 7, 2)}, cfg)


# ----------------------------------------------------------------------------- model
@pytest.mark.parametrize("decoder", ["candidates", "regress"])
def test_decoded_goals_enter_the_game_and_scene_goals_are_not_read(decoder):
    batch, game = scene_batch(4)
    B, N, M = 4, game.N, 2
    torch.manual_seed(0)
    model = build_model(ModelConfig(kind="epo", modes=M, goal_decoder=decoder, **TINY), game)
    model.eval()
    out = model(batch)
    goals = out["goals"]
    assert goals.shape == (B, M, N, 2) and out["decoded_goals"]
    for i, a in enumerate(game.agent_names):  # mode m of agent i uses its m-th goal
        torch.testing.assert_close(
            out["params"][..., game.params[f"goal.{a}"].slice], goals[:, :, i]
        )
    if decoder == "candidates":
        logits, cand = out["goal_logits"], out["goal_candidates"]
        assert logits.shape == (B, N, 60) and cand.shape == (B, N, 60, 2)
        order = logits.argsort(dim=-1, descending=True)
        for m in range(M):  # the m-th most likely candidate
            want = cand.gather(2, order[..., m, None, None].expand(B, N, 1, 2))[:, :, 0]
            torch.testing.assert_close(goals[:, m], want)
    nan_goals = dict(batch, goals=torch.full_like(batch["goals"], math.nan))
    again = model(nan_goals)
    torch.testing.assert_close(again["pos"], out["pos"])
    no_goals = {k: v for k, v in batch.items() if k != "goals"}
    torch.testing.assert_close(model(no_goals)["pos"], out["pos"])
    # the goal loss reaches the goal decoder
    model.train()
    model.zero_grad()
    parts = compute_loss("epo", model(batch), batch["gt"], PAPER_LOSS_WEIGHTS["epo"])
    assert parts["goal"] > 0
    parts["loss"].backward()
    grads = [p.grad for n, p in model.named_parameters() if n.startswith("goal_dec.")]
    assert grads and all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_given_goals_need_goals_in_the_scene():
    batch, game = scene_batch(2)
    model = build_model(ModelConfig(kind="epo", **TINY), game)
    out = model(batch)
    assert "goal_logits" not in out and not out.get("decoded_goals", False)
    assert compute_loss("epo", out, batch["gt"], PAPER_LOSS_WEIGHTS["epo"])["goal"] == 0
    with pytest.raises(SpecError) as e:
        model({k: v for k, v in batch.items() if k != "goals"})
    assert e.value.field == "goals"


@pytest.mark.parametrize("decoder", ["candidates", "regress"])
def test_goal_loss_of_one_batch_falls(decoder):
    with SceneDataset(synthetic_dataset(), "train") as ds:
        batch, game = ds.batch(np.arange(8)), ds.game
    torch.manual_seed(0)
    model = build_model(ModelConfig(kind="epo", goal_decoder=decoder, **TINY), game)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    goal = []
    with torch_threads(1):
        for _ in range(40):
            parts = compute_loss("epo", model(batch), batch["gt"], PAPER_LOSS_WEIGHTS["epo"])
            opt.zero_grad()
            parts["loss"].backward()
            opt.step()
            goal.append(parts["goal"].item())
    assert goal[-1] < goal[0] / 5, (goal[0], goal[-1])


def test_goal_decoder_config_errors_name_the_field():
    for kw, field in [
        ({"goal_decoder": "tnt"}, "model.goal_decoder"),
        ({"kind": "sc", "goal_decoder": "regress"}, "model.goal_decoder"),
        ({"goal_range": 0.0}, "model.goal_range"),
        ({"goal_rings": 0}, "model.goal_rings"),
    ]:
        with pytest.raises(SpecError) as e:
            ModelConfig(**kw)
        assert e.value.field == field
    batch, game = scene_batch(2)
    m = build_model(ModelConfig(goal_decoder="candidates", modes=3, **TINY), game)
    with pytest.raises(SpecError, match="at least M = 3"):
        m(dict(batch, goal_candidates=torch.zeros(2, game.N, 2, 2)))


# ----------------------------------------------------------------------------- losses
def test_goal_classification_loss_by_hand():
    # one scene, two agents, four candidates on a line; ground-truth ends at x = 2.2 and 0.4
    xs = torch.tensor([0.0, 1.0, 2.0, 3.0])
    cand = torch.stack([xs, torch.zeros(4)], -1).expand(1, 2, 4, 2)  # (1, 2, 4, 2)
    final = torch.tensor([[[2.2, 0.0], [0.4, 0.0]]])
    logits = torch.tensor([[[0.0, 0.0, math.log(3.0), 0.0], [0.0, 0.0, 0.0, 0.0]]])
    # agent 0: target 2, p = 3/6; agent 1: target 0, p = 1/4
    want = (-math.log(0.5) - math.log(0.25)) / 2
    assert goal_classification_loss(logits, cand, final).item() == pytest.approx(want)
    # masking candidate 0 makes agent 1's target candidate 1 (still p = 1/4 by the logits given)
    cmask = torch.tensor([[[True] * 4, [False, True, True, True]]])
    assert goal_classification_loss(logits, cand, final, cmask).item() == pytest.approx(want)
    amask = torch.tensor([[True, False]])
    assert goal_classification_loss(logits, cand, final, mask=amask).item() == pytest.approx(
        -math.log(0.5)
    )


def test_goal_regression_loss_by_hand():
    final = torch.tensor([[[1.0, 0.0], [0.0, 2.0]]])  # (B=1, N=2, 2)
    goals = torch.tensor(
        [[[[1.0, 1.0], [0.0, 0.0]], [[3.0, 0.0], [0.0, 2.0]]]]
    )  # mode 0: 1 and 4; mode 1: 4 and 0
    assert goal_regression_loss(goals, final).item() == pytest.approx(2.0)  # min(2.5, 2.0)
    mask = torch.tensor([[True, False]])
    assert goal_regression_loss(goals, final, mask).item() == pytest.approx(1.0)


# ----------------------------------------------------------------------------- datasets
def test_dataset_without_goals_trains_with_a_goal_decoder(tmp_path):
    src = synthetic_dataset()
    d = tmp_path / "nogoals"
    shutil.copytree(src, d)
    man = json.loads((d / "manifest.json").read_text())
    del man["schema"]["goals"]
    (d / "manifest.json").write_text(json.dumps(man))
    with SceneDataset(d, "train") as ds:
        assert "goals" not in ds.fields and "goals" not in ds.batch([0, 1])
    cfg = TrainConfig(model=ModelConfig(kind="epo", **TINY), epochs=1, batch_size=4, lr=1e-3)
    with pytest.raises(DatasetError) as e:
        train(d, tmp_path / "given", cfg, progress=False)
    assert e.value.where.endswith("manifest.json.schema.goals") and "goal_decoder" in str(e.value)
    cfg = TrainConfig(
        model=ModelConfig(kind="epo", goal_decoder="regress", **TINY), epochs=1, batch_size=4
    )
    res = train(d, tmp_path / "regress", cfg, progress=False)
    row = res.history[-1]
    assert row["train_goal"] > 0 and np.isfinite(row["val_minSADE"])
    png = show_predictions(tmp_path / "regress", d, 0, tmp_path / "fig.png", split="test")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
