"""What a potential solve of a coupled game is (solvers.result.Equilibrium), said everywhere.

With coupled dynamics (``GameSpec(couplings=...)``) an agent's controls move another
agent's state, so a minimizer of the potential is in general no open-loop Nash
equilibrium. The game: two players push one shared point mass (a joint model that steps
both players' copies of its state with the sum of their accelerations), each towards its
own goal. It is linear-quadratic, so both points are found by hand in numpy:

* the potential minimum solves ``dE/du = 0`` with ``E = C_a + C_b``;
* the open-loop Nash equilibrium solves the stacked first-order conditions
  ``dC_i/du_i = 0`` of both players, one linear system.

The potential solvers (LM, IPOPT, SQP) land on the first, say so in their result and in
every writer, and the certificate fails them; the second passes the certificate. Without
the coupling (each player its own mass) the two points coincide and nothing is flagged.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import casadi as ca
import numpy as np
import pytest

from epo_casadi import Acceleration, AgentSpec, GameSpec, Goal, PotentialGame
from epo_casadi.dynamics import JointDynamics
from epo_casadi.game import Coupling
from scenarios.commands.solve import result_dict, summary_lines, write_result
from solvers.compare import parse_solver, run_comparison
from solvers.ilq import solve_ilq
from solvers.ipopt import solve_ipopt
from solvers.lm import solve_lm
from solvers.nash import nash_certificate
from solvers.result import Equilibrium, Status, Verdict
from solvers.sqp import solve_sqp

K, DT, WG, WA = 10, 0.2, 2.0, 1.0
X0 = (0.0, 0.0, 0.0, 0.0)
GOALS = ((2.0, 1.0), (-1.0, 2.0))
POTENTIAL_SOLVERS = (solve_lm, solve_ipopt, solve_sqp)


@dataclass(frozen=True)
class SharedMass(JointDynamics):
    """One planar point mass, accelerated by the sum of both players' controls; both
    players' states are copies of it (explicit Euler, as the double integrator)."""

    name = "shared_mass"

    def step(self, xs, us, dt):
        x, a = xs[0], us[0] + us[1]
        nxt = ca.vertcat(x[0] + x[2] * dt, x[1] + x[3] * dt, x[2] + a[0] * dt, x[3] + a[1] * dt)
        return [nxt, nxt]


def make_game(coupled: bool) -> PotentialGame:
    agents = [
        AgentSpec(
            name,
            "double_integrator",
            [Goal(weight=WG), Acceleration(weight=WA)],
            x0=list(X0),
            goal=list(goal),
        )
        for name, goal in zip(("a", "b"), GOALS, strict=True)
    ]
    couplings = [Coupling(("a", "b"), SharedMass())] if coupled else ()
    return PotentialGame(GameSpec(agents, horizon=K, dt=DT, couplings=couplings))


def _terminal_map():
    """``p_K = c0 + G u_k-stacked``: the final position of a double integrator started at
    X0, ``G`` (2, 2K) over its accelerations (time-major, as the game's layout)."""
    A = np.eye(4)
    A[0, 2] = A[1, 3] = DT
    B = np.zeros((4, 2))
    B[2, 0] = B[3, 1] = DT
    S = np.eye(2, 4)
    G = np.hstack([S @ np.linalg.matrix_power(A, K - 1 - k) @ B for k in range(K)])
    return S @ np.linalg.matrix_power(A, K) @ np.array(X0), G


def shared_references() -> tuple[np.ndarray, np.ndarray]:
    """(potential minimum, open-loop Nash) of the shared-mass game, in numpy.

    ``C_i = WG^2/2 |p_K - g_i|^2 + WA^2/2 |u_i|^2`` with ``p_K = c0 + G (u_a + u_b)``.
    Nash: ``WG^2 G'(p_K - g_i) + WA^2 u_i = 0`` for both ``i``; potential:
    ``WG^2 G'(2 p_K - g_a - g_b) + WA^2 u_i = 0``.
    """
    c0, G = _terminal_map()
    n = G.shape[1]
    GG, R = WG**2 * G.T @ G, WA**2 * np.eye(n)
    ga, gb = (np.array(g) for g in GOALS)
    nash = np.linalg.solve(
        np.block([[GG + R, GG], [GG, GG + R]]),
        np.concatenate([WG**2 * G.T @ (ga - c0), WG**2 * G.T @ (gb - c0)]),
    )
    both = WG**2 * G.T @ (ga + gb - 2 * c0)
    potential = np.linalg.solve(
        np.block([[2 * GG + R, 2 * GG], [2 * GG, 2 * GG + R]]), np.concatenate([both, both])
    )
    return potential, nash


@pytest.fixture(scope="module")
def coupled():
    g = make_game(True)
    assert g.coupled
    return g, g.default_params()


@pytest.mark.parametrize("solve", POTENTIAL_SOLVERS, ids=lambda f: f.__name__)
def test_potential_solve_of_a_coupled_game_is_flagged(coupled, solve):
    g, p = coupled
    potential, nash = shared_references()
    res = solve(g, p)
    # the potential's own first-order tolerance holds: converged is the right status ...
    assert res.status is Status.CONVERGED
    np.testing.assert_allclose(res.controls, potential, atol=1e-6)
    # ... but the point is not the equilibrium, and the result says so
    assert np.max(np.abs(potential - nash)) > 0.5  # measured: 2.18
    assert res.equilibrium is Equilibrium.POTENTIAL_MINIMUM and res.potential_only
    assert "not a Nash equilibrium" in res.summary()
    d = json.loads(json.dumps(res.to_dict()))
    assert d["equilibrium"] == "potential minimum (coupled dynamics: not a Nash equilibrium)"


def test_certificate_fails_the_potential_minimum_and_passes_the_nash_point(coupled):
    g, p = coupled
    potential, nash = shared_references()
    lm = solve_lm(g, p)
    np.testing.assert_allclose(lm.controls, potential, atol=1e-8)
    cert = nash_certificate(g, p, lm.controls)
    assert cert.verdict is Verdict.FAILS and not cert.ok
    assert cert.verdicts == (Verdict.FAILS, Verdict.FAILS)
    # each player gains by its own deviation: pulling the mass further its own way
    assert np.all(cert.stationarity > 1.0) and np.all(cert.best_response_gap > 1.0)
    # the best response to the other's potential-minimum controls, by hand:
    # WG^2 G'(c0 + G(u_i + u_j) - g_i) + WA^2 u_i = 0
    c0, G = _terminal_map()
    n = G.shape[1]
    ub = lm.controls[n:]
    ua = np.linalg.solve(
        WG**2 * G.T @ G + WA**2 * np.eye(n), WG**2 * G.T @ (np.array(GOALS[0]) - c0 - G @ ub)
    )
    C = np.asarray(g.function("agent_costs")(np.concatenate([ua, ub]), p)).ravel()
    assert cert.best_response_costs[0] == pytest.approx(C[0], rel=1e-9)
    ok = nash_certificate(g, p, nash)
    assert ok.ok and ok.verdict is Verdict.PASSES
    assert np.all(ok.stationarity <= 1e-10) and np.all(ok.best_response_gap <= 1e-10)


def test_an_uncoupled_game_is_not_flagged():
    g = make_game(False)
    assert not g.coupled
    p = g.default_params()
    c0, G = _terminal_map()
    n = G.shape[1]
    own = np.concatenate(  # each player alone: WG^2 G'(c0 + G u_i - g_i) + WA^2 u_i = 0
        [
            np.linalg.solve(
                WG**2 * G.T @ G + WA**2 * np.eye(n), WG**2 * G.T @ (np.array(goal) - c0)
            )
            for goal in GOALS
        ]
    )
    for solve in POTENTIAL_SOLVERS:
        res = solve(g, p)
        assert res.status is Status.CONVERGED
        assert res.equilibrium is Equilibrium.OPEN_LOOP and not res.potential_only
        np.testing.assert_allclose(res.controls, own, atol=1e-6)
        assert "not a Nash equilibrium" not in res.summary()
    assert nash_certificate(g, p, own).ok


def test_ilq_says_feedback_nash_on_the_coupled_game(coupled):
    g, p = coupled
    res = solve_ilq(g, p)
    assert res.status is Status.CONVERGED
    assert res.equilibrium is Equilibrium.FEEDBACK and not res.potential_only
    batch = solve_lm(g, np.stack([p, p]))
    assert batch.equilibrium is Equilibrium.POTENTIAL_MINIMUM
    assert batch[1].equilibrium is Equilibrium.POTENTIAL_MINIMUM
    assert "not a Nash equilibrium" in batch.summary()


def test_every_writer_says_potential_minimum(coupled, tmp_path):
    g, p = coupled
    res = solve_lm(g, p)
    cert = nash_certificate(g, p, res.controls)
    data = result_dict(g, p, res, cert, source="shared.yaml")
    back = json.loads(write_result(data, tmp_path / "r.json").read_text())
    assert back["equilibrium"] == Equilibrium.POTENTIAL_MINIMUM.value
    assert back["status"] == "converged" and back["certificate"]["verdict"] == "fails"
    text = "\n".join(summary_lines(g, back))
    assert "equilibrium: potential minimum (coupled dynamics: not a Nash equilibrium)" in text
    assert "Nash certificate: FAILS" in text
    comp = run_comparison(
        [("shared", g, p)], [parse_solver("lm"), parse_solver("ilq")], progress=False
    )
    rows = {r.solver: r for r in comp.rows}
    assert rows["lm"].equilibrium == Equilibrium.POTENTIAL_MINIMUM.value
    assert rows["lm"].status == "converged" and rows["lm"].verdict == "fails"
    assert rows["ilq"].equilibrium == "feedback Nash"
    assert "potential minimum (coupled dynamics: not a Nash equilibrium)" in comp.markdown()
    assert "potential minimum (coupled dynamics: not a Nash equilibrium)" in comp.csv()
