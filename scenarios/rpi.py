"""RPI: simulated robot-pedestrian interaction, multi-modal demonstrations (paper App. E.1).

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

History before the start
    Steps before ``k = 0`` do not exist in a main game; they are filled by a constant-
    velocity backward extrapolation of ``x_0`` and marked ``False`` in ``history_valid``.

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
from dataclasses import asdict, dataclass, fields
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
from epo_casadi.errors import SpecError, check_number

from .dataset import FieldSpec, Scenario

__all__ = ["RPIRecipe", "RPIScenario", "MainGameConfig", "Mode", "SAMPLES_PER_GAME"]

#: measured mean samples per main game of the default recipe (docs/rpi.md)
SAMPLES_PER_GAME = 30.0
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


@dataclass(frozen=True)
class RPIRecipe:
    """Everything that defines an RPI dataset (with the seed). Frozen; unknown keys fail."""

    main_games: int = 2000  #: work units; ~30 samples each (2000 -> ~60k, the paper's order)
    games_per_shard: int = 20  #: main games per HDF5 shard (resume granularity)
    horizon: int = 40  #: K, steps of the main game, the subgames and the predicted future
    history: int = 18  #: H, past steps in a sample (plus the current state)
    modes: int = 2  #: M, joint futures per sample
    dt: float = 0.1  #: step length (s)
    radius: float = 0.25  #: agent radius r_i (m)
    circle: float = 3.0  #: radius of the pedestrian start/goal circle (m)
    robot_start: tuple[float, float] = (-3.0, 0.0)  #: fixed robot start (m)
    robot_goal: tuple[float, float] = (3.0, 0.0)  #: fixed robot goal (m)
    exclude: float = 45.0  #: no pedestrian start within this angle (deg) of the robot start
    goal_jitter: float = 30.0  #: pedestrian goal angle = start + 180 + U(-j, j) (deg)
    speed0: tuple[float, float] = (1.0, 1.0)  #: initial speeds (robot, pedestrian) (m/s)
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
    n_samples: int = 8  #: solves per (sub)game, from sampled initial strategies
    warm_start: int = 2  #: of those, initial strategies from the previous subgame's modes
    max_iter: int = 30  #: iteration cap of each solve (a solve that hits it is dropped)
    compiled: bool = True  #: iLQ Riccati recursion as generated C (needs a C compiler)
    max_subgames: int | None = None  #: cap of subgames per executed mode (None: until passing)
    split: tuple[float, float, float] = (0.8, 0.1, 0.1)  #: train/val/test fractions of main games

    def __post_init__(self):
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

    @classmethod
    def full(cls, **overrides) -> RPIRecipe:
        """The full-size dataset: 2,000 main games, about 60k samples."""
        return cls(**overrides)

    @classmethod
    def for_samples(cls, samples: int, **overrides) -> RPIRecipe:
        """About ``samples`` samples: ``ceil(samples / 30)`` main games (at least 3).

        The exact count depends on the games (see the module docstring); the manifest
        records it. Shards shrink so that a small set still has a few per split.
        """
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise SpecError("samples", f"expected an integer >= 1, got {samples!r}")
        games = max(3, math.ceil(samples / SAMPLES_PER_GAME))
        base = dict(
            main_games=games,
            games_per_shard=max(1, min(cls.games_per_shard, math.ceil(games / 30))),
        )
        base.update(overrides)
        return cls.from_dict(base)

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> RPIRecipe:
        if not isinstance(d, dict):
            raise SpecError("rpi", f"expected a mapping of recipe fields, got {type(d).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise SpecError("rpi", f"unknown recipe field(s) {unknown}; allowed: {sorted(names)}")
        return cls(**d)


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

    def __init__(self, recipe: RPIRecipe | None = None):
        if recipe is not None and not isinstance(recipe, RPIRecipe):
            raise SpecError("recipe", f"expected an RPIRecipe, got {type(recipe).__name__}")
        self.recipe = recipe or RPIRecipe()

    # pickling: send only the recipe; the CasADi game is rebuilt in the worker
    def __getstate__(self):
        return {"recipe": self.recipe}

    def __setstate__(self, state):
        self.recipe = state["recipe"]

    # ---- Scenario interface ----------------------------------------------------------
    def recipe_dict(self) -> dict:
        return self.recipe.to_dict()

    @property
    def n_units(self) -> int:
        return self.recipe.main_games

    @property
    def units_per_shard(self) -> int:
        return self.recipe.games_per_shard

    @property
    def split_fractions(self):
        return self.recipe.split

    def expected_samples(self) -> int:
        return int(self.recipe.main_games * SAMPLES_PER_GAME)

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
        g = self.game
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
        """The game (built once per process; configurations differ only in ``p``)."""
        return PotentialGame(self.game_spec())

    def _n_params(self) -> int:
        return self.game.n_p

    def sample_config(self, index: int, rng: np.random.Generator) -> MainGameConfig:
        """Pedestrian start/goal angles and the collision weight of main game ``index``."""
        r = self.recipe
        rs, rg = np.asarray(r.robot_start), np.asarray(r.robot_goal)
        robot_angle = math.atan2(rs[1], rs[0])
        ex = math.radians(r.exclude)
        phi = robot_angle + ex + rng.uniform(0.0, 2 * math.pi - 2 * ex)
        goal = phi + math.pi + rng.uniform(-1.0, 1.0) * math.radians(r.goal_jitter)
        wc = rng.uniform(*r.collision_weight)
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
        """Parameter vector of the game from state ``x`` (``(N, 4)``; default: start)."""
        x = config.x0 if x is None else np.asarray(x).reshape(2, 4)
        vals = {}
        for n, a in enumerate(AGENTS):
            vals[f"x0.{a}"] = x[n]
            vals[f"goal.{a}"] = config.goals[n]
        vals["w.robot-pedestrian.collision"] = [config.collision_weight]
        return self.game.params.pack(vals)

    def solver_options(self):
        """Options of every solve (:class:`solvers.ilq.ILQOptions` or ``LMOptions``)."""
        r = self.recipe
        if r.solver == "ilq":
            from solvers.ilq import ILQOptions

            return ILQOptions(max_iter=r.max_iter, compiled=r.compiled)
        from solvers.lm import LMOptions

        return LMOptions(steps=r.max_iter, threads=1)

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

    def _sample(self, cfg, main_mode, main_share, k, hist, hist_valid, modes, p, executed):
        """One sample; ``executed`` ``(K-k, N, nx)`` is what the agents do next (main mode)."""
        g = self.game
        M, T = self.recipe.modes, self.recipe.horizon
        fut = np.zeros((M, 2, T, 4))
        ctl = np.zeros((M, 2, T, 2))
        share = np.zeros(M)
        valid = np.zeros(M, bool)
        for j in range(M):
            m = modes[min(j, len(modes) - 1)]
            fut[j] = np.stack([s[1:] for s in g.split_states(m.states)])
            ctl[j] = np.stack(g.split_controls(m.controls))
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
