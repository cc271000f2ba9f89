"""``epo inspect GAME.yaml``: the energy terms of a game file, the Jacobian's sparsity,
and (with ``--at result.json``) where the energy of a solution goes."""

from __future__ import annotations

from pathlib import Path

import click


@click.command("inspect")
@click.argument("game_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--at",
    "at",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="A result file of 'epo solve': also print the energy per term and the agent costs there.",
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
    help="With --at: show only the TOP largest terms.",
)
@click.option(
    "--spy/--no-spy",
    default=True,
    show_default=True,
    help="Print a text picture of which terms touch which agents' controls.",
)
@click.option(
    "--spy-png",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write a spy plot of the Jacobian dr/du (PNG) here.",
)
def inspect_cmd(
    game_file: Path,
    at: Path | None,
    settings: tuple[str, ...],
    top: int | None,
    spy: bool,
    spy_png: Path | None,
):
    """List every energy term of GAME_FILE, its Jacobian sparsity and (--at) an energy breakdown."""
    from epo_casadi.inspect import breakdown_table, jacobian_sparsity, spy_text, term_table
    from scenarios.gamefile import apply_settings, load_game

    gf = load_game(game_file)
    game = gf.game
    click.echo(f"{game_file}")
    click.echo(term_table(game))
    if at is not None:
        from scenarios.commands.solve import read_result

        u, p = read_result(at, game)
        p = apply_settings(game, p, settings)
        click.echo("")
        click.echo(f"at {at}:")
        click.echo(breakdown_table(game, u, p, top=top))
    elif settings:
        apply_settings(game, gf.params, settings)  # validate; nothing else depends on p here
    click.echo("")
    if spy:
        click.echo(spy_text(game))
    else:
        sp = jacobian_sparsity(game)
        click.echo(
            f"J = dr/du: {sp['shape'][0]} x {sp['shape'][1]}, {sp['nnz']} structural nonzeros "
            f"(density {sp['density']:.3f})"
        )
    if spy_png is not None:
        from scenarios.plotting import plot_sparsity

        plot_sparsity(game, spy_png, title=f"{game_file.name}: J = dr/du")
        click.echo(f"wrote {spy_png}")
