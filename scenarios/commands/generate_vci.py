"""``epo generate vci``: scenes of vehicle-crowd clips in the CITR layout (:mod:`scenarios.real.vci`)."""

from __future__ import annotations

from pathlib import Path

import click

from .dataset_options import (
    dataset_options,
    exclusive,
    make_recipe,
    parse_set,
    run_dataset,
)


@click.command("vci", short_help="Vehicle-crowd scenes of CITR-layout clips (Yang et al. 2019).")
@click.option(
    "--raw",
    required=True,
    type=click.Path(path_type=Path),
    help="Folder of clips <clip>_traj_ped_filtered.csv (+ <clip>_traj_veh_filtered.csv), found "
    "anywhere below it: one folder per experiment type or all in one (docs/real_data.md).",
)
@click.option(
    "--fps",
    type=click.FloatRange(min=0.1, max=1000.0),
    default=None,
    help="Frames per second of the recordings (the files carry frame numbers only; default: "
    "the recipe's, 29.97, the CITR videos'; 0.1 to 1,000).",
)
@click.option(
    "--agents",
    type=click.IntRange(min=1, max=64),
    default=None,
    help="N: the vehicle and N - 1 pedestrians per scene, fewer padded (default: the recipe's, 4).",
)
@dataset_options(
    "Override a recipe field (repeatable), e.g. --set dt=0.4 --set horizon=8 (docs/real_data.md)."
)
def vci(raw, fps, agents, overrides, **run):
    """A vehicle and the N - 1 pedestrians that interact with it most, dt 0.2 s, 1 s history,
    3 s future; split by clip within every experiment type."""
    from scenarios.real.vci import VciScenario

    kw = parse_set(overrides)
    exclusive(kw, "fps", "--fps", fps)
    exclusive(kw, "agents", "--agents", agents)
    scenario = make_recipe(lambda **k: VciScenario.from_raw(raw, **k), kw)
    run_dataset(scenario, **run)
