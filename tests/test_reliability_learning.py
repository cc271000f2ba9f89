"""Reliability of datasets and learning: hostile manifests and shards, output folders,
sizes, indices, duplicate runs, full disks and read-only folders.

One regression test per defect. The data are tiny: the toy scenario of
``tests/test_dataset.py`` and the synthetic RPI set and tiny networks of
``tests/test_models.py``; the trainings are one or two epochs of the tiny SC model.
A full disk is simulated by making ``os.fsync`` fail with ``ENOSPC`` for one file; a
read-only folder is ``chmod 0o500`` (those tests are skipped when run as root, who may
write anyway).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from epo_casadi.errors import OutputError, SpecError
from learning.checkpoint import load_checkpoint
from learning.commands import _model_config, _parse_set
from learning.evaluate import evaluate
from learning.layer import GameLayer
from learning.models import SIZE_LIMITS, ModelConfig
from learning.train import TrainConfig, train
from scenarios import dataset as ds
from scenarios.dataset import DatasetError
from scenarios.files import BusyError, output_lock
from tests.helpers import cli, crossing_game, one_error_line
from tests.test_dataset import ToyScenario
from tests.test_models import TINY, synthetic_dataset

TINY_SET = [f"--set={k}={v}" for k, v in TINY.items()]
ROOT_USER = hasattr(os, "geteuid") and os.geteuid() == 0


def manifest(d: Path) -> dict:
    return json.loads((d / "manifest.json").read_text())


def write_manifest(d: Path, m: dict) -> None:
    (d / "manifest.json").write_text(json.dumps(m, indent=1))


def copy_shard(src: Path, dst_dir: Path, name: str, dst_name: str | None = None) -> None:
    """Copy shard ``name`` of dataset ``src`` into ``dst_dir`` (as ``dst_name``) together
    with its checksum and sample count, as a user copying files by hand would."""
    dst_name = dst_name or name
    shutil.copyfile(src / name, dst_dir / dst_name)
    m = manifest(dst_dir)
    m["shards"][dst_name]["sha256"] = ds.sha256_file(dst_dir / dst_name)
    m["shards"][dst_name]["samples"] = manifest(src)["shards"][name]["samples"]
    write_manifest(dst_dir, m)


def toy(tmp_path: Path, name: str = "a", seed: int = 3, tag: float = 0.0) -> Path:
    d = tmp_path / name
    ds.generate(ToyScenario(tag=tag), d, seed=seed, progress=False)
    return d


def synthetic_copy(tmp_path: Path, name: str = "data", **kw) -> Path:
    return Path(shutil.copytree(synthetic_dataset(**kw), tmp_path / name))


def train_args(data, out, *more) -> list:
    return [
        "train", "--model", "sc", "--data", data, "--out", out, "--epochs", "1",
        "--batch-size", "4", "--lr", "1e-3", "--seed", "1", "--no-progress", *TINY_SET, *more,
    ]  # fmt: skip


def sc_config(epochs: int = 1) -> TrainConfig:
    return TrainConfig(
        model=ModelConfig(kind="sc", **TINY), epochs=epochs, batch_size=4, lr=1e-3, seed=1
    )


# ------------------------------------------------------------------ shards and splits
def test_manifest_listing_a_train_shard_as_test_is_refused(tmp_path, capsys):
    """Defect: a manifest edited so that ``test`` lists a training shard passed
    ``epo data verify``, and the test split then read training samples. The manifest
    must agree with the plan of its splits (each shard in exactly its own split)."""
    d = toy(tmp_path)
    m = manifest(d)
    train_shard = m["splits"]["train"]["shards"][0]
    m["splits"]["test"]["shards"] = [train_shard]
    m["counts"]["test"] = m["shards"][train_shard]["samples"]
    write_manifest(d, m)
    rep = ds.verify(d)
    assert not rep.ok
    assert any(
        p.startswith(f"splits.test.shards: shard {train_shard!r} belongs to split 'train'")
        and "not to split 'test'" in p
        for p in rep.problems
    ), rep.problems
    with pytest.raises(DatasetError) as e:
        ds.SplitReader(d, "test")
    assert e.value.where == "manifest.json.splits.test.shards"
    assert train_shard in e.value.message and "'train'" in e.value.message
    with pytest.raises(DatasetError):
        ds.load_split(d, "test")
    rc, _, err = cli(capsys, "data", "verify", d)
    one_error_line(rc, err, train_shard, "'test'", "'train'")
    rc, _, err = cli(capsys, "data", "show", d, "--split", "test", "--out", tmp_path / "s.png")
    one_error_line(rc, err, train_shard, "'test'", "'train'")
    assert not (tmp_path / "s.png").exists()


def test_shard_listed_in_two_splits_is_refused(tmp_path):
    """A shard listed in its own split and in another is named by verify and refused."""
    d = toy(tmp_path)
    m = manifest(d)
    name = m["splits"]["train"]["shards"][0]
    m["splits"]["val"]["shards"].append(name)
    write_manifest(d, m)
    rep = ds.verify(d)
    want = f"splits.val.shards: shard {name!r} belongs to split 'train'"
    assert any(p.startswith(want) for p in rep.problems), rep.problems
    for split in ds.SPLITS:  # the manifest is damaged: every split is refused
        with pytest.raises(DatasetError, match="exactly one split"):
            ds.SplitReader(d, split)


def test_shard_file_moved_into_another_split_is_refused(tmp_path, capsys):
    """Defect: a training shard copied over a test shard (its checksum and count copied into
    the manifest too) was read as test data. The shard records its split and units; the
    reader compares them with the plan and names the shard and both splits."""
    d = toy(tmp_path)
    m = manifest(d)
    src, dst = m["splits"]["train"]["shards"][0], m["splits"]["test"]["shards"][0]
    copy_shard(d, d, src, dst)
    m = manifest(d)
    m["counts"]["test"] = m["shards"][dst]["samples"]
    write_manifest(d, m)
    rep = ds.verify(d)
    assert any(
        p.startswith(f"{dst}: holds samples of split 'train'") and "split 'test'" in p
        for p in rep.problems
    ), rep.problems
    with pytest.raises(DatasetError) as e:
        ds.load_split(d, "test")
    assert e.value.where == str(d / dst)
    assert "split 'train'" in e.value.message and "split 'test'" in e.value.message
    rc, _, err = cli(capsys, "data", "show", d, "--split", "test", "--out", tmp_path / "s.png")
    one_error_line(rc, err, dst, "'train'", "'test'")


def test_shards_without_an_identity_still_load_and_are_plan_checked(tmp_path):
    """Shards written before the dataset identity was recorded (no ``dataset`` and
    ``seed`` attributes) still load and verify; their split and units are still checked."""
    d = toy(tmp_path)
    ref = {s: ds.load_split(d, s) for s in ds.SPLITS}
    m = manifest(d)
    for name in m["shards"]:
        with h5py.File(d / name, "r+") as h:
            assert h.attrs["dataset"] == ds.dataset_digest(m) and h.attrs["seed"] == 3
            del h.attrs["dataset"], h.attrs["seed"]
        m["shards"][name]["sha256"] = ds.sha256_file(d / name)
    write_manifest(d, m)
    assert ds.verify(d).ok, ds.verify(d).problems
    for s in ds.SPLITS:
        got = ds.load_split(d, s)
        assert all(np.array_equal(got[k], ref[s][k]) for k in got)
    src, dst = m["splits"]["train"]["shards"][0], m["splits"]["val"]["shards"][0]
    copy_shard(d, d, src, dst)
    with pytest.raises(DatasetError, match="holds samples of split 'train'"):
        ds.load_split(d, "val")


def test_shard_of_another_dataset_with_its_checksum_is_refused(tmp_path, capsys):
    """Defect: a shard copied in from another dataset together with its checksum gave
    broadcast errors (train, evaluate, data show), or, with equal sample counts, silently
    other samples. Every shard records its dataset's identity, checked on read."""
    a, b = toy(tmp_path, "a", tag=0.0), toy(tmp_path, "b", tag=5.0)  # same plan, other recipe
    name = manifest(a)["splits"]["train"]["shards"][0]
    assert manifest(a)["shards"][name]["samples"] == manifest(b)["shards"][name]["samples"]
    copy_shard(b, a, name)
    rep = ds.verify(a)
    assert [p for p in rep.problems if p.startswith(f"{name}: belongs to another dataset")]
    with pytest.raises(DatasetError) as e:
        ds.load_split(a, "train")
    assert e.value.where == str(a / name) and "another recipe" in e.value.message
    c = toy(tmp_path, "c", seed=4)  # another seed: named as such
    copy_shard(
        c, a, manifest(c)["splits"]["val"]["shards"][0], manifest(a)["splits"]["val"]["shards"][0]
    )
    with pytest.raises(DatasetError, match="seed 4, the manifest's 3"):
        ds.load_split(a, "val")

    # the commands of the issue: train, evaluate and data show, on an RPI-style set
    data = synthetic_copy(tmp_path, "data")
    other = synthetic_dataset(straight=True)  # another seed and other samples
    for split in ("train", "test"):
        copy_shard(other, data, manifest(data)["splits"][split]["shards"][0])
    shard = manifest(data)["splits"]["train"]["shards"][0]
    rc, _, err = cli(capsys, *train_args(data, tmp_path / "run"))
    one_error_line(rc, err, shard, "another dataset")
    test_shard = manifest(data)["splits"]["test"]["shards"][0]
    rc, _, err = cli(capsys, "evaluate", "--model", "cv", "--data", data)
    one_error_line(rc, err, test_shard, "another dataset")
    rc, _, err = cli(capsys, "data", "show", data, "--out", tmp_path / "s.png")
    one_error_line(rc, err, test_shard, "another dataset")


def test_shard_shapes_are_checked_against_the_schema(tmp_path, capsys):
    """A shard (of an older layout, without an identity) whose rows or field shapes differ
    from the manifest is one line naming the shard's field, never a broadcast error."""
    d = toy(tmp_path)
    m = manifest(d)
    name = m["splits"]["train"]["shards"][0]
    n = m["shards"][name]["samples"]
    with h5py.File(d / name, "r+") as h:
        x = h["x"][()]
        del h["x"], h.attrs["dataset"]
        h.create_dataset("x", data=np.concatenate([x, x[:1]]))
    m["shards"][name]["sha256"] = ds.sha256_file(d / name)
    write_manifest(d, m)
    with pytest.raises(DatasetError) as e:
        ds.load_split(d, "train")
    assert e.value.where == str(d / f"{name}.x")
    assert f"shape ({n + 1}, 3, 2) float32, manifest says ({n}, 3, 2) float32" in e.value.message
    assert any(p.startswith(f"{name}.x: shape") for p in ds.verify(d).problems)


def test_resume_regenerates_a_foreign_shard(tmp_path):
    """A resumed generation keeps only shards that belong to it: a foreign shard with a
    matching checksum is written again, and the dataset verifies."""
    a, b = toy(tmp_path, "a"), toy(tmp_path, "b", tag=5.0)
    name = manifest(a)["splits"]["train"]["shards"][0]
    good = (a / name).read_bytes()
    copy_shard(b, a, name)
    rep = ds.generate(ToyScenario(), a, seed=3, progress=False)
    assert rep.shards_written == [name]
    assert (a / name).read_bytes() == good and ds.verify(a).ok


# ------------------------------------------------------------------ output folders
def test_concurrent_train_into_one_out_is_refused(tmp_path, capsys):
    """Defect: two ``epo train`` into one ``--out`` both ran and overwrote each other's
    config.json and checkpoints. The run folder is locked for the whole run."""
    data, run = synthetic_dataset(), tmp_path / "run"
    rc, _, err = cli(capsys, *train_args(data, run))
    assert rc == 0, err
    before = {f.name: f.read_bytes() for f in run.iterdir() if f.is_file()}
    with output_lock(run, "epo train"):  # a training in progress
        rc, _, err = cli(capsys, *train_args(data, run, "--epochs", "2"))
        one_error_line(rc, err, str(run), "another epo train is writing")
        with pytest.raises(BusyError):
            train(data, run, sc_config(2), progress=False)
    assert {f.name: f.read_bytes() for f in run.iterdir() if f.is_file()} == before
    rc, _, err = cli(capsys, *train_args(data, run, "--epochs", "2"))  # lock released: resumes
    assert rc == 0, err


def test_train_and_evaluate_refuse_the_dataset_folder_as_out(tmp_path, capsys):
    """Defect: ``train --out DATA`` wrote checkpoints into the dataset folder. A run or
    results folder is never a folder holding manifest.json."""
    data = synthetic_copy(tmp_path)
    before = sorted(p.name for p in data.iterdir())
    rc, _, err = cli(capsys, *train_args(data, data))
    one_error_line(rc, err, "--out", str(data), "dataset folder")
    with pytest.raises(SpecError, match="dataset folder"):
        train(data, data, sc_config(), progress=False)
    rc, _, err = cli(capsys, "evaluate", "--model", "cv", "--data", data, "--out", data)
    one_error_line(rc, err, "--out", "dataset folder")
    rc, _, err = cli(capsys, "evaluate", "--model", "cv", "--data", data, "--out", data / "r.md")
    one_error_line(rc, err, "--out", "dataset folder")
    assert sorted(p.name for p in data.iterdir()) == before and ds.verify(data).ok


@pytest.fixture(scope="module")
def sc_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("run")
    train(synthetic_dataset(), root / "sc", sc_config(), progress=False)
    return root / "sc"


def test_evaluate_refuses_a_run_given_twice(sc_run, tmp_path, capsys):
    """Defect: ``evaluate RUN RUN`` counted one run twice in its mean ± std."""
    data = synthetic_dataset()
    for twice in (sc_run, sc_run.parent / ".." / sc_run.parent.name / "sc"):
        rc, _, err = cli(capsys, "evaluate", sc_run, twice, "--data", data)
        one_error_line(rc, err, "runs", "given twice", "counts once")
    link = tmp_path / "link"
    link.symlink_to(sc_run)
    with pytest.raises(SpecError, match=f"also as {sc_run}"):
        evaluate([sc_run, link], data)
    assert len(evaluate([sc_run], data).results) == 1


# ------------------------------------------------------------------ sizes and indices
@pytest.mark.parametrize("field", sorted(SIZE_LIMITS))
def test_model_sizes_are_bounded(field):
    """Defect: ``--set hist_width=1000000`` asked for 16 TB. Every size of ModelConfig is
    bounded before any network is built; the limit itself is accepted."""
    limit = SIZE_LIMITS[field]
    with pytest.raises(SpecError) as e:
        ModelConfig(**{field: limit + 1})
    assert e.value.field == f"model.{field}" and f"limit of {limit:,}" in e.value.message
    assert getattr(ModelConfig(**{field: limit}), field) == limit


def test_huge_hist_width_is_one_line(tmp_path, capsys):
    rc, _, err = cli(capsys, "train", "--data", synthetic_dataset(), "--out", tmp_path / "r",
                     "--set", "hist_width=1000000", "--no-progress")  # fmt: skip
    one_error_line(rc, err, "model.hist_width", "1,000,000", "limit of 2,048")
    assert not (tmp_path / "r" / "checkpoint.pt").exists()


def test_huge_index_is_one_line(sc_run, tmp_path, capsys):
    """Defect: ``--index 99999999999999999999999`` ended in an OverflowError traceback."""
    data, huge = synthetic_dataset(), "99999999999999999999999"
    with ds.SplitReader(data, "test") as r:
        n = len(r)
        with pytest.raises(SpecError, match=f"got {huge}"):
            r[int(huge)]
        with pytest.raises(SpecError, match="integer indices"):
            r.read([0, int(huge)])
    for args in (
        ("data", "show", data),
        ("show-predictions", "cv", "--data", data),
        ("show-weights", sc_run, "--data", data),
    ):
        rc, _, err = cli(capsys, *args, "--index", huge, "--out", tmp_path / "x.png")
        one_error_line(rc, err, "--index", huge)
        big = str(2**63 - 1)  # passes the option's type: refused by the readers
        rc, _, err = cli(capsys, *args, "--index", big, "--out", tmp_path / "x.png")
        one_error_line(rc, err, "index", f"[0, {n})", big)
    assert not (tmp_path / "x.png").exists()


def test_set_none_means_none(tmp_path):
    """``--set`` is read by the one settings parser: ``none`` is None (the model's
    optional collision margin), ``no`` stays the word (layer_compiled)."""
    over = _parse_set(("collision_margin=none", "layer_compiled=no", "hist_width=8"))
    assert over == {"collision_margin": None, "layer_compiled": "no", "hist_width": 8}
    cfg = _model_config("epo", None, synthetic_dataset(), over)
    assert cfg.collision_margin is None and cfg.layer_compiled == "no" and cfg.modes == 2


def test_game_layer_refuses_a_meta_tensor():
    """Defect: a ``meta`` tensor reached numpy and failed deep inside the layer."""
    g = crossing_game(K=5)
    layer = GameLayer(g)
    with pytest.raises(SpecError) as e:
        layer(torch.zeros(2, g.n_p, device="meta"))
    assert e.value.field == "p" and "meta" in e.value.message
    with pytest.raises(SpecError) as e:
        layer(layer.default_params()[None], torch.zeros(1, g.n_u, device="meta"))
    assert e.value.field == "u_init"


# ------------------------------------------------------------------ full disk, read-only
def enospc_for(monkeypatch, prefix: str) -> list:
    """Make ``os.fsync`` fail with ENOSPC for temporary files named ``.PREFIX...``."""
    real, hits = os.fsync, []

    def fsync(fd):
        name = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
        if name.startswith(f".{prefix}"):
            hits.append(name)
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    return hits


@pytest.mark.parametrize("name", ["checkpoint.pt", "metrics.csv"])
def test_full_disk_in_train_keeps_the_previous_files(name, tmp_path, monkeypatch, capsys):
    """Defect: a full disk in ``train`` ended in an OSError traceback. Every file of a run is
    written atomically: one OutputError line, the previous file intact, no temporary left;
    the run then resumes."""
    data, run = synthetic_dataset(), tmp_path / "run"
    train(data, run, sc_config(1), progress=False)
    before = (run / name).read_bytes()
    with monkeypatch.context() as mp:
        hits = enospc_for(mp, name)
        rc, _, err = cli(capsys, *train_args(data, run, "--epochs", "2"))
    assert hits
    one_error_line(rc, err, str(run / name), "cannot write", "no space left")
    assert (run / name).read_bytes() == before
    assert not [p.name for p in run.iterdir() if p.name.endswith(".tmp")]
    if name == "checkpoint.pt":
        assert load_checkpoint(run / name)["epoch"] == 1
    res = train(data, run, sc_config(2), progress=False)
    assert res.epochs == 2 and load_checkpoint(run / "checkpoint.pt")["epoch"] == 2


def test_full_disk_in_generate_is_one_error_and_resumes(tmp_path, monkeypatch):
    """Defect: a full disk while a shard was written crashed inside HDF5 (a segfault in
    ``generate exid``). HDF5 builds the shard in memory; its bytes are written atomically,
    so the full disk is one OutputError naming the shard and leaves no partial file."""
    d = tmp_path / "a"
    with monkeypatch.context() as mp:
        hits = enospc_for(mp, "train-00001.h5")
        with pytest.raises(OutputError) as e:
            ds.generate(ToyScenario(), d, seed=3, progress=False)
    assert hits and e.value.path == str(d / "train-00001.h5")
    assert "no space left" in str(e.value)
    assert not (d / "train-00001.h5").exists() and not list(d.glob(".*.tmp"))
    assert list(manifest(d)["shards"]) == ["train-00000.h5"]
    rep = ds.generate(ToyScenario(), d, seed=3, progress=False)
    assert rep.shards_kept == ["train-00000.h5"] and ds.verify(d).ok
    ref = ds.generate(ToyScenario(), tmp_path / "b", seed=3, progress=False)
    assert ref.counts == rep.counts
    assert {n: v["sha256"] for n, v in manifest(d)["shards"].items()} == {
        n: v["sha256"] for n, v in manifest(tmp_path / "b")["shards"].items()
    }


def test_full_disk_for_the_manifest_is_one_error(tmp_path, monkeypatch):
    d = tmp_path / "a"
    with monkeypatch.context() as mp:
        enospc_for(mp, "manifest.json")
        with pytest.raises(OutputError, match="manifest.json: cannot write: no space left"):
            ds.generate(ToyScenario(), d, seed=3, progress=False)
    assert not list(d.glob(".*.tmp"))


@pytest.fixture
def read_only(tmp_path):
    if ROOT_USER:
        pytest.skip("root writes into read-only folders")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    yield ro
    ro.chmod(0o700)


def test_read_only_folders_are_one_line(read_only, sc_run, tmp_path, capsys):
    """Defect: read-only folders for ``train``, ``evaluate --out`` and ``data show --out``
    ended in PermissionError tracebacks. Each is one ``cannot write`` line; nothing is
    left behind."""
    data = synthetic_dataset()
    rc, _, err = cli(capsys, *train_args(data, read_only / "run"))
    one_error_line(rc, err, str(read_only / "run"), "cannot write")
    run = Path(shutil.copytree(sc_run, tmp_path / "sc"))
    run.chmod(0o500)
    try:
        rc, _, err = cli(capsys, *train_args(data, run, "--epochs", "2"))
        one_error_line(rc, err, str(run), "cannot write")
    finally:
        run.chmod(0o700)
    assert load_checkpoint(run / "checkpoint.pt")["epoch"] == 1
    for out in (read_only, read_only / "sub"):
        rc, _, err = cli(capsys, "evaluate", "--model", "cv", "--data", data, "--out", out)
        one_error_line(rc, err, str(out), "cannot write")
    rc, _, err = cli(capsys, "data", "show", data, "--out", read_only / "s.png")
    one_error_line(rc, err, str(read_only / "s.png"), "cannot write")
    rc, _, err = cli(capsys, "data", "show", data, "--out", read_only / "sub" / "s.png")
    one_error_line(rc, err, "cannot write")
    assert list(read_only.iterdir()) == []


def test_data_show_refuses_an_unknown_image_format(tmp_path, capsys):
    rc, _, err = cli(capsys, "data", "show", synthetic_dataset(), "--out", tmp_path / "s.xyz")
    one_error_line(rc, err, "--out", "'.xyz'", ".png")
    rc, _, err = cli(capsys, "data", "show", synthetic_dataset(), "--out", tmp_path / "s.svg")
    assert rc == 0 and (tmp_path / "s.svg").read_text().lstrip().startswith("<?xml"), err


# ------------------------------------------------------------------ SIGTERM
def test_sigterm_stops_train_like_ctrl_c_and_frees_the_folder(tmp_path, capsys):
    """SIGTERM stops ``epo train`` as Ctrl-C does (130, no traceback); the last checkpoint
    is intact and the run folder's lock goes with the process, so the run resumes."""
    data, run = synthetic_dataset(), tmp_path / "run"
    args = [sys.executable, "-m", "scenarios.cli", *map(str, train_args(data, run))]
    args[args.index("--epochs") + 1] = "1000"
    args += ["--checkpoint-steps", "1"]
    root = Path(__file__).resolve().parents[1]
    with open(tmp_path / "log.txt", "w+") as log:
        p = subprocess.Popen(args, cwd=root, stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 240
            while time.monotonic() < deadline and p.poll() is None:
                if (run / "checkpoint.pt").exists():
                    break
                time.sleep(0.05)
            assert p.poll() is None, "the run ended before it could be stopped"
            p.send_signal(signal.SIGTERM)
            p.wait(60)
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
        log.seek(0)
        text = log.read()
    assert p.returncode == 130 and "Traceback" not in text, (p.returncode, text)
    step = load_checkpoint(run / "checkpoint.pt")["step"]
    assert step >= 1
    rc, _, err = cli(capsys, *train_args(data, run, "--checkpoint-steps", "1"))
    assert rc == 0, err  # the lock is free: the run resumes (1 epoch is 2 steps)
    assert load_checkpoint(run / "checkpoint.pt")["epoch"] >= 1
