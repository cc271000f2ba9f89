"""``epo generate eth-ucy``: the ETH/UCY pedestrian files into a dataset
(:mod:`scenarios.real.eth_ucy`)."""

from __future__ import annotations

from pathlib import Path

import click

from epo_casadi.errors import check_number, check_size

from .dataset_options import (
    dataset_options,
    exclusive,
    make_recipe,
    parse_set,
    run_dataset,
)

_SCENES = ("eth", "hotel", "univ", "zara1", "zara2")  # scenarios.real.eth_ucy.SCENES


@click.command("eth-ucy", short_help="ETH/UCY pedestrians, leave one scene out.")
@click.option(
    "--raw",
    required=True,
    type=click.Path(path_type=Path),
    help="Folder of the ETH/UCY text files (biwi_eth.txt, biwi_hotel.txt, students001.txt, "
    "students003.txt, crowds_zara01.txt, crowds_zara02.txt, crowds_zara03.txt, "
    "uni_examples.txt; 'frame ped x y' rows). Other files are ignored unless named in "
    "--set files=[[name,scene],...].",
)
@click.option(
    "--test-scene",
    type=click.Choice(_SCENES, case_sensitive=False),
    default=None,
    help="The left-out (test) scene; default: the recipe's, eth.",
)
@click.option(
    "--dt",
    type=float,
    default=None,
    help="Seconds per row step (0.01 to 5; default 0.4, the benchmark's; biwi_eth's raw "
    "annotation suggests 0.667).",
)
@click.option(
    "--agents",
    type=click.IntRange(min=1),
    default=None,
    help="N: the focal pedestrian and up to N - 1 others (default 4; at most 64); scenes "
    "with fewer are padded and masked.",
)
@dataset_options(
    "Override a recipe field (repeatable), e.g. --set val_fraction=0.2, --set stride=2, "
    "--set history=7, --set horizon=12 (docs/real_data.md)."
)
def eth_ucy(raw, test_scene, dt, agents, overrides, **run):
    """Scenes around every pedestrian: 8 observed and 12 future steps at 0.4 s, leave one
    scene out (eth, hotel, univ, zara1, zara2), validation the last part of each training file."""
    from scenarios.real.eth_ucy import EthUcyScenario

    kw = parse_set(overrides)
    if dt is not None:
        check_number("--dt", dt, lo=0.01, hi=5.0)
    if agents is not None:
        check_size("--agents", agents, 64, "agents of every sample")
    exclusive(kw, "test_scene", "--test-scene", None if test_scene is None else test_scene.lower())
    exclusive(kw, "dt", "--dt", dt)
    exclusive(kw, "agents", "--agents", agents)
    scenario = make_recipe(lambda **k: EthUcyScenario.from_raw(raw, **k), kw)
    run_dataset(scenario, **run)
