"""IPOPT on the potential (solvers.ipopt) against independent references.

References: the closed-form least-squares optimum (numpy lstsq on a hand-built matrix),
the independent LM solver on a crossing game with an active collision term, and the
bounds themselves.
"""

from __future__ import annotations

import numpy as np
import pytest

from epo_casadi import Acceleration, AgentSpec, GameSpec, Goal, PotentialGame, SpecError, Velocity
from solvers.ipopt import IpoptOptions, IpoptSolver, _solver_for, ipopt_status, solve_ipopt
from solvers.lm import solve_lm
from solvers.result import Status

from .helpers import crossing_game

K, DT = 10, 0.2
W_GOAL, W_VEL, W_ACC = 2.0, 0.3, 0.5
X0 = [0.5, -0.2, 1.0, 0.4]
R_SUM = 0.25 + 0.25  # radii of the two crossing agents


def di_game() -> PotentialGame:
    agent = AgentSpec(
        "di",
        "double_integrator",
        [Goal(weight=W_GOAL), Velocity(weight=W_VEL), Acceleration(weight=W_ACC)],
        x0=X0,
        goal=[3.0, 1.0],
    )
    return PotentialGame(GameSpec([agent], horizon=K, dt=DT))


def di_reference(goal):
    """Exact minimizer from ``r = A u + b`` built by hand (same derivation as test_lm)."""
    x0, goal = np.asarray(X0), np.asarray(goal, float)
    rows, rhs = [], []
    for c in range(2):
        a = np.zeros(2 * K)
        a[c::2] = W_GOAL * DT**2 * (K - 1 - np.arange(K))
        rows.append(a)
        rhs.append(W_GOAL * (x0[c] + K * DT * x0[2 + c] - goal[c]))
    for k in range(1, K + 1):
        for c in range(2):
            a = np.zeros(2 * K)
            a[c : 2 * k : 2] = W_VEL * DT
            rows.append(a)
            rhs.append(W_VEL * x0[2 + c])
    A = np.vstack([np.array(rows), W_ACC * np.eye(2 * K)])
    b = np.concatenate([rhs, np.zeros(2 * K)])
    u = np.linalg.lstsq(A, -b, rcond=None)[0]
    return u, 0.5 * np.sum((A @ u + b) ** 2)


def straight_start(g):
    """Both agents accelerate straight at each other (1 m/s^2): they pass through each other."""
    return g.join_controls([np.tile([1.0, 0.0], (g.K, 1)) for _ in range(g.N)])


def min_distance(g, x):
    pos = g.positions(x)
    return float(np.min(np.linalg.norm(pos[0] - pos[1], axis=-1)))


@pytest.mark.parametrize("hessian", ["exact", "gn"])
def test_ipopt_reaches_closed_form_optimum(hessian):
    g = di_game()
    goal = [2.0, -1.5]
    u_ref, e_ref = di_reference(goal)
    res = solve_ipopt(g, g.default_params(goal__di=goal), options={"hessian": hessian})
    assert res.status is Status.CONVERGED
    assert res.info["return_status"] == "Solve_Succeeded"
    np.testing.assert_allclose(res.controls, u_ref, atol=1e-7)
    np.testing.assert_allclose(res.energy, e_ref, rtol=1e-10)


def test_lm_and_ipopt_agree_with_active_collision():
    g = crossing_game(offset=0.3)
    p = g.default_params()
    u0 = straight_start(g)
    coll = [t.index for t in g.terms if t.feature_type == "collision"]
    assert len(coll) == 1
    e0 = np.asarray(g.function("term_energies")(u0, p)).ravel()
    assert e0[coll[0]] > 1.0  # the collision term is active at the start
    assert min_distance(g, g.function("rollout")(u0, p).full().ravel()) < 0.5 * R_SUM

    ip = solve_ipopt(g, p, u0)
    lm = solve_lm(g, p, u0)
    assert ip.status is Status.CONVERGED and lm.status is Status.CONVERGED
    # measured: controls 3.8e-6 apart (LM stops by ftol), states 2.4e-6, energies 3e-12
    np.testing.assert_allclose(lm.controls, ip.controls, atol=2e-5)
    np.testing.assert_allclose(lm.states, ip.states, atol=2e-5)
    np.testing.assert_allclose(lm.energy, ip.energy, rtol=1e-10)
    # soft collision penalty (weight 10): a few cm of overlap at most
    assert min_distance(g, ip.states) >= R_SUM - 0.05
    np.testing.assert_allclose(
        ip.states, g.function("rollout")(ip.controls, p).full().ravel(), atol=1e-12
    )

    # without the collision term the same start leads to a solution that collides
    p0 = g.params.pack({"w.a0-a1.collision": 0.0})
    free = solve_ipopt(g, p0, u0)
    assert free.status is Status.CONVERGED
    assert min_distance(g, free.states) < R_SUM - 0.2


def test_energy_history_and_warm_start():
    g = crossing_game(offset=0.3)
    p = g.default_params()
    u0 = straight_start(g)
    res = solve_ipopt(g, p, u0)
    assert res.energy_history[0] == pytest.approx(float(g.function("energy")(u0, p)), rel=1e-12)
    assert res.energy_history[-1] == pytest.approx(float(res.energy), rel=1e-10)
    assert res.energy_history.shape == (int(res.iterations) + 1,)
    warm = solve_ipopt(g, p, res.controls)
    assert warm.status is Status.CONVERGED
    assert warm.iterations <= 2 < res.iterations
    np.testing.assert_allclose(warm.controls, res.controls, atol=1e-7)


def test_control_bounds_are_hard():
    g = crossing_game(offset=0.3)
    p = g.default_params()
    u0 = straight_start(g)
    free = solve_ipopt(g, p, u0)
    acc_free = max(np.abs(c[:, 0]).max() for c in g.split_controls(free.controls))
    assert acc_free > 1.0  # unconstrained solution violates |a| <= 0.5
    bounds = {"a0": ([-0.5, -0.3], [0.5, 0.3]), "a1": ([-0.5, None], [0.5, np.inf])}
    res = solve_ipopt(g, p, u0, {"control_bounds": bounds})
    assert res.status is Status.CONVERGED
    tol = 1e-6  # IPOPT relaxes bounds by ~1e-8
    for c, (lo, hi) in zip(
        g.split_controls(res.controls),
        [([-0.5, -0.3], [0.5, 0.3]), ([-0.5, -np.inf], [0.5, np.inf])],
        strict=True,
    ):
        assert np.all(c >= np.array(lo) - tol) and np.all(c <= np.array(hi) + tol)
        assert np.isclose(np.abs(c[:, 0]).max(), 0.5, atol=tol)  # active
    assert res.info["max_violation"] <= tol
    assert res.energy > free.energy


def test_state_bounds_are_hard_constraints():
    g = crossing_game(offset=0.3)
    p = g.default_params()
    u0 = straight_start(g)
    free = solve_ipopt(g, p, u0)
    assert max(s[:, 2].max() for s in g.split_states(free.states)) > 1.9  # the soft bound allows 2
    vmax = {n: ([None, None, 0.0, None], [None, None, 1.5, None]) for n in ("a0", "a1")}
    for hessian in ("exact", "gn"):
        res = solve_ipopt(g, p, u0, {"state_bounds": vmax, "hessian": hessian})
        assert res.status is Status.CONVERGED
        speeds = np.concatenate([s[1:, 2] for s in g.split_states(res.states)])
        assert speeds.max() <= 1.5 + 1e-6 and speeds.min() >= -1e-6
        assert speeds.max() == pytest.approx(1.5, abs=1e-6)  # active
    ex = solve_ipopt(g, p, u0, {"state_bounds": vmax})
    np.testing.assert_allclose(res.controls, ex.controls, atol=1e-5)  # gn and exact agree


def test_infeasible_and_max_iter_statuses():
    g = crossing_game(offset=0.3)
    p = g.default_params()
    u0 = straight_start(g)
    # |a| <= 0.1 cannot bring the speed from 1 to >= 2 within the first step
    opts = {
        "control_bounds": {"a0": ([-0.1, -1.0], [0.1, 1.0])},
        "state_bounds": {"a0": ([None, None, 2.0, None], [None] * 4)},
    }
    res = solve_ipopt(g, p, u0, opts)
    assert res.status is Status.INFEASIBLE
    assert res.info["return_status"] == "Infeasible_Problem_Detected"
    res = solve_ipopt(g, p, u0, {"max_iter": 2})
    assert res.status is Status.MAX_ITER
    assert int(res.iterations) == 2 and res.energy_history.shape == (3,)


def test_status_mapping():
    assert ipopt_status("Solve_Succeeded") is Status.CONVERGED
    assert ipopt_status("Solved_To_Acceptable_Level") is Status.CONVERGED
    assert ipopt_status("Maximum_Iterations_Exceeded") is Status.MAX_ITER
    assert ipopt_status("Infeasible_Problem_Detected") is Status.INFEASIBLE
    assert ipopt_status("Invalid_Number_Detected") is Status.NONFINITE
    assert ipopt_status("Restoration_Failed") is Status.FAILED


def test_batch_equals_one_by_one():
    g = di_game()
    goals = [[2.0, -1.5], [3.0, 1.0], [-1.0, 0.5]]
    P = np.stack([g.default_params(goal__di=q) for q in goals])
    res = solve_ipopt(g, P)
    assert res.controls.shape == (3, g.n_u) and res.status.shape == (3,)
    assert list(res.info["return_status"]) == ["Solve_Succeeded"] * 3
    for b, q in enumerate(goals):
        one = solve_ipopt(g, P[b])
        np.testing.assert_allclose(res.controls[b], one.controls, atol=1e-12)
        np.testing.assert_allclose(res.controls[b], di_reference(q)[0], atol=1e-7)
        assert res[b].info["return_status"] == "Solve_Succeeded"


def test_nlp_is_built_once_per_game_and_options():
    g = di_game()
    a = _solver_for(g, IpoptOptions(tol=1e-9))
    assert _solver_for(g, IpoptOptions(tol=1e-9)) is a
    assert _solver_for(g, IpoptOptions(tol=1e-7)) is not a
    solver = IpoptSolver(g, {"max_iter": 50})
    r1, r2 = solver.solve(g.default_params()), solver.solve(g.default_params(goal__di=[0.0, 0.0]))
    assert r1.status is Status.CONVERGED and r2.status is Status.CONVERGED
    assert not np.allclose(r1.controls, r2.controls)


@pytest.mark.parametrize(
    "options, field",
    [
        ({"maxiter": 10}, "ipopt"),
        ({"hessian": "bfgs"}, "ipopt.hessian"),
        ({"tol": 0.0}, "ipopt.tol"),
        ({"print_level": 13}, "ipopt.print_level"),
        ({"control_bounds": {"a0": ([1.0, 0.0], [0.0, 1.0])}}, "ipopt.control_bounds['a0']"),
        ({"control_bounds": {"a0": ([0.0], [1.0, 1.0])}}, "ipopt.control_bounds['a0']"),
        (
            {"control_bounds": {"a0": ([float("nan"), 0.0], [1.0, 1.0])}},
            "ipopt.control_bounds['a0'].lower[0]",
        ),
        ({"state_bounds": [1, 2]}, "ipopt.state_bounds"),
    ],
)
def test_bad_options_raise(options, field):
    g = di_game()
    with pytest.raises(SpecError) as e:
        solve_ipopt(g, g.default_params(), options=options)
    assert e.value.field == field


@pytest.mark.parametrize(
    "bounds, field",
    [
        ({"robot": ([0.0, 0.0], [1.0, 1.0])}, "ipopt.control_bounds['robot']"),  # unknown agent
        ({"di": ([0.0], [1.0])}, "ipopt.control_bounds['di']"),  # double integrator has 2 controls
    ],
)
def test_bounds_checked_against_game(bounds, field):
    g = di_game()
    with pytest.raises(SpecError) as e:
        solve_ipopt(g, g.default_params(), options={"control_bounds": bounds})
    assert e.value.field == field


def test_nan_in_p_raises_spec_error_naming_p():
    g = di_game()
    p = g.default_params()
    p[g.params["w.di.velocity"].start] = np.inf
    with pytest.raises(SpecError) as e:
        solve_ipopt(g, p)
    assert e.value.field == "p"


def test_exact_hessian_of_the_lagrangian_matches_finite_differences():
    """The Hessian handed to IPOPT (the Jacobian of the gradient of ``lam_f E + lam_g' g``)
    against central differences of the gradient, in float64, on a crossing game with an
    active collision and a bounded state (its constraint curvature included)."""
    import casadi as ca

    from solvers.ipopt import _build_hessian

    g = crossing_game(N=2, K=30, offset=0.3)
    p = g.default_params()
    solver = IpoptSolver(g, {"state_bounds": {"a0": ([None, None, 0.0, None], [None] * 4)}})
    cons = solver._g
    hess = _build_hessian(g, cons, "exact")
    sym = g.symbols
    lam_f, lam_g = 0.7, np.linspace(-1.0, 1.0, cons.shape[0])
    grad = ca.Function(
        "gl", [sym["u"], sym["p"]], [ca.gradient(lam_f * sym["E"] + ca.dot(lam_g, cons), sym["u"])]
    )
    u = np.random.default_rng(3).normal(scale=0.05, size=g.n_u)
    te = np.asarray(g.function("term_energies")(u, p)).ravel()
    assert sum(te[t.index] for t in g.terms if t.feature_type == "collision") > 1e-3
    H = np.asarray(hess(u, p, lam_f, lam_g).full())
    h = 1e-5
    fd = np.empty((g.n_u, g.n_u))
    for j in range(g.n_u):
        e = np.zeros(g.n_u)
        e[j] = h
        fd[:, j] = (np.asarray(grad(u + e, p)) - np.asarray(grad(u - e, p))).ravel() / (2 * h)
    np.testing.assert_allclose(H, np.triu(fd), rtol=0, atol=1e-6 * max(1.0, np.abs(fd).max()))
    assert np.abs(np.triu(fd, 1)).max() > 1e-3  # the coupling blocks are not trivially zero
