"""The game oracle and the constant-velocity planner (solvers.control.plan).

References computed another way: an independent IPOPT solve of the same game (oracle), the
full game solved by IPOPT with the others' controls pinned to zero by bounds (CV best
response), hand-made polylines (path windows)."""

from __future__ import annotations

import numpy as np
import pytest

from epo_casadi.errors import SpecError
from solvers import Status, solve_ipopt
from solvers.control.plan import (
    ConstantVelocityPlanner,
    GameOracle,
    PlannerOptions,
    path_window,
)
from solvers.control.types import AgentTask, Estimate, Observation, Plan


def turn_path() -> np.ndarray:
    """Northbound at x = 1.75, a left quarter turn of radius 6.75 m, westbound at y = 1.75."""
    th = np.linspace(0.0, np.pi / 2, 12)
    arc = np.array([-5.0, -5.0]) + 6.75 * np.stack([np.cos(th), np.sin(th)], axis=1)
    return np.concatenate([[[1.75, -60.0]], arc, [[-60.0, 1.75]]])


class TwoCarScene:
    """A planner's view of a left turn across an oncoming car (no dynamics needed)."""

    dt = 0.1
    n_agents = 2
    radii = np.array([1.5, 1.5])
    max_steps = 10

    def __init__(self):
        self.ego_task = AgentTask(turn_path(), 8.0, np.array([-60.0, 1.75]), 1.5)
        line = np.array([[-1.75, 80.0], [-1.75, -80.0]])
        self._tasks = [self.ego_task, AgentTask(line, 10.0, line[-1], 1.5)]
        self.x = np.array([[1.75, -12.0, 6.0, np.pi / 2], [-1.75, 14.0, 8.0, -np.pi / 2]])

    def tasks(self):
        return self._tasks

    def observe(self):
        est = Estimate(self.x[1:], np.zeros((1, 4, 4)), self.x[1:, None], np.ones((1, 1), bool))
        return Observation(0.0, self.x[0].copy(), self.x[1:, :2].copy()), est


def test_options_reject_unknown_and_bad_values():
    with pytest.raises(SpecError, match="unknown option"):
        PlannerOptions.from_dict({"horizn": 10})
    with pytest.raises(SpecError, match="planner.horizon"):
        PlannerOptions(horizon=1)
    with pytest.raises(SpecError, match="planner.backend"):
        PlannerOptions(backend="sparse")


def test_path_window_spacing_and_extension():
    line = np.array([[0.0, 0.0], [10.0, 0.0]])
    w = path_window(line, np.array([4.0, 3.0]), behind=2.0, ahead=16.0, n=10)
    # projection at s = 4; equally spaced from s = 2 to s = 20, straight beyond the end
    np.testing.assert_allclose(w[:, 0], np.linspace(2.0, 20.0, 10))
    np.testing.assert_allclose(w[:, 1], 0.0)
    corner = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0]])
    w = path_window(corner, np.array([0.0, 1.0]), behind=0.0, ahead=7.0, n=8)
    np.testing.assert_allclose(w[:6], np.stack([np.arange(6.0), np.zeros(6)], axis=1), atol=1e-12)
    np.testing.assert_allclose(w[6:], [[5.0, 1.0], [5.0, 2.0]], atol=1e-12)


def _collision_energy(game, u, p) -> float:
    e = np.asarray(game.function("term_energies")(u, p)).reshape(-1)
    return float(sum(e[t.index] for t in game.terms if t.feature_type == "collision"))


def test_oracle_step0_equals_independent_ipopt_solve():
    """The oracle's plan is an equilibrium of its game by an independent solver: IPOPT,
    started from the plan perturbed by 0.05 (seeded), returns to it (to 1e-5) with the same
    energy. (From the zero start IPOPT may reach another local equilibrium than LM, so the
    reference starts near the plan, not at the oracle's start.)"""
    scene = TwoCarScene()
    oracle = GameOracle({"gtol": 1e-10, "first_steps": 300})
    oracle.reset(scene)
    obs, est = scene.observe()
    plan = oracle.plan(obs, est)
    assert plan.ok, plan.message
    g, p, u = oracle.game, oracle.last_params, oracle._u
    start = u + 0.05 * np.random.default_rng(0).standard_normal(u.shape)
    ref = solve_ipopt(g, p, start, {"tol": 1e-10, "acceptable_iter": 0, "max_iter": 1000})
    assert ref.status is Status.CONVERGED
    assert np.max(np.abs(start - ref.controls)) > 1e-2  # IPOPT had work to do
    u_ref = g.split_controls(ref.controls)[0]
    # the regime: the two cars interact in the solution (collision term active)
    assert _collision_energy(g, ref.controls, p) > 1e-6
    assert plan.info["energy"] == pytest.approx(float(ref.energy), rel=1e-9)
    np.testing.assert_allclose(plan.controls, u_ref, atol=1e-5)
    ref_states = np.stack(g.split_states(ref.states))[:, 1:]
    np.testing.assert_allclose(plan.states, ref_states[0], atol=1e-5)
    np.testing.assert_allclose(plan.predictions[0], ref_states, atol=1e-5)
    assert plan.predictions.shape[1:] == (2, g.K, 4)
    np.testing.assert_allclose(plan.probabilities.sum(), 1.0)
    # the plan's states are the rollout of its controls from the exact ego state
    x = obs.ego.copy()
    for k in range(g.K):
        a, w = plan.controls[k]
        x = x + scene.dt * np.array([x[2] * np.cos(x[3]), x[2] * np.sin(x[3]), a, w])
        np.testing.assert_allclose(plan.states[k], x, atol=1e-9)


def test_cv_plan_is_the_best_response_to_constant_velocity():
    scene = TwoCarScene()
    cv = ConstantVelocityPlanner()
    cv.reset(scene)
    obs, est = scene.observe()
    plan = cv.plan(obs, est)
    assert plan.ok, plan.message
    g, p = cv.game, cv.last_params
    # the others predicted at constant velocity: a straight line at their speed
    other = plan.predictions[0, 1]
    k = np.arange(1, g.K + 1) * scene.dt
    np.testing.assert_allclose(other[:, 1], scene.x[1, 1] - scene.x[1, 2] * k, atol=1e-9)
    np.testing.assert_allclose(other[:, 2], scene.x[1, 2])
    # reference: the full game by IPOPT with the others' controls pinned to 0 by bounds
    pinned = {"a1": ([0.0, 0.0], [0.0, 0.0])}
    ref = solve_ipopt(
        g, p, cv.last_u0, {"control_bounds": pinned, "tol": 1e-12, "acceptable_iter": 0}
    )
    assert ref.status is Status.CONVERGED
    assert _collision_energy(g, ref.controls, p) > 1e-6
    np.testing.assert_allclose(plan.controls, g.split_controls(ref.controls)[0], atol=1e-5)
    # stationary in the ego's controls: the gradient of the potential vanishes there
    u = g.join_controls([plan.controls, np.zeros((g.K, 2))])
    grad = np.asarray(g.function("gradient")(u, p)).reshape(-1)
    assert np.max(np.abs(grad[: g.K * 2])) < 1e-5
    # and the ego's own cost C_0 moves by the same amount as the potential when the ego
    # deviates (potential game): only the ego's terms depend on its controls
    du = np.zeros_like(u)
    du[:4] = 0.05
    C = g.function("agent_costs")
    E = g.function("energy")
    dC0 = float(C(u + du, p)[0] - C(u, p)[0])
    dE = float(E(u + du, p) - E(u, p))
    assert dC0 == pytest.approx(dE, rel=1e-9, abs=1e-12)


def test_failures_give_not_ok_plans_never_raise():
    scene = TwoCarScene()
    oracle = GameOracle()
    obs, est = scene.observe()
    assert not oracle.plan(obs, est).ok  # before reset
    oracle.reset(scene)
    bad = Observation(0.0, np.array([np.nan, 0.0, 0.0, 0.0]), obs.others)
    plan = oracle.plan(bad, est)
    assert isinstance(plan, Plan) and not plan.ok and "ego state" in plan.message
    assert np.all(np.isnan(plan.states)) and plan.states.shape == (oracle.game.K, 4)
    # an agent never observed (NaN estimate) is left out, the plan is still made
    nan_est = Estimate(np.full((1, 4), np.nan), est.covariances, est.history, est.valid)
    plan = oracle.plan(obs, nan_est)
    assert plan.ok and plan.info["absent"] == [1]
    assert np.all(np.isfinite(plan.states))


def test_oracle_warm_start_is_the_shifted_previous_solution():
    scene = TwoCarScene()
    oracle = GameOracle()
    oracle.reset(scene)
    obs, est = scene.observe()
    oracle.plan(obs, est)
    prev = oracle.game.split_controls(oracle._u)
    starts = oracle.starts(obs.ego)
    warm = oracle.game.split_controls(starts[0])
    for a, b in zip(prev, warm, strict=True):
        np.testing.assert_array_equal(b[:-1], a[1:])
        np.testing.assert_array_equal(b[-1], a[-1])


def test_inscribed_circles_lie_in_the_footprint_and_reach_its_ends():
    from solvers.control.plan import inscribed_circles

    off, r = inscribed_circles((5.0, 2.0))
    assert (off, r) == (1.5, 1.0)
    # every point of the two circles is inside the 5 m x 2 m rectangle, and the front and
    # rear ends and the sides at the centres touch a circle (the stadium inscribed in it)
    a = np.linspace(0.0, 2 * np.pi, 721)
    for s in (1.0, -1.0):
        x, y = s * off + r * np.cos(a), r * np.sin(a)
        assert np.all(np.abs(x) <= 2.5 + 1e-12) and np.all(np.abs(y) <= 1.0 + 1e-12)
    for p in ((2.5, 0.0), (-2.5, 0.0), (1.5, 1.0), (-1.5, -1.0)):
        assert min(np.hypot(p[0] - s * off, p[1]) for s in (1, -1)) == pytest.approx(r)
    with pytest.raises(SpecError, match="world.footprint.length"):
        inscribed_circles((1.0, 2.0))  # shorter than wide
    with pytest.raises(SpecError, match="world.footprint"):
        inscribed_circles("5x2")
