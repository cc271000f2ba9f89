"""``epo generate waymo``: Waymo Open Motion ``Scenario`` records (TFRecord) as a dataset."""

from __future__ import annotations

from pathlib import Path

import click

from .dataset_options import (
    dataset_options,
    make_recipe,
    parse_set,
    run_dataset,
)


@click.command("waymo", short_help="Waymo Open Motion scenarios (TFRecord files, no TensorFlow).")
@click.option(
    "--raw",
    multiple=True,
    required=True,
    type=click.Path(path_type=Path),
    help="TFRecord file of Scenario records, or a folder of them (names with 'tfrecord'); "
    "repeatable. Train scenarios; without --val / --test, seeded val and test shares by "
    "scenario (at most 100,000 files).",
)
@click.option(
    "--val",
    multiple=True,
    type=click.Path(path_type=Path),
    help="TFRecord file or folder of validation scenarios (repeatable).",
)
@click.option(
    "--test",
    multiple=True,
    type=click.Path(path_type=Path),
    help="TFRecord file or folder of test scenarios (repeatable), e.g. the official "
    "validation split as in the paper.",
)
@click.option(
    "--draw",
    type=click.Path(path_type=Path),
    default=None,
    help="Also draw each scenario (lane map, the selected agents' history and future) into "
    "this folder as <scenario_id>.png.",
)
@dataset_options(
    "Override a recipe field (repeatable), e.g. --set step=5 (dt 0.5 s, a 16-step game), "
    "--set types=[vehicle] (the paper's vehicle pairs), --set pairs=predict (docs/real_data.md)."
)
def waymo(raw, val, test, draw, overrides, **run):
    """N = 2 interacting agents, 1 s history, 8 s future at 0.1 s, lanes and goal candidates."""
    from scenarios.real.waymo import WaymoScenario, draw_scenarios

    scenario = make_recipe(
        lambda **k: WaymoScenario.from_raw(raw, val=val, test=test, **k), parse_set(overrides)
    )
    if draw is not None:
        from scenarios.files import ensure_dir

        ensure_dir(draw)  # an unwritable folder fails before the work
    run_dataset(scenario, **run)
    if draw is not None:
        paths = draw_scenarios(scenario, draw)
        click.echo(f"{draw}: {len(paths)} scenario figure(s)")
