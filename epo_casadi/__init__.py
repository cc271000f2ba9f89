"""Symbolic core: dynamics, energy features and the single-shooting potential game.

No torch here. User features and dynamics (subclasses in the user's own module) plug in
through :mod:`epo_casadi.registry` (``docs/extending.md``). The problem contract (notation, shapes, index order) is the docstring
of :mod:`epo_casadi.game`.
"""

from .dynamics import (
    DoubleIntegrator,
    Dynamics,
    JointDynamics,
    KinematicBicycle,
    Unicycle,
    make_dynamics,
)
from .errors import EpoError, SpecError
from .features import (
    Acceleration,
    AccelerationBound,
    AgentContext,
    Collision,
    Feature,
    Goal,
    Jerk,
    PairFeature,
    ParamSpec,
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
from .game import AgentSpec, Coupling, GameSpec, ParamLayout, PotentialGame, Term
from .registry import register_dynamics, register_feature, register_pair_feature

__all__ = [
    "Acceleration",
    "AccelerationBound",
    "AgentContext",
    "AgentSpec",
    "Collision",
    "Coupling",
    "DoubleIntegrator",
    "Dynamics",
    "EpoError",
    "Feature",
    "GameSpec",
    "Goal",
    "Jerk",
    "JointDynamics",
    "KinematicBicycle",
    "PairFeature",
    "ParamLayout",
    "ParamSpec",
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
    "register_dynamics",
    "register_feature",
    "register_pair_feature",
]
