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

Modules. This module holds :func:`train`, :func:`train_parallel`, :func:`load_model`,
:func:`check_run_dir` and :func:`torch_threads`; the pieces live beside it and every name
stays importable from here: :mod:`learning.train_config` (:class:`TrainConfig`,
:class:`TrainResult`, :data:`PAPER_LOSS_WEIGHTS`) and :mod:`learning.train_loop`
(:func:`compute_loss` and the steps, epochs and records of one training call).
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import torch

from epo_casadi.errors import SpecError
from scenarios.dataset import MANIFEST, DatasetError, check_output_dir
from scenarios.files import output_lock

from .checkpoint import (
    RESUMABLE_CHANGES,
    CheckpointError,
    check_game,
    checkpoint_path,
    comparable_settings,
    load_checkpoint,
)
from .data import SceneDataset, game_summary
from .distributed import World, agree, convert_sync_batchnorm, joined, launch
from .models import build_model
from .records import tensorboard_writer
from .train_config import PAPER_LOSS_WEIGHTS, TrainConfig, TrainResult
from .train_config import _check_same_run as _check_same_run
from .train_config import _checkpoint_config as _checkpoint_config
from .train_config import _int as _int
from .train_loop import _PARTS as _PARTS
from .train_loop import _commit_epoch as _commit_epoch
from .train_loop import _ddp_quiet as _ddp_quiet
from .train_loop import _diverged as _diverged
from .train_loop import _diverged_error as _diverged_error
from .train_loop import _epoch_row as _epoch_row
from .train_loop import _global_loss as _global_loss
from .train_loop import _Progress as _Progress
from .train_loop import _restore as _restore
from .train_loop import _Run as _Run
from .train_loop import _Shard as _Shard
from .train_loop import _status_counts as _status_counts
from .train_loop import _status_names as _status_names
from .train_loop import _train_epoch as _train_epoch
from .train_loop import _train_step as _train_step
from .train_loop import _validate as _validate
from .train_loop import _write_run_info as _write_run_info
from .train_loop import _zero_sums as _zero_sums
from .train_loop import compute_loss

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


# --------------------------------------------------------------------------------------
# training
# --------------------------------------------------------------------------------------
def train(
    data_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    config: TrainConfig = TrainConfig(),  # noqa: B008 (frozen)
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
