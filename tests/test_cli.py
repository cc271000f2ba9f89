"""The ``epo`` command line end to end: ``solve`` on every example file, ``inspect``,
``demo``, and bad input (exit code 2, one message naming the field, no traceback).

Commands run in-process through :func:`scenarios.cli.main`; one test runs the installed
console script in a real subprocess.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import warnings
from pathlib import Path

import click
import numpy as np
import pytest
import yaml

from scenarios.cli import main
from scenarios.gamefile import EXAMPLES, example_path, load_game

PNG = b"\x89PNG\r\n\x1a\n"
SMALL = ("crossing2", "robot_pedestrian")  # IPOPT end to end on these


def run(capsys, *args) -> tuple[int, str, str]:
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def games():
    return {name: load_game(example_path(name)) for name in EXAMPLES}


def check_result(data: dict, gf, solver: str) -> None:
    """Shapes, status, certificate, and a solution that is better than doing nothing."""
    game = gf.game
    assert data["format"] == "epo-result/1"
    assert data["solver"] == solver
    assert data["agents"] == game.agent_names
    assert data["status"] == "converged", data["message"]
    assert data["ok"] is True and data["message"]
    assert data["iterations"] > 0 and data["time_s"] > 0
    for i, a in enumerate(game.agents):
        X = np.asarray(data["states"][a.name])
        U = np.asarray(data["controls"][a.name])
        assert X.shape == (game.K + 1, game.nx[i])
        assert U.shape == (game.K, game.nu[i])
        np.testing.assert_allclose(X[0], a.x0)
        assert data["state_names"][a.name] == list(a.dynamics.state_names)
    u = game.join_controls([np.asarray(data["controls"][a]) for a in game.agent_names])
    p = game.params.pack(data["params"])
    np.testing.assert_array_equal(p, gf.params)
    # energy and costs in the file are those of the controls in the file
    np.testing.assert_allclose(data["energy"], float(game.function("energy")(u, p)), rtol=1e-10)
    C = np.asarray(game.function("agent_costs")(u, p)).ravel()
    np.testing.assert_allclose([data["agent_costs"][a] for a in game.agent_names], C, rtol=1e-10)
    x = np.asarray(game.function("rollout")(u, p)).ravel()
    for i, a in enumerate(game.agent_names):
        np.testing.assert_allclose(
            np.asarray(data["states"][a]), game.split_states(x)[i], rtol=1e-10, atol=1e-10
        )
    # sensible: much lower energy than u = 0, collisions (active at u = 0) nearly resolved
    E0 = float(game.function("energy")(game.zero_controls(), p))
    assert data["energy"] < 0.5 * E0
    e = np.asarray(game.function("term_energies")(u, p)).ravel()
    e0 = np.asarray(game.function("term_energies")(game.zero_controls(), p)).ravel()
    coll = [t.index for t in game.terms if t.feature_type == "collision"]
    assert e[coll].sum() < 0.05 * e0[coll].sum()
    # the local Nash certificate is there and passes
    cert = data["certificate"]
    assert cert["agents"] == game.agent_names
    assert len(cert["stationarity"]) == len(cert["best_response_gap"]) == game.N
    assert cert["ok"] is True
    if solver == "lm":  # one entry before each step and one at the end, no padding
        hist = data["energy_history"]
        assert len(hist) == data["iterations"] + 1
        assert hist[-1] == pytest.approx(data["energy"], rel=1e-12)


CASES = [(n, "lm") for n in EXAMPLES] + [(n, "ipopt") for n in SMALL]


@pytest.mark.parametrize("name, solver", CASES, ids=[f"{n}-{s}" for n, s in CASES])
def test_solve_each_example(capsys, tmp_path, games, name, solver):
    out = tmp_path / "result.json"
    rc, stdout, err = run(capsys, "solve", example_path(name), "--solver", solver, "--out", out)
    assert rc == 0, err
    assert f"{solver}: converged" in stdout
    assert "Nash certificate: passes" in stdout
    assert f"wrote {out}" in stdout
    check_result(json.loads(out.read_text()), games[name], solver)


def test_lm_and_ipopt_agree_on_crossing(capsys, tmp_path):
    E = {}
    for solver in ("lm", "ipopt"):
        out = tmp_path / f"{solver}.json"
        assert (
            run(capsys, "solve", example_path("crossing2"), "--solver", solver, "--out", out)[0]
            == 0
        )
        E[solver] = json.loads(out.read_text())
    np.testing.assert_allclose(E["lm"]["energy"], E["ipopt"]["energy"], rtol=1e-6)
    for a in E["lm"]["agents"]:
        np.testing.assert_allclose(E["lm"]["states"][a], E["ipopt"]["states"][a], atol=1e-3)


def test_solve_set_steps_plot(capsys, tmp_path, games):
    out, fig = tmp_path / "r.json", tmp_path / "figs" / "traj.png"
    rc, stdout, err = run(
        capsys,
        "solve",
        example_path("crossing2"),
        "--steps",
        2,
        "--set",
        "w.a0-a1.collision=55",
        "--set",
        "goal.a0=2.5,0.5",
        "--set",
        "x0.a1.v=1.5",
        "--out",
        out,
        "--plot",
        fig,
        "--no-certificate",
    )
    assert rc == 0, err
    data = json.loads(out.read_text())
    assert data["iterations"] == 2 and data["status"] == "max_iter"
    assert data["params"]["w.a0-a1.collision"] == [55.0]
    assert data["params"]["goal.a0"] == [2.5, 0.5]
    assert data["states"]["a1"][0][2] == 1.5
    assert data["certificate"] is None
    assert fig.read_bytes()[:8] == PNG and fig.stat().st_size > 10_000


def test_solve_file_options_are_used(capsys, tmp_path):
    """solver.lm.steps of the file is the iteration limit; --steps overrides it."""
    d = yaml.safe_load(example_path("crossing2").read_text())
    d["solver"]["lm"] = {"steps": 3, "gtol": 0.0, "ftol": 0.0}
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(d))
    for extra, n in (((), 3), (("--steps", 5), 5)):
        out = tmp_path / "r.json"
        assert run(capsys, "solve", path, "--out", out, "--no-certificate", *extra)[0] == 0
        assert json.loads(out.read_text())["iterations"] == n


@pytest.mark.parametrize("solver", ["lm", "ipopt"])
def test_failed_solve_exit_1_after_writing(capsys, tmp_path, solver):
    """A real non-finite solve (a goal weight of 1e200 overflows the energy to inf) writes
    its result file and figure, prints a summary, then exits with status 1."""
    out, fig = tmp_path / "r.json", tmp_path / "r.png"
    args = ["--solver", solver, "--set", "w.a0.goal=1e200", "--out", out, "--plot", fig]
    rc, stdout, err = run(capsys, "solve", example_path("crossing2"), *args)
    assert rc == 1, err
    data = json.loads(out.read_text())  # strict JSON: the non-finite energy is null
    assert data["status"] == "nonfinite" and data["ok"] is False
    assert data["energy"] is None and data["agent_costs"]["a0"] is None
    assert data["agent_costs"]["a1"] is not None  # the other agent's cost is finite
    assert "energy none (non-finite)" in stdout and "Nash certificate: not computed" in stdout
    assert fig.read_bytes()[:8] == PNG
    assert "did not give a usable solution" in err and "Traceback" not in err


def test_inspect_terms_and_breakdown(capsys, tmp_path, games):
    gf = games["robot_pedestrian"]
    out, spy = tmp_path / "r.json", tmp_path / "spy.png"
    assert (
        run(capsys, "solve", example_path("robot_pedestrian"), "--out", out, "--no-certificate")[0]
        == 0
    )
    rc, stdout, err = run(
        capsys, "inspect", example_path("robot_pedestrian"), "--at", out, "--spy-png", spy
    )
    assert rc == 0, err
    for t in gf.game.terms:
        assert t.weight in stdout
    E = json.loads(out.read_text())["energy"]
    assert f"energy E = {E:.6g}" in stdout
    assert "agent costs C_i" in stdout
    assert "structural nonzeros" in stdout
    assert spy.read_bytes()[:8] == PNG
    rc, stdout, _ = run(capsys, "inspect", example_path("highway_merge"), "--no-spy")
    assert rc == 0 and "energy E" not in stdout and "structural nonzeros" in stdout


def test_inspect_result_of_other_game(capsys, tmp_path):
    out = tmp_path / "r.json"
    assert (
        run(
            capsys,
            "solve",
            example_path("crossing2"),
            "--steps",
            1,
            "--out",
            out,
            "--no-certificate",
        )[0]
        == 0
    )
    rc, stdout, err = run(capsys, "inspect", example_path("robot_pedestrian"), "--at", out)
    assert rc == 2
    assert "error: r.json.agents: expected the agents ['robot', 'ped']" in err
    assert "Traceback" not in err + stdout
    bad = tmp_path / "bad.json"
    data = json.loads(out.read_text())
    data["controls"]["a0"] = data["controls"]["a0"][:-1]
    bad.write_text(json.dumps(data))
    rc, _, err = run(capsys, "inspect", example_path("crossing2"), "--at", bad)
    assert rc == 2 and "error: bad.json.controls.a0: expected shape (30, 2), got (29, 2)" in err


def test_demo(capsys, tmp_path):
    rc, stdout, err = run(capsys, "demo", "--out", tmp_path / "demo")
    assert rc == 0, err
    lines = stdout.splitlines()
    table = [
        ln
        for ln in lines
        if ln.split()[:1] in (["crossing2"], ["intersection4"]) and "converged" in ln
    ]
    assert len(table) == 4  # 2 games x 2 solvers
    assert all(re.split(r"\s{2,}", ln)[7] == "yes" for ln in table)  # Nash column
    for name in ("crossing2", "intersection4"):
        for f in (f"{name}_lm.json", f"{name}_ipopt.json"):
            assert json.loads((tmp_path / "demo" / f).read_text())["status"] == "converged"
        for f in (f"{name}.png", f"{name}_energy.png"):
            assert (tmp_path / "demo" / f).read_bytes()[:8] == PNG
    assert any(ln.startswith("results: ") and str(tmp_path / "demo") in ln for ln in lines)
    assert any(ln.startswith("figures: ") for ln in lines)


def test_help_lists_commands(capsys):
    rc, stdout, _ = run(capsys, "--help")
    assert rc == 0
    for cmd in ("solve", "inspect", "demo"):
        assert cmd in stdout
    rc, stdout, _ = run(capsys, "solve", "--help")
    assert rc == 0 and "--set NAME=VALUE" in stdout


# ----------------------------------------------------------------------------- bad input
def _broken(tmp_path, name, edit):
    d = yaml.safe_load(example_path("crossing2").read_text())
    edit(d)
    p = tmp_path / name
    p.write_text(yaml.safe_dump(d))
    return p


BAD = [
    ("radius.yaml", lambda d: d["agents"][1].__setitem__("radius", -1.0), "agents[1].radius"),
    (
        "feature.yaml",
        lambda d: d["agents"][0]["features"][1].__setitem__("type", "speed"),
        "agents[0].features[1].type",
    ),
    ("key.yaml", lambda d: d.__setitem__("horizont", 3), "horizont"),
    ("x0.yaml", lambda d: d["agents"][0].__setitem__("x0", [0, 0]), "agents[0].x0"),
    ("lm.yaml", lambda d: d["solver"]["lm"].__setitem__("damping", -1), "solver.lm.damping"),
]


@pytest.mark.parametrize("name, edit, field", BAD, ids=[b[0] for b in BAD])
@pytest.mark.parametrize("command", ["solve", "inspect"])
def test_bad_file_exit_2(capsys, tmp_path, name, edit, field, command):
    path = _broken(tmp_path, name, edit)
    rc, stdout, err = run(capsys, command, path)
    assert rc == 2
    assert err.startswith(f"error: {field}: ")
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in stdout + err


@pytest.mark.parametrize(
    "text, words",
    [
        ("", "error: bad.yaml: the file is empty"),
        ("horizon: [1,\n", "error: bad.yaml: invalid YAML at line"),
    ],
)
def test_bad_syntax_exit_2(capsys, tmp_path, text, words):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    rc, stdout, err = run(capsys, "solve", path)
    assert rc == 2 and err.startswith(words) and "Traceback" not in stdout + err


def test_bad_options_exit_2(capsys, tmp_path):
    game = example_path("crossing2")
    rc, _, err = run(capsys, "solve", game, "--set", "w.a0.speed=1")
    assert rc == 2 and err.startswith("error: --set w.a0.speed: unknown parameter")
    rc, _, err = run(capsys, "solve", game, "--set", "goal.a0=1")
    assert rc == 2 and err.startswith("error: --set goal.a0: expected 2 comma-separated numbers")
    rc, _, err = run(capsys, "solve", tmp_path / "missing.yaml")
    assert rc == 2 and "missing.yaml: No such file or directory" in err
    rc, _, err = run(capsys, "solve", game, "--solver", "newton")
    assert rc == 2 and "'newton' is not one of" in err
    rc, _, err = run(capsys, "solve", game, "--steps", -1)
    assert rc == 2 and "--steps" in err
    assert "Traceback" not in err


# ----------------------------------------------------------------------------- documentation
DOC = Path(__file__).resolve().parents[1] / "docs" / "gamefiles.md"


def _doc_commands() -> list[str]:
    blocks = re.findall(r"```bash\n(.*?)```", DOC.read_text(), flags=re.S)
    lines = [ln.split("  #")[0].strip() for b in blocks for ln in b.splitlines()]
    return [
        ln for ln in lines if ln.startswith("epo ") and not ln.startswith("epo demo")
    ]  # demo: test_demo


def test_documented_commands_run(capsys, tmp_path, monkeypatch):
    """Every `epo` line of the CLI docs runs as written from a repository-like directory."""
    commands = _doc_commands()
    assert commands, "docs/gamefiles.md shows no epo commands"
    (tmp_path / "scenarios").mkdir()
    (tmp_path / "scenarios" / "examples").symlink_to(example_path("crossing2").parent)
    monkeypatch.chdir(tmp_path)
    for line in commands:
        rc, stdout, err = run(capsys, *shlex.split(line)[1:])
        assert rc == 0, f"{line}\n{err}"
        if line.startswith("epo solve") and "--modes" in line:  # modes with shares summing to 1
            shares = [float(x) for x in re.findall(r"^\s*mode \d+: share ([0-9.]+)", stdout, re.M)]
            assert shares and abs(sum(shares) - 1) <= 0.005 * len(shares), f"{line}\n{stdout}"
        elif line.startswith("epo solve"):  # the printed status, not only the exit code
            m = re.search(r"--solver (\w+)", line)
            solver = m.group(1) if m else "lm"
            assert re.search(rf"^{solver}: converged \(", stdout, re.M), f"{line}\n{stdout}"
            if solver != "ilq":  # open-loop certificate (iLQ reports its feedback residual)
                assert "Nash certificate: passes" in stdout, f"{line}\n{stdout}"
    assert (tmp_path / "results" / "rp_lm.json").exists()


# ----------------------------------------------------------------------------- console script
def _epo() -> Path:
    exe = Path(sys.executable).parent / "epo"
    if not exe.exists():
        pytest.skip("the 'epo' console script is not installed (pip install -e .)")
    return exe


def test_console_script_subprocess(tmp_path):
    exe = _epo()
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    out = tmp_path / "r.json"
    ok = subprocess.run(
        [str(exe), "solve", str(example_path("crossing2")), "--out", str(out)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
        cwd=tmp_path,
    )
    assert ok.returncode == 0, ok.stderr
    assert "lm: converged" in ok.stdout
    assert json.loads(out.read_text())["certificate"]["ok"] is True
    bad = _broken(tmp_path, "neg.yaml", lambda d: d["agents"][1].__setitem__("radius", -0.25))
    fail = subprocess.run(
        [str(exe), "solve", str(bad)], capture_output=True, text=True, env=env, timeout=300
    )
    assert fail.returncode == 2
    assert (
        fail.stderr.strip() == "error: agents[1].radius: expected a number >= 0 (metres), got -0.25"
    )
    assert "Traceback" not in fail.stdout + fail.stderr


@click.command()
def _warning_cmd():
    warnings.warn("an old checkpoint without a checksum", UserWarning, stacklevel=1)


def test_cli_prints_a_warning_as_one_line(monkeypatch, capsys):
    """A toolkit warning (e.g. an unverified old checkpoint) reaches a CLI user as one line,
    not Python's two-line format with a source location; the command still succeeds."""
    import scenarios.cli as cli_mod

    monkeypatch.setitem(cli_mod.COMMANDS, "warn-test", (f"{__name__}:_warning_cmd", "test"))
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        rc = main(["warn-test"])
    err = capsys.readouterr().err
    assert rc == 0
    assert err == "warning: an old checkpoint without a checksum\n"
