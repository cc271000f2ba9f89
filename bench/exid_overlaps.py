"""Diagnosis: where the box overlap rate (OR) of exiD-layout predictions comes from.

For the ground truth, constant velocity and each given run, on one split (default val):
the box OR of :func:`learning.metrics.overlap_rate_boxes` (most likely joint mode, any two
agents' oriented boxes intersect at any future step; asserted equal here) and, per
overlapping scene, its first overlapping step ``t1`` and pair ``(i, j)``, with ``j``'s
offset (``lon``, ``lat``: medians of the absolute values, m) in the frame of ``i``'s current
lane direction and the pair's relative heading ``relh`` (median, degrees). Classes:

- ``rear``: lateral offset < ``--lat`` (1 m): the same lane, one runs into the other;
- ``cutin``: laterally offset, and one of the two has moved more than ``--lat`` across its
  current lane direction since the current time: a lane change / merge;
- ``side``: laterally offset, both keep their lane: side by side in adjacent lanes.

Shares of the overlapping scenes: ``truck`` (a vehicle longer than 8 m in the pair), ``a0``
(agent 0, the scene's lane changer, in the pair), ``chk`` (the first overlap falls on a
step where the game checks collisions: every 5th, 5, 10, 15, 20), ``anychk`` (the scene
overlaps on some checked step), ``circ`` (at the first overlap the game's circles,
r = L / 2 each, overlap too), ``gt_near`` (the same pair comes within 0.5 m in the ground
truth). Multimodal predictors: ``modes_ov`` the share of all modes that overlap,
``other_free`` the share of overlapping scenes with an overlap-free other mode,
``OR_closest`` the OR of the mode closest to the ground truth (minSADE's mode).

Box clearance = the margin by which both boxes must grow (each side by half of it) to
touch, by bisection on :func:`learning.metrics.box_overlap` (0 when they intersect); for
parallel boxes it is their distance. Then the ground truth's own gaps (minimum clearance
per scene over all pairs and steps; same-lane and lateral pairs) and, for runs with game
parameters (ours), the learned collision and own weights of the most likely mode.

Run (CPU, ~30 s; nothing is written)::

    R=/work/runs/exid2
    nice -n 10 python bench/exid_overlaps.py --data /work/data/exid-gen --split val \\
        --run vlstm=$R/vlstm-vlstm-lr5e-4-s0 --run sc=$R/sc-vlstm-lr5e-4-s0 \\
        --run ours=$R/epo-vlstm-lr5e-4-s0 --run tgl=$R/tgl-vlstm-lr1e-3-s0
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from epo_casadi.errors import EpoError  # noqa: E402
from learning.baselines import ConstantVelocity  # noqa: E402
from learning.data import SceneDataset  # noqa: E402
from learning.metrics import (  # noqa: E402
    box_hits,
    marginal_to_joint,
    overlap_rate_boxes,
)
from learning.scoring import boxes, predict  # noqa: E402
from learning.train import load_model  # noqa: E402


def collect(data: SceneDataset, runs: dict[str, str], batch_size: int = 256) -> tuple:
    """Per predictor ``(pos (B, M, N, T, 2), probs (B, M), params or None)`` plus the batch."""
    models = {"GT": None, "CV": ConstantVelocity(data.game.K, data.modes)}
    models.update({k: load_model(v, data.game)[0] for k, v in runs.items()})
    parts: dict[str, list] = {k: [] for k in models}
    batches = []
    with torch.no_grad():
        for b in data.batches(batch_size):
            batches.append(b)
            for name, model in models.items():
                if model is None:
                    pos, probs, out = b["gt"][:, None], torch.ones(len(b["gt"]), 1), {}
                else:
                    pos, probs, out = predict(model, b)
                if probs.ndim == 3:
                    pos, probs = marginal_to_joint(pos, probs)
                parts[name].append((pos.float(), probs.float(), out.get("params")))
    batch = {k: torch.cat([b[k] for b in batches]) for k in batches[0]}
    res = {}
    for name, ps in parts.items():
        params = None if ps[0][2] is None else torch.cat([p[2] for p in ps]).double()
        res[name] = (torch.cat([p[0] for p in ps]), torch.cat([p[1] for p in ps]), params)
    return res, batch


def pairwise(pos, bx, margin=0.0):
    """Box hits ``(B, N, N, T)`` of trajectories ``pos`` ``(B, N, T, 2)`` with the metric's
    headings and boxes, each grown by ``margin`` in length and width, and the headings."""
    return box_hits(pos, bx["length"], bx["width"], bx["start"], bx["heading0"], grow=margin)


def clearance(pos, bx, hi: float = 64.0, iters: int = 14) -> torch.Tensor:
    """Box clearance ``(B, N, N, T)`` (m, to hi / 2^iters) by bisection on grown boxes."""
    hit = pairwise(pos, bx)[0]
    lo_, hi_ = torch.zeros(hit.shape), torch.full(hit.shape, hi)
    for _ in range(iters):
        mid = 0.5 * (lo_ + hi_)
        grown = pairwise(pos, bx, mid)[0]
        lo_, hi_ = torch.where(grown, lo_, mid), torch.where(grown, mid, hi_)
    return torch.where(hit, torch.zeros_like(hi_), hi_)


def _frame(d, h):
    """``d`` ``(..., 2)`` in the frame of heading ``h``: (longitudinal, lateral)."""
    c, s = torch.cos(h), torch.sin(h)
    return d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c


def lane_heading(batch) -> torch.Tensor:
    """Direction ``(B, N)`` of each agent's current lane (``paths``) at its current position."""
    path, start = batch["paths"], batch["history"][:, -1, :, :2]
    seg = path[:, :, 1:] - path[:, :, :-1]  # (B, N, P - 1, 2)
    mid = 0.5 * (path[:, :, 1:] + path[:, :, :-1])
    k = torch.linalg.vector_norm(mid - start[:, :, None], dim=-1).argmin(-1, keepdim=True)
    d = torch.gather(seg, 2, k[..., None].expand(-1, -1, 1, 2))[:, :, 0]
    return torch.atan2(d[..., 1], d[..., 0])


def lateral_motion(pos, bx, lane_h):
    """Largest sideways displacement so far ``(B, N, T)``: across the agent's current lane
    direction ``lane_h`` ``(B, N)``, from its current position."""
    lat = _frame(pos - bx["start"][:, :, None], lane_h[:, :, None])[1].abs()
    return lat.cummax(-1).values


def breakdown(pos, probs, bx, lane_h, radius, steps, gt_clear, lat_tol: float = 1.0) -> dict:
    """The OR of the most likely mode and the classes of its overlapping scenes."""
    B, N = pos.shape[0], pos.shape[2]
    best = pos[torch.arange(B), probs.argmax(1)]  # (B, N, T, 2)
    hit, h = pairwise(best, bx)
    hit = hit & torch.ones(N, N, dtype=torch.bool).triu(1)[None, :, :, None]
    scene = hit.flatten(1, 2).any(1)  # (B, T)
    ov = scene.any(-1)
    assert torch.equal(ov.to(pos.dtype), overlap_rate_boxes(pos, probs, **bx))  # same metric
    idx = ov.nonzero()[:, 0]
    row = {"OR": ov.float().mean().item(), "n": len(idx), "idx": idx, "best": best, "hit": hit}
    if len(idx) == 0:
        return row
    t1 = scene[idx].float().argmax(-1)  # first overlapping step (0-based)
    first = hit[idx, :, :, t1].flatten(1).float().argmax(1)
    i, j = first // N, first % N
    pi, pj, hi, hj = best[idx, i, t1], best[idx, j, t1], h[idx, i, t1], h[idx, j, t1]
    lon, lat = _frame(pj - pi, lane_h[idx, i])  # in agent i's lane frame
    moved = lateral_motion(best, bx, lane_h)
    lc = (moved[idx, i, t1] > lat_tol) | (moved[idx, j, t1] > lat_tol)
    rear = lat.abs() < lat_tol
    L = bx["length"]
    dist = torch.linalg.vector_norm(pi - pj, dim=-1)
    checked = torch.zeros(scene.shape[1], dtype=torch.bool)
    checked[[s - 1 for s in steps]] = True
    row.update(
        rear=rear.float().mean().item(),
        cutin=(~rear & lc).float().mean().item(),
        side=(~rear & ~lc).float().mean().item(),
        truck=(torch.maximum(L[idx, i], L[idx, j]) > 8).float().mean().item(),
        a0=(i == 0).float().mean().item(),
        t1=float((t1 + 1).float().median()),
        chk=checked[t1].float().mean().item(),
        anychk=scene[idx][:, checked].any(-1).float().mean().item(),
        circ=(dist < radius[idx, i] + radius[idx, j]).float().mean().item(),
        gt_near=(gt_clear[idx, i, j].amin(-1) < 0.5).float().mean().item(),
        relh=float(
            torch.rad2deg(torch.remainder(hj - hi + torch.pi, 2 * torch.pi) - torch.pi)
            .abs()
            .median()
        ),
        lon=float(lon.abs().median()),
        lat=float(lat.abs().median()),
        pairs=(i, j),
        t1s=t1 + 1,
        cls=np.where(rear.numpy(), "rear", np.where(lc.numpy(), "cut-in", "side")),
    )
    return row


def gt_gaps(gt, lane_h, gt_clear, lat_tol: float = 1.0) -> dict:
    """The ground truth's minimum box clearance per scene: all pairs, same-lane, lateral."""
    N = gt.shape[1]
    lat = _frame(gt[:, None] - gt[:, :, None], lane_h[:, :, None, None])[1].abs()  # (B, N, N, T)
    upper = torch.ones(N, N, dtype=torch.bool).triu(1)[None, :, :, None]
    inf = torch.full_like(gt_clear, float("inf"))
    out = {}
    for name, sel in (
        ("all", upper),
        ("same lane", upper & (lat < lat_tol)),
        ("lateral", upper & (lat >= lat_tol)),
    ):
        m = torch.where(sel, gt_clear, inf).flatten(1).amin(1)
        out[name] = m
    return out


def mode_overlaps(pos, probs, bx, gt) -> dict:
    """Per mode the OR (as if it were the most likely); the other modes of overlapping scenes."""
    B, M = probs.shape
    eye = torch.eye(M)
    per = torch.stack([overlap_rate_boxes(pos, eye[m].expand(B, M), **bx) for m in range(M)], 1)
    top = per[torch.arange(B), probs.argmax(1)].bool()
    sade = torch.linalg.vector_norm(pos - gt[:, None], dim=-1).mean((-1, -2))  # (B, M)
    closest = per[torch.arange(B), sade.argmin(1)]
    free = (per[top] == 0).any(-1).float().mean().item() if top.any() else float("nan")
    return {"modes_ov": per.mean().item(), "other_free": free, "OR_closest": closest.mean().item()}


def collision_weights(params, game, best_mode) -> torch.Tensor:
    """Learned collision weights of the most likely mode ``(B, N, N)`` (upper triangle)."""
    names = [a.name for a in game.agents]
    blocks = game.params.unpack(params.numpy())
    B, N = params.shape[0], len(names)
    W = torch.full((B, N, N), float("nan"), dtype=torch.float64)
    for a in range(N):
        for b in range(a + 1, N):
            w = torch.as_tensor(blocks[f"w.{names[a]}-{names[b]}.collision"][..., 0])
            W[:, a, b] = w[torch.arange(B), best_mode]
    return W


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--run", action="append", default=[], metavar="NAME=RUN_DIR")
    ap.add_argument("--lat", type=float, default=1.0, help="same-lane lateral offset (m)")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    if any("=" not in r for r in a.run):
        ap.exit(2, "error: --run: expected NAME=RUN_DIR\n")
    runs = dict(r.split("=", 1) for r in a.run)
    try:
        data = SceneDataset(a.data, a.split)
        preds, batch = collect(data, runs)
    except EpoError as e:  # a missing dataset / split / run: one line, exit 2
        ap.exit(2, f"error: {e}\n")
    bx = boxes(batch)
    if bx is None:
        ap.exit(2, "error: --data: no vehicle length / width (not an exiD-layout dataset)\n")
    gt = batch["gt"]
    steps = [
        s
        for pf in data.game.spec.pair_features
        if pf.kind == "collision"
        for s in pf.steps(data.game.K)
    ]
    gt_clear = clearance(gt, bx)
    lane_h = lane_heading(batch)
    print(
        f"{a.data} split {a.split}: {len(gt)} scenes; collision checked at steps {steps}; "
        f"vehicles {bx['length'].min():.1f}-{bx['length'].max():.1f} m long, "
        f"{bx['width'].min():.2f}-{bx['width'].max():.2f} m wide"
    )
    cols = "OR n rear cutin side truck a0 t1 chk anychk circ gt_near relh lon lat".split()
    cols += ["modes_ov", "other_free", "OR_closest"]
    print("| predictor | " + " | ".join(cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    rows = {}
    for name, (pos, probs, _params) in preds.items():
        r = breakdown(pos, probs, bx, lane_h, batch["radius"], steps, gt_clear, a.lat)
        if probs.shape[1] > 1:
            r.update(mode_overlaps(pos, probs, bx, gt))
        rows[name] = r
        cells = [f"{r[c]:.3f}" if isinstance(r.get(c), float) else str(r.get(c, "-")) for c in cols]
        print(f"| {name} | " + " | ".join(cells) + " |")
    g = gt_gaps(gt, lane_h, gt_clear, a.lat)
    print("\nground truth: minimum box clearance per scene over the future (m)")
    print("| pairs | p10 | p25 | median | < 0.5 m | < 1 m | < 2 m |")
    print("|---|---|---|---|---|---|---|")
    for k, m in g.items():
        q = torch.quantile(m[m.isfinite()], torch.tensor([0.1, 0.25, 0.5]))
        share = [(m < x).float().mean().item() for x in (0.5, 1.0, 2.0)]
        print(
            f"| {k} | "
            + " | ".join(f"{v:.2f}" for v in q.tolist())
            + " | "
            + " | ".join(f"{v:.3f}" for v in share)
            + " |"
        )
    for name, (_pos, probs, params) in preds.items():
        if params is None or rows[name]["n"] == 0:
            continue
        r = rows[name]
        W = collision_weights(params, data.game, probs.argmax(1)).log10()
        ov = torch.zeros(len(gt), dtype=torch.bool)
        ov[r["idx"]] = True
        i, j = r["pairs"]
        best_clear = clearance(r["best"], bx).amin(-1)  # (B, N, N)
        upper = torch.ones(W.shape[1:], dtype=torch.bool).triu(1)
        near = (~ov[:, None, None]) & upper & (best_clear < 1.0)
        far = (~ov[:, None, None]) & upper & (best_clear >= 1.0)
        print(
            f"\n{name}: log10 collision weight of the most likely mode, median "
            f"(game default {np.log10(data.game.spec.pair_features[0].weight):.2f}): "
            f"overlapping pair {W[r['idx'], i, j].median():.2f} (n={len(i)}); "
            f"non-overlapping scenes, pairs within 1 m {W[near].median():.2f} "
            f"(n={int(near.sum())}), pairs further {W[far].median():.2f} (n={int(far.sum())})"
        )
        own = data.game.params.unpack(params.numpy())
        sel = np.arange(len(gt)), probs.argmax(1).numpy()
        med = {}
        for k, v in own.items():
            if k.startswith("w.") and "-" not in k:
                med.setdefault(k.split(".")[2], []).append(np.log10(v[sel][:, 0]))
        print(
            "  own weights, median log10: "
            + ", ".join(f"{f} {np.median(v):.2f}" for f, v in med.items())
        )
    data.close()


if __name__ == "__main__":
    main()
