"""Scene batches for training and evaluation, read from a dataset directory.

A dataset directory is the one :mod:`scenarios.dataset` writes (``manifest.json`` plus
HDF5 shards). :class:`SceneDataset` reads one split of it:

- small splits (below ``memory_limit_mb``, e.g. the full RPI set at ~1 KB per sample)
  are read whole into memory once (:meth:`scenarios.dataset.SplitReader.read_all`, one
  ``read_direct`` per shard and field); larger ones are read batch by batch
  (:meth:`~scenarios.dataset.SplitReader.read`, one fancy-indexed read per shard and field).
  Never one file access per sample.
- :meth:`SceneDataset.batches` yields collated batches (dicts of torch tensors) in a
  fixed order, or in the permutation of ``(seed, epoch)``: the order of an epoch does
  not depend on any RNG state, so a resumed training run sees the same batches.

A batch (``B`` samples, ``N`` agents, ``H+1`` history steps, ``T`` future steps)::

    history        (B, H+1, N, 4) float32   states (x, y, v, theta), last = current
    goals          (B, N, 2)      float32   goal positions (if the dataset has them)
    goal_candidates (B, N, G, 2)  float32   candidate goal points (if the dataset has them)
    lanes          (B, L, P, 2)   float32   lane polylines, the map input (if stored)
    lanes_mask     (B, L)         bool      False: an empty lane slot (if stored; Waymo)
    paths          (B, N, P, 2)   float32   each agent's reference lane (game ``path``; if stored)
    vref           (B, N)         float32   each agent's reference speed (game ``vref``; if stored)
    radius         (B, N)         float32   each agent's collision radius (game ``radius``; if stored)
    length, width  (B, N)         float32   vehicle size, metres (exiD layout; if stored)
    goal_lane      (B, N, G)      int64     per goal candidate the index in ``lanes`` of the
                                            lane it lies on, -1 off every lane (see below)
    history_valid  (B, H+1)       bool      False: extrapolated (all True if not stored)
    agents_mask    (B, N)         bool      False: a padded agent slot (all True if not stored)
    gt             (B, N, T, 2)   float32   ground-truth future positions
    gt_states      (B, N, T, 4)   float32   ground-truth future states
    index          (B,)           int64     sample indices in the split

``history``, ``goals`` and ``goal_candidates`` are the scene dict the models of
:mod:`learning.models` read. Only ``history`` and ``future`` are required: a dataset
without ``goals`` suits ours with a goal decoder (``goal_decoder="candidates"`` or
``"regress"``) and the baselines.
The ground truth is chosen by :func:`ground_truth`, the one place that knows how.

``agents_mask`` (dataset field ``(N,)`` bool, e.g. the readers of :mod:`scenarios.real`):
a scene with fewer than ``N`` recorded agents is padded, and its padded slots are False.
The batch always carries it (all True for a dataset without the field); the models,
losses and metrics mask the padded agents (:mod:`learning.masks`).

``goal_lane`` is derived from the exiD layout's ``goal_candidate_lane`` (0 left, 1 current,
2 right) and ``goal_candidate_on_lane`` when ``lanes`` holds each agent's three lanes in a
row (``L = 3 N``: agent ``i``'s at ``3 i .. 3 i + 2``): candidate ``g`` of agent ``i`` lies
on ``lanes[3 i + goal_candidate_lane[i, g]]``, and a candidate on a lane boundary (no
neighbouring lane) on none (-1). Ours uses it to give each mode the reference lane of its
goal (the paper's ``c_lane``; :class:`learning.models.ModelConfig` ``lane_path``).

The game a model needs for a dataset (agents, horizon, parameter layout) is built from
the manifest's scenario and recipe by :func:`dataset_game`.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

import numpy as np
import torch

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame
from scenarios.dataset import (
    MANIFEST,
    DatasetError,
    SplitReader,
    as_indices,
    check_index,
    read_manifest,
)

__all__ = [
    "REQUIRED_FIELDS",
    "SceneDataset",
    "dataset_game",
    "game_summary",
    "goal_lanes",
    "ground_truth",
]

#: fields training and evaluation cannot do without
REQUIRED_FIELDS = ("history", "future")
#: fields used when present
#: ``lanes``/``paths``/``vref``: map input and fixed game references (left-turn datasets)
OPTIONAL_FIELDS = (
    "goals",
    "goal_candidates",
    "history_valid",
    "gt_mode",
    "lanes",
    "paths",
    "vref",
    "radius",
    "length",
    "width",
    "goal_candidate_lane",
    "goal_candidate_on_lane",
    "agents_mask",
    "lanes_mask",
)
#: the optional fields a batch carries as float32 arrays (``history_valid``,
#: ``agents_mask`` and ``lanes_mask`` become masks, ``gt_mode`` selects the ground truth, the
#: ``goal_candidate_*`` ones become ``goal_lane``)
FLOAT_FIELDS = tuple(
    k
    for k in OPTIONAL_FIELDS
    if k
    not in (
        "history_valid",
        "agents_mask",
        "lanes_mask",
        "gt_mode",
        "goal_candidate_lane",
        "goal_candidate_on_lane",
    )
)


def goal_lanes(
    candidate_lane: np.ndarray, on_lane: np.ndarray | None, n_lanes: int
) -> np.ndarray | None:
    """``goal_lane`` ``(B, N, G)`` (int64) of the exiD layout (module docstring), or None
    when ``lanes`` does not hold three lanes per agent (``n_lanes != 3 N``)."""
    B, N, G = candidate_lane.shape
    if n_lanes != 3 * N:
        return None
    c = candidate_lane.astype(np.int64)
    idx = 3 * np.arange(N, dtype=np.int64)[None, :, None] + c
    bad = (c < 0) | (c > 2)
    if on_lane is not None:
        bad |= ~on_lane.astype(bool)
    return np.where(bad, -1, idx)


def ground_truth(future, gt_mode=None):
    """Ground-truth future of each sample: ``future[b, gt_mode[b]]``, or mode 0 without ``gt_mode``.

    ``future`` ``(B, M, N, T, nx)`` (numpy or torch), ``gt_mode`` ``(B,)`` integer mode
    indices (the subgame mode the agents actually follow) or ``None`` (datasets written
    before the field existed: the first mode). Returns ``(B, N, T, nx)``.
    """
    if gt_mode is None:
        return future[:, 0]
    if isinstance(future, torch.Tensor):
        idx = torch.as_tensor(gt_mode, dtype=torch.long, device=future.device)
        return future[torch.arange(future.shape[0], device=future.device), idx]
    idx = np.asarray(gt_mode).astype(np.int64)
    M = future.shape[1]
    if idx.size and (idx.min() < 0 or idx.max() >= M):
        bad = int(idx[(idx < 0) | (idx >= M)][0])
        raise DatasetError("gt_mode", f"expected a mode index in [0, {M}), got {bad}")
    return future[np.arange(future.shape[0]), idx]


# --------------------------------------------------------------------------------------
# games of datasets
# --------------------------------------------------------------------------------------
def _rpi_game(recipe: dict) -> PotentialGame:
    from scenarios.rpi import RPIRecipe, RPIScenario

    return RPIScenario(RPIRecipe.from_dict(recipe)).game


#: scenario name (manifest ``scenario``) -> builder of its game from the manifest recipe
def _left_turn_game(recipe: dict) -> PotentialGame:
    from scenarios.left_turn import LeftTurnRecipe, LeftTurnScenario

    return LeftTurnScenario(LeftTurnRecipe.from_dict(recipe)).game


def _exid_game(recipe: dict) -> PotentialGame:
    from scenarios.exid import ExidRecipe, ExidScenario

    # datasets written before radius_per_agent existed had one fixed radius in their game
    recipe = {"radius_per_agent": False, **recipe}
    return ExidScenario(ExidRecipe.from_dict(recipe)).game


#: (or its ``"module:function"`` path, imported on first use: the readers of recorded data)
GAME_BUILDERS: dict[str, Callable[[dict], PotentialGame] | str] = {
    "rpi": _rpi_game,
    "left-turn": _left_turn_game,
    "exid": _exid_game,
    "eth-ucy": "scenarios.real.eth_ucy:game_from_recipe",
    "vci": "scenarios.real.vci:game_from_recipe",
    "waymo": "scenarios.real.waymo:game_from_recipe",
}


@functools.lru_cache(maxsize=8)
def _cached_game(scenario: str, recipe_json: str) -> PotentialGame:
    build = GAME_BUILDERS[scenario]
    if isinstance(build, str):
        from epo_casadi.registry import load_class

        build = GAME_BUILDERS[scenario] = load_class(build, f"{MANIFEST}.scenario")
    return build(json.loads(recipe_json))


def dataset_game(directory_or_manifest: str | os.PathLike | Mapping) -> PotentialGame:
    """The game of a dataset (from its manifest's scenario and recipe; built once per process).

    A model trained or evaluated on the dataset needs this game: the game layer solves
    it and its agents, horizon and parameter layout size the decoders.
    """
    m = (
        directory_or_manifest
        if isinstance(directory_or_manifest, Mapping)
        else read_manifest(directory_or_manifest)
    )
    name = m.get("scenario")
    if name not in GAME_BUILDERS:
        raise DatasetError(
            f"{MANIFEST}.scenario",
            f"no game known for scenario {name!r}; known: {sorted(GAME_BUILDERS)}",
        )
    return _cached_game(name, json.dumps(m["recipe"], sort_keys=True))


def game_summary(game: PotentialGame) -> dict:
    """What a trained model depends on: agents, horizon, step, parameter names, radii."""
    return {
        "agents": list(game.agent_names),
        "horizon": int(game.K),
        "dt": float(game.dt),
        "param_names": list(game.params.names),
        "radii": [float(a.radius) for a in game.agents],
    }


def dataset_fingerprint(manifest: Mapping) -> dict:
    """Identity of a dataset: scenario, recipe and seed (generation is deterministic: equal ones hold the same samples)."""
    return {k: manifest.get(k) for k in ("scenario", "recipe", "seed")}


# --------------------------------------------------------------------------------------
# the dataset
# --------------------------------------------------------------------------------------
class SceneDataset(torch.utils.data.Dataset):
    """One split of a dataset directory as scene batches (see the module docstring).

    ``in_memory``: ``True`` reads the split once, ``False`` reads per batch, ``None``
    (default) decides by size against ``memory_limit_mb``. Errors name the field: a
    missing directory or manifest (:class:`~scenarios.dataset.DatasetError`), an unknown
    split (:class:`~epo_casadi.errors.SpecError` ``split``), a missing or misshaped field
    (``DatasetError`` ``manifest.json.schema.<field>``).
    """

    def __init__(
        self,
        directory: str | os.PathLike,
        split: str,
        in_memory: bool | None = None,
        memory_limit_mb: float = 1024.0,
    ):
        self.directory = Path(directory)
        self.split = split
        m = read_manifest(self.directory)
        schema = m["schema"]
        where = str(self.directory / MANIFEST)
        for k in REQUIRED_FIELDS:
            if k not in schema:
                raise DatasetError(
                    f"{where}.schema.{k}",
                    f"missing; training and evaluation need the fields {list(REQUIRED_FIELDS)}",
                )
        shape = {k: tuple(v["shape"]) for k, v in schema.items()}
        hs, fs = shape["history"], shape["future"]
        if len(hs) != 3 or hs[2] != 4:
            raise DatasetError(f"{where}.schema.history", f"expected shape (H+1, N, 4), got {hs}")
        N = hs[1]
        if "goals" in shape and shape["goals"] != (N, 2):
            raise DatasetError(
                f"{where}.schema.goals", f"expected shape ({N}, 2), got {shape['goals']}"
            )
        gc = shape.get("goal_candidates")
        if gc is not None and (len(gc) != 3 or gc[0] != N or gc[2] != 2 or gc[1] < 1):
            raise DatasetError(
                f"{where}.schema.goal_candidates", f"expected shape ({N}, G, 2), got {gc}"
            )
        if "agents_mask" in shape:
            if shape["agents_mask"] != (N,):
                raise DatasetError(
                    f"{where}.schema.agents_mask",
                    f"expected shape ({N},), got {shape['agents_mask']}",
                )
            if np.dtype(schema["agents_mask"]["dtype"]) != np.dtype(bool):
                raise DatasetError(
                    f"{where}.schema.agents_mask",
                    f"expected dtype bool, got {schema['agents_mask']['dtype']}",
                )
        if "lanes_mask" in shape:
            L = shape["lanes"][0] if "lanes" in shape else None
            if len(shape["lanes_mask"]) != 1 or (L is not None and shape["lanes_mask"] != (L,)):
                raise DatasetError(
                    f"{where}.schema.lanes_mask",
                    f"expected shape ({'L' if L is None else L},) (one flag per lane of "
                    f"lanes), got {shape['lanes_mask']}",
                )
            if np.dtype(schema["lanes_mask"]["dtype"]) != np.dtype(bool):
                raise DatasetError(
                    f"{where}.schema.lanes_mask",
                    f"expected dtype bool, got {schema['lanes_mask']['dtype']}",
                )
        if len(fs) != 4 or fs[1] != N or fs[3] < 2:
            raise DatasetError(
                f"{where}.schema.future", f"expected shape (M, {N}, T, nx), got {fs}"
            )
        self.manifest = m
        self.n_agents, self.history_steps = N, hs[0]
        self.modes, self.horizon = fs[0], fs[2]
        self.fields = list(REQUIRED_FIELDS) + [k for k in OPTIONAL_FIELDS if k in schema]
        self.reader = SplitReader(self.directory, split, fields=self.fields)
        per_sample = sum(
            int(np.prod(shape[k])) * np.dtype(schema[k]["dtype"]).itemsize for k in self.fields
        )
        if in_memory is None:
            in_memory = per_sample * len(self.reader) <= memory_limit_mb * 2**20
        self.in_memory = bool(in_memory)
        self._arrays: dict[str, np.ndarray] | None = None
        if self.in_memory:
            self._arrays = self._prepare(self.reader.read_all())
            self.reader.close()

    # ---- facts ---------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.reader)

    @property
    def game(self) -> PotentialGame:
        """The dataset's game (:func:`dataset_game`); checked against the stored shapes."""
        g = dataset_game(self.manifest)
        if g.N != self.n_agents or g.K != self.horizon:
            raise DatasetError(
                f"{self.directory / MANIFEST}.recipe",
                f"its game has {g.N} agents and horizon {g.K}, the samples {self.n_agents} "
                f"agents and {self.horizon} future steps",
            )
        return g

    @property
    def fingerprint(self) -> dict:
        return dataset_fingerprint(self.manifest)

    # ---- reading -------------------------------------------------------------------------
    def _prepare(self, raw: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        gt = ground_truth(raw["future"], raw.get("gt_mode"))
        n = raw["history"].shape[0]
        valid = raw.get("history_valid")
        if valid is None:
            valid = np.ones((n, self.history_steps), bool)
        out = {"history": np.ascontiguousarray(raw["history"], np.float32)}
        for k in FLOAT_FIELDS:
            if k in raw:
                out[k] = np.ascontiguousarray(raw[k], np.float32)
        out["history_valid"] = np.ascontiguousarray(valid, bool)
        agents = raw.get("agents_mask")
        if agents is None:
            agents = np.ones((n, self.n_agents), bool)
        out["agents_mask"] = np.ascontiguousarray(agents, bool)
        if "lanes_mask" in raw:
            out["lanes_mask"] = np.ascontiguousarray(raw["lanes_mask"], bool)
        if "goal_candidate_lane" in raw and "lanes" in raw:
            gl = goal_lanes(
                raw["goal_candidate_lane"], raw.get("goal_candidate_on_lane"), raw["lanes"].shape[1]
            )
            if gl is not None:
                out["goal_lane"] = gl
        out["gt_states"] = np.ascontiguousarray(gt, np.float32)
        return out

    def scalar_fields(self) -> list[str]:
        """The dataset's numeric fields of one number per sample (shape ``()``), e.g.
        ``min_distance``: the fields :meth:`sample_field` reads (and ``--subset`` compares)."""
        out = []
        for k, v in self.manifest["schema"].items():
            dt = np.dtype(v["dtype"])
            if tuple(v["shape"]) == () and (dt.kind in "iuf" or dt == np.dtype(bool)):
                out.append(k)
        return out

    def sample_field(self, name: str) -> np.ndarray:
        """The values ``(n,)`` of the scalar per-sample field ``name`` over the split, in
        sample order, read from the shards for this call only (batches do not carry it). A
        field that is not stored, or not one number per sample, is refused naming it
        (:class:`~epo_casadi.errors.SpecError` ``field``) with the fields there are."""
        scalars = self.scalar_fields()
        if name not in scalars:
            schema = self.manifest["schema"]
            why = (
                f"not one number per sample (shape {tuple(schema[name]['shape'])}, dtype "
                f"{schema[name]['dtype']})"
                if name in schema
                else f"not a field of {self.directory}"
            )
            raise SpecError("field", f"{name!r} is {why}; the scalar per-sample fields: {scalars}")
        with SplitReader(self.directory, self.split, fields=[name]) as r:
            return r.read_all()[name]

    def read(self, indices) -> dict[str, np.ndarray]:
        """Numpy arrays of the samples ``indices`` (any order): the batch fields but ``index``."""
        idx = as_indices(indices, len(self), self.split)  # as in SplitReader
        if self._arrays is not None:
            return {k: v[idx] for k, v in self._arrays.items()}
        return self._prepare(self.reader.read(idx))

    def batch(self, indices) -> dict[str, torch.Tensor]:
        """Collated batch (see the module docstring) of the samples ``indices``."""
        idx = as_indices(indices, len(self), self.split)
        a = self.read(idx)
        out = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in a.items()}
        out["gt"] = out["gt_states"][..., :2]
        out["index"] = torch.from_numpy(idx.copy())
        return out

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        """One sample (no batch axis); prefer :meth:`batches` for speed."""
        i = check_index(i, len(self), self.split)
        return {k: v[0] for k, v in self.batch([i]).items()}

    def order(self, shuffle: bool = False, seed: int = 0, epoch: int = 0) -> np.ndarray:
        """Sample order of an epoch: ``0..n-1``, or the permutation drawn from ``(seed, epoch)``."""
        n = len(self)
        if not shuffle:
            return np.arange(n, dtype=np.int64)
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(2, int(epoch))))
        return rng.permutation(n).astype(np.int64)

    def num_batches(self, batch_size: int) -> int:
        return -(-len(self) // int(batch_size))

    def batches(
        self,
        batch_size: int,
        shuffle: bool = False,
        seed: int = 0,
        epoch: int = 0,
        start: int = 0,
    ) -> Iterator[dict[str, torch.Tensor]]:
        """Batches of ``batch_size`` (the last may be smaller), from batch number ``start`` on."""
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise SpecError("batch_size", f"expected an integer >= 1, got {batch_size!r}")
        order = self.order(shuffle, seed, epoch)
        for b in range(int(start), self.num_batches(batch_size)):
            yield self.batch(order[b * batch_size : (b + 1) * batch_size])

    def close(self) -> None:
        self.reader.close()

    def __enter__(self) -> SceneDataset:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
