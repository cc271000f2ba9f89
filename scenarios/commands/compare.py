"""``epo compare``: games x solvers x initial strategies -> one table and figures.

The study itself is :func:`solvers.compare.run_comparison` (time and check definitions
in its module docstring and ``docs/compare.md``). This command reads the games (files,
or every ``.yaml``/``.yml``/``.json`` file of a directory; ``example:NAME`` for a shipped
example), runs the study and writes, atomically, into ``--out``:

* ``compare.md`` and ``compare.csv``: one row per (game, solver, init), with what each
  point is (``equilibrium``: ``potential minimum (coupled dynamics: not a Nash
  equilibrium)`` for a potential solve of a coupled game) and the check's verdict
  (``passes`` / ``fails`` / ``unknown``, local by default; ``check_note`` says why);
* ``<game>_gap.png``: the energy gap ``E - E_best`` against iterations and solve time;
* with ``--scaling``: ``scaling.csv``, ``scaling.md`` and ``scaling.png`` (time per
  solve against ``N`` and ``K`` on a crossing family, log-log with fitted slopes).

Bad input (unknown solver, bad option, missing game) is one line on stderr, exit 2. A
failed solve is a row with its status; the command still exits 0.
"""

from __future__ import annotations

import io
from pathlib import Path

import click
import numpy as np

from epo_casadi.errors import SpecError
from scenarios.commands.options import allow_import_option

__all__ = ["compare", "load_games", "crossing_family", "SCALING_N", "SCALING_K"]

SCALING_N = (2, 3, 4, 6, 8)
SCALING_K = (20, 50, 100, 200)
GAME_SUFFIXES = (".yaml", ".yml", ".json")


def load_games(items) -> list:
    """``[(name, game, p)]`` from files, directories and ``example:NAME`` entries."""
    from scenarios.gamefile import example_path, load_game

    paths: list[Path] = []
    for it in items:
        if it.startswith("example:"):
            paths.append(example_path(it.split(":", 1)[1]))
            continue
        path = Path(it)
        if path.is_dir():
            found = sorted(q for q in path.iterdir() if q.suffix.lower() in GAME_SUFFIXES)
            if not found:
                raise SpecError("GAMES", f"{path}: no game files (.yaml, .yml, .json) in it")
            paths.extend(found)
        elif not path.exists():
            raise SpecError("GAMES", f"{path}: no such file or folder")
        else:
            paths.append(path)
    out, seen = [], set()
    for path in paths:
        gf = load_game(path)
        name = path.stem
        while name in seen:
            name += "'"
        seen.add(name)
        out.append((name, gf.game, gf.params))
    return out


def crossing_family(N: int, K: int):
    """The scaling study's games: ``N`` unicycles on a circle of radius 3 m, each heading
    to the opposite side (goals shifted 0.3 m sideways), collision weight 20, dt 0.1."""
    from epo_casadi import (
        Acceleration,
        AgentSpec,
        Collision,
        GameSpec,
        Goal,
        PotentialGame,
        TurnRate,
        Velocity,
    )

    agents = []
    for i in range(N):
        a = 2 * np.pi * i / N
        c, s = np.cos(a), np.sin(a)
        agents.append(
            AgentSpec(
                f"a{i}",
                "unicycle",
                [Goal(weight=3.0), Velocity(weight=0.3), Acceleration(), TurnRate()],
                radius=0.25,
                x0=[3 * c, 3 * s, 1.0, a + np.pi],
                goal=[-3 * c - 0.3 * s, -3 * s + 0.3 * c],
            )
        )
    game = PotentialGame(GameSpec(agents, [Collision(weight=20.0)], horizon=K, dt=0.1))
    return game, game.default_params()


def _read_init(text: str, games):
    from scenarios.commands.solve import read_result
    from solvers.compare import InitChoice, parse_init

    if not text.startswith("file:"):
        return parse_init(text)
    path = text.split(":", 1)[1]
    if len(games) != 1:
        raise SpecError("--init", "file:PATH needs exactly one game (a result fits one game)")
    u, _p = read_result(path, games[0][1])
    return InitChoice("given", controls=u, label=f"file:{Path(path).name}")


def _save_figure(path: Path, fig) -> None:
    import matplotlib.pyplot as plt

    from scenarios.plotting import save_figure

    try:
        save_figure(fig, path, "--out", dpi=90)
    finally:
        plt.close(fig)


@click.command("compare")
@click.argument("games", nargs=-1)
@click.option(
    "--solver",
    "solver_texts",
    multiple=True,
    help="NAME[:key=value,...], NAME a registered solver (lm, ipopt, ilq, sqp or your own; "
    "repeat). Default: every registered solver.",
)
@click.option(
    "--init",
    "init_texts",
    multiple=True,
    help="zero, perturb:SEED[:SCALE] or file:PATH (an 'epo solve' result); repeat. Default: zero.",
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("results/compare"),
    show_default=True,
    help="Folder for the table and figures.",
)
@click.option(
    "--no-check",
    is_flag=True,
    help="Skip the equilibrium checks (local open-loop certificate or feedback Nash check).",
)
@click.option("--no-figures", is_flag=True, help="Write the table only.")
@click.option(
    "--scaling", is_flag=True, help="Also run the scaling study (N 2..8, K 20..200; minutes)."
)
@click.option("--quick", is_flag=True, help="Scaling study on fewer sizes (N 2, 4; K 20, 50).")
@allow_import_option
def compare(games, solver_texts, init_texts, out_dir, no_check, no_figures, scaling, quick):
    """Compare solvers on GAMES (files, folders or example:NAME) from several starts."""
    from scenarios.files import check_output_file, ensure_dir, write_atomic
    from solvers.compare import (
        fit_slopes,
        parse_solver,
        plot_gaps,
        plot_scaling,
        run_comparison,
        scaling_study,
    )
    from solvers.registry import SOLVERS

    check_output_file(out_dir / "compare.md", "--out")  # a folder that can be written, first
    solvers = [parse_solver(s) for s in (solver_texts or SOLVERS)]
    labels = [s.label for s in solvers]
    if len(set(labels)) != len(labels):
        raise SpecError("--solver", f"the same solver choice twice: {labels}")
    if not games and not scaling:
        raise SpecError("GAMES", "expected at least one game file or folder (or --scaling)")
    loaded = load_games(games)
    inits = [_read_init(t, loaded) for t in (init_texts or ("zero",))]
    ensure_dir(out_dir)
    if loaded:
        comp = run_comparison(loaded, solvers, inits, check=not no_check)
        write_atomic(out_dir / "compare.md", comp.markdown())
        write_atomic(out_dir / "compare.csv", comp.csv())
        click.echo(
            comp.markdown(
                (
                    "game",
                    "solver",
                    "init",
                    "status",
                    "equilibrium",
                    "energy",
                    "gap",
                    "iterations",
                    "setup_s",
                    "solve_s",
                    "check",
                    "verdict",
                )
            ),
            nl=False,
        )
        if not no_figures:
            for g in comp.games:
                _save_figure(out_dir / f"{g}_gap.png", plot_gaps(comp, g))
        click.echo(f"wrote {out_dir / 'compare.md'}, {out_dir / 'compare.csv'}")
    if scaling:
        from solvers.compare import ScalingRow

        Ns, Ks = ((2, 4), (20, 50)) if quick else (SCALING_N, SCALING_K)
        K_fixed, N_fixed = (20, 2) if quick else (40, 2)
        rows = scaling_study(crossing_family, solvers, Ns, Ks, K_fixed=K_fixed, N_fixed=N_fixed)
        buf = io.StringIO()
        import csv

        w = csv.writer(buf, lineterminator="\n")
        w.writerow(ScalingRow.header())
        for r in rows:
            w.writerow([getattr(r, c) for c in ScalingRow.header()])
        write_atomic(out_dir / "scaling.csv", buf.getvalue())
        sN, sK = fit_slopes(rows, "N", K_fixed), fit_slopes(rows, "K", N_fixed)
        md = [
            "| solver | N | K | n_u | status | iterations | setup_s | solve_s |",
            "|---" * 8 + "|",
        ]
        for r in rows:
            md.append(
                f"| {r.solver} | {r.N} | {r.K} | {r.n_u} | {r.status} | {r.iterations} | "
                f"{r.setup_s:.3f} | {r.solve_s:.4f} |"
            )
        md += ["", "| solver | slope in N | slope in K |", "|---|---|---|"]
        md += [f"| {s} | {sN[s]:.2f} | {sK[s]:.2f} |" for s in sN]
        write_atomic(out_dir / "scaling.md", "\n".join(md) + "\n")
        click.echo("\n".join(md))
        if not no_figures:
            _save_figure(out_dir / "scaling.png", plot_scaling(rows, K_fixed, N_fixed))
        click.echo(f"wrote {out_dir / 'scaling.md'}, {out_dir / 'scaling.csv'}")
