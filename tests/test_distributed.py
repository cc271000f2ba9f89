"""Data-parallel training on 2 local ranks (gloo): equal to one process, resumable, seeded.

Each launch starts two fresh processes (:func:`learning.distributed.launch`); to keep the
module fast, one launch runs several trainings in one process group (:func:`_on_two_ranks`)
and the tests read what it left. No timing is asserted.
"""

from __future__ import annotations

import math
import os
import shutil
import signal

import numpy as np
import pytest
import torch
import torch.distributed as dist

from learning.checkpoint import load_checkpoint
from learning.distributed import (
    DistributedError,
    SyncBatchNorm1d,
    World,
    agree,
    launch,
    shard,
)
from learning.models import ModelConfig
from learning.train import TrainConfig, train, train_parallel
from tests.test_models import TINY, synthetic_dataset

#: the timing columns of metrics.csv (wall clock: differ between any two runs)
TIMING = ("seconds", "samples_per_s", "val_seconds")


def _cfg(**kw) -> TrainConfig:
    """SC on the 8 training samples, batch 3: steps 1-3 in epoch 1, 4-6 in epoch 2."""
    base = dict(
        model=ModelConfig(kind="sc", **TINY), epochs=2, batch_size=3, lr=1e-3, seed=3,
        checkpoint_steps=2,
    )  # fmt: skip
    return TrainConfig(**{**base, **kw})


#: ours, one step on the whole training split (8 samples: one global batch)
ONE_STEP = TrainConfig(
    model=ModelConfig(kind="epo", **TINY), epochs=1, batch_size=8, lr=1e-3, seed=3
)


def _batch_norm_check() -> dict:
    """SyncBatchNorm1d on this rank's shard of a fixed float64 batch: its output, input
    gradient and running statistics, and the affine gradients summed over the ranks."""
    g = torch.Generator().manual_seed(0)
    x = 3.0 + 2.0 * torch.randn(7, 5, generator=g, dtype=torch.float64)
    c = torch.randn(7, 5, generator=g, dtype=torch.float64)
    idx = shard(np.arange(7), dist.get_rank(), dist.get_world_size())
    bn = SyncBatchNorm1d(5).double()
    with torch.no_grad():
        bn.weight.copy_(torch.linspace(0.5, 1.5, 5))
        bn.bias.copy_(torch.linspace(-1, 1, 5))
    xs = x[idx].clone().requires_grad_(True)
    y = bn(xs)
    (y * c[idx]).sum().backward()
    affine = torch.cat([bn.weight.grad, bn.bias.grad])
    dist.all_reduce(affine)
    return {
        "idx": idx,
        "y": y.detach(),
        "dx": xs.grad,
        "affine": affine,
        "running": torch.cat([bn.running_mean, bn.running_var]),
    }


def _on_two_ranks(data: str, root: str) -> dict:
    """What the module's one 2-rank launch does on each rank."""
    rank = dist.get_rank()
    out = {"bn": _batch_norm_check()}
    train(data, f"{root}/one-step", ONE_STEP, progress=False)
    for name in ("full", "again"):
        out[name] = train(data, f"{root}/{name}", _cfg(), progress=False).step_losses
    try:  # rank 1 started with another learning rate: refused on both ranks
        train(data, f"{root}/disagree", _cfg(lr=1e-3 * (1 + rank)), progress=False)
    except DistributedError as e:
        out["disagree"] = str(e)
    return out


def _kill_rank_1_at_step_5(step: int, parts: dict) -> None:
    if step == 5 and dist.get_rank() == 1:
        os.kill(os.getpid(), signal.SIGKILL)


@pytest.fixture(scope="module")
def two_ranks(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp")
    data = synthetic_dataset()
    results = launch(2, _on_two_ranks, (str(data), str(root)))
    return data, root, results


def _checkpoint(run) -> dict:
    return load_checkpoint(run / "checkpoint.pt")


def _equal_rows(got: list[dict], want: list[dict], rel: float = 0.0) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert set(g) == set(w)
        for k in w:
            if k in TIMING:
                continue
            a, b = float(g[k]), float(w[k])
            assert a == b or abs(a - b) <= rel * (1 + abs(b)), (k, a, b)


# ------------------------------------------------------------------------------ pieces
def test_shards_partition_every_batch():
    for n in range(0, 12):
        idx = np.arange(100, 100 + n)
        for size in (1, 2, 3, 5):
            parts = [shard(idx, r, size) for r in range(size)]
            assert np.array_equal(np.concatenate(parts), idx)  # disjoint, in order, all
            assert max(map(len, parts)) - min(map(len, parts)) <= 1


def test_one_process_needs_no_group():
    assert World().main and World().size == 1
    agree(World(), {"config": {"lr": 1}})  # nothing to compare with
    with pytest.raises(ValueError, match="mine"):
        agree(World(), {}, ValueError("mine"))  # a rank's own error, as it is
    bn, ref = SyncBatchNorm1d(3), torch.nn.BatchNorm1d(3)
    x = torch.randn(6, 3)
    torch.testing.assert_close(bn(x), ref(x), rtol=0, atol=0)  # no group: the plain one
    torch.testing.assert_close(bn.running_var, ref.running_var, rtol=0, atol=0)


def test_sync_batch_norm_is_the_global_batch_norm(two_ranks):
    """Forward, input and affine gradients and running statistics of SyncBatchNorm1d on
    two shards (float64) equal torch's BatchNorm1d on the whole batch."""
    _, _, results = two_ranks
    g = torch.Generator().manual_seed(0)
    x = 3.0 + 2.0 * torch.randn(7, 5, generator=g, dtype=torch.float64)
    c = torch.randn(7, 5, generator=g, dtype=torch.float64)
    ref = torch.nn.BatchNorm1d(5).double()
    with torch.no_grad():
        ref.weight.copy_(torch.linspace(0.5, 1.5, 5))
        ref.bias.copy_(torch.linspace(-1, 1, 5))
    xr = x.clone().requires_grad_(True)
    y = ref(xr)
    (y * c).sum().backward()
    for r in results:
        bn = r["bn"]
        idx = torch.as_tensor(bn["idx"])
        torch.testing.assert_close(bn["y"], y.detach()[idx], rtol=0, atol=1e-12)
        torch.testing.assert_close(bn["dx"], xr.grad[idx], rtol=0, atol=1e-12)
        want = torch.cat([ref.weight.grad, ref.bias.grad])
        torch.testing.assert_close(bn["affine"], want, rtol=0, atol=1e-12)
        want = torch.cat([ref.running_mean, ref.running_var])
        torch.testing.assert_close(bn["running"], want, rtol=0, atol=1e-12)
    assert len(results[0]["bn"]["idx"]) == 4 and len(results[1]["bn"]["idx"]) == 3


# ----------------------------------------------------------------------------- training
def test_one_step_on_two_ranks_is_one_step_on_one(two_ranks, tmp_path):
    """Ours (game layer, batch norm in the probability decoder), one Adam step on the
    8-sample global batch: 2 ranks of 4 samples give the losses, layer statuses,
    validation metrics, gradients and parameters of one process.

    Parameters are compared to 1e-6 where the gradient is above rounding (|g| > 1e-6; 79 %
    of the entries here). The others have a gradient of zero to rounding (a bias before a
    batch norm, the shift of the scene logits, the key bias of attention, ...): there
    Adam's first step, ``lr * g / (|g| + 1e-8)``, turns float32 rounding in ``g`` into a
    step of up to ``lr`` in either process alike, so they are compared through the
    gradient only."""
    data, root, _ = two_ranks
    single = tmp_path / "one-step"
    train(data, single, ONE_STEP, progress=False)
    one, two = _checkpoint(single), _checkpoint(root / "one-step")
    assert one["step"] == two["step"] == 1
    _equal_rows(two["history"], one["history"], rel=1e-6)
    row = two["history"][0]
    assert row["layer_max_iter"] + row["layer_converged"] == 8 * ONE_STEP.model.modes
    names = [n for n, p in _named_parameters(one)]
    s1, s2 = one["optimizer"]["state"], two["optimizer"]["state"]
    assert set(s1) == set(s2) and 0 < len(s1) < len(names)  # no gradient: the lane encoder
    compared = total = 0
    for i, name in enumerate(names):
        if i not in s1:  # unused by the model on this data (no lanes): untouched
            assert torch.equal(one["model"][name], two["model"][name]), name
            continue
        m1, m2 = s1[i]["exp_avg"], s2[i]["exp_avg"]  # 0.1 * gradient after one step
        torch.testing.assert_close(m2, m1, rtol=1e-4, atol=1e-7, msg=name)
        p1, p2 = one["model"][name], two["model"][name]
        above = 10 * m1.abs() > 1e-6
        compared += int(above.sum())
        total += above.numel()
        assert max((p1 - p2)[above].abs().tolist(), default=0.0) <= 1e-6, name
    assert compared > 0.7 * total, (compared, total)
    for name, v in one["model"].items():  # running statistics of the batch norms
        if "running" in name:
            torch.testing.assert_close(two["model"][name], v, rtol=1e-5, atol=1e-6)


def _named_parameters(ck: dict):
    """(name, tensor) of the model's parameters in the optimizer's order (buffers left out)."""
    from learning.data import SceneDataset
    from learning.models import build_model

    with SceneDataset(synthetic_dataset(), "train") as ds:
        model = build_model(ONE_STEP.model, ds.game)
    return list(model.named_parameters())


def test_seeds_give_the_same_two_rank_run_twice(two_ranks):
    data, root, results = two_ranks
    full, again = _checkpoint(root / "full"), _checkpoint(root / "again")
    assert [s for s, _ in results[0]["full"]] == [1, 2, 3, 4, 5, 6]
    assert results[0]["full"] == results[0]["again"] == results[1]["full"]  # bit for bit
    for k, v in full["model"].items():
        assert torch.equal(v, again["model"][k]), k
    _equal_rows(again["history"], full["history"])


def test_ranks_that_disagree_are_refused_in_one_line(two_ranks):
    _, root, results = two_ranks
    msgs = {r["disagree"] for r in results}
    assert len(msgs) == 1  # the same line on both ranks
    (msg,) = msgs
    assert "\n" not in msg and "disagree about the training settings" in msg
    assert "lr (0.001 vs 0.002)" in msg
    assert not (root / "disagree" / "checkpoint.pt").exists()


def test_a_killed_two_rank_run_resumes(two_ranks, tmp_path, capsys):
    """Rank 1 is killed (SIGKILL) after step 5, the last checkpoint is after step 4; the
    same command again (``epo train --nproc 2``, with TensorBoard) ends with the
    parameters of the uninterrupted run, bit for bit, and so does (to rounding) a resume
    on one process."""
    from scenarios.cli import main

    data, root, results = two_ranks
    run = tmp_path / "killed"
    with pytest.raises(DistributedError, match="rank 1 stopped by signal 9") as e:
        train_parallel(2, data, run, _cfg(), progress=False, on_step=_kill_rank_1_at_step_5)
    assert "\n" not in str(e.value)
    ck = _checkpoint(run)
    assert (ck["epoch"], ck["step"], ck["step_in_epoch"]) == (1, 4, 1)
    shutil.copytree(run, tmp_path / "killed-1", ignore=shutil.ignore_patterns(".lock"))
    m = _cfg().model
    rc = main(
        ["train", "--model", "sc", "--data", str(data), "--out", str(run), "--nproc", "2",
         "--epochs", "2", "--batch-size", "3", "--lr", "1e-3", "--seed", "3",
         "--checkpoint-steps", "2", "--no-progress"]
        + [a for k in TINY for a in ("--set", f"{k}={getattr(m, k)}")]
    )  # fmt: skip
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert out.out.count("epoch 2, step 6") == 1  # rank 0 reports, once
    full, resumed = _checkpoint(root / "full"), _checkpoint(run)
    assert resumed["step"] == 6
    for k, v in full["model"].items():
        assert torch.equal(v, resumed["model"][k]), k
    _equal_rows(resumed["history"], full["history"])
    events = list((run / "tb").glob("events.out.tfevents.*"))
    assert len(events) == 1  # rank 0 writes; the other rank none
    tags = _event_tags(run / "tb")
    assert {"train/loss", "train/imitation", "train/probability", "train/lr"} <= tags["scalars"]
    assert {"epoch/train_loss", "epoch/val_minADE", "epoch/val_minSADE"} <= tags["scalars"]
    assert tags["images"] == ["predictions"]
    # it resumed after step 4 (a run from scratch ends with the same parameters)
    assert tags["train/loss steps"] == [5, 6]

    one = train(data, tmp_path / "killed-1", _cfg(), progress=False)  # on one process
    assert one.resumed_from == 4 and [s for s, _ in one.step_losses] == [5, 6]
    want = dict(results[0]["full"])
    for s, loss in one.step_losses:
        assert math.isclose(loss, want[s], rel_tol=1e-5), (s, loss, want[s])
    _equal_rows(_checkpoint(tmp_path / "killed-1")["history"], full["history"], rel=1e-5)


def _event_tags(folder) -> dict:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(folder), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    tags = acc.Tags()
    return {
        "scalars": set(tags["scalars"]),
        "images": list(tags["images"]),
        "train/loss steps": [e.step for e in acc.Scalars("train/loss")],
    }
