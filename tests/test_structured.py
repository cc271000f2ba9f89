"""StructuredGN (Riccati over stages) against DenseGN (dense J'J, Cholesky): same numbers.

The dense backend is the independent reference: it forms J from CasADi's Jacobian of the
rolled-out residual and solves the damped normal equations with a batched Cholesky. The
structured backend never forms J; equal steps to float64 round-off show that the stage
decomposition (including lagged states for rows that couple stages) is exact.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest

from epo_casadi import (
    Acceleration,
    AgentSpec,
    Collision,
    GameSpec,
    PotentialGame,
)
from solvers.lm import DenseGN, LMOptions, _merge, solve_lm
from solvers.structured import StructuredGN, StructuredLinearization, stage_layout
from tests.helpers import crossing_game

RTOL = 1e-9


def _close(a, b, rtol=RTOL):
    """Equal up to ``rtol`` relative to the largest entry of the reference."""
    scale = max(float(np.max(np.abs(b))), 1e-300)
    np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale)


@dataclass(frozen=True)
class SecondDifference(Acceleration):
    """Test-only feature coupling three stages: second differences of u and of the speed.

    ``a_{k+2} - 2 a_{k+1} + a_k + speed(x_{k+2}) - speed(x_k)``: lags of 2 in both the
    controls and the states, which no built-in feature has.
    """

    kind: ClassVar[str] = "acceleration"  # registered kind, so AgentSpec accepts it
    label: str | None = "second_difference"

    def steps(self, K):
        return list(range(K - 2))

    def residual(self, ctx):
        import casadi as ca

        acc, spd = ctx.dynamics.acceleration, ctx.dynamics.speed
        X, U = ctx.X, ctx.U
        return ca.vertcat(
            *[
                acc(U[:, k + 2])
                - 2 * acc(U[:, k + 1])
                + acc(U[:, k])
                + spd(X[:, k + 2])
                - spd(X[:, k])
                for k in self.steps(ctx.K)
            ]
        )


@dataclass(frozen=True)
class TotalAcceleration(Acceleration):
    """Test-only feature whose one row touches every stage (forces the dense fallback)."""

    kind: ClassVar[str] = "acceleration"
    label: str | None = "total_acceleration"

    def steps(self, K):
        return [0]

    def residual(self, ctx):
        import casadi as ca

        return ca.sum2(ctx.U[0, :])


def _two_agent_game(dynamics, features, K=12, pair=True):
    agents = [
        AgentSpec(
            "a",
            dynamics,
            features,
            x0=[0, 0, 1.0, 0.1],
            goal=[3, 1],
            vref=1.0,
            path=[[0, 0], [2, 1], [4, 0]],
        ),
        AgentSpec(
            "b",
            dynamics,
            features,
            x0=[3, 0.2, 1.0, 3.0],
            goal=[0, 1],
            vref=1.2,
            path=[[3, 0], [1, 1], [0, 2]],
        ),
    ]
    pfs = [Collision(weight=5.0, every=2)] if pair else []
    return PotentialGame(GameSpec(agents, pfs, horizon=K, dt=0.1))


COUPLED = [
    "goal",
    "acceleration",
    "jerk",
    "turn_rate",
    "turn_acceleration",
    {"type": "acceleration_bound", "lower": -0.5, "upper": 0.5},
]

GAMES = {
    "crossing_n2": lambda: crossing_game(N=2, K=40, offset=0.3),
    "crossing_n3": lambda: crossing_game(N=3, K=40, offset=0.2),
    "unicycle_jerk_turn_acc": lambda: _two_agent_game("unicycle", COUPLED),
    "double_integrator": lambda: _two_agent_game(
        "double_integrator",
        [
            "goal",
            "velocity",
            "acceleration",
            "jerk",
            {"type": "velocity_bound", "upper": 0.8},
            "path",
        ],
    ),
    "bicycle": lambda: _two_agent_game(
        {"type": "bicycle", "wheelbase": 2.0},
        [
            "goal",
            "velocity",
            "jerk",
            "turn_rate",
            "turn_acceleration",
            "reference_velocity",
            "path",
            {"type": "turn_rate_bound", "lower": -0.3, "upper": 0.3},
        ],
    ),
    "second_difference": lambda: _two_agent_game(
        "unicycle", ["goal", "acceleration", SecondDifference()], K=30
    ),
}


def _batch(game, B=4, seed=0):
    """Different controls, initial states, references and weights per problem."""
    rng = np.random.default_rng(seed)
    U = 0.4 * rng.normal(size=(B, game.n_u))
    P = np.tile(game.default_params(), (B, 1))
    P *= 1 + 0.1 * rng.uniform(-1, 1, size=P.shape)  # weights, x0, goals all vary
    lam = 10.0 ** rng.uniform(-2, 1.5, size=B)
    return U, P, lam


@pytest.fixture(scope="module", params=sorted(GAMES))
def case(request):
    game = GAMES[request.param]()
    return request.param, game, StructuredGN(game, threads=1), DenseGN(game, threads=1)


def test_layout_from_sparsity():
    lay = stage_layout(crossing_game(N=2, K=10))
    assert (lay.n, lay.m, lay.nz, lay.coupled_rows) == (8, 4, 8, 0)
    assert lay.x_lags == () and lay.u_lags == ()
    # jerk and turn_acceleration of a unicycle couple u_k and u_{k+1}: one control lag
    lay = stage_layout(_two_agent_game("unicycle", COUPLED))
    assert lay.x_lags == () and lay.u_lags == ((0, 1, 2, 3),) and lay.coupled_rows > 0
    # a bicycle's turn rate reads the speed x[2]: turn_acceleration needs x_k[2] too
    lay = stage_layout(_two_agent_game({"type": "bicycle"}, ["turn_acceleration"], pair=False))
    assert lay.x_lags == ((2, 6),) and lay.u_lags == ((1, 3),)
    lay = stage_layout(GAMES["second_difference"]())  # speed is x[2], acceleration u[0]
    assert lay.x_lags == ((2, 6), (2, 6)) and lay.u_lags == ((0, 2), (0, 2))


def test_linearization_matches_dense(case):
    name, game, sg, dg = case
    U, P, _ = _batch(game)
    ls, ld = sg.linearize(U, P), dg.linearize(U, P)
    assert isinstance(ls, StructuredLinearization) and sg.fallback is None
    _close(ls.energy, ld.energy, 1e-12)
    _close(ls.gradient, ld.gradient)
    _close(
        ls.diag_jtj().reshape(len(U), -1)[:, np.argsort(sg._u_index)], np.einsum("bii->bi", ld.JtJ)
    )
    _close(sg.energy(U, P), ld.energy, 1e-12)


@pytest.mark.parametrize("ellipsoidal", [False, True])
def test_step_matches_dense(case, ellipsoidal):
    name, game, sg, dg = case
    U, P, lam = _batch(game, seed=1)
    ls, ld = sg.linearize(U, P), dg.linearize(U, P)
    if name.startswith("crossing"):  # the regime: some collision residuals are active
        pair_rows = np.concatenate(
            [np.arange(t.rows.start, t.rows.stop) for t in game.terms if t.kind == "pair"]
        )
        assert np.any(ld.r[:, pair_rows] > 0)
    _close(
        sg.solve(ls, lam, -ls.gradient, ellipsoidal), dg.solve(ld, lam, -ld.gradient, ellipsoidal)
    )


def test_arbitrary_rhs_and_damping_cache(case):
    _, game, sg, dg = case
    U, P, lam = _batch(game, seed=2)
    ls, ld = sg.linearize(U, P), dg.linearize(U, P)
    V = np.random.default_rng(3).normal(size=(len(U), game.n_u))
    for damping, ell in [
        (lam, False),
        (lam, False),
        (2 * lam, False),
        (lam, True),
        (2 * lam, False),
    ]:
        x = sg.solve(ls, damping, V, ell)  # cached factor reused or rebuilt for new damping
        _close(x, dg.solve(ld, damping, V, ell))
    # the solution satisfies the system: (J'J + lam I) x = v
    x = sg.solve(ls, lam, V)
    res = np.einsum("bij,bj->bi", ld.JtJ, x) + lam[:, None] * x - V
    assert np.max(np.abs(res)) <= 1e-9 * np.max(np.abs(V))


@pytest.mark.parametrize(
    "opts",
    [LMOptions(steps=15), LMOptions.paper(), LMOptions(steps=10, ellipsoidal=True)],
    ids=["adaptive", "paper", "ellipsoidal"],
)
def test_solve_lm_backends_agree(opts):
    game = _two_agent_game("unicycle", COUPLED, K=20)
    assert StructuredGN(game, threads=1).fallback is None
    _, P, _ = _batch(game, B=3, seed=4)
    rd = solve_lm(game, P, options=opts)
    rs = solve_lm(game, P, options=LMOptions(**{**opts.__dict__, "backend": "structured"}))
    _close(rs.controls, rd.controls)
    _close(rs.energy, rd.energy)
    np.testing.assert_array_equal(rs.iterations, rd.iterations)
    assert list(rs.status) == list(rd.status)
    assert np.all(rs.energy < rs.energy_history[0])  # the solve did something


def test_merge_of_frozen_problems_still_solves():
    """solve_lm's ``_merge`` (problems frozen as non-finite) reads J/JtJ: still exact."""
    game = crossing_game(N=2, K=20)
    sg, dg = StructuredGN(game, threads=1), DenseGN(game, threads=1)
    assert sg.fallback is None
    U, P, lam = _batch(game, B=3, seed=5)
    a, b = sg.linearize(U, P), sg.linearize(U + 0.1, P)
    keep = np.array([True, False, True])
    merged = _merge(a, b, keep)  # a dense Linearization built from lazy dense properties
    ref = _merge(dg.linearize(U, P), dg.linearize(U + 0.1, P), keep)
    _close(sg.solve(merged, lam, -merged.gradient), dg.solve(ref, lam, -ref.gradient))
    sel = b.select(a, ~keep)  # the structured merge a patched _merge would use
    _close(sg.solve(sel, lam, -sel.gradient), dg.solve(ref, lam, -ref.gradient))


def test_fallback_when_rows_couple_every_stage():
    game = _two_agent_game("unicycle", ["goal", "acceleration", TotalAcceleration()], K=10)
    sg = StructuredGN(game, threads=1)
    assert sg.fallback is not None and "DenseGN" in sg.fallback
    U, P, lam = _batch(game, seed=6)
    ls, ld = sg.linearize(U, P), DenseGN(game, threads=1).linearize(U, P)
    _close(sg.solve(ls, lam, -ls.gradient), DenseGN.solve(ld, lam, -ld.gradient))


def test_bad_rhs_shape_is_an_error():
    game = crossing_game(N=2, K=20)
    sg = StructuredGN(game, threads=1)
    assert sg.fallback is None
    U, P, lam = _batch(game, B=2)
    lin = sg.linearize(U, P)
    with pytest.raises(ValueError, match="rhs"):
        sg.solve(lin, lam, np.zeros((2, game.n_u + 1)))
