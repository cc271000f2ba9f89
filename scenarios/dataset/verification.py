"""Verifying a dataset: every check of the manifest and its shards, every problem one line
(:mod:`scenarios.dataset`, "Checks on read")."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .manifest import _planned, plan_problems, read_manifest
from .scenario import SPLITS
from .shards import sha256_file, shard_problems


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
