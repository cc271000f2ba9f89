"""Benchmark: paper App. G's runtime and parameter table on an exiD-format dataset.

One run, one table: inference time per sample of V-LSTM, V-LSTM + SC, V-LSTM + TGL and
V-LSTM + Ours (ours split into NN: observation encoding, goal / weight / initial-strategy
and scene-probability decoders, and Opt: the S = 2 LM steps of the game layer) and the
number of trainable parameters, on the first ``--samples`` samples of a split of a dataset
made by ``epo generate exid`` (N = 4, K = 20, M = 5; paper network sizes). Two timings:
one batch of all the samples (time / samples) and the samples one at a time (mean), each
the median over ``--repeats`` runs after one warm-up, eval mode, no gradients; both as
wall time and as the process's CPU time (``time.process_time``: on a machine shared with
other jobs the wall time also counts the time the process waits for a core).

The models are freshly initialized (seed 0) unless ``--run KIND=RUN_DIR`` loads a trained
run (its ``best.pt``); TGL's and the layer's work do not depend much on the weights (S is
fixed; OSQP's iterations do vary).

Run ``python bench/bench_exid_runtime.py --data data/exid`` (100 samples, 5 repeats) or
``--quick`` (20 samples, 2 repeats).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from learning.data import SceneDataset  # noqa: E402
from learning.models import ModelConfig, build_model, count_parameters  # noqa: E402
from learning.train import load_model  # noqa: E402

KINDS = (("vlstm", "V-LSTM"), ("sc", "+ SC"), ("tgl", "+ TGL"), ("epo", "Ours"))


class _LayerClock:
    """Accumulates the wall and CPU time spent inside ``model.layer`` (ours' game layer)."""

    def __init__(self, layer: torch.nn.Module):
        self.total, self._t0 = np.zeros(2), np.zeros(2)
        layer.register_forward_pre_hook(self._pre)
        layer.register_forward_hook(self._post)

    def _pre(self, *_):
        self._t0 = _now()

    def _post(self, *_):
        self.total += _now() - self._t0


def _now() -> np.ndarray:
    return np.array([time.perf_counter(), time.process_time()])


def _subset(batch: dict, i: int) -> dict:
    return {k: v[i : i + 1] for k, v in batch.items()}


def time_model(model, batch: dict, repeats: int, clock: _LayerClock | None) -> dict:
    """Seconds per sample ``{(mode, clock): (full, in the layer)}``: ``mode`` "batch" (all
    samples at once) or "single" (one at a time), ``clock`` "wall" or "cpu"."""
    B = int(batch["history"].shape[0])
    singles = [_subset(batch, i) for i in range(B)]
    out = {}
    with torch.no_grad():
        for mode, runs in (("batch", [batch]), ("single", singles)):
            full, opt = [], []
            for r in range(repeats + 1):
                if clock is not None:
                    clock.total[:] = 0.0
                t0 = _now()
                for b in runs:
                    model(b)
                dt = _now() - t0
                if r:  # the first run is the warm-up
                    full.append(dt / B)
                    opt.append(clock.total / B if clock is not None else np.zeros(2))
            for j, name in enumerate(("wall", "cpu")):
                out[mode, name] = (
                    statistics.median(f[j] for f in full),
                    statistics.median(o[j] for o in opt),
                )
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="data/exid", help="dataset directory (epo generate exid)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--samples", type=int, default=None, help="default 100 (--quick: 20)")
    ap.add_argument("--repeats", type=int, default=None, help="default 5 (--quick: 2)")
    ap.add_argument("--modes", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--quick", action="store_true", help="20 samples, 2 repeats")
    ap.add_argument(
        "--run",
        action="append",
        default=[],
        metavar="KIND=RUN_DIR",
        help="load a trained run for a model kind (vlstm, sc, tgl, epo); repeatable",
    )
    a = ap.parse_args(argv)
    S = a.samples or (20 if a.quick else 100)
    R = a.repeats or (2 if a.quick else 5)
    runs = dict(r.split("=", 1) for r in a.run)
    torch.set_num_threads(a.threads)
    with SceneDataset(a.data, a.split) as data:
        game = data.game
        batch = data.batch(range(min(S, len(data))))
    B = int(batch["history"].shape[0])
    rows = {}
    for kind, label in KINDS:
        if kind in runs:
            model, cfg, _ = load_model(runs[kind], game)
            src = f"trained ({runs[kind]})"
        else:
            torch.manual_seed(0)
            extra = {"goal_decoder": "candidates"} if kind == "epo" else {}
            model = build_model(ModelConfig(kind=kind, modes=a.modes, **extra), game)
            src = "initialized (seed 0)"
        model.eval()
        clock = _LayerClock(model.layer) if kind == "epo" else None
        rows[kind] = (label, time_model(model, batch, R, clock), count_parameters(model), src)
        t = rows[kind][1]["batch", "cpu"][0]
        print(f"  {label}: {t * 1e3:.2f} ms CPU / sample", file=sys.stderr)

    print(
        f"\nInference time per sample in s (exiD format: N = {game.N}, K = {game.K}, "
        f"M = {a.modes}; {B} samples of '{a.split}', median of {R}; "
        f"{a.threads} torch thread(s))\n"
    )
    print("| | V-LSTM | + SC | + TGL | Ours (NN) | Ours (Opt.) | Ours (full) |")
    print("|---|---|---|---|---|---|---|")
    for key, title in (
        (("batch", "cpu"), f"CPU time, batch of {B}"),
        (("single", "cpu"), "CPU time, batch of 1"),
        (("batch", "wall"), f"wall time, batch of {B}"),
        (("single", "wall"), "wall time, batch of 1"),
    ):
        t = {k: rows[k][1][key] for k in rows}
        full, opt = t["epo"]
        cells = [f"{t[k][0]:.4f}" for k in ("vlstm", "sc", "tgl")]
        cells += [f"{full - opt:.4f}", f"{opt:.4f}", f"{full:.4f}"]
        print(f"| {title} | " + " | ".join(cells) + " |")
    n = {k: f"{rows[k][2]:,}" for k in rows}
    print(
        f"| learnable parameters | {n['vlstm']} | {n['sc']} | {n['tgl']} | {n['epo']} | - "
        f"| {n['epo']} |"
    )
    print("\nmodels: " + "; ".join(f"{rows[k][0]} {rows[k][3]}" for k in rows))


if __name__ == "__main__":
    main()
