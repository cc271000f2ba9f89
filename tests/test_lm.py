"""Levenberg-Marquardt (solvers.lm) against independent references.

References: a closed-form least-squares optimum (numpy lstsq on a hand-built matrix),
a hand-written dense LM step with a finite-difference Jacobian, and one-by-one solves.
"""

from __future__ import annotations

import numpy as np
import pytest

from epo_casadi import Acceleration, AgentSpec, GameSpec, Goal, PotentialGame, SpecError, Velocity
from solvers.lm import LMOptions, solve_lm
from solvers.result import Status

from .helpers import crossing_game

K, DT = 10, 0.2
W_GOAL, W_VEL, W_ACC = 2.0, 0.3, 0.5


def di_game() -> PotentialGame:
    """One double integrator with goal, velocity and acceleration features: linear least squares."""
    agent = AgentSpec(
        "di",
        "double_integrator",
        [Goal(weight=W_GOAL), Velocity(weight=W_VEL), Acceleration(weight=W_ACC)],
        x0=[0.5, -0.2, 1.0, 0.4],
        goal=[3.0, 1.0],
    )
    return PotentialGame(GameSpec([agent], horizon=K, dt=DT))


def di_reference(x0, goal):
    """Exact minimizer and energy, from ``r = A u + b`` built by hand (explicit Euler).

    ``v_k = v_0 + dt sum_{j<k} a_j``; ``p_K = p_0 + K dt v_0 + dt^2 sum_j (K-1-j) a_j``;
    ``u[2k + c] = a_{k,c}``.
    """
    x0, goal = np.asarray(x0, float), np.asarray(goal, float)
    n = 2 * K
    rows, rhs = [], []
    for c in range(2):  # goal
        a = np.zeros(n)
        for j in range(K):
            a[2 * j + c] = W_GOAL * DT**2 * (K - 1 - j)
        rows.append(a)
        rhs.append(W_GOAL * (x0[c] + K * DT * x0[2 + c] - goal[c]))
    for k in range(1, K + 1):  # velocity at k = 1..K
        for c in range(2):
            a = np.zeros(n)
            for j in range(k):
                a[2 * j + c] = W_VEL * DT
            rows.append(a)
            rhs.append(W_VEL * x0[2 + c])
    for k in range(K):  # acceleration at k = 0..K-1
        for c in range(2):
            a = np.zeros(n)
            a[2 * k + c] = W_ACC
            rows.append(a)
            rhs.append(0.0)
    A, b = np.array(rows), np.array(rhs)
    u = np.linalg.lstsq(A, -b, rcond=None)[0]
    return u, 0.5 * np.sum((A @ u + b) ** 2)


def fd_jacobian(f, u, h=1e-6):
    cols = []
    for j in range(u.size):
        e = np.zeros_like(u)
        e[j] = h
        cols.append((f(u + e) - f(u - e)) / (2 * h))
    return np.stack(cols, axis=1)


def test_lm_reaches_closed_form_optimum():
    g = di_game()
    x0, goal = [0.5, -0.2, 1.0, 0.4], [2.0, -1.5]
    p = g.default_params(goal__di=goal)
    u_ref, e_ref = di_reference(x0, goal)
    res = solve_lm(g, p)
    assert res.status is Status.CONVERGED
    np.testing.assert_allclose(res.controls, u_ref, atol=1e-7)
    np.testing.assert_allclose(res.energy, e_ref, rtol=1e-10)
    assert e_ref > 0.1  # the optimum is not trivial (goal, velocity, effort compete)
    assert res.energy_history[0] == pytest.approx(float(g.function("energy")(np.zeros(g.n_u), p)))


@pytest.mark.parametrize("backend", ["dense", "structured"])
def test_lm_paper_setting_equals_hand_written_steps(backend):
    g = crossing_game(offset=0.3)
    p = g.default_params()
    rng = np.random.default_rng(1)
    parts = [
        np.column_stack([0.8 + 0.3 * rng.standard_normal(g.K), 0.2 * rng.standard_normal(g.K)])
        for _ in range(g.N)
    ]
    u0 = g.join_controls(parts)
    res = solve_lm(g, p, u0, LMOptions.paper(backend=backend))
    assert int(res.iterations) == 2
    assert res.energy_history.shape == (3,)
    assert res.status is Status.MAX_ITER

    residual = g.function("residual")

    def r(u):
        return np.asarray(residual(u, p), dtype=float).ravel()

    u = u0.copy()
    energies = [0.5 * r(u) @ r(u)]
    for _ in range(2):  # (J'J + 10 I) du = -J'r, u <- u + 0.3 du
        J = fd_jacobian(r, u)
        du = np.linalg.solve(J.T @ J + 10.0 * np.eye(g.n_u), -J.T @ r(u))
        u = u + 0.3 * du
        energies.append(0.5 * r(u) @ r(u))
    assert np.max(np.abs(u - u0)) > 1e-2  # the steps moved
    np.testing.assert_allclose(res.controls, u, atol=1e-7)
    np.testing.assert_allclose(res.energy_history, energies, rtol=1e-8)


def test_batch_equals_one_by_one():
    g = crossing_game(offset=0.3)
    P = np.stack(
        [
            g.default_params(),
            g.default_params(goal__a0=[-2.5, 0.8]),
            g.default_params(goal__a1=[2.0, -1.0], w__a0__goal=1.0),
        ]
    )
    rng = np.random.default_rng(2)
    U0 = 0.1 * rng.standard_normal((3, g.n_u))
    batch = solve_lm(g, P, U0)
    assert batch.controls.shape == (3, g.n_u) and batch.status.shape == (3,)
    assert np.ptp(batch.energy) > 1e-3  # the problems really differ
    for b in range(3):
        one = solve_lm(g, P[b], U0[b])
        assert one.status is batch.status[b]
        np.testing.assert_allclose(batch.controls[b], one.controls, atol=1e-8)
        np.testing.assert_allclose(batch.energy[b], one.energy, rtol=1e-10)
        assert batch.iterations[b] == one.iterations


def test_nan_in_p_raises_spec_error_naming_p():
    g = di_game()
    P = np.stack([g.default_params(), g.default_params()])
    P[1, g.params["goal.di"].start] = np.nan
    with pytest.raises(SpecError) as e:
        solve_lm(g, P)
    assert e.value.field == "p"
    assert "goal.di.x" in e.value.message


@pytest.mark.parametrize(
    "options, field",
    [
        ({"stepsize": 0.5}, "lm"),  # typo of step_size: unknown key
        ({"step_size": 1.5}, "lm.step_size"),
        ({"step_size": 0.0}, "lm.step_size"),
        ({"step_size": float("nan")}, "lm.step_size"),
        ({"steps": -1}, "lm.steps"),
        ({"damping": -1.0}, "lm.damping"),
        ({"backend": "sparse"}, "lm.backend"),
    ],
)
def test_bad_options_raise(options, field):
    with pytest.raises(SpecError) as e:
        solve_lm(di_game(), di_game().default_params(), options=options)
    assert e.value.field == field


def test_paper_options():
    o = LMOptions.paper()
    assert (o.steps, o.step_size, o.damping, o.adaptive_damping) == (2, 0.3, 10.0, False)
    assert LMOptions.paper(steps=20, step_size=1.0).steps == 20  # CARLA setting


def test_nonfinite_problem_is_masked_others_unaffected():
    g = di_game()
    P = np.stack(
        [
            g.default_params(),
            g.default_params(goal__di=[2.0, -1.5]),
            g.default_params(goal__di=[5.0, 0.0]),
        ]
    )
    P[1, g.params["w.di.goal"].start] = 1e160  # finite weight; its energy overflows to inf
    U0 = np.full((3, g.n_u), 0.05)
    res = solve_lm(g, P, U0)  # no numpy warning escapes: overflow is handled per problem
    assert res.status[1] is Status.NONFINITE
    np.testing.assert_array_equal(res.controls[1], U0[1])  # frozen at its last finite iterate
    assert np.all(np.isfinite(res.controls))
    for b in (0, 2):
        one = solve_lm(g, P[b], U0[b])
        assert res.status[b] is Status.CONVERGED
        np.testing.assert_allclose(res.controls[b], one.controls, atol=1e-10)
        u_ref, _ = di_reference([0.5, -0.2, 1.0, 0.4], P[b, g.params["goal.di"].slice])
        np.testing.assert_allclose(res.controls[b], u_ref, atol=1e-7)


def test_ill_conditioned_problem_does_not_abort_batch():
    g = di_game()
    P = np.stack([g.default_params(), g.default_params()])
    P[1, g.params["w.di.goal"].start] = 1e100  # J'J + lambda I numerically singular
    res = solve_lm(g, P)
    assert res.status[0] is Status.CONVERGED


def test_backend_is_built_once_per_game_and_reused():
    """solve_lm must not rebuild its Gauss-Newton backend (40 ms) on every call."""
    from solvers.lm import make_backend

    g = crossing_game(K=5)
    opts = LMOptions(steps=3)
    assert make_backend(g, opts) is make_backend(g, opts)
    assert make_backend(g, LMOptions(backend="dense")) is not make_backend(g, opts)
    first, second = (
        solve_lm(g, g.default_params(), options=opts),
        solve_lm(g, g.default_params(), options=opts),
    )
    np.testing.assert_array_equal(first.controls, second.controls)


def test_gtol_stops_at_the_first_iterate_below_it():
    """Stopping rule by |J'r|_inf <= gtol alone (ftol off): the solve stops at the first
    iterate that meets it; one step fewer does not."""
    g = di_game()
    p = g.default_params(goal__di=[2.0, -1.5])
    opts = LMOptions(ftol=0.0, gtol=1e-8)
    res = solve_lm(g, p, options=opts)
    assert res.status is Status.CONVERGED and res.grad_norm <= 1e-8
    assert res.info["stop"] == "gtol"  # the stop reasons of docs/solvers.md
    assert 1 < res.iterations < opts.steps
    shorter = solve_lm(g, p, options=LMOptions(ftol=0.0, gtol=1e-8, steps=int(res.iterations) - 1))
    assert shorter.status is Status.MAX_ITER and shorter.grad_norm > 1e-8
    assert shorter.info["stop"] == "max_iter"


def test_ftol_stops_at_the_first_small_relative_decrease():
    """With fixed damping (every step accepted) and gtol off, the solve stops after the first
    step that lowers E by <= ftol (1 + E), and no earlier step did."""
    g = crossing_game(offset=0.3)
    p = g.default_params()
    u0 = g.join_controls([np.tile([1.0, 0.0], (g.K, 1)) for _ in range(g.N)])
    ftol = 1e-6
    opts = LMOptions(adaptive_damping=False, damping=1.0, gtol=0.0, ftol=ftol, steps=200)
    res = solve_lm(g, p, u0, opts)
    k = int(res.iterations)
    assert 2 < k < opts.steps and res.status is not Status.MAX_ITER
    h = res.energy_history[: k + 1]
    dec = h[:-1] - h[1:]
    assert dec[-1] <= ftol * (1 + abs(h[-1])) and res.info["stop"] == "ftol"
    assert np.all(dec[:-1] > ftol * (1 + np.abs(h[1:-1])))


def test_rejected_steps_raise_the_damping_and_the_solve_goes_on():
    """From zero controls with a tiny damping the first Gauss-Newton steps overshoot: they
    are rejected (E unchanged, lambda x10) and the solve continues to a stationary point."""
    g = crossing_game(offset=0.3)
    p = g.default_params()
    res = solve_lm(g, p, options=LMOptions(damping=1e-9))
    lam = res.info["damping_history"]
    assert lam[1] == pytest.approx(10 * lam[0]) and res.energy_history[1] == res.energy_history[0]
    assert res.iterations > 10 and res.energy < 0.6 * res.energy_history[0]
    assert res.status is Status.CONVERGED and res.grad_norm <= 1e-4
