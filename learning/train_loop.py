"""The steps of one training call (:func:`learning.train.train`): losses, epochs, records.

:func:`compute_loss` is the loss of one batch by model kind. ``_Run`` holds what the steps
of one call share (settings, data, model, optimizer, files) and ``_Progress`` where the run
stands (what a checkpoint stores besides the weights); ``_train_step`` takes one optimizer
step on this rank's shard of the global batch (losses, gradients and status counts summed
over the ranks), ``_train_epoch`` one epoch with its step checkpoints, ``_validate`` and
``_epoch_row`` the validation and the metrics.csv row of an epoch, ``_commit_epoch`` its
checkpoint, ``best.pt`` and records. A non-finite loss or parameters stop the run
(``_diverged``) naming the epoch and step.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from epo_casadi.errors import EpoError, SpecError
from scenarios.files import write_atomic

from .checkpoint import CHECKPOINT_FORMAT, CheckpointError, save_checkpoint
from .data import SceneDataset
from .distributed import World, all_sum, gather_objects, shard
from .losses import LossWeights, goal_loss, marginal_loss, scene_loss
from .models import count_parameters
from .records import plot_history, predictions_image, write_csv
from .scoring import METRICS, evaluate_model, mean_metrics, score_samples
from .train_config import TrainConfig


# --------------------------------------------------------------------------------------
# losses, records
# --------------------------------------------------------------------------------------
def compute_loss(
    kind: str,
    out: dict,
    gt: torch.Tensor,
    weights: LossWeights,
    mask: torch.Tensor | None = None,
    imitation_reduction: str = "mean",
) -> dict[str, torch.Tensor]:
    """The training loss of a model's output: scene loss (ours, SC) or marginal loss (V-LSTM),
    plus ``weights.goal`` times the goal loss when the model decodes goals (part ``goal``,
    zero otherwise). ``mask`` ``(B, N)``: the batch's ``agents_mask``; every per-agent term
    averages over its real agents only (:mod:`learning.losses`). ``imitation_reduction``:
    the imitation loss's reduction over the future steps, ``"mean"`` or ``"sum"``."""
    red = imitation_reduction
    if kind == "vlstm":
        parts = marginal_loss(
            out["pos"], out["marginal_logits"], gt, weights, mask=mask, imitation_reduction=red
        )
    else:
        parts = scene_loss(
            out["pos"], out["logits"], gt, weights, mask=mask, imitation_reduction=red
        )
    g = goal_loss(out, gt, mask)
    if g is None:
        parts["goal"] = torch.zeros((), dtype=parts["loss"].dtype)
    else:
        parts["goal"] = g
        parts["loss"] = parts["loss"] + weights.goal * g
    return parts


def _zero_sums() -> dict:
    return {
        "loss": 0.0,
        "imitation": 0.0,
        "probability": 0.0,
        "goal": 0.0,
        "samples": 0,
        "seconds": 0.0,
    }


def _diverged_error(epoch: int, step: int, lr: float, ck_path: Path, what: str) -> EpoError:
    kept = "the last checkpoint is kept" if ck_path.exists() else "no checkpoint was written yet"
    return EpoError(
        f"train: the loss diverged at epoch {epoch + 1}, step {step} ({what} became "
        f"non-finite); {kept}; try a lower learning rate than {lr:g} (--lr)"
    )


@contextlib.contextmanager
def _diverged(epoch: int, step: int, lr: float, ck_path: Path, what: str):
    """Turn the game layer's refusal of non-finite inputs into the divergence message.

    Huge weights after a step with a huge learning rate decode to inf/NaN game weights,
    which :class:`learning.layer.GameLayer` refuses; that message speaks of the layer's
    options, which a user of ``epo train`` cannot act on.
    """
    try:
        yield
    except SpecError as e:
        if getattr(e, "field", None) not in ("p", "u_init"):  # the layer's inputs only
            raise
        raise _diverged_error(epoch, step, lr, ck_path, what) from None


@dataclass
class _Progress:
    """Where a run stands: what a checkpoint stores besides the weights and RNG."""

    epoch: int = 0  #: epochs completed
    step: int = 0  #: optimizer steps completed
    start_batch: int = 0  #: batches of the current epoch already done
    sums: dict = field(default_factory=_zero_sums)  #: the current epoch's sums so far
    history: list[dict] = field(default_factory=list)  #: metrics.csv rows
    best: float = math.inf  #: lowest validation minSADE so far
    step_losses: list[tuple[int, float]] = field(default_factory=list)  #: of this call


@dataclass
class _Run:
    """What the steps of one training call share: settings, data, model, files."""

    cfg: TrainConfig
    out: Path
    train_ds: SceneDataset
    val_ds: SceneDataset | None
    model: nn.Module
    opt: torch.optim.Optimizer
    summary: dict  #: the game summary (checkpoint ``game``)
    fingerprint: dict  #: the dataset identity (checkpoint ``data``)
    data_dir: Path = Path(".")  #: the dataset folder
    world: World = World()  #: this process's rank and the number of ranks
    net: nn.Module | None = None  #: what a training step calls: ``model`` or its DDP wrapper

    @property
    def ck_path(self) -> Path:
        return self.out / "checkpoint.pt"

    @property
    def best_path(self) -> Path:
        return self.out / "best.pt"

    def snapshot(self, pr: _Progress, epoch: int, step: int, in_epoch: int) -> dict:
        """The checkpoint of the run now (format :data:`~learning.checkpoint.CHECKPOINT_FORMAT`)."""
        return {
            "format": CHECKPOINT_FORMAT,
            "config": self.cfg.to_dict(),
            "game": self.summary,
            "data": self.fingerprint,
            "model": self.model.state_dict(),
            "optimizer": self.opt.state_dict(),
            "rng": torch.get_rng_state(),
            "epoch": epoch,
            "step": step,
            "step_in_epoch": in_epoch,
            "sums": dict(pr.sums),
            "history": pr.history,
            "best": pr.best,
        }

    def facts(self, pr: _Progress) -> dict:
        """What every rank must agree on (:func:`learning.distributed.agree`)."""
        sizes = {"train": len(self.train_ds)}
        sizes["val"] = None if self.val_ds is None else len(self.val_ds)
        return {
            "config": self.cfg.to_dict(),
            "data": {**self.fingerprint, "samples": sizes, "game": self.summary},
            "resume": {"epoch": pr.epoch, "step": pr.step, "step_in_epoch": pr.start_batch},
        }

    def close(self) -> None:
        self.train_ds.close()
        if self.val_ds is not None:
            self.val_ds.close()


def _restore(run: _Run, state: dict) -> _Progress:
    """Model, optimizer and torch RNG states and the progress of a checkpoint."""
    try:
        run.model.load_state_dict(state["model"])
        run.opt.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["rng"])
    except (RuntimeError, KeyError, ValueError, TypeError) as e:
        raise CheckpointError(
            str(run.ck_path), f"does not fit the model ({str(e).splitlines()[0][:160]})"
        ) from None
    return _Progress(
        epoch=int(state["epoch"]),
        step=int(state["step"]),
        start_batch=int(state["step_in_epoch"]),
        sums=dict(state["sums"]),
        history=list(state["history"]),
        best=float(state["best"]),
    )


def _write_run_info(run: _Run, data_dir) -> None:
    """``config.json``: settings, dataset identity, counts, schema and meta, game, sizes."""
    ds = run.train_ds
    info = {
        "train": run.cfg.to_dict(),
        "data": {
            "directory": str(Path(data_dir).resolve()),
            **run.fingerprint,
            "counts": ds.manifest.get("counts"),
            # shapes and meta (frame) of the samples: what a closed-loop planner rebuilds
            "schema": {k: v["shape"] for k, v in ds.manifest["schema"].items()},
            "meta": ds.manifest.get("meta", {}),
        },
        "game": run.summary,
        "parameters": count_parameters(run.model),
        "torch": torch.__version__,
    }
    write_atomic(run.out / "config.json", json.dumps(info, indent=1) + "\n")


def _status_names(kind: str) -> tuple[str, ...]:
    """Names of a model's per-problem solver statuses (``out["status"]`` codes), or ()."""
    if kind == "epo":
        from .layer import STATUS_CODES

        return tuple(s.value for s in STATUS_CODES)
    if kind == "tgl":
        return ("solved", "osqp_only", "failed")  # learning.tgl.QPStatus 0, 1, 2
    return ()


_PARTS = ("imitation", "probability", "goal")


def _status_counts(run: _Run, res: dict) -> torch.Tensor:
    """Problems of the step per status (float64 ``(len(names),)``; empty without a layer)."""
    names = _status_names(run.cfg.model.kind)
    st = res.get("status")
    if not names or st is None:
        return torch.zeros(len(names), dtype=torch.float64)
    c = torch.bincount(st.detach().reshape(-1).long().cpu(), minlength=len(names))
    return c[: len(names)].double()


def _global_loss(run: _Run, parts: dict, res: dict, batch: dict, n_global: int):
    """``(objective, values, statuses)`` of this rank's shard of a global batch.

    Each loss part is a mean over the shard's samples or (the marginal loss, the goal
    classification) over its real agents; ``objective`` weights this rank's parts by the
    shard's share of the global count, times the number of ranks, so the gradient
    DistributedDataParallel averages over the ranks is that of the global batch's loss.
    ``values``: the global batch's loss parts (floats); ``statuses``: layer status counts
    over all ranks."""
    w, kind, size = run.cfg.loss_weights, run.cfg.model.kind, run.world.size
    n = int(batch["history"].shape[0])
    mask = batch.get("agents_mask")
    agents = float(mask.sum()) if mask is not None else float(n * batch["history"].shape[2])
    by = {
        "imitation": "agents" if kind == "vlstm" else "samples",
        "probability": "agents" if kind == "vlstm" else "samples",
        "goal": "agents" if "goal_logits" in res else "samples",
    }
    mine = {"samples": float(n), "agents": agents}
    status = _status_counts(run, res)
    local = torch.tensor(
        [mine["samples"], mine["agents"]]
        + [float(parts[k].detach()) * mine[by[k]] for k in _PARTS],
        dtype=torch.float64,
    )
    tot = all_sum(torch.cat([local, status]))
    count = {"samples": float(tot[0]), "agents": float(tot[1])}
    coef = {
        "imitation": w.imitation,
        "probability": w.probability,
        "goal": w.goal if res.get("decoded_goals", False) else 0.0,
    }
    objective = sum(
        coef[k] * parts[k] * (size * mine[by[k]] / max(count[by[k]], 1.0)) for k in _PARTS
    )
    vals = {k: float(tot[2 + i]) / max(count[by[k]], 1.0) for i, k in enumerate(_PARTS)}
    vals = {"loss": sum(coef[k] * vals[k] for k in _PARTS), **vals}
    return objective, vals, tot[2 + len(_PARTS) :]


@contextlib.contextmanager
def _ddp_quiet():
    """Without DDP's note that a model used every parameter of a batch (it looks for
    unused ones, e.g. the lane encoder on data without lanes): not for the user."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "find_unused_parameters=True was specified")
        yield


def _train_step(run: _Run, pr: _Progress, batch: dict, t0: float, n_global: int) -> dict | None:
    """One optimizer step on ``batch`` (this rank's shard of a global batch of ``n_global``
    samples); the global batch's loss parts as floats (None: batch skipped)."""
    cfg, model = run.cfg, run.model
    if n_global * cfg.model.modes < 2:  # BatchNorm needs two values per channel
        return None
    with _ddp_quiet() if run.world.size > 1 else contextlib.nullcontext():
        with _diverged(pr.epoch, pr.step + 1, cfg.lr, run.ck_path, "the model's output"):
            res = run.net(batch)
        parts = compute_loss(
            cfg.model.kind,
            res,
            batch["gt"],
            cfg.loss_weights,
            batch.get("agents_mask"),
            cfg.imitation_reduction,
        )
        if run.world.size == 1:
            loss, vals, status = parts["loss"], None, _status_counts(run, res)
            finite = bool(torch.isfinite(loss))
        else:
            loss, vals, status = _global_loss(run, parts, res, batch, n_global)
            finite = math.isfinite(vals["loss"])  # the same on every rank
        if not finite:
            raise _diverged_error(pr.epoch, pr.step + 1, cfg.lr, run.ck_path, "the loss")
        run.opt.zero_grad(set_to_none=True)
        loss.backward()
    run.opt.step()
    pr.step += 1
    if not all(bool(torch.isfinite(p).all()) for p in model.parameters()):
        raise _diverged_error(pr.epoch, pr.step, cfg.lr, run.ck_path, "the weights")
    if vals is None:
        vals = {k: v.item() for k, v in parts.items()}
    for k in ("loss", "imitation", "probability", "goal"):
        pr.sums[k] = pr.sums.get(k, 0.0) + vals[k] * n_global
    for name, c in zip(_status_names(cfg.model.kind), status.tolist(), strict=True):
        pr.sums[f"layer_{name}"] = pr.sums.get(f"layer_{name}", 0) + int(c)
        vals[f"layer_{name}"] = int(c)
    pr.sums["samples"] += n_global
    pr.sums["seconds"] = time.perf_counter() - t0
    pr.step_losses.append((pr.step, vals["loss"]))
    return vals


def _train_epoch(run: _Run, pr: _Progress, writer, progress: bool, on_step) -> float:
    """The batches of epoch ``pr.epoch`` from ``pr.start_batch`` on (order: the permutation
    of ``(seed, epoch)``; on several ranks each takes its :func:`~learning.distributed.shard`
    of every batch); returns the epoch's start time (less the seconds spent in it before a
    resume)."""
    cfg, world = run.cfg, run.world
    nb = run.train_ds.num_batches(cfg.batch_size)
    bar = None
    try:
        if progress and world.main:
            from tqdm import tqdm

            bar = tqdm(
                total=nb,
                initial=pr.start_batch,
                desc=f"{cfg.model.kind} epoch {pr.epoch + 1}/{cfg.epochs}",
                unit="batch",
                dynamic_ncols=True,
                leave=False,
            )
        run.model.train()
        t0 = time.perf_counter() - pr.sums["seconds"]
        order = run.train_ds.order(shuffle=True, seed=cfg.seed, epoch=pr.epoch)
        B = cfg.batch_size
        for b in range(pr.start_batch, nb):
            idx = order[b * B : (b + 1) * B]
            if len(idx) < world.size:  # a last batch with fewer samples than ranks
                continue
            part = shard(idx, world.rank, world.size) if world.size > 1 else idx
            vals = _train_step(run, pr, run.train_ds.batch(part), t0, len(idx))
            if vals is None:
                continue
            if writer is not None:
                for k, v in vals.items():
                    tag = f"layer/{k[6:]}" if k.startswith("layer_") else f"train/{k}"
                    writer.add_scalar(tag, v, pr.step)
                writer.add_scalar("train/lr", run.opt.param_groups[0]["lr"], pr.step)
            if bar is not None:
                bar.update(1)
                rate = pr.sums["samples"] / max(pr.sums["seconds"], 1e-9)
                bar.set_postfix(loss=f"{vals['loss']:.4g}", rate=f"{rate:.1f} samples/s")
            if cfg.checkpoint_steps and pr.step % cfg.checkpoint_steps == 0 and b + 1 < nb:
                if world.main:
                    save_checkpoint(run.snapshot(pr, pr.epoch, pr.step, b + 1), run.ck_path)
            if on_step is not None:
                on_step(pr.step, vals)
    finally:
        if bar is not None:
            bar.close()
    return t0


def _validate(run: _Run) -> dict:
    """Validation metrics of the model now: :func:`~learning.scoring.evaluate_model`; on
    several ranks each scores its shard of the split and the per-sample values of all
    ranks are averaged as one process does (:func:`~learning.scoring.mean_metrics`)."""
    world, ds = run.world, run.val_ds
    if world.size == 1:
        return evaluate_model(run.model, ds, batch_size=run.cfg.eval_batch_size)
    idx = shard(np.arange(len(ds), dtype=np.int64), world.rank, world.size)
    per = score_samples(run.model, _Shard(ds, idx), batch_size=run.cfg.eval_batch_size)
    gathered = [p for p in gather_objects(per if len(idx) else None) if p is not None]
    keys = list(dict.fromkeys(k for p in gathered for k in p))
    return mean_metrics({k: np.concatenate([p[k] for p in gathered if k in p]) for k in keys})


class _Shard:
    """The samples ``indices`` of a split, read like the split (what scoring reads)."""

    def __init__(self, ds: SceneDataset, indices: np.ndarray):
        self._ds, self._idx = ds, indices

    def __getattr__(self, name):
        return getattr(self._ds, name)

    def __len__(self) -> int:
        return len(self._idx)

    def batches(self, batch_size: int, **_):
        for i in range(0, len(self._idx), batch_size):
            yield self._ds.batch(self._idx[i : i + batch_size])


def _epoch_row(run: _Run, pr: _Progress, t0: float) -> dict:
    """The metrics.csv row of the epoch just trained: training sums, then validation."""
    seconds = time.perf_counter() - t0
    sums = pr.sums
    ns = max(sums["samples"], 1)
    row = {
        "epoch": pr.epoch + 1,
        "step": pr.step,
        "seconds": round(seconds, 3),
        "samples_per_s": round(sums["samples"] / max(seconds, 1e-9), 3),
        "train_loss": sums["loss"] / ns,
        "train_imitation": sums["imitation"] / ns,
        "train_probability": sums["probability"] / ns,
        "train_goal": sums.get("goal", 0.0) / ns,
        "lr": run.opt.param_groups[0]["lr"],
    }
    for name in _status_names(run.cfg.model.kind):
        row[f"layer_{name}"] = int(sums.get(f"layer_{name}", 0))
    if run.val_ds is not None:
        t1 = time.perf_counter()
        with _diverged(pr.epoch, pr.step, run.cfg.lr, run.ck_path, "the validation output"):
            vm = _validate(run)
        row.update({f"val_{k}": vm[k] for k in METRICS})
        # the initial strategies of a model with them (ours): val_init_minADE, ...
        row.update({f"val_init_{k}": vm[f"init_{k}"] for k in METRICS if f"init_{k}" in vm})
        row["val_seconds"] = round(time.perf_counter() - t1, 3)
    else:
        row.update({f"val_{k}": math.nan for k in METRICS})
    return row


def _commit_epoch(run: _Run, pr: _Progress, row: dict, writer) -> None:
    """Record the epoch: ``best.pt`` if it improved, metrics.csv, loss.png, then the
    checkpoint (last: it commits the epoch), then TensorBoard (rank 0 writes; every rank
    keeps the same progress)."""
    pr.history.append(row)
    pr.epoch += 1
    pr.start_batch = 0
    pr.sums = _zero_sums()
    score = row["val_minSADE"]
    improved = run.val_ds is None or score < pr.best
    if improved and run.val_ds is not None:
        pr.best = score
    if not run.world.main:
        return
    snap = run.snapshot(pr, pr.epoch, pr.step, 0)
    if improved:
        keep = ("format", "config", "game", "data", "model", "epoch", "step")
        save_checkpoint({k: snap[k] for k in keep} | {"metrics": row}, run.best_path)
    write_csv(run.out / "metrics.csv", pr.history)
    plot_history(pr.history, run.out / "loss.png", title=f"{run.cfg.model.kind}: {run.out.name}")
    # the checkpoint last: it commits the epoch, so a failed write of any file (a full
    # disk) leaves the previous epoch's checkpoint, and a rerun redoes the epoch and
    # writes every file again
    save_checkpoint(snap, run.ck_path)
    if writer is not None:
        for k, v in row.items():
            if k.startswith(("val_", "train_", "layer_")) or k in ("lr", "samples_per_s"):
                if math.isfinite(v):
                    writer.add_scalar(f"epoch/{k}", v, pr.step)
        split = run.cfg.val_split if run.val_ds is not None else "train"
        image = predictions_image(run.out, run.data_dir, split)
        if image is not None:
            writer.add_image("predictions", image, pr.step, dataformats="HWC")
        writer.flush()
