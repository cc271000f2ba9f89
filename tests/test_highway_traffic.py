"""The generator's traffic (scenarios/highway/) on hand-placed highway-env vehicles: queues
keep the jam distance bumper to bumper behind cars and trucks, braking ends at standstill
(no reversing), and a car inside a truck's box is a crash, whatever the sizes."""

from __future__ import annotations

import numpy as np
import pytest

from scenarios.highway import driver_class, size_vehicle

hw = pytest.importorskip("highway_env")


def _road():
    from highway_env.road.road import Road, RoadNetwork

    net = RoadNetwork.straight_road_network(lanes=1, length=2000.0, speed_limit=30.0)
    return Road(network=net, np_random=np.random.RandomState(0))


def _car(road, Driver, x, speed, length, width, target_speed):
    lane = road.network.get_lane(("0", "1", 0))
    kw = {} if target_speed is None else {"target_speed": target_speed}
    v = Driver(road, lane.position(x, 0.0), heading=0.0, speed=speed, **kw)
    size_vehicle(v, length, width)
    v.DISTANCE_WANTED = 3.0
    road.vehicles.append(v)
    return v


@pytest.mark.parametrize("front_length", [4.5, 16.0])
def test_queue_stops_at_the_jam_distance_without_reversing(front_length):
    Driver = driver_class()
    road = _road()
    from highway_env.vehicle.kinematics import Vehicle  # no controller: stands still

    front = _car(road, Vehicle, 300.0, 0.0, front_length, 2.5, target_speed=None)
    rear = _car(road, Driver, 150.0, 20.0, 4.6, 1.9, target_speed=25.0)
    xs, speeds = [], []
    for _ in range(1500):  # 60 s at 25 Hz
        road.act()
        road.step(1 / 25)
        xs.append(rear.position[0])
        speeds.append(rear.speed)
    gap = (front.position[0] - rear.position[0]) - 0.5 * (front_length + 4.6)
    # the IDM's standstill gap is its jam distance, bumper to bumper (3 m here): before the
    # fix the IDM kept its jam distance between the centres: behind a truck, boxes overlapped
    assert gap == pytest.approx(3.0, abs=0.05)
    assert min(speeds) >= 0.0 and np.all(np.diff(xs) >= 0.0)
    assert front.position[0] == 300.0 and not rear.crashed


def test_car_inside_a_truck_box_is_a_crash():
    Driver = driver_class()
    road = _road()
    truck = _car(road, Driver, 100.0, 0.0, 15.0, 2.5, target_speed=0.0)
    car = _car(road, Driver, 107.0, 0.0, 4.5, 1.9, target_speed=0.0)  # boxes overlap by 2.75 m
    road.act()
    road.step(1 / 25)
    assert truck.crashed and car.crashed
    # the pre-check reach is the vehicle's own diagonal, not highway-env's 5 x 2 m default
    assert truck.diagonal == pytest.approx(np.hypot(15.0, 2.5))
