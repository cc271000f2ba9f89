"""Benchmark: TGL (learning/tgl.py) beside ours and the other predictors; not part of the tests.

One run, one table: forward + backward (scene or marginal loss) of one training batch for
V-LSTM, V-LSTM + SC, V-LSTM + TGL and V-LSTM + Ours (paper App. G's runtime row, here on
CPU) in the RPI setting (N = 2, K = 40, dt = 0.1, H = 18, M = 2; paper network sizes),
medians over ``--repeats`` runs after one warm-up, as seconds and as ratios to ours. TGL's
time is also split into the OSQP loop (one solve per problem), the batched KKT refinement
and its backward, and the rest (networks, QP assembly). Trainable parameter counts too.

Run ``python bench/bench_tgl.py`` (batch 32, 5 repeats) or ``--quick`` (batch 8, 2 repeats).
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

from learning import tgl  # noqa: E402
from learning.models import ModelConfig, build_model, count_parameters  # noqa: E402
from learning.train import PAPER_LOSS_WEIGHTS, compute_loss  # noqa: E402
from scenarios.rpi import RPIRecipe, RPIScenario  # noqa: E402


def rpi_batch(scn: RPIScenario, B: int, seed: int = 0) -> dict:
    """``B`` RPI-like scenes: start states of sampled main games, constant-velocity
    histories, ground truth = a slightly perturbed constant-velocity future."""
    r = scn.recipe
    rng = np.random.default_rng(seed)
    hist, gt, goals = [], [], []
    for b in range(B):
        cfg = scn.sample_config(b, rng)
        x = cfg.x0.copy()
        x[:, 2] = np.maximum(x[:, 2], 0.5)
        hist.append(np.concatenate([scn.pre_history(x, r.history), x[None]]))
        t = r.dt * np.arange(1, r.horizon + 1)[:, None]
        fut = (
            x[:, None, :2]
            + x[:, None, 2:3] * t * np.stack([np.cos(x[:, 3]), np.sin(x[:, 3])], -1)[:, None]
        )
        gt.append(fut + rng.normal(0, 0.05, fut.shape))
        goals.append(cfg.goals)
    f = torch.float32
    return {
        "history": torch.tensor(np.stack(hist), dtype=f),
        "gt": torch.tensor(np.stack(gt), dtype=f),
        "goals": torch.tensor(np.stack(goals), dtype=f),
    }


class _Split:
    """Accumulates the time spent in TGL's OSQP loop, KKT refinement and QP backward."""

    def __init__(self):
        self.t = {"osqp": 0.0, "kkt": 0.0, "qp_backward": 0.0}
        self._osqp, self._solve, self._bwd = tgl._osqp_solve, tgl.solve_qp, tgl.QPFunction.backward

    def __enter__(self):
        split = self

        def osqp_solve(*a, **k):
            t0 = time.perf_counter()
            out = split._osqp(*a, **k)
            split.t["osqp"] += time.perf_counter() - t0
            return out

        def solve_qp(*a, **k):
            t0 = time.perf_counter()
            o0 = split.t["osqp"]
            out = split._solve(*a, **k)
            split.t["kkt"] += time.perf_counter() - t0 - (split.t["osqp"] - o0)
            return out

        def backward(ctx, *g):
            t0 = time.perf_counter()
            out = split._bwd(ctx, *g)
            split.t["qp_backward"] += time.perf_counter() - t0
            return out

        tgl._osqp_solve, tgl.solve_qp = osqp_solve, solve_qp
        tgl.QPFunction.backward = staticmethod(backward)
        return self

    def __exit__(self, *exc):
        tgl._osqp_solve, tgl.solve_qp = self._osqp, self._solve
        tgl.QPFunction.backward = staticmethod(self._bwd)


def time_step(model, kind: str, batch: dict, repeats: int) -> list[float]:
    weights = PAPER_LOSS_WEIGHTS[kind]
    out = []
    for i in range(repeats + 1):
        model.zero_grad(set_to_none=True)
        t0 = time.perf_counter()
        parts = compute_loss(kind, model(batch), batch["gt"], weights)
        parts["loss"].backward()
        if i:  # the first run is the warm-up
            out.append(time.perf_counter() - t0)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="batch 8, 2 repeats")
    ap.add_argument("--batch", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    a = ap.parse_args(argv)
    B = a.batch or (8 if a.quick else 32)
    R = a.repeats or (2 if a.quick else 5)
    torch.set_num_threads(a.threads)
    scn = RPIScenario(RPIRecipe())
    game = scn.game
    batch = rpi_batch(scn, B)
    rows = {}
    split = None
    for kind, label in (
        ("vlstm", "V-LSTM"),
        ("sc", "V-LSTM + SC"),
        ("tgl", "V-LSTM + TGL"),
        ("epo", "V-LSTM + Ours"),
    ):
        torch.manual_seed(0)
        model = build_model(ModelConfig(kind=kind, modes=2), game).train()
        if kind == "tgl":
            with _Split() as sp:
                ts = time_step(model, kind, batch, R)
            split = {k: v / (R + 1) for k, v in sp.t.items()}  # per step (warm-up included)
        else:
            ts = time_step(model, kind, batch, R)
        rows[label] = (statistics.median(ts), count_parameters(model))
        print(f"  {label}: {rows[label][0]:.3f} s", file=sys.stderr)
    ours = rows["V-LSTM + Ours"][0]
    print(
        f"\nForward + backward of one training batch (RPI: N = 2, K = 40, M = 2, batch {B}; "
        f"median of {R}; {a.threads} torch thread(s))\n"
    )
    print("| model | s / batch | ms / sample | x ours | parameters |")
    print("|---|---|---|---|---|")
    for label, (t, n) in rows.items():
        print(f"| {label} | {t:.3f} | {1e3 * t / B:.1f} | {t / ours:.2f} | {n:,} |")
    if split:
        tt = rows["V-LSTM + TGL"][0]
        print(f"\nTGL per batch ({B * 2} QPs): " + ", ".join(
            f"{k} {v:.3f} s ({v / tt:.0%})" for k, v in split.items()
        ) + f", rest {max(tt - sum(split.values()), 0):.3f} s")  # fmt: skip


if __name__ == "__main__":
    main()
