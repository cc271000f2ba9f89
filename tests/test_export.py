"""``epo export``: the serialized CasADi functions load back, the C export compiles, and
both give the interpreted functions' values to 1e-12 (on random controls and parameters)."""

from __future__ import annotations

import json
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest

from scenarios.cli import main
from scenarios.gamefile import example_path, load_game

NAMES = ("rollout", "residual", "jacobian", "energy", "gradient", "agent_costs")


@pytest.fixture(scope="module")
def crossing():
    return load_game(example_path("crossing2"))


def _inputs(game, n=3, seed=0):
    rng = np.random.default_rng(seed)
    p0 = game.default_params()
    return [
        (rng.normal(scale=0.3, size=game.n_u), p0 * (1 + 0.1 * rng.uniform(-1, 1, game.n_p)))
        for _ in range(n)
    ]


def _same(game, loaded: dict, names=NAMES):
    for u, p in _inputs(game):
        for n in names:
            ref = np.asarray(game.function(n)(u, p), dtype=float)
            got = np.asarray(loaded[n](u, p), dtype=float)
            np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12, err_msg=n)


def test_export_casadi_loads_back(capsys, tmp_path, crossing):
    out = tmp_path / "cas"
    rc = main(
        [
            "export",
            str(example_path("crossing2")),
            "--format",
            "casadi",
            "--out",
            str(out),
            "--set",
            "w.a0.goal=5",
        ]
    )
    assert rc == 0, capsys.readouterr().err
    man = json.loads((out / "manifest.json").read_text())
    assert man["format"] == "epo-export/1" and man["export"] == "casadi"
    assert [f["name"] for f in man["functions"]] == list(NAMES)
    game = crossing.game
    p = np.asarray(man["p"])
    np.testing.assert_array_equal(
        p, crossing.game.params.pack({"w.a0.goal": 5.0}, base=crossing.params)
    )
    jac = next(f for f in man["functions"] if f["name"] == "jacobian")
    assert jac["inputs"] == [
        {"name": "u", "shape": [game.n_u, 1]},
        {"name": "p", "shape": [game.n_p, 1]},
    ]
    loaded = {n: ca.Function.load(str(out / f"{n}.casadi")) for n in NAMES}
    _same(game, loaded)


@pytest.mark.skipif(
    not any(shutil.which(c) for c in ("gcc", "cc", "clang")), reason="no C compiler"
)
def test_export_c_compiles_and_matches(capsys, tmp_path, crossing):
    from solvers.codegen import find_compiler

    out = tmp_path / "c"
    rc = main(
        [
            "export",
            str(example_path("crossing2")),
            "--format",
            "c",
            "--out",
            str(out),
            "--function",
            "residual",
            "--function",
            "energy",
            "--function",
            "gradient",
        ]
    )
    stdout = capsys.readouterr().out
    assert rc == 0
    man = json.loads((out / "manifest.json").read_text())
    assert (out / "epo_game.c").exists() and (out / "epo_game.h").exists()
    header = (out / "epo_game.h").read_text()
    for n in ("residual", "energy", "gradient"):
        assert f"int {n}(" in header
    assert man["build"] in stdout and man["build"] in (out / "BUILD.txt").read_text()
    # build with the documented line (the compiler found as the project does elsewhere)
    cmd = man["build"].replace("cc ", find_compiler() + " ", 1)
    subprocess.run(cmd, shell=True, cwd=out, check=True, capture_output=True)
    lib = str(out / "libepo_game.so")
    loaded = {n: ca.external(n, lib) for n in ("residual", "energy", "gradient")}
    _same(crossing.game, loaded, ("residual", "energy", "gradient"))


def test_export_bad_input_exit_2(capsys, tmp_path):
    rc = main(["export", str(example_path("crossing2")), "--format", "xml", "--out", str(tmp_path)])
    assert rc == 2 and "'xml' is not one of" in capsys.readouterr().err
    rc = main(
        [
            "export",
            str(example_path("crossing2")),
            "--format",
            "c",
            "--out",
            str(tmp_path),
            "--set",
            "w.a0.gaol=1",
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "did you mean 'w.a0.goal'" in err and "Traceback" not in err
