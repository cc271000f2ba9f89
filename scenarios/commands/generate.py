"""``epo generate``: dataset generators (``epo generate rpi --out DIR``).

A thin layer over :func:`scenarios.dataset.generate` and the scenario classes: options
become a recipe, input errors name the option, and a run killed at any point resumes
when started again with the same options (finished shards are kept). SIGTERM stops a
run as Ctrl-C does (exit 130); the worker processes also end when the command is killed
with SIGKILL. ``--workers`` above the usable cores is lowered to them (with a warning), and
every count and size option is bounded before any work starts (the limits are in each
option's help and in the recipe classes).
"""

from __future__ import annotations

from pathlib import Path

import click

from epo_casadi.errors import SpecError, check_size

from .dataset_options import (
    capped_workers,
    dataset_options,
    exclusive,
    make_recipe,
    parse_set,
    run_dataset,
)
from .generate_eth_ucy import eth_ucy
from .generate_vci import vci
from .generate_waymo import waymo


@click.group("generate")
def generate():
    """Generate a dataset (sharded HDF5 files + manifest.json, resumable)."""


@generate.command("rpi", short_help="Robot-pedestrian interaction dataset (paper App. E.1).")
@click.option(
    "--samples",
    type=click.IntRange(min=1),
    default=None,
    help="About N samples (N/70 main games, N/30 for ground_truth=potential, at least 3; the "
    "manifest has the exact count; at most 10,000,000). Default: the full set, ~60k samples.",
)
@click.option(
    "--solver",
    type=click.Choice(["ilq", "lm"]),
    default=None,
    help="Multimodal game solver (default: the recipe's, ilq).",
)
@dataset_options(
    "Override a recipe field (repeatable), e.g. --set n_samples=6 (docs/rpi.md; sizes are "
    "bounded: main_games <= 1,000,000, horizon, history <= 1,000, ...)."
)
def rpi(samples, solver, overrides, **run):
    """Robot-pedestrian interaction dataset (paper App. E.1)."""
    from scenarios.rpi import MAX_SAMPLES, RPIRecipe, RPIScenario

    kw = parse_set(overrides)
    exclusive(kw, "solver", "--solver", solver)
    if samples is not None:
        check_size("--samples", samples, MAX_SAMPLES, "samples of one dataset")
        if "main_games" in kw:
            raise SpecError("--set main_games", "is chosen by --samples; give one of them")
        recipe = make_recipe(lambda **k: RPIRecipe.for_samples(samples, **k), kw)
    else:
        recipe = make_recipe(lambda **k: RPIRecipe.from_dict(k), kw)
    run_dataset(RPIScenario(recipe), **run)


@generate.command("left-turn", short_help="Left-turn demonstrations (paper App. E, CARLA).")
@click.option(
    "--episodes-per-geometry",
    type=click.IntRange(min=1),
    default=None,
    help="Episodes per intersection geometry (default: the recipe's, 5 as in the paper; at "
    "most 100,000).",
)
@dataset_options(
    "Override a recipe field (repeatable), e.g. --set augment_copies=2 (docs/left_turn.md; "
    "sizes are bounded: horizon, history <= 1,000, augment_copies <= 100, ...)."
)
def left_turn(episodes_per_geometry, overrides, **run):
    """Left-turn demonstrations on four intersections, split by intersection (docs/left_turn.md)."""
    from scenarios.left_turn import MAX_EPISODES_PER_GEOMETRY, LeftTurnRecipe, LeftTurnScenario

    kw = parse_set(overrides)
    if episodes_per_geometry is not None:
        check_size(
            "--episodes-per-geometry",
            episodes_per_geometry,
            MAX_EPISODES_PER_GEOMETRY,
            "episodes (work units) per geometry",
        )
    exclusive(kw, "episodes_per_geometry", "--episodes-per-geometry", episodes_per_geometry)
    run_dataset(LeftTurnScenario(make_recipe(lambda **k: LeftTurnRecipe.from_dict(k), kw)), **run)


@generate.command("exid", short_help="Scenes of the exiD release layout (paper App. E, exiD).")
@click.option(
    "--raw",
    required=True,
    type=click.Path(path_type=Path),
    help="Directory of the exiD release (data/NN_*.csv, maps/lanelet2/*.osm), or one made by "
    "'epo generate highway-raw'.",
)
@dataset_options(
    "Override a recipe field (repeatable), e.g. --set test_locations=[2] (docs/exid.md)."
)
def exid(raw, overrides, **run):
    """N = 4 scenes with a lane change, dt 0.2 s, 1.8 s history, 4 s future; test on its own map."""
    from scenarios.exid import ExidScenario

    scenario = make_recipe(lambda **k: ExidScenario.from_raw(raw, **k), parse_set(overrides))
    run_dataset(scenario, **run)


@generate.command("highway-raw", short_help="highway-env traffic written in the exiD layout.")
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(path_type=Path),
    help="Output directory (data/ and maps/lanelet2/; records its recipe in recipe.json: a "
    "rerun with the same options resumes, with more --recordings extends the set; other "
    "options are refused).",
)
@click.option(
    "--recordings",
    type=click.IntRange(min=1),
    default=8,
    show_default=True,
    help="Recordings, round-robin over the locations (at most 10,000).",
)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option(
    "--duration",
    type=float,
    default=120.0,
    show_default=True,
    help="Recorded seconds per recording (1 to 3,600; at most 100,000 frames).",
)
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="KEY=VALUE",
    help="Override a generator option (repeatable), e.g. --set locations=[0,1,2] (docs/exid.md).",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Recordings simulated at a time, in worker processes (the same files for any "
    "number; at most the usable cores).",
)
@click.option(
    "--progress/--no-progress", default=True, show_default=True, help="tqdm progress bar."
)
def highway_raw(out, recordings, seed, duration, overrides, workers, progress):
    """Recordings round-robin over the locations (on- and off-ramps, 2 and 3 lanes)."""
    from epo_casadi.errors import check_number
    from scenarios.files import sigterm_as_interrupt
    from scenarios.highway import MAX_DURATION, MAX_RECORDINGS, HighwayOptions, generate_raw
    from scenarios.sim.common import build_options

    check_size("--recordings", recordings, MAX_RECORDINGS, "recordings of a set")
    check_number("--duration", duration, lo=1.0, hi=MAX_DURATION)
    kw = parse_set(overrides)
    exclusive(kw, "recordings", "--recordings", recordings)
    exclusive(kw, "duration", "--duration", duration)
    try:
        opts = build_options(HighwayOptions, "highway", kw)
    except TypeError as e:
        raise SpecError("--set", str(e)) from None
    workers = capped_workers(workers)
    with sigterm_as_interrupt():
        st = generate_raw(out, opts, seed=seed, progress=progress, workers=workers)
    click.echo(
        f"{out}: {st['recordings']} recordings ({st['written']} written: {st['tracks']} tracks, "
        f"{st['rows']} rows, {st['crashes']} crashes removed) in {st['seconds']:.1f} s"
    )


for _command in (eth_ucy, vci, waymo):  # the readers of recorded data, a module each
    generate.add_command(_command)
