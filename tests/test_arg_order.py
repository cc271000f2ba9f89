"""One argument order ``(game, p, u)``: the certificate and the inspection helpers take the
solvers' order, positionally or as keywords; ``(game, u, p)`` is refused by the sizes it gets
(``n_u != n_p``) and never read by guessing."""

from __future__ import annotations

import inspect as pyinspect
import warnings

import numpy as np
import pytest

from epo_casadi import Acceleration, AgentSpec, GameSpec, Goal, PotentialGame, SpecError
from epo_casadi import inspect as ins
from solvers.nash import NashChecker, nash_certificate

NO_BR = {"best_response": False}  # the stationarity test only: fast, same for every order


def small_game(K: int) -> PotentialGame:
    """Two double integrators; ``n_u = 4 K``, ``n_p = 16`` (equal at ``K = 4``)."""
    agents = [
        AgentSpec(n, "double_integrator", [Goal(weight=1.0), Acceleration()], x0=x0, goal=gl)
        for n, x0, gl in [("a", [0, 0, 1, 0], [1, 0.5]), ("b", [1, 1, 0, -1], [0, -1])]
    ]
    return PotentialGame(GameSpec(agents, [], horizon=K, dt=0.1))


@pytest.fixture(scope="module")
def game():
    g = small_game(5)
    assert (g.n_u, g.n_p) == (20, 16)
    u = np.random.default_rng(0).standard_normal(g.n_u)
    return g, g.default_params(), u


@pytest.fixture(scope="module")
def square():
    g = small_game(4)
    assert g.n_u == g.n_p == 16
    u = np.random.default_rng(1).standard_normal(g.n_u)
    return g, g.default_params(), u


def _cert(c):
    return c.ok, c.costs.tolist(), c.stationarity.tolist()


# name, call(f, game, first, second, *rest), normalise the result for comparison
CASES = {
    "nash_certificate": (lambda g, a, b: nash_certificate(g, a, b, NO_BR), _cert),
    "certify": (lambda g, a, b: NashChecker(g, NO_BR).certify(a, b), _cert),
    "energy_breakdown": (lambda g, a, b: ins.energy_breakdown(g, a, b), lambda r: r),
    "agent_breakdown": (lambda g, a, b: ins.agent_breakdown(g, a, b), lambda r: r),
    "breakdown_table": (lambda g, a, b: ins.breakdown_table(g, a, b), lambda r: r),
    "term_series": (lambda g, a, b: ins.term_series(g, a, b), lambda r: r),
}


def test_signatures_put_p_before_u():
    for f in (
        nash_certificate,
        NashChecker.certify,
        ins.energy_breakdown,
        ins.agent_breakdown,
        ins.breakdown_table,
        ins.term_series,
        ins.inspect_report,
    ):
        names = list(pyinspect.signature(f).parameters)
        assert names.index("p") < names.index("u"), f.__name__


def test_new_order_matches_the_game_functions(game):
    """Reference: the game's own CasADi functions, which take ``(u, p)`` column vectors."""
    g, p, u = game
    e = np.asarray(g.function("term_energies")(u, p)).ravel()
    C = np.asarray(g.function("agent_costs")(u, p)).ravel()
    rows = ins.energy_breakdown(g, p, u)
    np.testing.assert_allclose([r["energy"] for r in rows], e, rtol=1e-12)
    assert e.sum() > 0.1  # a non-trivial point
    np.testing.assert_allclose([a["cost"] for a in ins.agent_breakdown(g, p, u)], C, rtol=1e-12)
    np.testing.assert_allclose([s["total"] for s in ins.term_series(g, p, u)], e, rtol=1e-12)
    cert = nash_certificate(g, p, u, NO_BR)
    np.testing.assert_allclose(cert.costs, C, rtol=1e-12)
    pg = np.asarray(g.function("pseudo_gradient")(u, p)).ravel()
    stat = [np.abs(pg[g.uoff[i] : g.uoff[i + 1]]).max() for i in range(g.N)]
    np.testing.assert_allclose(cert.stationarity, stat, rtol=1e-12)
    assert not cert.ok  # a random strategy is not stationary


@pytest.mark.parametrize("name", list(CASES))
def test_old_order_is_refused(game, name):
    """``(game, u, p)`` is not read by size: the ``u`` it passes as ``p`` has the wrong size."""
    g, p, u = game
    call, norm = CASES[name]
    new = norm(call(g, p, u))
    with pytest.raises(SpecError, match=r"^u: expected last dimension n_u = 20, got shape \(16,\)"):
        call(g, u, p)
    # keywords are always the same call, in either order
    if name == "nash_certificate":
        assert _cert(nash_certificate(g, u=u, p=p, options=NO_BR)) == new
        with pytest.raises(TypeError, match="multiple values for argument 'p'"):
            nash_certificate(g, u, p=p, options=NO_BR)  # old order with p as a keyword
    if name == "energy_breakdown":
        assert ins.energy_breakdown(g, u=u, p=p) == new
        assert ins.energy_breakdown(g, p, u=u) == new


def test_no_deprecation_warning(game):
    g, p, u = game
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for call, _ in CASES.values():
            call(g, p, u)
            with pytest.raises(SpecError):
                call(g, u, p)


# the same calls with keywords
KEYWORDS = {
    "nash_certificate": lambda g, p, u: nash_certificate(g, p=p, u=u, options=NO_BR),
    "certify": lambda g, p, u: NashChecker(g, NO_BR).certify(p=p, u=u),
    "energy_breakdown": lambda g, p, u: ins.energy_breakdown(g, p=p, u=u),
    "agent_breakdown": lambda g, p, u: ins.agent_breakdown(g, p=p, u=u),
    "breakdown_table": lambda g, p, u: ins.breakdown_table(g, p=p, u=u),
    "term_series": lambda g, p, u: ins.term_series(g, p=p, u=u),
}


@pytest.mark.parametrize("name", list(CASES))
def test_equal_sizes_positional_is_p_then_u(square, name):
    """With ``n_u == n_p`` a positional call is read in the documented order, like keywords;
    swapped arrays are another point, not the same result read by size."""
    g, p, u = square
    call, norm = CASES[name]
    new = norm(call(g, p, u))
    assert new == norm(KEYWORDS[name](g, p, u))
    assert norm(call(g, u, p)) != new


def test_equal_sizes_keywords_work(square):
    g, p, u = square
    e = np.asarray(g.function("term_energies")(u, p)).ravel()
    rows = ins.energy_breakdown(g, p=p, u=u)
    np.testing.assert_allclose([r["energy"] for r in rows], e, rtol=1e-12)
    C = np.asarray(g.function("agent_costs")(u, p)).ravel()
    np.testing.assert_allclose(nash_certificate(g, p=p, u=u, options=NO_BR).costs, C)
    # internal calls use keywords: the report of a square game works
    rep = ins.inspect_report(g, p, u, hessian=False)
    np.testing.assert_allclose(rep["solution"]["energy"], e.sum(), rtol=1e-12)


def test_wrong_sizes_name_the_argument(game):
    g, p, u = game
    with pytest.raises(SpecError, match="^u: expected last dimension n_u = 20"):
        ins.energy_breakdown(g, p, u[:-1])
    with pytest.raises(SpecError, match="^p: expected last dimension n_p = 16"):
        nash_certificate(g, p[:-1], u)
