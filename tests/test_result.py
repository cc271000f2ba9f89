"""The common result object (solvers.result): indexing, statuses, JSON and summaries."""

from __future__ import annotations

import json

import numpy as np
import pytest

from solvers.ilq import solve_ilq
from solvers.ipopt import solve_ipopt
from solvers.lm import solve_lm
from solvers.result import SolveResult, Status

from .helpers import crossing_game

B, NU, NX, N, S = 3, 4, 6, 2, 5


def batch_result() -> SolveResult:
    rng = np.random.default_rng(0)
    return SolveResult(
        solver="test",
        controls=rng.standard_normal((B, NU)),
        states=rng.standard_normal((B, NX)),
        energy=np.array([1.0, 2.0, np.inf]),
        agent_costs=rng.standard_normal((B, N)),
        status=np.array([Status.CONVERGED, Status.MAX_ITER, Status.NONFINITE], dtype=object),
        iterations=np.array([4, 5, 0]),
        energy_history=rng.standard_normal((S, B)),
        grad_norm=np.array([1e-9, 1e-3, np.nan]),
        wall_time=0.25,
        info={
            "damping": np.array([0.1, 0.2, 0.3]),
            "return_status": np.array(["a", "b", "c"], dtype=object),
            "name": "kept",
            "history": rng.standard_normal((S + 1, 7)),
        },
    )


def test_indexing_picks_one_problem():
    res = batch_result()
    assert res.batched
    one = res[1]
    assert not one.batched
    np.testing.assert_array_equal(one.controls, res.controls[1])
    np.testing.assert_array_equal(one.states, res.states[1])
    np.testing.assert_array_equal(one.agent_costs, res.agent_costs[1])
    np.testing.assert_array_equal(one.energy_history, res.energy_history[:, 1])
    assert one.energy == 2.0 and one.iterations == 5 and one.status is Status.MAX_ITER
    assert one.info["damping"] == 0.2 and one.info["return_status"] == "b"
    assert one.info["name"] == "kept"
    assert one.info["history"].shape == (S + 1, 7)  # not batch-shaped: passed through
    assert one.wall_time == res.wall_time and one.solver == "test"
    with pytest.raises(IndexError):
        one[0]


def test_slicing_keeps_a_batch():
    res = batch_result()[0:2]
    assert res.batched and res.controls.shape == (2, NU) and res.energy_history.shape == (S, 2)
    assert list(res.status) == [Status.CONVERGED, Status.MAX_ITER]
    np.testing.assert_array_equal(res.ok, [True, True])


def test_ok_and_status_messages():
    res = batch_result()
    np.testing.assert_array_equal(res.ok, [True, True, False])
    assert res.message == "1 converged, 1 max_iter, 1 nonfinite"
    assert res[2].message == Status.NONFINITE.message
    msgs = {s: s.message for s in Status}
    assert all(isinstance(m, str) and len(m) > 10 for m in msgs.values())
    assert len(set(msgs.values())) == len(Status)
    assert msgs[Status.INFEASIBLE].startswith("stopped")
    assert {s for s in Status if s.ok} == {Status.CONVERGED, Status.MAX_ITER}


def test_to_dict_is_json_serializable():
    res = batch_result()
    d = json.loads(json.dumps(res.to_dict()))
    assert d["status"] == ["converged", "max_iter", "nonfinite"]
    assert d["controls"] == res.controls.tolist()
    assert d["info"]["return_status"] == ["a", "b", "c"]
    assert d["message"] == res.message
    one = json.loads(json.dumps(res[0].to_dict()))
    assert one["status"] == "converged" and one["energy"] == 1.0 and one["iterations"] == 4
    assert one["energy_history"] == res.energy_history[:, 0].tolist()


def test_summaries():
    res = batch_result()
    s = res.summary()
    assert s.startswith("test: 3 problems") and "1 nonfinite" in s
    s1 = res[0].summary()
    assert s1.startswith("test: converged") and Status.CONVERGED.message in s1
    assert "energy 1," in s1 and "4 iterations" in s1


@pytest.mark.parametrize("solve", [solve_lm, solve_ipopt, solve_ilq])
def test_solver_results_are_json_serializable(solve):
    """Every solver's result survives strict JSON (no NaN/inf tokens) with its numbers."""
    g = crossing_game(K=5)
    res = solve(g, g.default_params())
    assert res.status.ok and np.isfinite(res.energy)
    back = json.loads(json.dumps(res.to_dict(), allow_nan=False))
    assert back["solver"] == res.solver and back["status"] == res.status.value
    assert back["message"] == res.message and back["iterations"] == int(res.iterations)
    np.testing.assert_array_equal(np.array(back["controls"]), res.controls)
    np.testing.assert_array_equal(np.array(back["states"]), res.states)
    np.testing.assert_array_equal(np.array(back["agent_costs"]), res.agent_costs)
    np.testing.assert_array_equal(np.array(back["energy_history"]), res.energy_history)
    assert back["energy"] == float(res.energy)


@pytest.mark.parametrize("solve", [solve_lm, solve_ipopt])
def test_solvers_return_the_documented_shapes(solve):
    g = crossing_game(K=5)
    P = np.stack([g.default_params(), g.default_params(goal__a0=[-2.0, 1.0])])
    res = solve(g, P)
    assert res.controls.shape == (2, g.n_u) and res.states.shape == (2, g.n_x)
    assert res.energy.shape == (2,) and res.agent_costs.shape == (2, g.N)
    assert res.energy_history.shape[1:] == (2,) and res.energy_history.shape[0] >= 1
    assert all(isinstance(s, Status) for s in res.status)
    one = solve(g, P[1])
    assert not one.batched and isinstance(one.status, Status)
    np.testing.assert_allclose(one.energy, res.energy[1], rtol=1e-8)
