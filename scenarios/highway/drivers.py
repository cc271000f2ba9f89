"""The generator's drivers: highway-env's IDM/MOBIL vehicle with mandatory lane changes
for ramp traffic (:func:`driver_class`; behaviour in :mod:`scenarios.highway`, "Traffic")
and the sizing of a vehicle with its crash pre-check reach (:func:`size_vehicle`)."""

from __future__ import annotations

import functools
import math


@functools.cache
def driver_class():
    """highway-env's IDM/MOBIL vehicle with mandatory lane changes for ramp traffic
    (:mod:`scenarios.highway`); built on first use (highway-env is imported lazily)."""
    from ..sim._highway import hw

    H = hw()
    from highway_env import utils

    class RampDriver(H.Driver):
        """``want``: callable(vehicle) -> wanted lane number on the current edge or None;
        ``aux``: the auxiliary lane index (through traffic may not enter it);
        ``aux_end``: obstacle at its end (merging vehicles brake for it)."""

        want = None
        aux = None
        aux_end = None
        urgency = 0.0

        def change_lane_policy(self):
            if self.lane_index != self.target_lane_index:
                # a mandatory change still on its own lane is called off when it became
                # unsafe (a fast follower closed up); then highway-env's abort logic
                if self.want is not None and not self._safe(self.target_lane_index):
                    self.target_lane_index = self.lane_index
                    return None
                return H.IDMVehicle.change_lane_policy(self)
            on_aux = self.lane_index == self.aux
            self.stop_obstacle = self.aux_end if on_aux and self.aux_end is not None else None
            if not utils.do_every(self.LANE_CHANGE_DELAY, self.timer):
                return
            self.timer = 0
            cur = self.lane_index
            want = self.want(self) if self.want is not None else None
            if want is not None and want != cur[2]:
                cand = (cur[0], cur[1], cur[2] + (1 if want > cur[2] else -1))
                if cand[2] < len(self.road.network.graph[cur[0]][cur[1]]) and self._safe(cand):
                    self.target_lane_index = cand
                return
            if abs(self.speed) < 1:
                return
            for li in self.road.network.side_lanes(cur):
                if li == self.aux or not self.road.network.get_lane(li).is_reachable_from(
                    self.position
                ):
                    continue
                if self.mobil(li):
                    self.target_lane_index = li

        def acceleration(self, ego_vehicle, front_vehicle=None, rear_vehicle=None) -> float:
            # the IDM on bumper-to-bumper gaps: highway-env's free-road term, and the
            # interaction term -a (s* / s)^2 with s the gap between the bumpers (highway-env
            # uses the distance between the centres) and s* its desired gap (jam distance
            # DISTANCE_WANTED plus the speed terms), so that a queue stands DISTANCE_WANTED
            # apart behind cars and trucks alike
            acc = super().acceleration(ego_vehicle, None, rear_vehicle)
            if front_vehicle is None or ego_vehicle is None:
                return acc
            s = ego_vehicle.lane_distance_to(front_vehicle)
            s -= 0.5 * (ego_vehicle.LENGTH + front_vehicle.LENGTH)
            ratio = self.desired_gap(ego_vehicle, front_vehicle) / max(s, 0.1)
            return acc - self.COMFORT_ACC_MAX * ratio**2

        def step(self, dt: float) -> None:
            super().step(dt)
            if self.speed < 0.0:  # IDM braking ends at standstill: vehicles never reverse
                self.speed = 0.0

        def _safe(self, lane_index) -> bool:
            pre, fol = self.road.neighbour_vehicles(self, lane_index)
            b = self.LANE_CHANGE_MAX_BRAKING_IMPOSED * (1.0 + 0.75 * self.urgency)
            for other, ego, front in ((fol, fol, self), (pre, self, pre)):
                if other is None:
                    continue
                gap = abs(self.lane_distance_to(other)) - 0.5 * (self.LENGTH + other.LENGTH)
                if gap < 2.0 or self.acceleration(ego_vehicle=ego, front_vehicle=front) < -b:
                    return False
            return True

    return RampDriver


def size_vehicle(v, length: float, width: float) -> None:
    """Give a highway-env vehicle its length and width, and the crash pre-check its reach:
    highway-env caches ``diagonal`` at construction (from the class's 5 x 2 m), so a longer
    vehicle set afterwards would not be checked against vehicles beyond that reach."""
    v.LENGTH, v.WIDTH = float(length), float(width)
    v.diagonal = float(math.hypot(length, width))
