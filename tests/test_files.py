"""The shared input and output kernels: the KEY=VALUE reader, the size check, output folders
(one writer, one recipe) and atomic writes."""

from __future__ import annotations

import json
import math
import multiprocessing as mp

import pytest

from epo_casadi.errors import OutputError, SpecError, check_size
from epo_casadi.settings import parse_settings, parse_value
from scenarios.files import (
    RECIPE,
    BusyError,
    check_output_dir,
    claim_output,
    output_lock,
    recipe_difference,
    usable_cores,
)


# ---- parse_value / parse_settings --------------------------------------------------------
@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("1e-6", 1e-6),  # YAML 1.1 reads this as a string; every --set must read a number
        ("1.0e-6", 1e-6),
        ("-3", -3),
        (" 2 ", 2),
        ("none", None),
        ("None", None),
        ("null", None),
        ("TRUE", True),
        ("false", False),
        ("lm", "lm"),
        ("left-turn", "left-turn"),
        ("[1, 2]", [1, 2]),
        ("[a, b]", ["a", "b"]),
        ("{w: 1e-3}", {"w": 1e-3}),
        ('"quoted none"', "quoted none"),
    ],
)
def test_parse_value_reads_one_way_everywhere(text, value):
    got = parse_value(text)
    assert got == value and type(got) is type(value), (text, got)


def test_parse_value_nan_is_a_float_for_the_option_checks_to_refuse():
    assert math.isnan(parse_value("NaN"))


def test_parse_settings_names_the_option_and_key():
    assert parse_settings(["a=1", "b.c=x", "d=[1,2]"]) == {"a": 1, "b.c": "x", "d": [1, 2]}
    with pytest.raises(SpecError) as e:
        parse_settings(["noequals"], "--set")
    assert e.value.field == "--set" and "KEY=VALUE" in e.value.message
    with pytest.raises(SpecError) as e:
        parse_settings(["a=1", "a=2"])
    assert e.value.field == "--set a" and "twice" in e.value.message
    with pytest.raises(SpecError) as e:
        parse_settings(["x=[1, 2"])
    assert e.value.field == "--set x"
    with pytest.raises(SpecError) as e:
        parse_settings(["=3"])
    assert e.value.field == "--set"
    with pytest.raises(SpecError):
        parse_value("[" * 100_000)  # too long to be a setting: refused before any parsing


def test_solver_options_use_the_same_reader():
    from solvers.compare import parse_solver

    c = parse_solver("ipopt:tol=1e-6,max_iter=50")
    assert c.options == {"tol": 1e-6, "max_iter": 50}


# ---- check_size --------------------------------------------------------------------------
def test_check_size_bounds_and_names_the_limit():
    assert check_size("episodes", 5, 10) == 5
    assert check_size("episodes", 5.0, 10) == 5 and isinstance(check_size("e", 5.0, 10), int)
    with pytest.raises(SpecError) as e:
        check_size("episodes", 10**9, 1_000_000, "memory")
    assert e.value.field == "episodes"
    assert "1,000,000,000" in e.value.message and "1,000,000" in e.value.message
    assert "memory" in e.value.message
    for bad in (0, -1, 1.5, True, "3", math.inf, math.nan, None):
        with pytest.raises(SpecError):
            check_size("n", bad, 10)
    assert check_size("n", 0, 10, lo=0) == 0


# ---- output folders ----------------------------------------------------------------------
def _hold(path, started, release):
    with output_lock(path, "epo test"):
        started.set()
        release.wait(30)


def test_a_second_writer_is_refused_while_the_first_holds_the_folder(tmp_path):
    ctx = mp.get_context("spawn")
    started, release = ctx.Event(), ctx.Event()
    p = ctx.Process(target=_hold, args=(tmp_path / "out", started, release))
    p.start()
    try:
        assert started.wait(60)
        with pytest.raises(BusyError) as e:
            with output_lock(tmp_path / "out", "epo test"):
                pass
        assert "another epo test is writing" in str(e.value)
    finally:
        release.set()
        p.join(30)
    with output_lock(tmp_path / "out"):  # released with its process
        pass


def test_claim_output_records_the_recipe_and_refuses_another(tmp_path):
    d = tmp_path / "out"
    with claim_output(d, "toy", {"seed": 0, "duration": 10.0}) as got:
        assert got == d
        (d / "part-0.csv").write_text("a\n")
    rec = json.loads((d / RECIPE).read_text())
    assert rec == {"kind": "toy", "recipe": {"seed": 0, "duration": 10.0}}
    with claim_output(d, "toy", {"seed": 0, "duration": 10.0}):  # the same recipe resumes
        pass
    with pytest.raises(SpecError) as e:
        with claim_output(d, "toy", {"seed": 1, "duration": 10.0}):
            pass
    assert "field 'seed' (0 there, 1 asked)" in e.value.message
    with pytest.raises(SpecError) as e:
        with claim_output(d, "other", {"seed": 0}):
            pass
    assert "'toy'" in e.value.message
    # a folder with files but no recipe (another job's, or an older layout) is not adopted
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "00_tracks.csv").write_text("x\n")
    with pytest.raises(SpecError) as e:
        with claim_output(foreign, "toy", {"seed": 0}):
            pass
    assert "00_tracks.csv" in e.value.message and not (foreign / RECIPE).exists()


def test_recipe_difference_names_every_field_in_order():
    assert recipe_difference({"a": 1, "b": [1]}, {"b": (1,), "a": 1}) is None
    diff = recipe_difference({"z": 1, "a": 2}, {"z": 3, "a": 2, "new": 0})
    assert diff == "field 'z' (1 there, 3 asked); field 'new' (None there, 0 asked)"


def test_output_folders_through_files_are_refused(tmp_path):
    f = tmp_path / "notes.txt"
    f.write_text("x")
    with pytest.raises(OutputError, match="exists and is not a directory"):
        check_output_dir(f)
    with pytest.raises(OutputError, match="is a file"):
        check_output_dir(f / "run")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    with pytest.raises(OutputError):
        check_output_dir(tmp_path / "dangling")
    with pytest.raises(OutputError):
        with output_lock(f / "run"):
            pass


def test_usable_cores_is_the_affinity_mask():
    """Not the machine's core count: a process pinned to one core may use one."""
    import os
    import subprocess
    import sys

    assert usable_cores() == len(os.sched_getaffinity(0))
    code = (
        "import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); "
        "from scenarios.files import usable_cores; print(usable_cores(), os.cpu_count())"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    pinned, machine = map(int, r.stdout.split())
    assert pinned == 1 and machine >= 1
