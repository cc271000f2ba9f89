"""RPI generation speed: samples/s per worker and the projected full-size time.

Usage::

    .venv/bin/python bench/bench_rpi.py [--games 10] [--pipeline-games 30] [--workers 2]
                                        [--solver ilq] [--n-samples 8]

1. *Per worker*: ``--games`` main games of the full recipe (``K = 40``) run one after the
   other in this process (the game is built first and not timed): samples per main game,
   seconds per main game, samples/s per worker.
2. *Pipeline*: :func:`scenarios.dataset.generate` with ``--workers`` spawned processes
   on ``--pipeline-games`` main games (another seed), timed end to end (process
   start, game build, HDF5 writes): the aggregate samples/s.
3. *Projection*: the full recipe's main games x measured samples per game / the pipeline
   rate, printed against the 30-minute target as a ratio (< 1 is within the target); and
   the same with the workers' measured samples per CPU-second on ``--workers`` cores of
   their own (the pipeline line prints how many cores the workers actually got: on a
   machine shared with other jobs it is fewer than ``--workers``).

Timings depend on the machine's load; run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("EPO_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from scenarios import dataset as ds  # noqa: E402
from scenarios.rpi import RPIRecipe, RPIScenario  # noqa: E402

TARGET_S = 30 * 60


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--games", type=int, default=10, help="main games run in process")
    ap.add_argument("--pipeline-games", type=int, default=30, help="main games of the pipeline run")
    ap.add_argument("--workers", type=int, default=2, help="processes for the pipeline run")
    ap.add_argument("--solver", default=None, choices=["ilq", "lm"], help="default: the recipe's")
    ap.add_argument(
        "--n-samples", type=int, default=None, help="solves per (sub)game; default: the recipe's"
    )
    ap.add_argument("--seed", type=int, default=1000)
    a = ap.parse_args(argv)
    kw = {}
    if a.solver:
        kw["solver"] = a.solver
    if a.n_samples:
        kw["n_samples"] = a.n_samples
    full = RPIRecipe.full(**kw)
    print(
        f"recipe: {full.main_games} main games, K={full.horizon}, H={full.history}, "
        f"solver={full.solver}, n_samples={full.n_samples}; cores: {len(os.sched_getaffinity(0))}"
    )

    # 1. per worker, in process
    sc = RPIScenario(full)
    t = time.perf_counter()
    _ = sc.game
    build = time.perf_counter() - t
    sc.run_unit(0, ds.unit_seed(a.seed, 0))  # warm-up (caches, compiled code)
    n, secs = [], []
    for i in range(1, a.games + 1):
        t = time.perf_counter()
        out = sc.run_unit(i, ds.unit_seed(a.seed, i))
        secs.append(time.perf_counter() - t)
        n.append(len(out["step"]))
        print(
            f"  main game {i}: {n[-1]:3d} samples, {secs[-1]:6.2f} s, "
            f"two modes in {out['mode_valid'][:, 1].mean():.0%} of the samples"
        )
    per_game = float(np.mean(n))
    rate1 = sum(n) / sum(secs)
    print(
        f"per worker: game build {build:.2f} s; {per_game:.1f} samples/main game, "
        f"{np.mean(secs):.2f} s/main game, {rate1:.2f} samples/s"
    )

    # 2. the pipeline with W processes
    games = max(3, a.pipeline_games)
    rec = RPIRecipe.full(main_games=games, games_per_shard=1, **kw)
    with tempfile.TemporaryDirectory() as tmp:
        cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        rep = ds.generate(
            RPIScenario(rec), Path(tmp) / "d", seed=a.seed + 1, workers=a.workers, progress=False
        )
        wall = time.perf_counter() - t
        cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)
    rate = rep.samples_written / wall
    print(
        f"pipeline: {a.workers} workers, {games} main games, {rep.samples_written} samples in {wall:.1f} s "
        f"= {rate:.2f} samples/s ({rate / a.workers:.2f} per worker; "
        f"{rate / (a.workers * rate1):.2f} x the in-process rate per worker)"
    )

    per_cpu = rep.samples_written / cpu if cpu > 0 else float("nan")
    print(
        f"          worker CPU time {cpu:.1f} s = {cpu / wall:.2f} cores busy on average "
        f"({per_cpu:.2f} samples per CPU-second)"
    )

    # 3. projection: as measured, and with the workers' cores to themselves
    total = full.main_games * per_game
    proj = total / rate
    ded = total / (a.workers * per_cpu)
    print(
        f"full size: ~{total:,.0f} samples -> {proj / 60:.1f} min as measured "
        f"(ratio to the 30-min target {proj / TARGET_S:.2f}); "
        f"{ded / 60:.1f} min with {a.workers} dedicated cores (ratio {ded / TARGET_S:.2f})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
