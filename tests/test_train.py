"""Training: overfitting one batch, checkpoints and resume, run files, config validation."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch

from epo_casadi.errors import SpecError
from learning.checkpoint import CheckpointError, load_checkpoint
from learning.data import SceneDataset
from learning.losses import LossWeights
from learning.models import ModelConfig, build_model
from learning.train import (
    PAPER_LOSS_WEIGHTS,
    TrainConfig,
    compute_loss,
    load_model,
    torch_threads,
    train,
)
from tests.test_models import TINY, synthetic_dataset

PNG = b"\x89PNG\r\n\x1a\n"


class Killed(Exception):
    pass


@pytest.mark.parametrize("kind", ["epo", "sc"])
def test_single_batch_overfits(kind):
    with SceneDataset(synthetic_dataset(), "train") as ds:
        batch, game = ds.batch(np.arange(8)), ds.game
    torch.manual_seed(0)
    model = build_model(ModelConfig(kind=kind, **TINY), game)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    with torch_threads(1):
        for _ in range(50):
            parts = compute_loss(kind, model(batch), batch["gt"], PAPER_LOSS_WEIGHTS[kind])
            opt.zero_grad()
            parts["loss"].backward()
            opt.step()
            losses.append(parts["loss"].item())
    assert losses[-1] < losses[0] / 5, (losses[0], losses[-1])


def _cfg(**kw) -> TrainConfig:
    base = dict(model=ModelConfig(kind="sc", **TINY), epochs=2, batch_size=3, lr=1e-3, seed=3)
    return TrainConfig(**{**base, **kw})


def test_resume_gives_the_same_next_step_loss(tmp_path):
    data = synthetic_dataset()  # 8 train samples, batch 3: steps 1-3 in epoch 1, 4-6 in epoch 2
    full = train(data, tmp_path / "full", _cfg(checkpoint_steps=2), progress=False)
    assert (
        full.steps == 6
        and full.epochs == 2
        and [s for s, _ in full.step_losses] == [1, 2, 3, 4, 5, 6]
    )

    def kill_at(step):
        def cb(s, parts):
            if s == step:
                raise Killed

        return cb

    run = tmp_path / "killed"
    with pytest.raises(Killed):  # killed after step 5; the last checkpoint is after step 4
        train(data, run, _cfg(checkpoint_steps=2), progress=False, on_step=kill_at(5))
    ck = load_checkpoint(run / "checkpoint.pt")
    assert (ck["epoch"], ck["step"], ck["step_in_epoch"]) == (1, 4, 1)
    res = train(data, run, _cfg(checkpoint_steps=2), progress=False)
    assert res.resumed_from == 4 and [s for s, _ in res.step_losses] == [5, 6]
    assert res.step_losses == full.step_losses[4:]  # bit for bit
    timing = ("seconds", "samples_per_s", "val_seconds")
    assert len(res.history) == 2
    for got, want in zip(res.history, full.history, strict=True):  # epoch 2's means span the kill
        assert {k: v for k, v in got.items() if k not in timing} == {
            k: v for k, v in want.items() if k not in timing
        }
    a, b = (load_checkpoint(p / "checkpoint.pt")["model"] for p in (tmp_path / "full", run))
    for k in a:
        assert torch.equal(a[k], b[k]), k

    # stopped at an epoch end, then asked for more epochs: trains on as if never stopped
    part = tmp_path / "part"
    one = train(data, part, _cfg(epochs=1), progress=False)
    assert one.step_losses == full.step_losses[:3]
    more = train(data, part, _cfg(epochs=2), progress=False)
    assert more.resumed_from == 3 and more.step_losses == full.step_losses[3:]
    again = train(data, part, _cfg(epochs=2), progress=False)  # finished: nothing to do
    assert again.step_losses == [] and again.epochs == 2


def test_run_files_and_reload(tmp_path):
    data = synthetic_dataset()
    res = train(
        data,
        tmp_path / "run",
        _cfg(model=ModelConfig(kind="epo", **TINY), epochs=2),
        progress=False,
    )
    run = tmp_path / "run"
    for f in ("config.json", "checkpoint.pt", "best.pt", "metrics.csv", "loss.png"):
        assert (run / f).is_file(), f
    assert not list(run.glob(".*.tmp"))
    assert not (run / "tb").exists()  # TensorBoard events only when asked for (train())
    assert (run / "loss.png").read_bytes()[:8] == PNG
    info = json.loads((run / "config.json").read_text())
    assert info["train"]["model"]["kind"] == "epo" and info["train"]["loss"] == {
        "imitation": 1.0,
        "goal": 0.1,
        "probability": 0.1,
    }
    assert (
        info["game"]["horizon"] == 10
        and info["data"]["scenario"] == "rpi"
        and info["parameters"] > 0
    )
    rows = list(csv.DictReader((run / "metrics.csv").read_text().splitlines()))
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    for k in (
        "train_loss",
        "train_imitation",
        "train_probability",
        "samples_per_s",
        "val_minADE",
        "val_minFDE",
        "val_minSADE",
        "val_minSFDE",
        "val_OR",
    ):
        assert np.isfinite(float(rows[-1][k])), k
    assert rows[-1] == {k: str(v) for k, v in res.history[-1].items()}
    with SceneDataset(data, "val") as ds:
        model, cfg, ck = load_model(run, ds.game, which="best")
        assert cfg.model.kind == "epo" and not model.training
        best = min(res.history, key=lambda r: r["val_minSADE"])
        assert ck["epoch"] == best["epoch"]


def test_resume_refuses_another_setup(tmp_path):
    data = synthetic_dataset()
    run = tmp_path / "run"
    train(data, run, _cfg(epochs=1), progress=False)
    with pytest.raises(CheckpointError, match="different lr"):
        train(data, run, _cfg(epochs=1, lr=1e-2), progress=False)
    with pytest.raises(CheckpointError, match="another dataset"):
        train(synthetic_dataset(straight=True), run, _cfg(epochs=1), progress=False)
    (run / "checkpoint.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="checkpoint.pt: unreadable checkpoint"):
        train(data, run, _cfg(epochs=2), progress=False)
    with pytest.raises(CheckpointError, match="no such run directory"):
        load_model(tmp_path / "nope", None)


def test_train_config_defaults_and_validation():
    c = TrainConfig()
    assert (c.batch_size, c.lr, c.model.kind) == (32, 5e-5, "epo")
    assert c.loss_weights == LossWeights(1.0, 0.1, 0.1)
    assert TrainConfig(model=ModelConfig(kind="sc")).loss_weights == LossWeights(1.0, 0.0, 1.0)
    assert TrainConfig(model=ModelConfig(kind="vlstm")).loss_weights.probability == 1.0
    d = _cfg().to_dict()
    json.dumps(d)
    assert TrainConfig.from_dict(d) == TrainConfig(
        **{**_cfg().__dict__, "loss": LossWeights(1.0, 0.0, 1.0)}
    )
    with pytest.raises(SpecError, match=r"unknown field\(s\) \['epoch'\]"):
        TrainConfig.from_dict({"epoch": 3})
    with pytest.raises(SpecError, match=r"train.model: unknown field\(s\) \['width'\]"):
        TrainConfig.from_dict({"model": {"width": 3}})
    for kw, field in [
        ({"epochs": 0}, "train.epochs"),
        ({"lr": -1.0}, "train.lr"),
        ({"batch_size": 1.5}, "train.batch_size"),
        ({"val_split": "dev"}, "train.val_split"),
    ]:
        with pytest.raises(SpecError) as e:
            TrainConfig(**kw)
        assert e.value.field == field


def test_layer_backends_train_alike_and_resume_across(tmp_path):
    """The layer's backend is an execution setting: an epoch of ours with the fused backend
    in generated C (the default where a compiler is found) gives the losses and validation
    metrics of the interpreted structured backend to rounding; a run started with one
    resumes with the other, while a real setting change is still refused."""
    from learning.models import layer_execution
    from solvers.codegen import CompilerError, find_compiler
    from solvers.fast_gn import FusedGN
    from solvers.structured import StructuredGN

    try:
        find_compiler()
    except CompilerError:
        pytest.skip("no C compiler")
    auto = ModelConfig(kind="epo", **TINY)
    assert layer_execution(auto) == ("fused", True)
    data = synthetic_dataset()
    with SceneDataset(data, "train") as ds:
        assert isinstance(build_model(auto, ds.game).layer.core.backend, FusedGN)
    rows = {}
    for name, layer in (
        ("structured", dict(layer_backend="structured", layer_compiled="no")),
        ("fused", dict(layer_backend="auto", layer_compiled="auto")),
    ):
        cfg = _cfg(model=ModelConfig(kind="epo", **TINY, **layer), epochs=1)
        train(data, tmp_path / name, cfg, progress=False)
        with open(tmp_path / name / "metrics.csv") as f:
            rows[name] = next(csv.DictReader(f))
    with SceneDataset(data, "train") as ds:
        slow = ModelConfig(kind="epo", **TINY, layer_backend="structured", layer_compiled="no")
        assert isinstance(build_model(slow, ds.game).layer.core.backend, StructuredGN)
    for k in ("train_loss", "train_imitation", "val_minADE", "val_minSFDE"):
        a, b = float(rows["structured"][k]), float(rows["fused"][k])
        assert abs(a - b) <= 1e-6 * (1 + abs(a)), (k, a, b)  # float32 network, float64 layer
    # resume the structured run with the fused backend for a second epoch: accepted
    cfg = _cfg(model=ModelConfig(kind="epo", **TINY), epochs=2)
    res = train(data, tmp_path / "structured", cfg, progress=False)
    assert res.epochs == 2 and res.resumed_from is not None
    with pytest.raises(CheckpointError, match="lm_steps"):
        train(
            data,
            tmp_path / "structured",
            _cfg(model=ModelConfig(kind="epo", **TINY, lm_steps=3), epochs=3),
            progress=False,
        )
    with pytest.raises(SpecError, match="model.layer_backend"):
        ModelConfig(layer_backend="gpu")
    with pytest.raises(SpecError, match="model.layer_compiled"):
        ModelConfig(layer_compiled=True)


def test_tensorboard_events_hold_what_the_run_recorded(tmp_path):
    """``tensorboard=True``: event files in RUN/tb with the loss parts and learning rate
    per step, the game layer's status counts per step, the epoch rows of metrics.csv and a
    predictions figure per epoch; read back with TensorBoard's own reader, the numbers are
    the run's."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from learning.layer import STATUS_CODES

    data, run = synthetic_dataset(), tmp_path / "run"
    cfg = _cfg(model=ModelConfig(kind="epo", **TINY), epochs=2)
    res = train(data, run, cfg, progress=False, tensorboard=True)
    acc = EventAccumulator(str(run / "tb"), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    scalars = set(acc.Tags()["scalars"])
    statuses = {f"layer/{s.value}" for s in STATUS_CODES}
    parts = {"train/loss", "train/imitation", "train/probability", "train/goal", "train/lr"}
    epoch = {f"epoch/{k}" for k in ("train_loss", "val_minADE", "val_minSADE", "val_OR", "lr")}
    assert parts | statuses | epoch | {"epoch/layer_max_iter"} <= scalars, scalars
    loss = [(e.step, e.value) for e in acc.Scalars("train/loss")]
    assert [s for s, _ in loss] == [s for s, _ in res.step_losses] == [1, 2, 3, 4, 5, 6]
    for (_, got), (_, want) in zip(loss, res.step_losses, strict=True):
        assert math.isclose(got, want, rel_tol=1e-6)  # stored as float32
    lr = acc.Scalars("train/lr")
    assert len(lr) == 6 and all(math.isclose(e.value, cfg.lr, rel_tol=1e-6) for e in lr)
    rows = res.history
    per_step = [e.value for e in acc.Scalars("layer/max_iter")]
    assert (
        sum(per_step[:3]) == rows[0]["layer_max_iter"]
        and sum(per_step[3:]) == rows[1]["layer_max_iter"]
    )
    assert sum(rows[0][f"layer_{s.value}"] for s in STATUS_CODES) == 8 * cfg.model.modes
    # per step, the problems of every status add up to the step's samples x modes (8
    # samples in batches of 3: 3, 3, 2 per epoch), and per epoch to the row's counts
    per_status = {s.value: [e.value for e in acc.Scalars(f"layer/{s.value}")] for s in STATUS_CODES}
    assert [sum(v[k] for v in per_status.values()) for k in range(6)] == [
        n * cfg.model.modes for n in (3, 3, 2, 3, 3, 2)
    ]
    for s, v in per_status.items():
        assert (sum(v[:3]), sum(v[3:])) == (rows[0][f"layer_{s}"], rows[1][f"layer_{s}"]), s
    val = [(e.step, e.value) for e in acc.Scalars("epoch/val_minSADE")]
    assert [s for s, _ in val] == [3, 6]
    for (_, got), row in zip(val, rows, strict=True):
        assert math.isclose(got, row["val_minSADE"], rel_tol=1e-6)
    assert acc.Tags()["images"] == ["predictions"]
    images = acc.Images("predictions")
    assert [e.step for e in images] == [3, 6]
    assert all(e.encoded_image_string[:8] == PNG and e.width > 100 for e in images)
    with open(run / "metrics.csv") as f:
        header = next(csv.reader(f))
    assert {"lr", "layer_converged", "layer_max_iter", "layer_nonfinite"} <= set(header)
