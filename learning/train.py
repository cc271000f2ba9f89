"""Training: :class:`TrainConfig` and :func:`train` (paper Sec. 4.3, 5, App. F.4).

Optimizer and losses
    Adam, batch size 32, learning rate ``5e-5`` (the paper's for ours on RPI and exiD).
    Loss weights ``(lambda_imit, lambda_goal, lambda_prob)`` by model kind
    (:data:`PAPER_LOSS_WEIGHTS`): ours ``(1, 0.1, 0.1)``; V-LSTM + SC ``(1, 0, 1)``
    (``L_imit + L_prob``, Sec. 5); V-LSTM marginal: minADE + classification ``(1, -, 1)``.
    The goal loss is zero on RPI (goals are given). ``imitation_reduction`` reduces the
    imitation loss over the future steps: ``"mean"`` (the default) or ``"sum"`` (the
    paper's App. F.4 form, ``K`` times the mean; :mod:`learning.losses`). The networks
    train in float32; the game layer solves in float64 inside and casts back
    (:mod:`learning.layer`). Padded agents
    (the batch's ``agents_mask`` False, :mod:`learning.masks`) count in no loss term.

A run directory (``out_dir``)::

    config.json      TrainConfig, dataset identity (scenario, recipe, seed), game summary
    checkpoint.pt    the latest state: model, optimizer, torch RNG, epoch, step, history
    best.pt          model weights of the epoch with the lowest validation minSADE
    metrics.csv      one row per epoch: train loss parts, samples/s, learning rate, the
                     game layer's status counts (``layer_<status>``: ours, + TGL),
                     validation metrics (``val_<metric>``; for ours also those of the
                     initial strategies, ``val_init_<metric>``: :mod:`learning.scoring`)
    loss.png         training loss and validation minADE/minSADE per epoch
    tb/              TensorBoard events, with ``tensorboard=True`` (``epo train``: unless
                     ``--no-tensorboard``): per step ``train/loss``, ``train/imitation``,
                     ``train/probability``, ``train/goal``, ``train/lr`` and
                     ``layer/<status>`` (problems of the step per status); per epoch
                     ``epoch/<column>`` of metrics.csv and the image ``predictions`` (the
                     figure of ``epo show-predictions RUN --checkpoint last`` for sample 0
                     of the validation split)
    .lock            held (flock) while a training runs: a second ``train`` into the
                     same folder is refused at once (:func:`scenarios.files.output_lock`)

A run folder is never a dataset folder (one holding ``manifest.json``): :func:`train`
refuses one (:func:`check_run_dir`) before anything is written.

Checkpoints and resume
    A checkpoint is written at the end of every epoch (and every ``checkpoint_steps``
    optimizer steps, if set) to a temporary file, fsynced and renamed
    (:func:`scenarios.files.write_atomic`, like every file of the run): a run killed at
    any moment, or stopped by a full disk or a read-only folder (one
    :class:`~epo_casadi.errors.OutputError` naming the file), leaves the previous
    checkpoint intact and no partial file. ``checkpoint.pt`` and ``best.pt``
    carry a sha256 of their content (the file format: :mod:`learning.checkpoint`);
    :func:`~learning.checkpoint.load_checkpoint` verifies it and refuses a changed or
    damaged file naming it. A file written before checksums existed (a plain
    ``torch.save`` zip) still loads, with a
    :class:`~learning.checkpoint.UncheckedCheckpointWarning`; the next checkpoint of a
    resumed run is written with a checksum.
    :func:`train` on a directory that holds a checkpoint continues from it: same model,
    optimizer and RNG states, and the batches of an epoch come from the permutation of
    ``(seed, epoch)`` (:meth:`learning.data.SceneDataset.order`), so the resumed run takes
    exactly the steps the uninterrupted one would have taken (tested: equal next-step
    loss). Raising
    ``epochs`` and running again trains on; a different setting (other than ``epochs``,
    ``checkpoint_steps``, ``eval_batch_size``) or another dataset is refused, and so is a
    ``best.pt`` of another run (other model or settings). A directory that holds
    ``best.pt`` or ``metrics.csv`` but no ``checkpoint.pt`` is refused rather than
    trained from scratch over that history. A loss or parameters that become non-finite
    stop the run with one line naming the epoch and step (and suggesting a lower
    learning rate); the last checkpoint is kept.

Several processes
    In a process group (``torchrun``, ``epo train --nproc N``,
    :func:`train_parallel`) every rank runs :func:`train`: each takes
    a shard of every batch, gradients and batch-norm statistics span the global batch,
    ``metrics.csv`` holds the global batch's numbers, rank 0 writes the files, and the
    checkpoint does not depend on the number of ranks (details: :mod:`learning.distributed`).
    ``batch_size`` must be at least the number of ranks; on ``W`` ranks a last, partial
    batch of fewer than ``W`` samples is skipped.

BatchNorm in the scene-probability decoder needs two values per channel: a training batch
of one sample with ``modes = 1`` is skipped (only possible for a last, partial batch).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import torch
from torch import nn

from epo_casadi.errors import EpoError, SpecError
from scenarios.dataset import MANIFEST, DatasetError, check_output_dir
from scenarios.files import output_lock, write_atomic

from .checkpoint import (
    CHECKPOINT_FORMAT,
    RESUMABLE_CHANGES,
    CheckpointError,
    check_game,
    checkpoint_path,
    comparable_settings,
    load_checkpoint,
    save_checkpoint,
    setting_diff,
)
from .data import SceneDataset, game_summary
from .distributed import (
    World,
    agree,
    all_sum,
    convert_sync_batchnorm,
    gather_objects,
    joined,
    launch,
    shard,
)
from .losses import IMITATION_REDUCTIONS, LossWeights, goal_loss, marginal_loss, scene_loss
from .models import ModelConfig, build_model, count_parameters
from .records import plot_history, predictions_image, tensorboard_writer, write_csv
from .scoring import METRICS, evaluate_model, mean_metrics, score_samples

__all__ = [
    "PAPER_LOSS_WEIGHTS",
    "TrainConfig",
    "TrainResult",
    "check_run_dir",
    "compute_loss",
    "load_model",
    "torch_threads",
    "train",
    "train_parallel",
]

#: loss weights of the paper by model kind (imitation, goal, probability)
PAPER_LOSS_WEIGHTS = {
    "epo": LossWeights(1.0, 0.1, 0.1),
    "sc": LossWeights(1.0, 0.0, 1.0),
    "vlstm": LossWeights(1.0, 0.0, 1.0),
    "tgl": LossWeights(1.0, 0.0, 1.0),  # scene loss, as + SC (learning.tgl)
}


def _int(name, v, lo):
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise SpecError(f"train.{name}", f"expected an integer >= {lo}, got {v!r}")


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (with the dataset). Frozen; unknown keys fail."""

    model: ModelConfig = ModelConfig()  #: architecture, modes, game-layer steps (S, alpha, lambda)
    epochs: int = 10  #: passes over the training split
    batch_size: int = 32  #: samples per optimizer step (paper: 32)
    lr: float = 5e-5  #: Adam learning rate (paper, ours on RPI/exiD: 5e-5)
    seed: int = 0  #: initial weights and the shuffling of every epoch
    loss: LossWeights | None = None  #: None: PAPER_LOSS_WEIGHTS of the model kind
    checkpoint_steps: int = 0  #: also checkpoint every this many steps (0: at epoch ends only)
    eval_batch_size: int = 64  #: batch size of the validation pass
    val_split: str | None = "val"  #: split scored after every epoch (None: none)
    #: the imitation loss over the future steps: "mean" or "sum" (the paper's App. F.4)
    imitation_reduction: str = "mean"

    def __post_init__(self):
        if not isinstance(self.model, ModelConfig):
            raise SpecError(
                "train.model", f"expected a ModelConfig, got {type(self.model).__name__}"
            )
        if self.loss is not None and not isinstance(self.loss, LossWeights):
            raise SpecError("train.loss", f"expected LossWeights or None, got {self.loss!r}")
        _int("epochs", self.epochs, 1)
        _int("batch_size", self.batch_size, 1)
        _int("seed", self.seed, 0)
        _int("checkpoint_steps", self.checkpoint_steps, 0)
        _int("eval_batch_size", self.eval_batch_size, 1)
        lr = self.lr
        if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not 0 < lr < math.inf:
            raise SpecError("train.lr", f"expected a finite number > 0, got {lr!r}")
        if self.imitation_reduction not in IMITATION_REDUCTIONS:
            raise SpecError(
                "train.imitation_reduction",
                f"expected one of {list(IMITATION_REDUCTIONS)}, got {self.imitation_reduction!r}",
            )
        if self.val_split not in (None, "train", "val", "test"):
            raise SpecError(
                "train.val_split",
                f"expected 'val', 'test', 'train' or None, got {self.val_split!r}",
            )

    @property
    def loss_weights(self) -> LossWeights:
        """The loss weights used: ``loss``, or the paper's for the model kind."""
        return self.loss if self.loss is not None else PAPER_LOSS_WEIGHTS[self.model.kind]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["loss"] = asdict(self.loss_weights)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys (also in ``model`` and ``loss``) fail."""
        if not isinstance(d, dict):
            raise SpecError("train", f"expected a mapping, got {type(d).__name__}")
        d = dict(d)
        for key, klass in (("model", ModelConfig), ("loss", LossWeights)):
            sub = d.get(key)
            if isinstance(sub, dict):
                names = {f.name for f in fields(klass)}
                unknown = sorted(set(sub) - names)
                if unknown:
                    raise SpecError(
                        f"train.{key}", f"unknown field(s) {unknown}; allowed: {sorted(names)}"
                    )
                if key == "model" and "lane_path" not in sub:
                    # saved before ModelConfig.lane_path existed: ours used the current lane
                    sub = {**sub, "lane_path": "current"}
                d[key] = klass(**sub)
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise SpecError("train", f"unknown field(s) {unknown}; allowed: {sorted(names)}")
        return cls(**d)


@dataclass
class TrainResult:
    """What one :func:`train` call did."""

    run_dir: str
    epochs: int  #: epochs completed in the run (all calls)
    steps: int  #: optimizer steps completed in the run (all calls)
    history: list[dict]  #: the rows of metrics.csv
    seconds: float  #: wall time of this call
    resumed_from: int | None = None  #: step of the checkpoint this call resumed from
    step_losses: list[tuple[int, float]] = field(default_factory=list)  #: (step, loss) of this call


# --------------------------------------------------------------------------------------
# loading a run
# --------------------------------------------------------------------------------------
def _checkpoint_config(ck: dict, where: str) -> TrainConfig:
    try:
        return TrainConfig.from_dict(ck["config"])
    except (SpecError, TypeError) as e:
        raise CheckpointError(f"{where}.config", str(e)) from None


def _check_same_run(ck: dict, run_config: dict, path: Path) -> None:
    """Refuse a checkpoint whose settings differ from its run directory's (another run's file)."""
    diff = setting_diff(_checkpoint_config(ck, str(path)).to_dict(), run_config)
    if diff is not None:
        raise CheckpointError(
            str(path),
            f"belongs to another run: its {diff} differs from the run's config.json; "
            "copy back the run's own file or retrain",
        )


def load_model(run_dir: str | os.PathLike, game, which: str = "best"):
    """Model of a run directory for ``game`` in eval mode: ``(model, TrainConfig, checkpoint)``.

    ``which``: ``"best"`` (``best.pt``, falling back to ``checkpoint.pt`` when a run has
    no validation split yet) or ``"last"`` (``checkpoint.pt``).
    """
    d = Path(run_dir)
    path = checkpoint_path(d, which)
    ck = load_checkpoint(path)
    cfg = _checkpoint_config(ck, str(path))
    info = d / "config.json"
    if info.is_file():  # the run's own settings: a file copied from another run is refused
        try:
            run_config = TrainConfig.from_dict(json.loads(info.read_text())["train"]).to_dict()
        except (ValueError, KeyError, TypeError, SpecError) as e:
            raise CheckpointError(str(info), f"unreadable run settings ({e})") from None
        _check_same_run(ck, run_config, path)
    check_game(ck["game"], game, str(path))
    model = build_model(cfg.model, game)
    try:
        model.load_state_dict(ck["model"])
    except (RuntimeError, KeyError, TypeError) as e:
        raise CheckpointError(
            f"{path}.model", f"weights do not fit the model ({str(e).splitlines()[0][:160]})"
        ) from None
    model.eval()
    return model, cfg, ck


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


@contextlib.contextmanager
def torch_threads(n: int | None):
    """Run a block with ``n`` torch intra-op threads (None: leave as is), then restore.

    One thread is the default of the commands: these networks are small, and on a shared
    2-core machine two OpenMP threads made a training step 10-20x slower than one
    (measured in ``docs/learning.md``).
    """
    if n is None:
        yield
        return
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise SpecError("threads", f"expected an integer >= 1 or None, got {n!r}")
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


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


# --------------------------------------------------------------------------------------
# training
# --------------------------------------------------------------------------------------
def train(
    data_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    config: TrainConfig = TrainConfig(),
    *,
    progress: bool = True,
    on_step: Callable[[int, dict], None] | None = None,
    threads: int | None = 1,
    tensorboard: bool = False,
) -> TrainResult:
    """Train ``config.model`` on the train split of ``data_dir``; resume ``out_dir`` if it has a checkpoint.

    ``on_step(step, parts)`` runs after every optimizer step (and its checkpoint, if
    one is due) with the loss parts as floats; tests raise from it to simulate a kill.
    ``threads``: torch threads during the call (:func:`torch_threads`; None: unchanged).
    ``tensorboard``: also write TensorBoard events to ``out_dir/tb`` (module docstring).
    In a process group of several ranks (``torchrun``,
    :func:`train_parallel`) every rank calls this with the same
    arguments: data-parallel training, rank 0 writing the files
    (:mod:`learning.distributed`).
    Returns a :class:`TrainResult`; see the module docstring for the files written.
    """
    if not isinstance(config, TrainConfig):
        raise SpecError("config", f"expected a TrainConfig, got {type(config).__name__}")
    with joined() as world, torch_threads(threads), contextlib.ExitStack() as stack:
        run = error = None
        try:
            out = check_run_dir(out_dir, data_dir)
            if world.main:  # one lock per run: rank 0 holds it for all ranks
                stack.enter_context(output_lock(out, "epo train"))
            run, pr, resumed_from = _start(data_dir, out, config, world)
            stack.callback(run.close)
        except Exception as e:  # every rank learns of it (agree), none waits for the others
            error = e
        agree(world, {} if run is None else run.facts(pr), error)
        return _train(run, pr, resumed_from, progress, on_step, tensorboard)


def check_run_dir(
    out_dir: str | os.PathLike, data_dir: str | os.PathLike | None = None, field: str = "out"
) -> Path:
    """``out_dir`` as a run folder to create or resume; refused before anything is written.

    A path through a file is a :class:`CheckpointError`; a dataset folder (one holding
    ``manifest.json``, or ``data_dir`` itself) is a :class:`SpecError` naming ``field``:
    a run's files never go into a dataset.
    """
    out = Path(out_dir)
    try:
        check_output_dir(out)
    except DatasetError as e:
        raise CheckpointError(e.where, e.message) from None
    same = data_dir is not None and out.exists() and out.resolve() == Path(data_dir).resolve()
    if same or (out / MANIFEST).is_file():
        raise SpecError(
            field,
            f"{out} is a dataset folder (it holds {MANIFEST}); give a run folder of its own, "
            "e.g. runs/NAME",
        )
    return out


def _open_splits(data_dir, cfg: TrainConfig) -> tuple[SceneDataset, SceneDataset | None]:
    """The train split (refused when empty, or without the goals ours reads) and the
    validation split (None when ``cfg.val_split`` is None or the split is empty)."""
    train_ds = SceneDataset(data_dir, "train")
    if len(train_ds) == 0:
        raise SpecError("data", f"{data_dir}: the train split has no samples")
    game = train_ds.game
    m = cfg.model
    has_goal_param = any(f"goal.{a}" in game.params for a in game.agent_names)
    if m.kind == "epo" and m.goal_decoder == "given" and has_goal_param:
        if "goals" not in train_ds.fields:
            raise DatasetError(
                f"{Path(data_dir) / MANIFEST}.schema.goals",
                "missing; the model reads given goals (model.goal_decoder='given'): "
                "use --set goal_decoder=candidates or --set goal_decoder=regress",
            )
    val_ds = None
    if cfg.val_split is not None:
        val_ds = SceneDataset(data_dir, cfg.val_split)
        if len(val_ds) == 0:
            val_ds = None
    return train_ds, val_ds


def _resume_checkpoint(out: Path, data_dir, cfg: TrainConfig, fingerprint: dict, game):
    """The checkpoint ``out`` holds (None: a new run), refused when it belongs to another
    run (settings, dataset, game), or when an earlier run's files exist without it."""
    ck_path, best_path = out / "checkpoint.pt", out / "best.pt"
    history_files = [f for f in (best_path, out / "metrics.csv") if f.exists()]
    if not ck_path.exists() and history_files:
        raise CheckpointError(
            str(ck_path),
            f"missing, but {' and '.join(f.name for f in history_files)} of an earlier run "
            "exist and training from scratch would overwrite them; restore checkpoint.pt, "
            "or train into a new directory",
        )
    if not ck_path.exists():
        return None
    state = load_checkpoint(ck_path)
    old = comparable_settings(_checkpoint_config(state, str(ck_path)).to_dict())
    new = comparable_settings(cfg.to_dict())
    for k in new:
        if k not in RESUMABLE_CHANGES and old.get(k) != new[k]:
            raise CheckpointError(
                str(ck_path),
                f"holds a run with a different {k} ({old.get(k)!r}, now {new[k]!r}); "
                "use another output directory",
            )
    if json.dumps(state["data"], sort_keys=True) != json.dumps(fingerprint, sort_keys=True):
        raise CheckpointError(
            str(ck_path), f"holds a run trained on another dataset than {data_dir}"
        )
    check_game(state["game"], game, str(ck_path))
    if best_path.exists():  # verified now, and refused if it belongs to another run
        _check_same_run(load_checkpoint(best_path), cfg.to_dict(), best_path)
    return state


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


def _start(data_dir, out: Path, cfg: TrainConfig, world: World):
    """Open the splits, check a checkpoint to resume, seed and build the model (batch norm
    over all ranks on several) and optimizer, restore: ``(run, progress, resumed_from)``."""
    if world.size > cfg.batch_size:
        raise SpecError(
            "train.batch_size",
            f"expected at least one sample per rank ({world.size} ranks), got {cfg.batch_size}",
        )
    train_ds, val_ds = _open_splits(data_dir, cfg)
    try:
        game = train_ds.game
        summary, fingerprint = game_summary(game), train_ds.fingerprint
        state = _resume_checkpoint(out, data_dir, cfg, fingerprint, game)
        torch.manual_seed(cfg.seed)
        model = build_model(cfg.model, game)
        if world.size > 1:
            model = convert_sync_batchnorm(model)
        opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
        run = _Run(
            cfg, out, train_ds, val_ds, model, opt, summary, fingerprint, Path(data_dir), world
        )
        pr = _Progress() if state is None else _restore(run, state)
    except BaseException:
        train_ds.close()
        if val_ds is not None:
            val_ds.close()
        raise
    return run, pr, (pr.step if state is not None else None)


def _train(run: _Run, pr: _Progress, resumed_from, progress: bool, on_step, tb: bool):
    """The epochs of :func:`train` after a start every rank agreed on: wrap the model for
    several ranks, write ``config.json``, then per epoch train, validate and commit."""
    t_call = time.perf_counter()
    cfg, world = run.cfg, run.world
    run.net = run.model
    if world.size > 1:
        from torch.nn.parallel import DistributedDataParallel

        # parameters a model leaves unused (e.g. the lane encoder without lanes) get no
        # gradient on any rank; batch norm statistics are synchronized, not broadcast
        run.net = DistributedDataParallel(
            run.model, find_unused_parameters=True, forward_sync_buffers=False
        )
    writer = None
    if world.main:
        _write_run_info(run, run.data_dir)
        if tb and pr.epoch < cfg.epochs:
            writer = tensorboard_writer(run.out / "tb", pr.step)
            if writer is None:
                warnings.warn(
                    "tensorboard is not installed: no TensorBoard events are written "
                    "(pip install tensorboard, or train with --no-tensorboard)",
                    stacklevel=3,
                )
    try:
        while pr.epoch < cfg.epochs:
            t0 = _train_epoch(run, pr, writer, progress, on_step)
            _commit_epoch(run, pr, _epoch_row(run, pr, t0), writer)
    finally:
        if writer is not None:
            writer.close()
    return TrainResult(
        str(run.out),
        pr.epoch,
        pr.step,
        pr.history,
        time.perf_counter() - t_call,
        resumed_from,
        pr.step_losses,
    )


def _train_rank(data_dir, out_dir, config, progress, on_step, threads, tensorboard):
    rank = torch.distributed.get_rank()
    return train(
        data_dir,
        out_dir,
        config,
        progress=progress and rank == 0,
        on_step=on_step,
        threads=threads,
        tensorboard=tensorboard,
    )


def train_parallel(
    nproc: int,
    data_dir,
    out_dir,
    config=None,
    *,
    progress: bool = True,
    on_step=None,
    threads: int | None = 1,
    tensorboard: bool = False,
):
    """:func:`learning.train.train` on ``nproc`` local ranks (:func:`launch`); rank 0's
    :class:`~learning.train.TrainResult`. ``nproc = 1`` trains in this process.
    ``on_step`` runs on every rank (picklable: a module-level function)."""
    if isinstance(nproc, bool) or not isinstance(nproc, int) or nproc < 1:
        raise SpecError("nproc", f"expected an integer >= 1, got {nproc!r}")
    config = TrainConfig() if config is None else config
    if nproc == 1:
        return train(
            data_dir, out_dir, config, progress=progress, on_step=on_step, threads=threads,
            tensorboard=tensorboard,
        )  # fmt: skip
    args = (os.fspath(data_dir), os.fspath(out_dir), config, progress, on_step, threads)
    return launch(nproc, _train_rank, args + (tensorboard,))[0]
