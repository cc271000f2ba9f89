"""Small games shared by the tests."""

from __future__ import annotations

import numpy as np

from epo_casadi import (
    Acceleration,
    AccelerationBound,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    PotentialGame,
    TurnRate,
    TurnRateBound,
    Velocity,
    VelocityBound,
)


def crossing_spec(
    N: int = 2, K: int = 20, dt: float = 0.1, collision_weight: float = 10.0, offset: float = 0.0
) -> GameSpec:
    """N unicycles on a circle of radius 3 m, each heading to the opposite side.

    ``offset`` shifts every goal sideways (m) to break the symmetry of the head-on case.
    """
    agents = []
    for i in range(N):
        ang = 2 * np.pi * i / N
        c, s = np.cos(ang), np.sin(ang)
        agents.append(
            AgentSpec(
                f"a{i}",
                "unicycle",
                [
                    Goal(weight=3.0),
                    Velocity(weight=0.5),
                    Acceleration(),
                    TurnRate(),
                    VelocityBound(lower=0.0, upper=2.0, weight=5.0),
                    AccelerationBound(lower=-2.0, upper=2.0, weight=5.0),
                    TurnRateBound(lower=-1.5, upper=1.5, weight=5.0),
                ],
                radius=0.25,
                x0=[3 * c, 3 * s, 1.0, ang + np.pi],
                goal=[-3 * c - offset * s, -3 * s + offset * c],
            )
        )
    return GameSpec(agents, [Collision(weight=collision_weight)], horizon=K, dt=dt)


def crossing_game(**kw) -> PotentialGame:
    return PotentialGame(crossing_spec(**kw))
