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
``estimate_ms`` / ``track_ms`` (mean latencies) and ``fallbacks`` (steps that braked
instead of tracking a plan).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .log import EpisodeLog

__all__ = ["episode_metrics"]


def _arc(path: np.ndarray, points: np.ndarray) -> np.ndarray:
    from scenarios.maps import project_to_polyline

    return project_to_polyline(points, path)[0]


def episode_metrics(
    log: EpisodeLog, outcome: str, conflict_zone: tuple[float, float] | None = None
) -> dict:
    """The metrics of the module docstring from a finished episode's log; ``conflict_zone``:
    the ego's arc-length interval ``(s_in, s_out)`` of the world's conflict zone, if any."""
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
    return m
