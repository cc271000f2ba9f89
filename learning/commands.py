"""``epo train``, ``evaluate``, ``show-predictions``, ``show-weights``, ``pipeline``.

Thin click layer over :mod:`learning.train`, :mod:`learning.evaluate`, :mod:`learning.show`,
:mod:`learning.spider` and :mod:`learning.pipeline`; torch is imported only when a command
runs. Input errors (missing dataset, unknown split, corrupt checkpoint, unknown model)
raise the toolkit's typed errors, which :func:`scenarios.cli.main` prints as one
``error:`` line naming the field, with exit status 2.
"""

from __future__ import annotations

from pathlib import Path

import click

from epo_casadi.errors import SpecError

KINDS = ("epo", "sc", "vlstm", "tgl")
SPLITS = ("train", "val", "test")


def _parse_set(items: tuple[str, ...]) -> dict:
    """``KEY=VALUE`` model overrides, read by :func:`epo_casadi.settings.parse_settings`."""
    from epo_casadi.settings import parse_settings

    return parse_settings(items, "--set")


def _parse_loss_weights(text: str, field_name: str = "--loss-weights"):
    """``IMIT,GOAL,PROB`` (three finite numbers >= 0) as :class:`learning.losses.LossWeights`;
    anything else is a :class:`SpecError` naming ``field_name``."""
    import math

    from .losses import LossWeights

    parts = [p.strip() for p in str(text).split(",")]
    values = []
    for p in parts:
        try:
            values.append(float(p))
        except ValueError:
            values = None
            break
    if values is None or len(values) != 3 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise SpecError(
            field_name,
            "expected three finite numbers >= 0 separated by commas, lambda_1,lambda_2,lambda_3 "
            f"(imitation, goal, probability), e.g. 1,0.1,0.1; got {text!r}",
        )
    return LossWeights(*values)


def _model_config(kind: str, modes: int | None, data: Path, overrides: dict):
    from dataclasses import fields

    from scenarios.dataset import read_manifest

    from .models import ModelConfig

    if kind not in KINDS:
        raise SpecError("--model", f"expected one of {list(KINDS)}, got {kind!r}")
    names = {f.name for f in fields(ModelConfig)} - {"kind"}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise SpecError("--set", f"unknown model field(s) {unknown}; allowed: {sorted(names)}")
    if modes is None:
        fut = read_manifest(data)["schema"].get("future", {}).get("shape", [2])
        modes = int(fut[0])
    try:
        return ModelConfig(kind=kind, modes=modes, **overrides)
    except TypeError as e:
        raise SpecError("--set", str(e)) from None


@click.command("train")
@click.option(
    "--model",
    "kind",
    type=click.Choice(KINDS),
    default="epo",
    show_default=True,
    help="epo (ours), sc (+ SC), vlstm (marginal) or tgl (+ TGL); the backbone: "
    "--set backbone=vlstm|vibes|hivt.",
)
@click.option(
    "--data",
    required=True,
    type=click.Path(path_type=Path),
    help="Dataset directory (epo generate).",
)
@click.option(
    "--out",
    required=True,
    type=click.Path(path_type=Path),
    help="Run directory (resumed if it holds a checkpoint).",
)
@click.option("--epochs", type=click.IntRange(min=1), default=10, show_default=True)
@click.option("--batch-size", type=click.IntRange(min=1), default=32, show_default=True)
@click.option(
    "--lr",
    type=click.FloatRange(min=0, min_open=True),
    default=5e-5,
    show_default=True,
    help="Adam learning rate (paper: 5e-5).",
)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option(
    "--modes",
    type=click.IntRange(min=1),
    default=None,
    help="Joint modes M (default: the dataset's).",
)
@click.option(
    "--lm-steps",
    type=click.IntRange(min=1),
    default=None,
    help="S, LM steps of the game layer (default 2).",
)
@click.option(
    "--loss-weights",
    default=None,
    metavar="IMIT,GOAL,PROB",
    help="lambda_1,lambda_2,lambda_3 of L = l1 L_imit + l2 L_goal + l3 L_prob, e.g. 1,1,1 "
    "(default: the paper's for the model: ours 1,0.1,0.1; sc, tgl, vlstm 1,0,1).",
)
@click.option(
    "--imitation-reduction",
    type=click.Choice(["mean", "sum"]),
    default=None,
    help="The imitation loss over the future steps: mean (default) or sum (the paper's "
    "form, App. F.4; K times the mean).",
)
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="KEY=VALUE",
    help="Another ModelConfig field, e.g. --set hist_width=32, --set goal_decoder=candidates, --set learned_init=false (repeatable).",
)
@click.option(
    "--checkpoint-steps",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Also checkpoint every N steps (0: at epoch ends).",
)
@click.option(
    "--threads",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="torch threads (1 is fastest for these small networks on a shared machine).",
)
@click.option(
    "--preset",
    default=None,
    metavar="NAME",
    help="Settings of a paper experiment (learning.presets), e.g. waymo: batch 32, lr 1e-4, "
    "loss weights 1/1/1, imitation loss summed over the steps, M = 6, regressed goals; "
    "options given here override them.",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
@click.option(
    "--nproc",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Data-parallel ranks on this machine (each a process; under torchrun: 1, "
    "torchrun starts the ranks).",
)
@click.option(
    "--tensorboard/--no-tensorboard",
    default=True,
    show_default=True,
    help="Write TensorBoard events to OUT/tb (losses, learning rate, layer statuses, a "
    "predictions figure per epoch).",
)
def train_cmd(
    kind,
    data,
    out,
    epochs,
    batch_size,
    lr,
    seed,
    modes,
    lm_steps,
    loss_weights,
    imitation_reduction,
    overrides,
    checkpoint_steps,
    threads,
    progress,
    preset,
    nproc,
    tensorboard,
):
    """Train a model on the train split of a dataset; validate on val after every epoch.

    One training at a time per --out folder (a second is refused while the first runs);
    --out must not be a dataset folder. --nproc N trains on N local processes
    (data-parallel: each takes a shard of every batch); under torchrun every rank runs
    this command with the same options.
    """
    from .presets import get_preset
    from .train import TrainConfig, check_run_dir

    p = None if preset is None else get_preset(preset)
    given_loss = None if loss_weights is None else _parse_loss_weights(loss_weights)
    check_run_dir(out, data, field="--out")
    over = _parse_set(overrides)
    loss = None
    if p is not None:  # the preset's values where no option was given
        from click.core import ParameterSource

        from .losses import LossWeights

        ctx = click.get_current_context()
        defaults = (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)
        given = {n for n in ("batch_size", "lr") if ctx.get_parameter_source(n) not in defaults}
        batch_size = batch_size if "batch_size" in given else p.train.get("batch_size", batch_size)
        lr = lr if "lr" in given else p.train.get("lr", lr)
        pm = p.model_fields(kind)
        preset_modes = pm.pop("modes", None)
        modes = preset_modes if modes is None and "modes" not in over else modes
        over = {**pm, **over}
        loss = LossWeights(**p.loss)
        if imitation_reduction is None:
            imitation_reduction = p.imitation_reduction
    if given_loss is not None:
        loss = given_loss
    if lm_steps is not None:
        over["lm_steps"] = lm_steps
    model = _model_config(kind, modes, data, over)
    cfg = TrainConfig(
        model=model,
        epochs=epochs,
        batch_size=batch_size,
        lr=lr,
        seed=seed,
        loss=loss,
        checkpoint_steps=checkpoint_steps,
        imitation_reduction=imitation_reduction or "mean",
    )
    import os

    from scenarios.dataset import sigterm_as_interrupt

    from .train import train_parallel

    ranks = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if nproc > 1 and ranks > 1:
        raise SpecError(
            "--nproc", f"expected 1 inside a process group of {ranks} ranks (torchrun), got {nproc}"
        )
    with sigterm_as_interrupt():  # kill PID stops like Ctrl-C; the last checkpoint is kept
        res = train_parallel(
            nproc, data, out, cfg, progress=progress, threads=threads, tensorboard=tensorboard
        )
    if res.history and int(os.environ.get("RANK", "0") or 0) == 0:
        last = res.history[-1]
        files = "checkpoint.pt best.pt metrics.csv loss.png" + (" tb/" if tensorboard else "")
        click.echo(
            f"{out}: epoch {res.epochs}, step {res.steps}, train loss {last['train_loss']:.4g}, "
            f"val minADE {last['val_minADE']:.3f} minSADE {last['val_minSADE']:.3f} OR {last['val_OR']:.3f}, "
            f"{last['samples_per_s']:.1f} samples/s; files: {files}"
        )


@click.command("evaluate")
@click.argument("runs", nargs=-1, type=click.Path(path_type=Path))
@click.option("--data", required=True, type=click.Path(path_type=Path), help="Dataset directory.")
@click.option(
    "--split", type=click.Choice(SPLITS), default="test", show_default=True, help="Split to use."
)
@click.option(
    "--model",
    "baseline",
    type=click.Choice(["cv"]),
    default=None,
    help="A baseline to score as well: cv (constant velocity).",
)
@click.option(
    "--out",
    "out",
    type=click.Path(path_type=Path),
    default=None,
    help="Directory: write OUT/results.md, OUT/results.csv and OUT/results_runs.csv.",
)
@click.option(
    "--checkpoint", type=click.Choice(["best", "last"]), default="best", show_default=True
)
@click.option("--batch-size", type=click.IntRange(min=1), default=64, show_default=True)
@click.option(
    "--threads", type=click.IntRange(min=1), default=1, show_default=True, help="torch threads."
)
@click.option(
    "--subset",
    "subsets",
    multiple=True,
    metavar="EXPR",
    help="Also score the samples whose per-sample number FIELD compares so, e.g. "
    "'min_distance<1' (OP one of < <= > >= == !=), or a name: interacting (= "
    "'min_distance<1': the recorded agents come within 1 m of each other); a table beside "
    "the whole split's (repeatable).",
)
@click.option("--progress/--no-progress", default=False, show_default=True)
def evaluate_cmd(
    runs, data, split, baseline, out, checkpoint, batch_size, threads, subsets, progress
):
    """Score run directories (mean ± std over runs of one model) and baselines on a split.

    Each RUN counts once: a run folder given twice (also through another path) is
    refused. --out must not be the dataset folder. A dataset whose manifest names a focal
    agent (meta.focal_slot: the readers of recorded data) also gets ADE_focal / FDE_focal
    (best of the M modes) and ADE_focal_top1 / FDE_focal_top1 (the most likely mode).
    """
    from .evaluate import evaluate, parse_subset

    parsed = [parse_subset(s) for s in subsets]  # a malformed one before any work

    if baseline is not None and baseline != "cv":
        raise SpecError(
            "--model",
            f"expected 'cv' (trained models are given as RUN directories), got {baseline!r}",
        )
    if not runs and baseline is None:
        raise SpecError("RUN", "expected at least one run directory, or --model cv")
    if out is not None:  # before the evaluation: a bad --out wastes no time
        _check_results_dir(out.parent if out.suffix == ".md" else out, data)
    report = evaluate(
        list(runs),
        data,
        split,
        cv=baseline == "cv",
        batch_size=batch_size,
        checkpoint=checkpoint,
        progress=progress,
        threads=threads,
        subsets=parsed,
    )
    click.echo(report.markdown(), nl=False)
    if out is not None:
        if out.suffix == ".md":  # the old form: --out PREFIX.md wrote PREFIX.md, PREFIX.csv, ...
            click.echo(
                f"warning: --out {out}: a file name is deprecated and will be refused in a "
                "later version; give a directory (writes DIR/results.md, DIR/results.csv, "
                "DIR/results_runs.csv)",
                err=True,
            )
            paths = report.write(out.with_suffix(""))
        else:
            if out.exists() and not out.is_dir():
                raise SpecError("--out", f"expected a directory, {out} is a file")
            paths = report.write(out / "results")
        click.echo("wrote " + ", ".join(str(p) for p in paths))


def _check_results_dir(folder: Path, data: Path) -> None:
    """Refuse an evaluate --out folder that is a file, a dataset folder or not writable."""
    import os

    from epo_casadi.errors import OutputError
    from scenarios.dataset import MANIFEST
    from scenarios.files import check_output_dir

    if folder.exists() and not folder.is_dir():
        raise SpecError("--out", f"expected a directory, {folder} is a file")
    check_output_dir(folder)
    if (folder / MANIFEST).is_file() or (folder.exists() and folder.resolve() == data.resolve()):
        raise SpecError(
            "--out",
            f"{folder} is a dataset folder (it holds {MANIFEST}); give a folder of its own "
            "for the results",
        )
    near = next(a for a in (folder, *folder.parents) if a.exists())
    if not os.access(near, os.W_OK | os.X_OK):
        raise OutputError(folder, "Permission denied")


def _sample_figure_options(default_out: str):
    """RUN, --data, --split, --index, --out and --checkpoint of the one-sample figures."""

    def wrap(f):
        for deco in reversed(
            [
                click.argument("run", type=click.Path(path_type=Path)),
                click.option(
                    "--data", required=True, type=click.Path(path_type=Path),
                    help="Dataset directory.",
                ),
                click.option(
                    "--split", type=click.Choice(SPLITS), default="test", show_default=True,
                    help="Split to use.",
                ),
                click.option(
                    "--index", type=int, default=0, show_default=True,
                    help="Sample index in the split, 0 to its size - 1 (negative indices are "
                    "refused).",
                ),
                click.option(
                    "--out", "out", type=click.Path(dir_okay=False, path_type=Path),
                    default=Path(default_out), show_default=True,
                ),
                click.option(
                    "--checkpoint", type=click.Choice(["best", "last"]), default="best",
                    show_default=True,
                ),
            ]
        ):  # fmt: skip
            f = deco(f)
        return f

    return wrap


@click.command("show-predictions")
@_sample_figure_options("predictions.png")
@click.option(
    "--frame",
    type=click.Choice(["world", "scene"]),
    default="world",
    show_default=True,
    help="Recorded data (a dataset with `origin`): world, the recording's frame (the origin "
    "added back); scene, the sample's frame. Other datasets have one frame.",
)
def show_cmd(run, data, split, index, out, checkpoint, frame):
    """Draw one sample with a run's predicted modes, probabilities and (ours) weights; RUN may be cv.

    Recorded data: the real scene, i.e. the other recorded agents near the focal one (grey;
    ETH/UCY, CITR) or the lane map (Waymo), history solid, truth dashed, the modes coloured
    by their probability."""
    from .show import show_predictions

    png = show_predictions(run, data, index, out, split=split, checkpoint=checkpoint, frame=frame)
    click.echo(f"wrote {png}")


@click.command("show-weights")
@_sample_figure_options("weights.png")
def show_weights_cmd(run, data, split, index, out, checkpoint):
    """Spider plots of ours' predicted weights per mode, one panel per agent (as the paper's, App. G.1)."""
    from .spider import weight_spider

    click.echo(f"wrote {weight_spider(run, data, index, out, split=split, checkpoint=checkpoint)}")


@click.command("pipeline")
@click.option(
    "--out", "out", type=click.Path(path_type=Path), default=Path("epo-pipeline"), show_default=True
)
@click.option(
    "--samples",
    type=click.IntRange(min=1),
    default=1200,
    show_default=True,
    help="About N RPI samples.",
)
@click.option("--epochs", type=click.IntRange(min=1), default=15, show_default=True)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=1e-3, show_default=True)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="Generation processes (default: usable cores).",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
def pipeline_cmd(out, samples, epochs, seed, lr, workers, progress):
    """Generate a small RPI set, train ours and SC, evaluate with CV, draw predictions."""
    from scenarios.dataset import sigterm_as_interrupt

    from .pipeline import run_pipeline

    with sigterm_as_interrupt():  # kill PID stops like Ctrl-C: finished work is kept
        run_pipeline(
            out,
            samples=samples,
            epochs=epochs,
            seed=seed,
            lr=lr,
            workers=workers,
            progress=progress,
            echo=click.echo,
        )
