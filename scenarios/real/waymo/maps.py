"""Map inputs of a Waymo scene: lane centres cut into equal pieces, the distance of a point to
them, the pool of goal points along lanes and crosswalks and the goal candidates of one agent
(the rules are in :mod:`scenarios.real.waymo`, "Lanes" and "Goal candidates")."""

from __future__ import annotations

import math

import numpy as np

from ...maps import arc_length, resample_at
from .records import ScenarioRecord


def _dedupe(xy: np.ndarray) -> np.ndarray:
    if len(xy) < 2:
        return xy
    keep = np.r_[True, np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6]
    return xy[keep]


def lane_pieces(rec: ScenarioRecord, piece: float, points: int):
    """Every lane centre cut into equal pieces of at most ``piece`` m, each ``points``
    points: ``(pts (K, P, 2), lane index into rec.lines("lane") (K,))``."""
    pts, which = [], []
    for k, ln in enumerate(rec.lines("lane")):
        xy = _dedupe(ln.points[:, :2])
        if len(xy) < 2:
            continue
        total = float(arc_length(xy)[-1])
        n = max(1, math.ceil(total / piece - 1e-9))
        edges = np.linspace(0.0, total, n + 1)
        s = np.linspace(edges[:-1], edges[1:], points, axis=1)  # (n, P)
        pts.append(resample_at(xy, s.ravel()).reshape(n, points, 2))
        which += [k] * n
    if not pts:
        return np.zeros((0, points, 2)), np.zeros(0, np.int64)
    return np.concatenate(pts), np.array(which, np.int64)


def _distance_to_pieces(p: np.ndarray, pieces: np.ndarray) -> np.ndarray:
    """Distance ``(K,)`` of the point ``p`` ``(2,)`` to each piece ``(K, P, 2)``."""
    a, b = pieces[:, :-1], pieces[:, 1:]
    ab = b - a
    L2 = np.maximum((ab**2).sum(-1), 1e-18)
    t = np.clip(((p - a) * ab).sum(-1) / L2, 0.0, 1.0)
    d = np.linalg.norm(a + t[..., None] * ab - p, axis=-1)
    return d.min(axis=1)


def goal_pool(rec: ScenarioRecord, spacing: float) -> np.ndarray:
    """Points ``(Q, 2)`` every ``spacing`` m along the lane centres and crosswalk outlines."""
    out = []
    for ln in rec.map:
        if ln.kind not in ("lane", "crosswalk"):
            continue
        xy = ln.points[:, :2]
        if ln.kind == "crosswalk" and len(xy) >= 2:
            xy = np.concatenate([xy, xy[:1]])
        xy = _dedupe(xy)
        if len(xy) < 2:
            out.append(xy)
            continue
        total = float(arc_length(xy)[-1])
        out.append(resample_at(xy, np.arange(0.0, total + 1e-9, spacing)))
    return np.concatenate(out) if out else np.zeros((0, 2))


def _spiral(n: int, radius: float) -> np.ndarray:
    """``n`` points of a Vogel (golden-angle) spiral filling a disc of ``radius``."""
    k = np.arange(n) + 0.5
    r = radius * np.sqrt(k / max(n, 1))
    a = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def goal_candidates(
    pool: np.ndarray, p: np.ndarray, v: float, theta: float, reach: float, G: int, R: float
) -> tuple[np.ndarray, np.ndarray]:
    """``G`` candidates ``(G, 2)`` and their on-map flags for an agent at ``p`` (the module
    docstring; ``reach`` = v T dt, ``R`` the candidate range)."""
    near = pool[np.linalg.norm(pool - p, axis=1) <= R] if len(pool) else pool
    if len(near) >= G:
        end = p + reach * np.array([math.cos(theta), math.sin(theta)])
        j = int(np.argmin(np.linalg.norm(near - end, axis=1)))
        idx = [j]
        d = np.linalg.norm(near - near[j], axis=1)
        for _ in range(G - 1):
            j = int(np.argmax(d))
            idx.append(j)
            d = np.minimum(d, np.linalg.norm(near - near[j], axis=1))
        return near[idx], np.ones(G, bool)
    fill = p + _spiral(G - len(near), R)
    on = np.r_[np.ones(len(near), bool), np.zeros(G - len(near), bool)]
    return np.concatenate([near, fill]), on
