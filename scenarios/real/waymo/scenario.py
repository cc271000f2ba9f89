"""The Waymo dataset scenario (:class:`WaymoScenario`): planning the work units (one per kept
pair) from the files, the splits by scenario, the schema and meta, and the cut of one pair's
sample (window, states, lanes, goal candidates; the rules are in :mod:`scenarios.real.waymo`)."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from epo_casadi.errors import SpecError

from ...dataset import SPLITS, DatasetError, FieldSpec, Scenario
from ..scenes import (
    Track,
    closest_approach,
    crowd_game_spec,
    scene_schema,
    select_agents,
    stack_scenes,
    window_scenes,
)
from ..tfrecord import read_record
from ..waymo_schema import OBJECT_TYPES
from .maps import _distance_to_pieces, goal_candidates, goal_pool, lane_pieces
from .pairs import _scan
from .recipe import WaymoRecipe
from .records import MPH, ScenarioRecord, _records, find_files, parse_scenario


@dataclass(frozen=True)
class _Unit:
    scenario: int  #: index into WaymoScenario.scenarios
    tracks: tuple[int, int]  #: the pair's track indices, slot order


@dataclass(frozen=True)
class _Source:
    file: int  #: index into WaymoScenario.paths
    index: int  #: record index in the file
    offset: int
    scenario_id: str


class WaymoScenario(Scenario):
    """Samples of Waymo Open Motion records (module docstring); one work unit per pair."""

    name = "waymo"
    pickled = ("recipe", "paths", "scenarios", "units", "skipped")

    def __init__(
        self,
        recipe: WaymoRecipe | None = None,
        paths: Sequence[str] = (),
        scenarios: Sequence[_Source] = (),
        units: Sequence[_Unit] = (),
        skipped: dict | None = None,
    ):
        if recipe is not None and not isinstance(recipe, WaymoRecipe):
            raise SpecError("recipe", f"expected a WaymoRecipe, got {type(recipe).__name__}")
        self.recipe = recipe or WaymoRecipe()
        self.paths = tuple(str(p) for p in paths)
        self.scenarios = tuple(scenarios)
        self.units = tuple(units)
        self.skipped = dict(skipped or {})

    @classmethod
    def from_raw(
        cls,
        raw: Sequence[str | os.PathLike],
        val: Sequence[str | os.PathLike] = (),
        test: Sequence[str | os.PathLike] = (),
        **overrides,
    ) -> WaymoScenario:
        """The scenario of every record in the files (or folders) ``raw`` (train), ``val``
        and ``test``; ``overrides`` are recipe fields."""
        for k in ("files", "raw_digest"):
            if k in overrides:
                raise SpecError(f"--set {k}", "is read from --raw, --val and --test")
        recipe = WaymoRecipe.from_dict(overrides)
        tagged: list[tuple[Path, str]] = []
        for option, split, given in (
            ("--raw", "train", raw),
            ("--val", "val", val),
            ("--test", "test", test),
        ):
            if given:
                tagged += [(p, split) for p in find_files(given, option)]
        if not tagged:
            raise SpecError("--raw", "expected at least one TFRecord file")
        keys = [os.path.realpath(p) for p, _ in tagged]
        if len(set(keys)) != len(keys):
            dup = next(p for (p, _), k in zip(tagged, keys, strict=True) if keys.count(k) > 1)
            raise SpecError("--raw", f"{dup} is given twice (in --raw, --val or --test)")
        h = hashlib.sha256()
        sources, units = [], []
        skipped = {"type": 0, "invalid": 0, "no pair": 0}
        for fi, (path, split) in enumerate(tagged):
            h.update(f"{path.name}\0{split}\0{path.stat().st_size}\0".encode())
            for rec in _records(path):
                where = f"{path}:record {rec.index}"
                sid, pairs, sk = _scan(recipe, rec.payload, where)
                for k, v in sk.items():
                    skipped[k] += v
                h.update(f"{rec.offset}\0{sid}\0{pairs}\0".encode())
                if pairs:
                    units += [_Unit(len(sources), tuple(int(t) for t in pr)) for pr in pairs]
                    sources.append(_Source(fi, rec.index, rec.offset, sid))
        if not units:
            raise DatasetError(
                "--raw",
                f"no pair to make a sample of in {len(tagged)} file(s): {skipped['no pair']} "
                "record(s) list fewer than "
                f"two agents, {skipped['type']} pair(s) of other types than {list(recipe.types)}, "
                f"{skipped['invalid']} with invalid steps in the window",
            )
        recipe = dataclasses.replace(
            recipe,
            files=tuple((p.name, s) for p, s in tagged),
            raw_digest=h.hexdigest(),
        )
        return cls(recipe, [os.path.abspath(p) for p, _ in tagged], sources, units, skipped)

    # ---- Scenario interface ----------------------------------------------------------
    @property
    def n_units(self) -> int:
        return len(self.units)

    @property
    def units_per_shard(self) -> int:
        return 64

    def scenario_splits(self, seed: int) -> dict[str, list[int]]:
        """Split -> scenario indices (the module docstring, "Splits")."""
        r = self.recipe
        tags = [r.files[s.file][1] for s in self.scenarios]
        by = {s: [i for i, t in enumerate(tags) if t == s] for s in SPLITS}
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0,)))
        given = {t for _, t in r.files}
        train = list(by["train"])
        if "test" not in given and train:
            nt = min(max(1, round(r.test_fraction * len(train))), len(train) - 1)
            pick = set(rng.permutation(len(train))[:nt].tolist()) if nt > 0 else set()
            by["test"] = sorted(train[j] for j in pick)
            train = [u for j, u in enumerate(train) if j not in pick]
        if "val" not in given and r.val_fraction > 0 and len(train) >= 3:
            nv = min(max(1, round(r.val_fraction * len(train))), len(train) - 1)
            pick = set(rng.permutation(len(train))[:nv].tolist())
            by["val"] = sorted(train[j] for j in pick)
            train = [u for j, u in enumerate(train) if j not in pick]
        by["train"] = train
        if not by["train"] or not by["test"]:
            raise SpecError(
                "--raw",
                f"need scenarios with a pair for training and for testing; got "
                f"{len(by['train'])} train, {len(by['val'])} val, {len(by['test'])} test "
                "(give more --raw scenarios, or --test files)",
            )
        return {s: sorted(by[s]) for s in SPLITS}

    def split_units(self, seed: int) -> dict[str, list[int]]:
        """By scenario (:meth:`scenario_splits`): a scenario's pairs are in one split."""
        sc = self.scenario_splits(seed)
        where = {i: s for s, ids in sc.items() for i in ids}
        out: dict[str, list[int]] = {s: [] for s in SPLITS}
        for u, unit in enumerate(self.units):
            out[where[unit.scenario]].append(u)
        return out

    def schema(self) -> dict[str, FieldSpec]:
        r = self.recipe
        N, L, P, G = r.agents, r.lane_count, r.lane_points, r.goal_points
        out = scene_schema(N, r.history, r.horizon, r.modes)
        out["agent_kind"] = FieldSpec((N,), "int8", "Waymo object type, index in meta.kinds")
        out["radius"] = FieldSpec((N,), "float32", "length / 2 (m), the paper's r = L / 2")
        out["frame"] = FieldSpec((), "int64", "current_time_index of the record")
        out.update(
            {
                "lanes": FieldSpec((L, P, 2), "float32", "lane centre pieces nearest the agents"),
                "lanes_mask": FieldSpec((L,), "bool", "True: a lane piece; False: empty slot"),
                "lane_id": FieldSpec((L,), "int64", "map feature id of each piece (-1: empty)"),
                "goal_candidates": FieldSpec(
                    (N, G, 2), "float32", "map points near each agent (current state only)"
                ),
                "goal_candidates_on_map": FieldSpec(
                    (N, G), "bool", "False: a spiral point (too few map points in range)"
                ),
                "speed_limit": FieldSpec(
                    (N,), "float32", "limit of each agent's nearest lane (m/s)"
                ),
                "scenario": FieldSpec((), "int32", "index in meta.scenarios"),
            }
        )
        return out

    @cached_property
    def game(self):
        from epo_casadi import PotentialGame

        return PotentialGame(crowd_game_spec(self.recipe))

    def meta(self) -> dict:
        r = self.recipe
        return {
            "state": ["x", "y", "v", "theta"],
            "kinds": list(OBJECT_TYPES),
            "types": list(r.types),
            "agents": [f"a{i}" for i in range(r.agents)],
            "focal_slot": 0,
            "dt": r.dt,
            "step": r.step,
            "units": "metres, seconds, radians",
            "frame": "the record's frame translated by origin (the slot-0 agent's current "
            "position); not rotated",
            "pairs": r.pairs,
            "skipped": dict(self.skipped),
            "files": [[p, t] for p, (_, t) in zip(self.paths, r.files, strict=True)],
            "scenarios": [s.scenario_id for s in self.scenarios],
            "param_names": list(self.game.params.names),
            "source": "Waymo Open Motion Dataset (Waymo non-commercial licence)",
        }

    # ---- extraction --------------------------------------------------------------------
    def record(self, scenario: int) -> ScenarioRecord:
        """The parsed record of scenario index ``scenario`` (the last one is kept)."""
        cache = self.__dict__.get("_cache")
        if cache is not None and cache[0] == scenario:
            return cache[1]
        s = self.scenarios[scenario]
        path = self.paths[s.file]
        rec = parse_scenario(read_record(path, s.offset, s.index), path, s.index, s.offset)
        if rec.scenario_id != s.scenario_id:
            raise DatasetError(
                rec.where,
                f"scenario_id {rec.scenario_id!r}, expected {s.scenario_id!r}: the file changed "
                "since the dataset was planned",
            )
        extra = {
            "pieces": lane_pieces(rec, self.recipe.lane_piece, self.recipe.lane_points),
            "pool": goal_pool(rec, self.recipe.goal_spacing),
        }
        self.__dict__["_cache"] = (scenario, rec, extra)
        return rec

    def _extra(self) -> dict:
        return self.__dict__["_cache"][2]

    def agents_of(self, rec: ScenarioRecord, pair: tuple[int, int]) -> list[int]:
        """Track indices of a pair's scene: the pair, then up to N - 2 others (the module
        docstring), closest approach on observed positions only."""
        r = self.recipe
        out = list(pair)
        if r.agents <= 2:
            return out
        grid = r.grid(rec.current)
        H = r.history
        keep = np.isin(rec.object_type, [OBJECT_TYPES.index(t) for t in r.types])
        ok = rec.valid[:, grid].all(axis=1) & keep
        ok[list(pair)] = False
        cand = np.flatnonzero(ok)
        if cand.size == 0:
            return out
        obs = rec.states[:, grid[: H + 1], :2]
        scores = closest_approach(obs[pair[0]], obs[cand], r.horizon)
        pick = select_agents(scores, rec.track_ids[cand], r.agents - 2, r.max_distance)
        return out + [int(cand[j]) for j in pick]

    def cut(self, rec: ScenarioRecord, pair: tuple[int, int], scenario: int) -> dict:
        """The sample of one pair (every schema field)."""
        r = self.recipe
        H, T, N, s = r.history, r.horizon, r.agents, r.step
        grid = r.grid(rec.current)
        agents = self.agents_of(rec, pair)
        tracks = []
        for k in agents:
            st = rec.states[k, grid]
            head = np.unwrap(st[:, 6])
            head -= 2 * math.pi * math.floor((head[H] + math.pi) / (2 * math.pi))
            tracks.append(
                Track(
                    int(rec.track_ids[k]),
                    grid.astype(np.int64),
                    st[:, :2].copy(),
                    head,
                    np.hypot(st[:, 7], st[:, 8]),
                    int(rec.object_type[k]),
                    float(st[H, 3]),
                    float(st[H, 4]),
                )
            )
        ids = [t.id for t in tracks]
        (scene,) = window_scenes(
            tracks,
            step=s,
            history=H,
            horizon=T,
            agents=N,
            dt=r.dt,
            focal_ids=[ids[0]],
            candidate_ids=ids[1:],
        )
        # the slots in the pair's order (window_scenes orders the others by closest approach)
        order = [list(scene["track_id"]).index(i) for i in ids] + list(range(len(ids), N))
        for k in ("agents_mask", "track_id", "kind", "length", "width"):
            scene[k] = scene[k][order]
        scene["history"] = scene["history"][:, order]
        scene["gt"] = scene["gt"][order]
        base = scene_schema(N, H, T, r.modes)
        out = stack_scenes([scene], base, radius=0.0)
        out = {k: v[0] for k, v in out.items()}
        mask = out["agents_mask"]
        out["radius"] = np.where(mask, 0.5 * out["length"], 0.0).astype(np.float32)
        origin = scene["origin"]
        # lanes
        pieces, which = self._extra()["pieces"]
        L, P, G = r.lane_count, r.lane_points, r.goal_points
        cur = np.array([t.xy[H] for t in tracks])  # (k, 2) world frame
        lanes = np.zeros((L, P, 2))
        lmask = np.zeros(L, bool)
        lid = np.full(L, -1, np.int64)
        limit = np.zeros(N)
        lines = rec.lines("lane")
        if len(pieces):
            d = np.stack([_distance_to_pieces(p, pieces) for p in cur])  # (k, K)
            dmin = d.min(axis=0)
            inside = np.flatnonzero(dmin <= r.lane_range)
            sel = inside[np.lexsort((inside, dmin[inside]))][:L]
            lanes[: len(sel)] = pieces[sel] - origin
            lmask[: len(sel)] = True
            lid[: len(sel)] = [lines[which[j]].id for j in sel]
            for a in range(len(tracks)):
                limit[a] = lines[which[int(np.argmin(d[a]))]].speed_limit_mph * MPH
        # goal candidates
        pool = self._extra()["pool"]
        cand = np.zeros((N, G, 2))
        on = np.zeros((N, G), bool)
        for a, t in enumerate(tracks):
            v, th = float(t.speed[H]), float(t.heading[H])
            reach = v * T * r.dt
            c, o = goal_candidates(
                pool, t.xy[H], v, th, reach, G, r.goal_scale * reach + r.goal_margin
            )
            cand[a], on[a] = c - origin, o
        out.update(
            {
                "lanes": lanes.astype(np.float32),
                "lanes_mask": lmask,
                "lane_id": lid,
                "goal_candidates": cand.astype(np.float32),
                "goal_candidates_on_map": on,
                "speed_limit": limit.astype(np.float32),
                "scenario": np.int32(scenario),
                "frame": np.int64(rec.current),
            }
        )
        return out

    def run_unit(self, index: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
        """The sample of pair ``units[index]`` (deterministic; the seed does not enter)."""
        u = self.units[index]
        rec = self.record(u.scenario)
        row = self.cut(rec, u.tracks, u.scenario)
        return {k: np.asarray(row[k]).astype(fs.dtype)[None] for k, fs in self.schema().items()}
