"""Closed-loop control: estimation, planning, tracking, and the worlds they drive in.

The vocabulary (observations, estimates, plans, commands, the four roles) is in
:mod:`solvers.control.types`; the ego's vehicle model in :mod:`solvers.control.vehicle`;
the filterpy UKF estimator in :mod:`solvers.control.estimate`; the PID and OSQP MPC trackers
in :mod:`solvers.control.track`; the game oracle and the constant-velocity planner in
:mod:`solvers.control.plan`. No torch here.
"""

from .estimate import UKFEstimator, UKFOptions
from .plan import ConstantVelocityPlanner, GameOracle, PlannerOptions
from .track import MPCOptions, MPCTracker, PIDOptions, PIDTracker
from .types import (
    AgentTask,
    Command,
    Estimate,
    Estimator,
    Observation,
    Plan,
    Planner,
    Tracker,
    World,
)
from .vehicle import VehicleModel

__all__ = [
    # types
    "AgentTask",
    "Command",
    "Estimate",
    "Estimator",
    "Observation",
    "Plan",
    "Planner",
    "Tracker",
    "World",
    # vehicle, estimation, tracking
    "VehicleModel",
    "UKFEstimator",
    "UKFOptions",
    "PIDOptions",
    "PIDTracker",
    "MPCOptions",
    "MPCTracker",
    # planners
    "PlannerOptions",
    "GameOracle",
    "ConstantVelocityPlanner",
]
