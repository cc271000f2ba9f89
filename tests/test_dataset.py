"""Storage layer: sharded HDF5 + manifest, resume, determinism, verification, loading.

These tests use :class:`ToyScenario`, a TEST-ONLY stand-in sample generator (no game
solve): each work unit draws a few samples from its own seed, so the storage semantics
are checked in milliseconds. The real RPI generator is tested in ``tests/test_rpi.py``.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from scenarios import dataset as ds
from scenarios.dataset import DatasetError, FieldSpec, Scenario


class ToyScenario(Scenario):
    """TEST-ONLY stand-in: unit i yields 1..4 samples of random numbers from its seed."""

    name = "toy"

    def __init__(self, units: int = 10, per_shard: int = 2, tag: float = 0.0):
        self.units, self.per_shard, self.tag = units, per_shard, tag

    def recipe_dict(self):
        return {"units": self.units, "per_shard": self.per_shard, "tag": self.tag}

    @property
    def n_units(self):
        return self.units

    @property
    def units_per_shard(self):
        return self.per_shard

    def schema(self):
        return {
            "x": FieldSpec((3, 2), "float32", "numbers"),
            "main_game": FieldSpec((), "int64"),
            "k": FieldSpec((), "int16"),
        }

    def run_unit(self, index, seed):
        rng = np.random.default_rng(seed)
        n = int(rng.integers(1, 5))
        return {
            "x": rng.normal(size=(n, 3, 2)) + self.tag,
            "main_game": np.full(n, index),
            "k": np.arange(n),
        }


def digests(d):
    m = json.loads((d / "manifest.json").read_text())
    return {n: v["sha256"] for n, v in m["shards"].items()}


def test_generate_verify_load(tmp_path):
    sc = ToyScenario()
    rep = ds.generate(sc, tmp_path / "a", seed=3, progress=False)
    assert rep.units_run == 10 and not rep.shards_kept
    v = ds.verify(tmp_path / "a")
    assert v.ok, v.problems
    assert v.counts == rep.counts and sum(v.counts.values()) == rep.samples_written
    m = ds.read_manifest(tmp_path / "a")
    assert m["complete"] and m["format_version"] == ds.FORMAT_VERSION
    assert {len(m["splits"][s]["units"]) for s in ("val", "test")} == {1} and len(
        m["splits"]["train"]["units"]
    ) == 8
    for split in ds.SPLITS:
        a = ds.load_split(tmp_path / "a", split)
        n = rep.counts[split]
        assert a["x"].shape == (n, 3, 2) and a["x"].dtype == np.float32
        assert a["main_game"].shape == (n,) and a["main_game"].dtype == np.int64
        # every unit of the split, in unit order, each exactly once (k restarts at 0)
        units = m["splits"][split]["units"]
        starts = a["main_game"][a["k"] == 0]
        assert starts.tolist() == units
        with ds.SplitReader(tmp_path / "a", split) as r:
            assert len(r) == n
            assert np.array_equal(r[n - 1]["x"], a["x"][n - 1])
            idx = np.array([n - 1, 0, n - 1, min(1, n - 1)])
            b = r.read(idx)
            assert np.array_equal(b["x"], a["x"][idx]) and np.array_equal(
                b["main_game"], a["main_game"][idx]
            )
            assert np.array_equal(r.read(slice(None))["k"], a["k"])
    # one unit's samples equal a direct call with its seed (independent of the engine)
    direct = sc.run_unit(5, ds.unit_seed(3, 5))
    split = next(s for s in ds.SPLITS if 5 in m["splits"][s]["units"])
    a = ds.load_split(tmp_path / "a", split)
    assert np.array_equal(a["x"][a["main_game"] == 5], direct["x"].astype(np.float32))


def test_same_seed_identical_files_any_worker_count(tmp_path):
    ds.generate(ToyScenario(), tmp_path / "a", seed=7, workers=1, progress=False)
    ds.generate(
        ToyScenario(), tmp_path / "b", seed=7, workers=2, progress=False
    )  # spawn process pool
    ds.generate(ToyScenario(), tmp_path / "c", seed=8, progress=False)
    assert digests(tmp_path / "a") == digests(tmp_path / "b")
    assert (tmp_path / "a/manifest.json").read_bytes() == (
        tmp_path / "b/manifest.json"
    ).read_bytes()
    for name in digests(tmp_path / "a"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert digests(tmp_path / "a") != digests(tmp_path / "c")


def test_splits_are_disjoint_by_unit(tmp_path):
    ds.generate(ToyScenario(units=30, per_shard=4), tmp_path, seed=1, progress=False)
    m = ds.read_manifest(tmp_path)
    sets = {s: set(m["splits"][s]["units"]) for s in ds.SPLITS}
    assert (len(sets["train"]), len(sets["val"]), len(sets["test"])) == (24, 3, 3)
    assert (
        not sets["train"] & sets["test"]
        and not sets["train"] & sets["val"]
        and not sets["val"] & sets["test"]
    )
    assert set().union(*sets.values()) == set(range(30))
    for s in ds.SPLITS:  # the samples on disk respect the assignment
        assert (
            set(np.unique(ds.load_split(tmp_path, s, ["main_game"])["main_game"]).tolist())
            == sets[s]
        )


class Killed(RuntimeError):
    pass


@pytest.mark.parametrize("workers", [1, 2])
def test_resume_after_kill_loses_and_duplicates_nothing(tmp_path, workers):
    ref = tmp_path / "ref"
    ds.generate(ToyScenario(), ref, seed=5, progress=False)
    d = tmp_path / "run"
    seen = []

    def kill(name):
        seen.append(name)
        if len(seen) == 1:
            raise Killed(name)

    with pytest.raises(Killed):
        ds.generate(ToyScenario(), d, seed=5, workers=workers, progress=False, on_shard=kill)
    m = ds.read_manifest(d)
    assert list(m["shards"]) == seen and not m["complete"]
    assert not ds.verify(d).ok and "unfinished" in ds.verify(d).summary()
    (d / ".train-00003.h5.tmp").write_bytes(b"half a shard")  # debris of the kill
    with pytest.raises(DatasetError, match="unfinished"):
        ds.load_split(d, "train")
    rep = ds.generate(ToyScenario(), d, seed=5, workers=workers, progress=False)
    assert rep.shards_kept == seen and seen[0] not in rep.shards_written
    assert not list(d.glob(".*.tmp"))
    assert ds.verify(d).ok
    assert digests(d) == digests(ref)
    for s in ds.SPLITS:
        a, b = ds.load_split(d, s), ds.load_split(ref, s)
        assert all(np.array_equal(a[k], b[k]) for k in a)
        pairs = list(zip(a["main_game"].tolist(), a["k"].tolist(), strict=True))
        assert len(pairs) == len(set(pairs))  # no duplicate sample
    # a finished dataset is left as it is
    again = ds.generate(ToyScenario(), d, seed=5, progress=False)
    assert again.units_run == 0 and not again.shards_written


def test_shard_renamed_but_not_in_manifest_is_rewritten(tmp_path):
    """Killed between the shard's rename and the manifest update: the shard is redone."""
    d = tmp_path / "d"
    ds.generate(ToyScenario(), d, seed=2, progress=False)
    m = ds.read_manifest(d)
    name = next(iter(m["shards"]))
    del m["shards"][name]
    m["complete"] = False
    (d / "manifest.json").write_text(json.dumps(m))
    (d / name).write_bytes(b"stale")
    rep = ds.generate(ToyScenario(), d, seed=2, progress=False)
    assert rep.shards_written == [name]
    assert ds.verify(d).ok


def test_corrupt_shard_detected_and_regenerated(tmp_path):
    d = tmp_path / "d"
    ds.generate(ToyScenario(), d, seed=4, progress=False)
    name = "train-00001.h5"
    raw = bytearray((d / name).read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (d / name).write_bytes(bytes(raw))
    rep = ds.verify(d)
    assert not rep.ok and rep.problems == [
        f"{name}: sha256 checksum mismatch (file changed or corrupt)"
    ]
    (d / "val-00000.h5").unlink()
    assert any("val-00000.h5: file missing" == p for p in ds.verify(d).problems)
    again = ds.generate(ToyScenario(), d, seed=4, progress=False)  # resume repairs both
    assert sorted(again.shards_written) == sorted([name, "val-00000.h5"])
    assert ds.verify(d).ok


def test_count_mismatch_detected(tmp_path):
    ds.generate(ToyScenario(), tmp_path, seed=4, progress=False)
    m = ds.read_manifest(tmp_path)
    m["counts"]["test"] += 1
    (tmp_path / "manifest.json").write_text(json.dumps(m))
    assert any(p.startswith("counts.test:") for p in ds.verify(tmp_path).problems)


def test_errors_name_the_field(tmp_path):
    with pytest.raises(DatasetError, match="no such dataset directory"):
        ds.verify(tmp_path / "missing")
    with pytest.raises(DatasetError, match="manifest.json: missing"):
        ds.load_split(tmp_path, "train")
    ds.generate(ToyScenario(), tmp_path / "d", seed=1, progress=False)
    with pytest.raises(DatasetError, match="different recipe"):
        ds.generate(ToyScenario(tag=1.0), tmp_path / "d", seed=1, progress=False)
    with pytest.raises(DatasetError, match="different seed"):
        ds.generate(ToyScenario(), tmp_path / "d", seed=2, progress=False)
    with pytest.raises(ds.SpecError, match="split"):
        ds.load_split(tmp_path / "d", "training")
    with pytest.raises(ds.SpecError, match=r"index: expected an index in \[0, "):
        ds.SplitReader(tmp_path / "d", "test")[10_000]
    with pytest.raises(ds.SpecError, match="fields"):
        ds.load_split(tmp_path / "d", "test", ["nope"])
    with pytest.raises(ds.SpecError, match="engine"):
        ds.generate(ToyScenario(), tmp_path / "e", engine="spark")
    with pytest.raises(ds.SpecError, match="workers"):
        ds.generate(ToyScenario(), tmp_path / "e", workers=0)
    with pytest.raises(ds.SpecError, match="units"):
        ds.generate(ToyScenario(units=2), tmp_path / "f")
    (tmp_path / "g").mkdir()
    (tmp_path / "g" / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not empty and holds no manifest.json"):
        ds.generate(ToyScenario(), tmp_path / "g")


def test_dask_engine_matches_local(tmp_path):
    distributed = pytest.importorskip("distributed")
    ds.generate(ToyScenario(), tmp_path / "local", seed=9, progress=False)
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        rep = ds.generate(
            ToyScenario(), tmp_path / "dask", seed=9, engine="dask", client=client, progress=False
        )
    assert rep.units_run == 10
    assert digests(tmp_path / "dask") == digests(tmp_path / "local")
    assert ds.verify(tmp_path / "dask").ok


def test_shards_are_chunked_and_compressed(tmp_path):
    import h5py

    ds.generate(ToyScenario(units=6, per_shard=6), tmp_path, seed=0, progress=False)
    with h5py.File(tmp_path / "train-00000.h5", "r") as f:
        assert f["x"].chunks is not None and f["x"].compression == "gzip"
        assert f.attrs["format_version"] == ds.FORMAT_VERSION and f.attrs["split"] == "train"
    assert os.path.getsize(tmp_path / "manifest.json") > 0
