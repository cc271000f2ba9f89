"""The exiD scenario: the split by location, the schema, the App. F.3 game and the sample
extraction of one recording (:mod:`scenarios.exid`, "Extraction", "Splits" and "Game")."""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path as FilePath

import numpy as np

from epo_casadi import (
    AgentSpec,
    GameSpec,
    PotentialGame,
)
from epo_casadi.errors import SpecError, check_size
from epo_casadi.presets import driving_agents, driving_game_spec

from ..dataset import SPLITS, DatasetError, FieldSpec, RawScenario, stack_rows
from ..maps import Lane, RoadMap, arc_length, project_to_polyline, resample_at
from .lanelet import (
    LaneletMap,
    _dedupe,
    _heading,
    check_map_near,
    find_map,
    lane_changes,
    read_lanelet_map,
)
from .recipe import ExidRecipe, raw_digest
from .recording import Recording, _recording_meta, find_recordings, read_recording
from .tables import MAP_DISTANCE, MAX_GRID_CELLS

#: vehicle classes (index stored in ``vehicle_class``); others map to the last entry
CLASSES = ("car", "van", "truck", "bus", "trailer", "motorcycle", "other")


class ExidScenario(RawScenario):
    """Samples of the exiD layout (:mod:`scenarios.exid`); one work unit per recording.
    Construct hooks: :meth:`agent_specs`, :meth:`game_spec`, :meth:`scenes`, :meth:`cut`."""

    name = "exid"
    recipe_class = ExidRecipe

    @classmethod
    def from_raw(cls, raw: str | FilePath, **overrides) -> ExidScenario:
        """The scenario of every recording in ``raw`` (``overrides``: recipe fields; a
        ``recordings`` override given as ids selects recordings)."""
        dirs = find_recordings(raw)
        want = overrides.pop("recordings", None)
        ids = (
            sorted(dirs)
            if want is None
            else [int(r[0] if isinstance(r, (list, tuple)) else r) for r in want]
        )
        bad = [r for r in ids if r not in dirs]
        if bad:
            raise SpecError(
                "exid.recordings", f"no such recording(s) {bad} in {raw}; found {sorted(dirs)}"
            )
        recs = []
        for rid in ids:
            m = _recording_meta(dirs[rid] / f"{rid:02d}_recordingMeta.csv", rid)
            recs.append((rid, int(m["locationId"])))
        recipe = ExidRecipe.from_dict(
            {**overrides, "recordings": recs, "raw_digest": raw_digest(raw, ids)}
        )
        return cls(recipe, raw)

    # ---- Scenario interface ----------------------------------------------------------

    @property
    def n_units(self) -> int:
        return len(self.recipe.recordings)

    @property
    def units_per_shard(self) -> int:
        return 1

    def split_units(self, seed: int) -> dict[str, list[int]]:
        """By location (:mod:`scenarios.exid`)."""
        r = self.recipe
        test = [i for i, (_, loc) in enumerate(r.recordings) if loc in r.test_locations]
        rest = [i for i, (_, loc) in enumerate(r.recordings) if loc not in r.test_locations]
        if not test or not rest:
            raise SpecError(
                "exid.test_locations",
                f"need recordings of a test location {list(r.test_locations)} and of another one; "
                f"locations present: {sorted({loc for _, loc in r.recordings})}",
            )
        out = {"train": list(rest), "val": [], "test": test}
        if len(rest) >= 2 and r.val_fraction > 0:
            rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0,)))
            nv = max(1, round(r.val_fraction * len(rest)))
            nv = min(nv, len(rest) - 1)
            val = sorted(int(rest[j]) for j in rng.permutation(len(rest))[:nv])
            out = {"train": [u for u in rest if u not in val], "val": val, "test": test}
        return {s: sorted(out[s]) for s in SPLITS}

    def schema(self) -> dict[str, FieldSpec]:
        r = self.recipe
        N, H, M, T, P, G = r.agents, r.history, r.modes, r.horizon, r.lane_points, r.goal_points
        return {
            "history": FieldSpec(
                (H + 1, N, 4), "float32", "states (x, y, v, theta) at t-H..t, scene frame"
            ),
            "history_valid": FieldSpec((H + 1,), "bool", "always True (complete windows only)"),
            "future": FieldSpec(
                (M, N, T, 4), "float32", "states at t+1..t+T; slot gt_mode: the recording"
            ),
            "mode_valid": FieldSpec((M,), "bool", "True only for the ground-truth slot"),
            "gt_mode": FieldSpec((), "int8", "slot of the recorded future (0)"),
            "lanes": FieldSpec(
                (3 * N, P, 2), "float32", "per agent: left, current, right lane windows"
            ),
            "paths": FieldSpec(
                (N, P, 2), "float32", "current lane window of each agent (game path)"
            ),
            "vref": FieldSpec((N,), "float32", "speed limit of each agent's lanelet (m/s)"),
            "goal_candidates": FieldSpec(
                (N, G, 2), "float32", "G/3 points on each of the three lanes"
            ),
            "goal_candidate_lane": FieldSpec((N, G), "int8", "0 left, 1 current, 2 right lane"),
            "goal_candidate_on_lane": FieldSpec(
                (N, G), "bool", "False: on a lane boundary (no neighbour)"
            ),
            "length": FieldSpec((N,), "float32", "vehicle length (m)"),
            "width": FieldSpec((N,), "float32", "vehicle width (m)"),
            "vehicle_class": FieldSpec((N,), "int8", "index in meta.classes"),
            "radius": FieldSpec((N,), "float32", "L / 2 (m), the paper's collision radius"),
            "track_id": FieldSpec((N,), "int32", "trackId in the recording"),
            "lane_change": FieldSpec((N,), "bool", "the agent changes lane in the window"),
            "recording": FieldSpec((), "int16", "recordingId"),
            "location": FieldSpec((), "int16", "locationId (map)"),
            "frame": FieldSpec((), "int64", "current frame in the recording"),
            "origin": FieldSpec((2,), "float64", "scene origin in the recording's local frame (m)"),
        }

    def meta(self) -> dict:
        r = self.recipe
        return {
            "state": ["x", "y", "v", "theta"],
            "classes": list(CLASSES),
            "agents": [f"v{i}" for i in range(r.agents)],
            "splits_by_location": {"test": list(r.test_locations)},
            "raw": None if self.raw is None else str(self.raw),
            "frame": "recording's local frame (UTM minus origin) translated by origin; not rotated",
            "param_names": list(self.game.params.names),
            "dt": r.dt,
            "units": "metres, seconds, radians",
        }

    # ---- the game ----------------------------------------------------------------------
    def agent_specs(self) -> list[AgentSpec]:
        """App. F.3 exiD features plus the goal term, per agent."""
        r = self.recipe
        return driving_agents(
            r,
            [f"v{i}" for i in range(r.agents)],
            lane_points=r.lane_points,
            radius_param=r.radius_per_agent,
        )

    def game_spec(self) -> GameSpec:
        return driving_game_spec(self.recipe, self.agent_specs(), every=self.recipe.collision_every)

    @cached_property
    def game(self) -> PotentialGame:
        return PotentialGame(self.game_spec())

    # ---- extraction --------------------------------------------------------------------
    def load(self, rid: int) -> tuple[Recording, LaneletMap]:
        """Recording ``rid`` and its location's map."""
        if self.raw is None:
            raise SpecError(
                "exid.raw", "this scenario has no raw directory (ExidScenario.from_raw)"
            )
        rec = read_recording(self.raw, rid)
        lmap = read_lanelet_map(
            find_map(self.raw, rec.location), rec.utm_origin, rec.lonlat, rec.speed_limit
        )
        check_map_near(lmap, rec)
        return rec, lmap

    def resample(self, rec: Recording, lmap: LaneletMap) -> dict:
        """Per track, the samples on the ``dt`` grid: ``x`` ``(n_tracks, S, 4)`` states and
        ``lanelet`` ``(n_tracks, S)`` (NaN / -1 where the track does not exist),
        ``first`` / ``last`` sample index per track, ``grid`` frames ``(S,)`` (from the first
        grid frame of the recording), ``step`` frames per sample."""
        r = self.recipe
        step = r.dt * rec.frame_rate
        if abs(step - round(step)) > 1e-6 or round(step) < 1:
            raise DatasetError(
                f"{rec.files[2]}:frameRate",
                f"dt = {r.dt} s times frameRate {rec.frame_rate} is not a whole number of frames",
            )
        step = int(round(step))
        rows = rec.rows
        fr = rows["frame"].astype(np.int64)
        on = fr % step == 0
        tid = np.repeat(np.arange(rec.n_tracks), np.diff(np.append(rec.start, len(fr))))
        k0 = int(-(-fr.min() // step))  # the first grid frame is k0 * step
        S = max(int(fr.max() // step) - k0 + 1, 1)
        check_size(
            f"{rec.files[0]}:frame",
            rec.n_tracks * S,
            MAX_GRID_CELLS,
            f"memory: {rec.n_tracks} tracks x {S} samples of {r.dt} s from frame "
            f"{k0 * step} to {int(fr.max())}",
        )
        x = np.full((rec.n_tracks, S, 4), np.nan)
        lan = np.full((rec.n_tracks, S), -1, dtype=np.int64)
        j, k = tid[on], fr[on] // step - k0
        head = np.radians(rows["heading"][on])
        x[j, k] = np.stack(
            [
                rows["xCenter"][on],
                rows["yCenter"][on],
                np.hypot(rows["xVelocity"][on], rows["yVelocity"][on]),
                head,
            ],
            axis=1,
        )
        ll = rows["laneletId"][on].copy()
        unknown = ll < 0
        if unknown.any():
            ll[unknown] = lmap.locate(
                np.stack([rows["xCenter"][on][unknown], rows["yCenter"][on][unknown]], 1)
            )
        lan[j, k] = ll
        exists = np.isfinite(x[..., 0])
        first = np.where(exists.any(1), np.argmax(exists, 1), S)
        last = np.where(exists.any(1), S - 1 - np.argmax(exists[:, ::-1], 1), -1)
        # continuous headings per track
        th = x[..., 3]
        filled = np.where(exists, th, 0.0)
        filled = np.unwrap(filled, axis=1)
        x[..., 3] = np.where(exists, filled, np.nan)
        grid = (k0 + np.arange(S)) * step
        return {
            "x": x,
            "lanelet": lan,
            "first": first,
            "last": last,
            "grid": grid,
            "step": step,
        }

    def check_windows(self, rec: Recording, res: dict) -> None:
        """Refuse a recording of which no sample can be made: fewer than ``agents`` tracks
        span the ``history + 1 + horizon`` samples of a scene (all tracks too short for the
        window, or a ``frameRate`` that puts too few samples in each)."""
        r = self.recipe
        need = r.history + 1 + r.horizon
        span = np.maximum(res["last"] - res["first"] + 1, 0)
        n = int((span >= need).sum())
        if n < r.agents:
            raise DatasetError(
                rec.files[0],
                f"recording {rec.id:02d}: no sample can be made: a scene needs {r.agents} "
                f"tracks that each span {need} samples ({(need - 1) * r.dt:g} s), {n} do; "
                f"the longest spans {int(span.max(initial=0))} (a sample every "
                f"{res['step']} frames at frameRate {rec.frame_rate:g} Hz)",
            )

    def scenes(self, res: dict, lmap: LaneletMap) -> list[tuple[int, tuple[int, ...], np.ndarray]]:
        """``(t, agents, changes)`` of every scene (:mod:`scenarios.exid`, step 3); ``changes``:
        per agent, a lane change in the window."""
        r = self.recipe
        H, T, N = r.history, r.horizon, r.agents
        x, lan, first, last = res["x"], res["lanelet"], res["first"], res["last"]
        lc = np.zeros(lan.shape, dtype=bool)
        for j in range(len(x)):
            if last[j] > first[j]:
                lc[j, first[j] : last[j] + 1] = lane_changes(lan[j, first[j] : last[j] + 1], lmap)
        out, seen = [], set()
        for i, c in zip(*np.nonzero(lc), strict=True):
            lo = max(c - T, first[i] + H)
            hi = min(c + H - 1, last[i] - T)
            t0 = -(-lo // r.stride) * r.stride
            for t in range(t0, hi + 1, r.stride):
                alive = (first <= t - H) & (last >= t + T)
                alive[i] = False
                cand = np.flatnonzero(alive)
                d = np.linalg.norm(x[cand, t, :2] - x[i, t, :2], axis=1)
                keep = d <= r.neighbour_range
                cand, d = cand[keep], d[keep]
                if len(cand) < N - 1:
                    continue
                agents = (int(i), *(int(a) for a in cand[np.argsort(d, kind="stable")[: N - 1]]))
                key = (t, tuple(sorted(agents)))
                if key in seen:
                    continue
                seen.add(key)
                win = lc[list(agents), t - H + 1 : t + T + 1].any(1)
                out.append((t, agents, win))
        out.sort(key=lambda s: (s[0], s[1]))
        m = r.max_scenes_per_recording
        if m and len(out) > m:
            pick = np.unique(np.linspace(0, len(out) - 1, m).round().astype(int))
            out = [out[k] for k in pick]
        return out

    def _corridor(self, lmap: LaneletMap, lid: str, cache: dict) -> tuple[np.ndarray, float]:
        """Centre polyline of ``lid`` continued through its straightest predecessors and
        successors (up to ``lane_behind`` / ``lane_ahead`` + 200 m), and the arc length at
        which ``lid`` starts on it."""
        if lid in cache:
            return cache[lid]
        rm, r = lmap.road_map, self.recipe
        lane = rm.lane(lid)
        parts, s0 = [lane.centre], 0.0
        cur, total = lane, 0.0
        seen = {lid}
        while total < r.lane_ahead + 200 and cur.successors:
            nxt = _straightest(rm, cur, cur.successors, forward=True)
            if nxt.id in seen:
                break
            seen.add(nxt.id)
            parts.append(nxt.centre)
            total += nxt.length
            cur = nxt
        cur, total = lane, 0.0
        while total < r.lane_behind + 200 and lmap.predecessors.get(cur.id):
            prv = _straightest(rm, cur, lmap.predecessors[cur.id], forward=False)
            if prv.id in seen:
                break
            seen.add(prv.id)
            parts.insert(0, prv.centre)
            s0 += prv.length
            total += prv.length
            cur = prv
        line = _dedupe(np.concatenate(parts))
        cache[lid] = (line, s0)
        return cache[lid]

    def cut(self, res: dict, rec: Recording, lmap: LaneletMap, scene, cache: dict) -> dict:
        """The sample of one scene (:mod:`scenarios.exid`, steps 4-7)."""
        r = self.recipe
        H, T, N, M, P, G = r.history, r.horizon, r.agents, r.modes, r.lane_points, r.goal_points
        t, agents, changes = scene
        ag = list(agents)
        X = res["x"][ag, t - H : t + T + 1]  # (N, H+T+1, 4)
        origin = X[:, H, :2].mean(axis=0)
        X = X.copy()
        X[..., :2] -= origin
        cur = X[:, H, 3]
        X[..., 3] -= (2 * math.pi * np.ceil((cur - math.pi) / (2 * math.pi)))[:, None]
        hist = X[:, : H + 1].transpose(1, 0, 2)
        fut = np.repeat(X[None, :, H + 1 :], M, axis=0)
        lanes = np.empty((N, 3, P, 2))
        cands = np.empty((N, 3, G // 3, 2))
        on = np.ones((N, 3), dtype=bool)
        vref = np.empty(N)
        rm = lmap.road_map
        meta_tid = rec.meta["trackId"]
        for a, j in enumerate(ag):
            p = res["x"][j, t, :2]
            v = float(res["x"][j, t, 2])
            lid = int(res["lanelet"][j, t])
            if lid < 0 or str(lid) not in rm:
                lid = int(lmap.locate(p[None])[0])
            if lid < 0:  # off every lanelet: the nearest one
                lid = int(rm.ids[int(np.argmin([ln.project(p[None])[1][0] for ln in rm.lanes]))])
            sid = str(lid)
            lane = rm.lane(sid)
            vref[a] = lane.speed_limit
            span = v * T * r.dt
            ahead = np.linspace(r.goal_near * span, r.goal_far * span + r.goal_margin, G // 3)
            win = np.linspace(-r.lane_behind, r.lane_ahead, P)
            line, _ = self._corridor(lmap, sid, cache)
            s, dist = project_to_polyline(p[None], line)
            _check_near(lmap, sid, dist[0], rec, int(meta_tid[j]), int(res["grid"][t]))
            centre_w = _along(line, s[0] + win)
            centre_c = _along(line, s[0] + ahead)
            for side, nb, sign in ((0, lmap.left.get(sid), 1.0), (2, lmap.right.get(sid), -1.0)):
                if nb is not None:
                    nline, _ = self._corridor(lmap, nb, cache)
                    ns, dist = project_to_polyline(p[None], nline)
                    _check_near(lmap, nb, dist[0], rec, int(meta_tid[j]), int(res["grid"][t]))
                    lanes[a, side] = _along(nline, ns[0] + win)
                    cands[a, side] = _along(nline, ns[0] + ahead)
                else:
                    off = sign * 0.5 * lane.width
                    lanes[a, side] = _offset(line, s[0] + win, off)
                    cands[a, side] = _offset(line, s[0] + ahead, off)
                    on[a, side] = False
            lanes[a, 1], cands[a, 1] = centre_w, centre_c
        lanes -= origin
        cands -= origin
        meta = rec.meta
        length = meta["length"][ag]
        cls = [CLASSES.index(c) if c in CLASSES else len(CLASSES) - 1 for c in meta["class"][ag]]
        return {
            "history": hist,
            "history_valid": np.ones(H + 1, dtype=bool),
            "future": fut,
            "mode_valid": np.arange(M) == 0,
            "gt_mode": 0,
            "lanes": lanes.reshape(3 * N, P, 2),
            "paths": lanes[:, 1],
            "vref": vref,
            "goal_candidates": cands.reshape(N, G, 2),
            "goal_candidate_lane": np.repeat(np.arange(3), G // 3)[None].repeat(N, 0),
            "goal_candidate_on_lane": np.repeat(on, G // 3, axis=1),
            "length": length,
            "width": meta["width"][ag],
            "vehicle_class": np.array(cls),
            "radius": 0.5 * length,
            "track_id": meta["trackId"][ag].astype(np.int64),
            "lane_change": changes,
            "recording": rec.id,
            "location": rec.location,
            "frame": int(res["grid"][t]),
            "origin": origin,
        }

    def run_unit(self, index: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
        """Every sample of recording ``recordings[index]`` (deterministic; the seed does not
        enter)."""
        rid = self.recipe.recordings[index][0]
        rec, lmap = self.load(rid)
        res = self.resample(rec, lmap)
        self.check_windows(rec, res)
        cache: dict = {}
        rows = [self.cut(res, rec, lmap, sc, cache) for sc in self.scenes(res, lmap)]
        return stack_rows(rows, self.schema())


def _check_near(lmap: LaneletMap, lid: str, d: float, rec: Recording, tid: int, frame: int):
    """Refuse a lane (corridor centre line) farther than :data:`MAP_DISTANCE` from its agent."""
    if not d <= MAP_DISTANCE:
        raise DatasetError(
            lmap.path,
            f"lanelet {lid} is {d:,.0f} m from track {tid} of recording {rec.id:02d} at frame "
            f"{frame}; expected the lanes of a sample within {MAP_DISTANCE:g} m of its agent",
        )


def _straightest(rm: RoadMap, cur: Lane, ids: Sequence[str], forward: bool) -> Lane:
    h = _heading(cur.centre[-2:] if forward else cur.centre[:2])
    best = max(
        (rm.lane(i) for i in ids),
        key=lambda ln: (
            math.cos(_heading(ln.centre[:2] if forward else ln.centre[-2:]) - h),
            ln.id,
        ),
    )
    return best


def _along(line: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points of ``line`` at arc lengths ``s``, clamped to its ends (so they stay on the map)."""
    return resample_at(line, np.asarray(s, dtype=float))


def _offset(line: np.ndarray, s: np.ndarray, off: float) -> np.ndarray:
    """Points at arc lengths ``s`` (clamped) shifted ``off`` metres to the left (negative:
    right)."""
    sa = arc_length(line)
    seg = np.diff(line, axis=0)
    s = np.clip(s, 0.0, sa[-1])
    k = np.clip(np.searchsorted(sa, s, side="right") - 1, 0, len(seg) - 1)
    d = seg[k] / np.linalg.norm(seg[k], axis=1, keepdims=True)
    return _along(line, s) + off * np.stack([-d[:, 1], d[:, 0]], axis=1)
