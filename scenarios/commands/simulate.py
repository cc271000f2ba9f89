"""``epo simulate``: closed-loop episodes of one configuration, in parallel, resumable.

``epo simulate left-turn --planner oracle --tracker mpc --episodes 200 --out DIR`` runs the
episodes (seeds ``seed .. seed + episodes - 1``) with :func:`scenarios.closed_loop.run_episodes`
and writes ``DIR/summary.md`` / ``summary.csv`` / ``episodes.csv``, one JSON per episode, and
the figures: ``DIR/figures/episode-00000.png`` (map, trajectories, predicted modes),
``episode-00000.gif`` (animation) and ``latency.png`` (all episodes' planning latencies).
A run interrupted and started again with the same options keeps its finished episodes
(SIGTERM stops it as Ctrl-C does: the worker processes are shut down, exit status 130); a
rerun with other options, or against a run directory whose model was trained further, is
refused naming the differing field. Every command passes the safety filter
(:mod:`solvers.control.safety`) unless ``--no-safety-filter``. ``--workers`` beyond the usable cores is lowered to
them (one warning line). When every episode ended in an error the command prints one line
saying so with the first error and exits with status 1; when some did, one warning line
(and ``summary.md`` says so too).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from epo_casadi.errors import OutputError, SpecError, check_size
from scenarios.closed_loop.roles import PLANNERS, TRACKERS

from .dataset_options import capped_workers, cores, engine_options, parse_set


@click.command("simulate")
@click.argument("scenario")
@click.option(
    "--planner",
    type=click.Choice(PLANNERS.names()),
    default="oracle",
    show_default=True,
    help="model: the trained network (ours); oracle: the game with the true tasks; "
    "cv: constant-velocity predictions + best response; sc: the SC baseline network "
    "(and any registered with scenarios.closed_loop.register_planner).",
)
@click.option("--model", "model", default=None, help="Trained run directory (planners model, sc).")
@click.option(
    "--tracker",
    type=click.Choice(TRACKERS.names()),
    default="mpc",
    show_default=True,
    help="pid: speed and heading PIDs; mpc: OSQP linear time-varying MPC.",
)
@click.option(
    "--episodes",
    type=click.IntRange(min=1),
    default=200,
    show_default=True,
    help="Episodes of the run (at most 100,000).",
)
@engine_options(seed_help="Episode i uses seed + i.")
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(path_type=Path),
    help="Output directory (resumed if it holds a run of the same options).",
)
@click.option(
    "--noise",
    type=float,
    default=None,
    help="Std of the position noise on the other agents (m); default: the scenario's "
    "(world.noise_std).",
)
@click.option(
    "--dropout",
    type=float,
    default=None,
    help="Fraction of an observed agent's positions lost, in bursts (world.dropout_prob); "
    "default: the scenario's.",
)
@click.option("--geometry", default=None, help="Intersection geometry (left-turn), e.g. g2.")
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="KEY=VALUE",
    help="Option override (repeatable): world.KEY, planner.KEY, tracker.KEY, "
    "estimator.KEY or filter.KEY, e.g. --set planner.horizon=40.",
)
@click.option(
    "--safety-filter/--no-safety-filter",
    "safety_filter",
    default=True,
    show_default=True,
    help="The safety filter between the tracker and the world (solvers.control.safety; "
    "options: --set filter.KEY=V); --no-safety-filter runs without it (studies).",
)
@click.option(
    "--figures/--no-figures",
    default=True,
    show_default=True,
    help="Episode plot, GIF of the first episode, latency histogram.",
)
def simulate(
    scenario,
    planner,
    model,
    tracker,
    episodes,
    seed,
    workers,
    engine,
    scheduler,
    scheduler_timeout,
    out,
    noise,
    dropout,
    geometry,
    overrides,
    safety_filter,
    figures,
    progress,
):
    """Closed-loop episodes of SCENARIO (left-turn, merge, crossing) with one planner and
    one tracker; a summary table, per-episode results and figures in --out."""
    from scenarios.closed_loop import MAX_EPISODES, SimConfig, error_note, run_episodes
    from scenarios.files import sigterm_as_interrupt
    from scenarios.sim import WORLDS

    if scenario not in WORLDS:
        raise SpecError("scenario", f"unknown scenario {scenario!r}; valid: {', '.join(WORLDS)}")
    trained = PLANNERS.needing_model()
    if model is not None and planner not in trained:
        raise click.BadParameter(
            f"is only used by --planner {' or '.join(trained)}, not {planner}",
            param_hint="'--model'",
        )
    if planner in trained and model is None:
        raise click.BadParameter(f"--planner {planner} needs a trained run", param_hint="'--model'")
    if model is not None and not Path(model).is_dir():
        raise click.BadParameter(f"no run directory at {model}", param_hint="'--model'")
    if scheduler is not None and engine != "dask":
        raise click.BadParameter("needs --engine dask", param_hint="'--scheduler'")
    groups = _option_groups(overrides, noise, dropout, geometry)
    if noise is not None and not noise >= 0:
        raise click.BadParameter(f"expected a number >= 0, got {noise}", param_hint="'--noise'")
    if dropout is not None and not 0 <= dropout <= 1:
        raise click.BadParameter(
            f"expected a number in [0, 1], got {dropout}", param_hint="'--dropout'"
        )
    check_size("--episodes", episodes, MAX_EPISODES, "results held in memory")
    if scheduler is None:  # processes on this machine: no more than its usable cores
        workers = capped_workers(workers)
    workers = workers or cores()
    config = SimConfig(
        scenario,
        planner=planner,
        tracker=tracker,
        model=str(model) if model is not None else None,
        world_options=groups["world"],
        planner_options=groups["planner"],
        tracker_options=groups["tracker"],
        estimator_options=groups["estimator"],
        safety_filter=safety_filter,
        filter_options=groups["filter"],
    )
    with sigterm_as_interrupt():  # kill PID stops like Ctrl-C: workers shut down, exit 130
        rep = run_episodes(
            config,
            episodes,
            seed=seed,
            workers=min(workers, episodes),
            engine=engine,
            out=out,
            keep_logs=(0,),
            progress=progress,
            address=scheduler,
            scheduler_timeout=scheduler_timeout,
        )
    s = rep.summary
    click.echo(
        f"{out}: {config.label}, {s['episodes']} episodes ({rep.ran} run, {rep.kept} kept) in "
        f"{rep.seconds:.1f} s: success {s['success_rate']:.2f}, collision "
        f"{s['collision_rate']:.2f}, plan p50 {s['plan_p50_ms']:.1f} ms, RTF {s['rtf']:.2f}"
    )
    errors = [r for r in rep.results if r.outcome == "error"]
    note = error_note(rep.results)
    if errors and len(errors) == len(rep.results):
        click.echo(f"error: {note}", err=True)
        return 1
    if errors:
        click.echo(f"warning: {note}", err=True)
    if figures:
        paths = write_figures(out, rep)
        click.echo("figures: " + ", ".join(str(p) for p in paths))
    return 0


def _option_groups(overrides, noise, dropout, geometry) -> dict[str, dict]:
    """``--set`` and the world's shortcuts (``--noise``, ``--dropout``, ``--geometry``) as
    options per role: ``{"world": ..., "planner": ..., "tracker": ..., "estimator": ...,
    "filter": ...}``."""
    groups: dict[str, dict] = {
        "world": {},
        "planner": {},
        "tracker": {},
        "estimator": {},
        "filter": {},
    }
    for key, value in parse_set(overrides).items():
        head, _, name = key.partition(".")
        if head not in groups or not name:
            raise click.BadParameter(
                f"expected world.KEY, planner.KEY, tracker.KEY, estimator.KEY or filter.KEY, "
                f"got {key!r}",
                param_hint="'--set'",
            )
        groups[head][name] = value
    for opt, name, value in (
        ("--noise", "noise_std", noise),
        ("--dropout", "dropout_prob", dropout),
        ("--geometry", "geometry", geometry),
    ):
        if value is None:
            continue
        if name in groups["world"]:
            raise click.BadParameter(
                f"sets the world's {name}, and so does --set world.{name}; give only one",
                param_hint=f"'{opt}'",
            )
        groups["world"][name] = value
    return groups


def write_figures(out: Path, rep) -> list[Path]:
    """Episode plot and GIF of the first episode, latency histogram of all; their paths.
    A figure that cannot be written is one :class:`OutputError` naming it."""
    import numpy as np

    from scenarios.files import ensure_dir
    from scenarios.sim_plots import animate_episode, plot_episode, plot_latency_histogram

    fig_dir = ensure_dir(Path(out) / "figures")
    paths: list[Path] = []
    try:
        log = rep.logs.get(0)
        if log is not None:
            r0 = rep.results[0]
            title = f"episode 0 (seed {r0.seed}): {r0.outcome}"
            paths.append(fig_dir / "episode-00000.png")
            plot_episode(log, paths[-1], title=title)
            paths.append(fig_dir / "episode-00000.gif")
            animate_episode(log, paths[-1], title=title)
            dt = log.dt
        else:
            dt = 0.1
        ms = np.concatenate([np.asarray(r.plan_ms, dtype=float) for r in rep.results] or [[]])
        paths.append(fig_dir / "latency.png")
        plot_latency_histogram(ms, dt, paths[-1])
    except OutputError:
        raise
    except OSError as e:
        for tmp in fig_dir.glob(".*.tmp*"):  # the GIF writer's temporary file
            with contextlib.suppress(OSError):
                tmp.unlink()
        raise OutputError(paths[-1] if paths else fig_dir, e.strerror or str(e)) from None
    return paths
