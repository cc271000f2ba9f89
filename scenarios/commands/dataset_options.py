"""The options and the run every dataset generator shares (``epo generate ...`` and
``epo simulate``): workers capped at the usable cores, the engine options, ``--out`` and
``--set``, recipe overrides and the resumable run with its report. One definition, so the
generators cannot drift apart."""

from __future__ import annotations

import warnings
from pathlib import Path

import click

from epo_casadi.errors import SpecError
from epo_casadi.settings import parse_settings
from scenarios.files import usable_cores

__all__ = [
    "capped_workers",
    "cores",
    "dataset_options",
    "engine_options",
    "exclusive",
    "make_recipe",
    "parse_set",
    "run_dataset",
]


def cores() -> int:
    """The usable cores (:func:`scenarios.files.usable_cores`; tests replace this to
    pretend another machine)."""
    return usable_cores()


def capped_workers(workers: int | None, option: str = "--workers") -> int:
    """``workers`` (default: the usable cores), lowered to the usable cores with a warning:
    more worker processes than cores only make every unit slower."""
    n = cores()
    if workers is None:
        return n
    if workers > n:
        warnings.warn(
            f"{option} {workers} is more than the {n} usable core(s); using {n}",
            stacklevel=2,
        )
        return n
    return workers


def exclusive(kw: dict, key: str, option: str, value) -> None:
    """Put ``value`` of ``option`` into the overrides ``kw`` under ``key`` (when given);
    the same field given by ``--set`` too is refused (one of them would be ignored)."""
    if value is None:
        return
    if key in kw:
        raise SpecError(f"--set {key}", f"has an option of its own, {option}; give it there")
    kw[key] = value


def parse_set(items: tuple[str, ...]) -> dict:
    """``KEY=VALUE`` recipe overrides, read by :func:`epo_casadi.settings.parse_settings`."""
    return parse_settings(items, "--set")


def _apply(options):
    def decorate(f):
        for opt in reversed(options):
            f = opt(f)
        return f

    return decorate


def engine_options(seed_help: str = "Seed of the whole dataset."):
    """Workers, seed, engine, scheduler, progress and scheduler timeout: the options of every
    command that runs work units on the local-process or Dask engine (generators,
    ``epo simulate``)."""
    return _apply(
        [
            click.option(
                "--workers",
                type=click.IntRange(min=1),
                default=None,
                help="Worker processes (default: usable cores).",
            ),
            click.option(
                "--seed", type=click.IntRange(min=0), default=0, show_default=True, help=seed_help
            ),
            click.option(
                "--engine",
                type=click.Choice(["local", "dask"]),
                default="local",
                show_default=True,
                help="local: process pool; dask: dask.distributed.",
            ),
            click.option(
                "--scheduler",
                default=None,
                help="dask scheduler address (engine dask); default: a new LocalCluster of --workers processes.",
            ),
            click.option(
                "--progress/--no-progress",
                default=True,
                show_default=True,
                help="tqdm progress bar.",
            ),
            click.option(
                "--scheduler-timeout",
                type=click.FloatRange(min=0, min_open=True, max=3600),
                default=10.0,
                show_default=True,
                help="Seconds to wait for the --scheduler before giving up with an error.",
            ),
        ]
    )


def dataset_options(set_help: str):
    """The options every dataset generator shares (one definition, so the generators
    cannot drift apart): output, the engine options, recipe overrides."""
    return _apply(
        [
            click.option(
                "--out",
                "out",
                required=True,
                type=click.Path(path_type=Path),
                help="Output directory (created; resumed if it holds an unfinished run of the same recipe).",
            ),
            engine_options(),
            click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help=set_help),
        ]
    )


def make_recipe(make, overrides: dict):
    """``make(**overrides)``; a value of the wrong type inside the recipe names ``--set``."""
    try:
        return make(**overrides)
    except TypeError as e:
        raise SpecError("--set", str(e)) from None


def run_dataset(scenario, out, workers, seed, engine, scheduler, scheduler_timeout, progress):
    """Generate ``scenario`` into ``out`` (resumable; SIGTERM stops like Ctrl-C) and report."""
    from scenarios.dataset import check_output_dir, sigterm_as_interrupt
    from scenarios.dataset import generate as run

    if scheduler is not None and engine != "dask":
        raise click.BadParameter("needs --engine dask", param_hint="'--scheduler'")
    check_output_dir(out)
    # local processes (a pool or a new LocalCluster); a running scheduler has its own workers
    workers = capped_workers(workers) if scheduler is None else (workers or cores())
    with sigterm_as_interrupt():
        rep = run(
            scenario,
            out,
            seed=seed,
            workers=workers,
            engine=engine,
            address=scheduler,
            progress=progress,
            scheduler_timeout=scheduler_timeout,
        )
    c = rep.counts
    click.echo(
        f"{out}: train {c['train']}, val {c['val']}, test {c['test']} samples; "
        f"{len(rep.shards_written)} shard(s) written, {len(rep.shards_kept)} kept; "
        f"{rep.samples_written} samples in {rep.seconds:.1f} s ({rep.samples_per_second:.2f} samples/s)"
    )
