"""The recipe of a Waymo dataset (:class:`WaymoRecipe`: window, pair rule, lanes, goal
candidates, splits; the defaults are the paper's, see :mod:`scenarios.real.waymo`) and the
game of a dataset from its manifest recipe (:func:`game_from_recipe`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size

from ...dataset import SPLITS
from ..recipe import SceneRecipe
from ..scenes import crowd_game_spec
from ..waymo_schema import OBJECT_TYPES
from .records import GRID_DT

PAIR_RULES = ("auto", "interest", "predict")


@dataclass(frozen=True)
class WaymoRecipe(SceneRecipe):
    """Everything that defines a Waymo dataset (with the seed). ``history``, ``horizon``,
    ``dt`` and ``collision_every`` left at None follow ``step`` (the module docstring);
    ``files`` and ``raw_digest`` are filled by :meth:`WaymoScenario.from_raw`."""

    prefix = "waymo"

    agents: int = 2  #: N: the interacting pair (+ N - 2 nearest others)
    history: int | None = None  #: H past steps (None: 10 // step, 1 s)
    horizon: int | None = None  #: T future steps (None: 80 // step, 8 s)
    modes: int = 6  #: M (the paper's Waymo setting)
    dt: float | None = None  #: 0.1 s x step
    radius: float = 2.5  #: the game's default radius (m); samples set L / 2
    collision_every: int | None = None  #: None: every 0.5 s (5 // step, at least 1)
    step: int = 1  #: grid steps (0.1 s) per sample step
    pairs: str = "auto"  #: "auto", "interest" (objects_of_interest), "predict" (tracks_to_predict)
    types: tuple[str, ...] = ("vehicle", "pedestrian", "cyclist")  #: object types kept
    lane_count: int = 128  #: L lane pieces
    lane_points: int = 10  #: P points per piece
    lane_piece: float = 20.0  #: longest piece (m)
    lane_range: float = 150.0  #: pieces farther from every agent are left out (m)
    goal_points: int = 64  #: G goal candidates per agent
    goal_spacing: float = 2.0  #: spacing of the candidate pool along lanes and crosswalks (m)
    goal_scale: float = 1.5  #: candidate range: goal_scale * v * T * dt ...
    goal_margin: float = 10.0  #: ... + goal_margin (m)
    val_fraction: float = 0.1  #: seeded val share of the --raw scenarios (without --val)
    test_fraction: float = 0.1  #: seeded test share of the --raw scenarios (without --test)
    files: tuple[tuple[str, str], ...] = ()  #: (file name, "train" | "val" | "test")
    raw_digest: str = ""  #: sha256 of the files' names, sizes and the units read from them

    def __post_init__(self):
        p = self.prefix
        check_number(f"{p}.step", self.step, lo=1, hi=80, integer=True)
        s = self.step
        if self.dt is None:
            object.__setattr__(self, "dt", round(GRID_DT * s, 12))
        else:
            check_number(f"{p}.dt", self.dt, lo=0.01, hi=8.0)
            if abs(self.dt - GRID_DT * s) > 1e-9:
                raise SpecError(
                    f"{p}.dt",
                    f"is {GRID_DT} s x step (the recordings' 10 Hz) = {GRID_DT * s:g} s, "
                    f"got {self.dt}; set step instead",
                )
        for k, default in (("history", 10 // s), ("horizon", 80 // s)):
            if getattr(self, k) is None:
                object.__setattr__(self, k, max(default, 1 if k == "history" else 2))
        if self.collision_every is None:
            object.__setattr__(self, "collision_every", max(1, round(5 / s)))
        super().__post_init__()
        check_number(f"{p}.agents", self.agents, lo=2, integer=True)
        if self.stride != 1:
            raise SpecError(f"{p}.stride", "expected 1: one scene per pair, at current_time_index")
        if self.pairs not in PAIR_RULES:
            raise SpecError(f"{p}.pairs", f"expected one of {list(PAIR_RULES)}, got {self.pairs!r}")
        types = self.types
        if isinstance(types, str) or not isinstance(types, (list, tuple)) or not types:
            raise SpecError(
                f"{p}.types", f"expected a list of {list(OBJECT_TYPES[1:])}, got {types!r}"
            )
        for t in types:
            if t not in OBJECT_TYPES[1:]:
                raise SpecError(
                    f"{p}.types", f"expected names of {list(OBJECT_TYPES[1:])}, got {t!r}"
                )
        object.__setattr__(self, "types", tuple(dict.fromkeys(types)))
        for k, lo, hi in (
            ("lane_count", 1, 4096),
            ("lane_points", 2, 1000),
            ("goal_points", 1, 10000),
        ):
            check_number(f"{p}.{k}", getattr(self, k), lo=lo, integer=True)
            check_size(f"{p}.{k}", getattr(self, k), hi, "the size of every sample", lo=lo)
        for k in ("lane_piece", "lane_range", "goal_spacing", "goal_margin"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, lo_open=True, hi=1e6)
        check_number(f"{p}.goal_scale", self.goal_scale, lo=0.0, hi=100.0)
        for k in ("val_fraction", "test_fraction"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, hi=0.9)
        try:
            files = tuple((str(a), str(b)) for a, b in self.files)
        except (TypeError, ValueError):
            raise SpecError(f"{p}.files", "expected [[file name, split], ...]") from None
        for _name, split in files:
            if split not in SPLITS:
                raise SpecError(f"{p}.files", f"expected a split of {list(SPLITS)}, got {split!r}")
        object.__setattr__(self, "files", files)
        if not isinstance(self.raw_digest, str):
            raise SpecError(f"{p}.raw_digest", "expected a string")

    @property
    def span(self) -> tuple[int, int]:
        """Grid steps before and after the current one: ``(H s, T s)``."""
        return self.history * self.step, self.horizon * self.step

    def grid(self, current: int) -> np.ndarray:
        """Record step indices of a window at ``current``: ``(H + 1 + T,)``."""
        return current + self.step * np.arange(-self.history, self.horizon + 1)


def game_from_recipe(recipe: dict):
    """The game of a Waymo dataset from its manifest recipe (the crowd game, App. F.3)."""
    from epo_casadi import PotentialGame

    return PotentialGame(crowd_game_spec(WaymoRecipe.from_dict(recipe)))
