"""The ego's vehicle model: the world's step exactly, exact Jacobians, limits, bad input."""

from __future__ import annotations

import math
import warnings

import casadi as ca
import numpy as np
import pytest

from epo_casadi.dynamics import Unicycle
from epo_casadi.errors import SpecError
from solvers.control.vehicle import VehicleModel

DT = 0.1


def _samples(rng, n, steer=0.7):
    X = rng.uniform([-50, -50, -45, -4], [50, 50, 45, 4], size=(n, 4))
    U = rng.uniform([-5, -steer], [5, steer], size=(n, 2))
    return X, U


def test_unicycle_step_is_the_games_explicit_euler_step():
    rng = np.random.default_rng(0)
    X, U = _samples(rng, 50)
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    ref = ca.Function("f", [x, u], [Unicycle().step(x, u, DT)])
    want = np.array([np.asarray(ref(a, b)).ravel() for a, b in zip(X, U, strict=True)])
    got = VehicleModel().step(X, U, DT)  # vectorized over the 50 samples
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("substeps", [1, 3])
def test_bicycle_step_is_highway_env_vehicle_step(substeps):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kin = pytest.importorskip(
            "highway_env.vehicle.kinematics",
            reason="highway-env (==1.12.1) is not installed in this environment",
        )
    rng = np.random.default_rng(1)
    X, U = _samples(rng, 200)  # speeds beyond +-40 m/s exercise highway-env's speed clip
    # highway-env's Vehicle as it is reverses: the plain model (the worlds' ego does not)
    model = VehicleModel.highway(substeps=substeps, no_reverse=False)
    want = np.empty_like(X)
    for i, (x, u) in enumerate(zip(X, U, strict=True)):
        veh = kin.Vehicle(None, x[:2].copy(), heading=x[3], speed=x[2])
        veh.act({"acceleration": u[0], "steering": u[1]})
        for _ in range(substeps):  # highway-env: simulation_frequency / policy_frequency
            veh.step(DT / substeps)
        want[i] = [veh.position[0], veh.position[1], veh.speed, veh.heading]
    assert np.any(np.abs(X[:, 2]) > 40)  # the clip regime is exercised
    np.testing.assert_allclose(model.step(X, U, DT), want, rtol=0, atol=1e-10)


def test_bicycle_hand_computed_step_and_speed_clip():
    m = VehicleModel.highway()
    x = np.array([1.0, 2.0, 10.0, 0.5])
    d = 0.3
    beta = math.atan(0.5 * math.tan(d))
    want = [
        1 + 10 * math.cos(0.5 + beta) * DT,
        2 + 10 * math.sin(0.5 + beta) * DT,
        10 + 2 * DT,
        0.5 + 10 * math.sin(beta) / 2.5 * DT,
    ]
    np.testing.assert_allclose(m.step(x, [2.0, d], DT), want, atol=1e-14)
    # above MAX_SPEED = 40 the acceleration becomes min(a, 40 - v) = -1
    fast = m.step([0, 0, 41.0, 0], [2.0, 0.0], DT)
    assert fast[2] == pytest.approx(41.0 - 0.1, abs=1e-14)


@pytest.mark.parametrize("kind", ["unicycle", "bicycle"])
def test_a_car_stops_rather_than_reverses(kind):
    """no_reverse (the worlds' ego): a braking command that would take the speed below zero
    stops the car exactly at zero within the step; positions move with the speed before the
    step (explicit Euler), the free model's rows elsewhere; at standstill with a = 0 the
    Jacobian still sees the acceleration (d v+ / d a = dt): a tracker can start the car."""
    free = VehicleModel(kind=kind)
    car = VehicleModel(kind=kind, no_reverse=True)
    assert VehicleModel.highway().no_reverse and not VehicleModel().no_reverse
    x = np.array([1.0, 2.0, 0.8, 0.3])
    for u in ([-10.0, 0.2], [-20.0, 0.0], [-100.0, -0.3]):
        want = free.step(x, u, DT)
        assert want[2] < 0  # the free model reverses
        want[2] = 0.0
        got = car.step(x, u, DT)
        np.testing.assert_array_equal(got, want)
        xn = np.asarray(car.function(DT)(x, u)[0]).ravel()
        np.testing.assert_array_equal(xn, want)
    # a gentle brake (no sign change) is the free step bit for bit
    np.testing.assert_array_equal(car.step(x, [-2.0, 0.1], DT), free.step(x, [-2.0, 0.1], DT))
    # standing still: braking keeps it at 0, never below, over many steps
    X = car.rollout(x, np.tile([-5.0, 0.0], (20, 1)), DT)
    assert np.all(X[:, 2] >= 0.0) and X[-1, 2] == 0.0
    _, _, B = car.function(DT)([0.0, 0.0, 0.0, 0.0], [0.0, 0.0])
    assert float(B[2, 0]) == pytest.approx(DT)
    # a negative speed (a hand-placed state) is brought to zero in one step
    assert car.step([0.0, 0.0, -3.0, 0.0], [0.0, 0.0], DT)[2] == 0.0
    with pytest.raises(SpecError, match="vehicle.no_reverse"):
        VehicleModel(no_reverse="yes")


@pytest.mark.parametrize("kind,substeps", [("unicycle", 1), ("bicycle", 1), ("bicycle", 2)])
def test_casadi_function_matches_numpy_and_finite_differences(kind, substeps):
    m = VehicleModel(kind=kind, substeps=substeps)
    f = m.function(DT)
    assert f is m.function(DT)  # cached
    rng = np.random.default_rng(2)
    X, U = _samples(rng, 8)
    h = 1e-6
    for x, u in zip(X, U, strict=True):
        xn, A, B = (np.asarray(v) for v in f(x, u))
        np.testing.assert_allclose(xn.ravel(), m.step(x, u, DT), atol=1e-12)
        E4, E2 = np.eye(4) * h, np.eye(2) * h
        A_fd = np.stack([(m.step(x + e, u, DT) - m.step(x - e, u, DT)) / (2 * h) for e in E4], 1)
        B_fd = np.stack([(m.step(x, u + e, DT) - m.step(x, u - e, DT)) / (2 * h) for e in E2], 1)
        np.testing.assert_allclose(A, A_fd, atol=1e-7)
        np.testing.assert_allclose(B, B_fd, atol=1e-7)


def test_from_unicycle_reproduces_the_turn_rate():
    m = VehicleModel.highway()
    rng = np.random.default_rng(3)
    X = rng.uniform([-5, -5, 1, -3], [5, 5, 20, 3], size=(30, 4))
    W = rng.uniform([-2, -0.5], [2, 0.5], size=(30, 2))
    C = m.from_unicycle(X, W)
    np.testing.assert_allclose(C[:, 0], W[:, 0])
    np.testing.assert_allclose(m.turn_rate(X, C), W[:, 1], atol=1e-12)
    # a standing vehicle gets no steering; the unicycle's command is unchanged
    assert m.from_unicycle([0, 0, 0.0, 0], [1.0, 0.4])[1] == 0.0
    np.testing.assert_array_equal(VehicleModel().from_unicycle(X, W), W)


def test_limits_and_clip():
    m = VehicleModel(a_min=-4, a_max=2, steer_max=0.5, jerk_max=10, steer_rate_max=1.0)
    lo, hi = m.bounds()
    np.testing.assert_array_equal(lo, [-4, -0.5])
    np.testing.assert_array_equal(hi, [2, 0.5])
    np.testing.assert_allclose(m.rate_bounds(DT), [1.0, 0.1])
    np.testing.assert_allclose(m.clip([9.0, -9.0]), [2.0, -0.5])
    # rates from the previous command, then the box
    np.testing.assert_allclose(m.clip([9.0, -9.0], u_prev=np.array([0.0, 0.0]), dt=DT), [1, -0.1])
    np.testing.assert_allclose(m.clip([9.0, 0.0], u_prev=np.array([1.8, 0.0]), dt=DT), [2, 0])


def test_rollout_is_repeated_steps():
    m = VehicleModel.highway()
    U = np.tile([[1.0, 0.1]], (5, 1))
    X = m.rollout([0, 0, 5.0, 0], U, DT)
    x = np.array([0, 0, 5.0, 0])
    for k in range(5):
        x = m.step(x, U[k], DT)
        np.testing.assert_array_equal(X[k], x)


@pytest.mark.parametrize(
    "kw,field",
    [
        ({"kind": "car"}, "vehicle.kind"),
        ({"length": 0.0}, "vehicle.length"),
        ({"a_min": 1.0}, "vehicle.a_min"),
        ({"kind": "bicycle", "steer_max": 1.6}, "vehicle.steer_max"),
        ({"jerk_max": -1.0}, "vehicle.jerk_max"),
        ({"v_min": 5.0, "v_max": 1.0}, "vehicle.v_max"),
        ({"v_max": float("nan")}, "vehicle.v_max"),
        ({"substeps": 0}, "vehicle.substeps"),
    ],
)
def test_bad_vehicle_options_name_the_field(kw, field):
    with pytest.raises(SpecError) as e:
        VehicleModel(**kw)
    assert e.value.field == field
