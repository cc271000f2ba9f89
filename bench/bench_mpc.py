"""Time one tracking step of the MPC (OSQP) and PID trackers, and one estimator update.

Not a test. Run from the repository root::

    .venv/bin/python bench/bench_mpc.py            # horizons 10, 20, 30; 400 steps each
    .venv/bin/python bench/bench_mpc.py --quick    # horizon 20 only, 100 steps

What is timed: a closed loop on the world's vehicle model (the highway-env bicycle,
``VehicleModel.highway``, and the unicycle), dt = 0.1 s, following a feasible curved
reference that speeds up and slows down; the ego starts 0.5 m off it. Every step the tracker
gets a fresh plan of 30 states (as a planner would give it). ``MPC step`` is the whole
``MPCTracker.control`` call: reference sampling, CasADi linearization, QP numbers, OSQP
``update`` (which refactorizes the KKT matrix because P and A change) and ``solve``; it is
split into ``build``, ``update`` and ``solve``. ``PID step`` is ``PIDTracker.control``;
``UKF update`` is ``UKFEstimator.update`` for one observed agent (CTRV). Times are
wall-clock medians and 99th percentiles over the steps after 10 warm-up steps, the process
pinned to one CPU core where the OS allows it, BLAS limited to one thread. Ratios are to the
100 ms planning period and to the 2 ms the MPC QP may take (issue 9).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("EPO_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from solvers.control import (  # noqa: E402
    MPCTracker,
    Observation,
    PIDTracker,
    Plan,
    UKFEstimator,
    VehicleModel,
)

DT = 0.1
PERIOD_MS, QP_MS = 100.0, 2.0


class _World:
    def __init__(self, vehicle):
        self.vehicle, self.dt = vehicle, DT


def _reference(veh, T):
    t = np.arange(T) * DT
    U = veh.clip(np.stack([0.8 * np.sin(0.5 * t), 0.3 * np.sin(0.3 * t)], axis=1))
    x0 = np.array([0.0, 0.0, 8.0, 0.2])
    X = veh.rollout(x0, U, DT)
    prev = np.concatenate([x0[None], X[:-1]])
    return x0, X, np.stack([U[:, 0], veh.turn_rate(prev, U)], axis=1)


def _loop(tracker, veh, steps, warm=10):
    x0, X, Uuni = _reference(veh, steps + warm + 31)
    tracker.reset(_World(veh))
    x = x0 + np.array([0.0, 0.5, 0.0, 0.0])
    times, parts, err = [], [], []
    for k in range(steps + warm):
        plan = Plan(t0=k * DT, dt=DT, states=X[k : k + 30], controls=Uuni[k : k + 30])
        t = time.perf_counter()
        cmd = tracker.control(x, plan, k * DT)
        t = time.perf_counter() - t
        x = veh.step(x, cmd.value, DT)
        if k >= warm:
            times.append(t)
            if "timing" in cmd.info:
                parts.append([cmd.info["timing"][p] for p in ("build", "update", "solve")])
            err.append(np.linalg.norm(x[:2] - X[k, :2]))
    return np.array(times) * 1e3, np.array(parts) * 1e3, float(np.max(err)), tracker.fallbacks


def _row(name, ms):
    p50, p99 = np.median(ms), np.percentile(ms, 99)
    print(f"{name:<28} {p50:8.3f} {p99:8.3f} {PERIOD_MS / p50:10.0f}x {QP_MS / p50:9.2f}x")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="horizon 20 only, 100 steps")
    args = ap.parse_args(argv)
    try:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
        pinned = "pinned to one core"
    except (AttributeError, OSError):
        pinned = "not pinned"
    steps = 100 if args.quick else 400
    horizons = [20] if args.quick else [10, 20, 30]
    print(f"bench_mpc: dt = {DT} s, {steps} timed steps per row, {pinned}")
    print(f"{'what':<28} {'p50 ms':>8} {'p99 ms':>8} {'100ms/p50':>11} {'2ms/p50':>10}")
    vehicles = {"bicycle": VehicleModel.highway(), "unicycle": VehicleModel()}
    for vname, veh in vehicles.items():
        for N in horizons:
            ms, parts, err, fb = _loop(MPCTracker(horizon=N), veh, steps)
            _row(f"MPC step {vname} N={N}", ms)
            for i, p in enumerate(("build", "update", "solve")):
                _row(f"  {p}", parts[:, i])
            print(f"  max tracking error {err:.3f} m, fallbacks {fb}")
        ms, _, err, fb = _loop(PIDTracker(), veh, steps)
        _row(f"PID step {vname}", ms)
        print(f"  max tracking error {err:.3f} m, fallbacks {fb}")
    # estimator: one agent, CTRV, noisy positions of a turning vehicle
    rng = np.random.default_rng(0)
    est = UKFEstimator(meas_std=0.2)
    th = 0.3 * np.arange(steps + 11) * DT
    Z = np.stack([np.cumsum(8 * np.cos(th) * DT), np.cumsum(8 * np.sin(th) * DT)], 1)
    Z = Z + 0.2 * rng.standard_normal(Z.shape)
    est.reset(Observation(0.0, np.zeros(4), Z[:1]), DT)
    ms = []
    for k in range(1, len(Z)):
        t = time.perf_counter()
        est.update(Observation(k * DT, np.zeros(4), Z[k : k + 1]))
        ms.append((time.perf_counter() - t) * 1e3)
    _row("UKF update (1 agent)", np.array(ms[10:]))


if __name__ == "__main__":
    main()
