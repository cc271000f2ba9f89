"""RPI: simulated robot-pedestrian interaction, multi-modal demonstrations (paper App. E.1).

Two ground truths (:attr:`RPIRecipe.ground_truth`), both recorded in the manifest
    ``"peters"`` (default): the general iLQ game of Peters et al. (2020) that the paper's
    RPI set was built with (:mod:`scenarios.rpi_peters`: unicycles starting at rest on the
    3 m circle, 10 s horizon ``K = game_horizon = 100``, the reference's costs, solves
    closer than 0.75 m dropped, DBSCAN modes; the proximity weight is drawn per main
    game). Samples are cut only at steps ``k >= H`` of the executed main mode, so every
    history is real (``history_valid`` all true); the future is the first ``T = horizon``
    (40) steps of the subgame modes. The model's game (:attr:`RPIScenario.game`) stays the
    App. F.3 game below at horizon ``T``.
    ``"potential"``: the recipe described in the rest of this docstring (the paper's own
    potential game as ground truth); its datasets are unchanged by the Peters recipe.

Scene (positions in metres, the fixed world frame of the paper; agent order
``[robot, pedestrian]``, both extended unicycles ``(x, y, v, theta)`` / ``(a, omega)``)
    The robot starts at :attr:`RPIRecipe.robot_start` and goes to
    :attr:`RPIRecipe.robot_goal` in every main game. The pedestrian starts on the circle of
    radius :attr:`RPIRecipe.circle` (3 m) around the origin at an angle drawn uniformly
    outside the arc of half-width :attr:`RPIRecipe.exclude` around the robot's start (so it
    does not start inside the robot), and its goal lies across the circle, at the start
    angle ``+ pi + U(-goal_jitter, goal_jitter)``. Both start with speed
    :attr:`RPIRecipe.speed0` heading straight to their goal; radius ``r = 0.25 m`` each.

Game (App. F.3)
    Horizon ``K = 40``, ``dt = 0.1`` s. Own features of each agent: goal (terminal),
    velocity, acceleration, velocity bound, acceleration bound, turn rate, turn-rate bound
    (soft bounds ``max(0, g)``); pair feature: collision at every step, with a safety
    margin of 0.15 m added to ``2 r``: a soft penalty lets the solutions penetrate a few
    centimetres, and without the margin ~80 % of the ground-truth futures overlapped
    (``dist < 2 r``), which made the overlap rate meaningless. Own weights are
    fixed by the recipe; the collision weight is drawn ``U(collision_weight)`` once per
    main game and shared by the main game and all its subgames.

Main game, subgames, samples (one work unit = one main game, see :mod:`scenarios.dataset`)
    1. Draw the configuration (pedestrian start/goal angles, collision weight) from the
       unit's seed and solve the main game multi-modally (:meth:`RPIScenario.solve_modes`:
       ``n_samples`` solves from random initial strategies, clustered into modes with
       shares); keep the ``M = 2`` modes with the largest shares.
    2. For each kept main mode the agents execute its open-loop controls. At every step
       ``k = 0, 1, ...`` (every ``dt``) while the agents have not passed each other
       (:meth:`RPIScenario.passed`: their distance is still decreasing) and ``k < K``, the
       *subgame* from the executed state ``x_k`` (same goals and weights) is solved and
       clustered the same way (for ``k = 0`` it is the main game: its modes are reused).
       ``warm_start`` of its initial strategies are the previous subgame's modes shifted
       by one step (the executed one first), so a mode once found is tracked; a subgame
       whose solves all fail (iteration cap, collision) gives no sample at that step.
    3. A sample is: the history ``x_{k-18..k}`` of both agents (1.8 s + the current
       state), the ``M = 2`` joint futures of the subgame over ``T = 40`` steps (4 s), their
       controls and shares, the goals and the full parameter vector of the subgame.

History before the start (potential ground truth)
    Steps before ``k = 0`` do not exist in a main game; they are filled by a constant-
    velocity backward extrapolation of ``x_0`` and marked ``False`` in ``history_valid``
    (measured: 74 % of 389 samples have such a step, docs/rpi.md). The Peters ground truth has none.

One mode only
    When clustering finds a single mode, slot 1 repeats mode 0 with ``mode_valid =
    [True, False]`` and ``mode_share = [1, 0]``: the arrays keep a fixed shape and a
    loss can mask the copy (or use it, which is the same as predicting one mode twice).

Sample count
    Each main game yields (main modes found) x (steps until passing) samples, 24 to 50,
    about 30 on average (measured in ``docs/rpi.md``). The paper reports 60,338 samples
    from 20 main games (~3,000 per main game), which one executed path per mode cannot
    produce; the text does not say what else varied inside a main game. This recipe keeps
    the order of the sample count instead: :meth:`RPIRecipe.full` has 2,000 main games
    (about 58k samples), :meth:`RPIRecipe.for_samples` scales the number of main games.

Limits (checked when a recipe is made, before any work)
    ``for_samples`` at most :data:`MAX_SAMPLES` (10 million) samples; every count and size
    of the recipe at most its :data:`SIZE_LIMITS` entry (``main_games`` 1,000,000,
    ``horizon``, ``history`` and ``game_horizon`` 1,000, ``modes`` 8, ``n_samples`` and
    ``sub_samples`` 10,000, ...); and the samples of one shard at most
    :data:`MAX_SHARD_BYTES` (2 GiB, estimated from the sizes: a shard is held in memory
    until it is written).

Fields of one sample (``N = 2`` agents, ``nx = 4``, ``nu = 2``, ``H = 18``, ``M = 2``,
``T = 40``; see :meth:`RPIScenario.schema`)::

    history          (H+1, N, nx) float32   states at steps k-H..k (last = current)
    history_valid    (H+1,)       bool      False: extrapolated before the main game start
    future           (M, N, T, nx) float32  subgame mode states at steps k+1..k+T
    future_controls  (M, N, T, nu) float32  their controls at steps k..k+T-1
    mode_share       (M,)         float32   fraction of the subgame solves in each mode
    mode_valid       (M,)         bool      False: copy of mode 0 (one mode found)
    goals            (N, 2)       float32   goal positions
    params           (n_p,)       float64   subgame parameter vector (names in the manifest)
    collision_weight ()           float32   the main game's collision weight
    main_game        ()           int64     work unit index (= main-game configuration)
    main_mode        ()           int8      which main-game mode the agents execute
    main_share       ()           float32   that mode's share in the main game
    step             ()           int16     k, steps since the main game start
    gt_mode          ()           int8      ground truth: the future mode closest to what the
                                            agents execute next (the main mode's continuation)
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any

import numpy as np

from epo_casadi import (
    Acceleration,
    AccelerationBound,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    PotentialGame,
    TurnRate,
    TurnRateBound,
    Velocity,
    VelocityBound,
)
from epo_casadi.errors import SpecError, check_number, check_size, from_mapping

from .dataset import FieldSpec, Scenario

__all__ = [
    "RPIRecipe",
    "RPIScenario",
    "MainGameConfig",
    "Mode",
    "GROUND_TRUTHS",
    "SAMPLES_PER_GAME",
    "SAMPLES_PER_GAME_BY_TRUTH",
    "MAX_SAMPLES",
    "SIZE_LIMITS",
    "MAX_SHARD_BYTES",
]

#: most samples :meth:`RPIRecipe.for_samples` (``epo generate rpi --samples``) asks for
MAX_SAMPLES = 10_000_000
#: upper bounds of the recipe's counts and sizes, checked before any work (each one is
#: far above what a dataset needs; a larger value is refused, not misread)
SIZE_LIMITS: dict[str, int] = {
    "main_games": 1_000_000,
    "games_per_shard": 10_000,
    "horizon": 1_000,
    "history": 1_000,
    "modes": 8,
    "n_samples": 10_000,
    "max_iter": 100_000,
    "max_subgames": 10_000,
    "game_horizon": 1_000,
    "sub_samples": 10_000,
    "dbscan_min_points": 10_000,
}
#: most bytes of the samples of one shard (held in memory until the shard is written)
MAX_SHARD_BYTES = 2 * 2**30

#: measured mean samples per main game of the potential recipe (docs/rpi.md)
SAMPLES_PER_GAME = 30.0
#: measured mean samples per main game of each ground truth (docs/rpi.md)
SAMPLES_PER_GAME_BY_TRUTH = {"potential": SAMPLES_PER_GAME, "peters": 70.0}
#: samples of the paper's RPI set (47,822 / 6,228 / 6,228 train / val / test)
PAPER_SAMPLES = 60_338
AGENTS = ("robot", "pedestrian")


def _num(name, v, lo=None, hi=None, integer=False):
    check_number(f"rpi.{name}", v, lo=lo, hi=hi, integer=integer)


def _pair(name, v, positive=False, ordered=False):
    try:
        t = tuple(float(x) for x in v)
    except (TypeError, ValueError):
        raise SpecError(f"rpi.{name}", f"expected two numbers, got {v!r}") from None
    if len(t) != 2 or not all(math.isfinite(x) for x in t):
        raise SpecError(f"rpi.{name}", f"expected two finite numbers, got {v!r}")
    if positive and min(t) <= 0:
        raise SpecError(f"rpi.{name}", f"expected numbers > 0, got {list(t)}")
    if ordered and not t[0] <= t[1]:
        raise SpecError(f"rpi.{name}", f"expected low <= high, got {list(t)}")
    return t


#: the ground truths a recipe can generate (module docstring)
GROUND_TRUTHS = ("peters", "potential")

#: defaults of the fields that depend on the ground truth (``None`` in the dataclass)
_TRUTH_DEFAULTS: dict[str, dict[str, Any]] = {
    "potential": dict(
        main_games=2000, speed0=(1.0, 1.0), goal_jitter=30.0, n_samples=8, max_iter=30
    ),
    "peters": dict(
        main_games=math.ceil(PAPER_SAMPLES / SAMPLES_PER_GAME_BY_TRUTH["peters"]),
        speed0=(0.0, 0.0),
        goal_jitter=0.0,
        n_samples=100,
        max_iter=100,
    ),
}
#: fields of the Peters ground truth only (refused with ``ground_truth="potential"``)
_PETERS_DEFAULTS: dict[str, Any] = dict(
    game_horizon=100,
    sub_samples=8,
    control_cost=10.0,
    speed_cost=30.0,
    bound_cost=50.0,
    turn_rate_bound=10.0,
    acceleration_bound=9.81,
    speed_bounds=(-0.05, 2.0),
    proximity_radius=1.5,
    proximity_weight=(10.0, 50.0),
    goal_cost=300.0,
    goal_steps=2,
    min_distance=0.75,
    dbscan_eps=10.0,
    dbscan_min_points=2,
    ilq_tol=1e-2,
)


@dataclass(frozen=True)
class RPIRecipe:
    """Everything that defines an RPI dataset (with the seed). Frozen; unknown keys fail.

    ``ground_truth`` chooses the game that makes the demonstrations (module docstring):
    ``"peters"`` (default) or ``"potential"`` (the recipe before 2026-11-30). Fields left
    ``None`` take that ground truth's default; the Peters fields (from ``game_horizon``
    on) are refused with ``"potential"``. The App. F.3 fields (``vmax`` .. ``collision_margin``)
    define the potential ground truth and, with either ground truth, the model's game
    (:attr:`RPIScenario.game`).
    """

    main_games: int | None = None  #: work units (~60k samples: potential 2000, Peters 862)
    games_per_shard: int = 20  #: main games per HDF5 shard (resume granularity)
    horizon: int = 40  #: T, predicted future steps (and K of the potential games / model game)
    history: int = 18  #: H, past steps in a sample (plus the current state)
    modes: int = 2  #: M, joint futures per sample
    dt: float = 0.1  #: step length (s)
    radius: float = 0.25  #: agent radius r_i (m)
    circle: float = 3.0  #: radius of the pedestrian start/goal circle (m)
    robot_start: tuple[float, float] = (-3.0, 0.0)  #: fixed robot start (m)
    robot_goal: tuple[float, float] = (3.0, 0.0)  #: fixed robot goal (m)
    exclude: float = 45.0  #: no pedestrian start within this angle (deg) of the robot start
    goal_jitter: float | None = None  #: ped. goal angle = start + 180 + U(-j, j) (deg); 30 / 0
    speed0: tuple[float, float] | None = None  #: initial speeds (robot, ped.) (m/s); 1 / 0
    vmax: tuple[float, float] = (2.0, 1.6)  #: velocity upper bounds (robot, pedestrian) (m/s)
    amax: float = 2.0  #: |acceleration| bound (m/s^2)
    wmax: float = 1.5  #: |turn rate| bound (rad/s)
    w_goal: float = 3.0  #: goal weight
    w_vel: float = 0.5  #: velocity weight
    w_acc: float = 1.0  #: acceleration weight
    w_turn: float = 1.0  #: turn-rate weight
    w_bound: float = 5.0  #: weight of every soft bound
    collision_weight: tuple[float, float] = (5.0, 30.0)  #: U(lo, hi) per main game
    collision_margin: float = 0.15  #: safety distance (m) added to 2 r: the soft penalty then keeps the agents >= 2 r apart
    solver: str = "ilq"  #: multimodal engine: "ilq" or "lm"
    n_samples: int | None = None  #: solves per main game (potential: and subgame); 8 / 100
    warm_start: int = 2  #: of those, initial strategies from the previous subgame's modes
    max_iter: int | None = None  #: iteration cap of each solve (hitting it drops it); 30 / 100
    compiled: bool = True  #: iLQ Riccati recursion as generated C (needs a C compiler)
    max_subgames: int | None = None  #: cap of subgames per executed mode (None: until passing)
    split: tuple[float, float, float] = (0.8, 0.1, 0.1)  #: train/val/test fractions of main games
    ground_truth: str = "peters"  #: "peters" (general iLQ game, DBSCAN) or "potential"
    # ---- Peters ground truth only (None: the default in brackets; units of the reference)
    game_horizon: int | None = None  #: K of the main game and subgames [100: 10 s]
    sub_samples: int | None = None  #: solves per subgame [8]
    control_cost: float | None = None  #: 1/2 c |u|^2 [10]
    speed_cost: float | None = None  #: 1/2 c v^2 [30]
    bound_cost: float | None = None  #: c gap^2 of every soft bound [50]
    turn_rate_bound: float | None = None  #: |omega| soft bound (deg/s) [10]
    acceleration_bound: float | None = None  #: |a| soft bound (m/s^2) [9.81]
    speed_bounds: tuple[float, float] | None = None  #: v soft bounds (m/s) [(-0.05, 2)]
    proximity_radius: float | None = None  #: proximity cost while d < this (m) [1.5]
    proximity_weight: tuple[float, float] | None = (
        None  #: w (d - R)^2, U(lo, hi) per main game [(10, 50)]
    )
    goal_cost: float | None = None  #: 1/2 c |(x, y, theta) - goal|^2 [300]
    goal_steps: int | None = None  #: last states with the goal cost (t >= T - 1.5 dt) [2]
    min_distance: float | None = None  #: drop solves closer than this (m) [0.75]
    dbscan_eps: float | None = None  #: DBSCAN radius on squared state distances [10]
    dbscan_min_points: int | None = None  #: DBSCAN core points (itself included) [2]
    ilq_tol: float | None = None  #: iLQ stops (converged) at max |a| <= this [1e-2]

    def __post_init__(self):
        if not isinstance(self.ground_truth, str) or self.ground_truth not in GROUND_TRUTHS:
            raise SpecError(
                "rpi.ground_truth",
                f"expected one of {list(GROUND_TRUTHS)}, got {self.ground_truth!r}",
            )
        peters = self.ground_truth == "peters"
        for k, v in _TRUTH_DEFAULTS[self.ground_truth].items():
            if getattr(self, k) is None:
                object.__setattr__(self, k, v)
        for k, v in _PETERS_DEFAULTS.items():
            if not peters and getattr(self, k) is not None:
                raise SpecError(
                    f"rpi.{k}", "applies to ground_truth='peters' only, this recipe is 'potential'"
                )
            if peters and getattr(self, k) is None:
                object.__setattr__(self, k, v)
        self._check_sizes()
        if peters:
            self._check_peters()
        _num("main_games", self.main_games, 3, integer=True)
        _num("games_per_shard", self.games_per_shard, 1, integer=True)
        _num("horizon", self.horizon, 2, integer=True)
        _num("history", self.history, 0, integer=True)
        _num("modes", self.modes, 1, integer=True)
        _num("dt", self.dt, 1e-6)
        _num("radius", self.radius, 0.0)
        _num("collision_margin", self.collision_margin, 0.0)
        _num("circle", self.circle, 1e-6)
        _num("exclude", self.exclude, 0.0, 179.0)
        _num("goal_jitter", self.goal_jitter, 0.0, 180.0)
        for k in ("amax", "wmax"):
            _num(k, getattr(self, k), 1e-9)
        for k in ("w_goal", "w_vel", "w_acc", "w_turn", "w_bound"):
            _num(k, getattr(self, k), 0.0)
        object.__setattr__(self, "robot_start", _pair("robot_start", self.robot_start))
        object.__setattr__(self, "robot_goal", _pair("robot_goal", self.robot_goal))
        object.__setattr__(self, "speed0", _pair("speed0", self.speed0))
        object.__setattr__(self, "vmax", _pair("vmax", self.vmax, positive=True))
        object.__setattr__(
            self, "collision_weight", _pair("collision_weight", self.collision_weight, ordered=True)
        )
        if self.solver not in ("ilq", "lm"):
            raise SpecError("rpi.solver", f"expected 'ilq' or 'lm', got {self.solver!r}")
        _num("n_samples", self.n_samples, 1, integer=True)
        _num("warm_start", self.warm_start, 0, self.n_samples, integer=True)
        _num("max_iter", self.max_iter, 1, integer=True)
        if not isinstance(self.compiled, bool):
            raise SpecError("rpi.compiled", f"expected true or false, got {self.compiled!r}")
        if self.max_subgames is not None:
            _num("max_subgames", self.max_subgames, 1, integer=True)
        try:
            sp = tuple(float(x) for x in self.split)
        except (TypeError, ValueError):
            raise SpecError("rpi.split", f"expected three fractions, got {self.split!r}") from None
        if len(sp) != 3 or min(sp) <= 0 or abs(sum(sp) - 1) > 1e-9:
            raise SpecError(
                "rpi.split", f"expected three fractions > 0 summing to 1, got {self.split!r}"
            )
        object.__setattr__(self, "split", sp)
        self._check_shard_bytes()

    def _check_sizes(self):
        """Every count and size at most its :data:`SIZE_LIMITS` entry (before any work)."""
        for k, limit in SIZE_LIMITS.items():
            v = getattr(self, k)
            if v is None:  # max_subgames: no cap; Peters fields of a potential recipe
                continue
            lo = {"main_games": 3, "horizon": 2, "history": 0}.get(k, 1)
            object.__setattr__(self, k, check_size(f"rpi.{k}", v, limit, "recipe size", lo=lo))

    def sample_bytes(self) -> int:
        """Bytes of one sample (the arrays of :meth:`RPIScenario.schema`; ``params``
        estimated at 64 values)."""
        H, M, T = self.history, self.modes, self.horizon
        return (H + 1) * 2 * 4 * 4 + (H + 1) + M * 2 * T * 6 * 4 + M * 5 + 2 * 2 * 4 + 64 * 8 + 20

    def samples_per_game_max(self) -> int:
        """Most samples one main game can give: one per executed main mode and subgame."""
        steps = self.game_horizon if self.ground_truth == "peters" else self.horizon
        if self.max_subgames is not None:
            steps = min(steps, self.max_subgames)
        return self.modes * steps

    def _check_shard_bytes(self):
        per = self.sample_bytes() * self.samples_per_game_max()
        shard = min(self.games_per_shard, self.main_games)
        check_size(
            "rpi",
            per * shard,
            MAX_SHARD_BYTES,
            f"bytes of one shard's samples, held in memory: {shard} main games "
            f"(games_per_shard) x {self.samples_per_game_max():,} samples (modes x subgames) "
            f"x {self.sample_bytes():,} bytes (history, modes, horizon)",
        )

    def _check_peters(self):
        _num("game_horizon", self.game_horizon, self.horizon, integer=True)
        _num("sub_samples", self.sub_samples, 1, integer=True)
        _num("warm_start", self.warm_start, 0, self.sub_samples, integer=True)
        for k in ("control_cost", "speed_cost", "bound_cost", "goal_cost"):
            _num(k, getattr(self, k), 0.0)
        for k in ("turn_rate_bound", "acceleration_bound", "dbscan_eps", "ilq_tol"):
            _num(k, getattr(self, k), 1e-12)
        _num("proximity_radius", self.proximity_radius, 2 * self.radius)
        _num("goal_steps", self.goal_steps, 1, self.game_horizon, integer=True)
        _num("min_distance", self.min_distance, 0.0)
        _num("dbscan_min_points", self.dbscan_min_points, 1, integer=True)
        object.__setattr__(
            self, "speed_bounds", _pair("speed_bounds", self.speed_bounds, ordered=True)
        )
        w = _pair("proximity_weight", self.proximity_weight, ordered=True)
        if w[0] < 0:
            raise SpecError("rpi.proximity_weight", f"expected weights >= 0, got {list(w)}")
        object.__setattr__(self, "proximity_weight", w)
        if self.solver != "ilq":
            raise SpecError(
                "rpi.solver", f"ground_truth='peters' is solved by 'ilq' only, got {self.solver!r}"
            )

    @property
    def samples_per_game(self) -> float:
        """Measured mean samples per main game of this ground truth (docs/rpi.md)."""
        return SAMPLES_PER_GAME_BY_TRUTH[self.ground_truth]

    @classmethod
    def full(cls, **overrides) -> RPIRecipe:
        """The full-size dataset: about 60k samples (the default ``main_games``: 2,000 for
        the potential ground truth, ``ceil(60,338 / 70) = 862`` for Peters)."""
        return cls(**overrides)

    @classmethod
    def for_samples(cls, samples: int, **overrides) -> RPIRecipe:
        """About ``samples`` samples: ``ceil(samples / per)`` main games (at least 3), ``per``
        the measured samples per main game of the ground truth (:data:`SAMPLES_PER_GAME_BY_TRUTH`:
        potential 30, Peters 70); at most :data:`MAX_SAMPLES`.

        The exact count depends on the games (see the module docstring); the manifest
        records it. Shards shrink so that a small set still has a few per split.
        """
        samples = check_size("samples", samples, MAX_SAMPLES, "samples of one dataset")
        truth = overrides.get("ground_truth", "peters")
        per = SAMPLES_PER_GAME_BY_TRUTH.get(truth, SAMPLES_PER_GAME)
        games = max(3, math.ceil(samples / per))
        base = dict(
            main_games=games,
            games_per_shard=max(1, min(cls.games_per_shard, math.ceil(games / 30))),
        )
        base.update(overrides)
        return cls.from_dict(base)

    def to_dict(self) -> dict:
        d = asdict(self)
        if self.ground_truth != "peters":
            d = {k: v for k, v in d.items() if k not in _PETERS_DEFAULTS}
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> RPIRecipe:
        """The recipe of a manifest's or ``--set``'s fields (unknown fields refused)."""
        return from_mapping(cls, d, "rpi", "recipe field")


@dataclass(frozen=True)
class MainGameConfig:
    """The random draws of one main game."""

    index: int
    ped_start_angle: float  # rad
    ped_goal_angle: float  # rad
    collision_weight: float
    x0: np.ndarray  # (N, 4) initial states
    goals: np.ndarray  # (N, 2)


@dataclass(frozen=True)
class Mode:
    """One clustered strategy: joint controls ``(n_u,)``, states ``(n_x,)``, share in [0, 1]."""

    controls: np.ndarray
    states: np.ndarray
    share: float


class RPIScenario(Scenario):
    """The RPI generator. Override the construct hooks to change the scene:

    :meth:`agent_specs`, :meth:`game_spec`, :meth:`sample_config`, :meth:`params`,
    :meth:`solve_modes`, :meth:`passed`, :meth:`pre_history`.
    """

    name = "rpi"
    pickled = ("recipe",)  # the CasADi game is rebuilt in the worker

    def __init__(self, recipe: RPIRecipe | None = None):
        if recipe is not None and not isinstance(recipe, RPIRecipe):
            raise SpecError("recipe", f"expected an RPIRecipe, got {type(recipe).__name__}")
        self.recipe = recipe or RPIRecipe()

    # ---- Scenario interface ----------------------------------------------------------

    @property
    def n_units(self) -> int:
        return self.recipe.main_games

    @property
    def units_per_shard(self) -> int:
        return self.recipe.games_per_shard

    @property
    def split_fractions(self):
        return self.recipe.split

    def schema(self) -> dict[str, FieldSpec]:
        r = self.recipe
        N, H, M, T = 2, r.history, r.modes, r.horizon
        n_p = self._n_params()
        return {
            "history": FieldSpec(
                (H + 1, N, 4), "float32", "states (x, y, v, theta) at steps k-H..k"
            ),
            "history_valid": FieldSpec(
                (H + 1,), "bool", "False where extrapolated before the main game"
            ),
            "future": FieldSpec((M, N, T, 4), "float32", "subgame mode states at steps k+1..k+T"),
            "future_controls": FieldSpec(
                (M, N, T, 2), "float32", "subgame mode controls (a, omega) at k..k+T-1"
            ),
            "mode_share": FieldSpec((M,), "float32", "share of the subgame solves in each mode"),
            "mode_valid": FieldSpec((M,), "bool", "False: a copy of mode 0 (fewer modes found)"),
            "goals": FieldSpec((N, 2), "float32", "goal positions"),
            "params": FieldSpec((n_p,), "float64", "subgame parameter vector (meta.param_names)"),
            "collision_weight": FieldSpec((), "float32", "collision weight of the main game"),
            "main_game": FieldSpec((), "int64", "main game (work unit) index"),
            "main_mode": FieldSpec((), "int8", "main-game mode the agents execute"),
            "main_share": FieldSpec((), "float32", "share of that main-game mode"),
            "step": FieldSpec((), "int16", "steps since the main game start"),
            "gt_mode": FieldSpec(
                (), "int8", "ground truth: index of the future mode the agents follow"
            ),
        }

    def meta(self) -> dict:
        g = self.truth_game
        return {
            "agents": list(AGENTS),
            "state": ["x", "y", "v", "theta"],
            "control": ["a", "omega"],
            "param_names": list(g.params.names),
            "dt": self.recipe.dt,
            "units": "metres, seconds, radians",
        }

    # ---- construct hooks ---------------------------------------------------------------
    def agent_specs(self) -> list[AgentSpec]:
        """Robot and pedestrian: App. F.3 features with the recipe's weights and bounds."""
        r = self.recipe
        out = []
        for n, name in enumerate(AGENTS):
            feats = [
                Goal(weight=r.w_goal),
                Velocity(weight=r.w_vel),
                Acceleration(weight=r.w_acc),
                VelocityBound(lower=0.0, upper=r.vmax[n], weight=r.w_bound),
                AccelerationBound(lower=-r.amax, upper=r.amax, weight=r.w_bound),
                TurnRate(weight=r.w_turn),
                TurnRateBound(lower=-r.wmax, upper=r.wmax, weight=r.w_bound),
            ]
            out.append(AgentSpec(name, "unicycle", feats, radius=r.radius))
        return out

    def game_spec(self) -> GameSpec:
        r = self.recipe
        w = 0.5 * (r.collision_weight[0] + r.collision_weight[1])
        return GameSpec(
            self.agent_specs(),
            [Collision(weight=w, every=1, margin=r.collision_margin)],
            horizon=r.horizon,
            dt=r.dt,
        )

    @cached_property
    def game(self) -> PotentialGame:
        """The model's game: App. F.3 features at horizon ``T`` (built once per process).

        With ``ground_truth="potential"`` it is also the ground truth's game; learning
        builds a dataset's game from the manifest recipe through this property.
        """
        return PotentialGame(self.game_spec())

    @cached_property
    def truth_game(self) -> PotentialGame:
        """The game the demonstrations are solved in (:attr:`game` for ``"potential"``,
        :func:`scenarios.rpi_peters.peters_game_spec` for ``"peters"``)."""
        if self.recipe.ground_truth == "potential":
            return self.game
        from .rpi_peters import peters_game_spec

        return PotentialGame(peters_game_spec(self.recipe, AGENTS))

    def _n_params(self) -> int:
        return self.truth_game.n_p

    def sample_config(self, index: int, rng: np.random.Generator) -> MainGameConfig:
        """Pedestrian start/goal angles and the collision weight of main game ``index``."""
        r = self.recipe
        rs, rg = np.asarray(r.robot_start), np.asarray(r.robot_goal)
        robot_angle = math.atan2(rs[1], rs[0])
        ex = math.radians(r.exclude)
        phi = robot_angle + ex + rng.uniform(0.0, 2 * math.pi - 2 * ex)
        goal = phi + math.pi + rng.uniform(-1.0, 1.0) * math.radians(r.goal_jitter)
        peters = r.ground_truth == "peters"
        wc = rng.uniform(*(r.proximity_weight if peters else r.collision_weight))
        ps = r.circle * np.array([math.cos(phi), math.sin(phi)])
        pg = r.circle * np.array([math.cos(goal), math.sin(goal)])
        x0 = []
        for n, (s, g) in enumerate(((rs, rg), (ps, pg))):
            d = g - s
            x0.append([s[0], s[1], r.speed0[n], math.atan2(d[1], d[0])])
        wrap = lambda a: (a + math.pi) % (2 * math.pi) - math.pi  # noqa: E731
        return MainGameConfig(
            index, wrap(phi), wrap(goal), float(wc), np.array(x0), np.stack([rg, pg])
        )

    def params(self, config: MainGameConfig, x: np.ndarray | None = None) -> np.ndarray:
        """Parameter vector of the ground-truth game (:attr:`truth_game`) from state ``x``
        (``(N, 4)``; default: start). Peters: the goal heading of each agent is its
        initial heading (start to goal) and the proximity weight ``sqrt(2 w)``."""
        x = config.x0 if x is None else np.asarray(x).reshape(2, 4)
        vals = {}
        for n, a in enumerate(AGENTS):
            vals[f"x0.{a}"] = x[n]
            vals[f"goal.{a}"] = config.goals[n]
        if self.recipe.ground_truth == "peters":
            for n, a in enumerate(AGENTS):
                vals[f"goal_heading.{a}"] = [config.x0[n, 3]]
            vals["w.robot-pedestrian.proximity"] = [math.sqrt(2 * config.collision_weight)]
        else:
            vals["w.robot-pedestrian.collision"] = [config.collision_weight]
        return self.truth_game.params.pack(vals)

    def solver_options(self):
        """Options of every solve (:class:`solvers.ilq.ILQOptions` or ``LMOptions``)."""
        r = self.recipe
        if r.solver == "ilq":
            from solvers.ilq import ILQOptions

            # the recipe's iLQ: a solve that stalls is dropped, as when the recipe was made
            # (no kink continuation, secant step or restart from LM, which came later and
            # would keep other samples: a dataset must not change when it is resumed)
            pinned = dict(kink_widths=(), adaptive_step=False, restart=False)
            if r.ground_truth == "peters":
                return ILQOptions(max_iter=r.max_iter, tol=r.ilq_tol, compiled=r.compiled, **pinned)
            return ILQOptions(max_iter=r.max_iter, compiled=r.compiled, **pinned)
        from solvers.lm import LMOptions

        return LMOptions(steps=r.max_iter, threads=1)

    def solve_peters_modes(
        self, p: np.ndarray, seed: int, warm: list[Mode] | None = None, shift: int = 1
    ) -> list[Mode]:
        """Peters ground truth: modes of :attr:`truth_game` at ``p``, sorted by share.

        ``n_samples`` solves for a main game (``warm`` is None), ``sub_samples`` for a
        subgame, of which the first ``min(warm_start, len(warm))`` start from ``warm``'s
        controls shifted by ``shift`` steps (last control repeated); the others from
        :func:`solvers.multimodal.sinusoid_sampler`. Dropping and DBSCAN as in
        :func:`scenarios.rpi_peters.solve_peters_modes`. Deterministic for a ``seed``.
        """
        from solvers.multimodal import sinusoid_sampler

        from .rpi_peters import solve_peters_modes

        r = self.recipe
        g = self.truth_game
        n = r.n_samples if warm is None else r.sub_samples
        U0 = sinusoid_sampler(g, p, n, np.random.default_rng(int(seed)))
        for j, m in enumerate((warm or [])[: r.warm_start]):
            parts = [
                np.concatenate([u[shift:], np.repeat(u[-1:], shift, axis=0)])
                for u in g.split_controls(m.controls)
            ]
            U0[j] = g.join_controls(parts)
        modes, _ = solve_peters_modes(
            g, p, U0, self.solver_options(), r.min_distance, r.dbscan_eps, r.dbscan_min_points
        )
        return [Mode(m.controls, m.states, m.share) for m in modes]

    def solve_modes(self, p: np.ndarray, seed: int, warm: list[Mode] | None = None) -> list[Mode]:
        """Multi-modal solve of the game at ``p``: modes sorted by share (largest first).

        :func:`solvers.multimodal.solve_multimodal` with the recipe's ``solver``,
        ``n_samples`` and options; deterministic for a given ``seed``. ``warm``: modes of
        the previous subgame; the first ``min(warm_start, len(warm))`` initial strategies
        are their controls shifted by one step (last control repeated), the others are
        the default sinusoid samples. May return no mode (every solve failed or collided).
        """
        from solvers.multimodal import sinusoid_sampler, solve_multimodal

        r = self.recipe
        g = self.game
        shifted = []
        for m in (warm or [])[: r.warm_start]:
            parts = [np.concatenate([u[1:], u[-1:]]) for u in g.split_controls(m.controls)]
            shifted.append(g.join_controls(parts))

        def sampler(game, p_, n, rng):
            U = sinusoid_sampler(game, p_, n, rng)
            if shifted:
                U[: len(shifted)] = shifted
            return U

        res = solve_multimodal(
            g,
            p,
            n_samples=r.n_samples,
            seed=int(seed),
            solver=r.solver,
            options=self.solver_options(),
            sampler=sampler,
        )
        return [
            Mode(
                np.asarray(m.controls, float).reshape(-1),
                np.asarray(m.states, float).reshape(-1),
                float(m.share),
            )
            for m in res.modes
        ]  # already sorted by share

    def passed(self, xk: np.ndarray) -> bool:
        """Whether the agents have passed each other at state ``xk`` (``(N, 4)``).

        Passed = past the closest approach: the distance is increasing,
        ``(p_1 - p_0) . (v_1 - v_0) > 0`` with ``v = speed * (cos theta, sin theta)``.
        """
        rel = xk[1, :2] - xk[0, :2]
        vel = [x[2] * np.array([math.cos(x[3]), math.sin(x[3])]) for x in xk]
        return float(rel @ (vel[1] - vel[0])) > 0.0

    def pre_history(self, x0: np.ndarray, steps: int) -> np.ndarray:
        """States at steps ``-steps..-1`` (``(steps, N, 4)``): constant-velocity extrapolation."""
        j = np.arange(-steps, 0, dtype=float)[:, None]
        out = np.repeat(x0[None], steps, axis=0).astype(float)
        for n in range(x0.shape[0]):
            v, th = x0[n, 2], x0[n, 3]
            out[:, n, 0] = x0[n, 0] + (j[:, 0] * self.recipe.dt) * v * math.cos(th)
            out[:, n, 1] = x0[n, 1] + (j[:, 0] * self.recipe.dt) * v * math.sin(th)
        return out

    # ---- one work unit -------------------------------------------------------------------
    def run_unit(self, index: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
        """All samples of main game ``index`` (see the module docstring)."""
        if self.recipe.ground_truth == "peters":
            return self._run_unit_peters(index, seed)
        r = self.recipe
        g = self.game
        K, H, M = r.horizon, r.history, r.modes
        cfg_ss, solve_ss = seed.spawn(2)
        cfg = self.sample_config(index, np.random.default_rng(cfg_ss))
        seeds = np.random.default_rng(solve_ss)

        def draw():
            return int(seeds.integers(0, 2**31 - 1))

        p_main = self.params(cfg)
        main_modes = self.solve_modes(p_main, draw())[:M]
        rows: list[dict[str, Any]] = []
        n_sub = K if r.max_subgames is None else min(K, r.max_subgames)
        for mi, mm in enumerate(main_modes):
            X = np.stack(g.split_states(mm.states), axis=1)  # (K+1, N, 4)
            traj = np.concatenate([self.pre_history(X[0], H), X], axis=0)  # row k + H is step k
            valid = np.arange(-H, K + 1) >= 0
            prev = [mm, *(o for o in main_modes if o is not mm)]  # executed mode first
            for k in range(n_sub):
                if self.passed(X[k]):
                    break
                p_sub = self.params(cfg, X[k])
                sub = main_modes if k == 0 else self.solve_modes(p_sub, draw(), warm=prev)
                if not sub:  # every solve failed: no sample at this step
                    continue
                if k > 0:  # (at k = 0 keep the executed main mode first)
                    prev = sub
                rows.append(
                    self._sample(
                        cfg,
                        mi,
                        mm.share,
                        k,
                        traj[k : k + H + 1],
                        valid[k : k + H + 1],
                        sub[:M],
                        p_sub,
                        X[k + 1 :],
                    )
                )
        return self._stack(rows)

    def _run_unit_peters(self, index: int, seed: np.random.SeedSequence) -> dict[str, np.ndarray]:
        """Peters ground truth: samples only at steps ``k >= H`` (every history is real)."""
        r = self.recipe
        g = self.truth_game
        K, H, M = r.game_horizon, r.history, r.modes
        cfg_ss, solve_ss = seed.spawn(2)
        cfg = self.sample_config(index, np.random.default_rng(cfg_ss))
        seeds = np.random.default_rng(solve_ss)

        def draw():
            return int(seeds.integers(0, 2**31 - 1))

        main_modes = self.solve_peters_modes(self.params(cfg), draw())[:M]
        rows: list[dict[str, Any]] = []
        valid = np.ones(H + 1, bool)
        for mi, mm in enumerate(main_modes):
            X = np.stack(g.split_states(mm.states), axis=1)  # (K+1, N, 4)
            prev, k_prev = [mm, *(o for o in main_modes if o is not mm)], 0
            n_sub = 0
            for k in range(K):
                if self.passed(X[k]) or (r.max_subgames is not None and n_sub >= r.max_subgames):
                    break
                if k < H:  # not H + 1 real states yet: no sample
                    continue
                p_sub = self.params(cfg, X[k])
                sub = self.solve_peters_modes(p_sub, draw(), warm=prev, shift=k - k_prev)
                n_sub += 1
                if not sub:
                    continue
                prev, k_prev = sub, k
                rows.append(
                    self._sample(
                        cfg, mi, mm.share, k, X[k - H : k + 1], valid, sub[:M], p_sub, X[k + 1 :]
                    )
                )
        return self._stack(rows)

    def _sample(self, cfg, main_mode, main_share, k, hist, hist_valid, modes, p, executed):
        """One sample; ``executed`` ``(K-k, N, nx)`` is what the agents do next (main mode)."""
        g = self.truth_game
        M, T = self.recipe.modes, self.recipe.horizon
        fut = np.zeros((M, 2, T, 4))
        ctl = np.zeros((M, 2, T, 2))
        share = np.zeros(M)
        valid = np.zeros(M, bool)
        for j in range(M):
            m = modes[min(j, len(modes) - 1)]
            fut[j] = np.stack([s[1 : T + 1] for s in g.split_states(m.states)])
            ctl[j] = np.stack([u[:T] for u in g.split_controls(m.controls)])
            if j < len(modes):
                share[j], valid[j] = m.share, True
        # Ground truth: the valid mode closest (mean position error over the steps both
        # cover) to the executed main-mode continuation; at k = 0 it is that mode itself.
        n = min(T, len(executed))
        err = np.linalg.norm(
            fut[:, :, :n, :2] - executed[None, :n].transpose(0, 2, 1, 3)[..., :2], axis=-1
        )
        err = np.where(valid, err.mean(axis=(1, 2)), np.inf)
        return {
            "gt_mode": int(np.argmin(err)),
            "history": hist,
            "history_valid": hist_valid,
            "future": fut,
            "future_controls": ctl,
            "mode_share": share,
            "mode_valid": valid,
            "goals": cfg.goals,
            "params": p,
            "collision_weight": cfg.collision_weight,
            "main_game": cfg.index,
            "main_mode": main_mode,
            "main_share": main_share,
            "step": k,
        }

    def _stack(self, rows: list[dict]) -> dict[str, np.ndarray]:
        schema = self.schema()
        if not rows:
            return {k: np.zeros((0, *fs.shape), fs.dtype) for k, fs in schema.items()}
        return {
            k: np.stack([np.asarray(row[k]) for row in rows]).astype(fs.dtype)
            for k, fs in schema.items()
        }
