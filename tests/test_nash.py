"""Local open-loop Nash certificate (solvers.nash) and the game structure it relies on."""

from __future__ import annotations

import json

import numpy as np
import pytest

from epo_casadi import SpecError
from solvers.lm import solve_lm
from solvers.nash import NashOptions, nash_certificate

from .helpers import crossing_game, solved_crossing


def close_start_params(g):
    """Parameters of a 3-agent crossing game with the agents starting within 0.3 m."""
    return g.params.pack(
        {
            "x0.a0": [0.0, 0.0, 1.0, 0.0],
            "x0.a1": [0.2, 0.1, 1.0, 2.0],
            "x0.a2": [-0.1, 0.2, 1.0, 4.0],
            "w.a0-a2.collision": 3.0,
        }
    )


@pytest.fixture(scope="module")
def crossing():
    """Crossing game, its parameters and the potential minimizer (collision term active)."""
    g, p, u0, sol = solved_crossing()
    assert sol.status.ok
    return g, p, u0, sol


def test_potential_minimizer_certifies(crossing):
    g, p, u0, ip = crossing
    lm = solve_lm(g, p, u0)
    # IPOPT converges to |grad| ~ 1e-9; LM stops by its relative energy test (ftol) at
    # |grad| ~ 1.2e-5 (gtol 1e-8 is not reached): the bounds follow what each reaches
    for u, stat_bound in ((ip.controls, 1e-8), (lm.controls, 3e-5)):
        cert = nash_certificate(g, p, u)
        assert cert.ok
        assert cert.agents == ("a0", "a1")
        assert np.all(cert.best_response_gap >= 0)
        assert np.all(cert.best_response_gap <= 1e-9)
        assert np.all(cert.stationarity <= stat_bound)
        assert cert.best_response_status == ("Solve_Succeeded", "Solve_Succeeded")
        np.testing.assert_allclose(cert.costs, np.asarray(g.function("agent_costs")(u, p)).ravel())


def test_perturbed_agent_is_flagged(crossing):
    g, p, _, sol = crossing
    rng = np.random.default_rng(3)
    u = sol.controls.copy()
    a, b = g.uoff[1], g.uoff[2]
    u[a:b] += 0.2 * rng.standard_normal(b - a)
    cert = nash_certificate(g, p, u)
    assert not cert.ok
    assert not cert.stat_ok[1] and not cert.gap_ok[1]
    assert cert.stationarity[1] > 0.1
    assert cert.best_response_gap[1] > 0.1
    assert cert.best_response_gap[1] > 5 * cert.best_response_gap[0]
    # agent 0 still plays its equilibrium strategy, so agent 1's best response to it
    # recovers agent 1's equilibrium cost
    c_star = np.asarray(g.function("agent_costs")(sol.controls, p)).ravel()
    assert cert.best_response_costs[1] == pytest.approx(c_star[1], rel=1e-7)
    assert "FAILS" in cert.summary()


def test_pseudo_gradient_is_gradient_of_potential():
    """Theorem 1: for the potential game, (dC_i/du_i)_i = dE/du at any u."""
    g = crossing_game(N=3, K=8, offset=0.2)
    p = close_start_params(g)
    rng = np.random.default_rng(4)
    costs = g.function("agent_costs")
    for _ in range(3):
        u = rng.normal(0.5, 0.6, g.n_u)
        e = np.asarray(g.function("term_energies")(u, p)).ravel()
        assert all(e[t.index] > 0 for t in g.terms if t.kind == "pair")  # coupling active
        pg = np.asarray(g.function("pseudo_gradient")(u, p)).ravel()
        grad = np.asarray(g.function("gradient")(u, p)).ravel()
        np.testing.assert_allclose(pg, grad, rtol=1e-10, atol=1e-10)
        # independent reference: central differences of C_i in agent i's own controls
        fd = np.zeros(g.n_u)
        h = 1e-6
        for i in range(g.N):
            for j in range(g.uoff[i], g.uoff[i + 1]):
                e = np.zeros(g.n_u)
                e[j] = h
                fd[j] = (float(costs(u + e, p)[i]) - float(costs(u - e, p)[i])) / (2 * h)
        np.testing.assert_allclose(pg, fd, atol=1e-5 * (1 + np.abs(pg).max()))


def test_agent_costs_from_terms_by_hand():
    """Non-potential bookkeeping: C_i = energies of i's own terms + pair terms with i."""
    g = crossing_game(N=3, K=8, offset=0.2)
    p = close_start_params(g)
    rng = np.random.default_rng(5)
    u = rng.normal(0.5, 0.6, g.n_u)
    r = np.asarray(g.function("residual")(u, p)).ravel()
    e = np.array([0.5 * np.sum(r[t.rows] ** 2) for t in g.terms])
    np.testing.assert_allclose(np.asarray(g.function("term_energies")(u, p)).ravel(), e, rtol=1e-12)
    assert all(e[t.index] > 0 for t in g.terms if t.kind == "pair")  # pairs really contribute
    by_hand = np.array(
        [sum(e[t.index] for t in g.terms if name in t.agents) for name in g.agent_names]
    )
    np.testing.assert_allclose(
        np.asarray(g.function("agent_costs")(u, p)).ravel(), by_hand, rtol=1e-12
    )
    # the pair terms are counted once in E and once per agent in the costs
    pair = sum(e[t.index] for t in g.terms if t.kind == "pair")
    assert by_hand.sum() == pytest.approx(float(g.function("energy")(u, p)) + pair, rel=1e-12)


def test_stationarity_only_and_outputs(crossing):
    g, p, _, sol = crossing
    cert = nash_certificate(g, p, sol.controls, {"best_response": False})
    assert cert.ok
    assert cert.options == NashOptions(best_response=False)
    assert cert.best_response_status == ("skipped", "skipped")
    np.testing.assert_array_equal(cert.best_response_gap, 0.0)
    d = json.loads(json.dumps(cert.to_dict()))
    assert d["ok"] is True and d["agents"] == ["a0", "a1"] and len(d["stationarity"]) == 2
    assert d["options"]["best_response"] is False
    text = cert.summary()
    assert "a0" in text and "a1" in text and "passes" in text


@pytest.mark.parametrize(
    "options, field",
    [
        ({"gap": 1e-3}, "nash"),
        ({"stat_tol": 0.0}, "nash.stat_tol"),
        ({"max_iter": -1}, "nash.max_iter"),
        ({"best_response": 1}, "nash.best_response"),
        ({"fallback": "yes"}, "nash.fallback"),
        ({"global_starts": -1}, "nash.global_starts"),
        ({"global_scale": 0.0}, "nash.global_scale"),
    ],
)
def test_bad_options_raise(crossing, options, field):
    g, p, _, sol = crossing
    with pytest.raises(SpecError) as e:
        nash_certificate(g, p, sol.controls, options)
    assert e.value.field == field


def test_one_problem_only(crossing):
    g, p, _, sol = crossing
    with pytest.raises(SpecError) as e:
        nash_certificate(g, p, np.stack([sol.controls, sol.controls]))
    assert e.value.field == "u/p"


def _perturbed(g, sol, eps, seed=3):
    """The equilibrium with agent 1's controls moved by ``eps`` along a fixed direction."""
    d = np.random.default_rng(seed).standard_normal(g.uoff[2] - g.uoff[1])
    u = sol.controls.copy()
    u[g.uoff[1] : g.uoff[2]] += eps * d / np.abs(d).max()
    return u


def _stat_and_scale(g, u, p, i=1):
    """Agent i's stationarity and its scale 1 + min(|C_i|, scale_cap), from the game's
    functions directly."""
    pg = np.asarray(g.function("pseudo_gradient")(u, p)).ravel()
    c = np.asarray(g.function("agent_costs")(u, p)).ravel()
    scale = 1 + min(abs(c[i]), NashOptions().scale_cap)
    return np.abs(pg[g.uoff[i] : g.uoff[i + 1]]).max(), scale


def test_small_perturbation_near_the_stationarity_tolerance_is_flagged(crossing):
    """A deviation whose stationarity is 3x the default tolerance fails (a 1000x looser
    tolerance would pass it); the unperturbed solution is far inside."""
    g, p, _, sol = crossing
    s0, scale0 = _stat_and_scale(g, sol.controls, p)
    tol = 1e-5  # the documented default (docs/solvers.md), not read from the code
    assert s0 < 0.01 * tol * scale0
    s1, _ = _stat_and_scale(g, _perturbed(g, sol, 1e-3), p)
    u = _perturbed(g, sol, 1e-3 * 3 * tol * scale0 / s1)  # stationarity is linear in eps here
    s, scale = _stat_and_scale(g, u, p)
    assert 2 * tol * scale < s < 4 * tol * scale
    cert = nash_certificate(g, p, u, {"best_response": False})
    assert not cert.ok and not cert.stat_ok[1]  # (agent 0 is coupled by the collision term)
    assert cert.stationarity[1] == pytest.approx(s, rel=1e-12)
    assert nash_certificate(g, p, sol.controls, {"best_response": False}).ok


def test_stationarity_exactly_at_the_tolerance_passes(crossing):
    g, p, _, sol = crossing
    u = _perturbed(g, sol, 1e-3)
    rel = [s / scale for s, scale in (_stat_and_scale(g, u, p, i) for i in range(g.N))]
    at, worst = max(rel), int(np.argmax(rel))
    s, scale = _stat_and_scale(g, u, p, worst)
    exact = _exactly(s, scale)  # exact * scale == s in floating point: "at" the tolerance
    assert nash_certificate(g, p, u, {"best_response": False, "stat_tol": exact}).ok
    below = nash_certificate(g, p, u, {"best_response": False, "stat_tol": at * (1 - 1e-9)})
    assert not below.ok and not below.stat_ok[worst]


def _exactly(value, scale):
    """A tolerance ``t`` with ``t * scale == value`` exactly (found next to value / scale)."""
    t = value / scale
    for _ in range(64):
        if t * scale == value:
            return t
        t = np.nextafter(t, np.inf if t * scale < value else -np.inf)
    raise AssertionError("no exact tolerance found")


def test_best_response_gap_at_and_near_the_tolerance(crossing):
    """The gap of a small deviation is ~quadratic in its size: one 3x the default gap
    tolerance fails, and a tolerance just above the measured relative gap passes."""
    g, p, _, sol = crossing
    tol = 1e-6  # the documented default, not read from the code
    loose = {"stat_tol": 1.0}  # isolate the gap test
    g1 = nash_certificate(g, p, _perturbed(g, sol, 0.05), loose).relative_gap[1]
    assert g1 > 100 * tol
    u = _perturbed(g, sol, 0.05 * np.sqrt(3 * tol / g1))
    cert = nash_certificate(g, p, u, loose)
    assert 2 * tol < cert.relative_gap[1] < 4 * tol
    assert not cert.ok and list(cert.gap_ok) == [True, False]
    at = cert.relative_gap[1]
    scale = cert.best_response_gap[1] / at
    exact = _exactly(
        cert.best_response_gap[1], 1 + min(abs(cert.costs[1]), NashOptions().scale_cap)
    )
    on = nash_certificate(g, p, u, {**loose, "gap_tol": exact})
    assert on.best_response_gap[1] == cert.best_response_gap[1]  # the same best response
    assert on.ok and scale == pytest.approx(1 + abs(cert.costs[1]), rel=1e-12)
    assert not nash_certificate(g, p, u, {**loose, "gap_tol": at * (1 - 1e-6)}).ok
