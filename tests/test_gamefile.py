"""Game files (scenarios.gamefile): the shipped examples, the dump/load round trip, and
one SpecError naming the right field for every kind of bad input."""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from epo_casadi import PotentialGame, SpecError
from scenarios.gamefile import (
    EXAMPLES,
    GameFile,
    apply_settings,
    dump_game,
    example_path,
    load_game,
    parse_game,
    save_game,
)

from .helpers import crossing_spec

RNG = np.random.default_rng(7)


@pytest.fixture(scope="module")
def loaded():
    return {name: load_game(example_path(name)) for name in EXAMPLES}


def base() -> dict:
    """The crossing example as a plain mapping, to be broken by the bad-input cases."""
    return yaml.safe_load(example_path("crossing2").read_text())


# ----------------------------------------------------------------------------- examples
@pytest.mark.parametrize("name", EXAMPLES)
def test_example_loads(loaded, name):
    gf = loaded[name]
    assert isinstance(gf, GameFile)
    assert gf.path == example_path(name)
    game = gf.game
    assert isinstance(game, PotentialGame)
    assert gf.params.shape == (game.n_p,)
    np.testing.assert_array_equal(gf.params, game.params.defaults())
    assert set(gf.solver_options) <= {"lm", "ipopt"}
    assert gf.options("lm").steps == gf.solver_options["lm"]["steps"]
    assert gf.options("ipopt", max_iter=7).max_iter == 7


@pytest.mark.parametrize("name", EXAMPLES)
def test_example_collision_active_at_zero_controls(loaded, name):
    """Every example is an interaction: some collision term is non-zero for u = 0."""
    gf = loaded[name]
    game = gf.game
    e = np.asarray(game.function("term_energies")(game.zero_controls(), gf.params)).ravel()
    coll = [t.index for t in game.terms if t.feature_type == "collision"]
    assert coll and e[coll].max() > 1.0


def test_robot_pedestrian_matches_paper_setting(loaded):
    gf = loaded["robot_pedestrian"]
    spec = gf.spec
    assert spec.horizon == 40 and spec.dt == 0.1
    assert [a.radius for a in spec.agents] == [0.25, 0.25]
    want = {
        "goal",
        "velocity",
        "acceleration",
        "velocity_bound",
        "acceleration_bound",
        "turn_rate",
        "turn_rate_bound",
    }
    for a in spec.agents:
        assert a.dynamics.name == "unicycle"
        assert {f.kind for f in a.features} == want
    assert [pf.every for pf in spec.pair_features] == [1]


def test_highway_uses_lanes_and_bicycles(loaded):
    spec = loaded["highway_merge"].spec
    for a in spec.agents:
        assert a.dynamics.name == "bicycle"
        kinds = {f.kind for f in a.features}
        assert {"path", "reference_velocity"} <= kinds
        assert a.path is not None and len(a.path) >= 2
    assert len(loaded["intersection4"].spec.agents) == 4


# ----------------------------------------------------------------------------- round trip
def _energies(game: PotentialGame, p: np.ndarray, U: np.ndarray) -> np.ndarray:
    f = game.function("energy")
    return np.array([float(f(u, p)) for u in U])


@pytest.mark.parametrize("name", EXAMPLES)
@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_round_trip_same_energy(loaded, name, suffix, tmp_path):
    gf = loaded[name]
    path = save_game(gf, tmp_path / f"copy{suffix}")
    gf2 = load_game(path)
    assert gf2.spec == gf.spec
    assert gf2.solver_options == gf.solver_options
    np.testing.assert_array_equal(gf2.params, gf.params)
    U = RNG.normal(scale=0.3, size=(3, gf.game.n_u))
    np.testing.assert_allclose(
        _energies(gf2.game, gf2.params, U), _energies(gf.game, gf.params, U), rtol=1e-13, atol=0
    )


def test_dump_of_python_spec_round_trips():
    """A spec built in Python (infinite bounds, features as objects) dumps to plain data."""
    spec = crossing_spec(N=3, K=8)
    data = dump_game(spec)
    text = json.dumps(data, allow_nan=False)  # strict JSON: no inf left in the dump
    gf = parse_game(json.loads(text))
    assert gf.spec == spec
    game = PotentialGame(spec)
    U = RNG.normal(scale=0.3, size=(2, game.n_u))
    np.testing.assert_allclose(
        _energies(gf.game, gf.params, U), _energies(game, game.default_params(), U), rtol=1e-13
    )


# ----------------------------------------------------------------------------- bad input
def _set(path, value):
    def f(d):
        *head, last = path
        for k in head:
            d = d[k]
        d[last] = value

    return f


def _pop(path):
    def f(d):
        *head, last = path
        for k in head:
            d = d[k]
        del d[last]

    return f


BAD = [
    # (mutation, field, words in the message)
    (_pop(["horizon"]), "horizon", "missing"),
    (_set(["horizon"], 0), "horizon", "integer >= 1"),
    (_set(["horizon"], 2.5), "horizon", "integer"),
    (_set(["dt"], -0.1), "dt", "> 0"),
    (_set(["dt"], "fast"), "dt", "number"),
    (_set(["dt"], "1e-3"), "dt", "1.0e-3"),
    (_set(["horizn"], 3), "horizn", "unknown key"),
    (_set(["agents"], []), "agents", "non-empty list"),
    (_set(["agents"], {"a0": {}}), "agents", "list"),
    (_set(["agents", 1], "a1"), "agents[1]", "mapping"),
    (_pop(["agents", 0, "name"]), "agents[0].name", "missing"),
    (_set(["agents", 1, "name"], "a0"), "agents[1].name", "duplicate"),
    (_set(["agents", 1, "name"], "a.1"), "agents[1].name", "letters"),
    (_set(["agents", 1, "radius"], -0.5), "agents[1].radius", ">= 0"),
    (_set(["agents", 1, "radius"], float("inf")), "agents[1].radius", "finite"),
    (_set(["agents", 0, "radius"], True), "agents[0].radius", "number"),
    (_set(["agents", 1, "colour"], "red"), "agents[1].colour", "unknown key"),
    (_set(["agents", 0, "dynamics"], "car"), "agents[0].dynamics.type", "unicycle"),
    (
        _set(["agents", 0, "dynamics"], {"type": "unicycle", "wheelbase": 2}),
        "agents[0].dynamics.wheelbase",
        "unknown key",
    ),
    (
        _set(["agents", 0, "dynamics"], {"type": "bicycle", "wheelbase": -2}),
        "agents[0].dynamics.wheelbase",
        "> 0",
    ),
    (_set(["agents", 0, "dynamics"], {"wheelbase": 2}), "agents[0].dynamics.type", "missing"),
    (_pop(["agents", 1, "x0"]), "agents[1].x0", "missing"),
    (_set(["agents", 1, "x0"], [0, 0, 1]), "agents[1].x0", "4 numbers"),
    (_set(["agents", 1, "x0"], "origin"), "agents[1].x0", "list of 4 numbers"),
    (_set(["agents", 1, "x0"], [0, 0, float("nan"), 0]), "agents[1].x0[2]", "finite"),
    (_set(["agents", 0, "goal"], [1, 2, 3]), "agents[0].goal", "2 numbers"),
    (_pop(["agents", 0, "goal"]), "agents[0].goal", "'goal' feature"),
    (_set(["agents", 0, "path"], [[0, 0]]), "agents[0].path", "two [x, y]"),
    (_set(["agents", 0, "path"], [[0, 0], [1, 2, 3]]), "agents[0].path[1]", "2 numbers"),
    (_set(["agents", 0, "features"], None), "agents[0].features", "null"),
    (_set(["agents", 0, "features"], "goal"), "agents[0].features", "list"),
    (
        _set(["agents", 1, "features", 2, "type"], "accel"),
        "agents[1].features[2].type",
        "unknown feature",
    ),
    (_pop(["agents", 1, "features", 2, "type"]), "agents[1].features[2].type", "missing"),
    (
        _set(["agents", 1, "features", 2, "wieght"], 1),
        "agents[1].features[2].wieght",
        "unknown key",
    ),
    (
        _set(["agents", 1, "features", 2, "weight"], "high"),
        "agents[1].features[2].weight",
        "number",
    ),
    (
        _set(["agents", 1, "features", 4, "upper"], -1.0),
        "agents[1].features[4].upper",
        "upper > lower",
    ),
    (
        _set(["agents", 1, "features", 4, "upper"], None),
        "agents[1].features[4].upper",
        None,
    ),  # lower alone is fine
    (
        _set(["agents", 1, "features", 3, "label"], "my label"),
        "agents[1].features[3].label",
        "letters",
    ),
    (_set(["agents", 1, "features", 3], {"type": "goal"}), "agents[1].features[3]", "duplicate"),
    (_set(["agents", 1, "features", 3], {"type": "path"}), "agents[1].path", "'path' feature"),
    (
        _set(["agents", 1, "features", 3], {"type": "reference_velocity"}),
        "agents[1].vref",
        "'reference_velocity'",
    ),
    (
        _set(["agents", 1, "features", 3], {"type": "velocity_bound"}),
        "agents[1].features[3]",
        "'lower', 'upper'",
    ),
    (_set(["agents", 0, "dynamics"], "double_integrator"), "agents[0].features[3]", "no heading"),
    (
        _set(["agents", 0, "features"], [{"type": "path", "points": 3}]),
        "agents[0].path",
        "'path' feature",
    ),
    (_set(["pair_features", 0, "type"], "proximity"), "pair_features[0].type", "collision"),
    (_set(["pair_features", 0, "every"], 0), "pair_features[0].every", "integer >= 1"),
    (
        _set(["pair_features", 0, "pairs"], [["a0", "zz"]]),
        "pair_features[0].pairs[0]",
        "agent names",
    ),
    (_set(["pair_features"], {"type": "collision"}), "pair_features", "list"),
    (_set(["solver", "newton"], {}), "solver.newton", "unknown key"),
    (_set(["solver", "lm", "stepz"], 3), "solver.lm.stepz", "unknown option"),
    (_set(["solver", "lm", "steps"], -3), "solver.lm.steps", "integer >= 0"),
    (_set(["solver", "lm", "step_size"], float("nan")), "solver.lm.step_size", "finite"),
    (_set(["solver", "ipopt", "tol"], 0), "solver.ipopt.tol", "> 0"),
    (
        _set(["solver", "ipopt", "control_bounds"], {"zz": [[-1, -1], [1, 1]]}),
        "solver.ipopt.control_bounds.zz",
        "unknown agent",
    ),
    (
        _set(["solver", "ipopt", "state_bounds"], {"a0": [[-1], [1]]}),
        "solver.ipopt.state_bounds.a0",
        "4 state entries",
    ),
    (_set(["solver", "lm"], [1, 2]), "solver.lm", "mapping"),
]


@pytest.mark.parametrize(
    "mutate, field, words", BAD, ids=[f"{i}-{b[1]}" for i, b in enumerate(BAD)]
)
def test_bad_input_names_field(mutate, field, words):
    d = base()
    mutate(d)
    if words is None:  # a variation that is valid
        parse_game(d)
        return
    with pytest.raises(SpecError) as e:
        parse_game(d)
    assert e.value.field == field, str(e.value)
    assert words in e.value.message, str(e.value)
    assert str(e.value).startswith(f"{field}: ")


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "name, text, words",
    [
        ("empty.yaml", "", "empty"),
        ("blank.yaml", "\n  \n# only a comment\n", "no data"),
        ("syntax.yaml", "horizon: 10\ndt: 0.1\nagents: [\n", "invalid YAML at line 4"),
        ("tabs.yaml", "horizon: 10\n\tdt: 0.1\n", "invalid YAML"),
        (
            "dup.yaml",
            "horizon: 10\nhorizon: 20\ndt: 0.1\nagents: []\n",
            "duplicate key 'horizon' at line 2",
        ),
        ("list.yaml", "- 1\n- 2\n", "mapping"),
        ("bad.json", '{"horizon": 10,,}', "invalid JSON at line 1"),
        ("dup.json", '{"horizon": 10, "horizon": 3}', "duplicate key 'horizon'"),
    ],
)
def test_bad_file_syntax(tmp_path, name, text, words):
    p = _write(tmp_path, name, text)
    with pytest.raises(SpecError) as e:
        load_game(p)
    assert e.value.field == name
    assert words in e.value.message


def test_nan_and_inf_in_yaml_and_json(tmp_path):
    d = base()
    text = yaml.safe_dump(d).replace("radius: 0.25", "radius: .nan", 1)
    with pytest.raises(SpecError, match=r"^agents\[0\]\.radius: expected a finite number"):
        load_game(_write(tmp_path, "nan.yaml", text))
    d["agents"][1]["goal"] = [float("inf"), 0.0]
    with pytest.raises(SpecError, match=r"^agents\[1\]\.goal\[0\]: expected a finite number"):
        load_game(_write(tmp_path, "inf.json", json.dumps(d)))


def test_path_points_must_match(tmp_path):
    d = base()
    d["agents"][0]["path"] = [[0, 0], [1, 0], [2, 1]]
    d["agents"][0]["features"].append({"type": "path", "points": 2})
    with pytest.raises(SpecError, match=r"^agents\[0\]\.features\[6\]\.points: expected 3"):
        parse_game(d)
    d["agents"][0]["features"][-1]["points"] = 3
    assert parse_game(d).game.params["path.a0"].size == 6


def test_not_utf8(tmp_path):
    p = tmp_path / "bin.yaml"
    p.write_bytes(b"\xff\xfe\x00horizon")
    with pytest.raises(SpecError, match="^bin.yaml: not a UTF-8 text file"):
        load_game(p)


def test_missing_file_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_game(tmp_path / "nope.yaml")


def test_example_path_unknown():
    with pytest.raises(SpecError, match="^example: unknown example 'nope'"):
        example_path("nope")
    assert example_path("crossing2.yaml") == example_path("crossing2")


def test_not_a_mapping():
    with pytest.raises(SpecError, match="^game: expected a mapping"):
        parse_game([1, 2])


def test_bad_solver_name_in_options(loaded):
    with pytest.raises(SpecError, match="^solver: expected one of"):
        loaded["crossing2"].options("newton")


# ----------------------------------------------------------------------------- --set
def test_apply_settings_blocks_and_entries(loaded):
    gf = loaded["crossing2"]
    game, p = gf.game, gf.params
    q = apply_settings(
        game, p, ["goal.a0=3.5,0.25", "w.a0-a1.collision=50", "x0.a1.v=1.25", "goal.a1=[-1, 2]"]
    )
    blocks = game.params.unpack(q)
    np.testing.assert_array_equal(blocks["goal.a0"], [3.5, 0.25])
    np.testing.assert_array_equal(blocks["goal.a1"], [-1.0, 2.0])
    assert blocks["w.a0-a1.collision"][0] == 50.0
    assert q[game.params.names.index("x0.a1.v")] == 1.25
    changed = np.flatnonzero(q != p)
    assert len(changed) == 6  # nothing else moved
    np.testing.assert_array_equal(
        apply_settings(game, p, {"w.a0.goal": 4}), game.params.pack({"w.a0.goal": 4})
    )
    assert np.all(p == gf.params)  # the input is not modified


@pytest.mark.parametrize(
    "setting, field, words",
    [
        ("goal.zz=1,2", "--set goal.zz", "unknown parameter"),
        ("goal.a0=1", "--set goal.a0", "expected 2"),
        ("x0.a0.v=1,2", "--set x0.a0.v", "one number"),
        ("goal.a0=1,abc", "--set goal.a0", "numbers"),
        ("goal.a0=nan,1", "--set goal.a0", "finite"),
        ("goal.a0=", "--set goal.a0", "at least one"),
        ("goal.a0", "--set", "NAME=VALUE"),
        ("=3", "--set", "parameter name"),
    ],
)
def test_apply_settings_errors(loaded, setting, field, words):
    gf = loaded["crossing2"]
    with pytest.raises(SpecError) as e:
        apply_settings(gf.game, gf.params, [setting])
    assert e.value.field == field
    assert words in e.value.message


def test_documented_game_file_loads():
    """The complete example of docs/gamefiles.md is valid and uses every key."""
    doc = Path(__file__).resolve().parents[1] / "docs" / "gamefiles.md"
    blocks = re.findall(r"```yaml\n(.*?)```", doc.read_text(), flags=re.S)
    assert blocks
    data = yaml.safe_load(blocks[0])
    gf = parse_game(data)
    agents = data["agents"]
    used = {k for a in agents for k in a}
    assert used == {"name", "dynamics", "radius", "x0", "goal", "vref", "path", "features"}
    assert set(data) == {"horizon", "dt", "agents", "pair_features", "solver"}
    opts = gf.options("ipopt")
    assert opts.control_bounds and opts.state_bounds
    assert "w.ped.slow_down" in gf.game.params


def test_base_is_untouched_between_cases():
    """parse_game never changes the mapping it reads (the cases above may reuse theirs)."""
    d = base()
    d["agents"][0]["features"].append("jerk")  # bare names and dicts, nested lists
    snapshot = copy.deepcopy(d)
    parse_game(d)
    assert d == snapshot


# ------------------------------------------------------------------- solver.ilq (iLQ)
@pytest.mark.parametrize(
    "values, field, words",
    [
        ({"max_itr": 3}, "solver.ilq.max_itr", "unknown option"),
        ({"tol": -1}, "solver.ilq.tol", ">= 0"),
        ({"line_search": "armijo"}, "solver.ilq.line_search", "expected one of"),
        ({"memory": 0}, "solver.ilq.memory", ">= 1"),
        ({"step_size": float("nan")}, "solver.ilq.step_size", "finite"),
        ({"compiled": "yes"}, "solver.ilq.compiled", "True or False"),
        ([1, 2], "solver.ilq", "mapping"),
    ],
)
def test_ilq_section_is_validated_like_lm_and_ipopt(values, field, words):
    d = base()
    d["solver"] = {"ilq": values}
    with pytest.raises(SpecError) as e:
        parse_game(d)
    assert e.value.field == field, str(e.value)
    assert words in e.value.message, str(e.value)


def test_ilq_section_reaches_the_options_and_round_trips(tmp_path):
    from solvers.ilq import ILQOptions

    d = base()
    d["solver"] = {"ilq": {"max_iter": 7, "tol": 1e-7, "line_search": "none"}}
    gf = parse_game(d)
    opts = gf.options("ilq", max_iter=9)
    assert opts == ILQOptions(max_iter=9, tol=1e-7, line_search="none")
    assert gf.options("ilq").max_iter == 7
    back = parse_game(dump_game(gf))
    assert back.solver_options == {"ilq": {"max_iter": 7, "tol": 1e-7, "line_search": "none"}}
