"""The stage-wise VJP of one unrolled LM step (solvers/fast_vjp.py) against the reference.

The reference is the layer's monolithic ``lm_step_vjp`` (one CasADi graph of the whole
trajectory, learning/layer.py), itself checked against finite differences through the
layer's gradchecks (tests/test_layer.py). Games cover what the stage construction has to
get right: several stage patterns (a collision term every 5th step), rows that couple
stages through lagged controls (jerk, turn acceleration of unicycles) and lagged states
(turn acceleration of bicycles), path terms with polyline parameters, terminal rows, and
collisions that are active at the test points.
"""

from __future__ import annotations

import functools

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
    TurnAcceleration,
    TurnRate,
    Velocity,
)
from learning.layer_core import layer_functions
from solvers.batch import BatchFunction
from solvers.fast_vjp import staged_step_vjp, staged_vjp_info
from solvers.structured import stage_layout

from .helpers import crossing_game


@functools.cache
def bicycle_lag_game(K: int = 9) -> PotentialGame:
    """Two bicycles with jerk and turn acceleration: rows couple x_k, u_k, x_{k+1}, u_{k+1}."""
    feats = [
        Goal(weight=2.0),
        Velocity(weight=0.5),
        Acceleration(),
        TurnRate(),
        Jerk(weight=0.3),
        TurnAcceleration(weight=0.4),
    ]
    dyn = {"type": "bicycle", "wheelbase": 0.5}
    agents = [
        AgentSpec("a", dyn, feats, radius=0.3, x0=[-1, 0, 1, 0.1], goal=[2, 0.5]),
        AgentSpec("b", dyn, feats, radius=0.3, x0=[1, 0.2, 1, 3.0], goal=[-2, -0.5]),
    ]
    return PotentialGame(GameSpec(agents, [Collision(weight=8.0, every=2)], horizon=K, dt=0.1))


@functools.cache
def left_turn_game(K: int = 10) -> PotentialGame:
    """The left-turn dataset's game (path terms, jerk, turn acceleration) at horizon K."""
    from scenarios.left_turn import LeftTurnRecipe, LeftTurnScenario

    return LeftTurnScenario(LeftTurnRecipe(horizon=K)).game


@functools.cache
def exid_game(K: int = 10) -> PotentialGame:
    """The exiD dataset's game (four agents, collision every 5th step) at horizon K."""
    from scenarios.exid import ExidRecipe, ExidScenario

    return ExidScenario(ExidRecipe(horizon=K, collision_every=5)).game


GAMES = {
    "crossing3": lambda: crossing_game(N=3, K=8),
    "bicycle_lags": bicycle_lag_game,
    "left_turn": left_turn_game,
    "exid": exid_game,
}


def points(game: PotentialGame, B: int = 3, seed: int = 0):
    """``(U, P, DU, Z)`` for B problems: default parameters with jittered goals and the
    agents' start positions packed within a few decimetres (collisions active)."""
    rng = np.random.default_rng(seed)
    P = np.tile(game.params.defaults(), (B, 1))
    for i, a in enumerate(game.agents):
        s = game.params[f"x0.{a.name}"].start
        P[:, s : s + 2] = 0.25 * np.array([np.cos(i), np.sin(i)]) + rng.normal(
            scale=0.05, size=(B, 2)
        )
    goal = game.params.group("goal")
    P[:, goal] += rng.normal(scale=0.3, size=(B, goal.size))
    U, DU, Z = (rng.normal(scale=0.4, size=(B, game.n_u)) for _ in range(3))
    return U, P, DU, Z


def collision_active(game: PotentialGame, U: np.ndarray, P: np.ndarray) -> bool:
    r = BatchFunction(game.function("residual"), 1)(U, P)[0]
    rows = [t.rows for t in game.terms if t.feature == "collision"]
    return bool(np.any(np.abs(np.concatenate([r[:, s] for s in rows], axis=1)) > 0))


def assert_equal_to_rounding(got, ref):
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.max(np.abs(b)))


@pytest.mark.parametrize("name", list(GAMES))
def test_staged_vjp_equals_monolithic(name):
    game = GAMES[name]()
    f = staged_step_vjp(game)
    assert f is not None and f.name_in() == ["u", "p", "du", "z"]
    assert f.name_out() == ["gu", "gp"]
    U, P, DU, Z = points(game)
    assert collision_active(game, U, P)
    got = BatchFunction(f, 1)(U, P, DU, Z)
    ref = BatchFunction(layer_functions(game, "lm_step_vjp"), 1)(U, P, DU, Z)
    assert np.max(np.abs(ref[0])) > 1 and np.max(np.abs(ref[1])) > 1
    assert_equal_to_rounding(got, ref)


def test_the_games_have_the_structure_they_claim():
    """Lags (rows coupling stages) and several stage patterns, read from the games."""
    lags = stage_layout(bicycle_lag_game())
    assert lags.x_lags and lags.u_lags and lags.coupled_rows > 0
    lt = left_turn_game()
    assert stage_layout(lt).u_lags and lt.params.group("path").size > 0
    # first, middle, terminal; exiD: and the collision stages
    assert staged_vjp_info(lt)["groups"] == 3
    assert staged_vjp_info(exid_game())["groups"] >= 4
    assert staged_vjp_info(bicycle_lag_game())["groups"] >= 4


def test_staged_vjp_is_built_once_and_refuses_coupled_dynamics():
    game = crossing_game(N=2, K=5)
    assert staged_step_vjp(game) is staged_step_vjp(game)
    from .test_extending import _coupled_game

    coupled = _coupled_game()[0]
    assert staged_step_vjp(coupled) is None
    assert "coupled" in staged_vjp_info(coupled)["reason"]


def test_compiled_staged_vjp_equals_monolithic(tmp_path):
    pytest.importorskip("solvers.codegen").find_compiler()
    from solvers.codegen import compile_functions

    game = bicycle_lag_game(K=6)
    f = staged_step_vjp(game)
    c = compile_functions([f], "epo_test_vjp_staged", tmp_path)[f.name()]
    U, P, DU, Z = points(game, B=5, seed=1)
    got = BatchFunction(c, 2)(U, P, DU, Z)
    ref = BatchFunction(layer_functions(game, "lm_step_vjp"), 1)(U, P, DU, Z)
    assert_equal_to_rounding(got, ref)
