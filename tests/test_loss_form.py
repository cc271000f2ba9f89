"""The imitation loss's reduction over the future steps and the loss weights of `epo train`.

References are computed independently: by hand on a one-sample example, and with plain
Python loops over samples, modes, agents and steps from the definitions (App. F.4).
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch

from epo_casadi.errors import SpecError
from learning.losses import IMITATION_REDUCTIONS, LossWeights, marginal_loss, scene_loss
from learning.models import ModelConfig
from learning.presets import get_preset
from learning.train import TrainConfig, compute_loss, train
from tests.helpers import cli, one_error_line
from tests.test_models import TINY, synthetic_dataset


def test_hand_computed_one_sample():
    """M = 2 modes of one agent, T = 2 steps, ground truth at the origin.

    Mode 0 is (1, 0) at both steps: squared distances 1, 1 (sum 2, mean 1); mode 1 is
    (0, 2) then (0, 0): 4, 0 (sum 4, mean 2). Mode 0 is the closest under both forms.
    """
    pos = torch.tensor([[[[[1.0, 0.0], [1.0, 0.0]]], [[[0.0, 2.0], [0.0, 0.0]]]]])  # (1,2,1,2,2)
    gt = torch.zeros(1, 1, 2, 2)
    logits = torch.tensor([[0.0, 0.0]])
    w = LossWeights(1.0, 0.0, 0.1)
    s = scene_loss(pos, logits, gt, w, imitation_reduction="sum")
    m = scene_loss(pos, logits, gt, w, imitation_reduction="mean")
    assert s["imitation"].item() == pytest.approx(2.0)
    assert m["imitation"].item() == pytest.approx(1.0)
    assert s["probability"].item() == pytest.approx(math.log(2)) == m["probability"].item()
    assert s["loss"].item() == pytest.approx(2.0 + 0.1 * math.log(2))
    assert m["loss"].item() == pytest.approx(1.0 + 0.1 * math.log(2))
    # the default is the mean: the numbers of before the option existed
    d = scene_loss(pos, logits, gt, w)
    assert all(torch.equal(d[k], m[k]) for k in d)


def _ref_scene(pos, logits, gt, mask, w, reduction):
    """min over modes of the mean over real agents of the per-agent reduction over steps of
    ||x - x_GT||^2; cross entropy with that mode as target; means over samples (loops)."""
    B, M, N, T, _ = pos.shape
    imits, ces = [], []
    for b in range(B):
        real = [i for i in range(N) if mask[b, i]]
        per_mode = []
        for m in range(M):
            per_agent = []
            for i in real:
                steps = [float(((pos[b, m, i, t] - gt[b, i, t]) ** 2).sum()) for t in range(T)]
                per_agent.append(sum(steps) if reduction == "sum" else sum(steps) / T)
            per_mode.append(sum(per_agent) / len(per_agent))
        best = int(np.argmin(per_mode))
        imits.append(per_mode[best])
        lg = logits[b].astype(np.float64)
        ces.append(-(lg[best] - math.log(np.exp(lg).sum())))
    imit, ce = float(np.mean(imits)), float(np.mean(ces))
    return imit, ce, w.imitation * imit + w.probability * ce


@pytest.mark.parametrize("reduction", IMITATION_REDUCTIONS)
def test_scene_loss_against_loops_with_a_padded_agent(reduction):
    rng = np.random.default_rng(0)
    B, M, N, T = 3, 4, 3, 5
    pos = rng.normal(size=(B, M, N, T, 2))
    gt = rng.normal(size=(B, N, T, 2))
    logits = rng.normal(size=(B, M))
    mask = np.ones((B, N), bool)
    mask[1, 2] = mask[2, 0] = False
    # pad values that would poison the loss if they reached it
    pos_t = torch.tensor(pos, requires_grad=True)
    gt_bad = gt.copy()
    gt_bad[1, 2] = np.nan
    gt_bad[2, 0] = 1e30
    w = LossWeights(1.0, 0.0, 0.3)
    got = scene_loss(
        pos_t, torch.tensor(logits), torch.tensor(gt_bad), w, torch.tensor(mask), reduction
    )
    imit, ce, total = _ref_scene(pos, logits, gt, mask, w, reduction)
    assert got["imitation"].item() == pytest.approx(imit, rel=1e-12)
    assert got["probability"].item() == pytest.approx(ce, rel=1e-12)
    assert got["loss"].item() == pytest.approx(total, rel=1e-12)
    got["loss"].backward()
    assert torch.isfinite(pos_t.grad).all()
    assert (pos_t.grad[1, :, 2] == 0).all() and (pos_t.grad[2, :, 0] == 0).all()


def test_sum_is_K_times_mean_with_the_same_mode():
    """The sum differs from the mean by the factor T; the closest mode (the target of the
    probability loss) is the same, so L_prob does not change."""
    rng = np.random.default_rng(1)
    B, M, N, T = 4, 3, 2, 7
    pos = torch.tensor(rng.normal(size=(B, M, N, T, 2)))
    gt = torch.tensor(rng.normal(size=(B, N, T, 2)))
    logits = torch.tensor(rng.normal(size=(B, M)))
    s = scene_loss(pos, logits, gt, imitation_reduction="sum")
    m = scene_loss(pos, logits, gt, imitation_reduction="mean")
    assert s["imitation"].item() == pytest.approx(T * m["imitation"].item(), rel=1e-12)
    assert s["probability"].item() == m["probability"].item()
    # and the weight of L_imit against L_prob grows by T
    assert (s["loss"] - 0.1 * s["probability"]).item() == pytest.approx(
        T * (m["loss"] - 0.1 * m["probability"]).item(), rel=1e-12
    )


@pytest.mark.parametrize("reduction", IMITATION_REDUCTIONS)
def test_marginal_loss_against_loops(reduction):
    rng = np.random.default_rng(2)
    B, M, N, T = 2, 3, 2, 4
    pos = rng.normal(size=(B, M, N, T, 2))
    gt = rng.normal(size=(B, N, T, 2))
    logits = rng.normal(size=(B, N, M))
    got = marginal_loss(
        torch.tensor(pos), torch.tensor(logits), torch.tensor(gt), imitation_reduction=reduction
    )
    imit, ce = [], []
    for b in range(B):
        for i in range(N):
            d = [
                [float(np.linalg.norm(pos[b, m, i, t] - gt[b, i, t])) for t in range(T)]
                for m in range(M)
            ]
            per_mode = [sum(x) if reduction == "sum" else sum(x) / T for x in d]
            best = int(np.argmin(per_mode))
            imit.append(per_mode[best])
            ce.append(-(logits[b, i, best] - math.log(np.exp(logits[b, i]).sum())))
    assert got["imitation"].item() == pytest.approx(np.mean(imit), rel=1e-12)
    assert got["probability"].item() == pytest.approx(np.mean(ce), rel=1e-12)


def test_unknown_reduction_is_refused():
    pos, gt = torch.zeros(1, 2, 1, 3, 2), torch.zeros(1, 1, 3, 2)
    with pytest.raises(SpecError, match="imitation_reduction"):
        scene_loss(pos, torch.zeros(1, 2), gt, imitation_reduction="max")
    with pytest.raises(SpecError, match="train.imitation_reduction"):
        TrainConfig(imitation_reduction="Sum")


def test_config_records_the_reduction_and_reads_old_configs():
    c = TrainConfig(imitation_reduction="sum", loss=LossWeights(1.0, 1.0, 1.0))
    d = c.to_dict()
    assert d["imitation_reduction"] == "sum" and d["loss"] == {
        "imitation": 1.0,
        "goal": 1.0,
        "probability": 1.0,
    }
    assert TrainConfig.from_dict(d) == c
    old = TrainConfig().to_dict()
    del old["imitation_reduction"]  # a config written before the option existed
    assert TrainConfig.from_dict(old).imitation_reduction == "mean"


def test_compute_loss_passes_the_reduction():
    rng = np.random.default_rng(3)
    out = {
        "pos": torch.tensor(rng.normal(size=(2, 2, 2, 6, 2))),
        "logits": torch.tensor(rng.normal(size=(2, 2))),
    }
    gt = torch.tensor(rng.normal(size=(2, 2, 6, 2)))
    w = LossWeights(1.0, 0.1, 0.1)
    s = compute_loss("epo", out, gt, w, imitation_reduction="sum")
    m = compute_loss("epo", out, gt, w)
    assert s["imitation"].item() == pytest.approx(6 * m["imitation"].item(), rel=1e-12)


def test_waymo_preset_uses_the_papers_form():
    p = get_preset("waymo")
    assert p.imitation_reduction == "sum"
    assert LossWeights(**p.loss) == LossWeights(1.0, 1.0, 1.0)
    assert TrainConfig().imitation_reduction == "mean"  # the defaults are unchanged


def test_first_step_imitation_is_K_times_with_sum(tmp_path):
    """Same seed, same first batch, before any update: the first step's imitation part
    with ``sum`` is K (the horizon, 10) times the one with ``mean``."""
    data = synthetic_dataset()
    first = {}
    for red in IMITATION_REDUCTIONS:
        seen: list[dict] = []
        cfg = TrainConfig(
            model=ModelConfig(kind="sc", **TINY),
            epochs=1,
            batch_size=4,
            lr=1e-3,
            imitation_reduction=red,
        )
        train(
            data,
            tmp_path / red,
            cfg,
            progress=False,
            on_step=lambda s, p, seen=seen: seen.append(p),
        )
        first[red] = seen[0]
        info = json.loads((tmp_path / red / "config.json").read_text())
        assert info["train"]["imitation_reduction"] == red
    assert first["sum"]["imitation"] == pytest.approx(10 * first["mean"]["imitation"], rel=1e-5)
    assert first["sum"]["probability"] == pytest.approx(first["mean"]["probability"], rel=1e-5)


# --------------------------------------------------------------------------------------
# epo train --loss-weights / --imitation-reduction
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", ["1,2", "1,a,1", "1,-1,1", "1,nan,1", "1,1,1,1", ""])
def test_bad_loss_weights_are_one_error_line(tmp_path, capsys, bad):
    rc, _, se = cli(
        capsys, "train", "--data", synthetic_dataset(), "--out", tmp_path / "r",
        "--loss-weights", bad, "--no-progress",
    )  # fmt: skip
    one_error_line(rc, se, "--loss-weights", repr(bad))
    assert not (tmp_path / "r").exists()  # refused before anything is written


def test_bad_reduction_is_one_error_line(tmp_path, capsys):
    rc, _, se = cli(
        capsys, "train", "--data", synthetic_dataset(), "--out", tmp_path / "r",
        "--imitation-reduction", "max",
    )  # fmt: skip
    one_error_line(rc, se, "--imitation-reduction", "'max'")


def _tiny_sets():
    return [a for k, v in TINY.items() for a in ("--set", f"{k}={v}")]


def test_cli_loss_weights_are_used_and_recorded(tmp_path, capsys):
    run = tmp_path / "run"
    rc, _, se = cli(
        capsys, "train", "--model", "sc", "--data", synthetic_dataset(), "--out", run,
        "--epochs", "1", "--batch-size", "4", "--lr", "1e-3", "--no-progress",
        "--no-tensorboard", "--loss-weights", "2, 0, 0.5", "--imitation-reduction", "sum",
        *_tiny_sets(),
    )  # fmt: skip
    assert rc == 0, se
    cfg = json.loads((run / "config.json").read_text())["train"]
    assert cfg["loss"] == {"imitation": 2.0, "goal": 0.0, "probability": 0.5}
    assert cfg["imitation_reduction"] == "sum"
    row = next(csv.DictReader((run / "metrics.csv").read_text().splitlines()))
    loss, imit, prob = (
        float(row[k]) for k in ("train_loss", "train_imitation", "train_probability")
    )
    assert loss == pytest.approx(2.0 * imit + 0.5 * prob, rel=1e-6) and prob > 0.1
    # the same command again resumes (nothing to do); another weight is refused
    rc, _, se = cli(
        capsys, "train", "--model", "sc", "--data", synthetic_dataset(), "--out", run,
        "--epochs", "1", "--batch-size", "4", "--lr", "1e-3", "--no-progress",
        "--no-tensorboard", "--loss-weights", "1,0,0.5", "--imitation-reduction", "sum",
        *_tiny_sets(),
    )  # fmt: skip
    one_error_line(rc, se, "checkpoint.pt", "loss")


def test_cli_preset_gives_sum_and_options_override_it(tmp_path, capsys):
    base = [
        "train", "--model", "sc", "--data", synthetic_dataset(), "--epochs", "1",
        "--batch-size", "4", "--no-progress", "--no-tensorboard", "--preset", "waymo",
        "--modes", "2", *_tiny_sets(),
    ]  # fmt: skip
    rc, _, se = cli(capsys, *base, "--out", tmp_path / "a")
    assert rc == 0, se
    cfg = json.loads((tmp_path / "a" / "config.json").read_text())["train"]
    assert cfg["imitation_reduction"] == "sum" and cfg["lr"] == 1e-4
    assert cfg["loss"] == {"imitation": 1.0, "goal": 1.0, "probability": 1.0}
    rc, _, se = cli(
        capsys, *base, "--out", tmp_path / "b", "--imitation-reduction", "mean",
        "--loss-weights", "1,0.1,0.1",
    )  # fmt: skip
    assert rc == 0, se
    cfg = json.loads((tmp_path / "b" / "config.json").read_text())["train"]
    assert cfg["imitation_reduction"] == "mean"
    assert cfg["loss"] == {"imitation": 1.0, "goal": 0.1, "probability": 0.1}
