"""Diagnostic: error per future step of trained runs, and of ours' learned games solved further.

Not a benchmark and not part of ``make test``; it produced the "Ours' final step" tables of
docs/experiment_rpi.md::

    .venv/bin/python bench/final_step_profile.py --data DATA RUN [RUN ...] [--every 4]
    .venv/bin/python bench/final_step_profile.py --data DATA RUN --resolve --every 16

For every run: the mean error at steps 10, 20, 30, 38, 39, 40 of the best joint mode (by
SADE) over every ``every``-th validation sample, with the run's last checkpoint. With
``--resolve`` (ours only): the run's predicted game parameters and initial strategies
solved again with S = 2 and 5 paper LM steps and with a converged LM (20 and 100 steps),
with the mean |acceleration| and |turn rate| of the last five controls.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from learning.data import SceneDataset
from learning.evaluate import predict
from learning.layer import GameLayer
from learning.metrics import marginal_to_joint, min_sade, min_sfde
from learning.train import load_model
from solvers.lm import LMOptions

STEPS = [9, 19, 29, 37, 38, 39]


def profile(pos: torch.Tensor, gt: torch.Tensor, tag: str) -> None:
    err = torch.linalg.vector_norm(pos - gt[:, None], dim=-1)  # (B, M, N, T)
    best = err.mean((-1, -2)).argmin(1)
    e = err[torch.arange(len(best)), best].mean((0, 1))
    sade, sfde = min_sade(pos, gt).mean(), min_sfde(pos, gt).mean()
    steps = " ".join(f"{v:.3f}" for v in e[STEPS].tolist())
    print(f"{tag:<34} minSADE {sade:.3f} minSFDE {sfde:.3f} | steps 10 20 30 38 39 40: {steps}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--resolve", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(1)
    with SceneDataset(a.data, a.split) as ds:
        game = ds.game
        batch = ds.batch(np.arange(0, len(ds), a.every))
    gt = batch["gt"]
    for run in a.runs:
        model, cfg, _ = load_model(run, game, which="last")
        with torch.no_grad():
            pos, probs, out = predict(model, batch)
        if probs.ndim == 3:  # marginal model: joint scenes as the evaluation builds them
            pos, _ = marginal_to_joint(pos, probs)
        profile(pos, gt, run)
        if not a.resolve or cfg.model.kind != "epo":
            continue
        with torch.no_grad():
            z = model.encoder(batch)
            B, M, N, K, nu = z.shape[0], cfg.model.modes, model.N, model.K, model.nu
            u0 = model.initial_strategies(z)
            p = out["params"].double()
            m = cfg.model
            for S in (2, 5, 20, 100):
                if S <= 5:
                    opts = LMOptions.paper(steps=S, step_size=m.step_size, damping=m.damping)
                    layer, tag = GameLayer(model.game, opts), f"  LM S={S}, paper steps"
                else:
                    layer = GameLayer(model.game, LMOptions(steps=S), backward="implicit")
                    tag = f"  LM up to {S} steps, converging"
                o = layer(p, u0.double())
                x = o.states.float().reshape(B, M, N, K + 1, -1)[:, :, :, 1:, :2]
                profile(x, gt, tag)
                U = o.controls.reshape(B, M, N, K, nu)[..., -5:, :].abs().mean((0, 1, 2))
                print(
                    "    mean |a| of the last 5 controls:",
                    " ".join(f"{v:.3f}" for v in U[:, 0].tolist()),
                    " |w|:",
                    " ".join(f"{v:.3f}" for v in U[:, 1].tolist()),
                )


if __name__ == "__main__":
    main()
