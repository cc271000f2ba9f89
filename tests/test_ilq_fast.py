"""The compiled iLQ path (``compiled=True``) against the interpreted reference.

The generated-C quadratization (:mod:`solvers.fast_ilq`: stage functions found from the
graph, mapped over the stages) must fill the same stage matrices, costs and energy as the
interpreted trajectory function, and the generated-C Riccati recursion
(:class:`solvers.ilq._CompiledRiccati`: one stage function folded over the horizon,
symmetric products computed once) must give the numpy
recursion's gains, feed-forward terms and shifts at the same linearization, to rounding
(1e-12 relative). The one-call trial (:class:`solvers.fast_ilq.CompiledTrial`: rollout,
quadratization and Riccati recursion in one generated function, what compiled solves with
the game's costs run) must give the separate calls' numbers bit for bit. Whole solves must
take the same path: iterates, statuses, iteration counts, accepted steps. Games: 2-4
unicycles with active collisions, bicycles, costs that couple consecutive stages (jerk,
carried as extra states), and custom costs (exact Hessian, costs left interpreted).
"""

from __future__ import annotations

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
    TurnRate,
    Velocity,
)
from solvers.ilq import ILQSolver, to_stages

from .helpers import crossing_spec

REL = 1e-12


def _close(a, b, rel=REL):
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    scale = max(1.0, float(np.max(np.abs(b))) if b.size else 1.0)
    err = float(np.max(np.abs(a - b))) if a.size else 0.0
    assert err <= rel * scale, f"max difference {err:.3e} > {rel:g} x {scale:.3g}"


def _jerk_game(dynamics: str, K: int) -> PotentialGame:
    feats = [Goal(weight=2.0), Velocity(weight=0.5), Acceleration(), TurnRate(), Jerk(weight=0.1)]
    agents = [
        AgentSpec("a", dynamics, feats, radius=0.4, x0=[0, 0, 1, 0], goal=[3, 0.2]),
        AgentSpec("b", dynamics, feats, radius=0.4, x0=[3, 0, 1, np.pi], goal=[0, 0]),
    ]
    return PotentialGame(GameSpec(agents, [Collision(weight=8.0)], horizon=K, dt=0.1))


GAMES = {
    "unicycle-2": lambda: PotentialGame(crossing_spec(2, 15, offset=0.3)),
    "unicycle-3": lambda: PotentialGame(crossing_spec(3, 12, offset=0.3)),
    "unicycle-4": lambda: PotentialGame(crossing_spec(4, 8, offset=0.2)),
    "unicycle-2-jerk": lambda: _jerk_game("unicycle", 12),
    "bicycle-2-jerk": lambda: _jerk_game("bicycle", 12),
    "custom-costs": lambda: _jerk_game("unicycle", 10),
}


@pytest.fixture(scope="module")
def compiler():
    """Skip without a C compiler. The libraries go to the usual cache (``$EPO_CACHE_DIR`` or
    ``~/.cache/epo``), so only the first run compiles (a fresh compile is tested in
    ``tests/test_ilq.py``)."""
    from solvers.codegen import CompilerError, find_compiler

    try:
        find_compiler()
    except CompilerError:
        pytest.skip("no C compiler")


@pytest.mark.parametrize("name", list(GAMES))
def test_compiled_path_equals_interpreted(name, compiler):
    game = GAMES[name]()
    p = game.default_params()
    costs = game.function("traj_agent_costs") if name == "custom-costs" else None
    ref = ILQSolver(game, costs).solve(p, options={"tol": 1e-5, "max_iter": 30})
    solver = ILQSolver(game, costs).compile()
    assert solver.quad_backend == "compiled"
    assert (solver._cquad.costs is not None) == (costs is not None)
    fast = solver.solve(p, options={"tol": 1e-5, "max_iter": 30, "compiled": True})
    assert fast.info["backend"] == "compiled" and ref.info["backend"] == "numpy"
    if name.endswith("jerk"):
        assert solver.na > 0  # stage-coupled costs carried as extra states
    # the collision term is active somewhere (not an uncoupled game)
    assert np.max(np.abs(ref.info["gains"])) > 0
    assert fast.status is ref.status and fast.info["stop"] == ref.info["stop"]
    assert fast.iterations == ref.iterations
    np.testing.assert_array_equal(fast.info["step_sizes"], ref.info["step_sizes"])
    _close(fast.controls, ref.controls)
    _close(fast.states, ref.states)
    for key in ("gains", "gains_prev", "feedforward", "regularization"):
        _close(fast.info[key], ref.info[key])
    _close(fast.info["residual_history"], ref.info["residual_history"], rel=1e-9)

    # one backward pass at a linearization away from the solution (collisions active,
    # large feed-forward), both recursions on the same Lam and Phi
    X, U = to_stages(game, ref.states, ref.controls)
    rng = np.random.default_rng(0)
    U = U + 0.3 * rng.standard_normal(U.shape)
    PA0 = np.zeros((game.K, solver.nu, solver.nxs + 1))
    X, U = solver.rollout(p, np.zeros_like(X), U, PA0, 0.0)
    C_c, E_c = solver.quadratize(X, U, p, compiled=True)
    Lam_c, Phi_c = solver.Lam.copy(), solver.Phi.copy()
    solver.Lam[solver._lam_tgt] = np.nan  # every entry the functions write is rewritten
    solver.Phi.reshape(-1)[solver._phi_tgt] = np.nan
    C_n, E_n = solver.quadratize(X, U, p)
    np.testing.assert_array_equal(Lam_c, solver.Lam)  # same SX graph: bit-identical
    np.testing.assert_array_equal(Phi_c, solver.Phi)
    _close(C_c, C_n)
    if costs is None:
        _close(E_c, E_n)
    else:
        assert np.isnan(E_c) and np.isnan(E_n)
    for mu0 in (0.0, 1e-3):
        PA_c, mu_c, ok_c = solver.backward(mu0, 1e-8)
        PA_n, mu_n, ok_n = solver._numpy_backward(mu0, 1e-8)
        assert ok_c and ok_n
        assert np.max(np.abs(PA_n[:, :, -1])) > 1e-2  # far from equilibrium
        _close(PA_c, PA_n)
        _close(mu_c, mu_n)
    # the compiled rollout: the same SX operations per stage as the interpreted function
    PA_r = PA_n.copy()
    for eps in (1.0, 0.25):
        Xc, Uc = solver.rollout(p, X, U, PA_r, eps, compiled=True)
        Xi, Ui = solver.rollout(p, X, U, PA_r, eps)
        assert np.abs(Xc - X).max() > 1e-3  # a real step
        _close(Xc, Xi)
        _close(Uc, Ui)

    # the one-call trial (game costs only): the separate compiled calls' numbers, bit for bit
    ft = solver._ftrial
    if costs is not None:
        assert ft is None
        return
    for eps, mu0 in ((1.0, 0.0), (0.25, 1e-3)):
        Xt, Ut, Ct, Et, PAt, mut, okt = ft(p, X, U, PA_r, eps, mu0, 1e-8)
        Xs, Us = solver.rollout(p, X, U, PA_r, eps, compiled=True)
        Cs, Es = solver.quadratize(Xs, Us, p, compiled=True)
        PAs, mus, oks = solver.backward(mu0, 1e-8)
        assert okt and oks and Et == Es
        for got, want in ((Xt, Xs), (Ut, Us), (Ct, Cs), (PAt, PAs), (mut, mus)):
            np.testing.assert_array_equal(got, want)
    # PA = None linearizes at the given rollout itself
    Xs, Us = solver.rollout(p, X, U, PA_r, 0.5, compiled=True)
    Xt, Ut, Ct, Et, PAt, mut, okt = ft(p, Xs, Us, None, 0.0, 0.0, 1e-8)
    np.testing.assert_array_equal(Xt, Xs)
    np.testing.assert_array_equal(Ut, Us)
    Cs, Es = solver.quadratize(Xs, Us, p, compiled=True)
    np.testing.assert_array_equal(PAt, solver.backward(0.0, 1e-8)[0])
