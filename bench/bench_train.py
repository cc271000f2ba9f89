"""Time a training epoch of ours, V-LSTM + SC and V-LSTM on a small Peters RPI set.

Not a test. Run from the repository root::

    .venv/bin/python bench/bench_train.py                       # generates ~600 samples first
    .venv/bin/python bench/bench_train.py --data /tmp/rpi-small  # an existing RPI set

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
from learning.train import TrainConfig, train  # noqa: E402

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
    args = ap.parse_args(argv)
    if args.epochs < 2:
        ap.error("--epochs must be >= 2 (the first epoch is not timed)")
    tmp = None
    data = args.data
    if data is None:
        tmp = tempfile.mkdtemp(prefix="epo_bench_rpi_")
        data = os.path.join(tmp, "rpi")
        generate(data, args.samples, args.seed)
    try:
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
