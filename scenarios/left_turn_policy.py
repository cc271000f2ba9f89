"""The hand-made SDV of the left-turn demonstrations and the runs it drives.

:class:`SDVPolicy` is the SDV's driver of :mod:`scenarios.left_turn` (intent, re-evaluation
every step, commitment, pure-pursuit steering and speed-limit following) on a
:class:`~scenarios.sim.left_turn.LeftTurnWorld`; :func:`simulate` steps a world with it and
records a :class:`Run` (states and the step at which each vehicle's front entered the
conflict zone), with deep copies of the world and policy for replays. Beside them the plain
numpy geometry they use: a polyline at given arc lengths (``_at``), an agent's progress along
one (``_progress``), positions in an agent's frame (:func:`to_frame`) and rotations
(``_rotate``).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

LENGTH = 5.0  # vehicle length (m), highway-env's Vehicle.LENGTH


# --------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------
def _at(route: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(n, 2)`` and headings ``(n,)`` of a polyline at arc lengths ``s``, linearly
    extended beyond both ends along the first / last segment."""
    seg = np.diff(route, axis=0)
    L = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(L)])
    s = np.atleast_1d(np.asarray(s, dtype=float))
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    t = (s - cum[k]) / L[k]
    pts = route[k] + t[:, None] * seg[k]
    return pts, np.arctan2(seg[k, 1], seg[k, 0])


def to_frame(xy: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Positions ``(..., 2)`` in the frame of ``pose = (x, y, theta)``:
    ``R(-theta) (p - (x, y))``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = np.asarray(xy, dtype=float) - np.asarray(pose[:2], dtype=float)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def _rotate(xy: np.ndarray, phi: float) -> np.ndarray:
    c, s = math.cos(phi), math.sin(phi)
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], axis=-1)


# --------------------------------------------------------------------------------------
# the SDV's hand-made policy
# --------------------------------------------------------------------------------------
class SDVPolicy:
    """The SDV's hand-made driver (:mod:`scenarios.left_turn`): intent, re-evaluation, commitment,
    pure-pursuit steering and speed-limit following. ``force``: ``None`` (natural),
    ``"sdv_first"`` or ``"other_first"`` (a replay towards that outcome)."""

    def __init__(self, world, recipe: LeftTurnRecipe, intent: str):  # noqa: F821 (scenarios.left_turn)
        rm = world.road_map
        self.recipe = recipe
        self.intent = intent
        self.force: str | None = None
        self.committed = False
        self.route = world.ego_route
        geo = world.geometry
        s_turn0 = rm.lane("ego_approach").length
        self.turn = (s_turn0, s_turn0 + rm.lane("ego_turn").length)
        self.v_lim = float(geo.speed_limit)
        self.v_turn = float(rm.lane("ego_turn").speed_limit)
        self.zone_in = float(world.conflict.a[0]) - LENGTH / 2  # centre arc length at entry
        self.s_stop = self.zone_in - recipe.stop_gap
        self.half = world.vehicle.length / 2

    def plan(self, world, s: float, v: float) -> str:
        """``"go"`` or ``"stop"`` at SDV arc length ``s`` and speed ``v`` (also updates
        :attr:`committed`)."""
        r = self.recipe
        if not self.committed:
            self.committed = s >= self.s_stop + 0.5 or v * v / (2 * r.brake_max) > self.zone_in - s
        zone = world.conflict
        s_o = float(_progress(world.driver.position, world.other_route))
        if self.committed or s_o - LENGTH / 2 > zone.b[1]:  # committed, or the other cleared
            return "go"
        other_yields = world.decision == "yield"
        if self.force == "other_first":
            return "stop"
        if self.force == "sdv_first" or self.intent == "enter":
            return "go" if other_yields else "stop"
        return "go" if other_yields and world.driver.speed < 1.0 else "stop"

    def command(self, world) -> np.ndarray:
        """The SDV's command ``(a, delta)`` for the next step."""
        r = self.recipe
        x = world.truth()[0]
        s = float(_progress(x[:2], self.route))
        v = float(x[2])
        t0, t1 = self.turn
        if s < t0:
            v_ref = min(self.v_lim, math.sqrt(self.v_turn**2 + 2 * r.brake_comfort * (t0 - s)))
        elif s < t1:
            v_ref = self.v_turn
        else:
            v_ref = self.v_lim
        a_ff = 0.0
        if self.plan(world, s, v) == "stop":
            v_stop = math.sqrt(2 * r.brake_comfort * max(self.s_stop - s, 0.0))
            if v_stop < v_ref:
                v_ref, a_ff = v_stop, (-r.brake_comfort if v_stop > 0 else 0.0)
        a = min(max(2.0 * (v_ref - v) + a_ff, -6.0), r.acc_max)
        a = max(a, -v / world.dt)  # never reverse
        # pure pursuit of the route at look-ahead Ld from the centre of the vehicle
        Ld = max(5.0, 0.6 * v + 3.0)
        tgt, _ = _at(self.route, s + Ld)
        d = tgt[0] - x[:2]
        alpha = math.atan2(d[1], d[0]) - x[3]
        kappa = 2 * math.sin(alpha) / max(float(np.hypot(*d)), 1e-6)
        sin_beta = min(max(kappa * self.half, -0.99), 0.99)
        delta = math.atan(2 * math.tan(math.asin(sin_beta)))
        return np.array([a, min(max(delta, -math.pi / 4), math.pi / 4)])


def _progress(p: np.ndarray, route: np.ndarray) -> float:
    from .maps import project_to_polyline

    return float(project_to_polyline(np.asarray(p, dtype=float)[None], route)[0][0])


# --------------------------------------------------------------------------------------
# runs
# --------------------------------------------------------------------------------------
@dataclass
class Run:
    """A recorded run: states ``(n+1, N, 4)`` (world frame) and the step at which each
    agent's front entered the conflict zone (``None``: not within the run)."""

    states: np.ndarray
    entry: list[int | None]
    collided: bool

    @property
    def outcome(self) -> str | None:
        es, eo = self.entry
        if es is None and eo is None:
            return None
        if eo is None or (es is not None and es < eo):
            return "sdv_first"
        return "other_first"


def _entered(world, policy: SDVPolicy) -> tuple[bool, bool]:
    x = world.truth()
    s_e = _progress(x[0, :2], policy.route)
    s_o = _progress(x[1, :2], world.other_route)
    return s_e >= policy.zone_in, s_o + LENGTH / 2 >= world.conflict.b[0]


def simulate(
    world,
    policy: SDVPolicy,
    steps: int,
    k0: int = 0,
    entry: list | None = None,
    until_outcome: int = 0,
    snapshots: int = 0,
):
    """Step ``world`` with ``policy`` for ``steps`` steps (and up to ``until_outcome`` more
    while no vehicle has entered the zone). ``k0``: the step number of the start;
    ``entry``: entry steps known so far. Returns the :class:`Run` and deep copies
    ``(world, policy)`` at the first ``snapshots`` steps (before stepping)."""
    entry = list(entry) if entry is not None else [None, None]
    states = [world.truth()]
    snaps = []
    k = k0
    for j in range(steps + until_outcome):
        if j >= steps and (entry[0] is not None or entry[1] is not None):
            break
        if j < snapshots:
            snaps.append(copy.deepcopy((world, policy)))
        if policy.force == "other_first":
            world.forced_decision = None if policy.committed else "go"
        elif policy.force == "sdv_first":
            world.forced_decision = "yield"
        world.step(policy.command(world))
        k += 1
        states.append(world.truth())
        for i, e in enumerate(_entered(world, policy)):
            if e and entry[i] is None:
                entry[i] = k
        if world.ego.crashed or world.driver.crashed:
            return Run(np.array(states), entry, True), snaps
    return Run(np.array(states), entry, False), snaps
