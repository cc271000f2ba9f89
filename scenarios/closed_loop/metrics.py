"""The metrics of one episode (:func:`episode_metrics`), from its :class:`EpisodeLog`.

``success`` / ``collision`` (the world's outcome), ``min_distance`` (m, ego to each other
agent: centre distance minus both radii, the minimum over the episode; the smallest over
agents is ``min_distance``), ``time_to_clear`` (s: when the ego's arc length along its
path first passes the end of the conflict zone; the zone is the world's
(:meth:`~solvers.control.types.World.conflict_zone`) where it has one, else the stretch of
``r_ego + r_other`` around the ego's position at the closest approach; ``NaN`` when it
never clears), ``progress`` (m along the ego's path) and ``progress_fraction``,
``rms_jerk`` (m/s^3, of the true speed), planning latency ``plan_p50_ms`` /
``plan_p99_ms``, ``rtf`` (mean planning time / ``dt``: below 1 keeps up in real time),
``estimate_ms`` / ``track_ms`` (mean latencies), ``fallbacks`` (steps that braked
instead of tracking a plan, the safety filter's fallbacks included), the safety filter's
``intervention_rate``, ``filter_fallbacks``, ``filter_uncertified``, ``filter_p50_ms`` /
``filter_p99_ms`` (:func:`filter_metrics`; ``NaN`` / 0 without a filter), ``min_speed``
(m/s, the ego's lowest true speed: negative when it reversed) and ``reverse_distance`` (m driven backwards), and, where the world has a
conflict zone, ``order_switches`` and ``reyields_in_zone`` (:func:`order_metrics`: how
often the plans changed who goes first, and the steps inside the zone whose plan let the
other agent through first).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .log import EpisodeLog

__all__ = ["episode_metrics", "filter_metrics", "order_metrics", "passing_orders"]


def _arc(path: np.ndarray, points: np.ndarray) -> np.ndarray:
    from scenarios.maps import project_to_polyline

    return project_to_polyline(points, path)[0]


def passing_orders(log: EpisodeLog, conflict_zone: tuple[float, float] | None) -> np.ndarray | None:
    """``(T, N-1)``: whom the plan of each step lets into the conflict zone first, per other
    agent: ``1`` the ego, ``-1`` the other agent, ``0`` neither reaches the zone within the
    horizon (or the step has no finite plan and predictions); None without a zone or
    without predictions.

    Computed from the log alone, whatever the planner: the plan's mode is the predicted
    mode whose ego trajectory is closest to the plan; the ego *enters* at the first of the
    step's state and its planned states whose arc length along its path reaches ``s_in``;
    the other agent *occupies* the zone at the first of its state and predicted states that
    is closer than ``r_0 + r_j`` to the ego path's stretch ``[s_in, s_out]``. The ego is
    first when it enters before the other occupies the zone (or enters while the other never
    does), the other when it occupies the zone first or at the same step (a waiting ego
    included). Steps after the ego's centre passed ``s_out`` are ``0``."""
    if conflict_zone is None or log.predictions.shape[1] == 0:
        return None
    from scenarios.maps import project_to_polyline, resample_at

    s_in, s_out = (float(v) for v in conflict_zone)
    path = log.ego_path
    zone = resample_at(path, np.linspace(s_in, s_out, max(int((s_out - s_in) / 0.25), 2)))
    T, N = len(log.t), log.truth.shape[1]
    out = np.zeros((T, N - 1), dtype=int)
    s0 = _arc(path, log.truth[:T, 0, :2])
    for k in range(T):  # one projection per step of the episode
        preds = log.predictions[k]  # (M, N, K, 4)
        ok = np.all(np.isfinite(preds[..., :2]), axis=(1, 2, 3))
        plan = log.plan_states[k, :, :2]
        if s0[k] >= s_out or not ok.any() or not np.all(np.isfinite(plan)):
            continue  # past the zone, or nothing planned
        gap = [
            np.max(np.abs(p[0, :, :2] - plan)) if o else np.inf
            for p, o in zip(preds, ok, strict=True)
        ]
        mode = preds[int(np.argmin(gap))]
        enter = _first(np.concatenate([[s0[k]], _arc(path, mode[0, :, :2])]) >= s_in)
        for j in range(1, N):
            pts = np.concatenate([log.truth[k, j, None, :2], mode[j, :, :2]])
            occupied = _first(project_to_polyline(pts, zone)[1] < log.radii[0] + log.radii[j])
            if math.isinf(occupied):
                out[k, j - 1] = 1 if math.isfinite(enter) else 0
            else:
                out[k, j - 1] = 1 if enter < occupied else -1
    return out


def _first(mask: np.ndarray) -> float:
    idx = np.flatnonzero(mask)
    return float(idx[0]) if idx.size else math.inf


def order_metrics(log: EpisodeLog, conflict_zone: tuple[float, float] | None) -> dict:
    """``order_switches`` (how often the passing order of :func:`passing_orders` changes
    between ego-first and other-first from one step to the next, over all other agents;
    steps where neither reaches the zone are skipped) and ``reyields_in_zone`` (steps whose
    ego position lies in ``[s_in, s_out)`` while its plan lets another agent through first);
    ``NaN`` without a conflict zone or predictions."""
    orders = passing_orders(log, conflict_zone)
    if orders is None:
        return {"order_switches": math.nan, "reyields_in_zone": math.nan}
    switches = 0
    for col in orders.T:
        seq = col[col != 0]
        switches += int(np.sum(seq[1:] != seq[:-1]))
    s = _arc(log.ego_path, log.truth[: len(log.t), 0, :2])
    inside = (s >= conflict_zone[0]) & (s < conflict_zone[1])
    reyield = int(np.sum(inside & np.any(orders == -1, axis=1)))
    return {"order_switches": switches, "reyields_in_zone": reyield}


def filter_metrics(steps: Sequence[dict] | None) -> dict:
    """The safety filter's metrics from its per-step records (``intervened``, ``fallback``,
    ``certified``, ``seconds``; None: no filter ran): ``intervention_rate`` (fraction of the
    steps whose command it changed beyond its tolerance or replaced by its fallback),
    ``filter_fallbacks`` (steps on its fallback), ``filter_uncertified`` (fallback steps
    whose check failed: the best it could do), ``filter_p50_ms`` / ``filter_p99_ms``; ``NaN``
    (counts 0) without a filter."""
    if steps is None:
        nan = math.nan
        return {
            "intervention_rate": nan,
            "filter_fallbacks": 0,
            "filter_uncertified": 0,
            "filter_p50_ms": nan,
            "filter_p99_ms": nan,
        }
    n = len(steps)
    ms = np.array([1e3 * float(s.get("seconds", math.nan)) for s in steps], dtype=float)
    ms = ms[np.isfinite(ms)]
    fb = [bool(s.get("fallback")) for s in steps]
    return {
        "intervention_rate": sum(bool(s.get("intervened")) for s in steps) / n if n else math.nan,
        "filter_fallbacks": int(sum(fb)),
        "filter_uncertified": int(
            sum(f and not bool(s.get("certified")) for f, s in zip(fb, steps, strict=True))
        ),
        "filter_p50_ms": float(np.percentile(ms, 50)) if ms.size else math.nan,
        "filter_p99_ms": float(np.percentile(ms, 99)) if ms.size else math.nan,
    }


def episode_metrics(
    log: EpisodeLog,
    outcome: str,
    conflict_zone: tuple[float, float] | None = None,
    filter_steps: Sequence[dict] | None = None,
) -> dict:
    """The metrics of the module docstring from a finished episode's log; ``conflict_zone``:
    the ego's arc-length interval ``(s_in, s_out)`` of the world's conflict zone, if any;
    ``filter_steps``: the safety filter's per-step records (:func:`filter_metrics`)."""
    dt = log.dt
    T = len(log.t)
    pos = log.truth[:, :, :2]  # (T+1, N, 2)
    r = log.radii
    m: dict[str, Any] = {"steps": T, "duration": T * dt}
    m["success"] = outcome == "success"
    m["collision"] = outcome == "collision"
    N = pos.shape[1]
    if N > 1:
        gap = np.linalg.norm(pos[:, 1:] - pos[:, :1], axis=2) - r[0] - r[1:]  # (T+1, N-1)
        per_agent = gap.min(axis=0)
        m["min_distance"] = float(per_agent.min())
        m["min_distance_per_agent"] = per_agent.tolist()
        closest = int(np.argmin(gap.min(axis=1)))
        j = int(np.argmin(gap[closest]))
    else:
        m["min_distance"] = math.nan
        m["min_distance_per_agent"] = []
    s = _arc(log.ego_path, pos[:, 0])
    m["progress"] = float(s[-1] - s[0])
    total = float(np.sum(np.linalg.norm(np.diff(log.ego_path, axis=0), axis=1)))
    m["progress_fraction"] = float(m["progress"] / total) if total > 0 else math.nan
    if conflict_zone is not None:
        s_out = conflict_zone[1]
    elif N > 1:
        s_out = s[closest] + r[0] + r[1 + j]
    else:
        s_out = math.nan
    cleared = np.flatnonzero(s >= s_out) if math.isfinite(s_out) else np.zeros(0, int)
    m["time_to_clear"] = float(cleared[0] * dt) if cleared.size else math.nan
    v = log.truth[:, 0, 2]
    jerk = np.diff(v, n=2) / dt**2
    m["rms_jerk"] = float(np.sqrt(np.mean(jerk**2))) if jerk.size else math.nan
    plan_ms = log.latency[:, 1] * 1e3
    m["plan_p50_ms"] = float(np.percentile(plan_ms, 50)) if T else math.nan
    m["plan_p99_ms"] = float(np.percentile(plan_ms, 99)) if T else math.nan
    m["rtf"] = float(np.mean(plan_ms) / (dt * 1e3)) if T else math.nan
    m["estimate_ms"] = float(np.mean(log.latency[:, 0]) * 1e3) if T else math.nan
    m["track_ms"] = float(np.mean(log.latency[:, 2]) * 1e3) if T else math.nan
    m["fallbacks"] = int(np.sum(log.fallback))
    m.update(filter_metrics(filter_steps))
    m["min_speed"] = float(v.min())
    m["reverse_distance"] = float(np.sum(np.maximum(-v[:-1], 0.0)) * dt)
    m.update(order_metrics(log, conflict_zone))
    return m
