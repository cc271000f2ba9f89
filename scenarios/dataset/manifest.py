"""The manifest: its schema check, its identity, and its agreement with the plan of its
splits (:mod:`scenarios.dataset`, "Manifest")."""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from epo_casadi.errors import SpecError

from ..files import check_input_file, recipe_difference, write_atomic
from .scenario import FORMAT_VERSION, MANIFEST, SPLITS, DatasetError, Scenario, plan_shards


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
    """Check the manifest's schema (:mod:`scenarios.dataset`); :class:`DatasetError` names
    the field.

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


def _recount(m: dict, planned: dict) -> None:
    m["counts"] = {
        s: sum(v["samples"] for v in m["shards"].values() if v["split"] == s) for s in SPLITS
    }
    m["complete"] = all(n in m["shards"] for n in planned)
