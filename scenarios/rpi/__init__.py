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

from .recipe import (
    GROUND_TRUTHS,
    MAX_SAMPLES,
    MAX_SHARD_BYTES,
    SAMPLES_PER_GAME,
    SAMPLES_PER_GAME_BY_TRUTH,
    SIZE_LIMITS,
    RPIRecipe,
)
from .recipe import PAPER_SAMPLES as PAPER_SAMPLES
from .scenario import AGENTS as AGENTS
from .scenario import MainGameConfig, Mode, RPIScenario

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
