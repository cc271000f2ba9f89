"""The dataset scenario interface: work units, their seeds, the split assignment and the
shard plan (:mod:`scenarios.dataset`, "Work units and seeds" and "Shards")."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from epo_casadi.errors import EpoError, SpecError

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


class RawScenario(Scenario):
    """A scenario read from a folder of recorded files (exiD, ETH/UCY, CITR): its recipe (an
    instance of :attr:`recipe_class`; default: the class's defaults) and the folder ``raw``
    the recipe was made from (:meth:`from_raw` of the subclass). Only these two go to a
    worker process."""

    pickled = ("recipe", "raw")
    #: the recipe dataclass of the scenario
    recipe_class: type = object

    def __init__(self, recipe=None, raw: str | os.PathLike | None = None):
        cls = self.recipe_class
        if recipe is not None and not isinstance(recipe, cls):
            raise SpecError("recipe", f"expected {cls.__name__}, got {type(recipe).__name__}")
        self.recipe = recipe or cls()
        self.raw = None if raw is None else Path(raw)


def stack_rows(rows: Sequence[dict], schema: dict[str, FieldSpec]) -> dict[str, np.ndarray]:
    """The samples ``(n, ...)`` of a work unit from its ``n`` per-sample dicts: every schema
    field stacked and cast to the field's dtype (empty arrays of the field's shape when
    ``rows`` is empty)."""
    if not rows:
        return {k: np.zeros((0, *fs.shape), fs.dtype) for k, fs in schema.items()}
    return {
        k: np.stack([np.asarray(row[k]) for row in rows]).astype(fs.dtype)
        for k, fs in schema.items()
    }


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
