"""The solver table (solvers.registry): one registration reaches every reader.

References: a user's solver (a wrapper of ``solve_lm`` under another name) gives LM's own
energy to 1e-12 through ``solve_game``, ``epo compare``'s Python API, a game file's
``solver:`` section and ``epo solve``; ``epo solve --solver sqp`` gives ``epo compare``'s
sqp row to 1e-9; an unknown name is one line listing the table wherever a name is read.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass

import numpy as np
import pytest
import yaml

from epo_casadi.errors import SpecError
from scenarios.cli import main
from scenarios.gamefile import example_path, load_game, parse_game
from solvers import LMOptions, solve_lm
from solvers.compare import parse_solver, run_comparison
from solvers.multimodal import solve_multimodal
from solvers.registry import (
    SOLVERS,
    register_solver,
    solve_game,
    solver_entry,
    unregister_solver,
)

TOY = "lm_twin"


def run(capsys, *args) -> tuple[int, str, str]:
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def toy_solve(game, p, u0=None, options=None):
    """The user's solver: LM under another name (its result says so)."""
    res = solve_lm(game, p, u0, options)
    res.info["wrapped"] = True
    return res


@pytest.fixture
def toy():
    entry = register_solver(TOY, toy_solve, LMOptions, description="LM, wrapped")
    try:
        yield entry
    finally:
        unregister_solver(TOY)


@pytest.fixture(scope="module")
def crossing():
    return load_game(example_path("crossing2"))


# ----------------------------------------------------------------------------- the table
def test_builtins_are_registered_once():
    assert list(SOLVERS)[:4] == ["lm", "ipopt", "ilq", "sqp"]
    from solvers import ILQOptions, IpoptOptions, SQPOptions, solve_ilq, solve_ipopt, solve_sqp

    want = {
        "lm": (solve_lm, LMOptions, "open-loop", "steps", True),
        "ipopt": (solve_ipopt, IpoptOptions, "open-loop", "max_iter", False),
        "ilq": (solve_ilq, ILQOptions, "feedback", "max_iter", True),
        "sqp": (solve_sqp, SQPOptions, "open-loop", "max_iter", False),
    }
    for name, (fn, cls, eq, limit, mm) in want.items():
        e = SOLVERS[name]
        assert (e.function, e.options, e.equilibrium, e.iteration_limit, e.multimodal) == (
            fn,
            cls,
            eq,
            limit,
            mm,
        )
        assert e.description and e.prepare is not None


def test_duplicates_refused_unless_replace(toy):
    with pytest.raises(SpecError, match="already the built-in solver"):
        register_solver("lm", toy_solve, LMOptions)
    with pytest.raises(SpecError, match="already the registered solver"):
        register_solver(TOY, solve_lm, LMOptions)
    assert register_solver(TOY, toy_solve, LMOptions, description="LM, wrapped") == toy  # no-op
    original = SOLVERS["lm"]
    register_solver("lm", toy_solve, LMOptions, replace=True)
    try:
        assert SOLVERS["lm"].function is toy_solve
    finally:
        unregister_solver("lm")
    assert SOLVERS["lm"] is original
    with pytest.raises(SpecError, match="built-in"):
        unregister_solver("lm")
    with pytest.raises(SpecError, match="no solver registered"):
        unregister_solver("no_such")


def test_registration_is_checked():
    @dataclass
    class Loose:
        steps: int = 1

    for kwargs, field in [
        (dict(name="1bad", entry=toy_solve, options=LMOptions), "register_solver.name"),
        (dict(name="x", entry=3, options=LMOptions), "register_solver.entry"),
        (dict(name="x", entry=toy_solve, options=dict), "register_solver.options"),
        (dict(name="x", entry=toy_solve, options=Loose), "register_solver.options"),
        (
            dict(name="x", entry=toy_solve, options=LMOptions, equilibrium="closed"),
            "register_solver.equilibrium",
        ),
        (
            dict(name="x", entry=toy_solve, options=LMOptions, iteration_limit="max_iter"),
            "register_solver.iteration_limit",
        ),
    ]:
        with pytest.raises(SpecError) as e:
            register_solver(**kwargs)
        assert e.value.field == field
    assert "x" not in SOLVERS
    e = register_solver("x", "tests.test_solver_registry:toy_solve", "solvers.lm:LMOptions")
    try:
        assert e.function is toy_solve and e.options is LMOptions
    finally:
        unregister_solver("x")


# ----------------------------------------------------------------------------- a user's solver
def test_user_solver_everywhere(toy, crossing, capsys, tmp_path):
    game, p = crossing.game, crossing.params
    ref = solve_lm(game, p)
    # the Python entry by name
    res = solve_game(game, p, solver=TOY, options={"steps": 200})
    assert res.info["wrapped"] and abs(res.energy - ref.energy) < 1e-12
    # epo compare's Python API: its row, its open-loop check
    comp = run_comparison(
        [("crossing2", game, p)], [parse_solver("lm"), parse_solver(TOY)], progress=False
    )
    lm_row, toy_row = comp.rows
    assert toy_row.solver == TOY and toy_row.status == "converged"
    assert toy_row.check == "open-loop" and toy_row.check_ok
    assert abs(toy_row.energy - lm_row.energy) < 1e-12
    assert toy_row.setup_s >= 0 and toy_row.solve_s > 0
    # a game file's solver section and epo solve --solver
    d = yaml.safe_load(example_path("crossing2").read_text())
    d["solver"] = {TOY: {"steps": 3, "gtol": 0.0, "ftol": 0.0}}
    gf = parse_game(d)
    assert gf.options(TOY) == LMOptions(steps=3, gtol=0.0, ftol=0.0)
    assert gf.options(TOY, steps=5).steps == 5
    f = tmp_path / "game.yaml"
    f.write_text(yaml.safe_dump(d))
    out = tmp_path / "r.json"
    rc, stdout, err = run(capsys, "solve", f, "--solver", TOY, "--out", out)
    data = json.loads(out.read_text())
    assert data["iterations"] == 3 and data["options"]["steps"] == 3, err
    assert data["certificate"] is not None  # an open-loop solver: certified
    rc, stdout, err = run(capsys, "solve", f, "--solver", TOY, "--steps", 7, "--out", out)
    assert json.loads(out.read_text())["iterations"] == 7
    # the multi-modal solver
    mm = solve_multimodal(game, p, n_samples=2, seed=0, solver=TOY)
    assert mm.info["solver"] == TOY and mm.results.info["wrapped"]


def test_user_solver_options_errors_name_the_field(toy):
    d = yaml.safe_load(example_path("crossing2").read_text())
    d["solver"] = {TOY: {"stepz": 3}}
    with pytest.raises(SpecError) as e:
        parse_game(d)
    assert e.value.field == f"solver.{TOY}.stepz" and "unknown option" in e.value.message
    d["solver"] = {TOY: {"steps": -1}}
    with pytest.raises(SpecError) as e:
        parse_game(d)
    assert e.value.field == f"solver.{TOY}.steps"
    with pytest.raises(SpecError) as e:
        parse_solver(f"{TOY}:steps=-1")
    assert e.value.field == f"{TOY}.steps"


# ----------------------------------------------------------------------------- sqp everywhere
def test_epo_solve_sqp_equals_compare_row(capsys, tmp_path):
    game = example_path("crossing2")
    out = tmp_path / "sqp.json"
    rc, stdout, err = run(capsys, "solve", game, "--solver", "sqp", "--out", out)
    assert rc == 0, err
    assert "sqp: converged" in stdout
    data = json.loads(out.read_text())
    assert data["status"] == "converged" and data["solver"] == "sqp"
    assert data["certificate"] is not None
    rc, _, err = run(
        capsys, "compare", game, "--solver", "sqp", "--no-check", "--no-figures", "--out", tmp_path
    )
    assert rc == 0, err
    (row,) = csv.DictReader((tmp_path / "compare.csv").read_text().splitlines())
    assert row["solver"] == "sqp" and row["status"] == "converged"
    assert abs(float(row["energy"]) - data["energy"]) <= 1e-9 * (1 + abs(data["energy"]))


def test_game_file_takes_sqp_options_checked_against_the_game():
    d = yaml.safe_load(example_path("crossing2").read_text())
    d["solver"] = {"sqp": {"collision": True, "max_iter": 30}}
    gf = parse_game(d)
    o = gf.options("sqp")
    assert o.collision is True and o.max_iter == 30
    d["solver"] = {"sqp": {"control_bounds": {"zz": [[-1, -1], [1, 1]]}}}
    with pytest.raises(SpecError) as e:
        parse_game(d)
    assert e.value.field == "solver.sqp.control_bounds.zz" and "unknown agent" in e.value.message


def test_modes_refuse_a_solver_without_multistart(capsys):
    rc, _, err = run(capsys, "solve", example_path("crossing2"), "--solver", "sqp", "--modes", 2)
    assert rc == 2 and "--modes" in err and "['lm', 'ilq']" in err


# ----------------------------------------------------------------------------- unknown names
def _one_line_listing_the_table(text: str) -> None:
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    assert str(list(SOLVERS)) in lines[0] and "'newton'" in lines[0], text
    assert "Traceback" not in text


def test_unknown_names_are_one_line_listing_the_table(capsys, crossing, toy, tmp_path):
    game = example_path("crossing2")
    for args in (
        ("solve", game, "--solver", "newton"),
        ("compare", game, "--solver", "newton", "--out", tmp_path),
    ):
        rc, _, err = run(capsys, *args)
        assert rc == 2
        _one_line_listing_the_table(err)
        assert TOY in err  # the table as it is now, a user's solver included
    d = yaml.safe_load(game.read_text())
    d["solver"] = {"newton": {}}
    with pytest.raises(SpecError) as e:
        parse_game(d)
    assert e.value.field == "solver.newton" and TOY in e.value.message
    for call in (
        lambda: crossing.options("newton"),
        lambda: solve_game(crossing.game, crossing.params, solver="newton"),
        lambda: solver_entry("newton"),
        lambda: parse_solver("newton"),
        lambda: solve_multimodal(crossing.game, crossing.params, n_samples=2, solver="newton"),
    ):
        with pytest.raises(SpecError) as e:
            call()
        _one_line_listing_the_table(str(e.value))


def test_make_options_is_the_one_reader():
    e = SOLVERS["ipopt"]
    assert e.make_options(None) == e.options()
    o = e.make_options({"max_iter": 5})
    assert e.make_options(o) is o
    with pytest.raises(SpecError) as err:
        e.make_options([1], "solver.ipopt")
    assert err.value.field == "solver.ipopt" and "mapping" in err.value.message
    with pytest.raises(SpecError) as err:
        e.make_options({"tol": 0}, "solver.ipopt")
    assert err.value.field == "solver.ipopt.tol"
    np.testing.assert_equal(parse_solver("ipopt:max_iter=5").options_object, o)
