"""epo_casadi.inspect: term listing, energy breakdown and Jacobian sparsity, each checked
against an independent computation (residual rows, finite differences)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from epo_casadi import AgentSpec, GameSpec, PotentialGame, SpecError
from epo_casadi.inspect import (
    agent_breakdown,
    breakdown_table,
    energy_breakdown,
    format_steps,
    jacobian_pattern,
    jacobian_sparsity,
    spy_text,
    term_rows,
    term_table,
)

from .helpers import crossing_game

RNG = np.random.default_rng(3)


def always_active_game() -> PotentialGame:
    """Every feature kind and all three dynamics, with bounds and collisions chosen so that
    every max(0, .) is active at any reasonable point: then the numeric Jacobian has
    exactly the structural nonzeros."""
    always = [
        {"type": "velocity_bound", "lower": 100.0},  # speed < 100: active
        {"type": "acceleration_bound", "upper": -100.0},  # a > -100: active
    ]
    uni = AgentSpec(
        "uni",
        "unicycle",
        [
            "goal",
            "velocity",
            "acceleration",
            "jerk",
            "turn_rate",
            "turn_acceleration",
            {"type": "reference_velocity", "weight": 0.5},
            *always,
            {"type": "turn_rate_bound", "lower": 100.0},
        ],
        radius=50.0,
        x0=[0.0, 0.0, 1.5, 0.3],
        goal=[3.0, 1.0],
        vref=1.0,
    )
    bic = AgentSpec(
        "bic",
        {"type": "bicycle", "wheelbase": 2.5},
        [
            {"type": "path", "weight": 2.0},
            "reference_velocity",
            "acceleration",
            "turn_rate",
            "turn_acceleration",
            {"type": "turn_rate_bound", "upper": -100.0},
        ],
        radius=50.0,
        x0=[1.0, -1.0, 2.0, 0.1],
        vref=2.0,
        path=[[0.0, -1.0], [2.0, -0.5], [6.0, 1.0]],
    )
    di = AgentSpec(
        "di",
        "double_integrator",
        ["goal", "velocity", "acceleration", "jerk", *always],
        radius=50.0,
        x0=[0.0, 2.0, 0.5, -0.2],
        goal=[2.0, 0.0],
    )
    return PotentialGame(
        GameSpec(
            [uni, bic, di], [{"type": "collision", "weight": 3.0, "every": 2}], horizon=6, dt=0.2
        )
    )


@pytest.fixture(scope="module")
def crossing():
    return crossing_game(N=3, K=30)


# ----------------------------------------------------------------------------- steps
@pytest.mark.parametrize(
    "steps, text",
    [
        ([], "-"),
        ([40], "40"),
        (range(1, 41), "1..40"),
        ([0, 1], "0..1"),
        (range(5, 41, 5), "5,10,..,40"),
        ([5, 10], "5,10"),
        ([0, 3, 7], "0,3,7"),
        ([0, 1, 2, 4, 8, 16, 32], "0,1,2,..,16,32"),
    ],
)
def test_format_steps(steps, text):
    assert format_steps(steps) == text


# ----------------------------------------------------------------------------- term table
def test_term_table_lists_every_term(crossing):
    game = crossing
    text = term_table(game)
    lines = text.splitlines()
    assert len(lines) == 3 + len(game.terms)  # title, header, rule, one line per term
    assert f"{len(game.terms)} energy terms" in lines[0]
    defaults = game.params.defaults()
    for t, line in zip(game.terms, lines[3:], strict=True):
        cells = line.split()
        assert cells[0] == str(t.index)
        assert cells[1] == t.kind
        assert cells[2] == "-".join(t.agents)
        assert t.weight in cells
        assert f"{defaults[game.params[t.weight].start]:g}" in cells
        assert format_steps(t.steps) in cells
        assert cells[-1] == f"{t.rows.start}:{t.rows.stop}"
        assert cells[-2] == str(t.size)
    kinds = {t.kind for t in game.terms}
    assert kinds == {"own", "pair"}


def test_term_rows_steps_compact(crossing):
    rows = term_rows(crossing)
    byfeat = {(r["agents"][0], r["feature"]): r for r in rows}
    K = crossing.K
    assert byfeat[("a0", "goal")]["steps"] == str(K)
    assert byfeat[("a0", "velocity")]["steps"] == f"1..{K}"
    assert byfeat[("a0", "acceleration")]["steps"] == f"0..{K - 1}"
    coll = [r for r in rows if r["kind"] == "pair"]
    assert len(coll) == 3 and all(r["weight_default"] == 10.0 for r in coll)
    assert sum(r["size"] for r in rows) == crossing.n_r


def test_labelled_feature_shows_type():
    a = AgentSpec(
        "a",
        "unicycle",
        [{"type": "velocity", "label": "slow", "weight": 2.0}, "goal"],
        x0=[0, 0, 1, 0],
        goal=[1, 0],
    )
    game = PotentialGame(GameSpec([a], horizon=4))
    assert "slow (velocity)" in term_table(game)
    assert "w.a.slow" in term_table(game)


# ----------------------------------------------------------------------------- breakdown
def test_breakdown_sums_to_energy(crossing):
    game = crossing
    p = game.default_params()
    u = RNG.normal(scale=0.2, size=game.n_u)
    r = np.asarray(game.function("residual")(u, p)).ravel()
    E = 0.5 * float(r @ r)  # independent of term_energies: the stacked residual
    rows = energy_breakdown(game, p, u)
    assert len(rows) == len(game.terms)
    for row, t in zip(rows, game.terms, strict=True):
        np.testing.assert_allclose(
            row["energy"], 0.5 * np.sum(r[t.rows] ** 2), rtol=1e-12, atol=1e-15
        )
    np.testing.assert_allclose(sum(x["energy"] for x in rows), E, rtol=1e-12)
    np.testing.assert_allclose(float(game.function("energy")(u, p)), E, rtol=1e-12)
    np.testing.assert_allclose(sum(x["share"] for x in rows), 1.0, rtol=1e-12)
    coll = [x for x in rows if x["feature_type"] == "collision"]
    assert max(x["energy"] for x in coll) > 0  # the regime this game claims: agents meet


def test_agent_breakdown_by_hand(crossing):
    game = crossing
    p = game.default_params()
    u = RNG.normal(scale=0.2, size=game.n_u)
    r = np.asarray(game.function("residual")(u, p)).ravel()
    C = np.asarray(game.function("agent_costs")(u, p)).ravel()
    for i, row in enumerate(agent_breakdown(game, p, u)):
        a = game.agent_names[i]
        own = sum(
            0.5 * np.sum(r[t.rows] ** 2) for t in game.terms if t.kind == "own" and t.agents == (a,)
        )
        pair = sum(
            0.5 * np.sum(r[t.rows] ** 2) for t in game.terms if t.kind == "pair" and a in t.agents
        )
        assert row["agent"] == a
        np.testing.assert_allclose(
            [row["own"], row["pair"], row["cost"]], [own, pair, own + pair], rtol=1e-12
        )
        np.testing.assert_allclose(row["cost"], C[i], rtol=1e-12)


def test_breakdown_table_text(crossing):
    game = crossing
    u = RNG.normal(scale=0.2, size=game.n_u)
    text = breakdown_table(game, game.default_params(), u)
    E = float(game.function("energy")(u, game.default_params()))
    assert f"energy E = {E:.6g}" in text
    for a in game.agent_names:
        assert any(line.startswith(a + " ") for line in text.splitlines())
    short = breakdown_table(game, game.default_params(), u, top=3)
    assert f"... {len(game.terms) - 3} more terms" in short


def test_breakdown_rejects_bad_inputs(crossing):
    with pytest.raises(SpecError, match="^u: "):
        energy_breakdown(crossing, crossing.default_params(), np.zeros(3))
    with pytest.raises(SpecError, match="^u/p: expected one problem"):
        energy_breakdown(crossing, crossing.default_params(), np.zeros((2, crossing.n_u)))
    with pytest.raises(SpecError, match="^game: "):
        term_table("not a game")


# ----------------------------------------------------------------------------- sparsity
def _fd_jacobian(game, u, p, h=1e-6):
    f = game.function("residual")
    J = np.empty((game.n_r, game.n_u))
    for j in range(game.n_u):
        e = np.zeros(game.n_u)
        e[j] = h
        J[:, j] = (np.asarray(f(u + e, p)).ravel() - np.asarray(f(u - e, p)).ravel()) / (2 * h)
    return J


def test_sparsity_matches_finite_differences():
    game = always_active_game()
    p = game.default_params()
    u = RNG.normal(scale=0.3, size=game.n_u)
    # the regime: every soft bound and collision term is active at u
    r = np.asarray(game.function("residual")(u, p)).ravel()
    for t in game.terms:
        if t.feature_type.endswith("_bound") or t.feature_type == "collision":
            assert np.all(r[t.rows] > 0), t
    J_fd = _fd_jacobian(game, u, p)
    sp = jacobian_sparsity(game)
    assert sp["shape"] == (game.n_r, game.n_u)
    assert sp["nnz"] == int(np.count_nonzero(J_fd))
    np.testing.assert_array_equal(jacobian_pattern(game), J_fd != 0)
    np.testing.assert_allclose(sp["density"], sp["nnz"] / (game.n_r * game.n_u))
    assert sum(t["nnz"] for t in sp["terms"]) == sp["nnz"]
    assert sum(a["nnz"] for a in sp["agents"]) == sp["nnz"]
    J = np.asarray(game.function("jacobian")(u, p))
    np.testing.assert_allclose(J, J_fd, rtol=1e-5, atol=1e-6)


def test_sparsity_structure_of_crossing(crossing):
    """Own terms touch only their agent's controls; the goal ignores the last control."""
    game = crossing
    pat = jacobian_pattern(game)
    for t in game.terms:
        cols = np.flatnonzero(pat[t.rows].any(axis=0))
        if t.kind == "own":
            i = game.agent_names.index(t.agents[0])
            assert cols.min() >= game.uoff[i] and cols.max() < game.uoff[i + 1]
        if t.feature_type == "goal":  # x_K depends on u_0 .. u_{K-2} only
            i = game.agent_names.index(t.agents[0])
            assert cols.max() == game.uoff[i + 1] - game.nu[i] - 1


def test_spy_text(crossing):
    text = spy_text(crossing, width=30)
    lines = text.splitlines()
    assert len(lines) == 2 + len(crossing.terms)
    for a in crossing.agent_names:
        assert "|" + a in lines[0]
    for t, line in zip(crossing.terms, lines[1:-1], strict=True):
        assert line.split()[0] == str(t.index)
        assert any(c in line for c in ".:#")
    assert lines[-1].startswith(f"J = dr/du: {crossing.n_r} x {crossing.n_u}")
    with pytest.raises(SpecError, match="^width: "):
        spy_text(crossing, width=2)


def test_inspect_imports_no_plotting():
    code = (
        "import sys, epo_casadi.inspect; print('matplotlib' in sys.modules, 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False False"


# ----------------------------------------------------------------------------- formulas
def _formula_value(game, t, u, p):
    """Evaluate a term's formula() expression with the symbols replaced by the rolled-out
    states, controls and parameters at every step of the term: one row block per step."""
    import casadi as ca

    from epo_casadi.inspect import FormulaSymbols, _feature_of

    i = game.agent_names.index(t.agents[0])
    expr = _feature_of(game, t).formula(FormulaSymbols(game, i))
    if isinstance(expr, str):
        return None
    x = np.asarray(game.function("rollout")(u, p)).ravel()
    X, U = game.split_states(x)[i], game.split_controls(u)[i]
    a = game.agents[i]
    names = {e: p[j] for j, e in enumerate(game.params.names)}
    syms = ca.symvar(expr)
    f = ca.Function("f", syms, [expr])
    out = []
    for k in t.steps:
        vals = []
        for s in syms:
            n = s.name()
            if n in names:
                vals.append(names[n])
                continue
            base, label = n.rsplit("_", 1)
            step = {"k": k, "{k+1}": k + 1, "K": game.K}[label]
            if base in a.dynamics.state_names:
                vals.append(X[step, a.dynamics.state_names.index(base)])
            else:
                vals.append(U[step, a.dynamics.control_names.index(base)])
        out.append(np.asarray(f(*vals), dtype=float).ravel())
    return np.concatenate(out)


def test_formulas_evaluate_to_the_residual():
    """Each built-in formula(), evaluated with the solution's numbers, gives the term's
    residual rows divided by the weight (so the formula is the feature's own definition)."""
    from epo_casadi.inspect import term_formula

    game = always_active_game()
    p = game.default_params()
    u = RNG.normal(scale=0.3, size=game.n_u)
    r = np.asarray(game.function("residual")(u, p)).ravel()
    checked = 0
    for t in game.terms:
        tf = term_formula(game, t)
        assert tf["source"] == "formula()"
        assert tf["formula"].startswith(t.weight + " * ")
        if t.kind != "own":
            continue
        val = _formula_value(game, t, u, p)
        if val is None:  # path: a sentence, not an expression
            assert "min over segments" in tf["residual"]
            continue
        w = p[game.params[t.weight].start]
        np.testing.assert_allclose(val * w, r[t.rows], rtol=1e-12, atol=1e-12)
        checked += 1
    assert checked >= 15
    goal = term_formula(game, game.terms[0])
    assert goal["formula"] == "w.uni.goal * [(x_K-goal.uni.x), (y_K-goal.uni.y)]"
    coll = next(t for t in game.terms if t.kind == "pair")
    text = term_formula(game, coll)["residual"]
    assert "uni.x_k" in text and "bic.x_k" in text and "max(0" in text


def test_feature_without_formula_gets_the_generic_display():
    from dataclasses import dataclass

    from epo_casadi.features import Velocity
    from epo_casadi.inspect import term_formula

    @dataclass(frozen=True)
    class Mine(Velocity):  # a user feature that declares no formula
        def formula(self, s):
            return None

    a = AgentSpec("a", "unicycle", [Mine(label="mine")], x0=[0, 0, 1, 0])
    game = PotentialGame(GameSpec([a], horizon=5))
    tf = term_formula(game, game.terms[0])
    assert tf["residual"] == "v_1" and "generic" in tf["source"]


# ----------------------------------------------------------------------------- report
def test_hessian_pattern_is_that_of_jt_j():
    from epo_casadi.inspect import hessian_pattern, hessian_sparsity

    game = always_active_game()
    p = game.default_params()
    u = RNG.normal(scale=0.3, size=game.n_u)
    J = _fd_jacobian(game, u, p)
    B = (J != 0).astype(int)
    ref = (B.T @ B) > 0
    H = hessian_pattern(game).toarray()
    np.testing.assert_array_equal(H, ref)
    hs = hessian_sparsity(game)
    assert hs["nnz"] == int(ref.sum())
    assert sum(map(sum, hs["agent_blocks"])) == hs["nnz"]
    # the exact Hessian's structure lies inside the Gauss-Newton pattern
    Hx = np.asarray(game.function("hessian")(u, p))
    assert not np.any((Hx != 0) & ~H)


def test_term_series_and_report(crossing):
    from epo_casadi.inspect import ENERGY_CONVENTION, inspect_report, report_text, term_series

    game = crossing
    p = game.default_params()
    u = RNG.normal(scale=0.2, size=game.n_u)
    e = np.asarray(game.function("term_energies")(u, p)).ravel()
    r = np.asarray(game.function("residual")(u, p)).ravel()
    for s, t in zip(term_series(game, p, u), game.terms, strict=True):
        np.testing.assert_allclose(sum(s["energy"]), e[t.index], rtol=1e-12, atol=1e-15)
        rows = r[t.rows].reshape(len(t.steps), -1)
        assert s["active"] == [k for k, row in zip(t.steps, rows, strict=True) if np.any(row)]
    coll = [s for s, t in zip(term_series(game, p, u), game.terms, strict=True) if t.kind == "pair"]
    assert any(0 < len(s["active"]) < len(s["steps"]) for s in coll)  # active on some steps
    rep = inspect_report(game, p, u)
    text = report_text(game, rep)
    assert text.count(ENERGY_CONVENTION) == 1 and "enters squared" in ENERGY_CONVENTION
    assert f"energy E = {e.sum():.6g}" in text
    assert f"{rep['hessian']['nnz']} structural nonzeros" in text
    assert "legend:" in text and "x+ = x+(0.1*(v*cos(theta)))" in text
    assert rep["dynamics"][0]["agents"] == game.agent_names
    assert rep["dynamics"][0]["integrator"] == "explicit Euler"
    np.testing.assert_allclose([v for b in rep["params"] for v in b["values"]], p, rtol=0, atol=0)


def test_cli_inspect_json_matches_text(tmp_path):
    """`epo inspect --solve --json` parses, and its numbers are the ones the text shows."""
    import json

    from scenarios.gamefile import example_path

    game_file = str(example_path("crossing2"))
    epo = [sys.executable, "-m", "scenarios.cli"]
    common = ["inspect", game_file, "--solve", "--set", "w.a0.goal=4"]
    plot = tmp_path / "t.png"
    js = subprocess.run(
        [*epo, *common, "--json"], capture_output=True, text=True, check=True
    ).stdout
    txt = subprocess.run(
        [*epo, *common, "--plot", str(plot)], capture_output=True, text=True, check=True
    ).stdout
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rep = json.loads(js)
    assert rep["format"] == "epo-inspect/1"
    assert f"energy E = {rep['solution']['energy']:.6g}" in txt
    for s in rep["solution"]["terms"]:
        assert f"{s['energy']:.6g}" in txt
    for a in rep["solution"]["agent_costs"]:
        assert f"{a['cost']:.6g}" in txt
    for t in rep["terms"]:
        assert t["formula"] in txt
    assert next(t for t in rep["terms"] if t["weight"] == "w.a0.goal")["weight_value"] == 4.0
    assert f"{rep['jacobian']['nnz']} structural nonzeros" in txt
    assert f"{rep['hessian']['nnz']} structural nonzeros" in txt
    X = np.asarray(rep["solution"]["states"]["a0"])
    assert X.shape == (31, 4)


# coupled dynamics (GameSpec.couplings): the summary shows the joint model's update
# --------------------------------------------------------------------------------------
def test_dynamics_summary_shows_the_joint_model_of_coupled_agents():
    """Reference: the game's own stage map (``stage_step``) at a random point, against the
    summary's update expressions evaluated as Python; the coupling term is non-zero there,
    so the members' own steps would give other values."""
    import json
    from dataclasses import dataclass
    from types import SimpleNamespace

    import casadi as ca

    from epo_casadi import Acceleration, Coupling, Goal, JointDynamics
    from epo_casadi.inspect import dynamics_summary, inspect_report, report_text

    @dataclass(frozen=True)
    class Tow(JointDynamics):
        name = "tow"
        k: float = 0.8

        def step(self, xs, us, dt):
            (x1, x2), (u1, u2) = xs, us
            v2 = x2[2:4] + dt * u2 + self.k * dt * (x1[2:4] - x2[2:4])
            return [
                ca.vertcat(x1[0:2] + dt * x1[2:4], x1[2:4] + dt * u1),
                ca.vertcat(x2[0:2] + dt * x2[2:4], v2),
            ]

    f = [Goal(weight=1.0), Acceleration()]
    agents = [
        AgentSpec("ped", "unicycle", f, x0=[0, 1, 1, 0], goal=[0, 0]),
        AgentSpec("truck", "double_integrator", f, x0=[0, 0, 1, 0], goal=[1, 0]),
        AgentSpec("trailer", "double_integrator", f, x0=[-1, 0, 1, 0], goal=[0, 0]),
    ]
    coupling = Coupling(("truck", "trailer"), Tow())
    g = PotentialGame(GameSpec(agents, horizon=3, dt=0.5, couplings=[coupling]))
    groups = dynamics_summary(g)
    assert [(d["model"], d["agents"], d["coupled"]) for d in groups] == [
        ("unicycle", ["ped"], False),
        ("tow", ["truck", "trailer"], True),
    ]
    tow = groups[1]
    assert tow["member_models"] == ["double_integrator", "double_integrator"]
    assert tow["states"][:2] == ["truck.x", "truck.y"] and len(tow["states"]) == 8
    assert tow["controls"] == ["truck.ax", "truck.ay", "trailer.ax", "trailer.ay"]
    assert "truck.vx" in tow["update"]["trailer.vx"]  # the coupling is visible

    rng = np.random.default_rng(0)
    x, u = rng.standard_normal(int(sum(g.nx))), rng.standard_normal(int(sum(g.nu)))
    nxt = np.asarray(ca.evalf(g.stage_step(ca.DM(x), ca.DM(u)))).ravel()
    # evaluate the printed expressions: agent.state -> value
    names = {"ped": ("x", "y", "v", "theta", "a", "omega")}
    names |= {a: ("x", "y", "vx", "vy", "ax", "ay") for a in ("truck", "trailer")}
    xs, us = np.split(x, [4, 8]), np.split(u, [2, 4])
    env = {"cos": np.cos, "sin": np.sin, "sq": np.square}
    for i, a in enumerate(("ped", "truck", "trailer")):
        env[a] = SimpleNamespace(**dict(zip(names[a], [*xs[i], *us[i]], strict=True)))
    got = [eval(e, env) for e in tow["update"].values()]  # noqa: S307 - our own printout
    np.testing.assert_allclose(got, nxt[4:], rtol=1e-12, atol=1e-12)
    own = np.asarray(ca.evalf(agents[2].dynamics.step(ca.DM(xs[2]), ca.DM(us[2]), 0.5))).ravel()
    assert np.abs(own - nxt[8:]).max() > 1e-3  # the own step would be wrong here
    assert list(groups[0]["update"]) == ["x", "y", "v", "theta"]  # uncoupled: as before

    rep = inspect_report(g, hessian=False)
    assert json.loads(json.dumps(rep["dynamics"])) == groups
    assert "tow [truck, trailer] (coupled" in report_text(g, rep, spy=False)
