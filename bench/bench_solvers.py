"""Solve time of every solver on the shipped examples, as ratios to the fastest in the run.

    .venv/bin/python bench/bench_solvers.py            # all four shipped examples, 3 repeats
    .venv/bin/python bench/bench_solvers.py --quick    # crossing2 and intersection4, 1 repeat

For each game, every solver (``lm``, ``ipopt``, ``ilq``, ``sqp``, default options) is set
up once (time printed apart, definition in :mod:`solvers.compare`) and then solves from
zero controls ``repeat`` times; the median solve time is printed with its ratio to the
fastest solver *of the same game in the same run*, so the numbers compare across
machines. Absolute seconds depend on the machine and its load (ours is shared).
"""

from __future__ import annotations

import argparse
import statistics
import time

from epo_casadi.game import PotentialGame
from scenarios.gamefile import example_path, load_game
from solvers.compare import parse_solver, setup_solver, solve_with
from solvers.registry import SOLVERS


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two games, one repeat")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    games = ("crossing2", "intersection4")
    if not args.quick:
        games += ("highway_merge", "robot_pedestrian")
    repeat = 1 if args.quick else max(1, args.repeat)
    print(
        f"{'game':16s} {'solver':6s} {'status':10s} {'setup s':>8s} {'solve s':>8s} {'ratio':>6s}"
    )
    for name in games:
        gf = load_game(example_path(name))
        rows = []
        for s in SOLVERS:
            choice = parse_solver(s)
            game = PotentialGame(gf.game.spec)
            u0 = game.zero_controls()
            t0 = time.perf_counter()
            setup_solver(choice, game, gf.params, u0)
            setup = time.perf_counter() - t0
            times, res = [], None
            for _ in range(repeat):
                res = solve_with(choice, game, gf.params, u0)
                times.append(res.wall_time)
            rows.append((s, res.status.value, setup, statistics.median(times)))
        fastest = min(r[3] for r in rows)
        for s, st, setup, t in rows:
            print(f"{name:16s} {s:6s} {st:10s} {setup:8.3f} {t:8.4f} {t / fastest:6.1f}")


if __name__ == "__main__":
    main()
