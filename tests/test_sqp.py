"""The OSQP-based SQP (solvers.sqp) against independent solvers and its constraints.

References: LM and IPOPT on the same unconstrained game (three different algorithms),
IPOPT with the same hard bounds, the bounds and distances themselves, an independent
stationarity test at a collision-constrained solution (condensed gradient and the
distance Jacobian by CasADi, multipliers by numpy lstsq), and a constraint set that
is infeasible by hand (speed 0 -> at least 2.5 m/s in one step with |a| <= 0.1).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import osqp
import pytest

from epo_casadi import SpecError
from epo_casadi.features import smooth_distance
from epo_casadi.game import PotentialGame
from scenarios.gamefile import example_path, load_game
from solvers.ipopt import solve_ipopt
from solvers.lm import solve_lm
from solvers.result import Status
from solvers.sqp import SQPOptions, SQPSolver, solve_sqp


@pytest.fixture(scope="module")
def crossing():
    gf = load_game(example_path("crossing2"))
    return gf.game, gf.params


def fresh(game: PotentialGame) -> PotentialGame:
    return PotentialGame(game.spec)  # empty solver cache


def test_unconstrained_matches_lm_and_ipopt(crossing):
    g, p = crossing
    sqp = solve_sqp(g, p)
    ip = solve_ipopt(g, p)
    lm = solve_lm(g, p, options={"steps": 500})
    assert sqp.status is Status.CONVERGED and ip.status is Status.CONVERGED
    assert lm.status is Status.CONVERGED
    assert sqp.info["stop"] == "kkt" and sqp.info["kkt_stationarity"] <= 1e-7
    assert np.abs(sqp.controls - ip.controls).max() < 1e-6
    assert np.abs(sqp.controls - lm.controls).max() < 1e-6
    assert abs(sqp.energy - ip.energy) < 1e-10 * (1 + ip.energy)
    assert sqp.grad_norm < 1e-6


BOUNDS = {
    "control_bounds": {"a0": ([-0.05, -0.2], [0.05, 0.2])},
    "state_bounds": {"a1": ([None, None, 0.0, None], [None, None, 1.9, None])},
}


def test_hard_bounds_match_ipopt_and_hold(crossing):
    g, p = crossing
    free = solve_ipopt(g, p)
    U0, X1 = g.split_controls(free.controls)[0], g.split_states(free.states)[1]
    # the regime: every bound is violated by the unconstrained solution
    assert np.abs(U0[:, 0]).max() > 0.05 and np.abs(U0[:, 1]).max() > 0.2
    assert X1[1:, 2].max() > 1.9
    sqp = solve_sqp(g, p, options=BOUNDS)
    ip = solve_ipopt(g, p, options=BOUNDS)
    assert sqp.status is Status.CONVERGED and ip.status is Status.CONVERGED
    assert np.abs(sqp.controls - ip.controls).max() < 1e-5
    assert abs(sqp.energy - ip.energy) < 1e-6 * (1 + ip.energy)
    U, X = g.split_controls(sqp.controls), g.split_states(sqp.states)
    assert np.abs(U[0][:, 0]).max() <= 0.05 + 1e-9
    assert np.abs(U[0][:, 1]).max() <= 0.2 + 1e-9
    assert X[1][1:, 2].max() <= 1.9 + 1e-9 and X[1][1:, 2].min() >= -1e-9
    assert sqp.info["max_violation"] <= 1e-9
    # active: the solution sits on each bound
    assert np.abs(U[0][:, 0]).max() > 0.05 - 1e-7 and X[1][1:, 2].max() > 1.9 - 1e-7


def test_collision_constraint_holds_and_is_stationary(crossing):
    g, p = crossing
    margin = 0.5
    reach = 2 * 0.25 + margin
    free = solve_sqp(g, p)
    pos = g.positions(free.states)
    assert np.linalg.norm(pos[0] - pos[1], axis=-1)[1:].min() < reach  # the regime: violated
    res = solve_sqp(g, p, options={"collision": True, "collision_margin": margin})
    assert res.status is Status.CONVERGED
    assert res.energy > free.energy
    # independent first-order test: condensed gradient + distance Jacobian, numpy lstsq
    u, xr = g.symbols["u"], g.symbols["x"]
    dist = ca.vertcat(
        *[
            smooth_distance(
                xr[int(g.xoff[0]) + 4 * k : int(g.xoff[0]) + 4 * k + 2],
                xr[int(g.xoff[1]) + 4 * k : int(g.xoff[1]) + 4 * k + 2],
            )
            for k in range(1, g.K + 1)
        ]
    )
    f = ca.Function("d", [u, g.symbols["p"]], [dist, ca.jacobian(dist, u)])
    d, J = (np.asarray(a) for a in f(res.controls, p))
    d = d.ravel()
    assert d.min() >= reach - 1e-8
    act = np.flatnonzero(d - reach < 1e-6)
    assert act.size >= 1
    grad = np.asarray(g.function("gradient")(res.controls, p)).ravel()
    mu = np.linalg.lstsq(J[act].T, -grad, rcond=None)[0]
    assert np.all(mu <= 1e-8)  # pushing outwards: dist >= reach
    assert np.abs(grad + J[act].T @ mu).max() < 1e-6
    assert np.abs(grad).max() > 0.1  # without the constraint's force it is not stationary


def test_infeasible_constraints(crossing):
    g, p = crossing
    # a0 starts at 2 m/s; |a| <= 0.1 cannot bring it to >= 2.5 m/s at step 1
    opts = {
        "control_bounds": {"a0": ([-0.1, None], [0.1, None])},
        "state_bounds": {"a0": ([None, None, 2.5, None], [None, None, 3.0, None])},
    }
    res = solve_sqp(g, p, options=opts)
    assert res.status is Status.INFEASIBLE
    assert "primal infeasible" in res.info["qp_status"]
    assert "primal infeasible" in res.info["stop"]
    assert not res.ok


def test_qp_set_up_once_per_structure(crossing, monkeypatch):
    g0, p = crossing
    g = fresh(g0)
    calls = []
    setup = osqp.OSQP.setup

    def counting(self, *a, **kw):
        calls.append(1)
        return setup(self, *a, **kw)

    monkeypatch.setattr(osqp.OSQP, "setup", counting)
    r1 = solve_sqp(g, p, options=BOUNDS)
    rng = np.random.default_rng(0)
    u0 = r1.controls + 0.01 * rng.standard_normal(g.n_u)  # near the solution: same basin
    r2 = solve_sqp(g, p, u0=u0, options=BOUNDS)
    rb = solve_sqp(g, np.stack([p, p]), u0=np.stack([u0, -u0]), options={**BOUNDS, "tol": 1e-7})
    assert len(calls) == 1  # one structure, one OSQP set-up: every other QP is an update
    assert r1.iterations > 1 and r2.iterations > 1
    assert np.abs(r1.controls - r2.controls).max() < 1e-5
    assert rb.controls.shape == (2, g.n_u) and list(rb.status) == [Status.CONVERGED] * 2
    solve_sqp(g, p)  # another structure (no bounds): a second set-up
    assert len(calls) == 2


def test_options_are_checked(crossing):
    g, p = crossing
    with pytest.raises(SpecError, match="unknown option"):
        solve_sqp(g, p, options={"max_iters": 3})
    with pytest.raises(SpecError, match="sqp.tol"):
        SQPOptions(tol=-1.0)
    with pytest.raises(SpecError, match="sqp.collision"):
        SQPOptions(collision="yes")
    with pytest.raises(SpecError, match="unknown agent"):
        SQPSolver(fresh(g), {"control_bounds": {"nobody": ([0, 0], [1, 1])}})
    s = SQPSolver(fresh(g))
    with pytest.raises(SpecError, match="structure"):
        s.solve(p, options={"collision": True})


def test_max_iter_status(crossing):
    g, p = crossing
    res = solve_sqp(g, p, options={"max_iter": 2})
    assert res.status is Status.MAX_ITER and res.iterations == 2
    assert res.energy_history.shape == (3,) and res.energy_history[-1] < res.energy_history[0]
