"""``epo simulate``: closed-loop episodes of one configuration, in parallel, resumable.

``epo simulate left-turn --planner oracle --tracker mpc --episodes 200 --out DIR`` runs the
episodes (seeds ``seed .. seed + episodes - 1``) with :func:`scenarios.closed_loop.run_episodes`
and writes ``DIR/summary.md`` / ``summary.csv`` / ``episodes.csv``, one JSON per episode, and
the figures: ``DIR/figures/episode-00000.png`` (map, trajectories, predicted modes),
``episode-00000.gif`` (animation) and ``latency.png`` (all episodes' planning latencies).
A run interrupted and started again with the same options keeps its finished episodes.
"""

from __future__ import annotations

from pathlib import Path

import click

from epo_casadi.errors import SpecError

from .generate import _cores, _parse_set, engine_options

PLANNERS = ("model", "oracle", "cv", "sc")
TRACKERS = ("pid", "mpc")


@click.command("simulate")
@click.argument("scenario")
@click.option(
    "--planner",
    type=click.Choice(PLANNERS),
    default="oracle",
    show_default=True,
    help="model: the trained network (ours); oracle: the game with the true tasks; "
    "cv: constant-velocity predictions + best response; sc: the SC baseline network.",
)
@click.option("--model", "model", default=None, help="Trained run directory (planners model, sc).")
@click.option(
    "--tracker",
    type=click.Choice(TRACKERS),
    default="mpc",
    show_default=True,
    help="pid: speed and heading PIDs; mpc: OSQP linear time-varying MPC.",
)
@click.option("--episodes", type=click.IntRange(min=1), default=200, show_default=True)
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
    help="Std of the position noise on the other agents (m); default: the scenario's.",
)
@click.option(
    "--dropout",
    type=float,
    default=None,
    help="Probability per step that an observed agent drops out; default: the scenario's.",
)
@click.option("--geometry", default=None, help="Intersection geometry (left-turn), e.g. g2.")
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="KEY=VALUE",
    help="Option override (repeatable): world.KEY, planner.KEY, tracker.KEY or "
    "estimator.KEY, e.g. --set planner.horizon=40.",
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
    out,
    noise,
    dropout,
    geometry,
    overrides,
    figures,
    progress,
):
    """Closed-loop episodes of SCENARIO (left-turn, merge, crossing) with one planner and
    one tracker; a summary table, per-episode results and figures in --out."""
    from scenarios.closed_loop import SimConfig, run_episodes
    from scenarios.sim import WORLDS

    if scenario not in WORLDS:
        raise SpecError("scenario", f"unknown scenario {scenario!r}; valid: {', '.join(WORLDS)}")
    if model is not None and planner not in ("model", "sc"):
        raise click.BadParameter(
            f"is only used by --planner model or sc, not {planner}", param_hint="'--model'"
        )
    if planner in ("model", "sc") and model is None:
        raise click.BadParameter(f"--planner {planner} needs a trained run", param_hint="'--model'")
    if model is not None and not Path(model).is_dir():
        raise click.BadParameter(f"no run directory at {model}", param_hint="'--model'")
    if scheduler is not None and engine != "dask":
        raise click.BadParameter("needs --engine dask", param_hint="'--scheduler'")
    groups: dict[str, dict] = {"world": {}, "planner": {}, "tracker": {}, "estimator": {}}
    for key, value in _parse_set(overrides).items():
        head, _, name = key.partition(".")
        if head not in groups or not name:
            raise click.BadParameter(
                f"expected world.KEY, planner.KEY, tracker.KEY or estimator.KEY, got {key!r}",
                param_hint="'--set'",
            )
        groups[head][name] = value
    for name, value in (("noise_std", noise), ("dropout_prob", dropout), ("geometry", geometry)):
        if value is not None:
            groups["world"][name] = value
    if noise is not None and not noise >= 0:
        raise click.BadParameter(f"expected a number >= 0, got {noise}", param_hint="'--noise'")
    if dropout is not None and not 0 <= dropout <= 1:
        raise click.BadParameter(
            f"expected a number in [0, 1], got {dropout}", param_hint="'--dropout'"
        )
    config = SimConfig(
        scenario,
        planner=planner,
        tracker=tracker,
        model=str(model) if model is not None else None,
        world_options=groups["world"],
        planner_options=groups["planner"],
        tracker_options=groups["tracker"],
        estimator_options=groups["estimator"],
    )
    rep = run_episodes(
        config,
        episodes,
        seed=seed,
        workers=min(workers or _cores(), episodes),
        engine=engine,
        out=out,
        keep_logs=(0,),
        progress=progress,
        address=scheduler,
    )
    s = rep.summary
    click.echo(
        f"{out}: {config.label}, {s['episodes']} episodes ({rep.ran} run, {rep.kept} kept) in "
        f"{rep.seconds:.1f} s: success {s['success_rate']:.2f}, collision "
        f"{s['collision_rate']:.2f}, plan p50 {s['plan_p50_ms']:.1f} ms, RTF {s['rtf']:.2f}"
    )
    errors = [r for r in rep.results if r.outcome == "error"]
    if errors:
        click.echo(
            f"warning: {len(errors)} episode(s) failed, first: {errors[0].message}", err=True
        )
    if figures:
        paths = write_figures(out, rep)
        click.echo("figures: " + ", ".join(str(p) for p in paths))


def write_figures(out: Path, rep) -> list[Path]:
    """Episode plot and GIF of the first episode, latency histogram of all; their paths."""
    import numpy as np

    from scenarios.sim_plots import animate_episode, plot_episode, plot_latency_histogram

    fig_dir = Path(out) / "figures"
    paths = []
    log = rep.logs.get(0)
    if log is not None:
        r0 = rep.results[0]
        title = f"episode 0 (seed {r0.seed}): {r0.outcome}"
        paths.append(fig_dir / "episode-00000.png")
        plot_episode(log, paths[-1], title=title)
        paths.append(animate_episode(log, fig_dir / "episode-00000.gif", title=title))
        dt = log.dt
    else:
        dt = 0.1
    ms = np.concatenate([np.asarray(r.plan_ms, dtype=float) for r in rep.results] or [[]])
    paths.append(fig_dir / "latency.png")
    plot_latency_histogram(ms, dt, paths[-1])
    return paths
