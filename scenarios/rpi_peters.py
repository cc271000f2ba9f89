"""The Peters et al. (2020) ground truth of RPI: an iLQ feedback Nash game, clustered by DBSCAN.

The paper builds RPI "based on the implementation of Peters et al. 2020" (App. E.1). This
module writes that game with the toolkit's features (one new feature, :class:`GoalPose`)
and the clustering of its solutions; :mod:`scenarios.rpi` uses it when
``RPIRecipe.ground_truth == "peters"`` (the default). The facts below were read in the
public code of GameInference.jl (``experiments/main.jl`` ``setup_problem``,
``experiments/montecarlo_study.jl``, ``src/distributions.jl``) and iLQGames.jl
(``src/n_player_unicycle_game.jl``, ``src/n_player_navigation_game.jl``,
``src/cost_design_utils.jl``, ``src/unicycle_4D.jl``); ``docs/rpi.md`` lists them with
their source and says where this module departs from them. Notation and index order
follow :mod:`epo_casadi.game`.

Players and dynamics
    Two unicycles; there ``(px, py, theta, v)`` with controls ``(theta_dot, a)``, here the
    toolkit's ``(x, y, v, theta)`` / ``(a, omega)`` (the same model, another order; the
    toolkit integrates with forward Euler). Horizon ``10 s`` at ``dt = 0.1``: ``K = 100``.
    Players start at rest on a 3 m circle heading to the opposite point (their goal).

Player ``i``'s cost (summed over the stages; ``d`` the distance of the two centres)
    ``1/2 * 10 |u_i|^2`` (control effort) ``+ 50 gap^2`` soft bounds on ``theta_dot``
    (``+-10 deg/s``), ``a`` (``+-9.81``) and ``v`` (``-0.05 .. 2``) ``+ 1/2 * 30 v_i^2``
    ``+ w (d - 1.5)^2`` while ``d < 1.5 m`` (proximity) ``+ 1/2 * 300 |(x, y, theta)_i -
    goal_i|^2`` on the states whose time is ``>= T - 1.5 dt`` (the last two). The
    proximity weight ``w`` is drawn per main game and shared by both players (a
    per-player weight needs custom costs and exact Hessians, on which the iLQ solver did
    not converge: docs/rpi.md), so the player costs are the game's own agent costs; the
    game is solved for a feedback Nash equilibrium by :func:`solvers.ilq.solve_ilq`.

    In the toolkit a term's energy is ``1/2 (w c)^2``; the weights are therefore
    ``sqrt(10)`` (acceleration, turn rate), ``sqrt(2 * 50) = 10`` (bounds),
    ``sqrt(30)`` (velocity), ``sqrt(300)`` (goal pose) and ``sqrt(2 w)`` (proximity,
    a :class:`~epo_casadi.features.Collision` whose reach ``r_i + r_j + margin`` is 1.5 m).
    Stages: the toolkit costs the states ``x_1..x_K`` and controls ``u_0..u_{K-1}``; the
    Julia code costs ``x_0..x_{K-1}`` (``x_0`` is fixed, so only ``x_K`` differs).

Solutions and modes (:func:`solve_peters_modes`)
    Every solve starts from a sinusoid feed-forward strategy (``cos(k pi / K)`` times
    ``U(-15, 15) deg/s`` on the turn rate and ``-0.05 U(1.5, 2.5)`` on the acceleration,
    :func:`solvers.multimodal.sinusoid_sampler`); solves that do not converge (iLQ stops
    at ``max |a| <= ilq_tol``, 1e-2 by default), or whose
    two agents come closer than ``min_distance`` (0.75 m, half the proximity radius) at
    any step, are dropped; the others are clustered by DBSCAN (:func:`dbscan`) on their
    flattened joint state trajectories with the squared Euclidean distance, ``eps = 10``,
    ``min_points = 2``; noise points are dropped; each cluster is represented by its
    medoid, its share is its size over the clustered solves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import casadi as ca
import numpy as np

from epo_casadi import (
    Acceleration,
    AccelerationBound,
    AgentSpec,
    Collision,
    GameSpec,
    PotentialGame,
    TurnRate,
    TurnRateBound,
    Velocity,
    VelocityBound,
)
from epo_casadi.errors import SpecError
from epo_casadi.features import Feature, ParamSpec
from solvers.multimodal import dbscan  # scikit-learn's DBSCAN, Clustering.jl's convention

__all__ = ["GoalPose", "PetersMode", "peters_game_spec", "dbscan", "solve_peters_modes"]


@dataclass(frozen=True)
class GoalPose(Feature):
    """``(p(x_k) - goal, theta_k - goal_heading)`` at the last ``last`` states ``k``.

    Reads the agent's ``goal`` (2) and declares its own block ``goal_heading.<agent>`` (1,
    rad). The heading residual is not wrapped (as in the reference implementation).
    """

    kind: ClassVar[str] = "goal_pose"
    last: int = 2  #: number of final states costed (``k = K-last+1 .. K``)

    def __post_init__(self):
        if isinstance(self.last, bool) or not isinstance(self.last, int) or self.last < 1:
            raise SpecError("goal_pose.last", f"expected an integer >= 1, got {self.last!r}")

    def refs(self):
        return {"goal": 2}

    def params(self):
        return (ParamSpec("goal_heading", 1, 0.0),)

    def steps(self, K):
        return list(range(max(1, K - self.last + 1), K + 1))

    def check(self, dynamics):
        if "theta" not in dynamics.state_names:
            raise SpecError(
                self.key, f"needs a state named 'theta', {dynamics.name} has {dynamics.state_names}"
            )
        super().check(dynamics)

    def residual(self, ctx):
        th = ctx.dynamics.state_names.index("theta")
        rows = []
        for k in self.steps(ctx.K):
            x = ctx.X[:, k]
            rows += [ctx.dynamics.position(x) - ctx.refs["goal"], x[th] - ctx.refs["goal_heading"]]
        return ca.vertcat(*rows)


def peters_game_spec(recipe, agents: tuple[str, str] = ("robot", "pedestrian")) -> GameSpec:
    """The game of :mod:`scenarios.rpi_peters` from an :class:`~scenarios.rpi.RPIRecipe`
    with ``ground_truth="peters"`` (its fields hold the costs in the reference's units)."""
    r = recipe
    wb = math.sqrt(2 * r.bound_cost)
    turn = math.radians(r.turn_rate_bound)
    specs = []
    for name in agents:
        feats = [
            Acceleration(weight=math.sqrt(r.control_cost)),
            TurnRate(weight=math.sqrt(r.control_cost)),
            TurnRateBound(lower=-turn, upper=turn, weight=wb),
            AccelerationBound(lower=-r.acceleration_bound, upper=r.acceleration_bound, weight=wb),
            Velocity(weight=math.sqrt(r.speed_cost)),
            VelocityBound(lower=r.speed_bounds[0], upper=r.speed_bounds[1], weight=wb),
            GoalPose(last=r.goal_steps, weight=math.sqrt(r.goal_cost)),
        ]
        specs.append(AgentSpec(name, "unicycle", feats, radius=r.radius))
    margin = r.proximity_radius - 2 * r.radius
    mid = 0.5 * (r.proximity_weight[0] + r.proximity_weight[1])
    pair = [Collision(label="proximity", margin=margin, weight=math.sqrt(2 * mid))]
    return GameSpec(specs, pair, horizon=r.game_horizon, dt=r.dt)


@dataclass(frozen=True)
class PetersMode:
    """One cluster: the medoid's joint controls ``(n_u,)`` and states ``(n_x,)``, its share
    and the medoid's index among the solves (``info["results"]``)."""

    controls: np.ndarray
    states: np.ndarray
    share: float
    index: int


def solve_peters_modes(
    game: PotentialGame,
    p: np.ndarray,
    U0: np.ndarray,
    options,
    min_distance: float,
    eps: float,
    min_points: int,
) -> tuple[list[PetersMode], dict]:
    """Solve from every initial strategy ``U0 (n, n_u)``, drop, cluster (module docstring).

    Returns the modes sorted by share (ties: the cluster whose first member comes first)
    and ``info`` (``kept`` mask, ``labels`` per solve with ``-1`` for dropped or noise,
    ``min_dist`` per solve, ``results`` the batched :class:`~solvers.result.SolveResult`).
    """
    from solvers.ilq import solve_ilq
    from solvers.result import Status

    n = U0.shape[0]
    res = solve_ilq(game, np.broadcast_to(p, (n, game.n_p)), U0, options)
    pos = game.positions(res.states)  # (n, N, K+1, 2)
    dmin = np.linalg.norm(pos[:, 0] - pos[:, 1], axis=-1).min(axis=-1)
    status = np.asarray(res.status, dtype=object).reshape(n)
    finite = np.isfinite(res.states).all(axis=1) & np.isfinite(res.controls).all(axis=1)
    kept = np.array([s is Status.CONVERGED for s in status]) & finite & (dmin >= min_distance)
    labels = np.full(n, -1, dtype=int)
    idx = np.nonzero(kept)[0]
    modes: list[PetersMode] = []
    if idx.size:
        S = res.states[idx]
        sq = np.sum(S**2, axis=1)
        D = np.maximum(sq[:, None] + sq[None, :] - 2 * S @ S.T, 0.0)  # squared Euclidean
        np.fill_diagonal(D, 0.0)
        lab = dbscan(D, eps, min_points)
        labels[idx] = lab
        total = int((lab >= 0).sum())
        groups = []
        for c in range(int(lab.max()) + 1):
            loc = np.nonzero(lab == c)[0]
            med = loc[int(np.argmin(D[np.ix_(loc, loc)].sum(axis=1)))]
            groups.append((-loc.size, int(loc[0]), int(idx[med]), loc.size))
        groups.sort()
        for _, _, j, size in groups:
            modes.append(
                PetersMode(
                    np.asarray(res.controls[j], float),
                    np.asarray(res.states[j], float),
                    size / total,
                    j,
                )
            )
    return modes, {"kept": kept, "labels": labels, "min_dist": dmin, "results": res}
