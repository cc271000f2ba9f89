"""Every solver's default options converge on a seeded family of games and on the examples.

The family (``tests/helpers.FAMILY``, built by ``family_spec``) goes beyond the shipped
examples: N = 2..6 agents, unicycles and bicycles, collision weights 1..100, crossing,
intersection and merge layouts, two of them with a jerk term (cross-stage costs), horizon
25. Every game starts in collision with zero controls (asserted), so every solve has to
resolve an interaction.

``converged`` is checked against a first-order test computed here, not only the solver's
word: for LM and IPOPT the gradient of the potential from the game's own ``gradient``
function; for iLQ a fresh solve started at the returned controls must stop at once (its
feed-forward term, recomputed from a new rollout, is within tolerance).

IPOPT builds an exact-Hessian NLP per game (seconds for 4 or more agents), so it sweeps the
games with N <= 3 here; ``EPO_SWEEP_ALL=1`` sweeps every game (all converged when this file
was written: 12 games, about 35 s for IPOPT alone on 2 shared cores).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from epo_casadi import PotentialGame
from scenarios.gamefile import EXAMPLES, example_path, load_game
from solvers.ilq import solve_ilq
from solvers.ipopt import solve_ipopt
from solvers.lm import solve_lm
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


#: iLQ on this game stops 'stalled' (regularized_only): the feedback iteration chatters on
#: the collision hinge (a pair sits at gap 4e-7 where the Gauss-Newton curvature and so the
#: other players' gains switch), and max |a| <= tol holds only with raised regularization,
#: which drives towards the open-loop point instead. Reported honestly, not yet fixed.
ILQ_KNOWN_STALL = {"intersection-4-unicycle-w30-s3"}


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


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.xfail(strict=True, reason="known iLQ stall"))
        if n in ILQ_KNOWN_STALL
        else n
        for n in NAMES
    ],
)
def test_ilq_defaults_converge(name):
    g, p = game_of(name)
    res = solve_ilq(g, p)
    assert res.status is Status.CONVERGED, (res.status, res.info["stop"])
    assert res.info["stationarity"] <= 1e-5
    again = solve_ilq(g, p, res.controls)
    assert again.status is Status.CONVERGED and again.iterations == 0


def test_ilq_known_stall_is_reported_as_stalled():
    """The game iLQ cannot finish is reported 'stalled', never 'converged' or 'max_iter':
    at the requested regularization its max |a| is above the tolerance."""
    (name,) = ILQ_KNOWN_STALL
    g, p = game_of(name)
    res = solve_ilq(g, p)
    assert res.status is Status.STALLED and res.info["stop"] == "regularized_only"
    assert res.info["stationarity"] > 1e-5
    assert not res.ok
