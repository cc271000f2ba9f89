"""One episode of the closed loop (:func:`run_episode`) and its fallback (:func:`brake`)."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from epo_casadi.errors import check_number
from solvers.control.types import Command, World, world_member

from .log import EpisodeResult, Recorder, usable
from .metrics import episode_metrics

__all__ = ["brake", "run_episode"]


def brake(world: World, ego: np.ndarray) -> Command:
    """The fallback: the vehicle's strongest deceleration (``world.vehicle.a_min``), limited
    so the speed stops at zero within one step, and a straight steering command (``0``
    for both models)."""
    a_min = float(world.vehicle.a_min)
    v = float(ego[2]) if np.isfinite(ego[2]) else 0.0
    a = max(a_min, -max(v, 0.0) / float(world.dt))
    return Command(np.array([a, 0.0]), fallback=True, info={"reason": "brake"})


def _safe(fn: Callable, *args):
    try:
        return fn(*args), None
    except Exception as e:  # noqa: BLE001 - the loop survives any planner/tracker failure
        return None, f"{type(e).__name__}: {e}"


def _filtered(safety, world, tracker, rec, steps, k, obs, est, plan, ok, command) -> Command:
    """``command`` through the safety filter; the step's record in ``steps``."""
    tic = time.perf_counter()
    out, err = _safe(safety.filter, obs, est, plan if ok else None, command)
    seconds = time.perf_counter() - tic
    if err is not None:
        rec.event(k, obs.t, "filter_error", f"safety filter raised {err}")
        out = brake(world, obs.ego)
        info = {"intervened": True, "fallback": True, "certified": False}
    else:
        info = out.info.get("safety", {}) if isinstance(out.info, dict) else {}
        if info.get("fallback"):
            rec.event(k, obs.t, "filter_fallback", str(info.get("reason", "fallback")))
        elif info.get("intervened"):
            rec.event(k, obs.t, "filter_intervened", str(info.get("reason", "")))
    steps.append(
        {
            "intervened": bool(info.get("intervened", False)),
            "fallback": bool(info.get("fallback", False)),
            "certified": bool(info.get("certified", False)),
            "seconds": seconds,
        }
    )
    notify = getattr(tracker, "applied", None)
    if callable(notify):
        _safe(notify, out.value)
    return out


def run_episode(
    world: World,
    estimator,
    planner,
    tracker,
    seed: int,
    max_steps: int | None = None,
    index: int = 0,
    keep_log: bool = True,
    safety=None,
) -> EpisodeResult:
    """Run one episode from ``world.reset(seed)`` until the world's outcome is no longer
    ``"running"`` (or ``max_steps``, default ``world.max_steps``, periods: ``"timeout"``).

    A failed plan, a planner or tracker that raises, or a tracker's own fallback, makes the
    ego brake for that period and adds an event; the episode goes on.

    ``safety``: a safety filter (:class:`solvers.control.safety.SafetyFilter`, reset here
    with the world) between the tracker and the world: every command, the braking ones
    included, goes through ``safety.filter(obs, est, plan or None, command)`` and the
    tracker is told what the actuators got (``tracker.applied(u)``, where it has it). Its
    interventions and fallbacks are events (``filter_intervened``, ``filter_fallback``;
    a filter that raises: ``filter_error`` and the ego brakes) and the metrics
    ``intervention_rate``, ``filter_fallbacks``, ... (:func:`episode_metrics`). None: no
    filter (``SimConfig`` builds one by default).
    """
    check_number("seed", seed, lo=0, integer=True)
    limit = int(max_steps if max_steps is not None else world_member(world, "max_steps"))
    obs = world.reset(int(seed))
    planner.reset(world)
    tracker.reset(world)
    if safety is not None:
        safety.reset(world)
    filter_steps: list[dict] | None = [] if safety is not None else None
    use_map = getattr(estimator, "use_map", None)
    if callable(use_map):  # the lanes a new track's heading starts from (optional member)
        use_map(world_member(world, "road_map"))
    tic = time.perf_counter()
    est = estimator.reset(obs, world.dt)
    t_est = time.perf_counter() - tic
    rec = Recorder(world)
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
        if safety is not None:
            command = _filtered(
                safety, world, tracker, rec, filter_steps, k, obs, est, plan, ok, command
            )
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
    metrics = episode_metrics(
        log,
        outcome,
        conflict_zone=world_member(world, "conflict_zone")(),
        filter_steps=filter_steps,
    )
    return EpisodeResult(
        index=int(index),
        seed=int(seed),
        outcome=outcome,
        metrics=metrics,
        events=rec.events,
        plan_ms=list(log.latency[:, 1] * 1e3),
        log=log if keep_log else None,
    )
