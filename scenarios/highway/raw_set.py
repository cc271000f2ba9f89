"""The output folder of a raw set (:func:`generate_raw`): its recipe (:func:`raw_recipe`),
the maps, one work unit per recording written atomically, and the pool of worker
processes that simulates several recordings at a time (folder rules:
:mod:`scenarios.highway`, "Output folder")."""

from __future__ import annotations

import contextlib
import os
import re
from dataclasses import fields
from pathlib import Path as FilePath

import numpy as np

from epo_casadi.errors import SpecError, check_number

from ..files import claim_output, ensure_dir, write_atomic
from .options import HighwayOptions
from .recording import record
from .road import LOCATIONS, write_map

_FILES = ("tracks", "tracksMeta", "recordingMeta")  # written in this order (meta last)


def _record_files(out: str, lid: int, opts: HighwayOptions, seed: int, i: int) -> tuple:
    """Simulate recording ``i`` at location ``lid`` and write its three CSV files atomically;
    ``(i, tracks, rows, crashes)``. One work unit of :func:`generate_raw` (a pool worker's).
    A recording whose files cannot all be written leaves none of them."""
    out = FilePath(out)
    (tracks, meta, rec), crashes = record(
        LOCATIONS[lid], opts, np.random.SeedSequence(int(seed), spawn_key=(i,)), i
    )
    paths = [out / "data" / f"{i:02d}_{n}.csv" for n in _FILES]
    try:
        for df, path in zip((tracks, meta, rec), paths, strict=True):
            write_atomic(path, df.to_csv(index=False, float_format="%.4f"))
    except BaseException:
        for path in paths:
            with contextlib.suppress(OSError):
                path.unlink()
        raise
    return i, len(meta), len(tracks), crashes


def raw_recipe(opts: HighwayOptions, seed: int) -> dict:
    """What ``recipe.json`` of a raw set records (:mod:`scenarios.highway`): the seed and every
    option but ``recordings`` (a rerun with more recordings extends the set)."""
    d = {f.name: getattr(opts, f.name) for f in fields(opts) if f.name != "recordings"}
    return {"seed": int(seed), **{k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}}


_NAME = re.compile(r"(\d+)_(?:tracks|tracksMeta|recordingMeta)\.csv")


def _held(data: FilePath) -> int:
    """1 + the largest recording number with a file in ``data`` (0 when none)."""
    top = -1
    if data.is_dir():
        for f in data.iterdir():
            m = _NAME.fullmatch(f.name)
            if m:
                top = max(top, int(m.group(1)))
    return top + 1


def _pool(workers: int):
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from ..dataset.engine import _single_threaded_children, _worker_init

    with _single_threaded_children():
        return ProcessPoolExecutor(
            max_workers=workers,
            mp_context=mp.get_context("spawn"),
            initializer=_worker_init,
            initargs=(os.getpid(),),
        )


def _run_pool(units, workers: int):
    """Results of ``_record_files(*u)`` for the lazy ``units``, ``workers`` at a time in
    worker processes (a bounded window in flight). Interrupted or failed: the recordings
    in flight are stopped at once (their files are never half-written) and the pool is
    shut down before the exception goes on, so no process or semaphore outlives it."""
    from concurrent.futures import FIRST_COMPLETED, wait

    from ..dataset.engine import stop_pool

    ex = _pool(workers)
    finished = False
    flight: dict = {}  # future -> its unit
    try:
        for u in units:
            flight[ex.submit(_record_files, *u)] = u
            if len(flight) >= 2 * workers:
                break
        while flight:
            done, _ = wait(set(flight), return_when=FIRST_COMPLETED)
            for f in done:
                res = f.result()
                del flight[f]
                yield res
                nxt = next(units, None)
                if nxt is not None:
                    flight[ex.submit(_record_files, *nxt)] = nxt
        finished = True
    finally:
        if not finished:
            stop_pool(ex)
            for out, _, _, _, i in flight.values():  # stopped while writing: no part stays
                _discard_partial(FilePath(out), i)
        ex.shutdown(wait=True, cancel_futures=True)


def _discard_partial(out: FilePath, i: int) -> None:
    """Remove the files of recording ``i`` unless all three are there (and temporaries)."""
    data = out / "data"
    if all((data / f"{i:02d}_{n}.csv").is_file() for n in _FILES):
        return
    for f in [*data.glob(f"{i:02d}_*.csv"), *data.glob(f".{i:02d}_*.tmp")]:
        with contextlib.suppress(OSError):
            f.unlink()


def generate_raw(
    out: str | os.PathLike,
    opts: HighwayOptions,
    seed: int = 0,
    progress: bool = False,
    workers: int = 1,
) -> dict:
    """Write the raw set (:mod:`scenarios.highway`) into ``out``: maps of the used locations and the
    recordings ``0 .. recordings - 1`` (existing complete ones are kept). ``workers`` > 1
    simulates that many recordings at a time in worker processes (the files are the same:
    recording ``i`` depends only on ``seed`` and ``i``; each is written atomically, so an
    interrupted run keeps every finished recording). The folder is locked for the whole
    run and records its recipe (:func:`raw_recipe`; :mod:`scenarios.highway`, "Output folder"):
    a run with another recipe, or a second run at the same time, is refused
    (:class:`~epo_casadi.errors.SpecError`, :class:`scenarios.files.BusyError`). Returns
    counts: ``recordings``, ``written``, ``tracks``, ``rows``, ``crashes``, ``seconds``."""
    import time

    if not isinstance(opts, HighwayOptions):
        raise SpecError("opts", f"expected HighwayOptions, got {type(opts).__name__}")
    check_number("seed", seed, lo=0, integer=True)
    check_number("workers", workers, lo=1, integer=True)
    t0 = time.perf_counter()
    with claim_output(out, "highway-raw", raw_recipe(opts, seed), what="epo generate highway-raw"):
        out = FilePath(out)
        held = _held(out / "data")
        if held > opts.recordings:
            raise SpecError(
                "recordings",
                f"{out} already holds recordings 0 .. {held - 1}; ask for {held} or more to "
                f"resume or extend the set (got {opts.recordings}), or use another folder",
            )
        ensure_dir(out / "data")
        for tmp in [*out.glob("data/.*.tmp"), *out.glob("maps/lanelet2/.*.tmp")]:
            with contextlib.suppress(OSError):  # left by a killed run (we hold the lock)
                tmp.unlink()
        for lid in sorted(set(opts.locations)):
            loc = LOCATIONS[lid]
            write_map(loc, out / "maps" / "lanelet2" / f"{lid}_{loc.name}.osm")

        def complete(i: int) -> bool:
            return all((out / "data" / f"{i:02d}_{n}.csv").is_file() for n in _FILES)

        n_done = sum(1 for i in range(opts.recordings) if complete(i))
        n_todo = opts.recordings - n_done
        units = (
            (str(out), opts.locations[i % len(opts.locations)], opts, int(seed), i)
            for i in range(opts.recordings)
            if not complete(i)
        )
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=opts.recordings, unit="recording", desc=f"highway -> {out}")
            bar.update(n_done)
        stats = dict(recordings=opts.recordings, written=0, tracks=0, rows=0, crashes=0)
        try:
            if workers <= 1 or n_todo <= 1:
                results = (_record_files(*u) for u in units)
            else:
                results = _run_pool(units, min(workers, n_todo))
            try:
                for _, n_tracks, n_rows, crashes in results:
                    stats["written"] += 1
                    stats["tracks"] += n_tracks
                    stats["rows"] += n_rows
                    stats["crashes"] += crashes
                    if bar is not None:
                        bar.update(1)
            finally:
                results.close()  # stops the pool now, also after an interrupt
        finally:
            if bar is not None:
                bar.close()
    stats["seconds"] = time.perf_counter() - t0
    return stats
