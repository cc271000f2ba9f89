"""Left-turn demonstrations after the paper's CARLA recipe (App. E), on :class:`LeftTurnWorld`.

Scene (agent order ``[sdv, other]``; both recorded as extended-unicycle states
``(x, y, v, theta)``: position, speed and heading of highway-env's vehicles, every
``dt = 0.1`` s). The SDV turns left across the lane of an oncoming vehicle on one of the
intersection geometries of :data:`scenarios.sim.left_turn.GEOMETRIES`. Everything about
the world (start distances and speeds, the oncoming driver's character: aggressiveness,
desired speed, reaction time) is drawn by ``LeftTurnWorld.reset(seed)``.

Hand-made policies (:class:`SDVPolicy` and the world's oncoming driver)
    1. The SDV first decides whether to enter: its *intent* is ``enter`` with probability
       ``p_enter`` (seeded per episode), else ``wait``.
    2. The oncoming driver yields or goes by its character (the world's gap rule, re-
       evaluated every step until it is committed).
    3. The SDV re-evaluates every step: with intent ``enter`` it drives on while the other
       yields and stops before the conflict zone when the other goes; with intent ``wait``
       it stops before the zone and goes when the other has cleared the zone or stands
       yielding. Once the SDV cannot stop before the zone (braking at ``brake_max``) it is
       committed and goes. It steers by pure pursuit along its route and follows the
       speed limits (the turn's ``min(v_lim, sqrt(3 R))``) with comfortable braking.

Outcomes and modes (``M = 2``)
    The *outcome* of a run is which vehicle enters the conflict zone first:
    ``sdv_first`` (slot 0) or ``other_first`` (slot 1). An episode is one *natural* run of
    ``episode_steps`` steps (both policies as above; continued up to ``replay_extra`` more
    steps while no vehicle has entered the zone, to know its outcome; replays likewise).
    At every step ``k`` of it with ``T``
    steps still to come, one sample: its future in the slot of the episode's outcome is
    what happened (``gt_mode``), and the other slot is the *alternative outcome* replayed
    from the same state: the world and the SDV policy at step ``k`` are copied
    (``copy.deepcopy``: bit-identical states) and the decisions forced towards the other
    outcome (``sdv_first``: the oncoming driver yields (``LeftTurnWorld.forced_decision``)
    and the SDV drives on while it does; ``other_first``: the SDV waits and the oncoming
    driver goes unless the SDV is already committed). A forced decision never overrides a
    committed driver, so when the other outcome can no longer happen (one vehicle is
    already in the zone, the SDV is committed, the oncoming driver is committed to go)
    or the replay collides or ends with the same outcome, the slot repeats the ground
    truth with ``mode_valid = False`` (the RPI convention).
    A natural run that collides or in which neither vehicle enters the zone is redrawn
    (next world seed, at most ``max_tries`` draws per episode).

Agent-centric frame (paper App. E, F.2)
    Every sample is expressed in the frame of the SDV at its current step ``k``: with the
    SDV's world pose ``(x_s, y_s, theta_s)`` (the ``frame`` field),
    ``p' = R(-theta_s) (p - (x_s, y_s))`` and ``theta' = theta - theta_s`` for positions and
    headings of both agents (history, futures), lanes, paths and goal candidates; speeds
    are unchanged. So the SDV is at the origin with heading 0 at the current step.
    Headings are continuous along each agent's trajectory (no wrapping inside a sample);
    each agent's headings are shifted by a multiple of ``2 pi`` so that its current
    heading lies in ``(-pi, pi]``.

Map input and goal candidates
    ``lanes`` ``(2, P, 2)``: the SDV's route (approach, turn, exit) and the other's lane,
    each a window from ``lane_behind`` m behind to ``lane_ahead`` m ahead of the agent's
    current arc position, resampled to ``P = lane_points`` points (linearly extended
    beyond the ends of the route). ``paths`` ``(N, P, 2)``: each agent's reference lane
    for the game's lane (path) feature: the same two polylines. ``vref`` ``(N,)``: the
    map's speed limit on each agent's window (the smallest on it: the turn's for the SDV
    while the turn is ahead). ``goal_candidates`` ``(N, G, 2)``: ``G = goal_points`` points
    on each agent's own lane centreline from its current arc position to ``goal_range``
    m ahead (the paper extracts them from the current and neighbouring lanes; the agents
    here never change lanes).

History before the start
    Steps before ``k = 0`` do not exist; they are a constant-velocity backward
    extrapolation of the first state, ``False`` in ``history_valid`` (as in RPI).

Splits (by intersection, as the paper: train intersection 1, val 2, test 3 and 4)
    Work unit ``i`` is episode ``i mod E`` of geometry ``geometries[i // E]`` with
    ``E = episodes_per_geometry``; units of ``train_geometries`` (``g0``) are the train
    split, of ``val_geometries`` (``g1``) val, of ``test_geometries`` (``g2, g3``) test.
    No geometry is in two splits.

Augmentation (training only, App. E)
    For every original train sample, ``augment_copies`` extra samples: the whole sample
    (history, futures, lanes, paths, goal candidates) rotated about the origin by an angle
    drawn from ``U[-augment_angle, augment_angle]`` (default ``pi/8``; headings shifted by
    it; the angle is in ``rotation``), and Gaussian noise of std ``augment_noise`` (0.02 m)
    added to the past history positions (steps ``k-H..k-1``; the current state, the
    game's initial state, stays exact). The paper rotates "all observations"; the futures
    are rotated too so that a sample stays a consistent scene. ``augment_copies = 4``
    matches the paper's counts (1836 train samples from five episodes, against 361 val
    from five: about 1 + 4 samples per original). Val and test samples are never augmented.

Limits (checked when a recipe is made, before any work)
    every count and size at most its :data:`SIZE_LIMITS` entry (``episodes_per_geometry``
    100,000, ``history`` and ``horizon`` 1,000, ``episode_steps`` 10,000,
    ``augment_copies`` 100, ...), and the samples of one shard at most
    :data:`MAX_SHARD_BYTES` (2 GiB, estimated from the sizes: a shard is held in memory
    until it is written).

Game (App. F.3, CARLA): per agent ``lane`` (:class:`~epo_casadi.features.Path`, the
``paths`` polyline as parameter), ``vref`` (:class:`~epo_casadi.features.ReferenceVelocity`,
``vref`` as parameter), velocity, acceleration, jerk, turn rate, turn acceleration, plus a
terminal goal term (the goal decoder's goal); collision between the two vehicles (every
step). Horizon ``K = T = 60``, ``dt = 0.1``. Radius ``r = 1.25`` m each, so ``2 r`` is
the world's conflict clearance (2.5 m): the paper's ``r = L / 2`` (5 m apart) would
penalize every ordinary pass in adjacent opposing lanes (3 to 3.75 m apart; a waiting SDV
is ~2.8 m from the passing vehicle), i.e. the ground truth itself.

Modules. The SDV's policy and the runs it drives (:class:`SDVPolicy`, :func:`simulate`,
:class:`Run`) and the geometry they use (:func:`to_frame`) live in
:mod:`scenarios.left_turn_policy`; this module holds the recipe, the dataset scenario and
the scene fields of the closed loop, and every name stays importable from here.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, fields
from functools import cached_property

import numpy as np

from epo_casadi import (
    AgentSpec,
    GameSpec,
    PotentialGame,
)
from epo_casadi.errors import SpecError, check_number, check_size, from_mapping
from epo_casadi.presets import check_weights, driving_agents, driving_game_spec

from .dataset import SPLITS, FieldSpec, Scenario, stack_rows
from .left_turn_policy import LENGTH as LENGTH
from .left_turn_policy import Run as Run
from .left_turn_policy import SDVPolicy as SDVPolicy
from .left_turn_policy import _at as _at
from .left_turn_policy import _entered as _entered
from .left_turn_policy import _progress as _progress
from .left_turn_policy import _rotate as _rotate
from .left_turn_policy import simulate as simulate
from .left_turn_policy import to_frame as to_frame

__all__ = [
    "LeftTurnRecipe",
    "LeftTurnScenario",
    "SDVPolicy",
    "OUTCOMES",
    "to_frame",
    "rotate_sample",
    "MAX_EPISODES_PER_GEOMETRY",
    "SIZE_LIMITS",
    "MAX_SHARD_BYTES",
]

#: most episodes (work units) per geometry (the paper has 5)
MAX_EPISODES_PER_GEOMETRY = 100_000
#: upper bounds of the recipe's counts and sizes, checked before any work (each one is
#: far above what a dataset needs; a larger value is refused, not misread)
SIZE_LIMITS: dict[str, int] = {
    "episodes_per_geometry": MAX_EPISODES_PER_GEOMETRY,
    "episodes_per_shard": 10_000,
    "history": 1_000,
    "horizon": 1_000,
    "episode_steps": 10_000,
    "replay_extra": 10_000,
    "lane_points": 10_000,
    "goal_points": 10_000,
    "augment_copies": 100,
    "max_tries": 1_000,
}
#: most bytes of the samples of one shard (held in memory until the shard is written)
MAX_SHARD_BYTES = 2 * 2**30

AGENTS = ("sdv", "other")
#: mode slots: the SDV enters the conflict zone first / the oncoming vehicle does
OUTCOMES = ("sdv_first", "other_first")


def _names(field: str, v) -> tuple[str, ...]:
    from .sim.left_turn import GEOMETRIES

    if isinstance(v, str) or not isinstance(v, (list, tuple)):
        raise SpecError(f"left-turn.{field}", f"expected a list of geometry names, got {v!r}")
    t = tuple(v)
    bad = [g for g in t if g not in GEOMETRIES]
    if bad or not t:
        raise SpecError(
            f"left-turn.{field}",
            f"expected a non-empty list of names from {sorted(GEOMETRIES)}, got {list(t)}",
        )
    return t


@dataclass(frozen=True)
class LeftTurnRecipe:
    """Everything that defines a left-turn dataset (with the seed). Frozen; unknown keys fail."""

    episodes_per_geometry: int = 5  #: E, episodes (work units) per intersection geometry
    train_geometries: tuple[str, ...] = ("g0",)  #: geometries of the train split
    val_geometries: tuple[str, ...] = ("g1",)  #: geometries of the val split
    test_geometries: tuple[str, ...] = ("g2", "g3")  #: geometries of the test split
    episodes_per_shard: int = 5  #: episodes per HDF5 shard (resume granularity)
    history: int = 18  #: H, past steps in a sample (plus the current state): 1.8 s
    horizon: int = 60  #: T = K, future steps of a sample and horizon of the game: 6 s
    dt: float = 0.1  #: step (s)
    episode_steps: int = 140  #: steps of a natural run; samples at k = 0 .. episode_steps - T
    replay_extra: int = 40  #: runs go on up to this many more steps until one vehicle entered
    p_enter: float = 0.5  #: probability that the SDV's first decision is to enter
    brake_comfort: float = 3.0  #: SDV's planned braking (m/s^2)
    brake_max: float = 5.0  #: SDV committed once it cannot stop before the zone at this (m/s^2)
    acc_max: float = 2.0  #: SDV's largest acceleration (m/s^2)
    stop_gap: float = 1.0  #: SDV stops with its front this far before the conflict zone (m)
    lane_points: int = 25  #: P, points of every lane / path polyline
    lane_behind: float = 10.0  #: lane window starts this far behind the agent (m)
    lane_ahead: float = 90.0  #: ... and ends this far ahead (m)
    goal_points: int = 60  #: G, goal candidates per agent (the paper's G = 60)
    goal_range: float = 90.0  #: candidates from the agent's position to this far ahead (m)
    augment_copies: int = 4  #: extra rotated + noisy samples per original train sample
    augment_angle: float = math.pi / 8  #: rotation drawn from U[-a, a] (rad)
    augment_noise: float = 0.02  #: std (m) of the noise on the past history positions
    radius: float = (
        1.25  #: collision radius of each vehicle in the game (m); 2 r = 2.5 m, see below
    )
    w_goal: float = 1.0  #: default weights of the game (the network predicts them)
    w_lane: float = 1.0
    w_vref: float = 1.0
    w_vel: float = 0.1
    w_acc: float = 1.0
    w_jerk: float = 0.1
    w_turn: float = 1.0
    w_turnacc: float = 0.1
    w_collision: float = 10.0
    max_tries: int = 5  #: world seeds drawn per episode until a natural run is usable

    def __post_init__(self):
        p = "left-turn"
        for k in ("train_geometries", "val_geometries", "test_geometries"):
            object.__setattr__(self, k, _names(k, getattr(self, k)))
        every = self.train_geometries + self.val_geometries + self.test_geometries
        dup = sorted({g for g in every if every.count(g) > 1})
        if dup:
            raise SpecError(f"{p}.test_geometries", f"a geometry may be in one split only: {dup}")
        for k, lo in (
            ("episodes_per_geometry", 1),
            ("episodes_per_shard", 1),
            ("history", 0),
            ("horizon", 2),
            ("replay_extra", 0),
            ("lane_points", 2),
            ("goal_points", 2),
            ("augment_copies", 0),
            ("max_tries", 1),
            ("episode_steps", 2),
        ):
            v = check_size(f"{p}.{k}", getattr(self, k), SIZE_LIMITS[k], "recipe size", lo=lo)
            object.__setattr__(self, k, v)
        check_number(f"{p}.episode_steps", self.episode_steps, lo=self.horizon, integer=True)
        check_number(f"{p}.dt", self.dt, lo=0.01, hi=1.0)
        check_number(f"{p}.p_enter", self.p_enter, lo=0.0, hi=1.0)
        for k in ("brake_comfort", "brake_max", "acc_max", "lane_ahead", "goal_range", "radius"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, lo_open=True)
        for k in ("stop_gap", "lane_behind", "augment_noise"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0)
        check_number(f"{p}.augment_angle", self.augment_angle, lo=0.0, hi=math.pi)
        check_weights(p, self)
        shard = min(self.episodes_per_shard, self.episodes_per_geometry * len(self.geometries))
        check_size(
            p,
            shard * self.samples_per_episode_max() * self.sample_bytes(),
            MAX_SHARD_BYTES,
            f"bytes of one shard's samples, held in memory: {shard} episodes "
            f"(episodes_per_shard) x {self.samples_per_episode_max():,} samples (episode_steps, "
            f"horizon, augment_copies) x {self.sample_bytes():,} bytes (history, horizon, "
            "lane_points, goal_points)",
        )

    def sample_bytes(self) -> int:
        """Bytes of one sample (the arrays of :meth:`LeftTurnScenario.schema`, about)."""
        H, T, P, G = self.history, self.horizon, self.lane_points, self.goal_points
        return (H + 1) * 33 + 2 * 2 * T * 16 + 2 * 2 * P * 8 + 2 * G * 8 + 256

    def samples_per_episode_max(self) -> int:
        """Samples of one train episode: one per step with a full future, plus the copies."""
        return (self.episode_steps - self.horizon + 1) * (1 + self.augment_copies)

    @property
    def geometries(self) -> tuple[str, ...]:
        """Geometries in unit order: train, then val, then test ones."""
        return self.train_geometries + self.val_geometries + self.test_geometries

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> LeftTurnRecipe:
        """The recipe of a manifest's or ``--set``'s fields (unknown fields refused)."""
        return from_mapping(cls, d, "left-turn", "recipe field")


# --------------------------------------------------------------------------------------
# the dataset scenario
# --------------------------------------------------------------------------------------
def _unwrap_shift(theta: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Shift each agent's headings ``(..., N)`` by the multiple of ``2 pi`` that puts its
    current heading ``cur`` ``(N,)`` into ``(-pi, pi]``."""
    return theta - 2 * math.pi * np.ceil((cur - math.pi) / (2 * math.pi))


def rotate_sample(sample: dict[str, np.ndarray], phi: float) -> dict[str, np.ndarray]:
    """The sample rotated about the origin by ``phi``: positions of history, futures,
    lanes, paths and goal candidates; headings ``+ phi`` (a new dict; ``rotation += phi``)."""
    out = dict(sample)
    for k in ("history", "future"):
        x = np.array(sample[k], dtype=float)
        x[..., :2] = _rotate(x[..., :2], phi)
        x[..., 3] += phi
        out[k] = x
    for k in ("lanes", "paths", "goal_candidates"):
        out[k] = _rotate(np.asarray(sample[k], dtype=float), phi)
    out["rotation"] = float(sample.get("rotation", 0.0)) + phi
    return out


def map_fields(
    r: LeftTurnRecipe, world, pol: SDVPolicy, ego_xy, other_xy
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A scene's map fields in world coordinates: ``lanes`` ``(2, P, 2)`` (windows of the
    SDV's route and the other's lane around their positions), ``goal_candidates``
    ``(2, G, 2)`` along them, and ``vref`` ``(2,)`` (the turn's limit while the turn is in the
    SDV's window). The generator (:meth:`LeftTurnScenario.cut`, exact positions) and the
    closed-loop planner (:func:`closed_loop_scene_fields`, the other's estimate) build their
    scenes with it."""
    s_e = _progress(np.asarray(ego_xy, float), pol.route)
    s_o = _progress(np.asarray(other_xy, float), world.other_route)
    win = np.linspace(-r.lane_behind, r.lane_ahead, r.lane_points)
    ahead = np.linspace(0.0, r.goal_range, r.goal_points)
    lanes = np.stack([_at(pol.route, s_e + win)[0], _at(world.other_route, s_o + win)[0]])
    cands = np.stack([_at(pol.route, s_e + ahead)[0], _at(world.other_route, s_o + ahead)[0]])
    t0, t1 = pol.turn
    turn_in_window = s_e + r.lane_ahead > t0 and s_e - r.lane_behind < t1
    vref = np.array([pol.v_turn if turn_in_window else pol.v_lim, pol.v_lim])
    return lanes, cands, vref


def closed_loop_scene_fields(world, obs, est, frame, recipe) -> dict[str, np.ndarray]:
    """The map fields of a left-turn scene (``lanes``, ``paths``, ``vref``,
    ``goal_candidates``) for a trained planner in the closed loop, built as
    :meth:`LeftTurnScenario.cut` builds them: lane windows and goal candidates along the
    ego's route from its exact position and along the oncoming car's lane from its
    *estimated* position (``est.states[0]``), speed limits from the ego's route, in
    ``frame`` (``frame.points_in``). ``world``: a :class:`scenarios.sim.left_turn.LeftTurnWorld`
    after ``reset``; ``recipe``: the run's dataset recipe (window lengths and point counts;
    defaults where absent). Found by :func:`scenarios.sim.scene_fields`."""
    known = {f.name for f in fields(LeftTurnRecipe)}
    r = LeftTurnRecipe.from_dict({k: v for k, v in (recipe or {}).items() if k in known})
    pol = SDVPolicy(world, r, "enter")  # the route, turn interval and speed limits
    ego, other = np.asarray(obs.ego, float)[:2], np.asarray(est.states, float)[0, :2]
    lanes, cands, vref = map_fields(r, world, pol, ego, other)
    lanes = frame.points_in(lanes).astype(np.float32)
    return {
        "lanes": lanes,
        "paths": lanes.copy(),
        "vref": vref.astype(np.float32),
        "goal_candidates": frame.points_in(cands).astype(np.float32),
    }


class LeftTurnScenario(Scenario):
    """The left-turn demonstration generator (module docstring). Construct hooks:
    :meth:`world`, :meth:`agent_specs`, :meth:`game_spec`, :meth:`episode`,
    :meth:`alternative`, :meth:`cut`, :meth:`augment`."""

    name = "left-turn"
    pickled = ("recipe",)

    def __init__(self, recipe: LeftTurnRecipe | None = None):
        if recipe is not None and not isinstance(recipe, LeftTurnRecipe):
            raise SpecError("recipe", f"expected a LeftTurnRecipe, got {type(recipe).__name__}")
        self.recipe = recipe or LeftTurnRecipe()

    # ---- Scenario interface ----------------------------------------------------------

    @property
    def n_units(self) -> int:
        return len(self.recipe.geometries) * self.recipe.episodes_per_geometry

    @property
    def units_per_shard(self) -> int:
        return self.recipe.episodes_per_shard

    def geometry_of(self, index: int) -> str:
        """Geometry name of work unit ``index``."""
        return self.recipe.geometries[index // self.recipe.episodes_per_geometry]

    def split_of(self, geometry: str) -> str:
        r = self.recipe
        return (
            "train"
            if geometry in r.train_geometries
            else "val"
            if geometry in r.val_geometries
            else "test"
        )

    def split_units(self, seed: int) -> dict[str, list[int]]:
        """By geometry (module docstring); the seed does not enter."""
        out: dict[str, list[int]] = {s: [] for s in SPLITS}
        for i in range(self.n_units):
            out[self.split_of(self.geometry_of(i))].append(i)
        return out

    def schema(self) -> dict[str, FieldSpec]:
        r = self.recipe
        N, H, M, T, P, G = 2, r.history, 2, r.horizon, r.lane_points, r.goal_points
        return {
            "history": FieldSpec(
                (H + 1, N, 4), "float32", "states (x, y, v, theta) at steps k-H..k, SDV frame"
            ),
            "history_valid": FieldSpec((H + 1,), "bool", "False where before the episode start"),
            "future": FieldSpec(
                (M, N, T, 4), "float32", "states at k+1..k+T; mode 0: SDV first, 1: other first"
            ),
            "mode_valid": FieldSpec((M,), "bool", "False: that outcome is impossible (copy of gt)"),
            "gt_mode": FieldSpec((), "int8", "ground truth: the outcome of the episode"),
            "lanes": FieldSpec((N, P, 2), "float32", "map input: SDV route, other's lane"),
            "paths": FieldSpec((N, P, 2), "float32", "reference lane of each agent (game path)"),
            "vref": FieldSpec((N,), "float32", "speed limit on each agent's lane window (m/s)"),
            "goal_candidates": FieldSpec((N, G, 2), "float32", "goal points on each agent's lane"),
            "frame": FieldSpec((3,), "float64", "SDV world pose (x, y, theta) at the current step"),
            "rotation": FieldSpec((), "float32", "augmentation rotation (rad); 0: original"),
            "augmented": FieldSpec((), "bool", "True: a rotated, noisy copy (train only)"),
            "main_game": FieldSpec((), "int64", "work unit (episode) index"),
            "geometry": FieldSpec((), "int8", "index of the intersection in meta.geometries"),
            "step": FieldSpec((), "int16", "k, steps since the episode start"),
            "intent": FieldSpec((), "int8", "the SDV's first decision: 1 enter, 0 wait"),
            "aggressiveness": FieldSpec((), "float32", "the oncoming driver's character"),
            "world_seed": FieldSpec((), "int64", "LeftTurnWorld.reset seed of the episode"),
        }

    def meta(self) -> dict:
        from .sim.left_turn import GEOMETRIES

        g = self.game
        return {
            "agents": list(AGENTS),
            "state": ["x", "y", "v", "theta"],
            "modes": list(OUTCOMES),
            "geometries": sorted(GEOMETRIES),
            "splits_by_geometry": {
                "train": list(self.recipe.train_geometries),
                "val": list(self.recipe.val_geometries),
                "test": list(self.recipe.test_geometries),
            },
            "frame": "SDV at the origin, x along its heading, at the current step",
            "param_names": list(g.params.names),
            "dt": self.recipe.dt,
            "units": "metres, seconds, radians",
        }

    # ---- construct hooks ---------------------------------------------------------------
    def agent_specs(self) -> list[AgentSpec]:
        """SDV and oncoming vehicle: App. F.3 CARLA features plus the goal term."""
        return driving_agents(self.recipe, AGENTS, lane_points=self.recipe.lane_points)

    def game_spec(self) -> GameSpec:
        return driving_game_spec(self.recipe, self.agent_specs())

    @cached_property
    def game(self) -> PotentialGame:
        return PotentialGame(self.game_spec())

    def world(self, geometry: str):
        from .sim.left_turn import LeftTurnWorld

        r = self.recipe
        return LeftTurnWorld(
            geometry=geometry,
            dt=r.dt,
            max_steps=r.episode_steps + r.horizon + r.replay_extra + 1,
            noise_std=0.0,
        )

    def episode(self, geometry: str, rng: np.random.Generator):
        """A usable natural run: ``(world_seed, intent, run, snapshots)`` (module docstring).
        Raises :class:`SpecError` when ``max_tries`` draws all collide or stay undecided."""
        r = self.recipe
        w = self.world(geometry)
        for _ in range(r.max_tries):
            wseed = int(rng.integers(0, 2**31 - 1))
            intent = "enter" if rng.random() < r.p_enter else "wait"
            w.reset(wseed)
            pol = SDVPolicy(w, r, intent)
            run, snaps = simulate(
                w,
                pol,
                r.episode_steps,
                until_outcome=r.replay_extra,
                snapshots=r.episode_steps - r.horizon + 1,
            )
            if not run.collided and run.outcome is not None:
                return wseed, intent, run, snaps, w.character.aggressiveness
        raise SpecError(
            "left-turn.max_tries",
            f"{r.max_tries} world draws on {geometry} gave no usable run (collision or "
            "no vehicle entered the conflict zone)",
        )

    def alternative(self, run: Run, k: int, snap) -> np.ndarray | None:
        """States ``(T, N, 4)`` after step ``k`` of the replay towards the other outcome, or
        ``None`` when that outcome can no longer happen (module docstring)."""
        r = self.recipe
        alt = OUTCOMES[1 - OUTCOMES.index(run.outcome)]
        if any(e is not None and e <= k for e in run.entry):
            return None
        world, pol = copy.deepcopy(snap)
        if alt == "other_first" and pol.committed:
            return None
        if alt == "sdv_first" and world.committed and world.decision == "go":
            return None
        pol.force = alt
        rep, _ = simulate(world, pol, r.horizon, k0=k, until_outcome=r.replay_extra)
        if rep.collided or rep.outcome != alt or len(rep.states) < r.horizon + 1:
            return None
        return rep.states[1 : r.horizon + 1]

    def cut(self, run: Run, k: int, snap, alt: np.ndarray | None) -> dict:
        """The sample at step ``k`` in the SDV frame (no augmentation)."""
        r = self.recipe
        H, T = r.history, r.horizon
        world, pol = snap
        X = run.states
        pre = _pre_history(X[0], H, r.dt)
        full = np.concatenate([pre, X], axis=0)  # row k + H is step k
        hist = full[k : k + H + 1]
        valid = np.arange(k - H, k + 1) >= 0
        gt = OUTCOMES.index(run.outcome)
        fut = np.empty((2, 2, T, 4))
        fut[gt] = X[k + 1 : k + T + 1].transpose(1, 0, 2)
        fut[1 - gt] = fut[gt] if alt is None else alt.transpose(1, 0, 2)
        pose = X[k, 0, [0, 1, 3]].astype(float)
        # frame: positions, headings (continuous per agent, current one in (-pi, pi])
        cur = X[k, :, 3] - pose[2]
        hist_l = np.array(hist, dtype=float)
        hist_l[..., :2] = to_frame(hist[..., :2], pose)
        hist_l[..., 3] = _unwrap_shift(hist[..., 3] - pose[2], cur)
        fut_l = np.array(fut)
        fut_l[..., :2] = to_frame(fut[..., :2], pose)
        fut_l[..., 3] = _unwrap_shift(fut[..., 3] - pose[2], cur[:, None])
        lanes, cands, vref = map_fields(r, world, pol, X[k, 0, :2], X[k, 1, :2])
        lanes = to_frame(lanes, pose)
        return {
            "history": hist_l,
            "history_valid": valid,
            "future": fut_l,
            "mode_valid": np.array([True, True]) if alt is not None else np.arange(2) == gt,
            "gt_mode": gt,
            "lanes": lanes,
            "paths": lanes,
            "vref": np.array(vref),
            "goal_candidates": to_frame(cands, pose),
            "frame": pose,
            "rotation": 0.0,
            "augmented": False,
            "step": k,
        }

    def augment(self, sample: dict, rng: np.random.Generator) -> dict:
        """One augmented copy (module docstring): rotation of the whole sample, noise on the
        past history positions."""
        r = self.recipe
        out = rotate_sample(sample, float(rng.uniform(-r.augment_angle, r.augment_angle)))
        h = out["history"]
        h[:-1, :, :2] += rng.normal(0.0, r.augment_noise, size=h[:-1, :, :2].shape)
        out["augmented"] = True
        return out

    # ---- one work unit -------------------------------------------------------------------
    def run_unit(self, index: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
        """Every sample of episode ``index`` (module docstring)."""
        from .sim.left_turn import GEOMETRIES

        r = self.recipe
        geo = self.geometry_of(index)
        ep_ss, aug_ss = seed.spawn(2)
        wseed, intent, run, snaps, aggr = self.episode(geo, np.random.default_rng(ep_ss))
        aug_rng = np.random.default_rng(aug_ss)
        train = self.split_of(geo) == "train"
        common = {
            "main_game": index,
            "geometry": sorted(GEOMETRIES).index(geo),
            "intent": int(intent == "enter"),
            "aggressiveness": aggr,
            "world_seed": wseed,
        }
        rows = []
        for k in range(r.episode_steps - r.horizon + 1):
            s = self.cut(run, k, snaps[k], self.alternative(run, k, snaps[k]))
            s.update(common)
            rows.append(s)
            if train:
                rows.extend({**self.augment(s, aug_rng)} for _ in range(r.augment_copies))
        return stack_rows(rows, self.schema())


def _pre_history(x0: np.ndarray, steps: int, dt: float) -> np.ndarray:
    """States at steps ``-steps..-1`` (``(steps, N, 4)``): constant-velocity extrapolation."""
    j = np.arange(-steps, 0, dtype=float)[:, None] * dt  # (steps, 1)
    out = np.repeat(x0[None], steps, axis=0).astype(float)
    out[..., 0] = x0[None, :, 0] + j * x0[None, :, 2] * np.cos(x0[None, :, 3])
    out[..., 1] = x0[None, :, 1] + j * x0[None, :, 2] * np.sin(x0[None, :, 3])
    return out
