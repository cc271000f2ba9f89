"""The paper's driving features (App. F.3), written once.

The agent-dependent features of the paper's urban experiments are
``c = [c_goal, c_lane, c_vref, c_vel, c_acc, c_jerk, c_turnr, c_turnacc]`` (CARLA, with the
goal term of ours; exiD the same), and of its Waymo experiments
``c = [c_goal, c_vel, c_acc, c_jerk, c_turnr, c_turnacc]`` (no map reference).
:func:`driving_features` builds either list from the default weights of a recipe, so the
left-turn, exiD-layout and recorded-data scenarios share one definition.

Weights are read from the attributes ``w_goal``, ``w_lane``, ``w_vref``, ``w_vel``,
``w_acc``, ``w_jerk``, ``w_turn`` and ``w_turnacc`` of ``weights`` (a recipe dataclass or any
object with them); they are the game's default weights, which the network replaces.
"""

from __future__ import annotations

from .features import (
    Acceleration,
    Feature,
    Goal,
    Jerk,
    Path,
    ReferenceVelocity,
    TurnAcceleration,
    TurnRate,
    Velocity,
)

__all__ = ["driving_features", "DRIVING_WEIGHTS"]

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
