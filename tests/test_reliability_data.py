"""Reliability of data and training (issue 15, items 3-6, clear errors, index rule).

One regression test per defect; each comment names the class of defects it closes. The
data are tiny: the toy scenario of ``tests/test_dataset.py``, the synthetic RPI set and
tiny networks of ``tests/test_models.py``, and a 15-game RPI generation for the kill test.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from learning.checkpoint import (
    CHECKSUM_MAGIC,
    CheckpointError,
    UncheckedCheckpointWarning,
    load_checkpoint,
)
from learning.data import SceneDataset
from learning.models import ModelConfig
from learning.train import TrainConfig, load_model, train
from scenarios import dataset as ds
from scenarios.dataset import DatasetError
from tests.helpers import cli, one_error_line, proc_children, process_family, survivors
from tests.test_dataset import ToyScenario
from tests.test_models import TINY, synthetic_dataset

ROOT = Path(__file__).resolve().parents[1]
TINY_SET = [f"--set={k}={v}" for k, v in TINY.items()]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """One-epoch runs of SC and V-LSTM (tiny networks) on the synthetic set, written once."""
    root = tmp_path_factory.mktemp("runs")
    out = {}
    for kind in ("sc", "vlstm"):
        cfg = TrainConfig(
            model=ModelConfig(kind=kind, **TINY), epochs=1, batch_size=4, lr=1e-3, seed=1
        )
        train(synthetic_dataset(), root / kind, cfg, progress=False)
        out[kind] = root / kind
    return out


def copy_run(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


# ------------------------------------------------------------------------ item 3
def test_any_changed_checkpoint_byte_is_refused(runs, tmp_path, capsys):
    """Class closed: a checkpoint changed after it was written (any byte: header, digest,
    payload) loads silently. Every checkpoint carries a sha256 checked on load."""
    run = copy_run(runs["sc"], tmp_path / "sc")
    for name in ("checkpoint.pt", "best.pt"):
        path = run / name
        good = path.read_bytes()
        assert good.startswith(CHECKSUM_MAGIC)
        ref = load_checkpoint(path)["model"]
        positions = [0, len(CHECKSUM_MAGIC) + 3, len(CHECKSUM_MAGIC) + 64]
        positions += [len(good) // 3, len(good) // 2, len(good) - 1]
        for pos in positions:
            bad = bytearray(good)
            bad[pos] ^= 0x01
            path.write_bytes(bytes(bad))
            with pytest.raises(CheckpointError) as e:
                load_checkpoint(path)
            assert e.value.where == str(path), pos
        path.write_bytes(good)
        got = load_checkpoint(path)["model"]
        assert all(torch.equal(got[k], ref[k]) for k in ref)
    # at the command line: one line naming the file
    bad = bytearray((run / "best.pt").read_bytes())
    bad[len(bad) // 2] ^= 0x10
    (run / "best.pt").write_bytes(bytes(bad))
    rc, _, err = cli(capsys, "evaluate", run, "--data", synthetic_dataset(), "--split", "val")
    one_error_line(rc, err, str(run / "best.pt"), "checksum")


def test_checkpoint_without_checksum_loads_with_a_warning(runs, tmp_path):
    """Class closed: checkpoints written before checksums existed. Documented choice: they
    load, unverified, with an UncheckedCheckpointWarning (not silently, not refused)."""
    run = copy_run(runs["sc"], tmp_path / "old")
    ck = load_checkpoint(run / "checkpoint.pt")
    torch.save(ck, run / "checkpoint.pt")  # the format before checksums: a plain torch zip
    with pytest.warns(UncheckedCheckpointWarning, match="without a checksum"):
        old = load_checkpoint(run / "checkpoint.pt")
    assert old["step"] == ck["step"]
    assert all(torch.equal(old["model"][k], v) for k, v in ck["model"].items())
    # a damaged old-format file is still refused (torch cannot read it), naming the file
    raw = bytearray((run / "checkpoint.pt").read_bytes())
    del raw[len(raw) // 2 :]
    (run / "checkpoint.pt").write_bytes(bytes(raw))
    with pytest.warns(UncheckedCheckpointWarning), pytest.raises(CheckpointError) as e:
        load_checkpoint(run / "checkpoint.pt")
    assert e.value.where == str(run / "checkpoint.pt")


# ------------------------------------------------------------------------ item 4
def test_missing_checkpoint_never_overwrites_history(runs, tmp_path, capsys):
    """Class closed: a run directory whose history (best.pt, metrics.csv) exists without
    checkpoint.pt is trained from scratch over it. It is refused, nothing is rewritten."""
    run = copy_run(runs["sc"], tmp_path / "sc")
    (run / "checkpoint.pt").unlink()
    before = {f: (run / f).read_bytes() for f in ("best.pt", "metrics.csv", "config.json")}
    cfg = TrainConfig(model=ModelConfig(kind="sc", **TINY), epochs=2, batch_size=4, lr=1e-3, seed=1)
    with pytest.raises(CheckpointError, match="best.pt and metrics.csv") as e:
        train(synthetic_dataset(), run, cfg, progress=False)
    assert e.value.where == str(run / "checkpoint.pt")
    assert {f: (run / f).read_bytes() for f in before} == before
    assert not (run / "checkpoint.pt").exists()
    (run / "best.pt").unlink()  # metrics.csv alone is history as well
    rc, _, err = cli(
        capsys, "train", "--model", "sc", "--data", synthetic_dataset(), "--out", run,
        "--epochs", "2", "--batch-size", "4", "--seed", "1", "--no-progress", *TINY_SET,
    )  # fmt: skip
    one_error_line(rc, err, "checkpoint.pt", "metrics.csv", "new directory")


def test_checkpoint_of_another_model_is_refused(runs, tmp_path, capsys):
    """Class closed: a best.pt copied from another run (another model type) is scored under
    the run's name. The settings stored in the checkpoint must match the run's config.json,
    when evaluating and when resuming."""
    run = copy_run(runs["sc"], tmp_path / "sc")
    shutil.copy(runs["vlstm"] / "best.pt", run / "best.pt")
    with SceneDataset(synthetic_dataset(), "val") as d:
        game = d.game
    with pytest.raises(CheckpointError, match=r"model\.kind \('vlstm', run: 'sc'\)"):
        load_model(run, game)
    rc, _, err = cli(capsys, "evaluate", run, "--data", synthetic_dataset(), "--split", "val")
    one_error_line(rc, err, str(run / "best.pt"), "another run", "model.kind")
    cfg = TrainConfig(model=ModelConfig(kind="sc", **TINY), epochs=2, batch_size=4, lr=1e-3, seed=1)
    with pytest.raises(CheckpointError, match="another run"):
        train(synthetic_dataset(), run, cfg, progress=False)
    model, got, _ = load_model(runs["vlstm"], game)  # each run's own file still loads
    assert got.model.kind == "vlstm"


# ------------------------------------------------------------------------ item 5
def test_readers_refuse_a_changed_shard_and_hash_once(tmp_path, monkeypatch, capsys):
    """Class closed: a shard changed after generation is read unnoticed by load_split,
    SplitReader (data show, training). Readers check the sha256 on open, once per file
    version (cached per path, size, mtime)."""
    d = tmp_path / "d"
    ds.generate(ToyScenario(), d, seed=4, progress=False)
    calls = []
    real = ds.sha256_file
    monkeypatch.setattr(
        ds.shards, "sha256_file", lambda p, *a: calls.append(Path(p).name) or real(p)
    )
    shards = ds.read_manifest(d)["splits"]["train"]["shards"]
    ds.load_split(d, "train")
    assert sorted(calls) == sorted(shards)  # each shard hashed once
    ds.load_split(d, "train")
    with ds.SplitReader(d, "train") as r:
        r.read([0, len(r) - 1])
    assert len(calls) == len(shards)  # the second and third opens cost no hashing
    name = shards[1]
    raw = bytearray((d / name).read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (d / name).write_bytes(bytes(raw))
    os.utime(d / name, ns=(time.time_ns(), time.time_ns() + 10**9))  # a later mtime
    with pytest.raises(DatasetError, match="sha256 checksum differs") as e:
        ds.load_split(d, "train")
    assert e.value.where == str(d / name)
    with pytest.raises(DatasetError, match=name):
        ds.SplitReader(d, "train").read_all()
    m = ds.read_manifest(d)
    index = m["shards"][shards[0]]["samples"]  # the first sample of the changed shard
    png = tmp_path / "s.png"
    rc, _, err = cli(capsys, "data", "show", d, "--split", "train", "--index", index, "--out", png)
    one_error_line(rc, err, name, "sha256")


MANIFEST_DAMAGE = {
    "shards": lambda m: m.update(shards=list(m["shards"])),
    "splits.train.units": lambda m: m["splits"]["train"].update(units="all"),
    "splits.val.shards": lambda m: m["splits"]["val"].update(shards=["../../etc/passwd"]),
    "counts": lambda m: m.update(counts={"train": "many"}),
    "complete": lambda m: m.update(complete="yes"),
    "schema.x.shape": lambda m: m["schema"]["x"].update(shape=3),
    "units_per_shard": lambda m: m.update(units_per_shard=0),
    "sha256": lambda m: next(iter(m["shards"].values())).update(sha256=None),
    "samples": lambda m: next(iter(m["shards"].values())).update(samples=-1),
}


@pytest.mark.parametrize("field", list(MANIFEST_DAMAGE))
def test_malformed_manifest_fields_give_one_line(field, tmp_path, capsys):
    """Class closed: a malformed manifest field (e.g. ``shards`` a list) ends in a
    traceback. The manifest schema is checked on read; the error names the field."""
    d = tmp_path / "d"
    ds.generate(ToyScenario(units=4, per_shard=2), d, seed=1, progress=False)
    m = json.loads((d / "manifest.json").read_text())
    MANIFEST_DAMAGE[field](m)
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(DatasetError) as e:
        ds.read_manifest(d)
    assert (
        e.value.where.startswith(str(d / "manifest.json")) and field.split(".")[0] in e.value.where
    )
    for args in (["data", "verify", d], ["data", "show", d, "--out", tmp_path / "x.png"]):
        rc, _, err = cli(capsys, *args)
        one_error_line(rc, err, "manifest.json")


# ------------------------------------------------------------------------ item 6
def _kill_when_a_shard_is_done(
    p: subprocess.Popen, out: Path, sig: int, more_than: int
) -> set[int]:
    """Send ``sig`` to ``p`` once its workers run and more than ``more_than`` shards are
    finished; returns the processes it had started (children and grandchildren)."""
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline and p.poll() is None:
            m = out / "manifest.json"
            if m.exists() and len(proc_children(p.pid)) >= 2:
                with open(m) as f:
                    if len(json.load(f)["shards"]) > more_than:
                        break
            time.sleep(0.05)
        assert p.poll() is None, "the generation ended before it could be killed"
        family = process_family(p.pid)
        assert len(family) >= 2
        p.send_signal(sig)
        p.wait(60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    return family


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux)")
def test_killed_generate_leaves_no_processes_and_resumes(tmp_path):
    """Class closed: worker processes (and the pool's helpers) outliving a killed
    ``epo generate``. A real tiny generation with 2 workers is killed with SIGKILL once a
    shard is finished, resumed and killed with SIGTERM once another one is; after each
    kill every descendant process must be gone within a few seconds, SIGTERM must exit
    like Ctrl-C (130, no traceback), and the last rerun keeps every finished shard."""
    out = tmp_path / "rpi"
    args = [sys.executable, "-m", "scenarios.cli", "generate", "rpi", "--out", out,
            "--samples", "450", "--workers", "2", "--no-progress", "--set=games_per_shard=1",
            "--set=history=4", "--set=n_samples=4", "--set=max_subgames=3",
            "--set=compiled=false", "--set=ground_truth=potential"]  # fmt: skip
    args = [str(a) for a in args]
    kept = 0
    for sig in (signal.SIGKILL, signal.SIGTERM):
        with open(tmp_path / "log.txt", "w+") as log:
            p = subprocess.Popen(args, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
            family = _kill_when_a_shard_is_done(p, out, sig, more_than=kept)
            log.seek(0)
            text = log.read()
        alive = survivors(family)
        assert not alive, f"processes outlived the {sig.name} generation: {alive}"
        if sig == signal.SIGTERM:
            assert p.returncode == 130 and "Traceback" not in text, (p.returncode, text)
        now = len(ds.read_manifest(out)["shards"])
        assert now > kept  # the run after the first kill resumed (it did not start over)
        kept = now
    args[args.index("--workers") + 1] = "1"  # resume in-process: same bytes, no spawn cost
    r = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert f"{kept} kept" in r.stdout and ds.verify(out).ok


# ------------------------------------------------------------------------ clear errors
def test_unreachable_scheduler_is_one_line(tmp_path, capsys):
    """Class closed: an unreachable dask scheduler waits 30 s, then an OSError traceback."""
    pytest.importorskip("distributed")
    rc, _, err = cli(
        capsys, "generate", "rpi", "--out", tmp_path / "d", "--samples", "3", "--engine",
        "dask", "--scheduler", "tcp://127.0.0.1:9", "--scheduler-timeout", "0.5",
        "--no-progress",
    )  # fmt: skip
    one_error_line(rc, err, "scheduler", "tcp://127.0.0.1:9", "0.5 s")


def test_out_that_is_a_file_is_one_line(tmp_path, capsys):
    """Class closed: an --out that is an existing file, or lies inside one, reaches mkdir
    and ends in a traceback (generate, pipeline, train)."""
    f = tmp_path / "notes.txt"
    f.write_text("mine")
    for out in (f, f / "sub"):
        rc, _, err = cli(capsys, "generate", "rpi", "--out", out, "--samples", "3")
        one_error_line(rc, err, str(out))
        rc, _, err = cli(capsys, "pipeline", "--out", out, "--samples", "3", "--no-progress")
        one_error_line(rc, err, str(out))
        rc, _, err = cli(capsys, "train", "--data", synthetic_dataset(), "--out", out)
        one_error_line(rc, err, str(out))
    assert f.read_text() == "mine"


def test_diverging_training_names_epoch_and_step(tmp_path, capsys):
    """Class closed: a diverging run (here --lr 1e30) stops with the game layer's message
    about ``on_invalid``. It says the loss diverged, where, suggests a lower learning rate
    and keeps the last good checkpoint."""
    run = tmp_path / "epo"
    rc, _, err = cli(
        capsys, "train", "--model", "epo", "--data", synthetic_dataset(), "--out", run,
        "--lr", "1e30", "--batch-size", "4", "--checkpoint-steps", "1", "--no-progress",
        *TINY_SET,
    )  # fmt: skip
    line = one_error_line(rc, err, "diverged", "epoch 1, step 2", "lower learning rate", "kept")
    assert "on_invalid" not in line
    ck = load_checkpoint(run / "checkpoint.pt")  # written after step 1, intact
    assert ck["step"] == 1 and all(torch.isfinite(v).all() for v in ck["model"].values())


# ------------------------------------------------------------------------ index rule
def test_one_index_rule_everywhere(tmp_path, capsys):
    """Class closed: index options that wrap negatives but refuse too-large values. One
    rule: an index is in [0, n); negatives are refused with the valid range."""
    data = synthetic_dataset()
    with ds.SplitReader(data, "test") as r:
        n = len(r)
        for bad in (-1, n):
            with pytest.raises(ds.SpecError, match=rf"expected an index in \[0, {n}\)"):
                r[bad]
    with SceneDataset(data, "test") as d:
        for bad in (-1, n):
            with pytest.raises(ds.SpecError, match=rf"\[0, {n}\)"):
                d.batch([0, bad])
        assert d.batch([n - 1])["index"].tolist() == [n - 1]
    for bad in ("-1", str(n)):
        rc, _, err = cli(capsys, "data", "show", data, "--index", bad, "--out", tmp_path / "a.png")
        one_error_line(rc, err, "index", f"[0, {n})", f"got {bad}")
        rc, _, err = cli(
            capsys, "show-predictions", "cv", "--data", data, "--index", bad,
            "--out", tmp_path / "b.png",
        )  # fmt: skip
        one_error_line(rc, err, "index", f"[0, {n})", f"got {bad}")
    assert not (tmp_path / "a.png").exists() and not (tmp_path / "b.png").exists()
