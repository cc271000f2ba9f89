"""Reading a split: random access by sample index (:class:`SplitReader`) and whole
(:func:`load_split`), each shard checked when it is opened (:mod:`scenarios.dataset`,
"Checks on read")."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from epo_casadi.errors import SpecError, short_repr

from .manifest import _planned, plan_problems, read_manifest
from .scenario import MANIFEST, SPLITS, DatasetError, FieldSpec
from .shards import check_shard, shard_problems


def _check_split(m: dict, split: str) -> None:
    if split not in SPLITS:
        raise SpecError("split", f"expected one of {list(SPLITS)}, got {split!r}")
    for where, msg in plan_problems(m)[:1]:
        raise DatasetError(
            f"{MANIFEST}.{where}",
            f"{msg}; the manifest was changed or damaged (epo data verify lists every problem)",
        )
    if not m["complete"]:
        missing = [n for n in m["splits"][split]["shards"] if n not in m["shards"]]
        if missing:
            raise DatasetError(
                f"{MANIFEST}.complete",
                f"split {split!r} is unfinished ({len(missing)} shard(s) missing); run generate again to resume",
            )
    for n in m["splits"][split]["shards"]:
        if n not in m["shards"]:
            raise DatasetError(
                f"{MANIFEST}.shards",
                f"shard {n!r} of split {split!r} is not listed although the manifest says "
                "complete; run generate again to redo it",
            )


def _index_error(bad: int, n: int, split: str) -> SpecError:
    return SpecError(
        "index",
        f"expected an index in [0, {n}) for split {split!r}"
        f"{' (negative indices are not accepted)' if bad < 0 else ''}, got {short_repr(bad)}",
    )


def check_indices(idx: np.ndarray, n: int, split: str) -> None:
    """Refuse sample indices outside ``[0, n)`` (negatives too) with one :class:`SpecError`."""
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise _index_error(int(idx[(idx < 0) | (idx >= n)][0]), n, split)


def check_index(i: Any, n: int, split: str) -> int:
    """One sample index as an ``int`` in ``[0, n)``; :class:`SpecError` otherwise (a
    non-integer, a negative, or any size of integer past the end: never an overflow)."""
    if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)):
        raise SpecError("index", f"expected an integer, got {short_repr(i)}")
    i = int(i)
    if not 0 <= i < n:
        raise _index_error(i, n, split)
    return i


def as_indices(indices: Any, n: int, split: str) -> np.ndarray:
    """Sample indices (an integer sequence or array) as an int64 array, each in ``[0, n)``.

    :class:`SpecError` for indices out of range and for values that are no int64 integers
    (an integer too large for int64 is refused, never an ``OverflowError``).
    """
    try:
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    except (OverflowError, TypeError, ValueError):
        raise SpecError(
            "index",
            f"expected integer indices in [0, {n}) for split {split!r}, got {short_repr(indices)}",
        ) from None
    check_indices(idx, n, split)
    return idx


class SplitReader:
    """Random access to one split without loading it: ``len``, ``reader[i]``, ``reader.read(idx)``.

    Shard files are opened on first use and kept open; use as a context manager or call
    :meth:`close`. The manifest must agree with the plan of its splits
    (:func:`plan_problems`: a shard listed in another split than its own is refused,
    naming the shard and both splits). Opening a shard checks its sha256 against the
    manifest once per file version (:func:`check_shard`), then that it belongs to this
    dataset, split and units and that its fields have the manifest's shapes
    (:func:`shard_problems`); a failed check is one :class:`DatasetError` naming the shard.
    Indices are ``0 .. len - 1``; negative indices and indices past the end (of any
    size) are refused (the index names a sample in figures and messages, so it has one
    spelling). ``reader[i]`` is a dict of per-sample arrays (no sample axis);
    :meth:`read` takes an index array (any order, repeats allowed) and returns a batch.
    """

    def __init__(
        self, directory: str | os.PathLike, split: str, fields: Iterable[str] | None = None
    ):
        self.directory = Path(directory)
        self.manifest = m = read_manifest(self.directory)
        _check_split(m, split)
        self.split = split
        self.schema = {
            k: FieldSpec(tuple(v["shape"]), v["dtype"], v.get("doc", ""))
            for k, v in m["schema"].items()
        }
        names = list(self.schema) if fields is None else list(fields)
        for k in names:
            if k not in self.schema:
                raise SpecError(
                    "fields", f"unknown field {k!r}; expected some of {list(self.schema)}"
                )
        self.fields = names
        self.shards = [n for n in m["splits"][split]["shards"]]
        self._plan = _planned(m)
        sizes = [m["shards"][n]["samples"] for n in self.shards]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self._files: dict[str, Any] = {}

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def _file(self, name: str):
        if name not in self._files:
            import h5py

            path = self.directory / name
            check_shard(path, self.manifest["shards"][name]["sha256"])
            try:
                h = h5py.File(path, "r")
            except (OSError, FileNotFoundError) as e:
                raise DatasetError(str(path), f"cannot open shard ({e})") from None
            try:
                found = shard_problems(h, name, self.manifest, self._plan[name])
            except (OSError, ValueError, TypeError, KeyError) as e:
                h.close()
                msg = str(e).strip().splitlines()[0][:120] if str(e).strip() else ""
                raise DatasetError(
                    str(path), f"unreadable shard ({type(e).__name__}: {msg})"
                ) from None
            except BaseException:
                h.close()
                raise
            if found:
                h.close()
                where, msg = found[0]
                raise DatasetError(str(self.directory / where), msg)
            self._files[name] = h
        return self._files[name]

    def _locate(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        check_indices(idx, len(self), self.split)
        shard = np.searchsorted(self.offsets, idx, side="right") - 1
        return shard, idx - self.offsets[shard]

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        b = self.read(np.array([check_index(i, len(self), self.split)]))
        return {k: v[0] for k, v in b.items()}

    def read(self, indices) -> dict[str, np.ndarray]:
        """Batch of samples ``indices`` (int array or slice) as dict of ``(B, *shape)`` arrays."""
        if isinstance(indices, slice):
            indices = np.arange(len(self))[indices]
        idx = as_indices(indices, len(self), self.split)
        shard, local = self._locate(idx)
        out = {
            k: np.empty((idx.size, *self.schema[k].shape), np.dtype(self.schema[k].dtype))
            for k in self.fields
        }
        for s in np.unique(shard):
            sel = np.nonzero(shard == s)[0]
            loc = local[sel]
            order = np.argsort(loc, kind="stable")
            uniq, inv = np.unique(loc[order], return_inverse=True)
            h = self._file(self.shards[s])
            for k in self.fields:
                vals = h[k][uniq]  # h5py fancy indexing needs increasing unique indices
                out[k][sel[order]] = vals[inv]
        return out

    def read_all(self) -> dict[str, np.ndarray]:
        out = {}
        for k in self.fields:
            fs = self.schema[k]
            a = np.empty((len(self), *fs.shape), np.dtype(fs.dtype))
            for j, name in enumerate(self.shards):
                lo, hi = self.offsets[j], self.offsets[j + 1]
                if hi > lo:
                    self._file(name)[k].read_direct(a, dest_sel=np.s_[lo:hi])
            out[k] = a
        return out

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        self._files.clear()

    def __enter__(self) -> SplitReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):  # pragma: no cover - best effort
        with contextlib.suppress(Exception):
            self.close()


def load_split(
    directory: str | os.PathLike, split: str, fields: Iterable[str] | None = None
) -> dict[str, np.ndarray]:
    """Every sample of ``split`` as a dict of numpy arrays ``(n, *shape)`` (shards in order)."""
    with SplitReader(directory, split, fields) as r:
        return r.read_all()
