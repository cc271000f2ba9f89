"""Solver comparison (solvers.compare, solvers.feedback_nash, ``epo compare``).

References: the table's documented columns; the definition of the gap (the best usable
row is 0 by construction, every other gap is E - min E recomputed here); OSQP's set-up
counted by phase (set-up vs solve); the feedback Nash check against a policy shifted by
hand (must fail) and the iLQ solver's own (must pass); the CLI's one-line errors.
"""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import osqp
import pytest

import solvers.compare as cmp
from scenarios.cli import main
from scenarios.commands.compare import crossing_family
from solvers.compare import (
    COLUMNS,
    InitChoice,
    parse_init,
    parse_solver,
    run_comparison,
)
from solvers.feedback_nash import feedback_nash_check
from solvers.ilq import solve_ilq
from solvers.result import Status


@pytest.fixture(scope="module")
def games():
    return [("two", *crossing_family(2, 12)), ("three", *crossing_family(3, 10))]


@pytest.fixture(scope="module")
def study(games):
    solvers = [parse_solver("lm"), parse_solver("sqp"), parse_solver("ilq")]
    inits = [InitChoice("zero"), parse_init("perturb:3:0.05")]
    return run_comparison(games, solvers, inits, progress=False)


def test_table_has_one_row_per_combination(study, games):
    rows = study.rows
    assert len(rows) == 2 * 3 * 2
    keys = {(r.game, r.solver, r.init) for r in rows}
    assert len(keys) == len(rows)
    table = list(csv.reader(io.StringIO(study.csv())))
    assert tuple(table[0]) == COLUMNS and len(table) == 1 + len(rows)
    md = study.markdown().splitlines()
    assert md[0] == "| " + " | ".join(COLUMNS) + " |" and len(md) == 2 + len(rows)
    for r in rows:
        assert r.check == ("feedback" if r.solver == "ilq" else "open-loop")
        assert r.status in {s.value for s in Status}
        if r.solver != "ilq":  # iLQ's defaults are another task's (max_iter on 'three')
            assert r.status == "converged", (r.game, r.solver, r.init, r.message)
            assert r.check_ok is True


def test_gap_of_best_row_is_zero(study):
    for g in study.games:
        rows = [r for r in study.rows if r.game == g]
        best = min(r.energy for r in rows if r.status in ("converged", "max_iter"))
        assert min(r.gap for r in rows) == 0.0
        for r in rows:
            assert r.gap == pytest.approx(r.energy - best, abs=1e-12)
        # the potential minimizers agree; iLQ's feedback equilibrium is another point
        assert max(r.gap for r in rows if r.solver != "ilq") < 1e-9 * (1 + best)


def test_times_positive_and_set_up_separate(games, monkeypatch):
    phase = {"now": None}
    calls = []
    setup, solve = cmp.setup_solver, cmp.solve_with
    osqp_setup = osqp.OSQP.setup

    def in_phase(name, f):
        def wrapped(*a, **kw):
            phase["now"] = name
            try:
                return f(*a, **kw)
            finally:
                phase["now"] = None

        return wrapped

    def counting(self, *a, **kw):
        calls.append(phase["now"])
        return osqp_setup(self, *a, **kw)

    monkeypatch.setattr(cmp, "setup_solver", in_phase("setup", setup))
    monkeypatch.setattr(cmp, "solve_with", in_phase("solve", solve))
    monkeypatch.setattr(osqp.OSQP, "setup", counting)
    comp = run_comparison(
        games[:1],
        [parse_solver("sqp"), parse_solver("lm")],
        [InitChoice("zero"), parse_init("perturb:1")],
        check=False,
        progress=False,
    )
    assert calls == ["setup"]  # OSQP is set up in the set-up phase, never in a timed solve
    for r in comp.rows:
        assert r.setup_s > 0 and r.solve_s > 0 and r.check == "none" and r.check_ok is None
    for s in ("sqp", "lm"):
        pair = [r.setup_s for r in comp.rows if r.solver == s]
        assert pair[0] == pair[1]  # measured once per (game, solver)


def test_failed_solves_are_rows(games, monkeypatch):
    infeasible = parse_solver(
        "sqp:control_bounds={a0: [[-0.1, null], [0.1, null]]},"
        "state_bounds={a0: [[null, null, 2.5, null], [null, null, 3, null]]}"
    )
    comp = run_comparison(games[:1], [infeasible], progress=False)
    (r,) = comp.rows
    assert r.status == "infeasible" and r.check == "none" and "primal infeasible" in r.message
    assert math.isfinite(r.energy) and math.isnan(r.gap)  # no usable row: no E_best

    def boom(*a, **kw):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(cmp, "solve_with", boom)
    (r,) = run_comparison(games[:1], [parse_solver("lm")], progress=False).rows
    assert r.status == Status.FAILED.value and "solver exploded" in r.message


def test_feedback_nash_check_flags_a_perturbed_policy():
    game, p = crossing_family(2, 20)
    res = solve_ilq(game, p)
    assert res.status is Status.CONVERGED
    own = feedback_nash_check(
        game, p, res.states, res.controls, res.info["gains"], res.info["feedforward"]
    )
    assert own.ok and np.all(own.gain <= 1e-6 * (1 + np.abs(own.costs)))
    a = res.info["feedforward"].copy()
    a[:, 0] += 0.05  # player 0 accelerates 0.05 m/s^2 more than its equilibrium policy
    bad = feedback_nash_check(game, p, res.states, res.controls, res.info["gains"], a)
    assert not bad.ok and not bad.ok_agent[0]
    assert bad.gain[0] > 10 * 1e-6 * (1 + abs(bad.costs[0]))  # well above the tolerance


@pytest.mark.parametrize(
    "args, field",
    [
        (["example:crossing2", "--solver", "newton"], "unknown solver"),
        (["example:crossing2", "--solver", "ipopt:max_iterz=3"], "unknown option"),
        (["example:crossing2", "--solver", "lm:steps=-1"], "lm.steps"),
        (["/nonexistent/game.yaml"], "no such file"),
        (["example:crossing2", "--init", "perturb:x"], "--init"),
    ],
)
def test_cli_errors_are_one_line(args, field, capsys, tmp_path):
    rc = main(["compare", *args, "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2
    assert field in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_cli_writes_table_and_figure(tmp_path, capsys):
    rc = main(["compare", "example:crossing2", "--solver", "lm", "--out", str(tmp_path)])
    assert rc == 0
    rows = list(csv.DictReader(io.StringIO((tmp_path / "compare.csv").read_text())))
    assert len(rows) == 1 and rows[0]["status"] == "converged" and float(rows[0]["gap"]) == 0
    assert (tmp_path / "compare.md").read_text().startswith("| game |")
    assert (tmp_path / "crossing2_gap.png").stat().st_size > 1000


def test_feedback_nash_check_with_lagged_gains_on_highway_merge():
    """highway_merge has stage-coupled costs (jerk), so iLQ's policy also feeds back the
    carried previous-stage variables Y_k through info["gains_prev"] Q. The check's closed
    loop with Q reproduces the solver's own rollout of that policy; iLQ's converged policy
    passes with Q (measured: all gains < 0; without Q one player gains ~1e-3, a different
    policy), and a feed-forward shifted by 0.05 fails."""
    from scenarios.gamefile import example_path, load_game
    from solvers.ilq import from_stages, get_solver, to_stages

    gf = load_game(example_path("highway_merge"))
    game, p = gf.game, gf.params
    res = solve_ilq(game, p)
    assert res.status is Status.CONVERGED
    info = res.info
    P, Q, a = info["gains"], info["gains_prev"], info["feedforward"]
    lag = {"gains_prev": Q, "prev_variables": info["prev_variables"]}
    assert Q.shape[2] > 0 and np.abs(Q).max() > 1e-2  # the policy does use the lagged terms
    # reference: the solver's own closed-loop rollout of [P | Q | a'] for an off-equilibrium a'
    a_off = a + 0.02 * np.random.default_rng(1).standard_normal(a.shape)
    X, U = to_stages(game, res.states, res.controls)
    Xn, Un = get_solver(game).rollout(p, X, U, np.concatenate([P, Q, a_off[:, :, None]], 2), 1.0)
    ref = np.asarray(game.function("traj_agent_costs")(*from_stages(game, Xn, Un), p)).ravel()
    none = {"n_random": 0, "n_coordinate": 0}
    base = feedback_nash_check(game, p, res.states, res.controls, P, a_off, none, **lag)
    np.testing.assert_allclose(base.costs, ref, rtol=1e-12, atol=1e-12)
    without = feedback_nash_check(game, p, res.states, res.controls, P, a_off, none)
    assert np.max(np.abs(without.costs - ref)) > 1e-2  # dropping Q is another policy

    own = feedback_nash_check(game, p, res.states, res.controls, P, a, **lag)
    assert own.ok, own.summary()
    shifted = a.copy()
    shifted[:, 0] += 0.05
    bad = feedback_nash_check(game, p, res.states, res.controls, P, shifted, **lag)
    assert not bad.ok and not bad.ok_agent[0]
    assert bad.gain[0] > 10 * 1e-6 * (1 + abs(bad.costs[0]))
