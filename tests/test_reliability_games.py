"""Reliability of game files and the game commands (``solve``, ``inspect``, ``export``,
``compare``, ``demo``): sizes refused before any build, outputs that cannot be written,
hostile game files, and one reader of ``--solver`` values.

Each test reproduces one defect class and names it in its docstring; everything is small
(the shipped crossing, estimates computed without building a game, faults simulated with
``monkeypatch``).
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import casadi as ca
import pytest
import yaml

from epo_casadi import PotentialGame
from epo_casadi import game as game_mod
from epo_casadi.errors import SpecError
from epo_casadi.game import (
    MAX_ENTRIES,
    MAX_JACOBIAN_NNZ,
    PAIR_WEIGHT,
    check_size_estimate,
    estimate_size,
)
from scenarios.commands.compare import crossing_family
from scenarios.gamefile import EXAMPLES, MAX_DEPTH, dump_game, example_path, load_game
from solvers.compare import parse_solver

from .helpers import cli, crossing_spec, one_error_line

CROSSING = example_path("crossing2")


def _game_file(tmp_path: Path, spec, name: str = "game.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(dump_game(spec), sort_keys=False))
    return path


def _files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden ones too) with its bytes."""
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


# --------------------------------------------------------------------------------------
# Sizes: a game that cannot fit is refused from its spec, before CasADi builds anything
# --------------------------------------------------------------------------------------
def test_fifty_agents_at_the_horizon_limit_are_refused_before_the_build(monkeypatch):
    """Class: games inside the horizon limit that exhaust memory (50 agents at K = 10^4:
    10 GB and a bad_alloc traceback after minutes). The estimate refuses it at once."""
    spec = crossing_spec(N=50, K=10_000)
    est = estimate_size(spec)
    assert est.entries > MAX_ENTRIES
    built = []
    monkeypatch.setattr(PotentialGame, "_build", lambda self: built.append(self))
    with pytest.raises(SpecError) as e:
        PotentialGame(spec)
    assert e.value.field == "game" and f"over the limit of {MAX_ENTRIES:,}" in e.value.message
    assert f"{est.entries:,}" in e.value.message and "GB" in e.value.message
    assert built == []  # refused before the layout and the symbolic build


def test_a_game_file_too_large_is_one_line_in_every_command(capsys, tmp_path):
    """Class: the size check sits in PotentialGame construction, so every entry point that
    loads a game file (solve, inspect, export, compare) refuses the same file in one line."""
    path = _game_file(tmp_path, crossing_spec(N=50, K=10_000))
    for args in (
        ("solve", path, "--no-certificate"),
        ("inspect", path, "--no-spy"),
        ("export", path, "--format", "c", "--out", tmp_path / "exp"),
        ("compare", path, "--solver", "lm", "--out", tmp_path / "cmp"),
    ):
        rc, out, err = cli(capsys, *args)
        one_error_line(rc, err, "game:", f"over the limit of {MAX_ENTRIES:,}")
    assert not (tmp_path / "exp").exists()


def test_the_estimate_counts_the_terms_the_build_makes():
    """Class: an estimate that does not follow the game (what it counts is what the build
    makes: rolled-out steps, own steps, pair steps); the Jacobian count is an upper bound."""
    spec = crossing_spec(N=3, K=12)
    game = PotentialGame(spec)
    own = sum(len(t.steps) for t in game.terms if t.kind == "own")
    pair = sum(len(t.steps) for t in game.terms if t.kind == "pair")
    est = game.size_estimate
    assert est == estimate_size(spec)
    assert est.entries == game.N * game.K + own + PAIR_WEIGHT * pair
    assert game.jacobian_sparsity().nnz() <= est.jacobian_nnz <= 10 * game.n_r * game.n_u


def test_export_refuses_a_jacobian_too_large_to_build(capsys, tmp_path, monkeypatch):
    """Class: `epo export` of 2 agents at K = 10^4 (4.5 GB and more: the Jacobian of single
    shooting grows with K^2). Functions without a Jacobian are still exported."""
    big = crossing_spec(N=2, K=10_000)
    assert estimate_size(big).entries <= MAX_ENTRIES  # the game itself fits
    with pytest.raises(SpecError, match=f"over the limit of {MAX_JACOBIAN_NNZ:,}") as e:
        check_size_estimate(big, ["residual", "jacobian"])
    assert e.value.field == "function jacobian"
    check_size_estimate(big, ["rollout", "residual", "energy", "gradient"])
    # through the command, with the limit lowered to just below the shipped crossing
    nnz = estimate_size(load_game(CROSSING).spec).jacobian_nnz
    monkeypatch.setattr(game_mod, "MAX_JACOBIAN_NNZ", nnz - 1)
    for fmt in ("c", "casadi"):
        rc, _, err = cli(capsys, "export", CROSSING, "--format", fmt, "--out", tmp_path / fmt)
        one_error_line(rc, err, "function jacobian", f"over the limit of {nnz - 1:,}")
        assert not (tmp_path / fmt).exists()
    rc, _, err = cli(
        capsys,
        "export",
        CROSSING,
        "--format",
        "c",
        "--out",
        tmp_path / "r",
        "--function",
        "residual",
    )
    assert rc == 0, err
    with pytest.raises(SpecError, match="function hessian"):  # the library path too
        load_game(CROSSING).game.generate_c(str(tmp_path / "h"), ["hessian"])


def test_shipped_examples_and_test_games_are_far_under_the_limits():
    """Class: a limit that refuses ordinary games. Every example, the compare scaling
    study's largest game and the README's 50-agent crossing stay at least 10x under."""
    specs = [load_game(example_path(n)).spec for n in EXAMPLES]
    specs += [crossing_family(8, 200)[0].spec, crossing_spec(N=50, K=20), crossing_spec(N=8, K=200)]
    for spec in specs:
        est = estimate_size(spec)
        assert 10 * est.entries < MAX_ENTRIES, (spec.horizon, len(spec.agents), est)
    for n in EXAMPLES:  # and their default export
        est = estimate_size(load_game(example_path(n)).spec)
        assert 10 * est.jacobian_nnz < MAX_JACOBIAN_NNZ, (n, est)


# --------------------------------------------------------------------------------------
# Outputs: one OutputError line, nothing partial left, refused before any work
# --------------------------------------------------------------------------------------
def test_export_output_paths_that_cannot_be_written(capsys, tmp_path):
    """Class: `epo export` tracebacks through a file, a dangling link, a 300-character name."""
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    dangling = tmp_path / "link"
    dangling.symlink_to(tmp_path / "missing")
    for out, words in (
        (blocker / "sub", ("is a file",)),
        (dangling, ("not a directory",)),
        (tmp_path / ("n" * 300), ("too long",)),
    ):
        rc, _, err = cli(capsys, "export", CROSSING, "--format", "c", "--out", out)
        one_error_line(rc, err, *words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt", "link"]
    assert blocker.read_text() == "x"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_export_and_solve_into_a_read_only_folder(capsys, tmp_path):
    """Class: a read-only folder gives a traceback (export) or is found after the solve."""
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        rc, _, err = cli(capsys, "export", CROSSING, "--format", "c", "--out", ro / "x")
        one_error_line(rc, err, str(ro))
        rc, out, err = cli(capsys, "solve", CROSSING, "--out", ro / "r.json")
        one_error_line(rc, err, "cannot be written")
        assert out == ""  # refused before the solve
    finally:
        ro.chmod(0o700)
    assert list(ro.iterdir()) == []


def test_export_into_a_read_only_mount(capsys, tmp_path, monkeypatch):
    """Class: a read-only mount (EROFS, which root meets too) is one line, nothing left."""
    import tempfile

    def erofs(*a, **kw):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "mkdtemp", erofs)
    rc, _, err = cli(capsys, "export", CROSSING, "--format", "casadi", "--out", tmp_path / "x")
    one_error_line(rc, err, "Read-only file system")
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("fmt", ["c", "casadi"])
def test_full_disk_during_export_leaves_the_older_export_intact(capsys, tmp_path, monkeypatch, fmt):
    """Class: a full disk left a truncated epo_game.c (CasADi writes its files itself and
    reports nothing). A failed write (ENOSPC at the flush) is one line; the previous export
    in the folder is unchanged and no file of the failed one is left."""
    out = tmp_path / "exp"
    rc, _, err = cli(capsys, "export", CROSSING, "--format", fmt, "--out", out)
    assert rc == 0, err
    before = _files(out)
    assert "manifest.json" in before

    def enospc(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", enospc)
    rc, _, err = cli(
        capsys, "export", CROSSING, "--format", fmt, "--out", out, "--set", "w.a0.goal=7"
    )
    one_error_line(rc, err, "no space left on the device")
    assert _files(out) == before


def test_a_truncated_casadi_write_is_detected(capsys, tmp_path, monkeypatch):
    """Class: CasADi's silent truncation on a full disk. Simulated: the generator and the
    serializer write only part of each file; the export refuses and leaves nothing."""
    real_generate, real_save = ca.CodeGenerator.generate, ca.Function.save

    def truncate(path: Path):
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])

    def generate(self, prefix=""):
        out = real_generate(self, prefix)
        for p in Path(prefix).glob("*.[ch]"):
            truncate(p)
        return out

    def save(self, fname, *a):
        real_save(self, fname, *a)
        truncate(Path(fname))

    monkeypatch.setattr(ca.CodeGenerator, "generate", generate)
    monkeypatch.setattr(ca.Function, "save", save)
    for fmt, name in (("c", "epo_game.c"), ("casadi", "rollout.casadi")):
        out = tmp_path / fmt
        rc, _, err = cli(capsys, "export", CROSSING, "--format", fmt, "--out", out)
        one_error_line(rc, err, name, "written incompletely")
        assert not out.exists()


def test_solve_refuses_unwritable_outputs_before_solving(capsys, tmp_path):
    """Class: `solve --out` with a long name (and a path through a file) found only after
    the solve; an unknown image extension for --plot / inspect --plot / --spy-png."""
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    for args, words in (
        (("--out", tmp_path / ("r" * 300 + ".json")), ("longer than the",)),
        (("--out", blocker / "r.json"), (f"{blocker} is a file, not a folder",)),
        (("--plot", tmp_path / "fig.xyz"), ("--plot", "'.xyz'", ".png", ".pdf")),
    ):
        rc, out, err = cli(capsys, "solve", CROSSING, *args)
        one_error_line(rc, err, *words)
        assert out == ""  # nothing solved
    for option in ("--plot", "--spy-png"):
        rc, out, err = cli(capsys, "inspect", CROSSING, "--solve", option, tmp_path / "a.XYZ")
        one_error_line(rc, err, option, "'.XYZ'", ".svg")
        assert out == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt"]


def test_figures_with_an_unknown_extension_are_refused_by_the_library(tmp_path):
    """Class: a matplotlib ValueError traceback for `.xyz` from any figure writer."""
    from scenarios.plotting import check_image_path, image_formats, plot_energy_history

    assert {"png", "pdf", "svg"} <= set(image_formats())
    with pytest.raises(SpecError, match="unknown image format '.xyz'") as e:
        plot_energy_history({"lm": [3.0, 2.0, 1.0]}, tmp_path / "e.xyz")
    assert e.value.field == "path"
    assert list(tmp_path.iterdir()) == []
    assert check_image_path(tmp_path / "plain", "--plot") == tmp_path / "plain"  # PNG
    plot_energy_history({"lm": [3.0, 2.0, 1.0]}, tmp_path / "e.PDF")
    assert (tmp_path / "e.PDF").read_bytes()[:4] == b"%PDF"


def test_demo_and_compare_check_their_folder_first(capsys, tmp_path, monkeypatch):
    """Class: an output folder that cannot be written, found after minutes of solving."""
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    rc, out, err = cli(capsys, "compare", "example:crossing2", "--out", blocker / "c")
    one_error_line(rc, err, str(blocker))
    monkeypatch.setattr(os, "access", lambda path, mode: False)  # a read-only folder
    for args in (("demo", "--out", tmp_path / "d"), ("compare", CROSSING, "--out", tmp_path / "c")):
        rc, out, err = cli(capsys, *args)
        one_error_line(rc, err, "cannot be written")
        assert "energy" not in out  # nothing solved


# --------------------------------------------------------------------------------------
# Hostile game files
# --------------------------------------------------------------------------------------
def _crossing_dict() -> dict:
    return dump_game(load_game(CROSSING))


def test_deeply_nested_json_is_one_line(capsys, tmp_path):
    """Class: a RecursionError traceback in `solve` and `inspect` for a deeply nested JSON
    game file; data nested beyond MAX_DEPTH that the decoder reads is refused by path."""
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    for cmd in ("solve", "inspect"):
        rc, _, err = cli(capsys, cmd, deep)
        one_error_line(rc, err, "deep.json", "nested more than")
    data = _crossing_dict()
    x: list = []
    for _ in range(MAX_DEPTH + 5):
        x = [x]
    data["agents"][0]["features"][0]["weight"] = x
    nested = tmp_path / "nested.json"
    nested.write_text(json.dumps(data))
    rc, _, err = cli(capsys, "inspect", nested)
    one_error_line(rc, err, "agents[0].features[0].weight", f"more than {MAX_DEPTH} levels")


def test_yaml_merge_keys_are_read(tmp_path):
    """Class: a merge key (`<<: *base`) was blamed on a missing constructor. Merged keys
    come first, the mapping's own keys win; duplicates of its own keys are still refused."""
    text = (CROSSING.read_text().split("agents:")[0]) + (
        "agents:\n"
        "  - &first\n"
        "    name: a0\n"
        "    dynamics: unicycle\n"
        "    x0: [0.0, -3.0, 1.0, 1.5708]\n"
        "    goal: [0.0, 3.0]\n"
        "    features: [{type: goal, weight: 3}, velocity]\n"
        "  - <<: *first\n"
        "    name: a1\n"
        "    x0: [-3.0, 0.0, 1.0, 0.0]\n"
    )
    path = tmp_path / "merge.yaml"
    path.write_text(text)
    gf = load_game(path)
    a0, a1 = gf.spec.agents
    assert a1.name == "a1" and a1.features == a0.features and a1.goal == a0.goal
    assert a1.x0 == (-3.0, 0.0, 1.0, 0.0) and a0.x0 != a1.x0
    path.write_text(text + "    name: again\n")
    with pytest.raises(SpecError, match="duplicate key 'name'"):
        load_game(path)
    path.write_text(text.replace("<<: *first", "<<: [1, 2]"))
    with pytest.raises(SpecError, match="merge key '<<' at line .* expects a mapping"):
        load_game(path)


def test_yaml_merge_chains_do_not_multiply(tmp_path):
    """Class: merge keys as a bomb (each level merging the one below four times would be
    4^15 entries if copied); merged mappings are read once, so the file is read at once
    and refused for its unknown key."""
    lines = ["horizon: 10", "dt: 0.1", "l0: &l0 {a: 1, b: 2}"]
    for k in range(1, 16):
        lines.append(f"l{k}: &l{k} {{<<: [*l{k - 1}, *l{k - 1}, *l{k - 1}, *l{k - 1}]}}")
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\nagents: []\n")
    with pytest.raises(SpecError, match="l0: unknown key"):
        load_game(path)


# --------------------------------------------------------------------------------------
# --solver NAME:key=value: the one KEY=VALUE reader
# --------------------------------------------------------------------------------------
def test_solver_values_are_read_like_set(capsys, tmp_path):
    """Class: `--solver ipopt:tol=1e-6` refused while `1.0e-6` worked (YAML 1.1 reads 1e-6
    as text); the lists and mappings compare took before still work."""
    assert parse_solver("ipopt:tol=1e-6").options == {"tol": 1e-6}
    assert parse_solver("ipopt:tol=1.0e-6,max_iter=20").options == {"tol": 1e-6, "max_iter": 20}
    assert parse_solver("sqp:collision=true").options == {"collision": True}
    bounds = parse_solver("sqp:control_bounds={a0: [[-0.1, null], [0.1, null]]}").options
    assert bounds == {"control_bounds": {"a0": [[-0.1, None], [0.1, None]]}}
    assert parse_solver("lm:backend=dense,damping=1e-3").options == {
        "backend": "dense",
        "damping": 1e-3,
    }
    with pytest.raises(SpecError, match="given twice"):
        parse_solver("lm:steps=1,steps=2")
    rc, _, err = cli(
        capsys,
        *("compare", "example:crossing2", "--solver", "lm:steps=3,gtol=1e-6", "--no-check"),
        *("--no-figures", "--out", tmp_path),
    )
    assert rc == 0, err
    assert "lm:steps=3,gtol=1e-6" in (tmp_path / "compare.csv").read_text()
