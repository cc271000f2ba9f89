"""Geometry of the safety filter of :mod:`solvers.control.safety`: the footprint circles of a
car (:func:`covering_circles`, :func:`world_footprints`), the bodies the collision constraints
use (:func:`body_shapes`), the constant-velocity prediction of an unconverged track (``_cv``),
the sampling of a plan on the filter's grid (``_sample``), the unicycle rollout with the
tracker's steering as a CasADi function (``_rollout_function``) and the lane path the filter
measures along (``_Path``)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError, check_number

from .safety_options import SHAPES
from .types import world_member
from .vehicle import VehicleModel


# ====================================================================== footprints
def covering_circles(length: float, width: float) -> tuple[float, float]:
    """``(offset, radius)`` of the two equal circles at ``+-offset`` along the heading that
    cover a ``length x width`` rectangle: ``length / 4`` and
    ``sqrt((length / 4)^2 + (width / 2)^2)`` (the smallest such pair)."""
    check_number("footprint.length", length, lo=0.0, lo_open=True)
    check_number("footprint.width", width, lo=0.0, lo_open=True)
    return float(length) / 4.0, math.hypot(float(length) / 4.0, float(width) / 2.0)


def world_footprints(world) -> np.ndarray:
    """``(N, 2)`` ``(offset, radius)`` of every agent's two circles (module docstring): from
    the world's ``footprint`` (``(length, width)`` of every agent, :func:`world_member`)
    where it has one, else from ``world.radii`` (one circle per agent, offset 0)."""
    n = int(world.n_agents)
    try:
        size = world_member(world, "footprint")
    except KeyError:  # a World protocol without the member
        size = getattr(world, "footprint", None)
    if size is not None:
        try:
            length, width = (float(v) for v in size)
        except (TypeError, ValueError):
            raise SpecError(
                "world.footprint", f"expected (length, width) in m, got {size!r}"
            ) from None
        return np.tile(covering_circles(length, width), (n, 1))
    radii = np.asarray(world.radii, dtype=float).reshape(-1)
    if radii.shape != (n,) or not np.all(np.isfinite(radii)) or np.any(radii <= 0):
        raise SpecError("world.radii", f"expected {n} positive radii, got {radii!r}")
    return np.stack([np.zeros(n), radii], axis=1)


def body_shapes(world, shape: str = "box") -> tuple[np.ndarray, float, np.ndarray]:
    """The bodies of the collision constraints: the ego's points ``(P, 2)`` (in its frame,
    x along its heading) with their radius ``r_0``, and every other agent's rounded
    rectangle ``(N-1, 3)`` ``(a, b, r)``: the points within ``r`` of the rectangle of
    half-length ``a`` (along its heading) and half-width ``b``. With the world's
    ``footprint`` ``(L, W)``: ``shape="box"``: the ego's four corners (``r_0 = 0``) and the
    others' rectangles ``(L/2, W/2, 0)``; ``"circles"``: the ego's two circles
    (:func:`covering_circles`) and the convex hull of each other's two circles (a stadium,
    ``(L/4, 0, sqrt((L/4)^2 + (W/2)^2))``, which holds both). Without a footprint every
    agent is the circle of its radius: the ego's centre with ``r_0``, ``(0, 0, r)``."""
    if shape not in SHAPES:
        raise SpecError("filter.shape", f"expected one of {SHAPES}, got {shape!r}")
    fp = world_footprints(world)
    try:
        size = world_member(world, "footprint")
    except KeyError:  # a World protocol without the member
        size = getattr(world, "footprint", None)
    n = len(fp)
    if size is not None and shape == "box":
        length, width = (float(v) for v in size)
        ego = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [length / 2, width / 2]
        return ego.astype(float), 0.0, np.tile([length / 2, width / 2, 0.0], (n - 1, 1))
    ego = np.array([[fp[0, 0], 0.0], [-fp[0, 0], 0.0]]) if fp[0, 0] > 0 else np.zeros((1, 2))
    others = np.stack([fp[1:, 0], np.zeros(n - 1), fp[1:, 1]], axis=1)
    return ego, float(fp[0, 1]), others


# ====================================================================== geometry
def _heading(theta: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(theta), np.sin(theta)], axis=-1)


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _cv(states: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """States ``(..., 4)`` carried ``tau`` (broadcast, s) ahead at constant velocity."""
    out = np.array(np.broadcast_to(states, np.broadcast_shapes(states.shape, tau.shape + (4,))))
    h = _heading(out[..., 3])
    out[..., :2] = out[..., :2] + (out[..., 2] * tau)[..., None] * h
    return out


def _sample(pred: np.ndarray, t0: float, pdt: float, times: np.ndarray) -> np.ndarray:
    """Predicted states ``(..., K, 4)`` at ``t0 + pdt (i + 1)`` sampled at ``times`` ``(H,)``
    (linear, heading unwrapped; constant velocity before the first and after the last)."""
    P = np.array(pred, dtype=float)
    K = P.shape[-2]
    P[..., 3] = np.unwrap(P[..., 3], axis=-1)
    s = (times - t0) / pdt - 1.0  # fractional index into the K states
    out = np.empty(P.shape[:-2] + (len(times), 4))
    if K == 1:
        return _cv(P[..., 0:1, :], times - (t0 + pdt))
    i0 = np.clip(np.floor(s).astype(int), 0, K - 2)
    f = np.clip(s - i0, 0.0, 1.0)[:, None]
    out[:] = P[..., i0, :] * (1 - f) + P[..., i0 + 1, :] * f
    before, after = s < 0, s > K - 1
    if before.any():
        out[..., before, :] = _cv(P[..., 0:1, :], times[before] - (t0 + pdt))
    if after.any():
        out[..., after, :] = _cv(P[..., K - 1 : K, :], times[after] - (t0 + pdt * K))
    return out


#: the operations of VehicleModel._integrate on Python floats (one state, fast)
_MATH = SimpleNamespace(
    where=lambda c, a, b: a if c else b, fmin=min, fmax=max, cos=math.cos, sin=math.sin,
    tan=math.tan, atan=math.atan,
)  # fmt: skip


def _steer_scalar(veh: VehicleModel, v: float, omega: float) -> float:
    """The steering command of ``veh`` with turn rate ``omega`` at speed ``v``:
    :meth:`VehicleModel.from_unicycle`'s second component for one state (unclipped)."""
    if veh.kind == "unicycle":
        return float(omega)
    if not abs(v) > 0.1:
        return 0.0
    sb = min(max(omega * (veh.length / 2) / v, -0.999), 0.999)
    return math.atan(2.0 * math.tan(math.asin(sb)))


def _rollout_function(veh: VehicleModel, dt: float, N: int, floor: bool) -> ca.Function:
    """``(x0[4], U[2 x N]) -> (X[4 x N], U'[2 x N])``: ``N`` steps of the vehicle model
    (CasADi ``mapaccum``); with ``floor`` an acceleration that would take the speed below
    zero is raised to the one that stops it (at most ``a_max``)."""
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    a = u[0]
    if floor:
        a = ca.if_else(x[2] + a * dt < 0, ca.fmin(-x[2] / dt, veh.a_max), a)
    uf = ca.vertcat(a, u[1])
    step = ca.Function("step", [x, u], [veh.casadi_step(x, uf, dt), uf])
    return step.mapaccum("rollout", N)


class _Path:
    """The ego's lane centre line for the fallback's lane keeping."""

    def __init__(self, path: np.ndarray):
        p = np.asarray(path, dtype=float).reshape(-1, 2)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9])
        p = p[keep]
        if len(p) < 2:  # a point: a short straight stub along +x
            p = np.stack([p[0], p[0] + [1.0, 0.0]])
        self.a, self.d = p[:-1], np.diff(p, axis=0)
        self.L = np.linalg.norm(self.d, axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(self.L)])

    def segment(self, p: np.ndarray) -> int:
        """The segment of the path closest to the point ``p`` ``(2,)``."""
        w = p[None] - self.a
        t = np.clip(np.einsum("si,si->s", w, self.d) / self.L**2, 0.0, 1.0)
        return int(np.argmin(np.linalg.norm(w - t[:, None] * self.d, axis=1)))

    def advance(self, seg: int, x: float, y: float) -> tuple[int, float]:
        """From segment ``seg`` on, the segment whose projection of ``(x, y)`` does not lie
        beyond its end, and the arc length of that projection (a vehicle moves on along its
        path, so the search only goes forward)."""
        last = len(self.L) - 1
        while True:
            ax, ay = self.a[seg]
            dx, dy = self.d[seg]
            t = ((x - ax) * dx + (y - ay) * dy) / (self.L[seg] ** 2)
            if t <= 1.0 or seg == last:
                break
            seg += 1
        return seg, float(self.cum[seg] + min(max(t, 0.0), 1.0) * self.L[seg])

    def point_from(self, seg: int, s: float) -> tuple[float, float]:
        """The point at arc length ``s`` (beyond the end: along the last segment)."""
        last = len(self.L) - 1
        while seg < last and self.cum[seg + 1] < s:
            seg += 1
        f = (s - self.cum[seg]) / self.L[seg]
        return (
            float(self.a[seg, 0] + f * self.d[seg, 0]),
            float(self.a[seg, 1] + f * self.d[seg, 1]),
        )
