"""The closed loop: world, estimator, planner, tracker; episodes, metrics, parallel runs.

One episode (:func:`run_episode`) is the loop of :mod:`solvers.control.types`::

    obs = world.reset(seed)
    est = estimator.reset(obs, world.dt)
    while world.outcome() == "running":
        plan = planner.plan(obs, est)
        command = tracker.control(obs.ego, plan, obs.t) if usable(plan) else brake(obs.ego)
        obs = world.step(command.value)
        est = estimator.update(obs)

A plan that is not ``ok`` or not finite, or a planner or tracker that raises, never ends
the episode: the ego brakes (:func:`brake`: the strongest deceleration of the vehicle
model down to standstill, steering straight) and the event is logged. Every step records
the truth, the observation, the estimate, the plan (ego states and the predicted joint
modes with their probabilities), the command and the latencies of estimation, planning
and tracking (:class:`EpisodeLog`).

Metrics per episode (:func:`episode_metrics`)
    ``success`` / ``collision`` (the world's outcome), ``min_distance`` (m, ego to each
    other agent: centre distance minus both radii, the minimum over the episode; the
    smallest over agents is ``min_distance``), ``time_to_clear`` (s: when the ego's arc
    length along its path first passes the end of the conflict zone; the zone is the
    world's (:class:`scenarios.maps.ConflictZone`) where it has one, else the stretch of
    ``r_ego + r_other`` around the ego's position at the closest approach; ``NaN`` when it
    never clears), ``progress`` (m along the ego's path) and ``progress_fraction``,
    ``rms_jerk`` (m/s^3, of the true speed), planning latency ``plan_p50_ms`` /
    ``plan_p99_ms``, ``rtf`` (mean planning time / ``dt``: below 1 keeps up in real time)
    and ``fallbacks`` (steps that braked instead of tracking a plan).

Parallel runs (:func:`run_episodes`)
    Episode ``i`` uses seed ``seed + i`` and a stack built fresh from the configuration,
    so its result does not depend on the engine, the workers or the order. Episodes run on
    the engines of data generation (:mod:`scenarios.dataset`: a local process pool or
    Dask), at most :data:`MAX_EPISODES` per run (every episode's result is held for the
    summary). Results go to ``DIR/episodes/episode-NNNNN.json`` (written atomically,
    :func:`scenarios.files.write_atomic`; an unwritable folder or a full disk is one
    :class:`~epo_casadi.errors.OutputError`); one run writes into a folder at a time
    (:func:`scenarios.files.output_lock`). ``DIR/config.json`` records the configuration,
    the seed and, for a trained planner, what identifies its model (the checkpoint file,
    its SHA-256, epoch and step: ``config.model_checkpoint``); a run started again with the
    same record keeps every finished episode and runs the rest (and again the episodes that
    ended in ``"error"``), one with another record is refused naming the fields that
    differ, so episodes of two models (a run trained further in between) never mix. Within
    a run every worker checks that it loads the same checkpoint. ``DIR/summary.md`` and
    ``DIR/summary.csv`` hold the table over the episodes (``summary.md`` also says how many
    episodes ended in an error, and the first error), ``DIR/episodes.csv`` one row per
    episode.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size, short_repr
from scenarios.dataset import FieldSpec, Scenario
from scenarios.files import check_output_dir, output_lock, write_atomic
from solvers.control.types import Command, Plan, World

__all__ = [
    "EpisodeLog",
    "EpisodeResult",
    "EpisodeConfig",
    "SimConfig",
    "RunReport",
    "run_episode",
    "run_episodes",
    "episode_metrics",
    "brake",
    "usable",
    "summarize",
    "write_summary",
    "error_note",
    "load_results",
    "load_log",
    "OUTCOMES",
    "SUMMARY_COLUMNS",
    "MAX_EPISODES",
    "MAX_WORKERS",
]

#: most episodes of one run (every result is held in memory for the summary)
MAX_EPISODES = 100_000
#: most worker processes of one run
MAX_WORKERS = 1024

#: every outcome an episode can end with ("error": the episode raised, see its message)
OUTCOMES = ("success", "collision", "timeout", "off_road", "error")
CONFIG = "config.json"
FORMAT_VERSION = 1


# --------------------------------------------------------------------------------------
# one episode
# --------------------------------------------------------------------------------------
def usable(plan: Any, horizon: int | None = None) -> tuple[bool, str]:
    """Whether a tracker may follow ``plan``: a :class:`Plan` that is ``ok`` with finite
    states and controls of matching shapes. Returns ``(ok, why not)``."""
    if not isinstance(plan, Plan):
        return False, f"the planner returned {type(plan).__name__}, not a Plan"
    if not plan.ok:
        return False, plan.message
    s, c = np.asarray(plan.states), np.asarray(plan.controls)
    if s.ndim != 2 or s.shape[1] != 4 or c.shape != (s.shape[0], 2) or s.shape[0] < 1:
        return False, f"plan shapes {s.shape} / {c.shape}, expected (K, 4) / (K, 2)"
    if not (np.all(np.isfinite(s)) and np.all(np.isfinite(c))):
        return False, "the plan is not finite"
    return True, ""


def brake(world: World, ego: np.ndarray) -> Command:
    """The fallback: the vehicle's strongest deceleration, limited so the speed stops at
    zero within one step, and a straight steering command (``0`` for both models)."""
    a_min = float(getattr(getattr(world, "vehicle", None), "a_min", -5.0))
    v = float(ego[2]) if np.isfinite(ego[2]) else 0.0
    a = max(a_min, -max(v, 0.0) / float(world.dt))
    return Command(np.array([a, 0.0]), fallback=True, info={"reason": "brake"})


@dataclass
class EpisodeLog:
    """Everything one episode did, per step ``k = 0..T-1`` (``T`` planning periods).

    ``truth`` has ``T + 1`` rows (the state after the last command too); ``predictions``
    ``(T, M, N, K, 4)`` and ``probabilities`` ``(T, M)`` are NaN-padded to the largest
    ``M`` of the episode (NaN where a plan had none); ``latency`` ``(T, 3)`` holds the
    seconds of estimation, planning and tracking.
    """

    dt: float
    t: np.ndarray  # (T,)
    truth: np.ndarray  # (T+1, N, 4)
    obs_ego: np.ndarray  # (T, 4)
    obs_others: np.ndarray  # (T, N-1, 2)
    est_states: np.ndarray  # (T, N-1, 4)
    plan_states: np.ndarray  # (T, K, 4)
    plan_ok: np.ndarray  # (T,)
    predictions: np.ndarray  # (T, M, N, K, 4)
    probabilities: np.ndarray  # (T, M)
    command: np.ndarray  # (T, 2)
    fallback: np.ndarray  # (T,)
    latency: np.ndarray  # (T, 3)
    radii: np.ndarray  # (N,)
    ego_path: np.ndarray  # (P, 2)
    paths: list = field(default_factory=list)  # true paths of every agent (figures)
    lanes: list = field(default_factory=list)  # the map's lane centre lines (figures)
    lane_widths: list = field(default_factory=list)

    ARRAYS = (
        "t",
        "truth",
        "obs_ego",
        "obs_others",
        "est_states",
        "plan_states",
        "plan_ok",
        "predictions",
        "probabilities",
        "command",
        "fallback",
        "latency",
        "radii",
        "ego_path",
    )

    def arrays(self) -> dict[str, np.ndarray]:
        d = {k: getattr(self, k) for k in self.ARRAYS}
        d["dt"] = np.array(self.dt)
        for i, p in enumerate(self.paths):
            d[f"path_{i}"] = np.asarray(p, dtype=float)
        for i, c in enumerate(self.lanes):
            d[f"lane_{i}"] = np.asarray(c, dtype=float)
        d["lane_widths"] = np.asarray(self.lane_widths, dtype=float)
        return d

    @classmethod
    def from_arrays(cls, d: dict) -> EpisodeLog:
        paths = [d[f"path_{i}"] for i in range(len(d["radii"])) if f"path_{i}" in d]
        widths = list(np.asarray(d.get("lane_widths", []), dtype=float))
        lanes = [d[f"lane_{i}"] for i in range(len(widths))]
        return cls(
            dt=float(d["dt"]),
            paths=paths,
            lanes=lanes,
            lane_widths=widths,
            **{k: np.asarray(d[k]) for k in cls.ARRAYS},
        )


@dataclass
class EpisodeResult:
    """One episode: ``seed``, ``outcome`` (:data:`OUTCOMES`), ``metrics``, ``events``
    (fallbacks and failures: step, time, kind, message), the per-step planning latency
    (ms) and, when kept, the full :class:`EpisodeLog`."""

    index: int
    seed: int
    outcome: str
    metrics: dict
    events: list
    plan_ms: list
    log: EpisodeLog | None = None
    message: str = ""

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "seed": self.seed,
            "outcome": self.outcome,
            "message": self.message,
            "metrics": {k: _json_number(v) for k, v in self.metrics.items()},
            "events": self.events,
            "plan_ms": [round(float(x), 4) for x in self.plan_ms],
        }

    @classmethod
    def from_dict(cls, d: dict) -> EpisodeResult:
        m = {k: (math.nan if v is None else v) for k, v in d["metrics"].items()}
        return cls(
            int(d["index"]),
            int(d["seed"]),
            str(d["outcome"]),
            m,
            list(d["events"]),
            list(d["plan_ms"]),
            message=str(d.get("message", "")),
        )


def _json_number(v):
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_json_number(x) for x in np.asarray(v).tolist()]
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


class _Recorder:
    def __init__(self, world: World):
        self.world = world
        self.rows: dict[str, list] = {k: [] for k in EpisodeLog.ARRAYS[:-2]}
        self.events: list[dict] = []

    def event(self, k: int, t: float, kind: str, message: str) -> None:
        self.events.append({"step": k, "t": round(float(t), 6), "kind": kind, "message": message})

    def step(self, obs, est, plan, command, latency) -> None:
        r, K = self.rows, self.world_horizon(plan)
        r["t"].append(float(obs.t))
        r["truth"].append(np.asarray(self.world.truth(), dtype=float))
        r["obs_ego"].append(np.asarray(obs.ego, dtype=float))
        r["obs_others"].append(np.asarray(obs.others, dtype=float).reshape(-1, 2))
        r["est_states"].append(np.asarray(est.states, dtype=float).reshape(-1, 4))
        ok = isinstance(plan, Plan)
        states = np.asarray(plan.states, dtype=float) if ok else np.full((K, 4), np.nan)
        r["plan_states"].append(states if states.shape == (K, 4) else np.full((K, 4), np.nan))
        r["plan_ok"].append(bool(ok and usable(plan)[0]))
        pred = plan.predictions if ok else None
        prob = plan.probabilities if ok else None
        r["predictions"].append(None if pred is None else np.asarray(pred, dtype=float))
        r["probabilities"].append(None if prob is None else np.asarray(prob, dtype=float))
        r["command"].append(np.asarray(command.value, dtype=float).reshape(2))
        r["fallback"].append(bool(command.fallback))
        r["latency"].append(np.asarray(latency, dtype=float))

    def world_horizon(self, plan) -> int:
        if not hasattr(self, "_K"):
            s = np.asarray(getattr(plan, "states", np.zeros((1, 4))))
            self._K = s.shape[0] if s.ndim == 2 and s.shape[0] else 1
        return self._K

    def finish(self, world: World) -> EpisodeLog:
        r = self.rows
        T = len(r["t"])
        N = int(world.n_agents)
        K = getattr(self, "_K", 1)
        preds, probs = r["predictions"], r["probabilities"]
        shapes = {p.shape[1:] for p in preds if p is not None and p.ndim == 4}
        M = max([p.shape[0] for p in preds if p is not None and p.ndim == 4] or [0])
        pshape = shapes.pop() if len(shapes) == 1 else (N, K, 4)
        P = np.full((T, M, *pshape), np.nan)
        W = np.full((T, M), np.nan)
        for k, (p, w) in enumerate(zip(preds, probs, strict=True)):
            if p is not None and p.ndim == 4 and p.shape[1:] == pshape:
                P[k, : p.shape[0]] = p
            if w is not None and w.ndim == 1 and w.size <= M:
                W[k, : w.size] = w

        def stack(name, shape):
            return np.stack(r[name]) if T else np.zeros((0, *shape))

        return EpisodeLog(
            dt=float(world.dt),
            t=np.asarray(r["t"], dtype=float),
            truth=np.stack([*r["truth"], np.asarray(world.truth(), dtype=float)]),
            obs_ego=stack("obs_ego", (4,)),
            obs_others=stack("obs_others", (N - 1, 2)),
            est_states=stack("est_states", (N - 1, 4)),
            plan_states=stack("plan_states", (K, 4)),
            plan_ok=np.asarray(r["plan_ok"], dtype=bool),
            predictions=P,
            probabilities=W,
            command=stack("command", (2,)),
            fallback=np.asarray(r["fallback"], dtype=bool),
            latency=stack("latency", (3,)),
            radii=np.asarray(world.radii, dtype=float).reshape(-1),
            ego_path=np.asarray(world.ego_task.path, dtype=float),
            paths=_true_paths(world),
            **_lanes(world),
        )


def _true_paths(world) -> list:
    try:
        return [np.asarray(t.path, dtype=float) for t in world.tasks()]
    except Exception:  # noqa: BLE001 - figures only; a world without tasks still runs
        return []


def _lanes(world) -> dict:
    rm = getattr(world, "road_map", None)
    lanes = getattr(rm, "lanes", None)
    if lanes is None:
        return {}
    if isinstance(lanes, dict):
        lanes = list(lanes.values())
    return {
        "lanes": [np.asarray(ln.centre, dtype=float) for ln in lanes],
        "lane_widths": [float(ln.width) for ln in lanes],
    }


def _safe(fn: Callable, *args):
    try:
        return fn(*args), None
    except Exception as e:  # noqa: BLE001 - the loop survives any planner/tracker failure
        return None, f"{type(e).__name__}: {e}"


def run_episode(
    world: World,
    estimator,
    planner,
    tracker,
    seed: int,
    max_steps: int | None = None,
    index: int = 0,
    keep_log: bool = True,
) -> EpisodeResult:
    """Run one episode from ``world.reset(seed)`` until the world's outcome is no longer
    ``"running"`` (or ``max_steps``, default ``world.max_steps``, periods: ``"timeout"``).

    A failed plan, a planner or tracker that raises, or a tracker's own fallback, makes the
    ego brake for that period and adds an event; the episode goes on.
    """
    check_number("seed", seed, lo=0, integer=True)
    limit = int(max_steps if max_steps is not None else getattr(world, "max_steps", 10**6))
    obs = world.reset(int(seed))
    planner.reset(world)
    tracker.reset(world)
    tic = time.perf_counter()
    est = estimator.reset(obs, world.dt)
    t_est = time.perf_counter() - tic
    rec = _Recorder(world)
    k, outcome = 0, world.outcome()
    while outcome == "running" and k < limit:
        tic = time.perf_counter()
        plan, err = _safe(planner.plan, obs, est)
        t_plan = time.perf_counter() - tic
        ok, why = usable(plan) if err is None else (False, f"planner raised {err}")
        tic = time.perf_counter()
        if ok:
            command, err = _safe(tracker.control, obs.ego, plan, obs.t)
            if err is not None:
                rec.event(k, obs.t, "tracker_error", f"tracker raised {err}")
                command = brake(world, obs.ego)
            elif command.fallback:
                msg = str(command.info.get("message", command.info.get("status", "fallback")))
                rec.event(k, obs.t, "tracker_fallback", msg)
        else:
            rec.event(k, obs.t, "plan_failed", why)
            command = brake(world, obs.ego)
        t_track = time.perf_counter() - tic
        rec.step(obs, est, plan, command, (t_est, t_plan, t_track))
        obs = world.step(command.value)
        k += 1
        outcome = world.outcome()
        tic = time.perf_counter()
        est = estimator.update(obs)
        t_est = time.perf_counter() - tic
    if outcome == "running":
        outcome = "timeout"
    log = rec.finish(world)
    metrics = episode_metrics(log, outcome, conflict_zone=_world_zone(world))
    return EpisodeResult(
        index=int(index),
        seed=int(seed),
        outcome=outcome,
        metrics=metrics,
        events=rec.events,
        plan_ms=list(log.latency[:, 1] * 1e3),
        log=log if keep_log else None,
    )


# --------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------
def _world_zone(world) -> tuple[float, float] | None:
    """The ego's arc-length interval of the world's conflict zone, if it defines one."""
    zone = getattr(world, "conflict_zone", None) or getattr(world, "conflict", None)
    if callable(zone):
        try:
            zone = zone()
        except TypeError:
            zone = None
    if zone is None:
        return None
    a = getattr(zone, "a", zone)
    try:
        s_in, s_out = (float(v) for v in a)
    except (TypeError, ValueError):
        return None
    return (s_in, s_out)


def _arc(path: np.ndarray, points: np.ndarray) -> np.ndarray:
    from scenarios.maps import project_to_polyline

    return project_to_polyline(points, path)[0]


def episode_metrics(
    log: EpisodeLog, outcome: str, conflict_zone: tuple[float, float] | None = None
) -> dict:
    """The metrics of the module docstring from a finished episode's log."""
    dt = log.dt
    T = len(log.t)
    pos = log.truth[:, :, :2]  # (T+1, N, 2)
    r = log.radii
    m: dict[str, Any] = {"steps": T, "duration": T * dt}
    m["success"] = outcome == "success"
    m["collision"] = outcome == "collision"
    N = pos.shape[1]
    if N > 1:
        gap = np.linalg.norm(pos[:, 1:] - pos[:, :1], axis=2) - r[0] - r[1:]  # (T+1, N-1)
        per_agent = gap.min(axis=0)
        m["min_distance"] = float(per_agent.min())
        m["min_distance_per_agent"] = per_agent.tolist()
        closest = int(np.argmin(gap.min(axis=1)))
        j = int(np.argmin(gap[closest]))
    else:
        m["min_distance"] = math.nan
        m["min_distance_per_agent"] = []
    s = _arc(log.ego_path, pos[:, 0])
    m["progress"] = float(s[-1] - s[0])
    total = float(np.sum(np.linalg.norm(np.diff(log.ego_path, axis=0), axis=1)))
    m["progress_fraction"] = float(m["progress"] / total) if total > 0 else math.nan
    if conflict_zone is not None:
        s_out = conflict_zone[1]
    elif N > 1:
        s_out = s[closest] + r[0] + r[1 + j]
    else:
        s_out = math.nan
    cleared = np.flatnonzero(s >= s_out) if math.isfinite(s_out) else np.zeros(0, int)
    m["time_to_clear"] = float(cleared[0] * dt) if cleared.size else math.nan
    v = log.truth[:, 0, 2]
    jerk = np.diff(v, n=2) / dt**2
    m["rms_jerk"] = float(np.sqrt(np.mean(jerk**2))) if jerk.size else math.nan
    plan_ms = log.latency[:, 1] * 1e3
    m["plan_p50_ms"] = float(np.percentile(plan_ms, 50)) if T else math.nan
    m["plan_p99_ms"] = float(np.percentile(plan_ms, 99)) if T else math.nan
    m["rtf"] = float(np.mean(plan_ms) / (dt * 1e3)) if T else math.nan
    m["estimate_ms"] = float(np.mean(log.latency[:, 0]) * 1e3) if T else math.nan
    m["track_ms"] = float(np.mean(log.latency[:, 2]) * 1e3) if T else math.nan
    m["fallbacks"] = int(np.sum(log.fallback))
    return m


# --------------------------------------------------------------------------------------
# configurations
# --------------------------------------------------------------------------------------
class EpisodeConfig(Protocol):
    """What :func:`run_episodes` needs: a picklable description that builds a fresh stack."""

    def to_dict(self) -> dict: ...

    def build(self) -> tuple[Any, Any, Any, Any]:
        """``(world, estimator, planner, tracker)``, new objects."""
        ...


PLANNERS = ("model", "oracle", "cv", "sc")
TRACKERS = ("pid", "mpc")


@dataclass(frozen=True)
class SimConfig:
    """One closed-loop configuration: scenario and its options, planner, tracker.

    ``planner``: ``"oracle"`` / ``"cv"`` (:mod:`solvers.control.plan`, options
    :class:`~solvers.control.plan.PlannerOptions`) or ``"model"`` / ``"sc"`` (a trained
    run in ``model``, loaded by ``learning.control.load_planner``); ``tracker``: ``"pid"``
    or ``"mpc"`` (:mod:`solvers.control.track`); ``world_options`` go to
    ``scenarios.sim.make_world(scenario, **world_options)``. ``model_checkpoint``: what
    identifies the trained model (``NetworkPlanner.identity``: checkpoint file, SHA-256,
    epoch, step); when set, :meth:`build` refuses a run directory whose checkpoint is
    another (:func:`run_episodes` sets it from the first build: :meth:`pinned`).
    """

    scenario: str
    planner: str = "oracle"
    tracker: str = "mpc"
    model: str | None = None
    world_options: dict = field(default_factory=dict)
    planner_options: dict = field(default_factory=dict)
    tracker_options: dict = field(default_factory=dict)
    estimator_options: dict = field(default_factory=dict)
    model_checkpoint: dict | None = None

    def __post_init__(self):
        if self.planner not in PLANNERS:
            raise SpecError("planner", f"expected one of {list(PLANNERS)}, got {self.planner!r}")
        if self.tracker not in TRACKERS:
            raise SpecError("tracker", f"expected one of {list(TRACKERS)}, got {self.tracker!r}")
        if self.planner in ("model", "sc") and not self.model:
            raise SpecError("model", f"planner {self.planner!r} needs a trained run directory")
        if self.model is not None and self.planner not in ("model", "sc"):
            raise SpecError(
                "model",
                f"a model is only used by the planners 'model' and 'sc', not {self.planner!r}",
            )
        for name in ("world_options", "planner_options", "tracker_options", "estimator_options"):
            if not isinstance(getattr(self, name), dict):
                raise SpecError(name, f"expected a mapping, got {getattr(self, name)!r}")

    def to_dict(self) -> dict:
        return {
            "scenario": self.scenario,
            "planner": self.planner,
            "tracker": self.tracker,
            "model": self.model,
            "world_options": dict(self.world_options),
            "planner_options": dict(self.planner_options),
            "tracker_options": dict(self.tracker_options),
            "estimator_options": dict(self.estimator_options),
        } | ({"model_checkpoint": dict(self.model_checkpoint)} if self.model_checkpoint else {})

    def pinned(self, planner) -> SimConfig:
        """This configuration with ``model_checkpoint`` set from a built network planner's
        ``identity`` (unchanged for the other planners or when already set)."""
        ident = getattr(planner, "identity", None)
        if self.model_checkpoint is not None or not isinstance(ident, dict):
            return self
        return replace(self, model_checkpoint=dict(ident))

    @property
    def label(self) -> str:
        return f"{self.scenario} {self.planner}+{self.tracker}"

    def build(self):
        from scenarios.sim import make_world
        from solvers.control.estimate import UKFEstimator
        from solvers.control.track import MPCTracker, PIDTracker

        world = make_world(self.scenario, **self.world_options)
        estimator = UKFEstimator(**self.estimator_options)
        tracker_cls = PIDTracker if self.tracker == "pid" else MPCTracker
        tracker = tracker_cls(**self.tracker_options)
        if self.planner == "oracle":
            from solvers.control.plan import GameOracle

            planner = GameOracle(self.planner_options)
        elif self.planner == "cv":
            from solvers.control.plan import ConstantVelocityPlanner

            planner = ConstantVelocityPlanner(self.planner_options)
        else:
            planner = _network_planner(
                self.model, self.scenario, self.planner_options, self.planner
            )
            _check_identity(self.model, self.model_checkpoint, getattr(planner, "identity", None))
        return world, estimator, planner, tracker


def _check_identity(model: str, want: dict | None, got: dict | None) -> None:
    """Refuse a loaded model that is not the one the run recorded (``model_checkpoint``)."""
    if want is None or got is None:
        return
    for k in ("checkpoint", "sha256", "epoch", "step"):
        if want.get(k) != got.get(k):
            raise SpecError(
                f"model_checkpoint.{k}",
                f"the run recorded {short_repr(want.get(k))}, the model at {model} now has "
                f"{short_repr(got.get(k))}: its checkpoint changed (trained further?); "
                "simulate it into another --out",
            )


def _network_planner(model: str, scenario: str, options: dict, name: str):
    if not Path(model).is_dir():
        raise SpecError("model", f"no trained run directory at {model!r}")
    try:
        from learning.control import load_planner
    except ImportError as e:
        raise SpecError(
            "planner",
            f"the network planner needs learning.control.load_planner, not available here ({e})",
        ) from None
    planner = load_planner(model, scenario, **options)
    kind = getattr(getattr(planner, "spec", None), "kind", None)
    want = "epo" if name == "model" else "sc"
    if kind is not None and kind != want:
        other = "model" if kind == "epo" else "sc"
        raise SpecError(
            "planner", f"the run {model} holds a {kind!r} model; use --planner {other} for it"
        )
    return planner


# --------------------------------------------------------------------------------------
# parallel episodes (the engines of scenarios.dataset)
# --------------------------------------------------------------------------------------


class EpisodeJob(Scenario):
    """Episodes as work units of :mod:`scenarios.dataset`'s engines: unit ``i`` is the
    episode of seed ``seed + i``, built from ``config`` in the worker."""

    name = "closed-loop"

    def __init__(self, config, seed: int, keep_logs: Sequence[int] = ()):
        self.config = config
        self.seed = int(seed)
        self.keep_logs = tuple(int(i) for i in keep_logs)

    def schema(self) -> dict[str, FieldSpec]:
        return {"episode": FieldSpec((), "O", "the episode's result")}

    def run_unit(self, index: int, seed) -> dict[str, np.ndarray]:
        out = np.empty(1, dtype=object)
        out[0] = episode_unit(self.config, index, self.seed + index, index in self.keep_logs)
        return {"episode": out}


def episode_unit(config, index: int, seed: int, keep_log: bool) -> EpisodeResult:
    """Build the stack from ``config`` and run episode ``index`` with ``seed``; an exception
    becomes the outcome ``"error"`` with its message (the other episodes go on)."""
    try:
        world, estimator, planner, tracker = config.build()
        return run_episode(world, estimator, planner, tracker, seed, index=index, keep_log=keep_log)
    except Exception as e:  # noqa: BLE001 - one broken episode must not lose the run
        return EpisodeResult(
            index, seed, "error", {}, [], [], message=f"{type(e).__name__}: {e}".splitlines()[0]
        )


@dataclass
class RunReport:
    """What :func:`run_episodes` did: results in episode order, the summary row, files."""

    directory: str | None
    results: list[EpisodeResult]
    summary: dict
    ran: int
    kept: int
    seconds: float
    logs: dict[int, EpisodeLog] = field(default_factory=dict)


def _episode_path(d: Path, i: int) -> Path:
    return d / "episodes" / f"episode-{i:05d}.json"


def _write_text(path: Path, text: str) -> None:
    write_atomic(path, text)


def _write_npz(path: Path, arrays: dict) -> None:
    write_atomic(path, lambda f: np.savez_compressed(f, **arrays))


def load_log(path: str | os.PathLike) -> EpisodeLog:
    """An :class:`EpisodeLog` saved by :func:`run_episodes` (``episode-NNNNN.npz``)."""
    with np.load(path) as z:
        return EpisodeLog.from_arrays({k: z[k] for k in z.files})


def load_results(directory: str | os.PathLike, episodes: int | None = None) -> list:
    """Finished :class:`EpisodeResult` of a run directory, in episode order."""
    d = Path(directory)
    out = []
    for p in sorted((d / "episodes").glob("episode-*.json")):
        try:
            r = EpisodeResult.from_dict(json.loads(p.read_text()))
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if episodes is None or r.index < episodes:
            out.append(r)
    return out


def run_episodes(
    config,
    episodes: int,
    seed: int = 0,
    workers: int = 1,
    engine: str = "local",
    out: str | os.PathLike | None = None,
    keep_logs: Sequence[int] = (0,),
    progress: bool = True,
    client=None,
    address: str | None = None,
    scheduler_timeout: float = 10.0,
) -> RunReport:
    """Run ``episodes`` episodes of ``config`` (seeds ``seed .. seed + episodes - 1``).

    ``config``: a :class:`SimConfig` or any picklable object with ``to_dict()`` and
    ``build()`` (and optionally ``pinned(planner)``, see :meth:`SimConfig.pinned`).
    ``engine``: ``"local"`` (``workers`` processes) or ``"dask"`` (``client``, scheduler
    ``address``, waited for ``scheduler_timeout`` s, or a new local cluster). With ``out``,
    results are written as the module docstring says and an interrupted run resumes; the
    logs of the episodes in ``keep_logs`` are saved as ``episodes/episode-NNNNN.npz`` and
    returned. ``episodes`` is at most :data:`MAX_EPISODES`, ``workers`` at most
    :data:`MAX_WORKERS` (:func:`~epo_casadi.errors.check_size`, before any work).
    """
    from scenarios.dataset import _iter_dask, _iter_local

    episodes = check_size("episodes", episodes, MAX_EPISODES, "results held in memory")
    check_number("seed", seed, lo=0, integer=True)
    workers = check_size("workers", workers, MAX_WORKERS, "processes")
    check_number("scheduler_timeout", scheduler_timeout, lo=0, lo_open=True)
    if engine not in ("local", "dask"):
        raise SpecError("engine", f"expected 'local' or 'dask', got {engine!r}")
    t0 = time.perf_counter()
    stack = config.build()  # input errors surface here, in one line, before any worker starts
    pin = getattr(config, "pinned", None)
    if callable(pin):  # a trained planner: every worker must load this very checkpoint
        config = pin(stack[2])
    del stack
    header = {"format_version": FORMAT_VERSION, "config": config.to_dict(), "seed": int(seed)}
    done: dict[int, EpisodeResult] = {}
    logs: dict[int, EpisodeLog] = {}
    d = Path(out) if out is not None else None
    lock = _nullcontext()
    if d is not None:
        lock = output_lock(check_output_dir(d), "epo simulate")
    with lock:
        if d is not None:
            cpath = d / CONFIG
            if cpath.exists():
                try:
                    old = json.loads(cpath.read_text())
                except (OSError, ValueError) as e:
                    raise SpecError(str(cpath), f"unreadable ({e})") from None
                diff = _differences(old, json.loads(_canon(header)))
                if diff:
                    raise SpecError(
                        str(cpath),
                        "holds a run with another configuration or seed: "
                        + "; ".join(
                            f"{k} ({short_repr(a, 60)} there, {short_repr(b, 60)} asked)"
                            for k, a, b in diff[:4]
                        )
                        + ("; ..." if len(diff) > 4 else "")
                        + "; use another --out",
                    )
            else:
                _write_text(cpath, json.dumps(header, indent=1) + "\n")
            for tmp in (d / "episodes").glob(".*.tmp"):
                with contextlib.suppress(OSError):  # left by a killed run
                    tmp.unlink()
            for r in load_results(d, episodes):
                npz = _episode_path(d, r.index).with_suffix(".npz")
                stale = r.seed != seed + r.index or r.outcome == "error"  # errors run again
                if stale or (r.index in keep_logs and not npz.is_file()):
                    continue
                done[r.index] = r
                if r.index in keep_logs:
                    logs[r.index] = load_log(npz)
        n_todo = episodes - len(done)
        todo = (i for i in range(episodes) if i not in done)  # lazily: never a list of all
        job = EpisodeJob(config, seed, keep_logs)
        bar = it = None
        if progress and n_todo:
            from tqdm import tqdm

            bar = tqdm(total=n_todo, unit="episode", desc=_label(config), dynamic_ncols=True)
        try:
            if engine == "local":
                it = _iter_local(job, todo, seed, workers)
            else:
                it = _iter_dask(job, todo, seed, workers, client, address, scheduler_timeout)
            counts: dict[str, int] = {}
            for index, arrays, _ in it:
                res: EpisodeResult = arrays["episode"][0]
                if d is not None:
                    if res.log is not None:
                        _write_npz(_episode_path(d, index).with_suffix(".npz"), res.log.arrays())
                    _write_text(_episode_path(d, index), json.dumps(res.to_dict()) + "\n")
                if res.log is not None:
                    logs[index] = res.log
                done[index] = res
                counts[res.outcome] = counts.get(res.outcome, 0) + 1
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix({k: v for k, v in sorted(counts.items())})
        finally:
            if it is not None:
                it.close()
            if bar is not None:
                bar.close()
        results = [done[i] for i in range(episodes)]
        summary = summarize(results, label=_label(config))
        if d is not None:
            write_summary(d, results, summary)
    return RunReport(
        str(d) if d is not None else None,
        results,
        summary,
        n_todo,
        episodes - n_todo,
        time.perf_counter() - t0,
        logs,
    )


_MISSING = "(absent)"


def _differences(old, new, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """The dotted fields (``config.model_checkpoint.sha256``) where two JSON records differ,
    with both values."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in [*old, *(k for k in new if k not in old)]:
            key = f"{prefix}.{k}" if prefix else str(k)
            out += _differences(old.get(k, _MISSING), new.get(k, _MISSING), key)
        return out
    return [] if old == new else [(prefix or "record", old, new)]


class _nullcontext:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def _canon(obj) -> str:
    return json.dumps(obj, sort_keys=True, default=str)


def _label(config) -> str:
    return str(getattr(config, "label", type(config).__name__))


# --------------------------------------------------------------------------------------
# summaries
# --------------------------------------------------------------------------------------
#: (column, header, format) of the summary table
SUMMARY_COLUMNS = (
    ("config", "configuration", "{}"),
    ("episodes", "episodes", "{:d}"),
    ("success_rate", "success", "{:.2f}"),
    ("collision_rate", "collision", "{:.2f}"),
    ("timeout_rate", "timeout", "{:.2f}"),
    ("off_road_rate", "off road", "{:.2f}"),
    ("error_rate", "error", "{:.2f}"),
    ("min_distance", "min dist (m)", "{:.2f}"),
    ("time_to_clear", "clear (s)", "{:.2f}"),
    ("progress", "progress (m)", "{:.1f}"),
    ("rms_jerk", "RMS jerk (m/s^3)", "{:.2f}"),
    ("plan_p50_ms", "plan p50 (ms)", "{:.1f}"),
    ("plan_p99_ms", "plan p99 (ms)", "{:.1f}"),
    ("rtf", "RTF", "{:.2f}"),
    ("fallbacks", "fallbacks", "{:d}"),
)


def _nanmean(values) -> float:
    a = np.asarray([v for v in values if v is not None], dtype=float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else math.nan


def summarize(results: Sequence[EpisodeResult], label: str = "") -> dict:
    """One summary row over ``results``: rates of every outcome, means of the metrics
    (over the episodes where a metric is defined), latency percentiles over all steps
    pooled, the mean real-time factor and the total number of fallbacks."""
    n = len(results)
    row: dict[str, Any] = {"config": label, "episodes": n}
    for o in OUTCOMES:
        row[f"{o}_rate"] = sum(r.outcome == o for r in results) / n if n else math.nan
    ms = [r.metrics for r in results if r.outcome != "error"]
    for k in ("min_distance", "time_to_clear", "progress", "rms_jerk", "rtf"):
        row[k] = _nanmean(m.get(k) for m in ms)
    pooled = np.concatenate([np.asarray(r.plan_ms, dtype=float) for r in results] or [[]])
    pooled = pooled[np.isfinite(pooled)]
    row["plan_p50_ms"] = float(np.percentile(pooled, 50)) if pooled.size else math.nan
    row["plan_p99_ms"] = float(np.percentile(pooled, 99)) if pooled.size else math.nan
    row["fallbacks"] = int(sum(int(m.get("fallbacks", 0) or 0) for m in ms))
    return row


def _cell(fmt: str, v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return fmt.format(v)


def summary_markdown(rows: Sequence[dict]) -> str:
    """The summary rows as a Markdown table (``n/a`` where a metric is undefined)."""
    head = "| " + " | ".join(h for _, h, _ in SUMMARY_COLUMNS) + " |"
    sep = "|" + "|".join("---" if k == "config" else "---:" for k, _, _ in SUMMARY_COLUMNS) + "|"
    lines = [head, sep]
    for row in rows:
        lines.append("| " + " | ".join(_cell(f, row.get(k)) for k, _, f in SUMMARY_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def _csv(rows: Sequence[dict], columns: Sequence[str]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for row in rows:
        vals = []
        for c in columns:
            v = row.get(c)
            if isinstance(v, float) and not math.isfinite(v):
                v = ""
            vals.append("" if v is None else v)
        w.writerow(vals)
    return buf.getvalue()


EPISODE_COLUMNS = (
    "index",
    "seed",
    "outcome",
    "min_distance",
    "time_to_clear",
    "progress",
    "rms_jerk",
    "plan_p50_ms",
    "plan_p99_ms",
    "rtf",
    "fallbacks",
    "message",
)


def error_note(results: Sequence[EpisodeResult]) -> str | None:
    """``"2 of 5 episodes ended in an error; the first, episode 1 (seed 1): ..."``, or None
    when none did."""
    errors = [r for r in results if r.outcome == "error"]
    if not errors:
        return None
    e = errors[0]
    return (
        f"{len(errors)} of {len(results)} episodes ended in an error; the first, episode "
        f"{e.index} (seed {e.seed}): {e.message}"
    )


def write_summary(directory: str | os.PathLike, results: Sequence[EpisodeResult], summary: dict):
    """Write ``summary.md``, ``summary.csv`` and ``episodes.csv`` atomically.

    ``summary.md`` is the table, then (when episodes ended in an error) one line saying how
    many and the first error (:func:`error_note`)."""
    d = Path(directory)
    note = error_note(results)
    md = summary_markdown([summary]) + (f"\n{note}\n" if note else "")
    _write_text(d / "summary.md", md)
    _write_text(d / "summary.csv", _csv([summary], [k for k, _, _ in SUMMARY_COLUMNS]))
    rows = [
        {
            "index": r.index,
            "seed": r.seed,
            "outcome": r.outcome,
            "message": r.message,
            **{k: r.metrics.get(k) for k in EPISODE_COLUMNS[3:-1]},
        }
        for r in results
    ]
    _write_text(d / "episodes.csv", _csv(rows, EPISODE_COLUMNS))
