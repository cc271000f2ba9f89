"""``epo demo``: the main job on built-in games, in a few seconds.

Solves the shipped 2-agent crossing (``crossing2.yaml``) and 4-agent intersection
(``intersection4.yaml``) with Levenberg-Marquardt and with IPOPT, checks each solution
with the local Nash certificate, prints a comparison table and writes, per game, the
result files (``<game>_<solver>.json``, the format of ``epo solve``), a trajectory
figure with both solutions (``<game>.png``) and the energy histories
(``<game>_energy.png``).
"""

from __future__ import annotations

import time
from pathlib import Path

import click

DEMO_GAMES = ("crossing2", "intersection4")
DEMO_SOLVERS = ("lm", "ipopt")


def _row(game_name: str, data: dict) -> list[str]:
    """One table row of a result object; total over every status (no certificate, or
    ``None`` for a non-finite value, prints as ``-`` / ``none``)."""
    from scenarios.commands.solve import _largest
    from solvers.result import fmt_number

    def num(v, spec):
        return "none" if v is None else fmt_number(v, spec)

    c = data.get("certificate")
    costs = " ".join(num(v, ".4g") for v in data["agent_costs"].values())
    return [
        game_name,
        data["solver"],
        data["status"],
        num(data["energy"], ".6g"),
        costs,
        num(_largest(c["best_response_gap"]), ".2g") if c else "-",
        num(_largest(c["stationarity"]), ".2g") if c else "-",
        {"passes": "yes", "fails": "NO"}.get(c.get("verdict"), c.get("verdict")) if c else "-",
        str(data["iterations"]),
        num(data["time_s"], ".3f"),
    ]


def _table(header, rows) -> str:
    widths = [max(len(h), *(len(r[c]) for r in rows)) for c, h in enumerate(header)]
    fmt = lambda cells: "  ".join(x.ljust(w) for x, w in zip(cells, widths, strict=True)).rstrip()  # noqa: E731
    return "\n".join([fmt(header), fmt(["-" * w for w in widths]), *(fmt(r) for r in rows)])


@click.command("demo")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("results/demo"),
    show_default=True,
    help="Directory for results and figures.",
)
def demo(out_dir: Path):
    """Solve a 2-agent crossing and a 4-agent intersection with LM and IPOPT; compare."""
    from scenarios.commands.solve import (
        energy_history,
        result_dict,
        run_solve,
        write_result,
    )
    from scenarios.files import check_output_file, ensure_dir
    from scenarios.gamefile import example_path, load_game
    from scenarios.plotting import plot_energy_history, plot_trajectories

    t_all = time.perf_counter()
    ensure_dir(out_dir)
    check_output_file(out_dir / f"{DEMO_GAMES[0]}_lm.json", "--out")  # writable, before work
    rows, written = [], []
    for name in DEMO_GAMES:
        gf = load_game(example_path(name))
        game, p = gf.game, gf.params
        click.echo(
            f"{name}: {game.N} agents, K = {game.K}, n_u = {game.n_u}, {len(game.terms)} energy terms"
        )
        states, hist = {}, {}
        for solver in DEMO_SOLVERS:
            t0 = time.perf_counter()
            res, cert = run_solve(game, p, solver, gf.options(solver))
            data = result_dict(game, p, res, cert, source=str(example_path(name)))
            written.append(write_result(data, out_dir / f"{name}_{solver}.json"))
            rows.append(_row(name, data))
            states[solver] = res.states
            hist[solver] = energy_history(res)
            click.echo(
                f"  {solver:5s} {data['status']}, energy {rows[-1][3]} "
                f"({time.perf_counter() - t0:.1f} s with set-up and certificate)"
            )
        fig = out_dir / f"{name}.png"
        plot_trajectories(
            game,
            states["lm"],
            p,
            fig,
            others={"ipopt (dotted)": states["ipopt"]},
            title=f"{name}: LM (solid) and IPOPT (dotted)",
        )
        plot_energy_history(
            hist, out_dir / f"{name}_energy.png", title=f"{name}: energy per iteration"
        )
        written += [fig, out_dir / f"{name}_energy.png"]
    click.echo("")
    header = [
        "game",
        "solver",
        "status",
        "energy",
        "agent costs",
        "Nash gap",
        "|dC_i/du_i|",
        "Nash",
        "iters",
        "time [s]",
    ]
    click.echo(_table(header, rows))
    click.echo(
        "Nash gap: largest best-response gap over agents (local certificate, solvers.nash); "
        "time: solver only."
    )
    click.echo("")
    click.echo(f"results: {', '.join(str(w) for w in written if w.suffix == '.json')}")
    click.echo(f"figures: {', '.join(str(w) for w in written if w.suffix == '.png')}")
    click.echo(f"done in {time.perf_counter() - t_all:.1f} s")
