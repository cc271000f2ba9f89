"""Shard files: writing one atomically, its checksum, and whether an open shard belongs to
its manifest (:mod:`scenarios.dataset`, "Shards", "Crash safety" and "Checks on read")."""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..files import write_atomic
from .manifest import _planned, _short, dataset_digest
from .scenario import CHUNK_ROWS, FORMAT_VERSION, DatasetError, FieldSpec


def sha256_file(path: str | os.PathLike, block: int = 1 << 20) -> str:
    """The sha256 of the file at ``path`` (hex), read ``block`` bytes at a time."""
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
        return [
            (
                name,
                f"belongs to another dataset ({what}); copy back this dataset's own shard, "
                "or regenerate it (epo generate with the same options)",
            )
        ]
    if plan is not None:
        split = _text(attrs.get("split"))
        units = attrs.get("units")
        units = None if units is None else np.asarray(units).reshape(-1).tolist()
        if split is not None and split != plan["split"]:
            return [
                (
                    name,
                    f"holds samples of split {split!r} (units {_short(units, 40)}), but the "
                    f"manifest lists it in split {plan['split']!r}",
                )
            ]
        if units is not None and units != plan["units"]:
            return [
                (
                    name,
                    f"holds units {_short(units, 40)}, the manifest plans units "
                    f"{_short(plan['units'], 40)} for it",
                )
            ]
    samples = m["shards"].get(name, {}).get("samples")
    out: list[tuple[str, str]] = []
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


def _shard_fits(path: Path, name: str, m: dict, plan: dict) -> bool:
    """Whether a finished shard is this dataset's (:func:`shard_problems` finds nothing)."""
    import h5py

    try:
        with h5py.File(path, "r") as h:
            return not shard_problems(h, name, m, plan)
    except (OSError, ValueError, TypeError, KeyError):
        return False
