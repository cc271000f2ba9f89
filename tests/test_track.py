"""Trackers: the OSQP MPC keeps its bounds, tracks, equals LQR when unconstrained, is set up
once and falls back to braking; the PID tracks straight and curved references."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import osqp
import pytest

from epo_casadi.errors import SpecError
from solvers.control.track import MPCOptions, MPCTracker, PIDTracker, reference
from solvers.control.types import Plan, Tracker
from solvers.control.vehicle import VehicleModel

DT = 0.1
BICYCLE = VehicleModel.highway(
    a_min=-4.0, a_max=3.0, steer_max=0.5, jerk_max=8.0, steer_rate_max=0.6
)
UNICYCLE = VehicleModel(a_min=-3.0, a_max=2.0, steer_max=1.0, jerk_max=5.0, steer_rate_max=2.0)


def _world(vehicle):
    return SimpleNamespace(vehicle=vehicle, dt=DT)


def _reference_run(veh, T=120, x0=(0.0, 0.0, 6.0, 0.2)):
    """A feasible reference: the model rolled out with commands inside its limits; and the
    unicycle controls (acceleration, turn rate) a planner would hand over."""
    t = np.arange(T) * DT
    U = veh.clip(np.stack([0.8 * np.sin(0.5 * t), 0.3 * np.sin(0.3 * t)], axis=1))
    x0 = np.asarray(x0)
    X = veh.rollout(x0, U, DT)
    prev = np.concatenate([x0[None], X[:-1]])
    return x0, X, U, np.stack([U[:, 0], veh.turn_rate(prev, U)], axis=1)


def _closed_loop(tracker, veh, X, Uuni, x_start, steps, K=30):
    tracker.reset(_world(veh))
    x, cmds, errs = np.asarray(x_start, float), [], []
    for k in range(steps):
        plan = Plan(t0=k * DT, dt=DT, states=X[k : k + K], controls=Uuni[k : k + K])
        cmd = tracker.control(x, plan, k * DT)
        cmds.append(cmd)
        x = veh.step(x, cmd.value, DT)
        errs.append(np.linalg.norm(x[:2] - X[k, :2]))
    return np.array(errs), cmds


def _assert_within_limits(veh, cmds, u0=None, tol=0.0):
    u0 = np.zeros(2) if u0 is None else u0
    lo, hi = veh.bounds()
    r = veh.rate_bounds(DT)
    U = np.array([c.value for c in cmds])
    assert np.all(U >= lo - tol) and np.all(U <= hi + tol)
    dU = np.diff(np.concatenate([u0[None], U]), axis=0)
    assert np.all(np.abs(dU) <= r + tol + 1e-12)


@pytest.mark.parametrize("veh", [UNICYCLE, BICYCLE], ids=["unicycle", "bicycle"])
def test_mpc_tracks_a_feasible_reference(veh):
    x0, X, _, Uuni = _reference_run(veh)
    start = x0 + np.array([0.5, -0.8, -1.0, 0.1])  # off the reference
    mpc = MPCTracker()
    assert isinstance(mpc, Tracker)
    errs, cmds = _closed_loop(mpc, veh, X, Uuni, start, 90)
    assert errs[0] > 0.5  # it starts off the reference
    assert np.max(errs[30:]) < 0.1 and errs[-1] < 0.01, errs[[0, 30, -1]]
    assert mpc.fallbacks == 0 and mpc.setups == 1
    _assert_within_limits(veh, cmds)


@pytest.mark.parametrize("veh", [UNICYCLE, BICYCLE], ids=["unicycle", "bicycle"])
def test_mpc_respects_bounds_and_rates_in_every_step_and_saturates(veh):
    """An infeasible reference (far off, too fast, sharp turn): the MPC saturates its
    commands and their rates, never beyond them, and the raw QP solution is within the
    solver tolerance of the bounds in every step."""
    T = 60
    t = np.arange(1, T + 41) * DT
    X = np.stack([20.0 * t, 3.0 + 0 * t, 20.0 + 0 * t, 0.0 * t + 0.6], axis=1)
    Uuni = np.zeros((len(t), 2))
    mpc = MPCTracker()
    errs, cmds = _closed_loop(mpc, veh, X, Uuni, [0.0, 0.0, 2.0, 0.0], T)
    lo, hi = veh.bounds()
    r = veh.rate_bounds(DT)
    U = np.array([c.value for c in cmds])
    Uqp = np.array([c.info["u_qp"] for c in cmds])
    assert mpc.fallbacks == 0
    _assert_within_limits(veh, cmds)  # applied commands: exactly within
    tol = 10 * mpc.options.eps_abs + 10 * mpc.options.eps_rel * 20.0
    assert np.all(Uqp >= lo - tol) and np.all(Uqp <= hi + tol)
    dqp = Uqp - np.concatenate([np.zeros((1, 2)), U[:-1]])
    assert np.all(np.abs(dqp) <= r + tol)
    # the regime is the one claimed: box and rate limits are active in many steps
    at_box = np.isclose(U, hi, atol=1e-4) | np.isclose(U, lo, atol=1e-4)
    at_rate = np.isclose(
        np.abs(np.diff(np.concatenate([np.zeros((1, 2)), U]), axis=0)), r, atol=1e-4
    )
    assert at_box[:, 0].sum() >= 5 and at_rate[:, 0].sum() >= 3
    assert (at_box[:, 1] | at_rate[:, 1]).sum() >= 3


def _lqr_first_command(veh, mpc, plan, ego, u_prev):
    """The unconstrained problem solved by a finite-horizon Riccati recursion on the state
    z = (x, u_prev, 1), with the model linearized by central finite differences of the
    numpy step (independent of CasADi and OSQP)."""
    o, N = mpc.options, mpc.options.horizon
    S, Uu = plan.states, plan.controls
    ref = S[:N]
    Xbar = np.concatenate([ego[None], ref[:-1]])
    Ubar = Uu[:N]
    h = 1e-6
    nz = 7
    F, G = [], []
    for k in range(N):
        xb, ub = Xbar[k], Ubar[k]
        A = np.stack(
            [
                (veh.step(xb + e, ub, DT) - veh.step(xb - e, ub, DT)) / (2 * h)
                for e in np.eye(4) * h
            ],
            axis=1,
        )
        B = np.stack(
            [
                (veh.step(xb, ub + e, DT) - veh.step(xb, ub - e, DT)) / (2 * h)
                for e in np.eye(2) * h
            ],
            axis=1,
        )
        c = veh.step(xb, ub, DT) - A @ xb - B @ ub
        Fk = np.zeros((nz, nz))
        Fk[:4, :4], Fk[:4, 6], Fk[6, 6] = A, c, 1.0
        Gk = np.zeros((nz, 2))
        Gk[:4], Gk[4:6] = B, np.eye(2)
        F.append(Fk)
        G.append(Gk)

    def Qk(k):  # weight of x_k (k = 1..N), in the reference frame
        th = ref[k - 1, 3]
        Rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        Q = np.zeros((4, 4))
        Q[:2, :2] = Rot @ np.diag([o.q_lon, o.q_lat]) @ Rot.T
        Q[2, 2], Q[3, 3] = o.q_v, o.q_theta
        return Q * (o.terminal if k == N else 1.0)

    def state_cost(k):  # 1/2 (x_k - r_k)' Q (x_k - r_k) as 1/2 z' W z
        L = np.zeros((4, nz))
        L[:, :4], L[:, 6] = np.eye(4), -ref[k - 1]
        return L.T @ Qk(k) @ L

    Rw, Sw = np.diag([o.r_a, o.r_steer]), np.diag([o.s_a, o.s_steer])
    V = state_cost(N)
    for k in reversed(range(N)):
        # stage cost on (z, u): state cost (k >= 1), |u - ubar|_R^2, |u - u_prev|_S^2
        Lr = np.zeros((2, nz + 2))
        Lr[:, nz:], Lr[:, 6] = np.eye(2), -Ubar[k]
        Ls = np.zeros((2, nz + 2))
        Ls[:, nz:], Ls[:, 4:6] = np.eye(2), -np.eye(2)
        H = Lr.T @ Rw @ Lr + Ls.T @ Sw @ Ls
        if k >= 1:
            H[:nz, :nz] += state_cost(k)
        FG = np.concatenate([F[k], G[k]], axis=1)
        H += FG.T @ V @ FG
        K = -np.linalg.solve(H[nz:, nz:], H[nz:, :nz])
        V = H[:nz, :nz] + H[:nz, nz:] @ K
        if k == 0:
            return K @ np.concatenate([ego, u_prev, [1.0]])


def test_unconstrained_mpc_equals_finite_horizon_lqr():
    wide = VehicleModel(
        a_min=-100.0, a_max=100.0, steer_max=100.0, jerk_max=1e4, steer_rate_max=1e4
    )
    x0, X, _, Uuni = _reference_run(wide, T=40)
    mpc = MPCTracker(horizon=15, eps_abs=1e-10, eps_rel=1e-10, max_iter=100000, polish=True)
    mpc.reset(_world(wide))
    ego = x0 + np.array([0.3, -0.4, -0.5, 0.05])
    plan = Plan(t0=0.0, dt=DT, states=X[:20], controls=Uuni[:20])
    u_prev = np.array([0.2, -0.1])
    mpc.u_prev = u_prev.copy()
    cmd = mpc.control(ego, plan, 0.0)
    want = _lqr_first_command(wide, mpc, plan, ego, u_prev)
    assert not cmd.fallback
    assert np.linalg.norm(want - u_prev) > 0.05  # a non-trivial correction
    np.testing.assert_allclose(cmd.value, want, atol=1e-6)


def test_qp_is_set_up_once_and_only_updated(monkeypatch):
    calls = {"setup": 0}
    setup = osqp.OSQP.setup

    def counting_setup(self, *a, **kw):
        calls["setup"] += 1
        return setup(self, *a, **kw)

    monkeypatch.setattr(osqp.OSQP, "setup", counting_setup)
    x0, X, _, Uuni = _reference_run(BICYCLE, T=60)
    mpc = MPCTracker()
    mpc.reset(_world(BICYCLE))
    solver, A_idx, P_idx = mpc.solver, mpc._A.indices.copy(), mpc._P.indices.copy()
    for k in range(25):
        plan = Plan(t0=k * DT, dt=DT, states=X[k : k + 30], controls=Uuni[k : k + 30])
        cmd = mpc.control(X[k - 1] if k else x0, plan, k * DT)
        assert not cmd.fallback
    assert mpc.solver is solver and calls["setup"] == 1 and mpc.setups == 1
    np.testing.assert_array_equal(mpc._A.indices, A_idx)
    np.testing.assert_array_equal(mpc._P.indices, P_idx)
    assert mpc.steps == 25


def test_reference_sampling_and_holding_the_last_state():
    S = np.array([[1.0, 0, 10, 0], [2, 0, 10, 0], [3, 0, 10, 0]])
    U = np.array([[0.5, 0.0], [0.0, 0.1], [0.0, 0.2]])
    plan = Plan(t0=1.0, dt=DT, states=S, controls=U)
    R, ub = reference(plan, 1.05, DT, 5)
    # t = 1.05: half-way between the back-extrapolated (0, 0, 9.95, 0) and the first state
    np.testing.assert_allclose(R[0], [0.5, 0, 0.5 * (10 - 0.05) + 5, 0])
    np.testing.assert_allclose(R[1], [1.5, 0, 10, 0])
    np.testing.assert_allclose(R[3:], np.tile(S[-1], (3, 1)))  # held beyond the plan
    # control j acts on [t0 + j dt, t0 + (j + 1) dt): sampled at 1.05, 1.15, ... -> 0, 1, 2
    np.testing.assert_allclose(ub, [[0.5, 0.0], [0.0, 0.1], [0.0, 0.2], [0, 0], [0, 0]])


def test_mpc_with_a_reference_shorter_than_its_horizon_stops_at_its_end():
    veh = UNICYCLE
    K = 8
    S = np.stack([np.arange(1, K + 1) * 0.3, np.zeros(K), np.full(K, 3.0), np.zeros(K)], 1)
    S[-1, 2] = 0.0
    plan = Plan(t0=0.0, dt=DT, states=S, controls=np.zeros((K, 2)))
    mpc = MPCTracker()
    mpc.reset(_world(veh))
    x = np.array([0.0, 0.0, 3.0, 0.0])
    for k in range(60):  # the plan of time 0 all along: after 0.8 s its end is held
        cmd = mpc.control(x, plan, k * DT)
        x = veh.step(x, cmd.value, DT)
    assert mpc.fallbacks == 0
    assert abs(x[0] - S[-1, 0]) < 0.3 and abs(x[2]) < 0.3


def test_fallback_brakes_and_counts():
    veh = BICYCLE
    x0, X, _, Uuni = _reference_run(veh, T=40)
    ego = np.array([0.0, 0.0, 6.0, 0.2])
    for tracker in (MPCTracker(), PIDTracker()):
        tracker.reset(_world(veh))
        good = Plan(t0=0.0, dt=DT, states=X[:30], controls=Uuni[:30])
        assert not tracker.control(ego, good, 0.0).fallback
        bad = [
            Plan(t0=0.1, dt=DT, states=X[:30], controls=Uuni[:30], ok=False, message="diverged"),
            Plan(t0=0.1, dt=DT, states=np.full((30, 4), np.nan), controls=Uuni[:30]),
            Plan(t0=0.1, dt=DT, states=X[:30, :3], controls=Uuni[:30]),
        ]
        for i, p in enumerate(bad):
            cmd = tracker.control(ego, p, 0.1)
            assert cmd.fallback and "reason" in cmd.info
            assert cmd.value[0] == veh.a_min  # 6 m/s cannot stop in 0.1 s: full braking
            assert tracker.fallbacks == i + 1
        assert "diverged" in tracker.control(ego, bad[0], 0.1).info["reason"]
        # a slow vehicle gets just the deceleration that stops it (no reversing)
        cmd = tracker.control(np.array([0, 0, 0.2, 0]), bad[0], 0.1)
        assert cmd.value[0] == pytest.approx(-2.0)
    # an unsolved QP (iteration limit) is a fallback too
    mpc = MPCTracker(max_iter=1)
    mpc.reset(_world(veh))
    cmd = mpc.control(ego, Plan(t0=0.0, dt=DT, states=X[:30], controls=Uuni[:30]), 0.0)
    assert cmd.fallback and "QP not solved" in cmd.info["reason"] and mpc.fallbacks == 1


@pytest.mark.parametrize("veh", [UNICYCLE, BICYCLE], ids=["unicycle", "bicycle"])
def test_pid_tracks_straight_and_curved_references(veh):
    # straight at constant speed, started 0.5 m beside it
    T = 100
    S = np.stack(
        [np.arange(1, T + 31) * 0.8, np.zeros(T + 30), np.full(T + 30, 8.0), np.zeros(T + 30)],
        axis=1,
    )
    errs, cmds = _closed_loop(PIDTracker(), veh, S, np.zeros((T + 30, 2)), [0.0, 0.5, 8.0, 0.0], T)
    assert errs[0] > 0.4 and np.max(errs[50:]) < 0.05, errs[[0, 50, -1]]
    _assert_within_limits(veh, cmds)
    # curved, accelerating and braking: stated error 0.35 m (unicycle) / 0.7 m (bicycle)
    x0, X, _, Uuni = _reference_run(veh)
    pid = PIDTracker()
    errs, cmds = _closed_loop(pid, veh, X, Uuni, x0 + [0.3, -0.3, -0.5, 0.05], 90)
    bound = 0.35 if veh.kind == "unicycle" else 0.7
    assert np.max(errs[30:]) < bound, np.max(errs[30:])
    assert pid.fallbacks == 0
    _assert_within_limits(veh, cmds)


def test_options_and_inputs_are_validated():
    with pytest.raises(SpecError) as e:
        MPCTracker(horizn=10)
    assert e.value.field == "mpc.horizn"
    with pytest.raises(SpecError, match="mpc.horizon"):
        MPCOptions(horizon=0)
    with pytest.raises(SpecError, match="pid.kp_v"):
        PIDTracker(kp_v=-1.0)
    with pytest.raises(SpecError, match="pid.gain"):
        PIDTracker(gain=1.0)
    with pytest.raises(SpecError, match="world.vehicle"):
        MPCTracker().reset(SimpleNamespace(vehicle="bicycle", dt=DT))
    with pytest.raises(SpecError, match="world.dt"):
        PIDTracker().reset(SimpleNamespace(vehicle=BICYCLE, dt=0.0))


@pytest.mark.parametrize(
    "veh", [UNICYCLE, dataclasses.replace(BICYCLE, no_reverse=False)], ids=["unicycle", "bicycle"]
)
def test_mpc_never_plans_to_reverse(veh):
    """A reference that slows to a stop and then drives backwards at 2 m/s, on models that
    could reverse: the MPC's predicted speeds stay >= 0 (to the solver's tolerance) in every
    step, the car stops instead of reversing, and the bound is active (predicted speeds at
    0 while the reference's are negative)."""
    assert not veh.no_reverse  # the model itself would reverse
    t = np.arange(1, 101) * DT
    v = np.maximum(3.0 - 2.0 * t, -2.0)
    x = np.concatenate([[0.0], np.cumsum(v[:-1] * DT)])
    X = np.stack([x, 0 * t, v, 0 * t], axis=1)
    Uuni = np.stack([np.gradient(v, DT), 0 * t], axis=1)
    mpc = MPCTracker()
    mpc.reset(_world(veh))
    state, lowest, active = np.array([0.0, 0.0, 3.0, 0.0]), [], 0
    for k in range(60):
        plan = Plan(t0=k * DT, dt=DT, states=X[k : k + 30], controls=Uuni[k : k + 30])
        cmd = mpc.control(state, plan, k * DT)
        assert not cmd.fallback, cmd.info
        vq = mpc.last["x"][:, 2]
        lowest.append(vq.min())
        active += bool(np.any(np.abs(vq) < 1e-3) and plan.states[:, 2].min() < -0.5)
        state = veh.step(state, cmd.value, DT)
        assert state[2] >= -1e-3, (k, state)
    assert min(lowest) >= -1e-3 and active >= 20
    assert abs(state[2]) < 0.05  # standing, not reversing


def test_applied_commands_set_the_rate_limits_of_the_next_call():
    """A safety filter changed the command: after ``applied(u)`` the next command is within
    one rate step of ``u``, not of the tracker's own last command."""
    veh = BICYCLE
    x0, X, _, Uuni = _reference_run(veh)
    for tracker in (MPCTracker(), PIDTracker()):
        tracker.reset(_world(veh))
        plan = Plan(t0=0.0, dt=DT, states=X[:30], controls=Uuni[:30])
        tracker.control(x0, plan, 0.0)
        tracker.applied(np.array([-4.0, 0.0]))  # the filter braked hard
        plan = Plan(t0=DT, dt=DT, states=X[1:31], controls=Uuni[1:31])
        cmd = tracker.control(veh.step(x0, np.array([-4.0, 0.0]), DT), plan, DT)
        assert abs(cmd.value[0] + 4.0) <= veh.jerk_max * DT + 1e-6
        tracker.applied(np.array([np.nan, 0.0]))  # not a command: ignored
        assert np.all(np.isfinite(tracker.u_prev))
