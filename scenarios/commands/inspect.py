"""``epo inspect GAME.yaml``: what the game is made of, for a control engineer.

Prints the energy convention, the dynamics, the parameter vector with values, every
energy term with its formula, the Jacobian and Gauss-Newton Hessian sparsity (text spy
pictures with a legend) and, with a solution (``--solve``, or ``--result`` / ``--at`` a
result file of ``epo solve``), the energy per term, when each term is active, the agent
costs, and (``--plot``) each term's value and every agent's states and controls over time.
``--json`` prints the same content as one JSON object (schema ``epo-inspect/1``,
docs/gamefiles.md).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click
import numpy as np

from scenarios.commands.options import allow_import_option


@click.command("inspect")
@click.argument("game_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--result",
    "--at",
    "at",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="A result file of 'epo solve': inspect that solution (energy per term over time, "
    "agent costs, states and controls).",
)
@click.option(
    "--solve",
    "solve",
    is_flag=True,
    default=False,
    help="Solve the game with LM (the file's options) and inspect the solution.",
)
@click.option(
    "--set",
    "settings",
    multiple=True,
    metavar="NAME=VALUE",
    help="Replace a parameter (applied after the result's parameters; repeatable).",
)
@click.option(
    "--top",
    type=click.IntRange(min=1),
    default=None,
    help="With a solution: show only the TOP largest terms.",
)
@click.option(
    "--spy/--no-spy",
    default=True,
    show_default=True,
    help="Print text pictures of the Jacobian and Hessian sparsity.",
)
@click.option(
    "--hessian/--no-hessian",
    default=True,
    show_default=True,
    help="Also find the Gauss-Newton Hessian pattern J^T J.",
)
@click.option(
    "--spy-png",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write spy images of J = dr/du (rows named by term) and of J^T J (PNG) here.",
)
@click.option(
    "--plot",
    "plot",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="With a solution: write each term's value and the states and controls over time.",
)
@click.option(
    "--json",
    "as_json",
    is_flag=True,
    default=False,
    help="Print one JSON object (schema epo-inspect/1) instead of the text.",
)
@allow_import_option
def inspect_cmd(
    game_file: Path,
    at: Path | None,
    solve: bool,
    settings: tuple[str, ...],
    top: int | None,
    spy: bool,
    hessian: bool,
    spy_png: Path | None,
    plot: Path | None,
    as_json: bool,
):
    """Show every energy term of GAME_FILE with its formula, the dynamics, the parameters,
    the Jacobian and Hessian sparsity and (--solve or --result) a solution over time."""
    from epo_casadi.errors import SpecError
    from epo_casadi.inspect import inspect_report, report_text
    from scenarios.commands.solve import _jsonable
    from scenarios.gamefile import apply_settings, load_game

    if solve and at is not None:
        raise SpecError("--solve", "give either --solve or --result/--at, not both")
    from scenarios.files import check_output_file
    from scenarios.plotting import check_image_path

    for option, path in (("--spy-png", spy_png), ("--plot", plot)):  # before any work
        if path is not None:
            check_output_file(check_image_path(path, option), option)
    gf = load_game(game_file)
    game = gf.game
    u = None
    p = gf.params
    if at is not None:
        from scenarios.commands.solve import read_result

        u, p = read_result(at, game)
    p = apply_settings(game, p, settings)
    note = None
    if solve:
        from solvers import solve_lm

        res = solve_lm(game, p, options=gf.options("lm"))
        note = f"solved with LM: {res.status.value}, {res.iterations} iterations"
        u = res.controls if np.all(np.isfinite(res.controls)) else None
        if u is None:  # every status gets a report: here one without a solution
            click.echo(f"warning: {note}; the controls are not finite, no solution shown", err=True)
            if plot is not None:
                raise SpecError("--plot", f"no finite solution to draw ({res.status.value})")
    if plot is not None and u is None:
        raise SpecError("--plot", "needs a solution: add --solve or --result FILE")
    rep = inspect_report(game, p, u, source=str(game_file), hessian=hessian)
    if rep["solution"] is not None:
        rep["solution"]["source"] = str(at) if at is not None else note
    if as_json:
        json.dump(_jsonable(rep), sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        click.echo(f"{game_file}")
        if rep["solution"] is not None:
            click.echo(f"solution: {rep['solution']['source']}")
        click.echo(report_text(game, rep, spy=spy, top=top))
    say = (lambda m: click.echo(m, err=True)) if as_json else click.echo
    if spy_png is not None:
        from scenarios.inspect_plots import plot_inspect_sparsity

        plot_inspect_sparsity(game, spy_png)
        say(f"wrote {spy_png}")
    if plot is not None:
        from scenarios.inspect_plots import plot_solution_over_time

        plot_solution_over_time(game, rep, plot)
        say(f"wrote {plot}")
