"""RPI generation speed: samples/s per worker and the projected full-size time.

Usage::

    .venv/bin/python bench/bench_rpi.py [--games 10] [--pipeline-games 30] [--workers 2]
                                        [--solver ilq] [--n-samples 8]
    .venv/bin/python bench/bench_rpi.py --batch [--games 10] [--starts 8 32 100]

``--batch``: the recipe's (Peters) main games, in this process, one CPU thread:

1. *Batched against per start*: each main game once with every (sub)game's starts solved
   in one batched iteration (:func:`solvers.ilq.iteration.solve_starts`, the default) and
   once start after start (the reference path), alternating; samples per CPU-second of
   each and their ratio, and whether the two gave the same samples (they must).
2. *Starts per subgame*: the same main games with ``sub_samples`` = each of ``--starts``
   (batched): CPU-seconds per sample, the share of samples with two valid modes, and the
   full recipe's main games projected onto 2 cores.

Without ``--batch``:

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
    ap.add_argument("--batch", action="store_true", help="batched against per-start solves")
    ap.add_argument("--starts", type=int, nargs="+", default=[8, 32, 100], help="with --batch")
    a = ap.parse_args(argv)
    if a.batch:
        return batch_main(a)
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


CLUSTER_CPU = [0.0]  # CPU seconds in the clustering (DBSCAN) of the Peters modes


def _timed_dbscan():
    """Count the CPU time of scenarios.rpi_peters' DBSCAN calls in CLUSTER_CPU."""
    from scenarios import rpi_peters

    inner = rpi_peters.dbscan

    def dbscan(*args):
        t = time.process_time()
        try:
            return inner(*args)
        finally:
            CLUSTER_CPU[0] += time.process_time() - t

    rpi_peters.dbscan = dbscan


def _unit(sc, i, seed, batched: bool):
    """Samples of main game ``i`` and the CPU seconds they took, batched or per start."""
    from solvers.ilq import iteration

    keep = iteration.batchable
    if not batched:  # the reference path: solve_starts solves one start after the other
        iteration.batchable = lambda s, opts: False
    try:
        t = time.process_time()
        out = sc.run_unit(i, ds.unit_seed(seed, i))
        return out, time.process_time() - t
    finally:
        iteration.batchable = keep


def batch_main(a) -> int:
    base = RPIRecipe.full()
    games = range(1, a.games + 1)
    print(
        f"recipe: ground truth {base.ground_truth}, {base.main_games} main games, K = "
        f"{base.game_horizon}, {base.n_samples} starts per main game, {base.sub_samples} per "
        f"subgame; {len(games)} main games (seed {a.seed}), CPU time of this process"
    )
    _timed_dbscan()
    sc = RPIScenario(base)
    _ = sc.truth_game
    t = time.process_time()
    _unit(sc, 0, a.seed, True)  # warm-up: code generation and compilation, not timed
    print(
        f"warm-up (main game 0, compiles the generated code): {time.process_time() - t:.1f} CPU-s"
    )

    # 1. batched against per start, alternating
    n = {True: 0, False: 0}
    cpu = {True: 0.0, False: 0.0}
    clus = {True: 0.0, False: 0.0}
    same = True
    for i in games:
        outs = {}
        for batched in (False, True) if i % 2 else (True, False):
            c0 = CLUSTER_CPU[0]
            outs[batched], c = _unit(sc, i, a.seed, batched)
            n[batched] += len(outs[batched]["step"])
            cpu[batched] += c
            clus[batched] += CLUSTER_CPU[0] - c0
        same &= all(np.array_equal(outs[True][k], outs[False][k]) for k in outs[True])
    rate = {b: n[b] / cpu[b] for b in (True, False)}
    print(
        f"per start: {n[False]} samples in {cpu[False]:.1f} CPU-s = {rate[False]:.2f} samples "
        f"per CPU-second; batched: {n[True]} in {cpu[True]:.1f} CPU-s = {rate[True]:.2f}; "
        f"ratio {rate[True] / rate[False]:.2f}; the same samples: {same}"
    )
    print(
        f"  of which clustering (scikit-learn DBSCAN): {clus[False]:.1f} / {clus[True]:.1f} "
        f"CPU-s ({1e3 * clus[True] / max(n[True], 1):.1f} ms per sample)"
    )

    # 2. starts per subgame (batched)
    ref = None
    for S in a.starts:
        r = RPIRecipe.full(sub_samples=S, warm_start=min(base.warm_start, S))
        scs = RPIScenario(r)
        _ = scs.truth_game
        m, c, two = 0, 0.0, 0
        for i in games:
            out, ci = _unit(scs, i, a.seed, True)
            m += len(out["step"])
            c += ci
            two += int(out["mode_valid"][:, 1].sum())
        per = c / max(m, 1)
        ref = per if ref is None else ref
        full = r.main_games * r.samples_per_game * per / 2 / 60
        print(
            f"{S:4d} starts per subgame: {m} samples, {per:.3f} CPU-s per sample "
            f"({ref / per:.2f} x the samples per CPU-second of {a.starts[0]}), two valid modes "
            f"in {two / max(m, 1):.0%}; full set ~{full:.0f} min on 2 cores"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
