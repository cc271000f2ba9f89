"""One lane / map representation shared by every driving scenario (and the simulated worlds).

A :class:`Lane` is a centre polyline ``(P, 2)`` in metres (world frame), a width, a speed
limit (m/s) and the ids of the lanes that continue it. A :class:`RoadMap` is a set of lanes
with lookup by id, fixed-count resampling (what a network or a game reads), routes (a
sequence of lanes joined end to end), conversion to :class:`solvers.control.types.AgentTask`
and the conflict zone of two lanes (where their centre lines come closer than a clearance).

Maps are written by hand (:class:`Lane` from points) or built from a highway-env road
network (:meth:`RoadMap.from_highway`, which samples ``lane.position(s, 0)``); nothing here
imports highway-env. Every input error is a :class:`~epo_casadi.errors.SpecError` naming
the field.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from epo_casadi.errors import SpecError, check_number
from solvers.control.types import AgentTask

__all__ = [
    "Lane",
    "RoadMap",
    "ConflictZone",
    "arc_length",
    "resample_polyline",
    "project_to_polyline",
]


def arc_length(points: np.ndarray) -> np.ndarray:
    """Cumulative arc length ``(P,)`` of a polyline ``(P, 2)`` (0 at the first point)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def resample_polyline(points: np.ndarray, n: int) -> np.ndarray:
    """``n`` points equally spaced in arc length along ``points`` (first and last kept)."""
    s = arc_length(points)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, points[:, 0]), np.interp(t, s, points[:, 1])], axis=1)


def project_to_polyline(points: np.ndarray, line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length of the closest point on ``line`` and the distance to it, per point.

    ``points``: ``(Q, 2)``; ``line``: ``(P, 2)``. Returns ``(s, d)``, each ``(Q,)``.
    Vectorized over points and segments.
    """
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    a, b = line[:-1], line[1:]  # (S, 2)
    ab = b - a
    L2 = np.maximum(np.einsum("sj,sj->s", ab, ab), 1e-18)
    rel = pts[:, None, :] - a[None]  # (Q, S, 2)
    t = np.clip(np.einsum("qsj,sj->qs", rel, ab) / L2, 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    d = np.linalg.norm(pts[:, None, :] - closest, axis=2)  # (Q, S)
    k = np.argmin(d, axis=1)
    rows = np.arange(len(pts))
    s0 = arc_length(line)
    s = s0[k] + t[rows, k] * np.sqrt(L2[k])
    return s, d[rows, k]


@dataclass(frozen=True, eq=False)
class Lane:
    """A lane: ``id``, ``centre`` polyline ``(P, 2)`` (P >= 2, no repeated points), ``width``
    (m), ``speed_limit`` (m/s) and the ids of its ``successors``. Compared by identity
    (it holds an array)."""

    id: str
    centre: np.ndarray
    width: float = 3.5
    speed_limit: float = 13.9
    successors: tuple[str, ...] = ()

    def __post_init__(self):
        if not isinstance(self.id, str) or not self.id:
            raise SpecError("lane.id", f"expected a non-empty string, got {self.id!r}")
        f = f"lanes[{self.id}]"
        try:
            c = np.array(self.centre, dtype=float)
        except (TypeError, ValueError):
            raise SpecError(f"{f}.centre", "expected a (P, 2) array of numbers") from None
        if c.ndim != 2 or c.shape[1] != 2 or c.shape[0] < 2:
            raise SpecError(f"{f}.centre", f"expected shape (P, 2) with P >= 2, got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise SpecError(f"{f}.centre", "expected finite coordinates")
        if np.any(np.linalg.norm(np.diff(c, axis=0), axis=1) < 1e-9):
            raise SpecError(f"{f}.centre", "two successive points coincide")
        c.setflags(write=False)
        object.__setattr__(self, "centre", c)
        check_number(f"{f}.width", self.width, lo=0.0, lo_open=True)
        check_number(f"{f}.speed_limit", self.speed_limit, lo=0.0, lo_open=True)
        if isinstance(self.successors, str):
            raise SpecError(f"{f}.successors", "expected a sequence of lane ids, got a string")
        succ = tuple(self.successors)
        if not all(isinstance(s, str) for s in succ):
            raise SpecError(f"{f}.successors", f"expected lane ids (strings), got {succ!r}")
        object.__setattr__(self, "successors", succ)

    @property
    def length(self) -> float:
        """Length of the centre line (m)."""
        return float(arc_length(self.centre)[-1])

    def resample(self, n: int) -> np.ndarray:
        """``(n, 2)`` centre points equally spaced in arc length (n >= 2)."""
        check_number("n", n, lo=2, integer=True)
        return resample_polyline(self.centre, n)

    def point(self, s: float | np.ndarray) -> np.ndarray:
        """Centre point(s) at arc length ``s`` (clamped to the lane), ``(2,)`` or ``(Q, 2)``."""
        sa = arc_length(self.centre)
        s = np.asarray(s, dtype=float)
        return np.stack(
            [np.interp(s, sa, self.centre[:, 0]), np.interp(s, sa, self.centre[:, 1])], axis=-1
        )

    def heading(self, s: float | np.ndarray) -> np.ndarray:
        """Heading (rad) of the segment at arc length ``s``."""
        sa = arc_length(self.centre)
        d = np.diff(self.centre, axis=0)
        k = np.clip(np.searchsorted(sa, s, side="right") - 1, 0, len(d) - 1)
        return np.arctan2(d[k, 1], d[k, 0])

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(s, distance)`` of each point ``(Q, 2)`` to the centre line."""
        return project_to_polyline(points, self.centre)


@dataclass(frozen=True, eq=False)
class ConflictZone:
    """Where two lanes' centre lines are closer than ``clearance``: the arc-length interval
    ``a`` = ``(s_in, s_out)`` on the first lane and ``b`` on the second, and ``point``, the
    place of their closest approach."""

    a: tuple[float, float]
    b: tuple[float, float]
    point: np.ndarray
    clearance: float


@dataclass(frozen=True, eq=False)
class RoadMap:
    """A set of lanes with unique ids; successors must name lanes of the map."""

    lanes: tuple[Lane, ...]

    def __post_init__(self):
        lanes = tuple(self.lanes)
        if not lanes:
            raise SpecError("road_map.lanes", "expected at least one lane")
        for i, ln in enumerate(lanes):
            if not isinstance(ln, Lane):
                raise SpecError(f"road_map.lanes[{i}]", f"expected a Lane, got {type(ln).__name__}")
        ids = [ln.id for ln in lanes]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise SpecError("road_map.lanes", f"duplicate lane ids {dup}")
        known = set(ids)
        for ln in lanes:
            bad = [s for s in ln.successors if s not in known]
            if bad:
                raise SpecError(f"lanes[{ln.id}].successors", f"unknown lane ids {bad}")
        object.__setattr__(self, "lanes", lanes)
        object.__setattr__(self, "_index", {ln.id: ln for ln in lanes})

    # --- lookup -----------------------------------------------------------------------------
    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(ln.id for ln in self.lanes)

    def lane(self, lane_id: str) -> Lane:
        """The lane with this id (SpecError naming the valid ids otherwise)."""
        try:
            return self._index[lane_id]
        except (KeyError, TypeError):
            raise SpecError(
                "lane", f"unknown lane id {lane_id!r}; valid: {', '.join(self.ids)}"
            ) from None

    def __contains__(self, lane_id: str) -> bool:
        return lane_id in self._index

    def resample(self, lane_id: str, n: int) -> np.ndarray:
        """``(n, 2)`` points of one lane, equally spaced in arc length."""
        return self.lane(lane_id).resample(n)

    # --- routes -----------------------------------------------------------------------------
    def route(self, lane_ids: Sequence[str], tol: float = 0.05) -> np.ndarray:
        """Centre polyline of lanes joined end to end. Each lane must be a successor of the
        previous one and start within ``tol`` metres of its end."""
        if isinstance(lane_ids, str) or len(lane_ids) == 0:
            raise SpecError("route", f"expected a non-empty sequence of lane ids, got {lane_ids!r}")
        lanes = [self.lane(i) for i in lane_ids]
        parts = [lanes[0].centre]
        for prev, nxt in zip(lanes[:-1], lanes[1:], strict=True):
            if nxt.id not in prev.successors:
                raise SpecError("route", f"lane {nxt.id!r} is not a successor of {prev.id!r}")
            gap = float(np.linalg.norm(nxt.centre[0] - prev.centre[-1]))
            if gap > tol:
                raise SpecError(
                    "route", f"lane {nxt.id!r} starts {gap:.3g} m from the end of {prev.id!r}"
                )
            parts.append(nxt.centre[1:])
        return np.concatenate(parts, axis=0)

    def task(
        self,
        lane_ids: Sequence[str],
        *,
        n_points: int = 50,
        radius: float,
        speed: float | None = None,
        goal: np.ndarray | None = None,
    ) -> AgentTask:
        """:class:`AgentTask` along a route: its centre resampled to ``n_points``, the
        smallest speed limit of its lanes (unless ``speed``) and its end point (unless
        ``goal``)."""
        check_number("n_points", n_points, lo=2, integer=True)
        check_number("radius", radius, lo=0.0)
        path = resample_polyline(self.route(lane_ids), n_points)
        v = min(self.lane(i).speed_limit for i in lane_ids) if speed is None else speed
        check_number("speed", v, lo=0.0)
        g = path[-1].copy() if goal is None else np.asarray(goal, dtype=float).reshape(2)
        return AgentTask(path=path, speed=float(v), goal=g, radius=float(radius))

    # --- geometry ---------------------------------------------------------------------------
    def distance_to_road(self, points: np.ndarray) -> np.ndarray:
        """Per point ``(Q, 2)``: distance to the nearest lane's centre minus its half width
        (``<= 0`` on some lane)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        out = np.full(len(pts), np.inf)
        for ln in self.lanes:
            _, d = ln.project(pts)
            out = np.minimum(out, d - 0.5 * ln.width)
        return out

    def conflict_zone(
        self, a: str | np.ndarray, b: str | np.ndarray, clearance: float, step: float = 0.25
    ) -> ConflictZone | None:
        """Conflict zone of two lanes (ids) or polylines: the arc-length intervals where each
        centre line is within ``clearance`` (m) of the other, sampled every ``step`` m (the
        first connected stretch on each). ``None`` if they never come that close."""
        check_number("clearance", clearance, lo=0.0, lo_open=True)
        check_number("step", step, lo=0.0, lo_open=True)
        pa = self.lane(a).centre if isinstance(a, str) else np.asarray(a, dtype=float)
        pb = self.lane(b).centre if isinstance(b, str) else np.asarray(b, dtype=float)
        ia = _stretch(pa, pb, clearance, step)
        ib = _stretch(pb, pa, clearance, step)
        if ia is None or ib is None:
            return None
        sa = np.arange(ia[0], ia[1] + step / 2, step)
        qa = resample_at(pa, sa)
        _, d = project_to_polyline(qa, pb)
        point = qa[int(np.argmin(d))]
        return ConflictZone(a=ia, b=ib, point=point, clearance=float(clearance))

    # --- construction -----------------------------------------------------------------------
    @classmethod
    def from_highway(cls, network, step: float = 1.0, names: dict | None = None) -> RoadMap:
        """Map of a highway-env ``RoadNetwork``: every lane ``(from, to, i)`` sampled at
        ``lane.position(s, 0)`` every ``step`` m (and at its end), width and speed limit
        from the lane, successors = the lanes leaving node ``to``. Ids are ``"from>to:i"``
        unless ``names`` maps a lane index tuple to an id."""
        check_number("step", step, lo=0.0, lo_open=True)
        names = dict(names or {})

        def lid(idx):
            return names.get(idx, f"{idx[0]}>{idx[1]}:{idx[2]}")

        lanes = []
        for _from, tos in network.graph.items():
            for _to, group in tos.items():
                succ = tuple(
                    lid((_to, nxt, j))
                    for nxt, g2 in network.graph.get(_to, {}).items()
                    for j in range(len(g2))
                )
                for i, hl in enumerate(group):
                    length = float(hl.length)
                    n = max(2, int(math.ceil(length / step)) + 1)
                    s = np.linspace(0.0, length, n)
                    pts = np.array([hl.position(float(x), 0.0) for x in s], dtype=float)
                    limit = hl.speed_limit if hl.speed_limit is not None else 20.0
                    lanes.append(
                        Lane(
                            id=lid((_from, _to, i)),
                            centre=pts,
                            width=float(hl.width_at(0.0)),
                            speed_limit=float(limit),
                            successors=succ,
                        )
                    )
        return cls(tuple(lanes))


def resample_at(points: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points of a polyline at arc lengths ``s`` (clamped)."""
    sa = arc_length(points)
    return np.stack([np.interp(s, sa, points[:, 0]), np.interp(s, sa, points[:, 1])], axis=-1)


def _stretch(pa, pb, clearance, step):
    sa = arc_length(pa)
    s = np.arange(0.0, sa[-1] + step / 2, step)
    _, d = project_to_polyline(resample_at(pa, s), pb)
    inside = d < clearance
    if not inside.any():
        return None
    k0 = int(np.argmax(inside))
    out = np.flatnonzero(~inside[k0:])
    k1 = k0 + int(out[0]) - 1 if out.size else len(inside) - 1
    return (float(s[k0]), float(min(s[k1], sa[-1])))
