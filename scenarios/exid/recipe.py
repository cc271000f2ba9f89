"""The recipe of an exiD-layout dataset and the digest of the raw files it was made from."""

from __future__ import annotations

import hashlib
import numbers
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path as FilePath

from epo_casadi.errors import SpecError, check_bool, check_number, check_size, from_mapping
from epo_casadi.presets import check_weights

from .lanelet import find_map
from .recording import _recording_meta, find_recordings
from .tables import MAX_ID


@dataclass(frozen=True)
class ExidRecipe:
    """Everything that defines an exiD-layout dataset (with the seed). Frozen; unknown keys
    fail. ``recordings`` (``[[id, location], ...]``) and ``raw_digest`` are filled from the
    raw directory by :meth:`ExidScenario.from_raw`."""

    recordings: tuple[tuple[int, int], ...] = ()  #: (recording id, location id) of each unit
    raw_digest: str = ""  #: sha256 of the raw files' names, sizes, metadata and maps
    agents: int = 4  #: N
    history: int = 9  #: H past samples (plus the current one): 1.8 s
    horizon: int = 20  #: T = K future samples: 4 s
    modes: int = 5  #: M future slots (one ground truth, the rest copies)
    dt: float = 0.2  #: resampling step (s)
    stride: int = 5  #: current samples of one lane changer's scenes are this many apart
    neighbour_range: float = 100.0  #: other agents within this distance at the current step (m)
    max_scenes_per_recording: int = 0  #: > 0: keep this many scenes, evenly spread
    test_locations: tuple[int, ...] = (0,)  #: locations (maps) of the test split
    val_fraction: float = 0.18  #: share of the other recordings in val (paper: 48745/255337)
    lane_points: int = 20  #: P, points of every lane / path polyline
    lane_behind: float = 20.0  #: lane windows start this far behind the agent (m)
    lane_ahead: float = 120.0  #: ... and end this far ahead (m)
    goal_points: int = 60  #: G (the paper's), G / 3 per lane
    goal_near: float = 0.3  #: candidates from goal_near * v * T * dt ahead ...
    goal_far: float = 1.4  #: ... to goal_far * v * T * dt + goal_margin ahead
    goal_margin: float = 10.0  #: (m)
    radius: float = 2.5  #: collision radius of every agent in the game (m): L / 2 of a 5 m car
    #: each agent's radius is a game parameter that the model sets to the sample's L / 2
    #: (the paper's r = L / 2); ``radius`` is then its default. False: ``radius`` for all
    radius_per_agent: bool = True
    collision_every: int = 5  #: the collision term every this many steps (paper: 5)
    w_goal: float = 1.0  #: default weights of the game (the network predicts them)
    w_lane: float = 1.0
    w_vref: float = 1.0
    w_vel: float = 0.1
    w_acc: float = 1.0
    w_jerk: float = 0.1
    w_turn: float = 1.0
    w_turnacc: float = 0.1
    w_collision: float = 10.0

    def __post_init__(self):
        p = "exid"
        try:
            recs = tuple((a, b) for a, b in self.recordings)
        except (TypeError, ValueError):
            raise SpecError(
                f"{p}.recordings", "expected [[recording id, location id], ...]"
            ) from None
        recs = tuple(
            (_id(f"{p}.recordings[{i}][0]", a), _id(f"{p}.recordings[{i}][1]", b))
            for i, (a, b) in enumerate(recs)
        )
        object.__setattr__(self, "recordings", recs)
        if isinstance(self.test_locations, (str, bytes)) or not isinstance(
            self.test_locations, (list, tuple)
        ):
            raise SpecError(
                f"{p}.test_locations",
                f"expected a list of location ids, got {self.test_locations!r}",
            )
        locs = tuple(_id(f"{p}.test_locations[{i}]", x) for i, x in enumerate(self.test_locations))
        object.__setattr__(self, "test_locations", locs)
        if not isinstance(self.raw_digest, str):
            raise SpecError(f"{p}.raw_digest", "expected a string")
        for k, lo, hi in (
            ("agents", 2, 32),
            ("history", 1, 1000),
            ("horizon", 2, 1000),
            ("modes", 1, 100),
            ("stride", 1, 10**6),
            ("max_scenes_per_recording", 0, 10**6),
            ("lane_points", 2, 1000),
            ("goal_points", 3, 3000),
            ("collision_every", 1, 1000),
        ):
            check_number(f"{p}.{k}", getattr(self, k), lo=lo, integer=True)
            check_size(f"{p}.{k}", getattr(self, k), hi, "the size of every sample", lo=lo)
        if self.goal_points % 3:
            raise SpecError(f"{p}.goal_points", f"expected a multiple of 3, got {self.goal_points}")
        check_number(f"{p}.dt", self.dt, lo=0.01, hi=2.0)
        check_number(f"{p}.val_fraction", self.val_fraction, lo=0.0, hi=0.9)
        for k in ("neighbour_range", "lane_ahead", "radius", "goal_far"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, lo_open=True)
        check_bool(f"{p}.radius_per_agent", self.radius_per_agent)
        for k in ("lane_behind", "goal_near", "goal_margin"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0)
        check_weights(p, self)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["recordings"] = [list(r) for r in self.recordings]
        d["test_locations"] = list(self.test_locations)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ExidRecipe:
        """The recipe of a manifest's or ``--set``'s fields (unknown fields refused)."""
        return from_mapping(cls, d, "exid", "recipe field")


def _id(field: str, x) -> int:
    """A recording or location id: an integer (numpy's too) in ``[0, MAX_ID]``."""
    if isinstance(x, numbers.Integral) and not isinstance(x, bool):
        x = int(x)
    return check_number(field, x, lo=0, hi=MAX_ID, integer=True)


def raw_digest(raw: str | FilePath, recordings: Sequence[int]) -> str:
    """sha256 over the names and sizes of the tracks files and the contents of the meta
    files and maps (a different raw set refuses to resume a dataset)."""
    raw = FilePath(raw)
    dirs = find_recordings(raw)
    h = hashlib.sha256()
    locs = set()
    for rid in recordings:
        d = dirs[rid]
        t = d / f"{rid:02d}_tracks.csv"
        h.update(f"{t.name}:{t.stat().st_size if t.exists() else -1}".encode())
        for n in ("tracksMeta", "recordingMeta"):
            f = d / f"{rid:02d}_{n}.csv"
            h.update(f.read_bytes() if f.exists() else b"-")
        locs.add(_recording_meta(d / f"{rid:02d}_recordingMeta.csv", rid)["locationId"])
    for loc in sorted(locs):
        h.update(find_map(raw, loc).read_bytes())
    return h.hexdigest()
