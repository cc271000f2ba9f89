"""Time a training epoch of ours, V-LSTM + SC and V-LSTM on a small Peters RPI set.

Not a test. Run from the repository root::

    .venv/bin/python bench/bench_train.py                       # generates ~600 samples first
    .venv/bin/python bench/bench_train.py --data /tmp/rpi-small  # an existing RPI set
    .venv/bin/python bench/bench_train.py --nproc 1 2 --rows ours SC   # data-parallel scaling

Each row trains one model from scratch for ``--epochs`` epochs (default 2) with the paper's
settings (batch 32; ours: S = 2 LM steps, alpha = 0.3, lambda = 10; no validation pass),
torch on ``--threads`` threads (default 1), and reports the *last* epoch (the first one
pays for building and, once per game structure, compiling the layer's generated C):

* ``samples/s``: what ``metrics.csv`` records (wall clock of the epoch's batches);
* ``CPU s / epoch``: process CPU time (``time.process_time``) of the epoch's optimizer
  steps: from the end of its first step to the end of its last, scaled by
  ``steps / (steps - 1)`` (so the previous epoch's checkpoint write and loss plot, about
  0.1 to 0.5 s of CPU for every model, are left out); ``wall s / epoch`` the same in wall
  clock;
* ``/ SC``: this row's CPU seconds per epoch over SC's (issue 14: ours <= 1.5).

With ``--nproc 1 2`` (any counts) each row instead trains on that many local ranks
(:func:`learning.train.train_parallel`: data-parallel, each rank a shard of every
batch of ``--batch``) and the table gives the last epoch's ``samples/s`` (rank 0's wall
clock of the epoch's batches, as ``metrics.csv`` records it), beside the single-process
figure, and the scaling efficiency ``rate(N) / (N * rate(1))``; the process start (torch
import, process group, the first epoch's compilation) is left out of the rate and shown
as the call's total wall time. CPU time is not measured there (it is spread over the
ranks' processes).

Rows: ``ours`` (the default ``layer_backend=auto``, ``layer_compiled=auto``: the fused
backend in generated C when a compiler is found), ``ours before`` (``layer_backend=
structured``, ``layer_compiled=no``: the interpreted structured backend, the default before
2026-11-30), ``SC`` and ``V-LSTM``. The rows run in turn in one process, ``--rounds`` times
(default 3; medians over rounds are printed). Without ``--data`` the set is generated first
(``epo generate rpi --samples N``, one worker) into a temporary folder that is removed
afterwards (``--keep`` keeps it and prints its path).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("EPO_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from learning.models import ModelConfig, layer_execution  # noqa: E402
from learning.train import (  # noqa: E402
    TrainConfig,
    train,
    train_parallel,  # noqa: E402
)

ROWS = {
    "ours": dict(kind="epo"),
    "ours before": dict(kind="epo", layer_backend="structured", layer_compiled="no"),
    "SC": dict(kind="sc"),
    "V-LSTM": dict(kind="vlstm"),
}


def generate(out: str, samples: int, seed: int) -> None:
    """An RPI set (the default Peters recipe) of about ``samples`` samples in ``out``."""
    cmd = [
        os.path.join(os.path.dirname(sys.executable), "epo"),
        "generate",
        "rpi",
        "--samples",
        str(samples),
        "--out",
        out,
        "--workers",
        "1",
        "--seed",
        str(seed),
        "--no-progress",
    ]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    print(f"generated {out} in {time.perf_counter() - t0:.1f} s")


def time_row(data: str, model: dict, epochs: int, batch: int, threads: int) -> dict:
    """Train one model from scratch; the last epoch's samples/s and CPU/wall seconds."""
    cfg = TrainConfig(
        model=ModelConfig(lm_steps=2, step_size=0.3, damping=10.0, **model),
        epochs=epochs,
        batch_size=batch,
        val_split=None,
    )
    marks: list[tuple[float, float]] = []

    def on_step(step: int, parts: dict) -> None:
        marks.append((time.process_time(), time.perf_counter()))

    with tempfile.TemporaryDirectory(prefix="epo_bench_train_") as out:
        c0, w0 = time.process_time(), time.perf_counter()
        res = train(data, out, cfg, progress=False, on_step=on_step, threads=threads)
        c1, w1 = time.process_time(), time.perf_counter()
    spe = res.steps // epochs
    if spe < 2:
        raise SystemExit(f"{data}: {spe} optimizer step(s) per epoch; the timing needs >= 2")
    last = res.history[-1]
    a, b = marks[-spe], marks[-1]  # end of the last epoch's first step, end of its last
    scale = spe / (spe - 1)
    return {
        "samples_per_s": float(last["samples_per_s"]),
        "cpu": scale * (b[0] - a[0]),
        "wall": scale * (b[1] - a[1]),
        "steps": spe,
        "first_cpu": marks[spe - 1][0] - c0,
        "total_cpu": c1 - c0,
        "total_wall": w1 - w0,
        "loss": float(last["train_loss"]),
    }


def time_parallel(data: str, model: dict, epochs: int, batch: int, threads: int, nproc: int):
    """Train one model from scratch on ``nproc`` local ranks; the last epoch's samples/s."""
    cfg = TrainConfig(
        model=ModelConfig(lm_steps=2, step_size=0.3, damping=10.0, **model),
        epochs=epochs,
        batch_size=batch,
        val_split=None,
    )
    with tempfile.TemporaryDirectory(prefix="epo_bench_train_") as out:
        w0 = time.perf_counter()
        res = train_parallel(nproc, data, out, cfg, progress=False, threads=threads)
        w1 = time.perf_counter()
    last = res.history[-1]
    return {
        "samples_per_s": float(last["samples_per_s"]),
        "epoch_wall": float(last["seconds"]),
        "total_wall": w1 - w0,
        "steps": res.steps // epochs,
        "loss": float(last["train_loss"]),
    }


def scaling(args, data: str) -> None:
    """The ``--nproc`` table: samples/s per row and rank count, efficiency against 1."""
    res: dict[tuple[str, int], list[dict]] = {}
    for rnd in range(args.rounds):
        for r in args.rows:
            for n in args.nproc:
                out = time_parallel(data, ROWS[r], args.epochs, args.batch, args.threads, n)
                res.setdefault((r, n), []).append(out)
                print(
                    f"  round {rnd + 1} {r:12s} nproc {n}: {out['samples_per_s']:8.1f} samples/s "
                    f"(epoch {out['epoch_wall']:.2f} s, call {out['total_wall']:.1f} s, "
                    f"loss {out['loss']:.4f})",
                    flush=True,
                )
    med = {
        k: {q: float(np.median([o[q] for o in v])) for q in ("samples_per_s", "total_wall")}
        for k, v in res.items()
    }
    print(
        f"\nlast epoch ({res[(args.rows[0], args.nproc[0])][0]['steps']} steps of "
        f"{args.batch}), median of {args.rounds} round(s), {os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.1f}\n"
    )
    print("| model | ranks | samples/s (wall) | vs 1 rank | efficiency | call wall s |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in args.rows:
        one = med.get((r, 1), {}).get("samples_per_s")
        for n in args.nproc:
            m = med[(r, n)]
            speed = f"{m['samples_per_s'] / one:.2f}x" if one else "-"
            eff = f"{m['samples_per_s'] / (n * one):.0%}" if one else "-"
            print(
                f"| {r} | {n} | {m['samples_per_s']:.1f} | {speed} | {eff} | "
                f"{m['total_wall']:.1f} |"
            )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", help="an RPI dataset folder (default: generate one)")
    ap.add_argument("--samples", type=int, default=600, help="samples to generate (no --data)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the generated set")
    ap.add_argument("--keep", action="store_true", help="keep the generated set")
    ap.add_argument("--epochs", type=int, default=2, help="epochs per row (the last is timed)")
    ap.add_argument("--batch", type=int, default=32, help="batch size (paper: 32)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--rounds", type=int, default=3, help="repeat all rows this many times")
    ap.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS), help="rows to run")
    ap.add_argument(
        "--nproc",
        nargs="+",
        type=int,
        default=None,
        help="rank counts: the data-parallel scaling table instead (e.g. --nproc 1 2)",
    )
    args = ap.parse_args(argv)
    if args.nproc is not None and min(args.nproc) < 1:
        ap.error("--nproc: every count must be >= 1")
    if args.epochs < 2:
        ap.error("--epochs must be >= 2 (the first epoch is not timed)")
    tmp = None
    data = args.data
    if data is None:
        tmp = tempfile.mkdtemp(prefix="epo_bench_rpi_")
        data = os.path.join(tmp, "rpi")
        generate(data, args.samples, args.seed)
    try:
        if args.nproc is not None:
            print(
                f"data {data}; epochs {args.epochs} (last timed), global batch {args.batch}, "
                f"torch threads {args.threads} per rank, ranks {args.nproc}; "
                f"load average {os.getloadavg()[0]:.1f}"
            )
            scaling(args, data)
            return 0
        backend, compiled = layer_execution(ModelConfig())
        print(
            f"data {data}; epochs {args.epochs} (last timed), batch {args.batch}, "
            f"torch threads {args.threads}, S = 2, alpha = 0.3, lambda = 10; "
            f"'ours' resolves to backend={backend}, compiled={compiled}; "
            f"load average {os.getloadavg()[0]:.1f}"
        )
        res: dict[str, list[dict]] = {r: [] for r in args.rows}
        for rnd in range(args.rounds):
            for r in args.rows:
                out = time_row(data, ROWS[r], args.epochs, args.batch, args.threads)
                res[r].append(out)
                print(
                    f"  round {rnd + 1} {r:12s} {out['samples_per_s']:8.1f} samples/s  "
                    f"CPU {out['cpu']:6.2f} s  wall {out['wall']:6.2f} s  "
                    f"(first epoch CPU {out['first_cpu']:.2f} s, loss {out['loss']:.4f})",
                    flush=True,
                )
        med = {
            r: {k: float(np.median([o[k] for o in v])) for k in ("samples_per_s", "cpu", "wall")}
            for r, v in res.items()
        }
        sc = med.get("SC", {}).get("cpu")
        print(
            f"\nlast epoch ({res[args.rows[0]][0]['steps']} steps of {args.batch}), "
            f"median of {args.rounds} round(s), load average {os.getloadavg()[0]:.1f}\n"
        )
        print("| model | samples/s (wall) | CPU s / epoch | wall s / epoch | CPU / SC |")
        print("|---|---:|---:|---:|---:|")
        for r, m in med.items():
            ratio = f"{m['cpu'] / sc:.2f}" if sc else "-"
            print(
                f"| {r} | {m['samples_per_s']:.1f} | {m['cpu']:.2f} | {m['wall']:.2f} | {ratio} |"
            )
        if sc and "ours" in med:
            print(f"\nours / SC (CPU per epoch): {med['ours']['cpu'] / sc:.2f} (issue 14: <= 1.5)")
    finally:
        if tmp is not None:
            if args.keep:
                print(f"kept {data}")
            else:
                shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
