"""Symbolic core: dynamics, energy features and the single-shooting potential game.

No torch here. The problem contract (notation, shapes, index order) is the docstring
of :mod:`epo_casadi.game`.
"""

from .dynamics import DoubleIntegrator, Dynamics, KinematicBicycle, Unicycle, make_dynamics
from .errors import EpoError, SpecError
from .features import (
    Acceleration,
    AccelerationBound,
    Collision,
    Goal,
    Jerk,
    Path,
    ReferenceVelocity,
    TurnAcceleration,
    TurnRate,
    TurnRateBound,
    Velocity,
    VelocityBound,
    make_feature,
    make_pair_feature,
)
from .game import AgentSpec, GameSpec, ParamLayout, PotentialGame, Term

__all__ = [
    "Acceleration",
    "AccelerationBound",
    "AgentSpec",
    "Collision",
    "DoubleIntegrator",
    "Dynamics",
    "EpoError",
    "GameSpec",
    "Goal",
    "Jerk",
    "KinematicBicycle",
    "ParamLayout",
    "Path",
    "PotentialGame",
    "ReferenceVelocity",
    "SpecError",
    "Term",
    "TurnAcceleration",
    "TurnRate",
    "TurnRateBound",
    "Unicycle",
    "Velocity",
    "VelocityBound",
    "make_dynamics",
    "make_feature",
    "make_pair_feature",
]
