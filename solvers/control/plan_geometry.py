"""Geometry shared by the planners of :mod:`solvers.control.plan` and their checks.

Plain numpy on positions and polylines: the unicycle rollout that never reverses
(:func:`stop_not_reverse`), the two circles inscribed in a car's footprint (:func:`inscribed_circles`),
the speed drop that says an agent brakes to yield (``_speed_change``), projection onto and
resampling of a polyline, the passing order of a joint future (:func:`passing_order`), the
lane window of an agent (:func:`path_window`) and the straight path of a constant-velocity
prediction (``_straight``).
"""

from __future__ import annotations

import math

import numpy as np

from epo_casadi.errors import SpecError, check_number, short_repr


def stop_not_reverse(x0: np.ndarray, U: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The unicycle rollout of controls ``U`` ``(K, 2)`` from ``x0`` ``(4,)`` (explicit
    Euler, as :class:`epo_casadi.dynamics.Unicycle`) in which no speed goes below zero:
    where ``v_k + a_k dt < 0`` the acceleration becomes ``-v_k / dt`` and ``v_{k+1} = 0``
    exactly (a negative ``v_0`` is brought to zero in the first step). Returns the states
    ``(K, 4)`` after each step and the controls that produce them."""
    U = np.array(U, dtype=np.float64, copy=True)
    X = np.empty((len(U), 4))
    x, y, v, th = (float(c) for c in x0)
    for k in range(len(U)):  # sequential by nature: each clamp depends on the speed so far
        a, w = U[k]
        v_next = v + a * dt
        if v_next < 0.0:
            U[k, 0], v_next = -v / dt, 0.0
        x, y, th = x + v * math.cos(th) * dt, y + v * math.sin(th) * dt, th + w * dt
        v = v_next
        X[k] = x, y, v, th
    return X, U


def inscribed_circles(footprint) -> tuple[float, float]:
    """``(offset, radius)`` of the planners' two circles of a ``(length, width)`` car:
    centres ``+-(length - width) / 2`` along the heading, radius ``width / 2`` (the stadium
    inscribed in its rectangle, :mod:`solvers.control.plan`)."""
    try:
        length, width = (float(v) for v in footprint)
    except (TypeError, ValueError):
        raise SpecError(
            "world.footprint", f"expected (length, width) in m, got {short_repr(footprint)}"
        ) from None
    check_number("world.footprint.width", width, lo=0, lo_open=True)
    check_number("world.footprint.length", length, lo=width)
    return 0.5 * (length - width), 0.5 * width


#: s of estimated history over which a speed drop says an agent is braking, and that drop
#: (m/s): 1 m/s^2 sustained for half a second
_SLOWING_WINDOW, _SLOWING_DROP = 0.5, 0.5


def _speed_change(est, n: int, dt: float) -> np.ndarray:
    """``(n,)`` each agent's estimated speed now minus ``_SLOWING_WINDOW`` s ago from
    ``est.history`` (0 where either row is not backed by a measurement, or without such a
    history)."""
    out = np.zeros(n)
    lag = int(round(_SLOWING_WINDOW / dt))
    try:
        h = np.asarray(getattr(est, "history", None), dtype=float)
        valid = np.asarray(getattr(est, "valid", None), dtype=bool)
    except (TypeError, ValueError):
        return out
    if h.ndim != 3 or h.shape[:1] != (n,) or h.shape[1] <= lag or valid.shape != h.shape[:2]:
        return out
    with np.errstate(invalid="ignore"):
        change = h[:, -1, 2] - h[:, -1 - lag, 2]
    ok = valid[:, -1] & valid[:, -1 - lag] & np.isfinite(change)
    return np.where(ok, change, 0.0)


def _project(points: np.ndarray, line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length along ``line`` ``(P, 2)`` of the closest point and the distance, per point
    of ``points`` ``(Q, 2)``."""
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    a, ab = line[:-1], np.diff(line, axis=0)
    L2 = np.maximum(np.einsum("sj,sj->s", ab, ab), 1e-18)
    t = np.clip(np.einsum("qsj,sj->qs", pts[:, None] - a[None], ab) / L2, 0.0, 1.0)
    d = np.linalg.norm(pts[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)
    k = np.argmin(d, axis=1)
    rows = np.arange(len(pts))
    cum = np.concatenate([[0.0], np.cumsum(np.sqrt(L2))])
    return cum[k] + t[rows, k] * np.sqrt(L2[k]), d[rows, k]


def _resample(line: np.ndarray, s: np.ndarray) -> np.ndarray:
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    return np.stack([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])], axis=-1)


def passing_order(
    ego: np.ndarray, other: np.ndarray, path: np.ndarray, zone: tuple[float, float], reach: float
) -> str:
    """Who enters the ego's stretch ``[s_in, s_out]`` of ``path`` first in a joint future:
    ``ego`` / ``other`` ``(K+1, >=2)`` positions (the current state first). The ego *enters*
    at its first position whose arc length along ``path`` is at least ``s_in``; the other
    agent *occupies* the zone at its first position closer than ``reach`` to the stretch.
    ``"ego"`` when the ego enters before the other occupies it (or enters while the other
    never does), ``"other"`` when the other is there first or at the same step (an ego that
    waits beyond the horizon included), ``"none"`` when neither reaches it."""
    s_in, s_out = zone
    s_e = _project(ego[:, :2], path)[0]
    enter = np.flatnonzero(s_e >= s_in)
    stretch = _resample(path, np.linspace(s_in, s_out, max(int((s_out - s_in) / 0.25), 2)))
    occ = np.flatnonzero(_project(other[:, :2], stretch)[1] < reach)
    if occ.size == 0:
        return "ego" if enter.size else "none"
    return "ego" if enter.size and enter[0] < occ[0] else "other"


# --------------------------------------------------------------------------------------
# the game


def path_window(
    path: np.ndarray, point: np.ndarray, behind: float, ahead: float, n: int
) -> np.ndarray:
    """``n`` points equally spaced along ``path`` from ``behind`` metres before the
    projection of ``point`` to ``ahead`` metres after it, ``(n, 2)``.

    Beyond its ends the polyline is extended along its first and last segments, so a
    window near the end of a lane stays straight instead of folding back.
    """
    pts = np.asarray(path, dtype=float).reshape(-1, 2)
    seg = np.diff(pts, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    keep = length > 1e-9
    if not keep.any():
        raise SpecError("task.path", "expected a polyline with two distinct points")
    pts = np.concatenate([pts[:1], pts[1:][keep]])
    seg, length = seg[keep], length[keep]
    cum = np.concatenate([[0.0], np.cumsum(length)])
    q = np.asarray(point, dtype=float)[:2]
    t = np.clip(np.einsum("sc,sc->s", q - pts[:-1], seg) / length**2, 0.0, 1.0)
    d = np.hypot(*(pts[:-1] + t[:, None] * seg - q).T)
    j = int(np.argmin(d))
    s0 = cum[j] + t[j] * length[j]
    s = np.linspace(s0 - behind, s0 + ahead, n)
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    tt = (s - cum[idx]) / length[idx]
    return pts[idx] + tt[:, None] * seg[idx]


def _straight(state: np.ndarray, behind: float, ahead: float, n: int) -> np.ndarray:
    """A straight path through the position along the heading (constant velocity)."""
    s = np.linspace(-behind, ahead, n)
    c, si = math.cos(state[3]), math.sin(state[3])
    return state[:2] + s[:, None] * np.array([c, si])
