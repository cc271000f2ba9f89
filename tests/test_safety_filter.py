"""The safety filter (solvers.control.safety): every command it lets through, and every
fallback it certifies, meets its constraints by an independent check (numpy rollout of the
vehicle model, exact rectangle / circle distances, v >= 0); a safe command passes
unchanged; an infeasible situation takes the flagged fallback; the closed loop runs it by
default and reports its interventions."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import norm

from epo_casadi.errors import SpecError
from scenarios.closed_loop import SimConfig, run_episode, summarize
from scenarios.closed_loop.metrics import filter_metrics
from solvers.control.safety import SafetyFilter, SafetyOptions, covering_circles
from solvers.control.track import speed_floor
from solvers.control.types import AgentTask, Command, Estimate, Observation, Plan
from solvers.control.vehicle import VehicleModel

from .helpers import LATE_ACCELERATOR

DT = 0.1
L, W = 5.0, 2.0
#: the plain bicycle (it may reverse), so that v >= 0 is the filter's doing
BICYCLE = VehicleModel.highway(no_reverse=False)
TOL = 1e-9


def _world(vehicle=BICYCLE, n_agents=2, path=None, footprint=(L, W), speed=12.0):
    path = np.array([[-100.0, 0.0], [300.0, 0.0]]) if path is None else path
    return SimpleNamespace(
        vehicle=vehicle,
        dt=DT,
        n_agents=n_agents,
        radii=np.full(n_agents, 1.75),
        footprint=footprint,
        ego_task=AgentTask(path, speed, path[-1], 1.75),
    )


# ------------------------------------------------------------------------- independent check
def _corners(x: np.ndarray) -> np.ndarray:
    """``(4, 2)`` corners of the L x W car at state ``x``."""
    c, s = math.cos(x[3]), math.sin(x[3])
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [L / 2, W / 2]
    return x[:2] + local @ np.array([[c, s], [-s, c]])


def _overlap(A: np.ndarray, B: np.ndarray) -> bool:
    """Separating-axis test of two rectangles (corners ``(4, 2)``, in order)."""
    for poly in (A, B):
        for i in range(4):
            e = poly[(i + 1) % 4] - poly[i]
            n = np.array([-e[1], e[0]])
            pa, pb = A @ n, B @ n
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def _seg_dist(p, a, b) -> float:
    t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * (b - a))))


def box_distance(x: np.ndarray, y: np.ndarray) -> float:
    """Distance between the cars at states ``x`` and ``y`` (``-1`` when they overlap):
    the smallest corner-to-edge distance of two disjoint convex polygons."""
    A, B = _corners(x), _corners(y)
    if _overlap(A, B):
        return -1.0
    d = [
        _seg_dist(p, Q[i], Q[(i + 1) % 4]) for P, Q in ((A, B), (B, A)) for p in P for i in range(4)
    ]
    return min(d)


def circles_distance(x: np.ndarray, y: np.ndarray) -> float:
    """Smallest distance between the two circles of each car minus both radii."""
    off, r = L / 4, math.hypot(L / 4, W / 2)
    cx = [x[:2] + s * off * np.array([math.cos(x[3]), math.sin(x[3])]) for s in (1, -1)]
    cy = [y[:2] + s * off * np.array([math.cos(y[3]), math.sin(y[3])]) for s in (1, -1)]
    return min(float(np.linalg.norm(a - b)) for a in cx for b in cy) - 2 * r


def independent_ok(veh, ego, U, modes, need: float, shape: str = "box") -> tuple[bool, float]:
    """Roll the vehicle forward with the commands ``U`` (numpy ``VehicleModel.rollout``)
    and check ``v >= 0`` and that every constrained mode's car (``modes``: ``(Mc, J, N, 4)``
    on the filter's time grid) stays ``need`` metres away (``box_distance`` /
    ``circles_distance``). Returns the verdict and the smallest margin."""
    X = veh.rollout(ego, U, DT)
    dist = box_distance if shape == "box" else circles_distance
    worst = math.inf
    for mode in modes:
        for agent in mode:
            for k in range(len(X)):
                worst = min(worst, dist(X[k], agent[k]) - need)
    return bool(np.all(X[:, 2] >= -TOL) and worst >= 0.0), worst


# ------------------------------------------------------------------------- situations
def _straight(x0: np.ndarray, K: int) -> np.ndarray:
    """``(K, 4)`` states at ``DT (k + 1)`` of a car going straight at constant speed."""
    t = DT * np.arange(1, K + 1)[:, None]
    h = np.array([math.cos(x0[3]), math.sin(x0[3])])
    out = np.repeat(x0[None], K, axis=0)
    out[:, :2] = x0[:2] + t * x0[2] * h
    return out


def situation(rng: np.random.Generator, K: int = 30):
    """A random scene: the ego on the x axis, one or two other cars with one to three
    constant-velocity modes each, random probabilities, an isotropic position uncertainty,
    a random nominal command inside the box."""
    J = int(rng.integers(1, 3))
    ego = np.array([0.0, rng.uniform(-0.5, 0.5), rng.uniform(0.0, 12.0), rng.uniform(-0.1, 0.1)])
    M = int(rng.integers(1, 4))
    pred = np.zeros((M, J + 1, K, 4))
    pred[:, 0] = _straight(ego, K)
    now = np.zeros((J, 4))
    for j in range(J):
        kind = rng.integers(3)
        if kind == 0:  # ahead in the lane, slower or standing
            x0 = np.array([rng.uniform(6, 40), rng.uniform(-1, 1), rng.uniform(0, 6), 0.0])
        elif kind == 1:  # oncoming, in the next lane or drifting into ours
            x0 = np.array([rng.uniform(15, 60), rng.uniform(-4, 0), rng.uniform(2, 12), math.pi])
        else:  # crossing ahead
            x0 = np.array(
                [rng.uniform(8, 35), rng.uniform(-25, -8), rng.uniform(2, 10), math.pi / 2]
            )
        now[j] = x0
        for m in range(M):
            xm = x0.copy()
            xm[2] *= rng.uniform(0.5, 1.5)
            xm[3] += rng.normal(0, 0.05)
            pred[m, j + 1] = _straight(xm, K)
    prob = rng.dirichlet(np.ones(M))
    sigma = rng.uniform(0.0, 0.3)
    cov = np.zeros((J, 4, 4))
    cov[:, 0, 0] = cov[:, 1, 1] = sigma**2
    lo, hi = BICYCLE.bounds()
    u = rng.uniform(lo, hi) * [1.0, 0.2]
    return ego, now, pred, prob, cov, sigma, u


def _inputs(ego, now, pred, prob, cov, t=0.0):
    J, K = len(now), pred.shape[2]
    plan = Plan(
        t,
        DT,
        pred[0, 0].copy(),
        np.zeros((K, 2)),
        predictions=pred,
        probabilities=prob,
    )
    est = Estimate(now.copy(), cov.copy(), now[:, None].copy(), np.ones((J, 1), bool))
    return Observation(t, ego.copy(), now[:, :2].copy()), est, plan


def _constrained(pred, prob, threshold, N):
    """The modes the filter must constrain against (by probability), on its time grid."""
    w = prob / prob.sum()
    top = int(np.argmax(w))
    keep = [m for m in range(len(w)) if w[m] >= threshold or m == top]
    return pred[keep, 1:, :N]


def _need(sigma, o: SafetyOptions) -> float:
    """The distance every pair must keep: the quantile of an isotropic position std,
    capped, plus the margin (independent of the filter's normals)."""
    return min(norm.ppf(o.quantile) * sigma, o.max_inflation) + o.margin


@pytest.mark.parametrize("shape", ["box", "circles"])
def test_no_command_passes_whose_predicted_state_violates_the_constraints(shape):
    """Random seeded scenes, infeasible ones among them: a command that is not a fallback,
    and a certified fallback, always pass the independent check; an uncertified fallback is
    flagged; the regimes all occur (passed unchanged, changed by the QP, fallbacks of both
    kinds)."""
    rng = np.random.default_rng(7)
    o = SafetyOptions(shape=shape)
    f = SafetyFilter(o)
    seen = {"unchanged": 0, "qp": 0, "certified": 0, "flagged": 0}
    for _ in range(60):
        ego, now, pred, prob, cov, sigma, u = situation(rng)
        f.reset(_world(n_agents=len(now) + 1))
        obs, est, plan = _inputs(ego, now, pred, prob, cov)
        cmd = f.filter(obs, est, plan, Command(u))
        s = cmd.info["safety"]
        U = np.asarray(s["sequence"])
        assert U.shape == (o.horizon, 2) and np.array_equal(cmd.value, U[0])
        lo, hi = BICYCLE.bounds()
        assert np.all(U >= lo - 1e-12) and np.all(U <= hi + 1e-12)
        modes = _constrained(pred, prob, o.threshold, o.horizon)
        assert len(s["modes"]) == len(modes)
        ok, worst = independent_ok(BICYCLE, ego, U, modes, _need(sigma, o), shape)
        if not s["fallback"]:
            assert ok, (worst, s["reason"])
            assert cmd.fallback is False
            seen["unchanged" if not s["intervened"] else "qp"] += 1
            if not s["intervened"]:
                assert np.allclose(cmd.value, np.clip(u, lo, hi), atol=o.tolerance * (hi - lo))
        elif s["certified"]:
            assert ok, (worst, s["reason"])
            assert cmd.fallback and s["intervened"]
            seen["certified"] += 1
        else:
            assert cmd.fallback and s["intervened"] and "not certified" in s["reason"]
            seen["flagged"] += 1
    assert all(v > 0 for v in seen.values()), seen


def test_an_unavoidable_collision_takes_the_flagged_fallback():
    """A standing car 4 m ahead of an ego at 10 m/s: no command avoids it, the QP is
    infeasible, the fallback is taken and flagged, and its sequence indeed fails the
    independent check."""
    o = SafetyOptions()
    f = SafetyFilter(o)
    f.reset(_world())
    ego = np.array([0.0, 0.0, 10.0, 0.0])
    now = np.array([[9.0, 0.0, 0.0, math.pi]])
    pred = np.zeros((1, 2, 30, 4))
    pred[0, 0], pred[0, 1] = _straight(ego, 30), now[0]
    obs, est, plan = _inputs(ego, now, pred, np.ones(1), np.zeros((1, 4, 4)))
    cmd = f.filter(obs, est, plan, Command(np.array([0.0, 0.0])))
    s = cmd.info["safety"]
    assert s["fallback"] and not s["certified"] and cmd.fallback and s["qp"] >= 1
    ok, worst = independent_ok(BICYCLE, ego, s["sequence"], pred[:, 1:, :20], 0.0)
    assert not ok and worst < 0
    assert cmd.value[0] == pytest.approx(BICYCLE.a_min)  # it brakes as hard as it can
    assert f.fallbacks == f.uncertified == 1


def test_a_safe_command_passes_unchanged():
    """Traffic far away, behind the ego going its way, or crossing well after it: the
    nominal command is returned exactly, with no QP solved and no intervention counted."""
    f = SafetyFilter()
    rng = np.random.default_rng(3)
    for far in (
        np.array([[150.0, 0.0, 5.0, 0.0]]),  # far ahead
        np.array([[-12.0, 0.0, 14.0, 0.0]]),  # right behind, going the ego's way
        np.array([[60.0, -40.0, 3.0, math.pi / 2]]),  # crosses long after
    ):
        f.reset(_world())
        ego = np.array([0.0, 0.0, 8.0, 0.0])
        pred = np.zeros((1, 2, 30, 4))
        pred[0, 0], pred[0, 1] = _straight(ego, 30), _straight(far[0], 30)
        u = np.array([rng.uniform(-2, 2), rng.uniform(-0.05, 0.05)])
        obs, est, plan = _inputs(ego, far, pred, np.ones(1), np.zeros((1, 4, 4)))
        cmd = f.filter(obs, est, plan, Command(u, info={"status": "solved"}))
        s = cmd.info["safety"]
        assert np.array_equal(cmd.value, u) and not cmd.fallback
        assert not s["intervened"] and s["qp"] == 0 and s["certified"]
        assert cmd.info["status"] == "solved"  # the tracker's info is kept
    assert f.interventions == 0


def test_the_qp_changes_the_command_only_as_much_as_needed():
    """Accelerating towards a car standing 20 m ahead: the filter brakes (the QP), the
    result passes the independent check, and a command that was already braking hard
    enough is left alone."""
    o = SafetyOptions()
    ego = np.array([0.0, 0.0, 10.0, 0.0])
    now = np.array([[20.0, 0.0, 0.0, math.pi]])
    pred = np.zeros((1, 2, 30, 4))
    pred[0, 0], pred[0, 1] = _straight(ego, 30), now[0]
    obs, est, plan = _inputs(ego, now, pred, np.ones(1), np.zeros((1, 4, 4)))
    f = SafetyFilter(o)
    f.reset(_world())
    f.applied(np.array([1.0, 0.0]))
    cmd = f.filter(obs, est, plan, Command(np.array([1.0, 0.0])))
    s = cmd.info["safety"]
    assert s["intervened"] and not s["fallback"] and s["qp"] >= 1
    assert cmd.value[0] < 1.0 - 0.01
    assert independent_ok(BICYCLE, ego, s["sequence"], pred[:, 1:, :20], 0.0)[0]
    # the QP respects the jerk limit from the command applied last
    assert abs(cmd.value[0] - 1.0) <= BICYCLE.jerk_max * DT + 1e-3
    f.reset(_world())
    f.applied(np.array([-5.0, 0.0]))
    brake = np.array([-5.0, 0.0])
    cmd = f.filter(obs, est, plan, Command(brake))
    assert np.array_equal(cmd.value, brake) and not cmd.info["safety"]["intervened"]


def test_the_fallback_brakes_within_its_lane():
    """On a curved lane, a command that is not a number takes the fallback: braking, its
    sequence certified against a car standing 25 m along the lane, follows the lane (pure
    pursuit): the ego stays within half a lane of the centre line and stops."""
    arc = np.linspace(0, math.pi / 2, 40)
    R = 30.0
    path = np.concatenate([[[-50.0, 0.0]], np.stack([R * np.sin(arc), R - R * np.cos(arc)], 1)])
    f = SafetyFilter(horizon=30)
    f.reset(_world(path=path))
    ego = np.array([0.0, 0.0, 10.0, 0.0])
    a = 25.0 / R
    now = np.array([[R * math.sin(a), R - R * math.cos(a), 0.0, a]])
    pred = np.zeros((1, 2, 30, 4))
    pred[0, 1] = now[0]
    obs, est, plan = _inputs(ego, now, pred, np.ones(1), np.zeros((1, 4, 4)))
    cmd = f.filter(obs, est, plan, Command(np.array([np.nan, 0.0])))
    s = cmd.info["safety"]
    assert s["fallback"] and s["certified"] and "brake" in s["reason"]
    assert independent_ok(BICYCLE, ego, s["sequence"], pred[:, 1:], 0.0)[0]
    X = BICYCLE.rollout(ego, s["sequence"], DT)
    lateral = np.abs(np.hypot(X[:, 0], X[:, 1] - R) - R)  # distance to the arc's centre line
    assert np.all(lateral[X[:, 0] > 0] < 1.75), lateral.max()
    assert X[-1, 2] == pytest.approx(0.0, abs=1e-9) and np.all(X[:, 2] >= -TOL)


def test_the_speed_bound_never_lets_the_ego_reverse():
    """A nominal command that would reverse (braking on through standstill) with nothing
    around: the filter raises it so the speed stops at zero (the plain bicycle, which could
    reverse); the MPC's speed floor after hard braking is the rate-limited highest speed."""
    f = SafetyFilter()
    f.reset(_world(n_agents=1))
    ego = np.array([0.0, 0.0, 0.2, 0.0])
    obs = Observation(0.0, ego, np.zeros((0, 2)))
    est = Estimate(
        np.zeros((0, 4)), np.zeros((0, 4, 4)), np.zeros((0, 1, 4)), np.zeros((0, 1), bool)
    )
    f.applied(np.array([-5.0, 0.0]))
    cmd = f.filter(obs, est, None, Command(np.array([-5.0, 0.0])))
    X = BICYCLE.rollout(ego, cmd.info["safety"]["sequence"], DT)
    assert np.all(X[:, 2] >= -TOL) and cmd.info["safety"]["certified"]
    assert cmd.value[0] == pytest.approx(-2.0)  # stops within the step, not beyond
    # speed_floor: from 0.1 m/s after a = -5 and a jerk limit of 1 m/s^2 per step
    floor = speed_floor(BICYCLE, DT, 15, 0.1, -5.0)
    a_top = np.minimum(5.0, -5.0 + 1.0 * np.arange(1, 16))
    np.testing.assert_allclose(floor, np.minimum(0.0, 0.1 + DT * np.cumsum(a_top)))
    assert floor[0] == pytest.approx(-0.3) and floor[-1] == 0.0
    assert np.all(speed_floor(BICYCLE, DT, 15, 3.0, 0.0) == 0.0)


def test_constant_velocity_constraints_without_predictions():
    """Without a plan (a failed one) the filter constrains against the estimate's
    constant-velocity prediction, and the nominal continuation brakes to a stop: a car
    standing 30 m ahead leaves the command alone, a car coming head-on in the ego's lane
    makes it intervene, and what it lets through passes the independent check against the
    constant-velocity prediction (computed here)."""
    ego = np.array([0.0, 0.0, 10.0, 0.0])
    t = DT * np.arange(1, 21)[:, None]
    for x0, changed in (
        (np.array([30.0, 0.0, 0.0, math.pi]), False),
        (np.array([30.0, 0.0, 12.0, math.pi]), True),
    ):
        f = SafetyFilter()
        f.reset(_world())
        obs, est, _ = _inputs(
            ego, x0[None], np.zeros((1, 2, 30, 4)), np.ones(1), np.zeros((1, 4, 4))
        )
        cmd = f.filter(obs, est, None, Command(np.array([1.0, 0.0])))
        s = cmd.info["safety"]
        assert s["modes"] == ["cv"] and s["intervened"] == changed
        cv = np.repeat(x0[None], 20, axis=0)
        cv[:, :2] += t * x0[2] * np.array([math.cos(x0[3]), math.sin(x0[3])])
        if s["certified"]:
            assert independent_ok(BICYCLE, ego, s["sequence"], cv[None, None], 0.0)[0]
        else:
            assert s["fallback"]
        # the regimes: the standing car leaves a certified nominal sequence; the head-on
        # car (closing at 22 m/s) cannot be avoided: the flagged fallback, which indeed
        # fails the independent check
        assert bool(s["certified"]) is not changed and bool(s["fallback"]) is changed
        if changed:
            assert not independent_ok(BICYCLE, ego, s["sequence"], cv[None, None], 0.0)[0]


def test_a_car_of_unknown_heading_is_kept_off_in_every_heading():
    """A standing car whose estimated heading is 90 degrees off and uncertain (std 1 rad):
    the filter treats it as the disc of all its headings, so the ego, driving at its true
    front, stops clear of the car as it really stands (the independent check with the true
    heading), while a confident estimate with that wrong heading would let it drive on."""
    ego = np.array([0.0, 0.0, 6.0, 0.0])
    true = np.array([15.0, 0.0, 0.0, math.pi])  # its front faces the ego
    wrong = true.copy()
    wrong[3] = math.pi / 2  # as the estimate has it: across the lane
    pred = np.zeros((1, 2, 30, 4))
    pred[0, 0], pred[0, 1] = _straight(ego, 30), wrong
    verdicts = {}
    for sd in (1.0, 0.0):
        cov = np.zeros((1, 4, 4))
        cov[0, 3, 3] = sd**2
        f = SafetyFilter()
        f.reset(_world())
        obs, est, plan = _inputs(ego, wrong[None], pred, np.ones(1), cov)
        cmd = f.filter(obs, est, plan, Command(np.array([0.0, 0.0])))
        s = cmd.info["safety"]
        truth = np.broadcast_to(true, (1, 1, 20, 4))
        verdicts[sd] = independent_ok(BICYCLE, ego, s["sequence"], truth, 0.0)[0]
        if sd:
            assert s["intervened"] and (s["certified"] or s["fallback"])
            rho = math.hypot(L / 2, W / 2)
            np.testing.assert_allclose(f.last["bodies"][0], [0.0, 0.0, rho])
    assert verdicts == {1.0: True, 0.0: False}, verdicts


def test_footprints_and_options():
    off, r = covering_circles(5.0, 2.0)
    assert off == 1.25 and r == pytest.approx(math.sqrt(1.25**2 + 1.0))
    # the two circles cover the rectangle: every corner and side midpoint within r
    for p in ((2.5, 1.0), (0.0, 1.0), (-2.5, -1.0), (1.25, -1.0)):
        assert min(math.hypot(p[0] - s * off, p[1]) for s in (1, -1)) <= r + 1e-12
    with pytest.raises(SpecError, match="filter.shape"):
        SafetyOptions(shape="ellipse")
    with pytest.raises(SpecError, match="filter.horizn"):
        SafetyFilter(horizn=3)
    with pytest.raises(SpecError, match="filter.quantile"):
        SafetyOptions(quantile=1.0)
    with pytest.raises(SpecError, match="before reset"):
        SafetyFilter().filter(None, None, None, Command(np.zeros(2)))


# ------------------------------------------------------------------------- the closed loop
class LaneFollower:
    """A planner that drives its lane at the task's speed and looks at nobody (no
    predictions): whatever keeps it from a collision is the safety filter."""

    K = 30

    def reset(self, world):
        self.path, self.v, self.dt = world.ego_task.path, world.ego_task.speed, world.dt

    def plan(self, obs, est):
        from scenarios.maps import project_to_polyline, resample_at

        s0 = project_to_polyline(obs.ego[None, :2], self.path)[0][0]
        v0 = float(obs.ego[2])
        step = np.clip(self.v - v0, -0.3, 0.2)  # at most 3 / 2 m/s^2 towards the task's speed
        v = v0 + step * np.minimum(
            np.arange(1, self.K + 1), abs(self.v - v0) / max(abs(step), 1e-9)
        )
        p = resample_at(self.path, s0 + np.cumsum(v) * self.dt)
        d = np.diff(np.concatenate([obs.ego[None, :2], p]), axis=0)
        th = np.unwrap(np.concatenate([[obs.ego[3]], np.arctan2(d[:, 1], d[:, 0])]))
        controls = np.stack([np.diff(np.concatenate([[v0], v])), np.diff(th)], axis=1) / self.dt
        return Plan(obs.t, self.dt, np.stack([p[:, 0], p[:, 1], v, th[1:]], 1), controls)


def test_the_filter_prevents_a_collision_with_a_late_accelerator():
    """Seed 4 of the late-accelerator left turn (UKF at 0.3 m noise, MPC): a planner that
    ignores the oncoming car collides without the filter; behind it (the estimate's
    constant-velocity prediction, inflated by its covariance) the ego stops or lets the car
    pass, and reaches the goal."""
    outcomes = {}
    for on in (False, True):
        cfg = SimConfig(
            "left-turn",
            planner="cv",
            tracker="mpc",
            safety_filter=on,
            world_options=LATE_ACCELERATOR,
        )
        world, est, _, tracker = cfg.build()
        r = run_episode(world, est, LaneFollower(), tracker, 4, safety=cfg.build_filter())
        assert world.character.aggressiveness >= 0.8 and r.log.truth[:, 1, 2].max() > 5.0
        outcomes[on] = r
    assert outcomes[False].outcome == "collision"
    assert outcomes[True].outcome == "success", outcomes[True].events[-3:]
    m = outcomes[True].metrics
    assert m["intervention_rate"] > 0 and m["filter_fallbacks"] >= 1


def test_the_loop_filters_by_default_and_reports_interventions():
    cfg = SimConfig("left-turn", planner="cv", tracker="pid", world_options={"max_steps": 15})
    assert cfg.safety_filter and isinstance(cfg.build_filter(), SafetyFilter)
    assert cfg.to_dict()["safety_filter"] is True and cfg.label.endswith("+filter")
    off = SimConfig("left-turn", planner="cv", safety_filter=False)
    assert off.build_filter() is None and off.to_dict()["safety_filter"] is False
    with pytest.raises(SpecError, match="safety_filter"):
        SimConfig("left-turn", safety_filter="yes")
    r = run_episode(*cfg.build(), seed=0, safety=cfg.build_filter())
    m = r.metrics
    assert 0.0 <= m["intervention_rate"] <= 1.0 and m["filter_p99_ms"] > 0
    kinds = {e["kind"] for e in r.events}
    n_events = sum(e["kind"] in ("filter_intervened", "filter_fallback") for e in r.events)
    assert n_events == round(m["intervention_rate"] * m["steps"]), kinds
    plain = run_episode(*off.build(), seed=0)
    assert math.isnan(plain.metrics["intervention_rate"]) and plain.metrics["filter_fallbacks"] == 0


def test_filter_metrics_and_summary():
    steps = [
        {"intervened": False, "fallback": False, "certified": True, "seconds": 0.001},
        {"intervened": True, "fallback": False, "certified": True, "seconds": 0.004},
        {"intervened": True, "fallback": True, "certified": False, "seconds": 0.010},
        {"intervened": True, "fallback": True, "certified": True, "seconds": 0.002},
    ]
    m = filter_metrics(steps)
    assert m["intervention_rate"] == 0.75 and m["filter_fallbacks"] == 2
    assert m["filter_uncertified"] == 1
    assert m["filter_p50_ms"] == pytest.approx(np.percentile([1, 4, 10, 2], 50))
    from scenarios.closed_loop import EpisodeResult

    a = EpisodeResult(0, 0, "success", {"steps": 4, **m, "fallbacks": 2}, [], [1.0])
    b = EpisodeResult(1, 1, "success", {"steps": 12, **filter_metrics(steps[:1] * 12)}, [], [1.0])
    s = summarize([a, b])
    assert s["intervention_rate"] == pytest.approx(3 / 16)  # pooled over the 16 steps
    assert s["filter_fallbacks"] == 2 and s["filter_uncertified"] == 1
    none = filter_metrics(None)
    assert math.isnan(none["intervention_rate"]) and none["filter_fallbacks"] == 0


def test_simulate_runs_the_filter_unless_told_not_to(tmp_path, capsys):
    import csv
    import json

    from scenarios.cli import main

    base = ["simulate", "left-turn", "--planner", "cv", "--tracker", "pid", "--episodes", "1"]
    base += ["--set", "world.max_steps=3", "--no-figures", "--no-progress"]
    rc = main([*base, "--set", "filter.horizn=3", "--out", str(tmp_path / "bad")])
    assert rc == 2 and "filter.horizn: unknown option" in capsys.readouterr().err
    rc = main(
        [*base, "--no-safety-filter", "--set", "filter.horizon=3", "--out", str(tmp_path / "o")]
    )
    assert rc == 2 and "the safety filter is off" in capsys.readouterr().err
    rows = {}
    for flag in ("--safety-filter", "--no-safety-filter"):
        out = tmp_path / flag
        opts = ["--set", "filter.horizon=10"] if flag == "--safety-filter" else []
        assert main([*base, flag, *opts, "--out", str(out)]) == 0
        record = json.loads((out / "config.json").read_text())["config"]
        assert record["safety_filter"] is (flag == "--safety-filter")
        assert ("filter_options" in record) is (flag == "--safety-filter")
        with open(out / "summary.csv") as f:
            rows[flag] = next(csv.DictReader(f))
    assert float(rows["--safety-filter"]["intervention_rate"]) >= 0.0
    assert rows["--no-safety-filter"]["intervention_rate"] == ""  # n/a: no filter ran
    # the filter ran on every step of the filtered run: its per-step times were recorded
    assert math.isfinite(float(rows["--safety-filter"]["filter_p99_ms"]))
    assert rows["--no-safety-filter"]["filter_p99_ms"] == ""
    assert rows["--safety-filter"]["config"].endswith("+filter")
