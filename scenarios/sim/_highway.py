"""The one place that imports highway-env (lazily: ``import scenarios.sim`` stays light).

highway-env 1.12.1 imports pygame, gymnasium, pandas and matplotlib; it neither opens a
window nor prints when imported this way (pygame's banner is hidden by highway-env itself,
and ``SDL_VIDEODRIVER=dummy`` is set, if unset, so nothing can ever open a display), and it
does not import torch. We use its road network (``RoadNetwork``, ``StraightLane``,
``CircularLane``, ``SineLane``), its ``Road`` (stepping and rectangle collisions), its
kinematic bicycle ``Vehicle`` (the ego) and its ``IDMVehicle`` (IDM longitudinal model and
lane-following steering) for the other drivers; never its gymnasium environments.
"""

from __future__ import annotations

import functools
import os
from types import SimpleNamespace

import numpy as np

from epo_casadi.errors import EpoError, check_number
from solvers.control.types import Observation, WorldBase

from ..maps import project_to_polyline
from .common import circles_overlap

__all__ = ["hw", "HighwayWorld", "LENGTH", "WIDTH"]

LENGTH = 5.0  # m, highway-env Vehicle.LENGTH: every car of the highway-env worlds
WIDTH = 2.0  # m, highway-env Vehicle.WIDTH


@functools.cache
def hw() -> SimpleNamespace:
    """highway-env's classes we use (imported on first call)."""
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    try:
        from highway_env.road.lane import CircularLane, LineType, SineLane, StraightLane
        from highway_env.road.road import Road, RoadNetwork
        from highway_env.vehicle.behavior import IDMVehicle
        from highway_env.vehicle.kinematics import Vehicle
        from highway_env.vehicle.objects import Obstacle
    except ImportError as exc:  # pragma: no cover - a broken install
        raise EpoError(
            f"highway-env is needed for this scenario (pip install highway-env==1.12.1): {exc}"
        ) from None

    class Driver(IDMVehicle):
        """An IDM vehicle with lane-following steering and no lane changes, whose
        acceleration is also capped by IDM towards ``stop_obstacle`` (a virtual standing
        obstacle that the world's decision logic places when the driver yields)."""

        stop_obstacle = None

        def act(self, action=None):
            if self.crashed:
                return
            self.follow_road()
            if self.enable_lane_change:
                self.change_lane_policy()
            steer = float(
                np.clip(
                    self.steering_control(self.target_lane_index),
                    -self.MAX_STEERING_ANGLE,
                    self.MAX_STEERING_ANGLE,
                )
            )
            front, rear = self.road.neighbour_vehicles(self, self.lane_index)
            acc = self.acceleration(ego_vehicle=self, front_vehicle=front, rear_vehicle=rear)
            if self.lane_index != self.target_lane_index:
                f2, r2 = self.road.neighbour_vehicles(self, self.target_lane_index)
                acc = min(acc, self.acceleration(ego_vehicle=self, front_vehicle=f2))
            if self.stop_obstacle is not None:
                acc = min(
                    acc, self.acceleration(ego_vehicle=self, front_vehicle=self.stop_obstacle)
                )
            acc = float(np.clip(acc, -self.ACC_MAX, self.ACC_MAX))
            Vehicle.act(self, {"steering": steer, "acceleration": acc})

    return SimpleNamespace(
        CircularLane=CircularLane,
        LineType=LineType,
        SineLane=SineLane,
        StraightLane=StraightLane,
        Road=Road,
        RoadNetwork=RoadNetwork,
        IDMVehicle=IDMVehicle,
        Vehicle=Vehicle,
        Obstacle=Obstacle,
        Driver=Driver,
    )


class HighwayWorld(WorldBase):
    """What the highway-env worlds share: truth, observation, placement and the outcome
    checks (collision, off-road, timeout; success is each world's own :meth:`_succeeded`).

    Subclasses provide ``vehicles`` (ego first), ``ego_route``, ``road_map``, ``sensor``,
    ``latch``, ``radii``, ``options`` (``collision``, ``off_road_margin``), ``t``, ``k``
    and ``max_steps``. Every car is a ``LENGTH x WIDTH`` (5 m x 2 m) rectangle, the
    world's :attr:`footprint` (what the planners' two circles per car are made from).
    The ego does not reverse (:meth:`_stop_not_reverse`, the rule of
    ``VehicleModel(no_reverse=True)``).
    """

    vehicles: list
    footprint = (LENGTH, WIDTH)

    def _stop_not_reverse(self) -> None:
        """After a step: an ego speed below zero becomes zero. highway-env moves the
        vehicle with the speed it had before the step, so this is exactly
        ``VehicleModel(no_reverse=True)``'s step (the ego stops, it does not reverse)."""
        ego = self.vehicles[0]
        if ego.speed < 0:
            ego.speed = 0.0

    def truth(self) -> np.ndarray:
        """``(N, 4)`` true ``(x, y, v, theta)`` of every agent, the ego first."""
        return np.array(
            [[v.position[0], v.position[1], v.speed, v.heading] for v in self.vehicles],
            dtype=float,
        )

    def outcome(self) -> str:
        return self.latch.value

    def progress(self) -> float:
        """Arc length (m) of the ego along its route."""
        return float(project_to_polyline(self.vehicles[0].position[None], self.ego_route)[0][0])

    def set_state(self, agent: int, state: np.ndarray) -> None:
        """Place agent ``agent`` at ``(x, y, v, theta)`` (tests, hand-made situations)."""
        check_number("agent", agent, lo=0, hi=self.n_agents - 1, integer=True)
        x = np.asarray(state, dtype=float).reshape(4)
        veh = self.vehicles[agent]
        veh.position = x[:2].copy()
        veh.speed, veh.heading = float(x[2]), float(x[3])
        veh.on_state_update()

    def _observe(self) -> Observation:
        x = self.truth()
        return Observation(t=self.t, ego=x[0].copy(), others=self.sensor.measure(x[1:, :2]))

    def _check(self) -> None:
        """Latch the first terminal outcome of this step."""
        o, ego = self.options, self.vehicles[0]
        if o.collision == "rectangles":
            hit = bool(ego.crashed)
        else:
            hit = circles_overlap(self.truth()[:, :2], self.radii)
        if hit:
            self.latch.set("collision")
        if self.road_map.distance_to_road(ego.position[None])[0] > o.off_road_margin:
            self.latch.set("off_road")
        if self._succeeded(np.asarray(ego.position, dtype=float)):
            self.latch.set("success")
        if self.k >= self.max_steps:
            self.latch.set("timeout")

    def _succeeded(self, position: np.ndarray) -> bool:  # pragma: no cover - abstract
        raise NotImplementedError
