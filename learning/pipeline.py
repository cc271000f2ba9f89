"""The small end-to-end job: data -> training (ours, SC) -> evaluation with CV -> figures.

:func:`run_pipeline` (``epo pipeline``) generates a small RPI set
(:meth:`scenarios.rpi.RPIRecipe.for_samples`), trains ours and V-LSTM + SC on it for a few
epochs, scores both and CV on the test split, prints the table and draws the
predictions of one test sample per model. Every stage resumes: run it again with the
same arguments and finished work (dataset shards, epochs) is kept.

Layout of ``out_dir``::

    data/                   the RPI dataset (manifest.json + shards)
    runs/epo-seed0/         training runs (checkpoints, metrics.csv, loss.png)
    runs/sc-seed0/
    results.md              the table (Markdown); results.csv, results_runs.csv
    figures/                predictions of one test sample per model (+ CV)
    pipeline.json           settings, counts and the seconds of every stage

Defaults are sized to finish in under 10 minutes on 2 shared CPU cores (measured in
``docs/learning.md``). The learning rate is ``1e-3``, not the paper's ``5e-5``:
the paper trains for many epochs on ~60k samples, here a few epochs on a few hundred
samples have to show learning. Pass ``lr=5e-5`` for the paper's setting.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from epo_casadi.errors import SpecError

__all__ = ["PipelineResult", "run_pipeline"]


@dataclass
class PipelineResult:
    """Where :func:`run_pipeline` put its results, and how long each stage took."""

    out_dir: Path
    data_dir: Path
    runs: dict[str, Path]
    table: str
    files: list[Path] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)


def _checked_workers(samples, epochs, seed, kinds, workers) -> int:
    """Refuse bad counts and kinds; the generation processes (default: usable cores)."""
    for name, v, lo in (("samples", samples, 1), ("epochs", epochs, 1), ("seed", seed, 0)):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise SpecError(name, f"expected an integer >= {lo}, got {v!r}")
    bad = [k for k in kinds if k not in ("epo", "sc", "vlstm")]
    if bad or not kinds:
        raise SpecError("kinds", f"expected some of 'epo', 'sc', 'vlstm', got {list(kinds)!r}")
    if workers is None:
        try:
            workers = max(1, len(os.sched_getaffinity(0)))
        except AttributeError:  # pragma: no cover - non-Linux
            workers = max(1, os.cpu_count() or 1)
    return workers


def _generate(data_dir: Path, samples, seed, workers, recipe_overrides, progress, echo):
    """Stage 1: the RPI dataset; ``(recipe, counts)``, refused when a split is empty."""
    from scenarios.dataset import generate
    from scenarios.rpi import RPIRecipe, RPIScenario

    t0 = time.perf_counter()
    recipe = RPIRecipe.for_samples(samples, **(recipe_overrides or {}))
    rep = generate(RPIScenario(recipe), data_dir, seed=seed, workers=workers, progress=progress)
    dt = time.perf_counter() - t0
    c = rep.counts
    echo(
        f"data: {data_dir}: train {c['train']}, val {c['val']}, test {c['test']} samples "
        f"({recipe.main_games} main games, {dt:.1f} s)"
    )
    if min(c.values()) == 0:
        raise SpecError("samples", f"a split got no samples ({c}); ask for more samples")
    return recipe, c, dt


def _train_all(out: Path, data_dir: Path, kinds, recipe, settings: dict, seconds, echo):
    """Stage 2: one run per model kind under ``out/runs``; ``{kind: run folder}``."""
    from .models import ModelConfig
    from .train import TrainConfig, train

    runs: dict[str, Path] = {}
    for kind in kinds:
        t0 = time.perf_counter()
        cfg = TrainConfig(
            model=ModelConfig(kind=kind, modes=recipe.modes, **settings["model_overrides"]),
            epochs=settings["epochs"],
            batch_size=settings["batch_size"],
            lr=settings["lr"],
            seed=settings["seed"],
        )
        run = out / "runs" / f"{kind}-seed{settings['seed']}"
        res = train(data_dir, run, cfg, progress=settings["progress"], threads=settings["threads"])
        seconds[f"train_{kind}"] = time.perf_counter() - t0
        runs[kind] = run
        last = res.history[-1]
        echo(
            f"train {kind}: {run}: {res.epochs} epochs, {res.steps} steps, loss {last['train_loss']:.4g}, "
            f"val minSADE {last['val_minSADE']:.3f} m ({seconds[f'train_{kind}']:.1f} s)"
        )
    return runs


def _figures(out: Path, data_dir: Path, runs: dict[str, Path]) -> tuple[int, list[Path]]:
    """Stage 4: a test sample with two valid modes if there is one, drawn with every run's
    predictions and CV's; ``(sample index, files)`` (the loss curves included)."""
    from scenarios.dataset import load_split

    from .show import show_predictions

    valid = load_split(data_dir, "test", fields=["mode_valid"])["mode_valid"]
    two = [i for i in range(len(valid)) if valid[i].all()]
    index = two[len(two) // 2] if two else 0
    files = [
        show_predictions(run, data_dir, index, out / "figures" / f"{kind}-test{index}.png")
        for kind, run in [*runs.items(), ("cv", "cv")]
    ]
    return index, files + [run / "loss.png" for run in runs.values()]


def run_pipeline(
    out_dir: str | os.PathLike = "epo-pipeline",
    samples: int = 1200,
    epochs: int = 15,
    seed: int = 0,
    *,
    lr: float = 1e-3,
    batch_size: int = 32,
    kinds: tuple[str, ...] = ("epo", "sc"),
    workers: int | None = None,
    threads: int | None = 1,
    recipe_overrides: dict | None = None,
    model_overrides: dict | None = None,
    progress: bool = True,
    echo: Callable[[str], None] = print,
) -> PipelineResult:
    """Generate, train, evaluate, draw; see the module docstring. Returns a :class:`PipelineResult`.

    ``recipe_overrides``: :class:`~scenarios.rpi.RPIRecipe` fields (e.g. ``max_subgames``);
    ``model_overrides``: :class:`~learning.models.ModelConfig` fields (e.g. widths);
    ``workers``: generation processes (default: usable cores); ``threads``: torch threads.
    """
    from scenarios.dataset import check_output_dir
    from scenarios.files import write_atomic

    from .evaluate import evaluate

    workers = _checked_workers(samples, epochs, seed, kinds, workers)
    out = check_output_dir(out_dir)  # an existing file (or a path into one) is refused
    data_dir = out / "data"
    seconds: dict[str, float] = {}
    t_all = time.perf_counter()
    recipe, c, seconds["generate"] = _generate(
        data_dir, samples, seed, workers, recipe_overrides, progress, echo
    )
    settings = {
        "epochs": epochs,
        "batch_size": batch_size,
        "lr": lr,
        "seed": seed,
        "model_overrides": model_overrides or {},
        "progress": progress,
        "threads": threads,
    }
    runs = _train_all(out, data_dir, kinds, recipe, settings, seconds, echo)

    # ---- 3. evaluation
    t0 = time.perf_counter()
    report = evaluate(list(runs.values()), data_dir, "test", cv=True, threads=threads)
    files = report.write(out / "results")
    seconds["evaluate"] = time.perf_counter() - t0
    table = report.markdown()
    echo("")
    echo(table)

    t0 = time.perf_counter()
    index, figures = _figures(out, data_dir, runs)
    files += figures
    seconds["figures"] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - t_all

    info = {
        "samples": samples,
        "epochs": epochs,
        "seed": seed,
        "lr": lr,
        "batch_size": batch_size,
        "kinds": list(kinds),
        "workers": workers,
        "recipe": recipe.to_dict(),
        "model_overrides": model_overrides or {},
        "counts": c,
        "seconds": seconds,
        "figure_index": index,
    }
    write_atomic(out / "pipeline.json", json.dumps(info, indent=1) + "\n")
    files.append(out / "pipeline.json")
    echo(
        f"results: {files[0]} (table), {out / 'figures'} (predictions), "
        f"{out / 'runs'}/*/loss.png (loss curves), {out / 'pipeline.json'} (timings); "
        f"total {seconds['total']:.1f} s"
    )
    return PipelineResult(out, data_dir, runs, table, files, seconds)
