"""The driving game the planners of :mod:`solvers.control.plan` solve.

The paper's driving features for every agent on the unicycle (the own terms of ``_OWN``, their
weights from :class:`~solvers.control.plan_options.PlannerOptions`), the collision term of
every pair (the built-in ``collision`` circle per agent, or :class:`FootprintCollision`, two
circles per car), and :func:`build_game`, which builds the potential game once per
structure (agents, footprint, ``dt``, options) and caches it in the process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import casadi as ca
import numpy as np

from epo_casadi.errors import check_number
from epo_casadi.features import PairFeature, smooth_distance
from epo_casadi.game import AgentSpec, GameSpec, PotentialGame

from .plan_geometry import inscribed_circles
from .plan_options import PlannerOptions

#: (feature type, option holding its weight), the order of the residual blocks
_OWN = (
    ("path", "w_path"),
    ("reference_velocity", "w_vref"),
    ("velocity", "w_velocity"),
    ("acceleration", "w_acceleration"),
    ("jerk", "w_jerk"),
    ("turn_rate", "w_turn_rate"),
    ("turn_acceleration", "w_turn_acceleration"),
    ("velocity_bound", "w_reverse"),
)
#: the own terms whose weights keep an unconverged agent at constant velocity (oracle)
_CV_TERMS = ("acceleration", "turn_rate")


@dataclass(frozen=True)
class FootprintCollision(PairFeature):
    """Collision avoidance of two cars, each two circles at ``+-offset`` along its heading:
    ``max(0, r_i + r_j + margin - dist(c_i, c_j))`` for the four pairs of circles ``c_i``,
    ``c_j`` (front and rear of each), four rows per step ``k = 1..K`` (m).

    ``r_i`` are the agents' radii (the game's ``radius.<agent>`` parameters, the width's
    half), the heading is the state's ``theta`` (unicycle). Symmetric in ``(i, j)``; with
    ``offset = 0`` the four rows are the built-in ``collision`` row four times. Fields:
    ``label``, ``weight``, ``pairs`` (:class:`~epo_casadi.features.PairFeature`),
    ``margin`` (m, >= 0) and ``offset`` (m, >= 0).
    """

    kind: ClassVar[str] = "footprint_collision"
    margin: float = 0.0
    offset: float = 0.0

    def __post_init__(self):
        check_number("footprint_collision.margin", self.margin, lo=0)
        check_number("footprint_collision.offset", self.offset, lo=0)
        check_number("footprint_collision.weight", self.weight, lo=0)

    def steps(self, K: int) -> list[int]:
        return list(range(1, K + 1))

    def residual(self, a, b):
        reach = a.radius + b.radius + float(self.margin)
        d = float(self.offset)
        rows = []
        for k in self.steps(a.K):
            ca_ = _circles(a.X[:, k], d)
            cb = _circles(b.X[:, k], d)
            rows += [ca.fmax(0, reach - smooth_distance(p, q)) for p in ca_ for q in cb]
        return ca.vertcat(*rows)


def _circles(x, d: float) -> list:
    """The centres of a unicycle state's two circles (symbolic)."""
    u = ca.vertcat(ca.cos(x[3]), ca.sin(x[3]))
    return [x[0:2] + d * u, x[0:2] - d * u]


_GAMES: dict[tuple, PotentialGame] = {}
_FAR = 1e3  # metres: where an agent without an estimate is parked


def agent_name(i: int) -> str:
    """The game's name of agent ``i``: ``"ego"`` for agent 0, else ``"a<i>"``."""
    return "ego" if i == 0 else f"a{i}"


def build_game(radii, dt: float, options: PlannerOptions, footprint=None) -> PotentialGame:
    """The driving game of ``len(radii)`` unicycles (cached per structure in the process).

    Agent ``0`` is ``"ego"``, the others ``"a1"``, ``"a2"``, ...; parameters as in
    :mod:`epo_casadi.game` (``x0.<agent>``, ``vref.<agent>``, ``path.<agent>``,
    ``radius.<agent>``). ``footprint``: ``(length, width)`` of every agent (two circles
    each, :class:`FootprintCollision`; the radii default to half the width), or None (one
    circle of ``radii`` each, the built-in ``collision``).
    """
    radii = tuple(float(r) for r in np.asarray(radii, dtype=float).reshape(-1))
    offset = None
    if footprint is not None:
        offset, r = inscribed_circles(footprint)
        radii = (r,) * len(radii)
    key = (radii, float(dt), options, offset)
    game = _GAMES.get(key)
    if game is not None:
        return game
    P = options.path_points
    feats = []
    for kind, w in _OWN:
        f = {"type": kind, "weight": float(getattr(options, w))}
        if kind == "path":
            f["points"] = P
        if kind == "velocity_bound":
            f["lower"], f["upper"] = 0.0, math.inf
        feats.append(f)
    agents = [
        AgentSpec(
            name=agent_name(i), dynamics="unicycle", features=feats, radius=r, radius_param=True
        )
        for i, r in enumerate(radii)
    ]
    margin = float(options.collision_margin)
    if offset is None:
        pair = {"type": "collision", "weight": float(options.w_collision), "margin": margin}
    else:
        pair = FootprintCollision(weight=float(options.w_collision), margin=margin, offset=offset)
    spec = GameSpec(
        agents, pair_features=[pair] if len(radii) > 1 else [], horizon=options.horizon, dt=dt
    )
    game = _GAMES[key] = PotentialGame(spec)
    return game
