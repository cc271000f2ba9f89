"""The RPI generator (:class:`RPIScenario`): the scene and the model's game, the random
draws of a main game (:class:`MainGameConfig`), its multi-modal solves (:class:`Mode`)
and the samples of one work unit (one main game), as :mod:`scenarios.rpi` describes."""

from __future__ import annotations

import math
from dataclasses import dataclass
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
from epo_casadi.errors import SpecError

from ..dataset import FieldSpec, Scenario, stack_rows
from .recipe import RPIRecipe

AGENTS = ("robot", "pedestrian")


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
        from ..rpi_peters import peters_game_spec

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

        from ..rpi_peters import solve_peters_modes

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
        """All samples of main game ``index`` (see :mod:`scenarios.rpi`)."""
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
        return stack_rows(rows, self.schema())
