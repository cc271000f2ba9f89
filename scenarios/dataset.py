"""Sharded HDF5 datasets: resumable, deterministic generation, verification, loading.

A dataset is a directory::

    DIR/manifest.json         what was asked for and what is finished (written atomically)
    DIR/train-00000.h5 ...    shards: one split each, a fixed group of work units each
    DIR/.lock                 held (flock) while a generation runs

Work units and seeds
    A :class:`Scenario` cuts its dataset into ``n_units`` independent *work units* (for
    RPI: one main game each). Unit ``i`` is computed from
    ``SeedSequence(seed, spawn_key=(1, i))`` only (the ``i``-th child of the second child of
    ``SeedSequence(seed)``), so its samples do not depend on the number of workers, the
    engine or the order in which units finish. The first child (``spawn_key=(0,)``) draws
    the split assignment: a permutation of the units, the first ~80 % train, ~10 % val,
    ~10 % test, so a split is a set of *units* and no unit contributes to two splits.

Shards
    Per split, the units (sorted by index) are grouped ``units_per_shard`` at a time; a
    shard holds the samples of its units in unit order, every schema field as one HDF5
    dataset of shape ``(n, *field_shape)`` (chunked along the first axis, deflate + shuffle
    filters). Attributes: ``format_version``, ``scenario``, ``split``, ``units``,
    ``seed`` and ``dataset`` (:func:`dataset_digest`: the identity of the dataset, a
    sha256 of the manifest's scenario, recipe and seed; shards written before it was
    recorded have no ``seed`` and ``dataset``). HDF5 files are written without
    timestamps, so equal content gives equal bytes and equal sha256 checksums.

Crash safety and resume
    A shard is built in memory (HDF5's ``core`` driver), written to a hidden temporary
    name, fsynced and renamed into place (:func:`scenarios.files.write_atomic`); only
    then is it added, with its sample count and sha256, to ``manifest.json`` (written the
    same way). HDF5 never writes to the disk itself, so a full disk or a read-only folder
    is one :class:`~epo_casadi.errors.OutputError` naming the file, and no partial file
    is left. A generation killed at any point and started again with the same scenario,
    recipe and seed keeps every shard listed in the manifest whose checksum still matches
    and that belongs to it (:func:`shard_problems`), removes temporary files, and
    recomputes the rest: nothing is lost or duplicated.

Checks on read
    Readers (:class:`SplitReader`, :func:`load_split`) check the manifest's schema
    (:func:`read_manifest`, :func:`check_manifest`) and that it agrees with the plan of
    its splits (:func:`plan_problems`: each shard listed in exactly its own split, with
    its planned units); when they open a shard, its sha256 (:func:`check_shard`, cached
    per file version), then that it belongs to this dataset, split and units and that
    every field has the manifest's shape and dtype (:func:`shard_problems`). So a shard
    moved to another split, or copied in from another dataset together with its
    checksum, is refused in one line naming the shard and what differs, never read as
    this split's samples. :func:`verify` runs every check and lists every problem.

Manifest (``format_version`` 1), JSON::

    {"format_version": 1, "scenario": "rpi", "recipe": {...}, "seed": 0,
     "n_units": 1200, "units_per_shard": 25,
     "schema": {"history": {"shape": [19, 2, 4], "dtype": "float32", "doc": "..."}, ...},
     "meta": {...scenario extras, e.g. parameter names...},
     "splits": {"train": {"units": [...], "shards": ["train-00000.h5", ...]}, ...},
     "shards": {"train-00000.h5": {"split": "train", "units": [...], "samples": 1234,
                                   "sha256": "..."}, ...},     # finished shards only
     "counts": {"train": 47822, "val": ..., "test": ...},      # finished samples
     "complete": true}

Engines
    ``local``: a process pool (``concurrent.futures``, spawn context; one worker runs in
    the calling process). ``dask``: a ``dask.distributed`` client (an existing one, a
    scheduler address, or a new ``LocalCluster``). Both call the same module-level
    :func:`run_unit`, so a cluster produces byte-identical shards. Pool workers end with
    the process that started them, also after ``kill -9`` (:func:`_worker_init`); an
    interrupt (Ctrl-C, or SIGTERM inside :func:`sigterm_as_interrupt`) stops them at once.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from epo_casadi.errors import EpoError, OutputError, SpecError, short_repr

from .files import (
    check_input_file,
    ensure_dir,
    output_lock,
    recipe_difference,
    sigterm_as_interrupt,
    write_atomic,
)
from .files import check_output_dir as _check_output_dir

__all__ = [
    "FORMAT_VERSION",
    "SPLITS",
    "DatasetError",
    "FieldSpec",
    "Scenario",
    "GenerateReport",
    "VerifyReport",
    "SplitReader",
    "generate",
    "verify",
    "load_split",
    "read_manifest",
    "unit_seed",
    "assign_splits",
    "run_unit",
    "sha256_file",
    "check_manifest",
    "check_shard",
    "check_index",
    "as_indices",
    "plan_problems",
    "shard_problems",
    "dataset_digest",
    "plan_shards",
    "check_output_dir",
    "sigterm_as_interrupt",
]

FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")
MANIFEST = "manifest.json"
CHUNK_ROWS = 256  # samples per HDF5 chunk


class DatasetError(EpoError):
    """A dataset directory, shard or manifest is missing, inconsistent or corrupt.

    ``where`` names the file or manifest field; the CLI prints ``where: message``.
    """

    def __init__(self, where: str, message: str):
        self.where = where
        self.message = message
        super().__init__(f"{where}: {message}")


@dataclass(frozen=True)
class FieldSpec:
    """One per-sample array of a dataset: shape without the sample axis, dtype, doc."""

    shape: tuple[int, ...]
    dtype: str
    doc: str = ""

    def to_dict(self) -> dict:
        return {"shape": list(self.shape), "dtype": self.dtype, "doc": self.doc}


class Scenario:
    """Base of dataset scenarios: work units, schema and the per-unit sample generator.

    Subclasses set :attr:`name` and implement :meth:`schema` and :meth:`run_unit`;
    :attr:`n_units`, :attr:`units_per_shard` and :attr:`split_fractions` come from the
    recipe. An instance must be picklable (it is sent to worker processes) and cheap to
    construct; expensive state (CasADi functions) is built lazily inside the worker.
    """

    name: str = "scenario"
    #: the attributes sent to a worker process (None: all of them). Scenarios that hold
    #: CasADi games or caches name only what rebuilds them (e.g. the recipe).
    pickled: tuple[str, ...] | None = None

    def __getstate__(self):
        if self.pickled is None:
            return self.__dict__
        return {k: getattr(self, k) for k in self.pickled}

    def __setstate__(self, state):
        self.__dict__.update(state)

    def recipe_dict(self) -> dict:
        """The recipe as JSON facts for the manifest (default: ``self.recipe.to_dict()``)."""
        return self.recipe.to_dict()

    @property
    def n_units(self) -> int:
        raise NotImplementedError

    @property
    def units_per_shard(self) -> int:
        return 16

    @property
    def split_fractions(self) -> tuple[float, float, float]:
        return (0.8, 0.1, 0.1)

    def split_units(self, seed: int) -> dict[str, list[int]]:
        """Split name -> sorted unit indices (default: :func:`assign_splits`, a seeded
        permutation by :attr:`split_fractions`; a scenario may split by construction)."""
        return assign_splits(seed, self.n_units, self.split_fractions)

    def schema(self) -> dict[str, FieldSpec]:
        raise NotImplementedError

    def meta(self) -> dict:
        """Extra JSON facts for the manifest (parameter names, units, ...)."""
        return {}

    def run_unit(self, index: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
        """Samples of unit ``index``: every schema field as ``(n_i, *shape)``."""
        raise NotImplementedError


# --------------------------------------------------------------------------------------
# seeds and splits
# --------------------------------------------------------------------------------------
def unit_seed(seed: int, index: int) -> np.random.SeedSequence:
    """Seed of work unit ``index``: ``SeedSequence(seed).spawn(2)[1].spawn(n)[index]``."""
    return np.random.SeedSequence(int(seed), spawn_key=(1, int(index)))


def split_sizes(n: int, fractions: Sequence[float]) -> tuple[int, int, int]:
    """Units per split: val and test get ``round(f * n)`` but at least 1, train the rest."""
    if n < 3:
        raise SpecError("units", f"need at least 3 work units for train/val/test, got {n}")
    nv = max(1, round(fractions[1] * n))
    nt = max(1, round(fractions[2] * n))
    return n - nv - nt, nv, nt


def assign_splits(
    seed: int, n: int, fractions: Sequence[float] = (0.8, 0.1, 0.1)
) -> dict[str, list[int]]:
    """Split name -> sorted unit indices; a seeded permutation, disjoint and complete."""
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0,)))
    perm = rng.permutation(n)
    ntr, nv, _ = split_sizes(n, fractions)
    parts = {"train": perm[:ntr], "val": perm[ntr : ntr + nv], "test": perm[ntr + nv :]}
    return {k: sorted(int(i) for i in v) for k, v in parts.items()}


def plan_shards(splits: dict[str, list[int]], per_shard: int) -> dict[str, dict]:
    """Shard name -> {"split", "units"}, in split order then unit order."""
    out = {}
    for s in SPLITS:
        units = splits[s]
        for j in range(math.ceil(len(units) / per_shard)):
            out[f"{s}-{j:05d}.h5"] = {
                "split": s,
                "units": units[j * per_shard : (j + 1) * per_shard],
            }
    return out


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


# --------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------
def sha256_file(path: str | os.PathLike, block: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()


def fsync_replace(tmp: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Flush ``tmp`` to disk and rename it to ``dst`` atomically (also used for checkpoints)."""
    tmp, dst = Path(tmp), Path(dst)
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, dst)
    with contextlib.suppress(OSError):  # make the rename durable
        dfd = os.open(dst.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def _write_json(path: Path, obj: dict) -> None:
    """``obj`` as JSON at ``path``, atomically (:func:`scenarios.files.write_atomic`)."""
    write_atomic(path, json.dumps(obj, indent=1, sort_keys=False) + "\n")


def dataset_digest(m: dict) -> str:
    """Identity of a dataset: sha256 of its manifest's ``scenario``, ``recipe`` and ``seed``.

    Generation is deterministic, so equal identities hold equal samples. Every shard
    records it (attribute ``dataset``) when it is written; readers and :func:`verify`
    refuse a shard whose identity differs from its manifest's (a shard of another
    dataset copied in, even with its checksum).
    """
    key = {k: m.get(k) for k in ("scenario", "recipe", "seed")}
    text = json.dumps(key, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def write_shard(
    path: Path,
    scenario_name: str,
    split: str,
    units: Sequence[int],
    schema: dict[str, FieldSpec],
    parts: Sequence[dict[str, np.ndarray]],
    *,
    dataset: str | None = None,
    seed: int | None = None,
) -> tuple[int, str]:
    """Write one shard atomically; returns ``(samples, sha256)``.

    ``dataset`` (:func:`dataset_digest` of the manifest) and ``seed`` are recorded as the
    shard's attributes ``dataset`` and ``seed`` beside ``format_version``, ``scenario``,
    ``split`` and ``units``. The HDF5 file is built in memory (HDF5's ``core`` driver, the
    same bytes as a file on disk) and its bytes written by
    :func:`scenarios.files.write_atomic`: the HDF5 library never writes to the disk
    itself, so a full disk or a read-only folder is one
    :class:`~epo_casadi.errors.OutputError` naming the shard, leaves no partial file, and
    never crashes inside HDF5.
    """
    import h5py

    data = {
        k: np.concatenate([p[k] for p in parts], axis=0)
        if parts
        else np.zeros((0, *fs.shape), fs.dtype)
        for k, fs in schema.items()
    }
    n = int(next(iter(data.values())).shape[0]) if data else 0
    f = h5py.File(path.name, "w", libver=("earliest", "v110"), driver="core", backing_store=False)
    try:
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["scenario"] = scenario_name
        f.attrs["split"] = split
        f.attrs["units"] = np.asarray(units, dtype=np.int64)
        if dataset is not None:
            f.attrs["dataset"] = dataset
        if seed is not None:
            f.attrs["seed"] = np.int64(seed)
        for k, fs in schema.items():
            a = data[k]
            if n:
                f.create_dataset(
                    k,
                    data=a,
                    chunks=(min(n, CHUNK_ROWS), *fs.shape),
                    # deflate, not lzf: liblzf leaves its hash table uninitialized, so
                    # the same arrays can compress to different bytes (shard checksums
                    # would then differ between engines and reruns); deflate is
                    # deterministic and readers are unchanged.
                    compression="gzip",
                    compression_opts=4,
                    shuffle=True,
                )
            else:
                f.create_dataset(k, data=a)
        f.flush()
        image = f.id.get_file_image()
    finally:
        f.close()
    write_atomic(path, image)
    return n, hashlib.sha256(image).hexdigest()


def read_manifest(directory: str | os.PathLike) -> dict:
    """The manifest of a dataset directory, schema-checked (:func:`check_manifest`).

    :class:`DatasetError` if it is missing, unreadable or malformed (naming the field).
    """
    d = Path(directory)
    if not d.is_dir():
        raise DatasetError(str(d), "no such dataset directory")
    p = d / MANIFEST
    if not p.is_file():
        raise DatasetError(
            str(p), "missing: not a dataset directory (or its generation never started)"
        )
    try:
        check_input_file(p, str(p))  # a regular file small enough to read whole
    except SpecError as e:
        raise DatasetError(str(p), e.message) from None
    try:
        m = json.loads(p.read_text())
    except (OSError, ValueError, RecursionError) as e:
        raise DatasetError(str(p), f"unreadable manifest ({type(e).__name__}: {e})") from None
    check_manifest(m, str(p))
    return m


def _short(v: Any, limit: int = 60) -> str:
    r = repr(v)
    return r if len(r) <= limit else r[: limit - 3] + "..."


def _is_int(v: Any, lo: int = 0) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= lo


def _is_file_name(v: Any) -> bool:
    """A plain file name inside the dataset directory (no path, not hidden, not a temp)."""
    return (
        isinstance(v, str)
        and v != ""
        and "/" not in v
        and "\\" not in v
        and "\x00" not in v
        and not v.startswith(".")
    )


def check_manifest(m: Any, where: str = MANIFEST) -> None:
    """Check the manifest's schema (module docstring); :class:`DatasetError` names the field.

    Every field a reader or the generator uses is checked for its type and range, so a
    hand-edited or damaged manifest gives one line naming the field, never a traceback.
    """
    if not isinstance(m, dict):
        raise DatasetError(where, f"expected a JSON object, got {type(m).__name__}")
    if m.get("format_version") != FORMAT_VERSION:
        raise DatasetError(
            f"{where}.format_version",
            f"expected {FORMAT_VERSION}, got {_short(m.get('format_version'))}",
        )
    keys = ("scenario", "recipe", "seed", "n_units", "units_per_shard", "schema", "splits")
    for key in (*keys, "shards", "counts", "complete"):
        if key not in m:
            raise DatasetError(f"{where}.{key}", "missing")

    def bad(key: str, expected: str, got: Any) -> DatasetError:
        return DatasetError(f"{where}.{key}", f"expected {expected}, got {_short(got)}")

    if not isinstance(m["scenario"], str) or not m["scenario"]:
        raise bad("scenario", "a non-empty string", m["scenario"])
    if not isinstance(m["recipe"], dict):
        raise bad("recipe", "an object", m["recipe"])
    if "meta" in m and not isinstance(m["meta"], dict):
        raise bad("meta", "an object", m["meta"])
    if not _is_int(m["seed"]):
        raise bad("seed", "an integer >= 0", m["seed"])
    n_units = m["n_units"]
    if not _is_int(n_units, 1):
        raise bad("n_units", "an integer >= 1", n_units)
    if not _is_int(m["units_per_shard"], 1):
        raise bad("units_per_shard", "an integer >= 1", m["units_per_shard"])
    if not isinstance(m["complete"], bool):
        raise bad("complete", "true or false", m["complete"])
    schema = m["schema"]
    if not isinstance(schema, dict) or not schema:
        raise bad("schema", "a non-empty object of fields", schema)
    for k, v in schema.items():
        if not isinstance(v, dict):
            raise bad(f"schema.{k}", "an object with shape and dtype", v)
        shape = v.get("shape")
        if not isinstance(shape, list) or not all(_is_int(x) for x in shape):
            raise bad(f"schema.{k}.shape", "a list of integers >= 0", shape)
        try:
            np.dtype(v.get("dtype"))
        except TypeError:
            raise bad(f"schema.{k}.dtype", "a numpy dtype name", v.get("dtype")) from None
        if not isinstance(v.get("dtype"), str):
            raise bad(f"schema.{k}.dtype", "a numpy dtype name", v.get("dtype"))
    splits = m["splits"]
    if not isinstance(splits, dict):
        raise bad("splits", f"an object with keys {list(SPLITS)}", splits)
    for s in SPLITS:
        sp = splits.get(s)
        if not isinstance(sp, dict):
            raise bad(f"splits.{s}", "an object with units and shards", sp)
        units = sp.get("units")
        if not isinstance(units, list) or not all(_is_int(u) and u < n_units for u in units):
            raise bad(f"splits.{s}.units", f"a list of unit indices in [0, {n_units})", units)
        names = sp.get("shards")
        if not isinstance(names, list) or not all(_is_file_name(n) for n in names):
            raise bad(f"splits.{s}.shards", "a list of shard file names", names)
    shards = m["shards"]
    if not isinstance(shards, dict):
        raise bad("shards", "an object of shard name -> {split, units, samples, sha256}", shards)
    for name, info in shards.items():
        if not _is_file_name(name):
            raise bad("shards", "plain shard file names as keys", name)
        key = f"shards[{name!r}]"
        if not isinstance(info, dict):
            raise bad(key, "an object with split, units, samples and sha256", info)
        if info.get("split") not in SPLITS:
            raise bad(f"{key}.split", f"one of {list(SPLITS)}", info.get("split"))
        units = info.get("units")
        if not isinstance(units, list) or not all(_is_int(u) and u < n_units for u in units):
            raise bad(f"{key}.units", f"a list of unit indices in [0, {n_units})", units)
        if not _is_int(info.get("samples")):
            raise bad(f"{key}.samples", "an integer >= 0", info.get("samples"))
        digest = info.get("sha256")
        if not isinstance(digest, str) or not re.fullmatch(r"[0-9a-f]{64}", digest):
            raise bad(f"{key}.sha256", "64 lowercase hex digits", digest)
    counts = m["counts"]
    if not isinstance(counts, dict) or not all(_is_int(counts.get(s)) for s in SPLITS):
        raise bad("counts", f"an object of integers >= 0 for {list(SPLITS)}", counts)


#: (real path, device, inode, size, mtime_ns) -> sha256 of the shard, per process
_SHARD_DIGESTS: dict[tuple, str] = {}


def check_shard(path: str | os.PathLike, sha256: str) -> None:
    """Refuse a shard whose sha256 differs from the manifest's (:class:`DatasetError`).

    Readers call this when they open a shard. The digest is cached per file identity,
    size and modification time, so opening the same unchanged file again costs one
    ``stat``; a file changed since (a new mtime or size) is hashed again.
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as e:
        raise DatasetError(str(p), f"cannot open shard ({e.strerror or e})") from None
    key = (os.path.realpath(p), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    digest = _SHARD_DIGESTS.get(key)
    if digest is None:
        digest = _SHARD_DIGESTS[key] = sha256_file(p)
    if digest != sha256:
        raise DatasetError(
            str(p),
            "sha256 checksum differs from manifest.json (file changed or corrupt); "
            "run `epo generate` with the same options to regenerate it",
        )


def plan_problems(m: dict) -> list[tuple[str, str]]:
    """Where a (schema-checked) manifest disagrees with the plan of its own splits.

    The plan (:func:`plan_shards` of ``splits.<split>.units`` and ``units_per_shard``)
    gives every shard its split and units. Returns ``(manifest field, message)`` pairs:
    a unit in two splits or in none, a shard listed in another split than its own or in
    two, a listed shard that is not planned, a split that lists not exactly its planned
    shards in order, and a finished shard whose recorded split or units differ from the
    plan. Empty for a consistent manifest. :func:`verify` reports them all; readers
    (:class:`SplitReader`) refuse the first. A shard's messages name the shard, the split
    it belongs to and the split that lists it.
    """
    out: list[tuple[str, str]] = []
    seen: dict[int, str] = {}
    for s in SPLITS:
        for u in m["splits"][s]["units"]:
            if u in seen:
                out.append((f"splits.{s}", f"unit {u} is also in split {seen[u]}"))
            seen[u] = s
    if sorted(seen) != list(range(m["n_units"])):
        out.append(("splits", f"units do not cover 0..{m['n_units'] - 1} exactly once"))
    planned = _planned(m)
    for s in SPLITS:
        names = m["splits"][s]["shards"]
        where = f"splits.{s}.shards"
        bad, earlier = False, set()
        for n in names:
            p = planned.get(n)
            bad = True
            if p is None:
                out.append((where, f"shard {n!r} is not a planned shard of this dataset"))
            elif p["split"] != s:
                out.append(
                    (
                        where,
                        f"shard {n!r} belongs to split {p['split']!r} (units "
                        f"{_short(p['units'], 40)}), not to split {s!r}; a shard is listed "
                        "in exactly one split",
                    )
                )
            elif n in earlier:
                out.append((where, f"shard {n!r} is listed twice"))
            else:
                bad = False
                earlier.add(n)
            if bad:
                break
        want = [n for n, p in planned.items() if p["split"] == s]
        if not bad and names != want:
            missing = [n for n in want if n not in names]
            if missing:
                msg = f"planned shard {missing[0]!r} of split {s!r} is not listed"
            else:
                msg = f"expected the planned order {_short(want)}, got {_short(names)}"
            out.append((f"splits.{s}.shards", msg))
    for name, info in m["shards"].items():
        p = planned.get(name)
        key = f"shards[{name!r}]"
        if p is None:
            out.append((key, "not a planned shard"))
        elif info["split"] != p["split"]:
            out.append(
                (
                    f"{key}.split",
                    f"{info['split']!r}, but the shard belongs to split {p['split']!r}",
                )
            )
        elif info["units"] != p["units"]:
            out.append(
                (
                    f"{key}.units",
                    f"{_short(info['units'], 40)}, but the plan of split {p['split']!r} gives "
                    f"{_short(p['units'], 40)}",
                )
            )
    return out


def _text(v: Any) -> Any:
    """An HDF5 attribute as a plain Python value (text, int) where it is one."""
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.generic):
        return v.item()
    return v


def shard_problems(h, name: str, m: dict, plan: dict | None = None) -> list[tuple[str, str]]:
    """Where an open shard ``h`` (h5py) disagrees with its manifest ``m``.

    Checked, in this order: the shard's dataset identity (attributes ``dataset``,
    ``scenario``, ``seed``; :func:`dataset_digest`), its split and units (attributes
    ``split``, ``units``) against the plan (``plan``: its entry of :func:`plan_shards`),
    and every schema field's shape ``(samples, *shape)`` and dtype against the manifest's
    schema and the shard's recorded sample count. Returns ``(where, message)`` pairs,
    ``where`` the shard name or ``name.field``. A shard written before the identity was
    recorded (no ``dataset`` attribute) is checked by the rest only.
    """
    import h5py

    out: list[tuple[str, str]] = []
    plan = _planned(m).get(name) if plan is None else plan
    attrs = h.attrs
    scen, seed, ident = _text(attrs.get("scenario")), attrs.get("seed"), attrs.get("dataset")
    what = None
    if scen is not None and scen != m["scenario"]:
        what = f"scenario {_short(scen, 40)}, the manifest's {m['scenario']!r}"
    elif seed is not None and _text(seed) != m["seed"]:
        what = f"seed {_short(_text(seed), 40)}, the manifest's {m['seed']}"
    elif ident is not None and _text(ident) != dataset_digest(m):
        what = "another recipe than the manifest's"
    if what is not None:
        out.append(
            (
                name,
                f"belongs to another dataset ({what}); copy back this dataset's own shard, "
                "or regenerate it (epo generate with the same options)",
            )
        )
        return out
    if plan is not None:
        split = _text(attrs.get("split"))
        units = attrs.get("units")
        units = None if units is None else np.asarray(units).reshape(-1).tolist()
        if split is not None and split != plan["split"]:
            out.append(
                (
                    name,
                    f"holds samples of split {split!r} (units {_short(units, 40)}), but the "
                    f"manifest lists it in split {plan['split']!r}",
                )
            )
            return out
        if units is not None and units != plan["units"]:
            out.append(
                (
                    name,
                    f"holds units {_short(units, 40)}, the manifest plans units "
                    f"{_short(plan['units'], 40)} for it",
                )
            )
            return out
    samples = m["shards"].get(name, {}).get("samples")
    for k, v in m["schema"].items():
        shape, dtype = (samples, *v["shape"]), np.dtype(v["dtype"])
        ds = h.get(k)
        if not isinstance(ds, h5py.Dataset):
            out.append((f"{name}.{k}", "field missing (the manifest's schema has it)"))
            continue
        if ds.shape != shape or ds.dtype != dtype:
            out.append(
                (
                    f"{name}.{k}",
                    f"shape {ds.shape} {ds.dtype}, manifest says {shape} {dtype}",
                )
            )
    return out


# --------------------------------------------------------------------------------------
# generation
# --------------------------------------------------------------------------------------
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


def _new_manifest(scenario: Scenario, seed: int) -> dict:
    splits = scenario.split_units(seed)
    shards = plan_shards(splits, scenario.units_per_shard)
    return {
        "format_version": FORMAT_VERSION,
        "scenario": scenario.name,
        "recipe": scenario.recipe_dict(),
        "seed": int(seed),
        "n_units": int(scenario.n_units),
        "units_per_shard": int(scenario.units_per_shard),
        "schema": {k: v.to_dict() for k, v in scenario.schema().items()},
        "meta": scenario.meta(),
        "splits": {
            s: {"units": splits[s], "shards": [n for n, v in shards.items() if v["split"] == s]}
            for s in SPLITS
        },
        "shards": {},
        "counts": {s: 0 for s in SPLITS},
        "complete": False,
    }


def _planned(m: dict) -> dict[str, dict]:
    return plan_shards({s: m["splits"][s]["units"] for s in SPLITS}, m["units_per_shard"])


def _same_dataset(old: dict, new: dict) -> str | None:
    for key in ("scenario", "recipe", "seed", "n_units", "units_per_shard", "schema", "splits"):
        a, b = json.loads(json.dumps(old.get(key))), json.loads(json.dumps(new.get(key)))
        if a != b:
            if key == "recipe" and isinstance(a, dict) and isinstance(b, dict):
                # name every recipe field that differs (in the recipe's own order), so a
                # field that selects a kind of recipe is named beside what follows from it
                return "recipe " + recipe_difference(a, b).replace("; field", "; recipe field")
            return key
    return None


def _lock(directory: Path):
    """The folder's writer lock (:func:`scenarios.files.output_lock`)."""
    return output_lock(directory, "generation")


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
            procs = list((getattr(ex, "_processes", None) or {}).values())
            ex.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                with contextlib.suppress(Exception):
                    proc.terminate()
            for proc in procs:
                with contextlib.suppress(Exception):
                    proc.join(timeout=5)
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
    """Generate (or resume) ``scenario``'s dataset in ``out``; see the module docstring.

    ``engine``: ``"local"`` (process pool of ``workers``) or ``"dask"`` (``client``, a
    scheduler ``address``, or a new ``LocalCluster`` of ``workers`` processes).
    ``scheduler_timeout``: seconds to wait for the scheduler at ``address``; an
    unreachable one raises :class:`SpecError` (field ``scheduler``).
    Pool workers exit when this process dies, also by ``kill -9`` (:func:`_worker_init`);
    an interrupt or error stops the units in flight and keeps the finished shards.
    ``on_shard(name)`` runs after each shard is committed (tests use it to simulate a
    kill). Returns a :class:`GenerateReport`.
    """
    if engine not in ("local", "dask"):
        raise SpecError("engine", f"expected 'local' or 'dask', got {engine!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise SpecError("workers", f"expected an integer >= 1, got {workers!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SpecError("seed", f"expected an integer >= 0, got {seed!r}")
    t = scheduler_timeout
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0 < t < math.inf:
        raise SpecError("scheduler_timeout", f"expected a finite number > 0, got {t!r}")
    t0 = time.perf_counter()
    d = check_output_dir(out)
    if d.is_dir() and not (d / MANIFEST).exists() and any(x.name != ".lock" for x in d.iterdir()):
        raise DatasetError(
            str(d),
            "exists, is not empty and holds no manifest.json; choose a new or empty directory",
        )
    ensure_dir(d)
    schema = scenario.schema()
    with _lock(d):
        new = _new_manifest(scenario, int(seed))
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
        identity = dataset_digest(m)
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

        todo_shards = [n for n in planned if n not in m["shards"]]
        unit_to_shard = {u: n for n in todo_shards for u in planned[n]["units"]}
        units = [u for n in todo_shards for u in planned[n]["units"]]
        results: dict[int, dict] = {}
        written: list[str] = []
        secs: list[float] = []
        n_samples = 0
        bar = it = None
        order = {n: j for j, n in enumerate(planned)}
        if progress:
            from tqdm import tqdm

            bar = tqdm(
                total=len(units), unit="game", desc=f"{scenario.name} -> {d}", dynamic_ncols=True
            )
        try:
            if engine == "local":
                it = _iter_local(scenario, units, int(seed), workers)
            else:
                it = _iter_dask(scenario, units, int(seed), workers, client, address, float(t))
            t_start = time.perf_counter()
            for index, arrays, dt in it:
                results[index] = arrays
                secs.append(dt)
                n_samples += len(next(iter(arrays.values()))) if arrays else 0
                if bar is not None:
                    el = time.perf_counter() - t_start
                    bar.update(1)
                    bar.set_postfix(
                        samples=n_samples, rate=f"{n_samples / max(el, 1e-9):.1f} samples/s"
                    )
                name = unit_to_shard[index]
                sunits = planned[name]["units"]
                if all(u in results for u in sunits):
                    n, digest = write_shard(
                        d / name,
                        scenario.name,
                        planned[name]["split"],
                        sunits,
                        schema,
                        [results.pop(u) for u in sunits],
                        dataset=identity,
                        seed=m["seed"],
                    )
                    m["shards"][name] = {
                        "split": planned[name]["split"],
                        "units": sunits,
                        "samples": n,
                        "sha256": digest,
                    }
                    m["shards"] = dict(sorted(m["shards"].items(), key=lambda kv: order[kv[0]]))
                    _recount(m, planned)
                    _write_json(mpath, m)
                    written.append(name)
                    if on_shard is not None:
                        on_shard(name)
        finally:
            if it is not None:
                it.close()  # shuts the pool or the cluster down, also after an error
            if bar is not None:
                bar.close()
        return GenerateReport(
            str(d),
            dict(m["counts"]),
            written,
            kept,
            len(secs),
            sum(m["shards"][n]["samples"] for n in written),
            time.perf_counter() - t0,
            secs,
        )


def _shard_fits(path: Path, name: str, m: dict, plan: dict) -> bool:
    """Whether a finished shard is this dataset's (:func:`shard_problems` finds nothing)."""
    import h5py

    try:
        with h5py.File(path, "r") as h:
            return not shard_problems(h, name, m, plan)
    except (OSError, ValueError, TypeError, KeyError):
        return False


def _recount(m: dict, planned: dict) -> None:
    m["counts"] = {
        s: sum(v["samples"] for v in m["shards"].values() if v["split"] == s) for s in SPLITS
    }
    m["complete"] = all(n in m["shards"] for n in planned)


# --------------------------------------------------------------------------------------
# verification
# --------------------------------------------------------------------------------------
@dataclass
class VerifyReport:
    """Outcome of :func:`verify`: ``ok`` and one line per problem found."""

    directory: str
    counts: dict[str, int]
    shards: int
    problems: list[str]

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        c = ", ".join(f"{s} {self.counts.get(s, 0)}" for s in SPLITS)
        if self.ok:
            return f"ok: {self.directory}: {self.shards} shards, {sum(self.counts.values())} samples ({c})"
        return f"{len(self.problems)} problem(s) in {self.directory}: " + "; ".join(self.problems)


def verify(directory: str | os.PathLike, checksums: bool = True) -> VerifyReport:
    """Check a dataset: manifest, completeness, checksums, shapes, counts, disjoint splits.

    The manifest must agree with the plan of its own splits (:func:`plan_problems`: each
    shard listed in exactly its own split, with the planned units), and every shard file
    with the manifest (:func:`shard_problems`: the dataset it belongs to, its split and
    units, the shape and dtype of every field). Raises :class:`DatasetError` only when the
    manifest itself is missing, unreadable or malformed (:func:`check_manifest`); every
    other problem becomes one line of :attr:`VerifyReport.problems`.
    """
    import h5py

    d = Path(directory)
    m = read_manifest(d)
    problems = [f"{where}: {msg}" for where, msg in plan_problems(m)]
    planned = _planned(m)
    if not m["complete"]:
        missing = [n for n in planned if n not in m["shards"]]
        problems.append(
            f"manifest.complete: generation unfinished, {len(missing)} shard(s) missing (run generate again to resume)"
        )
    counts = {s: 0 for s in SPLITS}
    for name, info in m["shards"].items():
        f = d / name
        if name not in planned:
            continue  # reported by plan_problems
        # a bad file is reported once; its manifest count stands in for the totals below
        counts[planned[name]["split"]] += info["samples"]
        if not f.is_file():
            problems.append(f"{name}: file missing")
            continue
        if checksums and sha256_file(f) != info["sha256"]:
            problems.append(f"{name}: sha256 checksum mismatch (file changed or corrupt)")
            continue
        try:
            with h5py.File(f, "r") as h:
                found = shard_problems(h, name, m, planned[name])
                problems += [f"{where}: {msg}" for where, msg in found]
                units = planned[name]["units"]
                if not found and "main_game" in h and info["samples"]:
                    ids = set(np.unique(h["main_game"][()]).tolist())
                    if not ids <= set(units):
                        problems.append(f"{name}.main_game: samples from units outside this shard")
        except (OSError, ValueError, TypeError, KeyError) as e:
            problems.append(f"{name}: unreadable HDF5 file ({type(e).__name__}: {e})")
    for s in SPLITS:
        if counts[s] != m["counts"].get(s):
            problems.append(
                f"counts.{s}: manifest says {m['counts'].get(s)}, its shards hold {counts[s]}"
            )
    return VerifyReport(str(d), counts, len(m["shards"]), problems)


# --------------------------------------------------------------------------------------
# loading
# --------------------------------------------------------------------------------------
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
