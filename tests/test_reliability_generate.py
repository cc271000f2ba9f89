"""Reliability of the data generators (``epo generate rpi``, ``left-turn``, ``highway-raw``).

One regression test per defect class: recipes recorded per output folder (a rerun with
other options never mixes data), one writer per folder, sizes bounded before any work,
``--set`` messages that name the key, ``--workers`` capped at the cores, SIGTERM like
Ctrl-C, and output failures as one line with nothing partial. Everything is tiny: highway
recordings of 2 s at 10 Hz, and RPI / left-turn units replaced by empty ones where only
the engine's bookkeeping is tested.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from epo_casadi.errors import SpecError
from scenarios import highway
from scenarios.commands import dataset_options as gen
from scenarios.files import output_lock
from scenarios.highway import HighwayOptions
from scenarios.left_turn import LeftTurnScenario
from scenarios.rpi import RPIScenario
from tests.helpers import cli, one_error_line, process_family, survivors

ROOT = Path(__file__).resolve().parents[1]
# highway-raw: 2 s recorded at 10 Hz after 4 s of warm-up, on one map
HW = ["--duration", "2", "--no-progress", "--set", "warmup=4", "--set", "frame_rate=10"]
HW += ["--set", "locations=[3]"]
RPI = ["--samples", "3", "--no-progress", "--workers", "1", "--set", "ground_truth=potential"]
RPI += ["--set", "horizon=4", "--set", "history=2", "--set", "compiled=false"]
LT = ["--no-progress", "--workers", "1", "--set", "episodes_per_geometry=1"]
LT += ["--set", "episodes_per_shard=1", "--set", "horizon=4", "--set", "episode_steps=6"]


def _files(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def _recordings(d: Path) -> list[str]:
    return sorted(p.name for p in (d / "data").iterdir())


def _empty_units(monkeypatch, cls):
    """Work units without samples: the engine's plan, locks and manifest stay real."""

    def run_unit(self, index, seed):
        return {k: np.zeros((0, *f.shape), f.dtype) for k, f in self.schema().items()}

    monkeypatch.setattr(cls, "run_unit", run_unit)


# ---- recipes: a rerun with other options is refused, more recordings extend ---------------
def test_highway_raw_records_its_recipe_and_refuses_another(tmp_path, capsys):
    """Class closed: highway-raw recorded no recipe, so reruns with another --seed,
    --duration or --set into one folder exited 0 and mixed recordings."""
    d = tmp_path / "raw"
    rc, out, err = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "1", *HW)
    assert rc == 0, err
    before = _files(d)
    assert _recordings(d) == ["00_recordingMeta.csv", "00_tracks.csv", "00_tracksMeta.csv"]
    for extra, field in (
        (["--seed", "1"], "'seed' (0 there, 1 asked)"),
        (["--duration", "3"], "'duration' (2.0 there, 3.0 asked)"),
        (["--set", "truck_share=0.5"], "'truck_share' (0.15 there, 0.5 asked)"),
    ):
        # (a second --duration wins over the one in HW)
        rc, _, err = cli(
            capsys, "generate", "highway-raw", "--out", d, "--recordings", 2, *HW, *extra
        )
        one_error_line(rc, err, "recipe.json", field)
        assert _files(d) == before  # nothing written, nothing mixed in
    # the same recipe with more recordings extends the set; recording 0 is kept as it was
    rc, out, err = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "2", *HW)
    assert rc == 0 and "2 recordings (1 written" in out, (out, err)
    after = _files(d)
    assert all(after[k] == v for k, v in before.items())
    assert "data/01_tracks.csv" in after
    # fewer recordings than the folder holds: refused (the folder would hold more than asked)
    rc, _, err = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "1", *HW)
    one_error_line(rc, err, "recordings", "holds recordings 0 .. 1", "ask for 2 or more")
    assert _files(d) == after


def test_highway_raw_refuses_a_folder_without_recipe(tmp_path, capsys):
    """A folder of something else (or of an epo that recorded no recipe) is not adopted."""
    d = tmp_path / "old"
    (d / "data").mkdir(parents=True)
    (d / "data" / "00_tracks.csv").write_text("mine")
    rc, _, err = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "1", *HW)
    one_error_line(rc, err, str(d), "records no recipe.json", "'data'")
    assert sorted(p.name for p in d.iterdir()) == [".lock", "data"]
    assert (d / "data" / "00_tracks.csv").read_text() == "mine"


def test_highway_raw_library_records_the_recipe(tmp_path):
    o = HighwayOptions(recordings=1, duration=2.0, warmup=4.0, frame_rate=10.0, locations=(3,))
    highway.generate_raw(tmp_path / "a", o, seed=5)
    with pytest.raises(SpecError, match=r"field 'seed' \(5 there, 6 asked\)"):
        highway.generate_raw(tmp_path / "a", o, seed=6)
    rec = highway.raw_recipe(o, 5)
    assert "recordings" not in rec and rec["seed"] == 5 and rec["locations"] == [3]


# ---- one writer per folder ------------------------------------------------------------------
def test_highway_raw_second_writer_is_refused_for_the_whole_run(tmp_path, capsys, monkeypatch):
    """Class closed: two highway-raw runs into one folder both reported success and the
    second overwrote the first's files. The folder is locked from start to end."""
    d = tmp_path / "raw"
    with output_lock(d, "test"):
        rc, _, err = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "1", *HW)
        one_error_line(rc, err, str(d), "another epo generate highway-raw is writing")
    assert sorted(p.name for p in d.iterdir()) == [".lock"]
    seen = []
    real = highway._record_files

    def record(*u):  # a second run starts while the first simulates its recording
        rc2, _, err2 = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "1", *HW)
        seen.append((rc2, err2))
        return real(*u)

    monkeypatch.setattr(highway.raw_set, "_record_files", record)
    rc, _, err = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "1", *HW)
    assert rc == 0, err
    assert len(seen) == 1
    one_error_line(*seen[0], "another epo generate highway-raw is writing")


@pytest.mark.parametrize(
    ("kind", "args", "cls"),
    [("rpi", RPI, RPIScenario), ("left-turn", LT, LeftTurnScenario)],
    ids=["rpi", "left-turn"],
)
def test_dataset_generators_refuse_another_recipe_and_a_second_writer(
    tmp_path, capsys, monkeypatch, kind, args, cls
):
    """rpi and left-turn go through the dataset engine: the manifest's recipe and the
    folder's lock. A rerun with another seed or option is refused naming it, and a
    second run while the first works is refused; the first one finishes."""
    _empty_units(monkeypatch, cls)
    d = tmp_path / kind
    seen = []
    real = cls.run_unit

    def run_unit(self, index, seed):
        if not seen:
            seen.append(cli(capsys, "generate", kind, "--out", d, *args)[::2])
        return real(self, index, seed)

    monkeypatch.setattr(cls, "run_unit", run_unit)
    rc, out, err = cli(capsys, "generate", kind, "--out", d, *args)
    assert rc == 0, err
    assert len(seen) == 1
    one_error_line(*seen[0], str(d), "another generation is writing")
    before = _files(d)
    rc, _, err = cli(capsys, "generate", kind, "--out", d, *args, "--seed", "1")
    one_error_line(rc, err, "manifest.json", "different seed")
    rc, _, err = cli(capsys, "generate", kind, "--out", d, *args, "--set", "radius=0.3")
    one_error_line(rc, err, "manifest.json", "recipe field 'radius'", "0.3 asked")
    assert _files(d) == before


# ---- sizes bounded before any work ------------------------------------------------------------
@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["rpi", "--samples", "1000000000"], ["--samples", "1,000,000,000", "10,000,000"]),
        (["rpi", "--set", "main_games=1e9"], ["rpi.main_games", "1,000,000"]),
        (["rpi", "--set", "history=100000000"], ["rpi.history", "limit of 1,000"]),
        (["rpi", "--set", "n_samples=1e7"], ["rpi.n_samples", "limit of 10,000"]),
        (
            ["rpi", "--set", "horizon=1000", "--set", "modes=8", "--set", "game_horizon=1000"],
            ["rpi:", "bytes of one shard", "games_per_shard"],
        ),
        (
            ["left-turn", "--episodes-per-geometry", "1000000000"],
            ["--episodes-per-geometry", "100,000"],
        ),
        (["left-turn", "--set", "augment_copies=1000000"], ["left-turn.augment_copies", "100"]),
        (
            ["left-turn", "--set", "episode_steps=10000", "--set", "augment_copies=100"],
            ["left-turn:", "bytes of one shard", "augment_copies"],
        ),
        (["highway-raw", "--recordings", "1000000000"], ["--recordings", "limit of 10,000"]),
        (["highway-raw", "--duration", "1e9"], ["--duration", "3600"]),
        (["highway-raw", "--set", "warmup=1e9"], ["highway.warmup", "600"]),
        (
            ["highway-raw", "--duration", "3000", "--set", "frame_rate=100"],
            ["highway.duration", "300,000", "limit of 100,000", "frames"],
        ),
    ],
)
def test_sizes_are_bounded_before_any_work(tmp_path, capsys, args, words):
    """Class closed: --episodes-per-geometry 1e9 died with a MemoryError traceback,
    --samples / --recordings 1e9 ran for minutes without output."""
    out = tmp_path / "out"
    rc, _, err = cli(capsys, "generate", args[0], "--out", out, "--no-progress", *args[1:])
    one_error_line(rc, err, *words)
    assert "over the limit" in err or "expected" in err
    assert not out.exists()  # refused before the engine made the folder


def test_limits_are_in_the_help(capsys):
    for cmd, text in (
        ("rpi", "10,000,000"),
        ("left-turn", "100,000"),
        ("highway-raw", "10,000"),
    ):
        rc, out, _ = cli(capsys, "generate", cmd, "--help")
        assert rc == 0 and text in " ".join(out.split()), (cmd, out)


# ---- --set: one parser, messages that name the key -----------------------------------------
@pytest.mark.parametrize("cmd", ["rpi", "left-turn", "highway-raw"])
def test_unknown_set_key_names_the_key_and_the_valid_ones(tmp_path, capsys, cmd):
    valid = {"rpi": "main_games", "left-turn": "episodes_per_geometry", "highway-raw": "warmup"}
    rc, _, err = cli(capsys, "generate", cmd, "--out", tmp_path / "o", "--set", "horizn=3")
    one_error_line(rc, err, "horizn", valid[cmd])
    rc, _, err = cli(capsys, "generate", cmd, "--out", tmp_path / "o", "--set", "noequals")
    one_error_line(rc, err, "--set", "KEY=VALUE")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("value", "shown"),
    [("abc", "got 'abc'"), ("5", "got 5"), ("[true]", "got [True]"), ("[7]", "got [7]")],
)
def test_highway_locations_message_names_the_value(tmp_path, capsys, value, shown):
    """Class closed: --set locations=abc was reported as the list ['a', 'b', 'c'], and
    locations=5 as "--set: 'int' object is not iterable"; [true] was read as location 1."""
    rc, _, err = cli(
        capsys, "generate", "highway-raw", "--out", tmp_path / "o", "--set", f"locations={value}"
    )
    one_error_line(rc, err, "highway.locations", "list of location ids", shown)


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["rpi", "--solver", "lm", "--set", "solver=ilq"], ["--set solver", "--solver"]),
        (["rpi", "--samples", "9", "--set", "main_games=4"], ["--set main_games", "--samples"]),
        (
            ["left-turn", "--episodes-per-geometry", "2", "--set", "episodes_per_geometry=3"],
            ["--set episodes_per_geometry", "--episodes-per-geometry"],
        ),
        (["highway-raw", "--set", "recordings=3"], ["--set recordings", "--recordings"]),
        (["highway-raw", "--set", "duration=3"], ["--set duration", "--duration"]),
    ],
)
def test_an_option_and_its_set_field_together_are_refused(tmp_path, capsys, args, words):
    """One of the two would be ignored without a word (the option overwrote --set)."""
    rc, _, err = cli(capsys, "generate", args[0], "--out", tmp_path / "o", *args[1:])
    one_error_line(rc, err, *words)


# ---- --workers capped at the cores --------------------------------------------------------
def test_workers_are_capped_at_the_usable_cores(tmp_path, capsys, monkeypatch):
    """Class closed: --workers 8 on 2 cores ran 8 processes (latencies three times longer)."""
    import scenarios.dataset as ds

    monkeypatch.setattr(gen, "cores", lambda: 1)
    asked = {}

    def fake_raw(out, opts, seed=0, progress=False, workers=1):
        asked["highway"] = workers
        return dict(recordings=1, written=0, tracks=0, rows=0, crashes=0, seconds=0.0)

    def fake_generate(scenario, out, **kw):
        asked[scenario.name] = kw["workers"]
        raise SpecError("stop", "here")

    monkeypatch.setattr(highway, "generate_raw", fake_raw)
    monkeypatch.setattr(ds, "generate", fake_generate)
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # the test suite turns warnings into errors
        rc, _, err = cli(capsys, "generate", "highway-raw", "--out", tmp_path / "h", "--workers", 4)
        assert rc == 0 and asked["highway"] == 1
        lines = err.strip().splitlines()
        assert lines == ["warning: --workers 4 is more than the 1 usable core(s); using 1"], err
        for cmd in ("rpi", "left-turn"):
            rc, _, err = cli(capsys, "generate", cmd, "--out", tmp_path / cmd, "--workers", 3)
            assert "warning: --workers 3 is more than the 1 usable core(s)" in err, err
            assert asked[cmd] == 1
    assert gen.capped_workers(None) == 1 and gen.capped_workers(1) == 1


# ---- output failures: one line, nothing partial ---------------------------------------------
def test_full_disk_in_highway_raw_is_one_line_and_leaves_no_partial_recording(
    tmp_path, capsys, monkeypatch
):
    """Class closed: a full disk while a recording's CSVs were written ended in a
    traceback. The tracks file is written, its meta file hits the full disk: no file of
    that recording stays, nor any temporary."""
    d = tmp_path / "raw"
    rc, _, err = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "1", *HW)
    assert rc == 0, err
    before = _files(d)
    real = os.fsync

    def fsync(fd):
        if "_tracksMeta" in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    rc, _, err = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "2", *HW)
    one_error_line(rc, err, "01_tracksMeta.csv", "no space left on the device")
    assert _files(d) == before  # recording 1: nothing; recording 0 intact
    assert not [p for p in d.rglob("*") if p.name.endswith(".tmp")]
    monkeypatch.setattr(os, "fsync", real)
    rc, out, err = cli(capsys, "generate", "highway-raw", "--out", d, "--recordings", "2", *HW)
    assert rc == 0 and "(1 written" in out, err


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_folder_in_highway_raw_is_one_line(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        for out in (ro, ro / "raw"):
            rc, _, err = cli(capsys, "generate", "highway-raw", "--out", out, *HW)
            one_error_line(rc, err, str(ro))
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o700)


# ---- SIGTERM: like Ctrl-C ------------------------------------------------------------------
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux)")
def test_sigterm_in_highway_raw_exits_130_without_leaks_and_resumes(tmp_path, capsys):
    """Class closed: SIGTERM killed highway-raw (exit 143) and its pool's resource tracker
    warned of leaked semaphores. Sent after the first recording of four (2 workers), it
    stops the run as Ctrl-C does: exit 130, no traceback or warning, no process left, the
    finished recordings kept; the rerun writes only the others."""
    d = tmp_path / "raw"
    args = [sys.executable, "-m", "scenarios.cli", "generate", "highway-raw", "--out", str(d)]
    args += ["--recordings", "4", "--workers", "2", *HW]
    args[args.index("--duration") + 1] = "20"
    p = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    family: set[int] = set()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and p.poll() is None:
            if list(d.glob("data/*_recordingMeta.csv")):
                break
            time.sleep(0.02)
        assert p.poll() is None, "the run ended before it could be stopped"
        family = process_family(p.pid)
        assert len(family) >= 2, family  # the pool's two workers are running
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        for pipe in (p.stdout, p.stderr):  # closed also when the test fails
            if pipe is not None:
                pipe.close()
    alive = survivors(family)
    assert not alive, f"processes outlived the stopped run: {alive}"
    assert p.returncode == 130, (p.returncode, err)
    assert "Traceback" not in err and "leaked" not in err and "semaphore" not in err, err
    names = _recordings(d)
    kept = sorted(n[:2] for n in names if n.endswith("_recordingMeta.csv"))
    assert 1 <= len(kept) < 4
    # the recordings in flight were stopped: none of their files (nor a temporary) stays
    assert names == sorted(f"{i}_{n}.csv" for i in kept for n in highway._FILES), names
    before = _files(d)
    rest = ["generate", "highway-raw", "--out", d, "--recordings", 4, *HW, "--duration", 20]
    rc, out, err = cli(capsys, *rest)  # resumed in this process (one worker: same bytes)
    assert rc == 0 and f"4 recordings ({4 - len(kept)} written" in out, (out, err)
    after = _files(d)
    assert all(after[k] == v for k, v in before.items())
    assert len(_recordings(d)) == 12
