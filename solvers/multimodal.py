"""Multi-modal solutions of one game: many sampled initial strategies, solve, cluster.

Following Peters et al. (2020) and the RPI dataset construction (paper App. E.1): a game
solved once gives one local equilibrium; solving it from many sampled initial strategies
and clustering the converged joint trajectories gives its *modes* (e.g. passing left or
right) and how often each is reached. Shapes follow :mod:`epo_casadi.game`.

Steps of :func:`solve_multimodal`
    1. **Sample** ``n_samples`` initial joint strategies with a seeded
       ``numpy.random.Generator`` (:func:`sinusoid_sampler` unless ``sampler`` is given).
    2. **Solve** them in one batched call of a solver of the table
       (:data:`solvers.registry.SOLVERS`, those with ``multimodal``): iLQ
       (:func:`solvers.ilq.solve_ilq`, feedback Nash), LM (:func:`solvers.lm.solve_lm`, the
       potential minimizer, by default with the structured Riccati backend) or a
       registered one.
    3. **Drop** failed solves (status not converged; ``accept_max_iter`` also keeps
       ``max_iter``) and solves whose smallest pairwise centre distance over ``k = 1..K``
       is below ``r_i + r_j - collision_tol``.
    4. **Cluster** the kept solves (:class:`MultiModalOptions`, ``cluster``):
       ``"distance"``: agglomerative clustering (``scipy.cluster.hierarchy``, ``linkage``)
       of the joint position trajectories with the RMS distance
       ``d(a, b) = sqrt(mean_{i,k} |p_a[i,k] - p_b[i,k]|^2)`` (metres), cut at
       ``cluster_tol``; ``"passing"``: one mode per pattern of passing sides, the sign of
       the angle swept by each pair's relative position ``p_j - p_i`` over the horizon
       (sum of ``atan2(cross, dot)`` of consecutive relative positions; ``0`` when
       ``|angle| < pass_angle``: the pair does not pass).
    5. **Represent** each mode by its medoid (the member with the least summed distance to
       the others; ties: lowest sample index) and its share of the kept solves; modes are
       sorted by share (ties: lower mean energy, then first sample index).

Everything is deterministic for a given ``seed``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from epo_casadi.dynamics import DoubleIntegrator
from epo_casadi.errors import SpecError, check_bool, check_number
from epo_casadi.game import PotentialGame

from .lm import check_options
from .registry import SOLVERS
from .result import SolveResult, Status

__all__ = [
    "Mode",
    "MultiModalOptions",
    "MultiModalResult",
    "dbscan",
    "passing_sides",
    "sinusoid_sampler",
    "solve_multimodal",
    "trajectory_distances",
]

CLUSTERINGS = ("distance", "passing")
LINKAGES = ("average", "complete", "single")


@dataclass(frozen=True)
class MultiModalOptions:
    """Filtering and clustering of the solves (defaults: the RPI recipe)."""

    cluster: str = "distance"  #: "distance" (RMS trajectory distance) or "passing" (sides)
    cluster_tol: float = 0.3  #: distance clustering: cut height of the dendrogram (m, RMS)
    linkage: str = "average"  #: distance clustering: "average", "complete" or "single"
    pass_angle: float = 0.5  #: passing clustering: |swept angle| below this (rad) = no pass
    collision_tol: float = 0.05  #: drop solves with a pair closer than r_i + r_j - this (m)
    accept_max_iter: bool = False  #: also keep solves that stopped at max_iter

    def __post_init__(self):
        if self.cluster not in CLUSTERINGS:
            raise SpecError(
                "multimodal.cluster", f"expected one of {CLUSTERINGS}, got {self.cluster!r}"
            )
        if self.linkage not in LINKAGES:
            raise SpecError(
                "multimodal.linkage", f"expected one of {LINKAGES}, got {self.linkage!r}"
            )
        for name in ("cluster_tol", "pass_angle", "collision_tol"):
            check_number(f"multimodal.{name}", getattr(self, name), lo=0)
        check_bool("multimodal.accept_max_iter", self.accept_max_iter)


@dataclass(frozen=True)
class Mode:
    """One mode: its representative (medoid) solve and how often it was reached."""

    controls: np.ndarray  #: joint strategy ``u`` of the medoid, ``(n_u,)``
    states: np.ndarray  #: its rolled-out states ``x``, ``(n_x,)``
    share: float  #: fraction of the kept solves in this mode
    cost: np.ndarray  #: the medoid's agent costs ``C_i``, ``(N,)``
    energy: float  #: the medoid's potential ``E`` (nan for iLQ with custom costs)
    members: np.ndarray  #: sample indices of the solves in this mode
    medoid: int  #: sample index of the representative
    passing: tuple[int, ...]  #: passing side of each pair ``(a < b)`` of the medoid, +1/-1/0


@dataclass(frozen=True)
class MultiModalResult:
    """Modes of one game (sorted by share, largest first) and every solve behind them."""

    modes: list[Mode]
    labels: np.ndarray  #: mode index of every sample, ``-1`` for dropped ones, ``(n_samples,)``
    kept: np.ndarray  #: which samples passed the filters, ``(n_samples,)``
    results: SolveResult  #: all solves (batched), in sample order
    initial_controls: np.ndarray  #: the sampled initial strategies, ``(n_samples, n_u)``
    wall_time: float
    info: dict = field(default_factory=dict)

    @property
    def shares(self) -> np.ndarray:
        return np.array([m.share for m in self.modes])

    def summary(self) -> str:
        kept = int(self.kept.sum())
        parts = ", ".join(f"{m.share:.2f} (passing {m.passing})" for m in self.modes)
        return f"{len(self.modes)} modes from {kept}/{self.kept.size} kept solves: {parts}"


# --------------------------------------------------------------------------------------
# sampling
# --------------------------------------------------------------------------------------
def sinusoid_sampler(
    game: PotentialGame, p: np.ndarray, n: int, rng: np.random.Generator
) -> np.ndarray:
    """Feed-forward sinusoids (after GameInference.jl, Peters et al. 2020): ``(n, n_u)``.

    With ``c_k = cos(k pi / K)`` and independent draws per sample and agent:

    * heading models (unicycle: ``(a, omega)``; bicycle: ``(a, delta)``):
      ``a_k = -0.05 c_k U(1.5, 2.5)`` and ``omega_k = c_k U(-15, 15) deg/s``
      (bicycle: ``delta_k = c_k U(-5, 5) deg``);
    * double integrator: the same longitudinal and a lateral ``0.5 c_k U(-1, 1) m/s^2``,
      along and across the initial velocity (or the x axis when at rest).
    """
    K = game.K
    c = np.cos(np.arange(K) * np.pi / K)
    blocks = game.params.unpack(np.asarray(p, float))
    out = np.zeros((n, game.n_u))
    for s in range(n):
        parts = []
        for a in game.agents:
            lon = -0.05 * c * rng.uniform(1.5, 2.5)
            if isinstance(a.dynamics, DoubleIntegrator):
                lat = 0.5 * c * rng.uniform(-1.0, 1.0)
                x0 = blocks[f"x0.{a.name}"]
                v = np.asarray(x0[2:4], float)
                e = v / np.linalg.norm(v) if np.linalg.norm(v) > 1e-9 else np.array([1.0, 0.0])
                lat_dir = np.array([-e[1], e[0]])
                parts.append(lon[:, None] * e[None] + lat[:, None] * lat_dir[None])
            else:
                amp = 5.0 if a.dynamics.name == "bicycle" else 15.0
                turn = c * np.deg2rad(rng.uniform(-amp, amp))
                u = np.zeros((K, a.dynamics.nu))
                u[:, 0] = lon
                if a.dynamics.nu > 1:
                    u[:, 1] = turn
                parts.append(u)
        out[s] = game.join_controls(parts)
    return out


# --------------------------------------------------------------------------------------
# geometry of joint trajectories
# --------------------------------------------------------------------------------------
def trajectory_distances(game: PotentialGame, states: np.ndarray) -> np.ndarray:
    """RMS position distance (m) between every two joint trajectories: ``(B, B)``."""
    pos = game.positions(np.asarray(states))  # (B, N, K+1, 2)
    flat = pos.reshape(pos.shape[0], -1)
    sq = np.sum(flat**2, axis=1)
    d2 = np.maximum(sq[:, None] + sq[None, :] - 2 * flat @ flat.T, 0.0)
    d = np.sqrt(d2 / (pos.shape[1] * pos.shape[2]))
    np.fill_diagonal(d, 0.0)
    return 0.5 * (d + d.T)


def _pairs(game: PotentialGame) -> list[tuple[int, int]]:
    return [(a, b) for a in range(game.N) for b in range(a + 1, game.N)]


def swept_angles(game: PotentialGame, states: np.ndarray) -> np.ndarray:
    """Angle (rad) swept by ``p_b - p_a`` over the horizon, per pair ``a < b``: ``(..., n_pairs)``."""
    pos = game.positions(np.asarray(states))  # (..., N, K+1, 2)
    out = []
    for a, b in _pairs(game):
        rel = pos[..., b, :, :] - pos[..., a, :, :]
        r0, r1 = rel[..., :-1, :], rel[..., 1:, :]
        cross = r0[..., 0] * r1[..., 1] - r0[..., 1] * r1[..., 0]
        dot = np.sum(r0 * r1, axis=-1)
        out.append(np.sum(np.arctan2(cross, dot), axis=-1))
    return np.stack(out, axis=-1) if out else np.zeros(np.shape(states)[:-1] + (0,))


def passing_sides(game: PotentialGame, states: np.ndarray, pass_angle: float = 0.5) -> np.ndarray:
    """Passing side per pair ``a < b``: ``+1`` (counter-clockwise), ``-1``, ``0`` (no pass)."""
    ang = swept_angles(game, states)
    return np.where(np.abs(ang) < pass_angle, 0, np.sign(ang)).astype(int)


def min_clearance(
    game: PotentialGame, states: np.ndarray, p: np.ndarray | None = None
) -> np.ndarray:
    """Smallest ``dist_ij - r_i - r_j`` over pairs and steps ``k = 1..K``: ``(...)``; the
    radii of agents with ``radius_param`` from ``p`` ``(..., n_p)`` (defaults if None)."""
    pos = game.positions(np.asarray(states))
    out = np.full(np.shape(states)[:-1], np.inf)
    radii = game.radii(p)
    for a, b in _pairs(game):
        d = np.linalg.norm(pos[..., a, 1:, :] - pos[..., b, 1:, :], axis=-1)
        r = radii[..., a] + radii[..., b]
        out = np.minimum(out, np.min(d, axis=-1) - r)
    return out


# --------------------------------------------------------------------------------------
# the entry function
# --------------------------------------------------------------------------------------
def solve_multimodal(
    game: PotentialGame,
    p: np.ndarray,
    n_samples: int = 16,
    seed: int | np.random.SeedSequence | None = 0,
    solver: str = "ilq",
    options=None,
    clustering: MultiModalOptions | dict | None = None,
    sampler: Callable | None = None,
    costs=None,
) -> MultiModalResult:
    """Solve ``game`` at ``p (n_p,)`` from ``n_samples`` sampled starts and cluster the modes.

    ``solver``: a registered solver the multi-modal solver may use (its entry's
    ``multimodal``): ``"ilq"`` (``options``: :class:`solvers.ilq.ILQOptions`; ``costs``:
    custom player costs, see :func:`solvers.ilq.solve_ilq`), ``"lm"`` (``options``:
    :class:`solvers.lm.LMOptions`) or a user's; one batched solve of all samples with
    the solver's options (its defaults when None). ``sampler(game, p, n, rng) ->
    (n, n_u)`` replaces :func:`sinusoid_sampler`. See the module docstring for the steps.
    """
    t0 = time.perf_counter()
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 1:
        raise SpecError("n_samples", f"expected an integer >= 1, got {n_samples!r}")
    entry = _multimodal_entry(solver, costs)
    mm = check_options(MultiModalOptions, clustering, "multimodal")
    n = int(n_samples)
    p = np.asarray(p, dtype=float)
    if p.shape != (game.n_p,):
        raise SpecError(
            "p", f"expected one parameter vector of {game.n_p} entries, got shape {p.shape}"
        )
    U0 = _sample_starts(game, p, n, seed, sampler)
    P = np.broadcast_to(p, (n, game.n_p))
    extra = {} if costs is None else {"costs": costs}
    res = entry.solve(game, P, U0, options=options, **extra)

    status = np.asarray(res.status, dtype=object).reshape(n)
    good = np.array(
        [s is Status.CONVERGED or (mm.accept_max_iter and s is Status.MAX_ITER) for s in status]
    )
    finite = np.isfinite(res.controls).all(axis=1) & np.isfinite(res.states).all(axis=1)
    clearance = min_clearance(game, res.states, P)
    kept = good & finite & (clearance >= -mm.collision_tol)
    sides = passing_sides(game, res.states, mm.pass_angle) if game.N > 1 else np.zeros((n, 0), int)
    labels, modes = _modes(game, res, np.nonzero(kept)[0], sides, mm)
    return MultiModalResult(
        modes=modes,
        labels=labels,
        kept=kept,
        results=res,
        initial_controls=U0,
        wall_time=time.perf_counter() - t0,
        info={
            "solver": solver,
            "clustering": mm,
            "clearance": clearance,
            "passing": sides,
            "dropped_failed": int((~(good & finite)).sum()),
            "dropped_collision": int((good & finite & (clearance < -mm.collision_tol)).sum()),
        },
    )


def _multimodal_entry(solver: str, costs):
    """The table's entry of ``solver``; refused unless it is a solver of many starts (and,
    with custom ``costs``, one that takes them)."""
    entry = SOLVERS.entry(solver, "solver")
    if not entry.multimodal:
        usable = [n for n, e in SOLVERS.items() if e.multimodal]
        raise SpecError(
            "solver", f"expected a solver of many starts, one of {usable}, got {solver!r}"
        )
    if costs is not None and not entry.takes("costs"):
        takers = [n for n, e in SOLVERS.items() if e.takes("costs")]
        raise SpecError("costs", f"custom player costs need a solver of {takers}, not {solver!r}")
    return entry


def _sample_starts(game: PotentialGame, p, n: int, seed, sampler) -> np.ndarray:
    """Step 1: ``n`` initial joint strategies ``(n, n_u)`` from a generator seeded by ``seed``."""
    rng = np.random.default_rng(seed)
    U0 = np.asarray((sampler or sinusoid_sampler)(game, p, n, rng), dtype=float)
    if U0.shape != (n, game.n_u):
        raise SpecError(
            "sampler", f"expected initial strategies of shape ({n}, {game.n_u}), got {U0.shape}"
        )
    return U0


def _modes(
    game: PotentialGame, res: SolveResult, idx: np.ndarray, sides: np.ndarray, mm
) -> tuple[np.ndarray, list[Mode]]:
    """Steps 4 and 5 on the kept solves ``idx``: each sample's mode label (``-1`` for the
    dropped) and the modes, sorted by share."""
    n = sides.shape[0]
    labels = np.full(n, -1, dtype=int)
    modes: list[Mode] = []
    if not idx.size:
        return labels, modes
    D = trajectory_distances(game, res.states[idx])
    if mm.cluster == "passing":
        keys = [tuple(int(v) for v in sides[i]) for i in idx]
        uniq = sorted(set(keys))
        raw = np.array([uniq.index(k) for k in keys])
    else:
        raw = _agglomerate(D, mm.cluster_tol, mm.linkage)
    energy = np.asarray(res.energy, float).reshape(n)
    groups = []
    for c in np.unique(raw):
        loc = np.nonzero(raw == c)[0]
        sub = D[np.ix_(loc, loc)]
        med = loc[int(np.argmin(sub.sum(axis=1)))]  # argmin: first index on ties
        mean_e = (
            float(np.mean(energy[idx[loc]])) if np.all(np.isfinite(energy[idx[loc]])) else math.inf
        )
        groups.append((-loc.size, mean_e, int(idx[loc[0]]), loc, med))
    groups.sort(key=lambda g: g[:3])
    for m, (_, _, _, loc, med) in enumerate(groups):
        labels[idx[loc]] = m
        j = int(idx[med])
        modes.append(
            Mode(
                controls=np.array(res.controls[j]),
                states=np.array(res.states[j]),
                share=loc.size / idx.size,
                cost=np.array(res.agent_costs[j]),
                energy=float(energy[j]),
                members=idx[loc].copy(),
                medoid=j,
                passing=tuple(int(v) for v in sides[j]),
            )
        )
    return labels, modes


def _agglomerate(D: np.ndarray, tol: float, method: str) -> np.ndarray:
    """Flat clusters of a distance matrix cut at ``tol`` (deterministic).

    ``"average"`` and ``"complete"``: the dendrogram of ``scipy.cluster.hierarchy``
    (``linkage``) cut at ``tol`` (``fcluster``, criterion ``"distance"``: clusters whose
    cophenetic distance is ``<= tol``). ``"single"``: that cut is the connected components
    of the graph ``D <= tol``, which is DBSCAN with one point per core (:func:`dbscan` with
    ``eps`` just above ``tol``).
    """
    if D.shape[0] == 1:
        return np.zeros(1, dtype=int)
    if method == "single":
        return dbscan(D, float(np.nextafter(tol, math.inf)), 1)
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    Z = linkage(squareform(D, checks=False), method=method)
    return fcluster(Z, t=tol, criterion="distance").astype(int)


def dbscan(D: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """DBSCAN labels of a precomputed distance matrix ``D (n, n)``: ``0, 1, ...`` or ``-1``.

    A point is a core point when at least ``min_points`` points (itself included) lie
    within ``D < eps`` (Clustering.jl's convention); clusters are the connected components
    of core points plus the border points within ``eps`` of one (assigned to the first
    such cluster in index order); the rest is noise (``-1``). Clusters are numbered in the
    order of their first core point, so the result depends on nothing but ``D``.

    scikit-learn's ``DBSCAN(metric="precomputed", eps=0.5, min_samples=min_points)`` on
    the 0/1 matrix ``D >= eps`` (neighbours: entries ``<= 0.5``, i.e. ``D < eps``, so no
    rounding at ``eps`` is involved): the same labels, numbering included (it grows the
    clusters from their first core point in index order, a border point keeping the
    first cluster that reaches it).
    """
    from sklearn.cluster import DBSCAN  # imported here: `import solvers` stays fast

    D = np.asarray(D, dtype=float)
    if D.ndim != 2 or D.shape[0] != D.shape[1]:
        raise SpecError("D", f"expected a square distance matrix, got shape {D.shape}")
    if isinstance(min_points, np.integer):
        min_points = int(min_points)
    check_number("min_points", min_points, lo=1, integer=True)
    if D.shape[0] == 0:
        return np.zeros(0, dtype=int)
    far = np.where(D < eps, 0.0, 1.0)
    db = DBSCAN(eps=0.5, min_samples=int(min_points), metric="precomputed")
    return db.fit_predict(far).astype(int)
