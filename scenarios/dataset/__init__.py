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

from epo_casadi.errors import SpecError as SpecError  # the error of bad arguments

from ..files import sigterm_as_interrupt
from .engine import run_unit
from .generation import GenerateReport, check_output_dir, generate
from .manifest import check_manifest, dataset_digest, plan_problems, read_manifest
from .reader import SplitReader, as_indices, check_index, check_indices, load_split
from .scenario import (
    CHUNK_ROWS,
    FORMAT_VERSION,
    MANIFEST,
    SPLITS,
    DatasetError,
    FieldSpec,
    RawScenario,
    Scenario,
    assign_splits,
    plan_shards,
    split_sizes,
    stack_rows,
    unit_seed,
)
from .shards import check_shard, fsync_replace, sha256_file, shard_problems, write_shard
from .verification import VerifyReport, verify

__all__ = [
    "FORMAT_VERSION",
    "SPLITS",
    "MANIFEST",
    "CHUNK_ROWS",
    "DatasetError",
    "FieldSpec",
    "RawScenario",
    "Scenario",
    "GenerateReport",
    "VerifyReport",
    "SplitReader",
    "generate",
    "verify",
    "load_split",
    "read_manifest",
    "unit_seed",
    "split_sizes",
    "stack_rows",
    "assign_splits",
    "run_unit",
    "sha256_file",
    "fsync_replace",
    "write_shard",
    "check_manifest",
    "check_shard",
    "check_index",
    "check_indices",
    "as_indices",
    "plan_problems",
    "shard_problems",
    "dataset_digest",
    "plan_shards",
    "check_output_dir",
    "sigterm_as_interrupt",
]
