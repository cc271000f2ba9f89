"""What one episode records: :class:`EpisodeLog` (every step), :class:`EpisodeResult`
(outcome, metrics, events) and the recorder that fills the log while the loop runs."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from solvers.control.types import Plan, World, world_member

__all__ = ["EpisodeLog", "EpisodeResult", "Recorder", "OUTCOMES", "usable"]

#: every outcome an episode can end with ("error": the episode raised, see its message)
OUTCOMES = ("success", "collision", "timeout", "off_road", "error")


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


class Recorder:
    """Fills an :class:`EpisodeLog` step by step (rows, then :meth:`finish`) and collects
    the episode's events."""

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
    rm = world_member(world, "road_map")
    if rm is None:
        return {}
    lanes = rm.lanes
    if isinstance(lanes, dict):
        lanes = list(lanes.values())
    return {
        "lanes": [np.asarray(ln.centre, dtype=float) for ln in lanes],
        "lane_widths": [float(ln.width) for ln in lanes],
    }
