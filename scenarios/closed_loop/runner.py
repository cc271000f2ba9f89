"""Many episodes of one configuration (:func:`run_episodes`): on the engines of data
generation, written as they finish, resumed after an interruption.

The run directory: ``config.json`` (the configuration, the seed, the format version),
``episodes/episode-NNNNN.json`` per finished episode (``.npz``: the logs kept), the
summary files of :mod:`scenarios.closed_loop.report`. A directory is written by one run
at a time (:func:`scenarios.files.output_lock`); every file is written atomically.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size, short_repr
from scenarios.dataset import FieldSpec, Scenario
from scenarios.files import check_output_dir, output_lock, write_atomic

from .log import EpisodeLog, EpisodeResult
from .report import summarize, write_summary

__all__ = [
    "EpisodeJob",
    "RunReport",
    "episode_unit",
    "load_log",
    "load_results",
    "run_episodes",
    "MAX_EPISODES",
    "MAX_WORKERS",
]

#: most episodes of one run (every result is held in memory for the summary)
MAX_EPISODES = 100_000
#: most worker processes of one run
MAX_WORKERS = 1024

CONFIG = "config.json"
FORMAT_VERSION = 1


class EpisodeJob(Scenario):
    """Episodes as work units of :mod:`scenarios.dataset`'s engines: unit ``i`` is the
    episode of seed ``seed + i``, built from ``config`` in the worker."""

    name = "closed-loop"

    def __init__(self, config, seed: int, keep_logs: Sequence[int] = ()):
        self.config = config
        self.seed = int(seed)
        self.keep_logs = tuple(int(i) for i in keep_logs)

    def schema(self) -> dict[str, FieldSpec]:
        return {"episode": FieldSpec((), "O", "the episode's result")}

    def run_unit(self, index: int, seed) -> dict[str, np.ndarray]:
        out = np.empty(1, dtype=object)
        out[0] = episode_unit(self.config, index, self.seed + index, index in self.keep_logs)
        return {"episode": out}


def episode_unit(config, index: int, seed: int, keep_log: bool) -> EpisodeResult:
    """Build the stack from ``config`` (and its safety filter, ``config.build_filter()``
    where the configuration has one) and run episode ``index`` with ``seed``; an exception
    becomes the outcome ``"error"`` with its message (the other episodes go on).

    The episode is run by ``scenarios.closed_loop.loop.run_episode``, looked up when
    called, so a replacement set there (a test's stand-in) is the one that runs."""
    from . import loop

    try:
        world, estimator, planner, tracker = config.build()
        build_filter = getattr(config, "build_filter", None)
        safety = build_filter() if callable(build_filter) else None
        return loop.run_episode(
            world, estimator, planner, tracker, seed, index=index, keep_log=keep_log, safety=safety
        )
    except Exception as e:  # noqa: BLE001 - one broken episode must not lose the run
        return EpisodeResult(
            index, seed, "error", {}, [], [], message=f"{type(e).__name__}: {e}".splitlines()[0]
        )


@dataclass
class RunReport:
    """What :func:`run_episodes` did: results in episode order, the summary row, files."""

    directory: str | None
    results: list[EpisodeResult]
    summary: dict
    ran: int
    kept: int
    seconds: float
    logs: dict[int, EpisodeLog] = field(default_factory=dict)


def _episode_path(d: Path, i: int) -> Path:
    return d / "episodes" / f"episode-{i:05d}.json"


def _write_npz(path: Path, arrays: dict) -> None:
    write_atomic(path, lambda f: np.savez_compressed(f, **arrays))


def load_log(path: str | os.PathLike) -> EpisodeLog:
    """An :class:`EpisodeLog` saved by :func:`run_episodes` (``episode-NNNNN.npz``)."""
    with np.load(path) as z:
        return EpisodeLog.from_arrays({k: z[k] for k in z.files})


def load_results(directory: str | os.PathLike, episodes: int | None = None) -> list:
    """Finished :class:`EpisodeResult` of a run directory, in episode order."""
    d = Path(directory)
    out = []
    for p in sorted((d / "episodes").glob("episode-*.json")):
        try:
            r = EpisodeResult.from_dict(json.loads(p.read_text()))
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if episodes is None or r.index < episodes:
            out.append(r)
    return out


def run_episodes(
    config,
    episodes: int,
    seed: int = 0,
    workers: int = 1,
    engine: str = "local",
    out: str | os.PathLike | None = None,
    keep_logs: Sequence[int] = (0,),
    progress: bool = True,
    client=None,
    address: str | None = None,
    scheduler_timeout: float = 10.0,
) -> RunReport:
    """Run ``episodes`` episodes of ``config`` (seeds ``seed .. seed + episodes - 1``).

    ``config``: a :class:`~scenarios.closed_loop.SimConfig` or any picklable object with
    ``to_dict()`` and ``build()`` (and optionally ``pinned(planner)``, see
    :meth:`~scenarios.closed_loop.SimConfig.pinned`). ``engine``: ``"local"``
    (``workers`` processes) or ``"dask"`` (``client``, scheduler ``address``, waited for
    ``scheduler_timeout`` s, or a new local cluster). With ``out``, results are written
    as the package docstring says and an interrupted run resumes; the logs of the
    episodes in ``keep_logs`` are saved as ``episodes/episode-NNNNN.npz`` and returned.
    ``episodes`` is at most :data:`MAX_EPISODES`, ``workers`` at most
    :data:`MAX_WORKERS` (:func:`~epo_casadi.errors.check_size`, before any work).
    """
    episodes = check_size("episodes", episodes, MAX_EPISODES, "results held in memory")
    check_number("seed", seed, lo=0, integer=True)
    workers = check_size("workers", workers, MAX_WORKERS, "processes")
    check_number("scheduler_timeout", scheduler_timeout, lo=0, lo_open=True)
    if engine not in ("local", "dask"):
        raise SpecError("engine", f"expected 'local' or 'dask', got {engine!r}")
    t0 = time.perf_counter()
    stack = config.build()  # input errors surface here, in one line, before any worker starts
    if callable(getattr(config, "build_filter", None)):
        config.build_filter()  # the filter's options too
    pin = getattr(config, "pinned", None)
    if callable(pin):  # a trained planner: every worker must load this very checkpoint
        config = pin(stack[2])
    del stack
    header = {"format_version": FORMAT_VERSION, "config": config.to_dict(), "seed": int(seed)}
    done: dict[int, EpisodeResult] = {}
    logs: dict[int, EpisodeLog] = {}
    d = Path(out) if out is not None else None
    lock = contextlib.nullcontext()
    if d is not None:
        lock = output_lock(check_output_dir(d), "epo simulate")
    with lock:
        if d is not None:
            _open_record(d, header)
            _resume(d, episodes, seed, keep_logs, done, logs)
        n_todo = episodes - len(done)
        todo = (i for i in range(episodes) if i not in done)  # lazily: never a list of all
        job = EpisodeJob(config, seed, keep_logs)
        engine_args = (engine, workers, client, address, scheduler_timeout)
        _run(job, todo, n_todo, seed, engine_args, d, progress, _label(config), done, logs)
        results = [done[i] for i in range(episodes)]
        summary = summarize(results, label=_label(config))
        if d is not None:
            write_summary(d, results, summary)
    return RunReport(
        str(d) if d is not None else None,
        results,
        summary,
        n_todo,
        episodes - n_todo,
        time.perf_counter() - t0,
        logs,
    )


def _open_record(d: Path, header: dict) -> None:
    """Write ``config.json``, or refuse a directory that records another run (the fields
    that differ, with both values)."""
    cpath = d / CONFIG
    if not cpath.exists():
        write_atomic(cpath, json.dumps(header, indent=1) + "\n")
        return
    try:
        old = json.loads(cpath.read_text())
    except (OSError, ValueError) as e:
        raise SpecError(str(cpath), f"unreadable ({e})") from None
    diff = _differences(old, json.loads(_canon(header)))
    if diff:
        raise SpecError(
            str(cpath),
            "holds a run with another configuration or seed: "
            + "; ".join(
                f"{k} ({short_repr(a, 60)} there, {short_repr(b, 60)} asked)"
                for k, a, b in diff[:4]
            )
            + ("; ..." if len(diff) > 4 else "")
            + "; use another --out",
        )


def _resume(d: Path, episodes: int, seed: int, keep_logs, done: dict, logs: dict) -> None:
    """Collect the finished episodes of ``d`` into ``done`` (their kept logs into ``logs``);
    episodes that ended in an error, of another seed or missing a kept log run again."""
    for tmp in (d / "episodes").glob(".*.tmp"):
        with contextlib.suppress(OSError):  # left by a killed run
            tmp.unlink()
    for r in load_results(d, episodes):
        npz = _episode_path(d, r.index).with_suffix(".npz")
        stale = r.seed != seed + r.index or r.outcome == "error"  # errors run again
        if stale or (r.index in keep_logs and not npz.is_file()):
            continue
        done[r.index] = r
        if r.index in keep_logs:
            logs[r.index] = load_log(npz)


def _run(job, todo, n_todo, seed, engine_args, d, progress, label, done, logs) -> None:
    """Run the episodes ``todo`` on the engine, writing each result as it comes in."""
    from scenarios.dataset.engine import _iter_dask, _iter_local

    engine, workers, client, address, scheduler_timeout = engine_args
    bar = it = None
    if progress and n_todo:
        from tqdm import tqdm

        bar = tqdm(total=n_todo, unit="episode", desc=label, dynamic_ncols=True)
    try:
        if engine == "local":
            it = _iter_local(job, todo, seed, workers)
        else:
            it = _iter_dask(job, todo, seed, workers, client, address, scheduler_timeout)
        counts: dict[str, int] = {}
        for index, arrays, _ in it:
            res: EpisodeResult = arrays["episode"][0]
            if d is not None:
                if res.log is not None:
                    _write_npz(_episode_path(d, index).with_suffix(".npz"), res.log.arrays())
                write_atomic(_episode_path(d, index), json.dumps(res.to_dict()) + "\n")
            if res.log is not None:
                logs[index] = res.log
            done[index] = res
            counts[res.outcome] = counts.get(res.outcome, 0) + 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix({k: v for k, v in sorted(counts.items())})
    finally:
        if it is not None:
            it.close()
        if bar is not None:
            bar.close()


_MISSING = "(absent)"


def _differences(old, new, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """The dotted fields (``config.model_checkpoint.sha256``) where two JSON records differ,
    with both values."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in [*old, *(k for k in new if k not in old)]:
            key = f"{prefix}.{k}" if prefix else str(k)
            out += _differences(old.get(k, _MISSING), new.get(k, _MISSING), key)
        return out
    return [] if old == new else [(prefix or "record", old, new)]


def _canon(obj) -> str:
    return json.dumps(obj, sort_keys=True, default=str)


def _label(config) -> str:
    return str(getattr(config, "label", type(config).__name__))
