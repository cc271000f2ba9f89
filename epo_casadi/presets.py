"""The paper's driving features (App. F.3), written once.

The agent-dependent features of the paper's urban experiments are
``c = [c_goal, c_lane, c_vref, c_vel, c_acc, c_jerk, c_turnr, c_turnacc]`` (CARLA, with the
goal term of ours; exiD the same), and of its Waymo experiments
``c = [c_goal, c_vel, c_acc, c_jerk, c_turnr, c_turnacc]`` (no map reference).
:func:`driving_features` builds either list from the default weights of a recipe, so the
left-turn, exiD-layout and recorded-data scenarios share one definition, and
:func:`driving_agents` / :func:`driving_game_spec` build their games (unicycles with these
features, circle collisions) from the same recipe attributes.

Weights are read from the attributes ``w_goal``, ``w_lane``, ``w_vref``, ``w_vel``,
``w_acc``, ``w_jerk``, ``w_turn`` and ``w_turnacc`` of ``weights`` (a recipe dataclass or any
object with them); they are the game's default weights, which the network replaces.
The games also read ``w_collision``, ``radius``, ``horizon`` and ``dt``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields

from .errors import check_number
from .features import (
    Acceleration,
    Collision,
    Feature,
    Goal,
    Jerk,
    Path,
    ReferenceVelocity,
    TurnAcceleration,
    TurnRate,
    Velocity,
)
from .game import AgentSpec, GameSpec

__all__ = [
    "driving_features",
    "driving_agents",
    "driving_game_spec",
    "check_weights",
    "DRIVING_WEIGHTS",
]

#: the recipe attribute of each feature's default weight, in feature order
DRIVING_WEIGHTS = (
    "w_goal",
    "w_lane",
    "w_vref",
    "w_vel",
    "w_acc",
    "w_jerk",
    "w_turn",
    "w_turnacc",
)


def driving_features(weights, lane_points: int | None = None) -> list[Feature]:
    """App. F.3's features of one agent: goal, lane (a ``Path`` of ``lane_points`` vertices,
    label ``lane``) and reference velocity (label ``vref``) when ``lane_points`` is given,
    then velocity, acceleration, jerk, turn rate and turn acceleration."""
    out: list[Feature] = [Goal(weight=weights.w_goal)]
    if lane_points is not None:
        out += [
            Path(weight=weights.w_lane, points=lane_points, label="lane"),
            ReferenceVelocity(weight=weights.w_vref, label="vref"),
        ]
    out += [
        Velocity(weight=weights.w_vel),
        Acceleration(weight=weights.w_acc),
        Jerk(weight=weights.w_jerk),
        TurnRate(weight=weights.w_turn),
        TurnAcceleration(weight=weights.w_turnacc),
    ]
    return out


def driving_agents(
    recipe, names: Sequence[str], *, lane_points: int | None = None, radius_param: bool = False
) -> list[AgentSpec]:
    """One unicycle per name with :func:`driving_features` of ``recipe`` (``lane_points`` as
    there) and collision radius ``recipe.radius`` (the default of a per-agent parameter
    block when ``radius_param``)."""
    return [
        AgentSpec(
            name,
            "unicycle",
            driving_features(recipe, lane_points=lane_points),
            radius=recipe.radius,
            radius_param=radius_param,
        )
        for name in names
    ]


def driving_game_spec(recipe, agents: Sequence[AgentSpec], *, every: int = 1) -> GameSpec:
    """The game of ``agents``: circle collisions every ``every`` steps with weight
    ``recipe.w_collision``, horizon ``recipe.horizon`` at step ``recipe.dt``."""
    return GameSpec(
        agents,
        [Collision(weight=recipe.w_collision, every=every)],
        horizon=recipe.horizon,
        dt=recipe.dt,
    )


def check_weights(prefix: str, recipe) -> None:
    """Every ``w_*`` field of the dataclass ``recipe`` is a number >= 0 (errors name
    ``prefix.w_...``)."""
    for f in fields(recipe):
        if f.name.startswith("w_"):
            check_number(f"{prefix}.{f.name}", getattr(recipe, f.name), lo=0.0)
