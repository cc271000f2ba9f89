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
    limit = int(max_steps if max_steps is not None else world_member(world, "max_steps"))
    obs = world.reset(int(seed))
    planner.reset(world)
    tracker.reset(world)
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
    metrics = episode_metrics(log, outcome, conflict_zone=world_member(world, "conflict_zone")())
    return EpisodeResult(
        index=int(index),
        seed=int(seed),
        outcome=outcome,
        metrics=metrics,
        events=rec.events,
        plan_ms=list(log.latency[:, 1] * 1e3),
        log=log if keep_log else None,
    )
