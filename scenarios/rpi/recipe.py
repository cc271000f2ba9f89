"""The RPI recipe (:class:`RPIRecipe`): every field that defines a dataset with its seed,
the defaults of each ground truth (:data:`GROUND_TRUTHS`), the measured samples per main
game and the limits checked before any work (:data:`MAX_SAMPLES`, :data:`SIZE_LIMITS`,
:data:`MAX_SHARD_BYTES`). What the fields mean: :mod:`scenarios.rpi`."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from epo_casadi.errors import SpecError, check_number, check_size, from_mapping

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


#: the ground truths a recipe can generate (:mod:`scenarios.rpi`)
GROUND_TRUTHS = ("peters", "potential")

#: defaults of the fields that depend on the ground truth (``None`` in the dataclass)
_TRUTH_DEFAULTS: dict[str, dict[str, Any]] = {
    "potential": dict(
        main_games=2000,
        speed0=(1.0, 1.0),
        goal_jitter=30.0,
        n_samples=8,
        max_iter=30,
        collision_margin=0.15,
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

    ``ground_truth`` chooses the game that makes the demonstrations (:mod:`scenarios.rpi`):
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
    #: distance (m) added to 2 r within which the model game's collision term acts; None: the
    #: ground truth's reach, 0.15 for "potential" (the soft penalty keeps the agents >= 2 r
    #: apart) and ``proximity_radius - 2 r`` for "peters" (the term acts wherever the
    #: demonstrations' proximity cost does)
    collision_margin: float | None = None
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
        if peters and self.collision_margin is None:
            _num("proximity_radius", self.proximity_radius, 0.0)
            _num("radius", self.radius, 0.0)
            reach = max(float(self.proximity_radius) - 2 * float(self.radius), 0.0)
            object.__setattr__(self, "collision_margin", reach)
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

        The exact count depends on the games (see :mod:`scenarios.rpi`); the manifest
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
