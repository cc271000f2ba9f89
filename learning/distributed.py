"""Data-parallel training on several processes (``torch.distributed``).

:func:`learning.train.train` runs on every rank of a process group: started by ``torchrun``
(each process reads ``RANK``, ``WORLD_SIZE``, ``MASTER_ADDR``, ``MASTER_PORT`` from its
environment), by ``epo train --nproc N`` or
:func:`learning.train.train_parallel` (which start ``N`` local
ranks themselves, :func:`launch`), or inside a process group a script created. One process
(``WORLD_SIZE`` unset or 1) trains as before, with no process group.

What the ranks share
    Every global batch (the ``batch_size`` samples of the permutation of ``(seed, epoch)``,
    :meth:`learning.data.SceneDataset.order`) is cut into ``world size`` contiguous,
    disjoint shards (:func:`shard`; sizes differ by at most one), one per rank. The model is
    wrapped in :class:`~torch.nn.parallel.DistributedDataParallel` (gradients averaged
    over ranks) and every :class:`~torch.nn.BatchNorm1d` becomes a :class:`SyncBatchNorm1d`
    (:func:`convert_sync_batchnorm`): batch statistics over the global batch, so a step on
    ``W`` ranks is the step of one process on the same global batch (to rounding; tested).
    torch's own ``SyncBatchNorm`` runs on GPUs only, and this toolkit trains on the CPU (the
    game layer solves on the host), hence this one; it communicates with
    ``all_reduce`` on any backend. Each rank's loss parts are weighted by its share of the
    global batch's samples (or real agents, for the terms averaged over agents) before the
    backward pass, and the parts, sample counts and layer statuses are summed over the
    ranks (:func:`all_sum`), so ``metrics.csv`` holds the global batch's numbers. The
    validation split is sharded the same way; the per-sample metrics are gathered and
    averaged as one process does (:func:`gather_objects`).

Start and files
    At start the ranks exchange a digest of their training settings, their dataset's
    fingerprint and split sizes and the checkpoint they resume from (:func:`agree`); any
    difference, or an error on any rank (a missing dataset, a locked run folder), stops
    every rank with the same one-line :class:`~epo_casadi.errors.EpoError` (``epo``: exit
    status 2) instead of a hang. Rank 0 alone holds the run folder's lock and writes its
    files (checkpoints, atomically; ``metrics.csv``, ``loss.png``, TensorBoard events); a
    checkpoint does not depend on the number of ranks, so a run resumes on any number.

Backend: ``gloo`` (CPU tensors); where CUDA is available ``cpu:gloo,cuda:nccl``
(:func:`default_backend`: nccl for CUDA tensors, gloo for the CPU tensors training uses).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import pickle
import traceback
from dataclasses import dataclass
from datetime import timedelta

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from epo_casadi.errors import EpoError, SpecError

__all__ = [
    "DistributedError",
    "SyncBatchNorm1d",
    "World",
    "agree",
    "all_sum",
    "convert_sync_batchnorm",
    "default_backend",
    "digest",
    "gather_objects",
    "joined",
    "launch",
    "shard",
]

#: how long a collective waits for the other ranks before failing
TIMEOUT = timedelta(minutes=30)


class DistributedError(EpoError):
    """Ranks disagree about the run, or another rank failed (the same line on every rank)."""


class _RelayedError(DistributedError):
    """This rank stops because another one failed (the launcher reports the origin)."""


@dataclass(frozen=True)
class World:
    """This process's place in the process group (``size == 1``: no process group)."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """Rank 0: the one that writes the run's files."""
        return self.rank == 0


def default_backend() -> str:
    """``gloo``, or ``cpu:gloo,cuda:nccl`` where CUDA is available."""
    return "cpu:gloo,cuda:nccl" if torch.cuda.is_available() else "gloo"


def _env_size() -> int:
    v = os.environ.get("WORLD_SIZE", "1")
    try:
        return int(v)
    except ValueError:
        raise SpecError("WORLD_SIZE", f"expected an integer, got {v!r}") from None


@contextlib.contextmanager
def joined():
    """The :class:`World` of this process within the block.

    An initialized process group is used as it is; otherwise, with ``WORLD_SIZE > 1`` in
    the environment (``torchrun``), the default group is created (``env://``,
    :func:`default_backend`) and destroyed at the end; otherwise ``World()``.
    """
    if dist.is_available() and dist.is_initialized():
        yield World(dist.get_rank(), dist.get_world_size(), _local_rank())
        return
    if _env_size() <= 1:
        yield World()
        return
    if not dist.is_available():
        raise SpecError("WORLD_SIZE", "torch.distributed is not available in this torch build")
    dist.init_process_group(default_backend(), timeout=TIMEOUT)
    try:
        yield World(dist.get_rank(), dist.get_world_size(), _local_rank())
    finally:
        dist.destroy_process_group()


def _local_rank() -> int:
    return int(os.environ.get("LOCAL_RANK", dist.get_rank() if dist.is_initialized() else 0))


def shard(indices: np.ndarray, rank: int, size: int) -> np.ndarray:
    """Rank ``rank``'s part of ``indices``: contiguous, disjoint, sizes within one of each
    other (the first ``len % size`` ranks one more); all of them in order give ``indices``."""
    n = len(indices)
    lo = rank * (n // size) + min(rank, n % size)
    return indices[lo : lo + n // size + (rank < n % size)]


def all_sum(t: torch.Tensor) -> torch.Tensor:
    """``t`` summed over the ranks (a new tensor; ``t`` itself without a process group)."""
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return t
    t = t.clone()
    dist.all_reduce(t)
    return t


def gather_objects(obj) -> list:
    """``[obj of rank 0, obj of rank 1, ...]`` on every rank (``[obj]`` without a group)."""
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return [obj]
    out = [None] * dist.get_world_size()
    dist.all_gather_object(out, obj)
    return out


def digest(obj) -> str:
    """sha256 of ``obj`` as canonical JSON (sorted keys)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def _first_difference(a, b, prefix: str = "") -> str:
    """The first key path where two JSON-like values differ, with both values."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in list(a) + [k for k in b if k not in a]:
            if a.get(k) != b.get(k):
                return _first_difference(a.get(k), b.get(k), f"{prefix}{k}.")
    return f"{prefix.rstrip('.') or 'value'} ({a!r} vs {b!r})"


def agree(world: World, facts: dict, error: BaseException | None = None) -> None:
    """Stop every rank alike unless all ranks started alike.

    ``facts``: ``{"config": ..., "data": ..., "resume": ...}`` of this rank (JSON-like);
    ``error``: what this rank's start raised (None: it started). Every rank calls this once
    at start; it raises on every rank or on none: this rank's own ``error``, a
    :class:`DistributedError` naming the rank that failed, or one naming the first fact in
    which two ranks differ (the same line on every rank).
    """
    if world.size == 1:
        if error is not None:
            raise error
        return
    msg = None if error is None else (str(error) or type(error).__name__)
    mine = {k: digest(v) for k, v in facts.items()}
    seen = gather_objects((msg, mine, facts))
    failed = [(r, m) for r, (m, _, _) in enumerate(seen) if m is not None]
    if failed:
        if error is not None:
            raise error
        r, m = failed[0]
        raise _RelayedError(f"rank {r}: {m}")
    what = {"config": "training settings", "data": "dataset", "resume": "checkpoint to resume"}
    for r, (_, theirs, f) in enumerate(seen[1:], start=1):
        for k in mine:
            if seen[0][1][k] != theirs.get(k):
                diff = _first_difference(seen[0][2][k], f.get(k))
                raise DistributedError(
                    f"train: the ranks disagree about the {what.get(k, k)}: rank 0 and rank "
                    f"{r} differ in {diff}; start every rank with the same command and data"
                )


# --------------------------------------------------------------------------------------
# batch norm over the global batch
# --------------------------------------------------------------------------------------
class _SyncNorm(torch.autograd.Function):
    """``x_hat = (x - mean) / sqrt(var + eps)`` with the mean and (biased) variance of the
    global batch (every rank's rows); returns ``x_hat``, ``mean``, ``var`` and the count."""

    @staticmethod
    def forward(ctx, x, eps):
        dims = [0, *range(2, x.dim())]
        shape = [1, -1] + [1] * (x.dim() - 2)
        C = x.shape[1]
        xd = x.double()  # sums in float64: no cancellation in E[x^2] - E[x]^2
        local = torch.cat(
            [xd.sum(dims), (xd * xd).sum(dims), xd.new_tensor([x.numel() // max(C, 1)])]
        )
        tot = all_sum(local)
        n = tot[-1]
        if n < 2:
            raise ValueError(
                f"Expected more than 1 value per channel when training, got {int(n)} in all"
            )
        mean = tot[:C] / n
        var = (tot[C : 2 * C] / n - mean * mean).clamp_min(0)
        invstd = (var + eps).rsqrt()
        xhat = ((xd - mean.reshape(shape)) * invstd.reshape(shape)).to(x.dtype)
        ctx.save_for_backward(xhat, invstd.to(x.dtype))
        ctx.n, ctx.dims, ctx.shape = n, dims, shape
        return xhat, mean.to(x.dtype), var.to(x.dtype), n

    @staticmethod
    def backward(ctx, g, _gm=None, _gv=None, _gn=None):
        xhat, invstd = ctx.saved_tensors
        C = xhat.shape[1]
        gd, xd = g.double(), xhat.double()
        tot = all_sum(torch.cat([gd.sum(ctx.dims), (gd * xd).sum(ctx.dims)]))
        mg = (tot[:C] / ctx.n).reshape(ctx.shape)
        mgx = (tot[C:] / ctx.n).reshape(ctx.shape)
        dx = (gd - mg - xd * mgx) * invstd.double().reshape(ctx.shape)
        return dx.to(g.dtype), None


class SyncBatchNorm1d(nn.BatchNorm1d):
    """:class:`~torch.nn.BatchNorm1d` whose training statistics span every rank's rows
    (the global batch); outside a process group, or in eval mode, the plain one. The same
    parameters and buffers (a checkpoint loads into either)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalized ``x`` ``(B, C)`` or ``(B, C, L)``; in training, with the statistics
        of every rank's rows (and the running ones updated with them)."""
        if not self.training or not (dist.is_available() and dist.is_initialized()):
            return super().forward(x)
        if dist.get_world_size() == 1:
            return super().forward(x)
        self._check_input_dim(x)
        xhat, mean, var, n = _SyncNorm.apply(x, self.eps)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                m = (
                    1.0 / float(self.num_batches_tracked)
                    if self.momentum is None
                    else self.momentum
                )
                unbiased = var * (n / (n - 1)).to(var.dtype)
                self.running_mean.mul_(1 - m).add_(mean, alpha=m)
                self.running_var.mul_(1 - m).add_(unbiased, alpha=m)
        if not self.affine:
            return xhat
        shape = [1, -1] + [1] * (x.dim() - 2)
        return xhat * self.weight.reshape(shape) + self.bias.reshape(shape)


def convert_sync_batchnorm(module: nn.Module) -> nn.Module:
    """``module`` with every :class:`~torch.nn.BatchNorm1d` replaced by a
    :class:`SyncBatchNorm1d` holding its parameters and buffers (in place; returned)."""
    for name, child in list(module.named_children()):
        if type(child) is nn.BatchNorm1d:
            new = SyncBatchNorm1d(
                child.num_features, child.eps, child.momentum, child.affine,
                child.track_running_stats,
            )  # fmt: skip
            new.load_state_dict(child.state_dict())
            new.train(child.training)
            setattr(module, name, new)
        else:
            convert_sync_batchnorm(child)
    return module


# --------------------------------------------------------------------------------------
# local ranks
# --------------------------------------------------------------------------------------
def _rank_main(rank: int, size: int, port: int, env: dict, target, args, kwargs, conn) -> None:
    """One local rank: join the group through the launcher's store, run ``target``,
    report ``("ok", result)``, ``("epo", message, relayed)`` or ``("exc", traceback)``."""
    os.environ.update(env)
    os.environ.update(
        {
            "RANK": str(rank),
            "LOCAL_RANK": str(rank),
            "WORLD_SIZE": str(size),
            "LOCAL_WORLD_SIZE": str(size),
            "MASTER_ADDR": "127.0.0.1",
            "MASTER_PORT": str(port),
            "TORCHELASTIC_USE_AGENT_STORE": "True",  # the launcher hosts the store
        }
    )
    report = None
    try:
        dist.init_process_group(default_backend(), timeout=TIMEOUT)
        report = ("ok", target(*args, **kwargs))
    except EpoError as e:
        report = ("epo", str(e), isinstance(e, _RelayedError))
    except BaseException:  # noqa: BLE001 (reported to the launcher, which raises)
        report = ("exc", traceback.format_exc())
    finally:
        # plain pickle bytes: torch's multiprocessing pickler would share tensors through
        # file descriptors that die with this process
        try:
            payload = pickle.dumps(report)
        except Exception:  # noqa: BLE001 (an unpicklable result)
            payload = pickle.dumps(("exc", traceback.format_exc()))
        conn.send_bytes(payload)
        conn.close()
        if dist.is_initialized():
            with contextlib.suppress(Exception):
                dist.destroy_process_group()


def launch(nproc: int, target, args=(), kwargs=None, rank_kwargs=None, grace: float = 5.0):
    """Run ``target(*args, **kwargs, **rank_kwargs[r])`` on ``nproc`` local ranks.

    Each rank is a fresh process (``spawn``) in one process group (:func:`default_backend`;
    the store is hosted here, as ``torchrun``'s agent does), so :func:`joined` inside
    ``target`` sees it. ``target`` must be importable (a module-level function). Returns the
    results in rank order. When a rank fails, the others get ``grace`` seconds to report,
    then are terminated; raised here: a rank's :class:`~epo_casadi.errors.EpoError`
    message as a :class:`DistributedError` (the rank where it arose, the lowest first), a
    :class:`RuntimeError` with a rank's traceback, or a :class:`DistributedError` naming a
    rank that died without reporting (e.g. killed). Ctrl-C terminates every rank.
    """
    import multiprocessing as mp

    if isinstance(nproc, bool) or not isinstance(nproc, int) or nproc < 1:
        raise SpecError("nproc", f"expected an integer >= 1, got {nproc!r}")
    kwargs = dict(kwargs or {})
    rank_kwargs = list(rank_kwargs or [{}] * nproc)
    if len(rank_kwargs) != nproc:
        raise SpecError("rank_kwargs", f"expected {nproc} mappings, got {len(rank_kwargs)}")
    ctx = mp.get_context("spawn")
    store = dist.TCPStore("127.0.0.1", 0, None, True, TIMEOUT, wait_for_workers=False)
    env = {"OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    procs, conns = [], []
    try:
        for r in range(nproc):
            recv, send = ctx.Pipe(duplex=False)
            p = ctx.Process(
                target=_rank_main,
                args=(r, nproc, store.port, env, target, args, {**kwargs, **rank_kwargs[r]}, send),
                name=f"epo-rank-{r}",
            )
            p.start()
            send.close()
            procs.append(p)
            conns.append(recv)
        reports = _collect(procs, conns, grace)
    except BaseException:
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(5)
            if p.is_alive():
                p.kill()
        raise
    finally:
        for c in conns:
            c.close()
        del store
    return _results(reports, procs)


def _collect(procs, conns, grace: float) -> list:
    """Reports of every rank (None: exited without one); terminates the ranks still
    running ``grace`` seconds after the first failure."""
    import time
    from multiprocessing.connection import wait

    n = len(procs)
    reports: list = [None] * n
    listening, running = set(range(n)), set(range(n))
    deadline = None

    def failed(r: int) -> bool:
        rep = reports[r]
        return (rep is not None and rep[0] != "ok") or (rep is None and r not in listening)

    while running:
        timeout = None if deadline is None else max(deadline - time.monotonic(), 0.0)
        ready = wait([conns[r] for r in listening] + [procs[r].sentinel for r in running], timeout)
        if not ready:  # the grace after a failure is over
            break
        for r in range(n):
            if r in listening and conns[r] in ready:
                try:
                    reports[r] = pickle.loads(conns[r].recv_bytes())
                except (EOFError, OSError):
                    pass
                listening.discard(r)
            if r in running and procs[r].sentinel in ready:
                running.discard(r)
                if r in listening and conns[r].poll():
                    with contextlib.suppress(EOFError, OSError):
                        reports[r] = pickle.loads(conns[r].recv_bytes())
                listening.discard(r)
            if deadline is None and failed(r):
                deadline = time.monotonic() + grace
    for r in running:
        procs[r].terminate()
    for p in procs:
        p.join(10)
        if p.is_alive():
            p.kill()
            p.join()
    return reports


def _results(reports: list, procs) -> list:
    """The results of :func:`launch`, or the error that stopped it."""
    if all(rep is not None and rep[0] == "ok" for rep in reports):
        return [rep[1] for rep in reports]
    for rep in reports:  # a rank's own error first (not one relayed from another rank)
        if rep is not None and rep[0] == "epo" and not rep[2]:
            raise DistributedError(rep[1])
    # then a rank that died (its peers then fail in a collective), then a traceback that
    # is not such a failure, then any
    for r, rep in enumerate(reports):
        if rep is None:
            code = procs[r].exitcode
            how = f"by signal {-code}" if code is not None and code < 0 else f"with status {code}"
            raise DistributedError(
                f"train: rank {r} stopped {how} without a report; the last checkpoint is "
                "kept: run the same command again to resume"
            )
    tracebacks = [(r, rep[1]) for r, rep in enumerate(reports) if rep[0] == "exc"]
    tracebacks.sort(key=lambda t: "distributed_c10d.py" in t[1])
    if tracebacks:
        r, tb = tracebacks[0]
        raise RuntimeError(f"rank {r} failed:\n{tb}")
    raise DistributedError(next(rep[1] for rep in reports if rep[0] == "epo"))
