"""The engines that run work units: a local spawn process pool and a dask cluster, both
calling :func:`run_unit` (:mod:`scenarios.dataset`, "Engines")."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np

from epo_casadi.errors import SpecError

from .scenario import DatasetError, FieldSpec, Scenario, unit_seed


def run_unit(scenario: Scenario, index: int, seed: int) -> tuple[int, dict[str, np.ndarray], float]:
    """Worker entry point (module level, spawn- and cloudpickle-safe).

    Returns ``(index, arrays, seconds)``; arrays are cast to the schema dtypes and
    checked against the schema shapes.
    """
    t0 = time.perf_counter()
    out = scenario.run_unit(index, unit_seed(seed, index))
    arrays = _conform(scenario.schema(), out, f"unit {index}")
    return index, arrays, time.perf_counter() - t0


def _conform(schema: dict[str, FieldSpec], arrays: dict, where: str) -> dict[str, np.ndarray]:
    missing = set(schema) - set(arrays)
    extra = set(arrays) - set(schema)
    if missing or extra:
        raise DatasetError(
            where,
            f"fields differ from the schema: missing {sorted(missing)}, extra {sorted(extra)}",
        )
    n = None
    out = {}
    for k, fs in schema.items():
        a = np.asarray(arrays[k])
        if n is None:
            n = a.shape[0] if a.ndim else -1
        if a.shape != (n, *fs.shape):
            raise DatasetError(
                f"{where}.{k}",
                f"expected shape ({n}, {', '.join(map(str, fs.shape))}), got {a.shape}",
            )
        out[k] = np.ascontiguousarray(a, dtype=np.dtype(fs.dtype))
    return out


@contextlib.contextmanager
def _single_threaded_children():
    """Children inherit one BLAS / CasADi thread each (set before they import numpy)."""
    keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "EPO_THREADS")
    old = {k: os.environ.get(k) for k in keys}
    for k in keys:
        os.environ.setdefault(k, "1")
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _worker_init(parent_pid: int) -> None:
    """Initializer of a pool worker: exit when the parent dies; leave SIGINT to the parent.

    On Linux the kernel kills the worker when its parent exits (``prctl(PR_SET_PDEATHSIG)``),
    also after ``kill -9`` of the parent. Everywhere, a daemon thread checks every 0.2 s
    that the parent is still the same process (``os.getppid()`` changes when the worker is
    re-parented) and ends the worker otherwise. SIGINT is ignored: the parent handles
    Ctrl-C and stops its workers, so they do not print tracebacks of their own.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):  # best effort; the thread below is the fallback
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL))
    if os.getppid() != parent_pid:  # the parent died before the line above took effect
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.2)
        os._exit(1)

    threading.Thread(target=watch, name="epo-parent-watch", daemon=True).start()


def stop_pool(ex) -> None:
    """Stop a ``ProcessPoolExecutor``'s work in flight now: cancel what has not started,
    terminate the worker processes and wait a little for each (an interrupted or failed
    run; the caller still calls ``ex.shutdown(wait=True)`` to release the pool)."""
    procs = list((getattr(ex, "_processes", None) or {}).values())
    ex.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.terminate()
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.join(timeout=5)


def _iter_local(scenario: Scenario, units: list[int], seed: int, workers: int) -> Iterator[tuple]:
    if workers <= 1:
        for i in units:
            yield run_unit(scenario, i, seed)
        return
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    with _single_threaded_children():
        ex = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=mp.get_context("spawn"),
            initializer=_worker_init,
            initargs=(os.getpid(),),
        )
    finished = False
    try:
        # keep a bounded window in flight so finished shards are written early
        pending, todo = set(), iter(units)
        for i in todo:
            pending.add(ex.submit(run_unit, scenario, i, seed))
            if len(pending) >= 2 * workers:
                break
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in sorted(done, key=lambda f: f.result()[0]):
                yield f.result()
                nxt = next(todo, None)
                if nxt is not None:
                    pending.add(ex.submit(run_unit, scenario, nxt, seed))
        finished = True
    finally:
        if not finished:  # interrupted or failed: stop the units in flight now
            stop_pool(ex)
        ex.shutdown(wait=True, cancel_futures=True)


def _iter_dask(
    scenario: Scenario,
    units: list[int],
    seed: int,
    workers: int,
    client=None,
    address: str | None = None,
    timeout: float = 10.0,
) -> Iterator[tuple]:
    try:
        import distributed
    except ImportError:  # pragma: no cover - optional dependency
        raise SpecError("engine", "the 'dask' engine needs dask[distributed] installed") from None
    cluster = None
    own = client is None
    if own:
        if address:
            try:
                client = distributed.Client(address, timeout=timeout)
            except (OSError, TimeoutError) as e:
                first = str(e).strip().splitlines()[0][:120] if str(e).strip() else ""
                raise SpecError(
                    "scheduler",
                    f"cannot reach the dask scheduler at {address!r} within {timeout:g} s "
                    f"({type(e).__name__}: {first}); check the address, or raise the timeout "
                    "(--scheduler-timeout)",
                ) from None
        else:
            with _single_threaded_children():
                cluster = distributed.LocalCluster(
                    n_workers=max(1, workers),
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=":0",
                )
            client = distributed.Client(cluster)
    futures = [client.submit(run_unit, scenario, i, seed, pure=False) for i in units]
    try:
        for fut in distributed.as_completed(futures):
            yield fut.result()
            fut.release()
    finally:
        for f in futures:
            f.cancel()
        if own:
            client.close()
            if cluster is not None:
                cluster.close()
