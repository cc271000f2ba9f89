"""Reliability of the solve path (issue 15, items 1, 2, 7, 8 and the clear-error and
consistency items): one regression test per defect, each naming the class it closes.

Every test is small: games of at most K = 30 steps, bombs of a few thousand values
against a lowered limit.
"""

from __future__ import annotations

import errno
import json
import os

import numpy as np
import pytest
import yaml

import scenarios.gamefile as gamefile
from epo_casadi import Collision, GameSpec, SpecError
from epo_casadi.errors import OutputError
from scenarios.cli import main
from scenarios.commands.demo import _row
from scenarios.commands.solve import (
    EXIT_FAILED,
    EXIT_STALLED,
    energy_history,
    exit_code,
    result_dict,
    summary_lines,
    write_result,
)
from scenarios.gamefile import apply_settings, example_path, load_game, parse_game
from scenarios.plotting import plot_energy_history, plot_trajectories
from solvers.ipopt import ipopt_status, solve_ipopt
from solvers.lm import MAX_STEPS, DenseGN, LMOptions, solve_lm
from solvers.result import SolveResult, Status, demote_nonfinite

from .test_lm import di_game, di_reference

PNG = b"\x89PNG\r\n\x1a\n"


def run(capsys, *args) -> tuple[int, str, str]:
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def crossing():
    return load_game(example_path("crossing2"))


def crossing_dict(**changes) -> dict:
    d = yaml.safe_load(example_path("crossing2").read_text())
    d.update(changes)
    return d


# --------------------------------------------------------------------------------------
# Item 1. Class: every summary, file and figure writer is total over every status,
# with NaN / inf / None values anywhere a solver can leave them.
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("status", list(Status))
def test_every_status_through_every_writer(status, crossing, tmp_path):
    game, p = crossing.game, crossing.params
    rng = np.random.default_rng(0)
    x = np.asarray(game.function("rollout")(np.zeros(game.n_u), p)).ravel()
    x[7:40] = np.nan  # part of a trajectory lost
    x[50] = np.inf
    res = SolveResult(
        solver="lm",
        controls=rng.standard_normal(game.n_u),
        states=x,
        energy=np.array(np.inf),
        agent_costs=np.array([np.nan, 2.5]),
        status=status,
        iterations=np.array(3),
        energy_history=np.array([1.0, np.inf, np.nan, np.inf]),
        grad_norm=np.array(np.nan),
        wall_time=0.1,
        info={"options": LMOptions()},
    )
    s = res.summary()
    assert s.startswith(f"lm: {status.value}") and "energy inf" in s and "|grad|_inf nan" in s
    batch = SolveResult(
        **{
            **res.__dict__,
            "energy": np.array([np.inf, 1.0]),
            "status": np.array([status, Status.CONVERGED], dtype=object),
            "iterations": np.array([3, 4]),
            "grad_norm": np.array([np.nan, 0.0]),
            "controls": np.zeros((2, game.n_u)),
            "energy_history": np.ones((4, 2)),
        }
    )
    assert "energy mean 1 (1 non-finite)" in batch.summary()
    json.dumps(res.to_dict(), allow_nan=False)  # strict JSON from the library too
    cert = {"ok": False, "stationarity": [None, 1.0], "best_response_gap": [0.5, None]}
    data = result_dict(game, p, res, source="crossing2.yaml")
    assert data["energy"] is None and data["agent_costs"]["a0"] is None
    path = write_result(data, tmp_path / "r.json")
    back = json.loads(path.read_text())  # strict JSON: NaN / inf became null
    assert back["status"] == status.value and back["agent_costs"] == {"a0": None, "a1": 2.5}
    for d in (back, {**back, "certificate": cert}):
        text = "\n".join(summary_lines(game, d))
        assert "energy none (non-finite)" in text and "a1 2.5" in text
        assert _row("crossing2", d)[3] == "none"
    assert "max |dC_i/du_i| none" in "\n".join(summary_lines(game, {**back, "certificate": cert}))
    plot_trajectories(game, res.states, p, tmp_path / "t.png", title="E = inf")
    plot_energy_history({"lm": energy_history(res)}, tmp_path / "e.png")
    assert (tmp_path / "t.png").read_bytes()[:8] == PNG
    assert (tmp_path / "e.png").read_bytes()[:8] == PNG
    # the documented exit status of every status
    expected = {Status.CONVERGED: 0, Status.MAX_ITER: 0, Status.STALLED: EXIT_STALLED}
    assert exit_code(status) == expected.get(status, EXIT_FAILED)


@pytest.mark.parametrize(
    "change",
    [
        {"dt": 1e308},
        {"agents": "radius"},
        {"agents": "x0"},
    ],
    ids=["dt", "radius", "x0"],
)
def test_overflowing_inputs_end_nonfinite_with_file_and_exit_1(change, capsys, tmp_path):
    """Class: finite but overflowing inputs (dt, radius, x0 of 1e308) end in a written file
    and exit 1, never in a traceback."""
    d = crossing_dict()
    if "dt" in change:
        d["dt"] = change["dt"]
    elif change["agents"] == "radius":
        d["agents"][0]["radius"] = 1e308
    else:
        d["agents"][0]["x0"][0] = 1e308
    game_file = tmp_path / "g.yaml"
    game_file.write_text(yaml.safe_dump(d))
    out = tmp_path / "r.json"
    rc, stdout, err = run(capsys, "solve", game_file, "--out", out, "--plot", tmp_path / "f.png")
    assert rc == 1, err
    assert json.loads(out.read_text())["status"] == "nonfinite"
    assert "Traceback" not in err and (tmp_path / "f.png").exists()


def test_usable_looking_status_with_nonfinite_values_is_nonfinite():
    """Class: no result reports a usable status while its energy, costs or states are
    NaN / inf (both solvers pass their arrays through demote_nonfinite)."""
    st = np.array([Status.CONVERGED, Status.MAX_ITER, Status.STALLED, Status.FAILED], object)
    E = np.array([[1.0], [np.inf], [1.0], [np.nan]])
    X = np.array([[0.0, 1.0], [0.0, 1.0], [np.nan, 1.0], [0.0, 1.0]])
    out = demote_nonfinite(st, E, X)
    assert list(out) == [Status.CONVERGED, Status.NONFINITE, Status.NONFINITE, Status.FAILED]


# --------------------------------------------------------------------------------------
# Item 2. Class: "converged" only where a first-order test holds; stalls are their own
# status and exit code.
# --------------------------------------------------------------------------------------
def test_lm_damping_cap_far_from_stationary_is_stalled(crossing):
    """The reported case: radius 1e6 makes LM's damping hit its cap with |grad| ~ 1e14.
    The independent reference (IPOPT) finds a much lower energy: not a minimum."""
    gf = parse_game(crossing_dict(agents=[{**a, "radius": 1e6} for a in crossing_dict()["agents"]]))
    lm = solve_lm(gf.game, gf.params, options=gf.options("lm"))
    assert lm.status is Status.STALLED and lm.info["stop"] == "max_damping"
    assert lm.grad_norm > 1e10 and lm.info["residual_cosine"] > 0.1
    ip = solve_ipopt(gf.game, gf.params, options=gf.options("ipopt"))
    assert ip.energy < lm.energy / 2


def test_lm_ftol_stop_with_large_gradient_is_stalled():
    """A tiny step (huge damping) meets ftol at once while the gradient is large; the
    closed-form optimum is far lower."""
    g = di_game()
    goal = [2.0, -1.5]
    p = g.default_params(goal__di=goal)
    res = solve_lm(g, p, options={"damping": 1e8, "damping_down": 0.99, "ftol": 1e-6})
    assert res.status is Status.STALLED and res.info["stop"] == "ftol"
    _, e_ref = di_reference([0.5, -0.2, 1.0, 0.4], goal)
    assert res.energy > 5 * e_ref


def test_ftol_stop_near_a_minimum_stays_converged(crossing):
    """The other side of the class: the examples stop by ftol with |grad| above gtol and
    must stay converged. The residual cosine is checked against a dense computation."""
    game, p = crossing.game, crossing.params
    res = solve_lm(game, p, options=crossing.options("lm"))
    assert res.status is Status.CONVERGED and res.info["stop"] == "ftol"
    assert res.grad_norm > LMOptions().gtol  # so the cosine test is what decided
    lin = DenseGN(game).linearize(res.controls[None], p[None])
    J, r = lin.J[0], lin.r[0]
    cos = np.max(np.abs(J.T @ r) / (np.linalg.norm(J, axis=0) * np.linalg.norm(r)))
    assert res.info["residual_cosine"] == pytest.approx(cos, rel=1e-6)
    assert cos < LMOptions().ctol


def test_stalled_solve_exit_3_after_writing(capsys, tmp_path):
    d = crossing_dict()
    for a in d["agents"]:
        a["radius"] = 1e6
    game_file = tmp_path / "g.yaml"
    game_file.write_text(yaml.safe_dump(d))
    out = tmp_path / "r.json"
    rc, stdout, err = run(capsys, "solve", game_file, "--out", out, "--no-certificate")
    assert rc == EXIT_STALLED == 3, err
    data = json.loads(out.read_text())
    assert data["status"] == "stalled" and data["ok"] is False
    assert "stalled" in err and "Traceback" not in err


def test_ipopt_no_progress_is_stalled_not_failed():
    assert ipopt_status("Search_Direction_Becomes_Too_Small") is Status.STALLED
    assert ipopt_status("Solved_To_Acceptable_Level") is Status.CONVERGED
    assert ipopt_status("Diverging_Iterates") is Status.FAILED


# --------------------------------------------------------------------------------------
# Item 7. Class: YAML aliases cannot make the loader walk or print more than a bound.
# --------------------------------------------------------------------------------------
def _bomb(levels: int, width: int = 10) -> str:
    parts = ["&a0 [" + ", ".join(["1"] * width) + "]"]
    parts += [f"&a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]" for i in range(1, levels)]
    return "[" + ", ".join(parts) + "]"


@pytest.mark.parametrize(
    "old, key", [("lm: {steps: 200}", "solver.lm.steps"), ("horizon: 30", "horizon")]
)
def test_alias_bomb_is_refused_fast(old, key, tmp_path, monkeypatch):
    monkeypatch.setattr(gamefile.checks, "MAX_VALUES", 500)
    text = example_path("crossing2").read_text()
    new = old.replace("200", _bomb(4)) if "steps" in old else f"horizon: {_bomb(4)}"
    path = tmp_path / "bomb.yaml"
    path.write_text(text.replace(old, new))
    with pytest.raises(SpecError, match="expands to more than 500 values") as e:
        load_game(path)
    assert e.value.field.startswith(key)  # names the entry: solver.lm.steps[3]
    # just under the limit: the count is the expanded one (1 + 10 + 10^2 + 10^3 ...)
    monkeypatch.setattr(gamefile.checks, "MAX_VALUES", 10**6)
    with pytest.raises(SpecError) as e:
        load_game(path)  # not a bomb any more, but still not an integer
    assert e.value.field == key and len(str(e.value)) < 300  # no repr of the structure


def test_recursive_alias_is_refused(tmp_path):
    text = example_path("crossing2").read_text().replace("horizon: 30", "horizon: &h [1, *h]")
    path = tmp_path / "rec.yaml"
    path.write_text(text)
    with pytest.raises(SpecError, match="contains it"):
        load_game(path)


def test_error_messages_are_bounded():
    """A huge value in an option is shown elided, never as its whole repr."""
    big = [list(range(10**4))] * 100
    with pytest.raises(SpecError) as e:
        LMOptions(steps=big)
    assert len(str(e.value)) < 300 and "..." in str(e.value)


# --------------------------------------------------------------------------------------
# Item 8. Class: what an input can allocate is bounded, and the error names the limit.
# --------------------------------------------------------------------------------------
def test_history_grows_with_steps_taken_not_the_limit():
    g = di_game()
    res = solve_lm(g, g.default_params(), options={"steps": MAX_STEPS})
    assert res.status is Status.CONVERGED and int(res.iterations) < 100
    assert res.energy_history.shape == (int(res.iterations) + 1,)
    assert res.info["damping_history"].shape == (int(res.iterations) + 1, 1)


def test_huge_limits_are_refused_naming_field_and_limit(capsys):
    with pytest.raises(SpecError, match=f"<= {MAX_STEPS}") as e:
        LMOptions(steps=MAX_STEPS + 1)
    assert e.value.field == "lm.steps"
    with pytest.raises(SpecError, match=rf"\[0, {MAX_STEPS}\]"):
        solve_ipopt(di_game(), di_game().default_params(), options={"max_iter": 10**12})
    with pytest.raises(SpecError, match=f"<= {gamefile.MAX_HORIZON}") as e:
        parse_game(crossing_dict(horizon=10**12))
    assert e.value.field == "horizon"
    rc, _, err = run(capsys, "solve", example_path("crossing2"), "--steps", 10**20)
    assert rc == 2 and str(MAX_STEPS) in err and "Traceback" not in err


# --------------------------------------------------------------------------------------
# Clear errors. Class: an output that cannot be written is one line, exit 2, and leaves
# no partial file (writes are atomic).
# --------------------------------------------------------------------------------------
def test_out_through_a_file_is_one_line_exit_2(capsys, tmp_path):
    blocker = tmp_path / "file.json"
    blocker.write_text("{}")
    target = blocker / "inside" / "r.json"
    for args in (
        ("solve", example_path("crossing2"), "--no-certificate", "--steps", 1, "--out", target),
        ("inspect", example_path("crossing2"), "--no-spy", "--spy-png", blocker / "s.png"),
        ("demo", "--out", blocker / "sub"),
    ):
        rc, _, err = run(capsys, *args)
        assert rc == 2, err
        line = err.strip()
        assert "\n" not in line and "is a file, not a folder" in line and "Traceback" not in err
    assert blocker.read_text() == "{}"


def test_full_disk_leaves_no_partial_file(capsys, tmp_path, monkeypatch):
    out = tmp_path / "r.json"
    out.write_text("old result")

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)  # the data never reaches the disk
    rc, _, err = run(
        capsys, "solve", example_path("crossing2"), "--no-certificate", "--steps", 1, "--out", out
    )
    assert rc == 2 and f"{out}: cannot write: no space left on the device" in err
    assert out.read_text() == "old result"  # the older file is intact
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]  # no temporary left
    with pytest.raises(OutputError):
        plot_energy_history([1.0, 0.5], tmp_path / "e.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]


# --------------------------------------------------------------------------------------
# Consistency. Class: one rule for weights (the layer's: >= 0) wherever they enter; a
# pair term that checks no step is refused.
# --------------------------------------------------------------------------------------
def test_negative_weights_are_refused_everywhere(crossing):
    rule = "weights must be >= 0"  # learning.layer's wording
    d = crossing_dict()
    d["agents"][0]["features"][0]["weight"] = -3.0
    with pytest.raises(SpecError, match=rule) as e:
        parse_game(d)
    assert e.value.field == "agents[0].features[0].weight"
    d = crossing_dict(pair_features=[{"type": "collision", "weight": -1.0}])
    with pytest.raises(SpecError, match=rule) as e:
        parse_game(d)
    assert e.value.field == "pair_features[0].weight"
    with pytest.raises(SpecError, match=rule) as e:
        apply_settings(crossing.game, crossing.params, ["w.a0-a1.collision=-0.5"])
    assert e.value.field == "--set w.a0-a1.collision"
    with pytest.raises(SpecError, match=rule):
        apply_settings(crossing.game, crossing.params, ["w.a1.velocity=-1"])
    with pytest.raises(SpecError, match=rule):
        Collision(weight=-1.0)
    spec = crossing.spec
    bad = spec.agents[0].features[0].__class__(weight=-1.0)
    with pytest.raises(SpecError, match=rule):
        GameSpec(
            [
                spec.agents[0].__class__(
                    **{**spec.agents[0].__dict__, "features": (bad, *spec.agents[0].features[1:])}
                ),
                spec.agents[1],
            ],
            spec.pair_features,
            horizon=spec.horizon,
            dt=spec.dt,
        )
    # zero is a valid weight, and negative entries outside the weights are fine
    p = apply_settings(crossing.game, crossing.params, ["w.a0.goal=0", "x0.a0.x=-5"])
    assert p[crossing.game.params["w.a0.goal"].start] == 0.0


def test_collision_every_beyond_horizon_is_refused():
    d = crossing_dict(pair_features=[{"type": "collision", "weight": 1.0, "every": 31}])
    with pytest.raises(SpecError, match=r"<= horizon \(30\)") as e:
        parse_game(d)
    assert e.value.field == "pair_features[0].every"
    d["pair_features"][0]["every"] = 30  # one checked step: the last
    gf = parse_game(d)
    pair = [t for t in gf.game.terms if t.kind == "pair"]
    assert len(pair) == 1 and pair[0].steps == (30,) and pair[0].size == 1


def test_library_specs_bound_horizon_and_every_like_game_files():
    """Class: the same limits for the Python API as for game files (GameSpec, not only the
    file parser, refuses a horizon beyond MAX_HORIZON and a pair term with no rows)."""
    from epo_casadi import AgentSpec, Collision, GameSpec, Goal
    from epo_casadi.game import MAX_HORIZON

    agents = [
        AgentSpec("a", "unicycle", [Goal()], x0=[0, 0, 1, 0], goal=[1, 0]),
        AgentSpec("b", "unicycle", [Goal()], x0=[0, 1, 1, 0], goal=[1, 1]),
    ]
    with pytest.raises(SpecError, match=f"horizon: expected at most {MAX_HORIZON}"):
        GameSpec(agents, horizon=10**12)
    with pytest.raises(
        SpecError, match=r"pair_features\[0\]\.every: expected an integer <= horizon \(10\)"
    ):
        GameSpec(agents, [Collision(every=11)], horizon=10)
    GameSpec(agents, [Collision(every=10)], horizon=10)  # the last step is a row: accepted


# --------------------------------------------------------------------------------------
# The same class for iLQ results and multi-modal results (epo solve --solver ilq,
# epo solve --modes N): every writer total over every status and over an empty mode list.
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("status", list(Status))
def test_every_status_through_ilq_and_mode_writers(status, crossing, tmp_path):
    from scenarios.commands.solve import mode_lines, modes_dict
    from scenarios.plotting import plot_modes
    from solvers.ilq import ILQOptions
    from solvers.multimodal import Mode, MultiModalResult

    game, p = crossing.game, crossing.params
    x = np.asarray(game.function("rollout")(np.zeros(game.n_u), p)).ravel()
    x[7:40] = np.nan
    res = SolveResult(
        solver="ilq",
        controls=np.zeros(game.n_u),
        states=x,
        energy=np.array(np.nan),
        agent_costs=np.array([np.inf, 2.5]),
        status=status,
        iterations=np.array(2),
        energy_history=np.array([1.0, np.nan, np.inf]),
        grad_norm=np.array(np.nan),
        wall_time=0.1,
        info={"options": ILQOptions(), "stationarity": np.inf, "stop": "line_search"},
    )
    data = result_dict(game, p, res, source="crossing2.yaml")
    assert data["feedback_residual"] is None and data["stop"] == "line_search"
    back = json.loads(write_result(data, tmp_path / "r.json").read_text())
    text = "\n".join(summary_lines(game, back))
    assert f"ilq: {status.value}" in text and "max |a| none (non-finite)" in text
    mode = Mode(
        controls=res.controls,
        states=x,
        share=1.0,
        cost=np.array([np.nan, 1.0]),
        energy=np.nan,
        members=np.array([0]),
        medoid=0,
        passing=(1,),
    )
    batch = SolveResult(
        **{
            **res.__dict__,
            "controls": res.controls[None],
            "states": x[None],
            "energy": np.array([np.nan]),
            "agent_costs": res.agent_costs[None],
            "status": np.array([status], dtype=object),
            "iterations": np.array([2]),
            "energy_history": res.energy_history[:, None],
            "grad_norm": np.array([np.nan]),
        }
    )
    for modes in ([mode], []):
        mm = MultiModalResult(modes, np.zeros(1, int), np.ones(1, bool), batch, res.controls, 0.1)
        listed = modes_dict(game, mm)
        back = json.loads(write_result({**data, "modes": listed}, tmp_path / "m.json").read_text())
        lines = "\n".join(mode_lines(game, back["modes"], 1, batch.message))
        assert f"1 {status.value}" in lines
        assert ("energy none (non-finite)" in lines) if modes else ("no mode" in lines)
        plot_modes(game, modes, p, tmp_path / "m.png", title="E = nan")
        assert (tmp_path / "m.png").read_bytes()[:8] == PNG


def test_ilq_from_the_command_line_file_options_and_stall(capsys, tmp_path):
    """`solver.ilq` options in the file reach the solver; a trust region no step fits in
    makes the solve 'stalled' (exit 3) after the file is written; a bad option is one line,
    exit 2."""
    d = crossing_dict(solver={"ilq": {"max_state_step": 1e-12}})
    game_file = tmp_path / "g.yaml"
    game_file.write_text(yaml.safe_dump(d))
    out = tmp_path / "r.json"
    rc, stdout, err = run(capsys, "solve", game_file, "--solver", "ilq", "--out", out)
    assert rc == EXIT_STALLED, err
    data = json.loads(out.read_text())
    # no step fits: regularization climbs until max |a| is tiny only because of it
    assert data["status"] == "stalled" and data["stop"] in ("regularized_only", "line_search")
    assert data["feedback_residual"] > 1e-5  # at the requested regularization
    assert data["options"]["max_state_step"] == 1e-12 and data["certificate"] is None
    assert "feedback Nash residual" in stdout and "Traceback" not in err
    d["solver"] = {"ilq": {"max_state_step": 1.0, "tol": -1}}
    game_file.write_text(yaml.safe_dump(d))
    rc, _, err = run(capsys, "solve", game_file, "--solver", "ilq")
    assert rc == 2 and "solver.ilq.tol" in err and len(err.strip().splitlines()) == 1


def test_modes_from_the_command_line(capsys, tmp_path):
    """`epo solve --modes N`: modes with shares printed, written and plotted; every solve
    dropped gives an empty list, the file and exit 1; IPOPT is refused (exit 2)."""
    f = example_path("crossing2")
    out, png = tmp_path / "m.json", tmp_path / "m.png"
    rc, stdout, err = run(
        capsys, "solve", f, "--solver", "ilq", "--modes", 6, "--out", out, "--plot", png
    )
    assert rc == 0, err
    data = json.loads(out.read_text())
    shares = [m["share"] for m in data["modes"]]
    assert data["samples"] == 6 and len(shares) >= 1
    assert abs(sum(shares) - 1) < 1e-12 and shares == sorted(shares, reverse=True)
    assert sum(len(m["members"]) for m in data["modes"]) <= 6
    assert data["status"] == "converged" and "mode 0: share" in stdout
    assert png.read_bytes()[:8] == PNG
    rc, stdout, err = run(capsys, "solve", f, "--solver", "lm", "--modes", 3, "--steps", 0,
                          "--out", out)  # fmt: skip
    assert rc == EXIT_FAILED and "no mode" in err
    data = json.loads(out.read_text())
    assert data["modes"] == [] and data["status"] == "max_iter"
    rc, _, err = run(capsys, "solve", f, "--solver", "ipopt", "--modes", 3)
    assert rc == 2 and "--modes" in err and "Traceback" not in err


def test_lm_polish_turns_a_tight_ftol_stall_into_converged(crossing):
    """Asked for a tight first-order test (ctol 1e-12), LM stops by ftol with |grad| ~ 2e-7
    > gtol: 'stalled'. With polish=3, exact-Hessian Newton steps bring |grad| below gtol
    (status 'converged', stop 'polish'), at IPOPT's solution (an independent solver)."""
    game, p = crossing.game, crossing.params
    tight = solve_lm(game, p, options={"ctol": 1e-12})
    assert tight.status is Status.STALLED and tight.info["stop"] == "ftol"
    assert tight.grad_norm > LMOptions().gtol
    res = solve_lm(game, p, options={"ctol": 1e-12, "polish": 3})
    assert res.status is Status.CONVERGED and res.info["stop"] == "polish"
    grad = np.abs(np.asarray(game.function("gradient")(res.controls, p))).max()
    assert grad <= LMOptions().gtol and res.grad_norm <= LMOptions().gtol
    ip = solve_ipopt(game, p)
    np.testing.assert_allclose(res.controls, ip.controls, atol=1e-6)
    assert res.energy <= tight.energy + 1e-12
    with pytest.raises(SpecError, match="lm.polish"):
        LMOptions(polish=-1)
