"""iLQ feedback Nash game solver (solvers.ilq) against independent references.

References: (a) a coupled Riccati recursion for LQ games written here in the textbook form
(Basar & Olsder, Dynamic Noncooperative Game Theory, Cor. 6.1, augmented with a constant
state for the affine terms); (b) finite differences of each player's closed-loop cost,
with a plain-numpy unicycle rollout; (c) the potential minimizer of solvers.lm.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from epo_casadi import (
    Acceleration,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    Jerk,
    PotentialGame,
    SpecError,
    TurnRate,
    Velocity,
)
from solvers.feedback_nash import FeedbackNashOptions, feedback_nash_check
from solvers.ilq import (
    ILQOptions,
    ILQSolver,
    from_stages,
    get_solver,
    solve_ilq,
    to_stages,
)
from solvers.ilq.iteration import _secant_step
from solvers.ilq.kinks import _smooth_kinks
from solvers.lm import solve_lm
from solvers.result import Status

from .helpers import crossing_game, family_spec

# --------------------------------------------------------------------------------------
# (a) an LQ game that is not a potential game: exact feedback Nash in one iteration
# --------------------------------------------------------------------------------------
K_LQ, DT_LQ = 12, 0.2


def lq_data():
    """Joint dynamics (A, B_0, B_1) of two double integrators and each player's cost matrices.

    Player i pays ``sum_{k=1..K} 1/2 x_k'Q_i x_k + q_i'x_k`` and
    ``sum_{k=0..K-1} sum_j 1/2 u_j,k' R_ij u_j,k``. The Q's couple the two agents with
    different weights and a state cross term, R_01 and R_10 penalize the other player's
    control: the mixed second derivatives differ, so no potential exists.
    """
    a = np.block([[np.eye(2), DT_LQ * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    b = np.vstack([np.zeros((2, 2)), DT_LQ * np.eye(2)])
    A = np.kron(np.eye(2), a)
    B = [np.vstack([b, np.zeros((4, 2))]), np.vstack([np.zeros((4, 2)), b])]
    pos = [
        np.hstack([np.eye(2), np.zeros((2, 6))]),
        np.hstack([np.zeros((2, 4)), np.eye(2), np.zeros((2, 2))]),
    ]
    vel = [
        np.hstack([np.zeros((2, 2)), np.eye(2), np.zeros((2, 4))]),
        np.hstack([np.zeros((2, 6)), np.eye(2)]),
    ]
    g0, g1, d0 = np.array([5.0, 1.0]), np.array([-1.0, 2.0]), np.array([0.5, 0.0])
    rel = pos[0] - pos[1]
    Q0 = 0.3 * pos[0].T @ pos[0] + 0.8 * rel.T @ rel + 0.1 * vel[0].T @ vel[0]
    q0 = -0.3 * pos[0].T @ g0 - 0.8 * rel.T @ d0
    Q1 = 0.5 * pos[1].T @ pos[1] + 0.2 * rel.T @ rel + 0.05 * vel[1].T @ vel[1]
    e_vx1, e_vy0 = np.eye(8)[6], np.eye(8)[3]
    Q1 = Q1 + 0.1 * (np.outer(e_vx1, e_vy0) + np.outer(e_vy0, e_vx1))  # 0.1 * vx_b * vy_a
    q1 = -0.5 * pos[1].T @ g1
    R = {
        (0, 0): np.eye(2),
        (0, 1): 0.2 * np.eye(2),
        (1, 1): 2.0 * np.eye(2),
        (1, 0): np.diag([0.1, 0.0]),
    }
    return A, B, [Q0, Q1], [q0, q1], R


def lq_game_and_costs():
    agents = [
        AgentSpec("a", "double_integrator", [Acceleration()], x0=[0.0, 0.0, 1.0, 0.0]),
        AgentSpec("b", "double_integrator", [Acceleration()], x0=[4.0, 1.0, -1.0, 0.5]),
    ]
    game = PotentialGame(GameSpec(agents, [], horizon=K_LQ, dt=DT_LQ))
    _, _, Q, q, R = lq_data()
    x = ca.SX.sym("x", game.n_x)
    u = ca.SX.sym("u", game.n_u)
    p = ca.SX.sym("p", game.n_p)
    Xs = [ca.reshape(x[game.xoff[i] : game.xoff[i + 1]], 4, K_LQ + 1) for i in range(2)]
    Us = [ca.reshape(u[game.uoff[i] : game.uoff[i + 1]], 2, K_LQ) for i in range(2)]
    C = [0, 0]
    for i in range(2):
        for k in range(1, K_LQ + 1):
            xk = ca.vertcat(Xs[0][:, k], Xs[1][:, k])
            C[i] += 0.5 * ca.bilin(ca.DM(Q[i]), xk, xk) + ca.dot(ca.DM(q[i]), xk)
        for k in range(K_LQ):
            for j in range(2):
                C[i] += 0.5 * ca.bilin(ca.DM(R[(i, j)]), Us[j][:, k], Us[j][:, k])
    costs = ca.Function("lq_costs", [x, u, p], [ca.vertcat(*C)], ["x", "u", "p"], ["C"])
    return game, costs


def textbook_feedback_nash(x0):
    """Feedback Nash gains and trajectory of the LQ game by the coupled Riccati recursion.

    Augmented state ``z = (x, 1)``: ``z+ = At z + sum_j Bt_j u_j``, player i's state cost
    ``1/2 z'Qt_i z``. Backward from ``Z_i,K = Qt_i``: solve for every ``P_j``
    ``(R_ii + Bt_i'Z_i Bt_i) P_i + Bt_i'Z_i sum_{j!=i} Bt_j P_j = Bt_i'Z_i At``, then
    ``F = At - sum_j Bt_j P_j``, ``Z_i <- F'Z_i F + sum_j P_j'R_ij P_j + Qt_i``.
    Policy ``u_j,k = -P_j,k z_k``.
    """
    A, B, Q, q, R = lq_data()
    nx = A.shape[0]
    At = np.eye(nx + 1)
    At[:nx, :nx] = A
    Bt = [np.vstack([b, np.zeros((1, 2))]) for b in B]
    Qt = []
    for i in range(2):
        m = np.zeros((nx + 1, nx + 1))
        m[:nx, :nx], m[:nx, nx], m[nx, :nx] = Q[i], q[i], q[i]
        Qt.append(m)
    Z = [Qt[0].copy(), Qt[1].copy()]
    gains = [None] * K_LQ
    for k in range(K_LQ - 1, -1, -1):
        lhs = np.zeros((4, 4))
        rhs = np.zeros((4, nx + 1))
        for i in range(2):
            ri = slice(2 * i, 2 * i + 2)
            for j in range(2):
                blk = Bt[i].T @ Z[i] @ Bt[j]
                if i == j:
                    blk = blk + R[(i, i)]
                lhs[ri, 2 * j : 2 * j + 2] = blk
            rhs[ri] = Bt[i].T @ Z[i] @ At
        Pk = np.linalg.solve(lhs, rhs)
        P = [Pk[0:2], Pk[2:4]]
        F = At - Bt[0] @ P[0] - Bt[1] @ P[1]
        Z = [
            F.T @ Z[i] @ F + sum(P[j].T @ R[(i, j)] @ P[j] for j in range(2)) + Qt[i]
            for i in range(2)
        ]
        gains[k] = Pk
    z = np.r_[x0, 1.0]
    xs, us = [z[:nx]], []
    for k in range(K_LQ):
        u = -gains[k] @ z
        z = At @ z + Bt[0] @ u[:2] + Bt[1] @ u[2:]
        xs.append(z[:nx])
        us.append(u)
    return np.array(gains), np.array(xs), np.array(us)


@pytest.fixture(scope="module")
def lq():
    game, costs = lq_game_and_costs()
    return game, costs, game.default_params()


def test_lq_game_is_not_a_potential_game(lq):
    """Regime check: d2C_0/du_0du_1 != d2C_1/du_0du_1, which a potential game would need."""
    game, costs, p = lq
    u = ca.SX.sym("u", game.n_u)
    C = costs(game.function("rollout")(u, p), u, p)
    H0, H1 = (
        np.array(ca.Function("h", [u], [ca.hessian(C[i], u)[0]])(np.zeros(game.n_u)))
        for i in range(2)
    )
    u0s, u1s = slice(game.uoff[0], game.uoff[1]), slice(game.uoff[1], game.uoff[2])
    assert np.max(np.abs(H0[u0s, u1s] - H1[u0s, u1s])) > 1e-2


def test_lq_game_exact_feedback_nash_in_one_iteration(lq):
    game, costs, p = lq
    rng = np.random.default_rng(3)
    u0 = rng.normal(size=game.n_u)  # any start: one Newton-exact step on an LQ game
    res = solve_ilq(game, p, u0, options={"tol": 1e-9}, costs=costs)
    assert res.status is Status.CONVERGED and res.iterations == 1
    assert res.info["hessian"] == "exact" and res.info["custom_costs"]
    assert np.isnan(res.energy) and res.info["max_regularization"] == 0.0
    x0 = np.r_[game.agents[0].x0, game.agents[1].x0]
    gains, xs, us = textbook_feedback_nash(x0)
    X, U = to_stages(game, res.states, res.controls)
    np.testing.assert_allclose(res.info["gains"], gains[:, :, :8], rtol=1e-9, atol=1e-9)
    assert np.max(np.abs(res.info["feedforward"])) < 1e-9
    np.testing.assert_allclose(X, xs, atol=1e-9)
    np.testing.assert_allclose(U, us, atol=1e-9)
    # the returned costs are the custom ones at the solution
    np.testing.assert_allclose(
        res.agent_costs, np.asarray(costs(res.states, res.controls, p)).ravel()
    )


def test_lq_game_compiled_riccati_matches_numpy(lq, monkeypatch, tmp_path):
    pytest.importorskip("solvers.codegen")
    from solvers.codegen import CompilerError, find_compiler

    try:
        find_compiler()
    except CompilerError:
        pytest.skip("no C compiler")
    monkeypatch.setenv("EPO_CACHE_DIR", str(tmp_path))
    game, costs, p = lq
    a = solve_ilq(game, p, options={"tol": 1e-9}, costs=costs)
    solver = ILQSolver(game, costs)
    b = solver.solve(p, options={"tol": 1e-9, "compiled": True})
    assert b.info["backend"] == "compiled" and b.iterations == 1
    np.testing.assert_allclose(b.info["gains"], a.info["gains"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(b.controls, a.controls, atol=1e-10)


def test_nonconvex_own_cost_is_regularized_and_reported(lq):
    """A player with a concave own-control cost: its own block gets a reported shift."""
    game, _, p = lq
    x, u, pp = ca.SX.sym("x", game.n_x), ca.SX.sym("u", game.n_u), ca.SX.sym("p", game.n_p)
    u1 = u[game.uoff[1] : game.uoff[2]]
    goal = x[game.xoff[1] + K_LQ * 4 : game.xoff[1] + K_LQ * 4 + 2]
    C0 = 0.5 * ca.sumsqr(u[: game.uoff[1]]) + 0.5 * ca.sumsqr(x[K_LQ * 4 : K_LQ * 4 + 2] - 1)
    C1 = -0.5 * ca.sumsqr(u1) + 0.5 * ca.sumsqr(goal)  # concave in u_1 at every stage
    costs = ca.Function("nc", [x, u, pp], [ca.vertcat(C0, C1)])
    res = solve_ilq(game, p, options={"max_iter": 3}, costs=costs)
    assert res.info["max_regularization"] > 0.5  # at least the concavity 1 minus margin
    assert np.all(res.info["regularization"][:, 1] > 0) and np.all(np.isfinite(res.controls))


# --------------------------------------------------------------------------------------
# (b) robot-pedestrian crossing: feedback Nash first-order conditions
# --------------------------------------------------------------------------------------
def unicycle_step(x, u, dt):
    """Explicit Euler of the dynamically extended unicycle, written independently."""
    out = np.empty_like(x)
    for i in range(x.size // 4):
        px, py, v, th = x[4 * i : 4 * i + 4]
        a, w = u[2 * i : 2 * i + 2]
        out[4 * i : 4 * i + 4] = [
            px + v * np.cos(th) * dt,
            py + v * np.sin(th) * dt,
            v + a * dt,
            th + w * dt,
        ]
    return out


@pytest.fixture(scope="module")
def crossing():
    g = crossing_game(N=2, K=40, offset=0.5)
    p = g.default_params()
    coll = next(t.index for t in g.terms if t.feature_type == "collision")
    assert float(g.function("term_energies")(g.zero_controls(), p)[coll]) > 1e-2  # start: head-on
    res = solve_ilq(g, p, options={"tol": 1e-9})
    return g, p, coll, res


def test_crossing_converges_with_interaction(crossing):
    g, p, coll, res = crossing
    assert res.status is Status.CONVERGED and res.info["stationarity"] <= 1e-9
    assert res.info["hessian"] == "gauss_newton"
    assert float(g.function("term_energies")(res.controls, p)[coll]) > 1e-4  # still interacting
    np.testing.assert_allclose(
        res.states, np.asarray(g.function("rollout")(res.controls, p)).ravel(), atol=1e-12
    )
    np.testing.assert_allclose(res.energy, float(g.function("energy")(res.controls, p)), rtol=1e-12)
    np.testing.assert_allclose(
        res.agent_costs, np.asarray(g.function("agent_costs")(res.controls, p)).ravel(), rtol=1e-12
    )
    assert res.energy_history.shape == (res.iterations + 1,)
    assert res.info["gains"].shape == (g.K, 4, 8) and res.info["feedforward"].shape == (g.K, 4)


def test_crossing_feedback_nash_first_order_conditions(crossing):
    """What is checked: along the returned feedback policy
    ``U_k(X) = U*_k - P_k (X - X*_k) - a_k`` of *all* players, add a perturbation
    ``d_i`` to player i's controls only (an open-loop deviation on top of its own policy)
    and roll out the nonlinear dynamics (plain numpy). ``dC_i/dd_i`` at ``d_i = 0``,
    by central differences, is the stage-wise first-order feedback Nash condition
    ``r_i,k + B_i' zeta_i,k+1 = 0`` (no player gains to first order by deviating at any
    stage while everybody, itself included, keeps to the feedback policies afterwards).
    It must vanish at the iLQ solution, although the *open-loop* condition (the game's
    pseudo-gradient, others' controls frozen) does not: the two equilibria differ.
    Small finite deviations do not lower C_i either (local check, 20 random directions).
    """
    g, p, _, res = crossing
    X, U = to_stages(g, res.states, res.controls)
    P, a = res.info["gains"], res.info["feedforward"]
    cost_fn = g.function("traj_agent_costs")

    def closed_loop_cost(i, d):
        x, xs, us = X[0].copy(), [X[0]], []
        for k in range(g.K):
            u = U[k] - P[k] @ (x - X[k]) - a[k]
            u[2 * i : 2 * i + 2] += d[k]
            x = unicycle_step(x, u, g.dt)
            xs.append(x)
            us.append(u)
        xf, uf = from_stages(g, np.array(xs), np.array(us))
        return float(cost_fn(xf, uf, p)[i])

    h = 1e-6
    pseudo = np.asarray(g.function("pseudo_gradient")(res.controls, p)).ravel()
    rng = np.random.default_rng(0)
    for i in range(2):
        c0 = closed_loop_cost(i, np.zeros((g.K, 2)))  # reproduces the solution
        np.testing.assert_allclose(c0, res.agent_costs[i], rtol=1e-10)
        grad = np.zeros((g.K, 2))
        for k in range(g.K):
            for c in range(2):
                d = np.zeros((g.K, 2))
                d[k, c] = h
                grad[k, c] = (closed_loop_cost(i, d) - closed_loop_cost(i, -d)) / (2 * h)
        open_loop = np.max(np.abs(pseudo[g.uoff[i] : g.uoff[i + 1]]))
        assert np.max(np.abs(grad)) < 1e-6, (i, np.max(np.abs(grad)))
        assert open_loop > 1e-2, (i, open_loop)  # the check discriminates
        for d in rng.normal(size=(10, g.K, 2)):
            for s in (0.02, -0.02):
                assert closed_loop_cost(i, s * d) >= c0 - 1e-9


# --------------------------------------------------------------------------------------
# (c) potential game with quadratic terms and linear dynamics vs the potential minimizer
# --------------------------------------------------------------------------------------
def di_potential_game(collision_weight: float) -> PotentialGame:
    agents = [
        AgentSpec(
            "a",
            "double_integrator",
            [Goal(weight=2.0), Velocity(weight=0.3), Acceleration()],
            radius=0.5,
            x0=[-2.0, 0.1, 1.0, 0.0],
            goal=[2.0, 0.1],
        ),
        AgentSpec(
            "b",
            "double_integrator",
            [Goal(weight=2.0), Velocity(weight=0.3), Acceleration()],
            radius=0.5,
            x0=[2.0, -0.1, -1.0, 0.0],
            goal=[-2.0, -0.1],
        ),
    ]
    return PotentialGame(GameSpec(agents, [Collision(weight=collision_weight)], horizon=20, dt=0.1))


def test_uncoupled_quadratic_potential_game_matches_lm():
    """Theory: with linear dynamics, quadratic costs and *no coupling* (collision weight 0)
    each player's problem is an independent LQR; a deterministic LQR's open-loop optimum
    and its feedback (Riccati) solution generate the same trajectory, so the feedback Nash
    trajectory equals the open-loop Nash one, i.e. the potential minimizer of LM. iLQ is
    exact on this LQ game (one iteration); agreement to 1e-8."""
    g = di_potential_game(0.0)
    p = g.default_params()
    ilq = solve_ilq(g, p, options={"tol": 1e-10})
    lm = solve_lm(g, p, options={"gtol": 1e-11})
    assert ilq.status is Status.CONVERGED and ilq.iterations == 1 and lm.status is Status.CONVERGED
    np.testing.assert_allclose(ilq.controls, lm.controls, atol=1e-8)
    np.testing.assert_allclose(ilq.states, lm.states, atol=1e-8)
    np.testing.assert_allclose(ilq.energy, lm.energy, rtol=1e-10)


def test_coupled_potential_game_feedback_differs_from_open_loop():
    """Theory: once the players are coupled (collision term active) the open-loop Nash
    equilibrium (the potential minimizer, Theorem 1) and the feedback Nash equilibrium
    differ in general: in feedback each player anticipates how the others' policies react
    to its state. Assert: both solvers converge to their own conditions; the trajectories
    differ clearly more than the uncoupled case's 1e-8 (> 1e-3 m) yet stay in the same
    mode (< 0.2 m); LM's potential is not higher than iLQ's, whose open-loop
    pseudo-gradient is not zero."""
    g = di_potential_game(5.0)
    p = g.default_params()
    coll = next(t.index for t in g.terms if t.feature_type == "collision")
    ilq = solve_ilq(g, p, options={"tol": 1e-9})
    lm = solve_lm(g, p, options={"gtol": 1e-9})
    assert ilq.status is Status.CONVERGED and lm.status is Status.CONVERGED
    assert float(g.function("term_energies")(ilq.controls, p)[coll]) > 1e-2  # coupled regime
    gap = np.max(np.abs(g.positions(ilq.states) - g.positions(lm.states)))
    assert 1e-3 < gap < 0.2, gap
    assert lm.energy <= ilq.energy + 1e-9
    assert np.max(np.abs(np.asarray(g.function("pseudo_gradient")(lm.controls, p)))) < 1e-6
    assert np.max(np.abs(np.asarray(g.function("pseudo_gradient")(ilq.controls, p)))) > 1e-2


# --------------------------------------------------------------------------------------
# interface
# --------------------------------------------------------------------------------------
def test_options_are_checked():
    g = di_potential_game(0.0)
    with pytest.raises(SpecError, match="ilq: unknown option"):
        solve_ilq(g, g.default_params(), options={"maxiter": 3})
    for bad in (
        {"tol": -1.0},
        {"step_size": 0.0},
        {"step_size": 1.5},
        {"line_search": "armijo"},
        {"hessian": "bfgs"},
        {"max_iter": 2.5},
        {"backtrack": 1.0},
        {"regularization": float("inf")},
        {"kink_widths": (1e-3, 1e-2)},
        {"kink_widths": (0.0,)},
        {"kink_widths": "1e-2"},
        {"adaptive_step": 1},
        {"restart": "yes"},
        {"kink_equilibrium": 1},
    ):
        with pytest.raises(SpecError, match="ilq."):
            ILQOptions(**bad)


def test_custom_costs_are_checked(lq):
    game, costs, p = lq
    x = ca.SX.sym("x", game.n_x)
    with pytest.raises(SpecError, match="costs"):
        solve_ilq(game, p, costs=ca.Function("bad", [x], [x[:2]]))
    with pytest.raises(SpecError, match="costs"):
        solve_ilq(game, p, costs="not a function")
    with pytest.raises(SpecError, match="gauss_newton"):
        solve_ilq(game, p, options={"hessian": "gauss_newton"}, costs=costs)


def test_batch_and_jerk_game():
    """A batch is solved problem by problem. A jerk feature couples consecutive stages: the
    previous accelerations are carried as extra states, so no curvature is dropped, and the
    feedback first-order conditions hold along the policy that also feeds back on them
    (central differences of each player's cost, independent numpy rollout). Here the other
    player's reaction to one's previous acceleration is weak, so this check does not
    discriminate the extra gains; the LQ test below does."""
    agents = [
        AgentSpec(
            "a",
            "unicycle",
            [Goal(weight=2.0), Acceleration(), TurnRate(), Jerk(weight=0.1)],
            x0=[0, 0, 1, 0],
            goal=[3, 1],
        ),
        AgentSpec(
            "b",
            "unicycle",
            [Goal(weight=2.0), Acceleration(), TurnRate(), Jerk(weight=0.1)],
            x0=[3, 1, 1, np.pi],
            goal=[0, 0],
        ),
    ]
    g = PotentialGame(GameSpec(agents, [Collision(weight=5.0)], horizon=15, dt=0.1))
    p = g.default_params()
    solver = ILQSolver(g)
    assert solver.dropped_cross_stage == 0
    assert list(solver.aug) == [0, 2]  # positions of both accelerations in U_k
    one = solve_ilq(g, p, options={"tol": 1e-10})
    assert one.status is Status.CONVERGED
    assert one.info["gains_prev"].shape == (g.K, 4, 2)
    assert np.abs(one.info["gains_prev"]).max() > 1e-3  # the policy does use them
    batch = solve_ilq(g, np.stack([p, p]), np.zeros((2, g.n_u)), options={"tol": 1e-10})
    assert batch.controls.shape == (2, g.n_u) and batch.info["gains"].shape == (2, g.K, 4, 8)
    np.testing.assert_allclose(batch[1].controls, one.controls, atol=1e-12)
    assert list(batch.ok) == [True, True]

    X, U = to_stages(g, one.states, one.controls)
    P, Q, a = one.info["gains"], one.info["gains_prev"], one.info["feedforward"]
    cost_fn = g.function("traj_agent_costs")

    def closed_loop_cost(i, d):
        x, dy, xs, us = X[0].copy(), np.zeros(2), [X[0]], []
        for k in range(g.K):
            u = U[k] - P[k] @ (x - X[k]) - Q[k] @ dy - a[k]
            u[2 * i : 2 * i + 2] += d[k]
            dy = (u - U[k])[[0, 2]]
            x = unicycle_step(x, u, g.dt)
            xs.append(x)
            us.append(u)
        xf, uf = from_stages(g, np.array(xs), np.array(us))
        return float(cost_fn(xf, uf, p)[i])

    h = 1e-6
    for i in range(2):
        np.testing.assert_allclose(
            closed_loop_cost(i, np.zeros((g.K, 2))), one.agent_costs[i], rtol=1e-10
        )
        grad = np.zeros((g.K, 2))
        for k in range(g.K):
            for c in range(2):
                d = np.zeros((g.K, 2))
                d[k, c] = h
                grad[k, c] = (closed_loop_cost(i, d) - closed_loop_cost(i, -d)) / (2 * h)
        assert np.max(np.abs(grad)) < 1e-6, (i, np.max(np.abs(grad)))


def test_jerk_lq_problem_is_solved_in_one_iteration():
    """One double integrator with quadratic goal, acceleration and jerk terms is an LQ
    problem once the previous acceleration is carried as a state: iLQ must solve it
    exactly in one iteration (dropping the jerk's cross-stage curvature took dozens),
    and with one player the feedback solution is the potential minimizer (LM)."""
    agents = [
        AgentSpec(
            "a",
            "double_integrator",
            [Goal(weight=2.0), Acceleration(), Jerk(weight=0.3)],
            x0=[0.0, 0.0, 1.0, 0.0],
            goal=[2.0, 1.0],
        )
    ]
    g = PotentialGame(GameSpec(agents, [], horizon=20, dt=0.1))
    p = g.default_params()
    res = solve_ilq(g, p, options={"tol": 1e-9})
    assert res.status is Status.CONVERGED and res.iterations == 1
    assert list(res.info["prev_variables"]) == [0, 1]  # both accelerations are carried
    lm = solve_lm(g, p, options={"gtol": 1e-12})
    np.testing.assert_allclose(res.controls, lm.controls, atol=1e-8)


def test_line_search_ends_the_two_cycle_of_full_steps():
    """On crossing2, full steps alternate between two iterates (max |a| 0.38 and 2.9) for
    ever; the default residual line search (merit: RMS of a, non-monotone over 5) ends it."""
    from scenarios.gamefile import example_path, load_game

    gf = load_game(example_path("crossing2"))
    g, p = gf.game, gf.params
    plain = solve_ilq(g, p, options={"line_search": "none", "max_iter": 40})
    assert plain.status is Status.MAX_ITER
    h = plain.info["residual_history"]
    np.testing.assert_allclose(h[-4:-2], h[-2:], rtol=1e-6)  # a two-cycle
    res = solve_ilq(g, p)
    assert res.status is Status.CONVERGED and res.info["stop"] == "tol"
    assert res.info["stationarity"] <= ILQOptions().tol and res.info["max_regularization"] == 0


def test_no_usable_step_is_stalled_with_the_honest_residual():
    """A trust region no step fits in: regularization climbs (shrinking a) until max |a| is
    small only because of it; the solve is 'stalled', and the reported max |a| is the one
    at the requested regularization, far above tol. The iterate is the start's rollout."""
    g = crossing_game(N=2, K=20, offset=0.5)
    p = g.default_params()
    res = solve_ilq(g, p, options={"max_state_step": 1e-12})
    assert res.status is Status.STALLED and not res.ok
    assert res.info["stop"] in ("regularized_only", "line_search")
    assert res.info["stationarity"] > 1e-3
    assert res.info["max_regularization"] >= 1e4
    np.testing.assert_array_equal(res.controls, np.zeros(g.n_u))


# --------------------------------------------------------------------------------------
# kinks and the secant step (used after a failed line search; docs/ilq.md)
# --------------------------------------------------------------------------------------
def test_kink_blend_is_exact_outside_the_band_and_a_ramp_inside():
    """``3 fmax(0, x0 - 1) + fmin(x1, 2)`` with its kinks blended over ``w``: values and
    derivatives are the original's outside ``|z| < w/2``; inside, the derivative is the
    ramp ``clip(z / w + 1/2, 0, 1)`` written out by hand."""
    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [3 * ca.fmax(0, x[0] - 1) + ca.fmin(x[1], 2)])
    sm = _smooth_kinks(f)
    assert _smooth_kinks(ca.Function("g", [x], [x[0] * x[1]])) is None  # no kink
    w = 0.1
    xs, ws = ca.SX.sym("x", 2), ca.SX.sym("w")
    r, z = sm(xs, ws)
    d = ca.Function("d", [xs, ws], [r, ca.jacobian(r, xs), z])
    for pt in ([0.5, 3.0], [1.2, 1.0], [0.94, 2.06]):  # every kink argument |z| > w/2
        val, jac, zk = (np.asarray(v).ravel() for v in d(pt, w))
        assert val[0] == pytest.approx(3 * max(0, pt[0] - 1) + min(pt[1], 2), abs=1e-15)
        np.testing.assert_allclose(jac, [3 * (pt[0] > 1), float(pt[1] < 2)], atol=1e-15)
        np.testing.assert_allclose(zk, [pt[0] - 1, pt[1] - 2], atol=1e-15)
    # inside: z0 = +w/4 -> fmax slope 3 * 3/4; z1 = x1 - 2 = -w/4 -> fmin slope 1 - 1/4
    _, jac, _ = (np.asarray(v).ravel() for v in d([1 + w / 4, 2 - w / 4], w))
    np.testing.assert_allclose(jac, [2.25, 0.75], rtol=1e-12)
    # w = 0 is the original function, values and derivatives
    val, jac, _ = (np.asarray(v).ravel() for v in d([1.0 + 1e-9, 2.0 - 1e-9], 0.0))
    np.testing.assert_allclose(jac, [3.0, 1.0], rtol=1e-12)
    # pinned: kink 0 at slope 0.3 wherever its argument is, kink 1 (s < 0) blended as above
    pin = _smooth_kinks(f, pinned=True)
    r, z = pin(xs, ws, ca.DM([0.3, -1.0]))
    dp = ca.Function("dp", [xs, ws], [ca.jacobian(r, xs)])
    for pt, slope1 in (([0.5, 3.0], 0.0), ([1.2, 2 - w / 4], 0.75)):
        np.testing.assert_allclose(np.asarray(dp(pt, w)).ravel(), [0.9, slope1], rtol=1e-12)


def test_an_equilibrium_on_a_collision_kink_is_certified():
    """``intersection-6-unicycle-w100-s33-jerk`` (bench/sweep_defaults.py, seed 33): the
    feedback equilibrium sits on a collision hinge ``1/2 max(0, z)^2``, where ``a = 0``
    holds only with the kink's Gauss-Newton curvature ``theta^2``, ``theta`` strictly
    inside ``(0, 1)`` (docs/ilq.md, "Equilibria on a kink"). With the default
    ``kink_equilibrium`` the solve ends ``converged`` there; the feedback-Nash check, own
    deviations rolled out with the nonlinear dynamics (other seed and directions than the
    solver's), passes with that policy and fails with either one-sided policy (``theta``
    0 or 1, gains and feed-forward of the same trajectory). (Without the option the solve
    stops ``stalled`` at the kink, as before; not run here: 3 s more.)"""
    g = PotentialGame(family_spec("intersection", 6, "unicycle", 100.0, 33, jerk=True))
    p = g.default_params()
    res = solve_ilq(g, p)
    assert res.status is Status.CONVERGED and res.info["stop"] == "kink_equilibrium"
    k = res.info["kink_equilibrium"]
    assert k["certified"] and k["equilibrium"]["ok"] and k["exact_stationarity"] > 1e-3
    ((idx, theta, z),) = k["equilibrium"]["kinks"]
    assert 0.1 < theta < 0.9 and abs(z) <= 1e-2 * min(ILQOptions().kink_widths)
    assert res.info["stationarity"] <= ILQOptions().tol
    # the same kink argument from a fresh evaluation at the returned trajectory
    solver = get_solver(g)
    X, U = to_stages(g, res.states, res.controls)
    zk = np.array(solver._kink_quad[1](X, U, p)[0]).ravel()
    assert zk[idx] == pytest.approx(z, abs=1e-15)

    def policy(th):  # gains and feed-forward with the kink at curvature th^2
        pins = np.full(zk.size, -1.0)
        pins[idx] = th
        solver.kink_pins = pins
        try:
            solver.quadratize(X, U, p)
            PA, _, ok = solver.backward(0.0, ILQOptions().min_curvature)
        finally:
            solver.kink_pins = None
        assert ok
        nx, nxs = solver.nx, solver.nxs
        return PA[:, :, :nx], PA[:, :, nxs], PA[:, :, nx:nxs]

    opts = FeedbackNashOptions(seed=7, n_random=6, n_coordinate=6)
    P, a, Q = policy(theta)
    np.testing.assert_allclose(P, res.info["gains"], rtol=0, atol=1e-12)
    for th, passes in ((theta, True), (0.0, False), (1.0, False)):
        P, a, Q = policy(th)
        assert bool(np.max(np.abs(a)) <= ILQOptions().tol) is passes  # a = 0 only at theta
        chk = feedback_nash_check(
            g, p, res.states, res.controls, P, a, opts, gains_prev=Q, prev_variables=solver.aug
        )
        assert chk.ok is passes, (th, chk.summary())


def test_secant_step_damps_an_overshoot_and_returns_to_full_steps():
    """``eps / (1 - rho)``, ``rho = <a_new, a_old> / |a_old|^2``, by hand."""
    a = np.array([[1.0, 0.0], [0.0, 0.0]])
    # a full step that flips a to -0.966 a: the linear model's root is 1 / 1.966
    assert _secant_step(a, -0.966 * a, 1.0, 1.0) == pytest.approx(1 / 1.966)
    # a full step that shrinks a, or flips it only a little: full steps are kept
    assert _secant_step(a, 0.1 * a, 1.0, 1.0) == 1.0
    assert _secant_step(a, -0.2 * a, 1.0, 1.0) == 1.0
    # after a damped step: keep it when the model fits (rho ~ 0), back to 1 when rho = 1/2
    assert _secant_step(a, 0.0 * a, 0.5, 1.0) == 0.5
    assert _secant_step(a, 0.5 * a, 0.5, 1.0) == 1.0
    assert _secant_step(a, -1e9 * a, 1.0, 1.0) == pytest.approx(1e-2)  # floor
    assert _secant_step(0 * a, a, 1.0, 1.0) == 1.0  # nothing to compare with
