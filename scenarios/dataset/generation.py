"""Generating (or resuming) a dataset: the directory, its lock, the shards to keep and the
units to run (:mod:`scenarios.dataset`, "Crash safety and resume")."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from epo_casadi.errors import OutputError, SpecError

from ..files import check_output_dir as _check_output_dir
from ..files import ensure_dir, output_lock
from .engine import _iter_dask, _iter_local
from .manifest import (
    _new_manifest,
    _planned,
    _recount,
    _same_dataset,
    _write_json,
    dataset_digest,
    read_manifest,
)
from .scenario import MANIFEST, DatasetError, Scenario
from .shards import _shard_fits, sha256_file, write_shard


@dataclass
class GenerateReport:
    """What one :func:`generate` call did."""

    directory: str
    counts: dict[str, int]
    shards_written: list[str]
    shards_kept: list[str]
    units_run: int
    samples_written: int
    seconds: float
    unit_seconds: list[float] = field(default_factory=list)

    @property
    def samples_per_second(self) -> float:
        return self.samples_written / self.seconds if self.seconds > 0 else float("nan")


def _lock(directory: Path):
    """The folder's writer lock (:func:`scenarios.files.output_lock`)."""
    return output_lock(directory, "generation")


def check_output_dir(path: str | os.PathLike) -> Path:
    """``path`` as a directory to create or reuse; :class:`DatasetError` if it cannot be one.

    Refuses an existing file at ``path`` and a path whose nearest existing ancestor is a
    file (``--out notes.txt/run``), before anything is written
    (:func:`scenarios.files.check_output_dir`).
    """
    try:
        return _check_output_dir(path)
    except OutputError as e:
        raise DatasetError(e.path, e.reason) from None


def generate(
    scenario: Scenario,
    out: str | os.PathLike,
    seed: int = 0,
    workers: int = 1,
    engine: str = "local",
    client=None,
    address: str | None = None,
    progress: bool = True,
    on_shard: Callable[[str], None] | None = None,
    scheduler_timeout: float = 10.0,
) -> GenerateReport:
    """Generate (or resume) ``scenario``'s dataset in ``out``; see :mod:`scenarios.dataset`.

    ``engine``: ``"local"`` (process pool of ``workers``) or ``"dask"`` (``client``, a
    scheduler ``address``, or a new ``LocalCluster`` of ``workers`` processes).
    ``scheduler_timeout``: seconds to wait for the scheduler at ``address``; an
    unreachable one raises :class:`SpecError` (field ``scheduler``).
    Pool workers exit when this process dies, also by ``kill -9`` (:func:`_worker_init`);
    an interrupt or error stops the units in flight and keeps the finished shards.
    ``on_shard(name)`` runs after each shard is committed (tests use it to simulate a
    kill). Returns a :class:`GenerateReport`.
    """
    _check_arguments(engine, workers, seed, scheduler_timeout)
    t0 = time.perf_counter()
    d = _output_directory(out)
    schema = scenario.schema()
    with _lock(d):
        m, kept = _resume(d, scenario, int(seed))
        run = _Run(d, scenario, m, schema, on_shard)
        bar = it = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(
                total=len(run.units),
                unit="game",
                desc=f"{scenario.name} -> {d}",
                dynamic_ncols=True,
            )
        try:
            if engine == "local":
                it = _iter_local(scenario, run.units, int(seed), workers)
            else:
                it = _iter_dask(
                    scenario,
                    run.units,
                    int(seed),
                    workers,
                    client,
                    address,
                    float(scheduler_timeout),
                )
            t_start = time.perf_counter()
            for index, arrays, dt in it:
                run.add(index, arrays, dt)
                if bar is not None:
                    el = time.perf_counter() - t_start
                    bar.update(1)
                    bar.set_postfix(
                        samples=run.n_samples,
                        rate=f"{run.n_samples / max(el, 1e-9):.1f} samples/s",
                    )
                run.commit_shard_of(index)
        finally:
            if it is not None:
                it.close()  # shuts the pool or the cluster down, also after an error
            if bar is not None:
                bar.close()
        return GenerateReport(
            str(d),
            dict(m["counts"]),
            run.written,
            kept,
            len(run.secs),
            sum(m["shards"][n]["samples"] for n in run.written),
            time.perf_counter() - t0,
            run.secs,
        )


def _check_arguments(engine: str, workers: int, seed: int, timeout: float) -> None:
    """Refuse an unknown engine, a worker count, seed or scheduler timeout out of range."""
    if engine not in ("local", "dask"):
        raise SpecError("engine", f"expected 'local' or 'dask', got {engine!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise SpecError("workers", f"expected an integer >= 1, got {workers!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SpecError("seed", f"expected an integer >= 0, got {seed!r}")
    t = timeout
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0 < t < math.inf:
        raise SpecError("scheduler_timeout", f"expected a finite number > 0, got {t!r}")


def _output_directory(out: str | os.PathLike) -> Path:
    """``out`` as the dataset's directory, created: new, empty or holding a manifest."""
    d = check_output_dir(out)
    if d.is_dir() and not (d / MANIFEST).exists() and any(x.name != ".lock" for x in d.iterdir()):
        raise DatasetError(
            str(d),
            "exists, is not empty and holds no manifest.json; choose a new or empty directory",
        )
    ensure_dir(d)
    return d


def _resume(d: Path, scenario: Scenario, seed: int) -> tuple[dict, list[str]]:
    """The manifest to continue (the folder's own, or a new one) and the shards it keeps.

    A folder's manifest of another dataset is refused; temporary files are removed; a
    listed shard is kept only if it is planned, present, has its checksum and belongs to
    this dataset (:func:`_shard_fits`). The manifest is written back with its counts.
    """
    new = _new_manifest(scenario, seed)
    mpath = d / MANIFEST
    if mpath.exists():
        m = read_manifest(d)
        key = _same_dataset(m, new)
        if key is not None:
            raise DatasetError(
                str(mpath),
                f"holds a dataset with a different {key}; use another --out directory",
            )
    else:
        m = new
    for tmp in d.glob(".*.tmp"):
        tmp.unlink()
    planned = _planned(m)
    kept = []
    for name in list(m["shards"]):
        f = d / name
        if (
            name not in planned
            or not f.is_file()
            or sha256_file(f) != m["shards"][name]["sha256"]
            or not _shard_fits(f, name, m, planned[name])
        ):
            del m["shards"][name]
        else:
            kept.append(name)
    _recount(m, planned)
    _write_json(mpath, m)
    return m, kept


class _Run:
    """The units still to run and the shards they finish: :meth:`add` takes one unit's
    samples, :meth:`commit_shard_of` commits its shard once all of the shard's units are
    in (the shard file, then the manifest)."""

    def __init__(self, d: Path, scenario: Scenario, m: dict, schema: dict, on_shard) -> None:
        self.d, self.scenario, self.m, self.schema, self.on_shard = d, scenario, m, schema, on_shard
        self.planned = planned = _planned(m)
        self.identity = dataset_digest(m)
        todo_shards = [n for n in planned if n not in m["shards"]]
        self.unit_to_shard = {u: n for n in todo_shards for u in planned[n]["units"]}
        self.units = [u for n in todo_shards for u in planned[n]["units"]]
        self.order = {n: j for j, n in enumerate(planned)}
        self.results: dict[int, dict] = {}
        self.written: list[str] = []
        self.secs: list[float] = []
        self.n_samples = 0

    def add(self, index: int, arrays: dict, seconds: float) -> None:
        """The samples of one finished unit and the seconds it took."""
        self.results[index] = arrays
        self.secs.append(seconds)
        self.n_samples += len(next(iter(arrays.values()))) if arrays else 0

    def commit_shard_of(self, index: int) -> None:
        """Commit the shard of unit ``index`` if all of its units are in."""
        name = self.unit_to_shard[index]
        sunits = self.planned[name]["units"]
        if all(u in self.results for u in sunits):
            self._commit(name, sunits)

    def _commit(self, name: str, sunits: list[int]) -> None:
        m, planned = self.m, self.planned
        n, digest = write_shard(
            self.d / name,
            self.scenario.name,
            planned[name]["split"],
            sunits,
            self.schema,
            [self.results.pop(u) for u in sunits],
            dataset=self.identity,
            seed=m["seed"],
        )
        m["shards"][name] = {
            "split": planned[name]["split"],
            "units": sunits,
            "samples": n,
            "sha256": digest,
        }
        m["shards"] = dict(sorted(m["shards"].items(), key=lambda kv: self.order[kv[0]]))
        _recount(m, planned)
        _write_json(self.d / MANIFEST, m)
        self.written.append(name)
        if self.on_shard is not None:
            self.on_shard(name)
