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
from solvers.lm import DenseGN, Linearization, LMOptions, _merge, solve_lm
from solvers.result import Status
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


class _Spy:
    """Wraps a backend and counts the calls that reach it (which backend really ran)."""

    def __init__(self, backend):
        self.backend, self.calls = backend, {"linearize": 0, "solve": 0, "energy": 0}

    def linearize(self, U, P):
        self.calls["linearize"] += 1
        return self.backend.linearize(U, P)

    def solve(self, lin, damping, rhs, ellipsoidal=False):
        self.calls["solve"] += 1
        if isinstance(self.backend, StructuredGN):  # the Riccati path, not a dense fallback
            assert isinstance(lin, StructuredLinearization)
        return self.backend.solve(lin, damping, rhs, ellipsoidal)

    def energy(self, U, P):
        self.calls["energy"] += 1
        return self.backend.energy(U, P)


@pytest.mark.parametrize(
    "opts",
    [LMOptions(steps=15), LMOptions.paper(), LMOptions(steps=10, ellipsoidal=True)],
    ids=["adaptive", "paper", "ellipsoidal"],
)
def test_solve_lm_backends_agree(opts):
    from solvers.lm import make_backend

    game = _two_agent_game("unicycle", COUPLED, K=20)
    _, P, _ = _batch(game, B=3, seed=4)
    runs = {}
    for name, cls in (("dense", DenseGN), ("structured", StructuredGN)):
        o = LMOptions(**{**opts.__dict__, "backend": name})
        be = make_backend(game, o)
        assert type(be) is cls  # options.backend picks the backend
        assert getattr(be, "fallback", None) is None
        spy = _Spy(be)
        runs[name] = solve_lm(game, P, options=o, backend=spy)
        assert spy.calls["linearize"] >= 2 and spy.calls["solve"] >= 2, name
        plain = solve_lm(game, P, options=o)  # the backend options name: the same numbers
        np.testing.assert_array_equal(plain.controls, runs[name].controls)
    rd, rs = runs["dense"], runs["structured"]
    _close(rs.controls, rd.controls)
    _close(rs.energy, rd.energy)
    np.testing.assert_array_equal(rs.iterations, rd.iterations)
    assert list(rs.status) == list(rd.status)
    assert np.all(rs.energy < rs.energy_history[0] - 1e-3)  # the solve did something


def _singular_batch():
    """A dense Linearization of 3 problems; problem 1 has a zero column in J (singular J'J)."""
    rng = np.random.default_rng(7)
    B, n_r, n_u = 3, 7, 4
    J = rng.normal(size=(B, n_r, n_u))
    J[1, :, 2] = 0.0
    r = rng.normal(size=(B, n_r))
    g = np.einsum("bij,bi->bj", J, r)
    lin = Linearization(r, J, 0.5 * (r * r).sum(1), g, J.transpose(0, 2, 1) @ J)
    return lin, rng.normal(size=(B, n_u))


def test_dense_solve_falls_back_per_problem_when_one_is_singular():
    lin, rhs = _singular_batch()
    damping = np.array([0.5, 0.0, 0.0])  # problem 1: J'J + 0 I is exactly singular
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(lin.JtJ + damping[:, None, None] * np.eye(4))  # the batch fails
    x = DenseGN.solve(lin, damping, rhs)
    assert np.isnan(x[1]).all()  # the singular problem is marked, not solved
    for b in (0, 2):  # the others: as solved alone (independent reference: lstsq)
        A = lin.JtJ[b] + damping[b] * np.eye(4)
        ref = np.linalg.lstsq(A, rhs[b], rcond=None)[0]
        np.testing.assert_allclose(x[b], ref, rtol=1e-10, atol=1e-12)
        assert np.abs(x[b]).max() > 1e-2
    ell = DenseGN.solve(lin, np.array([0.5, 0.5, 0.5]), rhs, ellipsoidal=True)
    # ellipsoidal: diag(J'J) is 0 in the zero column, clamped to 1e-12: still solvable
    A1 = lin.JtJ[1] + 0.5 * np.diag(np.maximum(np.diag(lin.JtJ[1]), 1e-12))
    np.testing.assert_allclose(ell[1], np.linalg.solve(A1, rhs[1]), rtol=1e-6)


@pytest.mark.parametrize("backend", ["dense", "structured"])
def test_solve_lm_with_a_singular_problem_finishes_the_others(backend):
    """solve_lm with zero damping: a problem whose J'J is exactly
    singular is marked non-finite; the other converges as when solved alone.

    Problem 1 keeps only the goal term: the last stage's controls then do not move the final
    position (explicit Euler), so their columns of J are exactly zero."""
    game = _two_agent_game("unicycle", ["goal", "acceleration", "turn_rate"], K=8, pair=False)
    P = np.tile(game.default_params(), (2, 1))
    for name in ("w.a.acceleration", "w.a.turn_rate", "w.b.acceleration", "w.b.turn_rate"):
        P[1, game.params[name].start] = 0.0
    J = DenseGN(game).linearize(np.zeros((2, game.n_u)), P).J
    assert np.any(np.all(J[1] == 0, axis=0)) and not np.any(np.all(J[0] == 0, axis=0))
    opts = LMOptions(backend=backend, damping=0.0, min_damping=0.0, steps=30)
    res = solve_lm(game, P, options=opts)
    assert res.status[1] is Status.NONFINITE
    np.testing.assert_array_equal(res.controls[1], 0.0)  # frozen at its start
    alone = solve_lm(game, P[0], options=opts)
    assert res.status[0] is alone.status is Status.CONVERGED
    np.testing.assert_allclose(res.controls[0], alone.controls, rtol=0, atol=1e-12)


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


def test_fallback_decision_at_the_crossover():
    """The backend falls back to dense exactly where the dense solve is cheaper: for this
    2-agent unicycle game (state 8, controls 4, no lags) the flop counts of the stage
    recursion, (K+1)(4 nz^2 d + 2 d^3) with d = 12, and of the dense solve,
    n_r n_u^2 + n_u^3 / 3, cross between K = 7 and K = 8."""
    feats = ["goal", "velocity", "acceleration", "turn_rate"]
    for K, falls_back in ((7, True), (8, False)):
        game = _two_agent_game("unicycle", feats, K=K)
        L = stage_layout(game)
        assert (L.nz, L.m) == (8, 4)
        riccati = (K + 1) * (4 * 8**2 * 12 + 2 * 12**3)  # 6528 flops per stage
        dense = game.n_r * game.n_u**2 + game.n_u**3 / 3
        assert (riccati > dense) == falls_back
        assert (StructuredGN(game, threads=1).fallback is not None) == falls_back
