"""Every solver's default options converge on a seeded family of games and on the examples.

The family (``tests/helpers.FAMILY``, built by ``family_spec``) goes beyond the shipped
examples: N = 2..6 agents, unicycles and bicycles, collision weights 1..100, crossing,
intersection and merge layouts, two of them with a jerk term (cross-stage costs), horizon
25. Every game starts in collision with zero controls (asserted), so every solve has to
resolve an interaction.

``converged`` is checked against a first-order test computed here, not only the solver's
word: for LM and IPOPT the gradient of the potential from the game's own ``gradient``
function; for iLQ a fresh solve started at the returned controls must stop at once (its
feed-forward term, recomputed from a new rollout, is within tolerance) and the sampled
feedback-Nash check (solvers.feedback_nash) must find no player that gains by deviating.

These call the solvers' entry functions themselves, so each family game converges at the
first attempt. The registry's solve (``solve_game``, ``epo solve``, ``epo compare``) adds
the continuation fallback (solvers.continuation); ``HARD_GAME`` is a game where first
attempts end at their iteration limit, and every solver's registered default converges on
it, by the same first-order tests and the Nash certificate.

IPOPT builds an exact-Hessian NLP per game (1-3 s of CPU for 4 or more agents), so it
sweeps the games with N <= 3 here; ``EPO_SWEEP_ALL=1`` sweeps every game (all 12 converged
on 2026-11-30; the LM and IPOPT tests together took 38 s on 2 shared cores).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from epo_casadi import PotentialGame
from scenarios.gamefile import EXAMPLES, example_path, load_game
from solvers.feedback_nash import check_ilq_result
from solvers.ilq import ILQOptions, solve_ilq
from solvers.ipopt import solve_ipopt
from solvers.lm import solve_lm
from solvers.nash import nash_certificate
from solvers.registry import solve_game
from solvers.result import Status

from .helpers import FAMILY, family_spec


def _name(layout, N, dyn, w, seed, jerk):
    return f"{layout}-{N}-{dyn}-w{w:g}-s{seed}" + ("-jerk" if jerk else "")


FAMILY_NAMES = {_name(*f): f for f in FAMILY}
NAMES = list(FAMILY_NAMES) + list(EXAMPLES)
_cache: dict = {}


def game_of(name: str) -> tuple[PotentialGame, np.ndarray]:
    if name not in _cache:
        if name in FAMILY_NAMES:
            layout, N, dyn, w, seed, jerk = FAMILY_NAMES[name]
            g = PotentialGame(family_spec(layout, N, dyn, w, seed, jerk=jerk))
            _cache[name] = (g, g.default_params())
        else:
            gf = load_game(example_path(name))
            _cache[name] = (gf.game, gf.params)
    return _cache[name]


def _ipopt_here(name: str) -> bool:
    if os.environ.get("EPO_SWEEP_ALL") == "1":
        return True
    return game_of(name)[0].N <= 3 and name not in ("highway_merge",)


#: the game where iLQ's line search fails at a collision kink (a pair at gap 4e-7 of its
#: hinge, where the Gauss-Newton curvature and with it the gains switch): the kink
#: continuation (ILQOptions.kink_widths) is what makes it converge (docs/ilq.md)
ILQ_KINK_GAME = "intersection-4-unicycle-w30-s3"


@pytest.mark.parametrize("name", NAMES)
def test_every_game_starts_in_collision(name):
    g, p = game_of(name)
    coll = [t.index for t in g.terms if t.feature_type == "collision"]
    te = np.asarray(g.function("term_energies")(g.zero_controls(), p)).ravel()
    assert sum(te[i] for i in coll) > 1e-2


def _check_potential_stationary(g, p, res):
    grad = np.abs(np.asarray(g.function("gradient")(res.controls, p))).max()
    # scale-aware: LM stops by ftol with |grad| up to ~4e-5 on the examples (docs/solvers.md)
    assert grad <= 1e-4 * (1.0 + abs(float(res.energy))), grad


@pytest.mark.parametrize("name", NAMES)
def test_lm_defaults_converge(name):
    g, p = game_of(name)
    res = solve_lm(g, p)
    assert res.status is Status.CONVERGED, (res.status, res.info["stop"], res.grad_norm)
    _check_potential_stationary(g, p, res)


@pytest.mark.parametrize("name", NAMES)
def test_ipopt_defaults_converge(name):
    if not _ipopt_here(name):
        pytest.skip("IPOPT's NLP build takes seconds here; EPO_SWEEP_ALL=1 runs it")
    g, p = game_of(name)
    res = solve_ipopt(g, p)
    assert res.status is Status.CONVERGED, (res.status, res.info["return_status"])
    _check_potential_stationary(g, p, res)


@pytest.mark.parametrize("name", NAMES)
def test_ilq_defaults_converge(name):
    """Converged by iLQ's own first-order test (a fresh solve from the result stops at once)
    and by the sampled feedback-Nash check (no player gains by deviating from its policy)."""
    g, p = game_of(name)
    res = solve_ilq(g, p)
    assert res.status is Status.CONVERGED, (res.status, res.info["stop"])
    assert res.info["stationarity"] <= 1e-5
    again = solve_ilq(g, p, res.controls)
    assert again.status is Status.CONVERGED and again.iterations == 0
    check = check_ilq_result(g, p, res)
    assert check.ok, check.gain


def test_ilq_kink_continuation_is_what_converges_the_hinge_game():
    """Without the continuation the game ends 'stalled' (never 'converged' or 'max_iter');
    with it (the default) the result is judged at the exact kinks: a solve from it with the
    continuation off stops at once."""
    g, p = game_of(ILQ_KINK_GAME)
    off = solve_ilq(g, p, options={"kink_widths": (), "restart": False})
    assert off.status is Status.STALLED and not off.ok
    assert off.info["stationarity"] > 1e-3 and off.info["kink_continuation"] == []
    assert "restart" not in off.info and off.info["kink_equilibrium"] is None
    res = solve_ilq(g, p)
    assert res.status is Status.CONVERGED
    widths = [w for _, w in res.info["kink_continuation"]]
    assert widths[0] == ILQOptions().kink_widths[0] and widths[-1] == 0.0
    again = solve_ilq(g, p, res.controls, options={"kink_widths": ()})
    assert again.status is Status.CONVERGED and again.iterations == 0


def test_ilq_stalled_solve_restarts_from_the_open_loop_equilibrium():
    """Without the continuation the kink game stalls; the default restart (ILQOptions.restart)
    then solves once more from LM's open-loop equilibrium, within the same max_iter, and that
    solve converges by iLQ's own test: a solve from its result stops at once, and the sampled
    feedback-Nash check passes. The iterations of both attempts are counted."""
    g, p = game_of(ILQ_KINK_GAME)
    off = solve_ilq(g, p, options={"kink_widths": (), "restart": False})
    res = solve_ilq(g, p, options={"kink_widths": ()})
    assert res.status is Status.CONVERGED and res.info["stop"] == "tol"
    r = res.info["restart"]
    assert r["at"] == off.iterations and r["stop"] == off.info["stop"] and r["result"] == "tol"
    assert off.iterations < res.iterations <= ILQOptions().max_iter
    again = solve_ilq(g, p, res.controls, options={"kink_widths": (), "restart": False})
    assert again.status is Status.CONVERGED and again.iterations == 0
    check = check_ilq_result(g, p, res)
    assert check.ok, check.gain
    # a budget the first attempt uses up leaves none for a restart: its own status stays
    short = solve_ilq(g, p, options={"kink_widths": (), "max_iter": int(off.iterations)})
    assert short.status is not Status.CONVERGED and "restart" not in short.info


#: the 6-vehicle bicycle intersection at collision weight 300, K = 20: the first attempts of
#: LM, SQP and OLNE end at their iteration limits (LM with an energy 5.7 times the
#: continuation's); IPOPT and iLQ converge at once
HARD_GAME = ("intersection", 6, "bicycle", 300.0, 0, 20)


@pytest.mark.parametrize("solver", ["lm", "ipopt", "ilq", "sqp", "olne"])
def test_registered_defaults_converge_on_the_hard_game(solver):
    name = "hard:" + _name(*HARD_GAME[:5], False)
    if name not in _cache:
        g = PotentialGame(family_spec(*HARD_GAME))
        _cache[name] = (g, g.default_params())
    g, p = _cache[name]
    res = solve_game(g, p, solver=solver)
    assert res.status is Status.CONVERGED, (res.status, res.info.get("attempts"))
    if solver == "ilq":
        check = check_ilq_result(g, p, res)
        assert check.ok, check.gain
        return
    _check_potential_stationary(g, p, res)
    assert nash_certificate(g, p=p, u=res.controls).verdict == "passes"
    if solver in ("lm", "sqp", "olne"):  # their first attempts stop at max_iter
        first = res.info["attempts"][0]
        assert first["status"] == "max_iter" and res.info["attempts"][-1]["kept"]
