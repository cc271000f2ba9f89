"""Planning latency on one core, as ratios to the 100 ms planning period; not part of the tests.

What one closed-loop period costs (``torch.set_num_threads(1)``, ``OPENBLAS_NUM_THREADS=1``,
``EPO_THREADS=1``), p50 / p99 over ``--calls`` calls after ``--warmup`` warm-up calls:

(a) the network as a planner (:class:`learning.planner.NetworkPlanner.plan`: scene building,
    encoder, decoders, the game layer, the most likely mode, the plan in the world frame) at
    the paper's CARLA layer setting (App. F.3/F.4: ``S = 20`` LM steps, ``alpha = 1``,
    ``lambda = 10``; networks at half width: ``hist_width = lane_width = 32``,
    ``global_width = 64``, ``dec_width = 32``), untrained weights (the cost does not depend
    on their values), on
      - an RPI-sized problem: the RPI game (N = 2, K = 40 at 0.1 s, M = 2, H = 18, given goals);
      - a left-turn-sized problem: N = 2, K = 60 at 0.1 s (6 s), M = 2, H = 18, the paper's
        CARLA features (goal, path, reference velocity, velocity, acceleration, jerk, turn
        rate, turn acceleration; collision every step), goals from the candidate decoder
        (60 generated candidates);
    and V-LSTM + SC (no game) on the same two problems for reference;
(b) the game oracle (:class:`solvers.control.plan.GameOracle`, LM warm-started, at most
    ``PlannerOptions.steps`` = 20 steps) on the same two sizes, with hand-made tasks (a
    crossing and an unprotected left turn against an oncoming vehicle);
(c) the UKF update (:class:`solvers.control.estimate.UKFEstimator`, one observed pedestrian)
    and the MPC step (:class:`solvers.control.MPCTracker`, horizon 20, timed by the loop of
    ``bench/bench_mpc.py``, which has the details and the PID tracker; wall time only);
(d) the safety filter (:class:`solvers.control.safety.SafetyFilter`, defaults: horizon 20,
    boxes): every step of closed-loop left turns (the oracle and the MPC, an aggressive
    oncoming driver that starts slowly and accelerates, 0.3 m noise; seeds 0-2: most steps
    pass the nominal command after one check, some solve the QP or fall back), and one
    step that must solve the QP every call (accelerating towards a car standing 20 m ahead).

Run ``python bench/bench_planning.py`` (200 calls each) or ``--quick`` (30 calls).
A ratio below 1 keeps up with 10 Hz on one core.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
for _k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "EPO_THREADS"):
    os.environ.setdefault(_k, "1")  # before numpy / torch are imported

import numpy as np  # noqa: E402
import torch  # noqa: E402

from epo_casadi import (  # noqa: E402
    Acceleration,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    Jerk,
    PotentialGame,
    ReferenceVelocity,
    TurnAcceleration,
    TurnRate,
    Velocity,
)
from epo_casadi import Path as PathFeature  # noqa: E402
from learning.models import ModelConfig, build_model  # noqa: E402
from learning.observation import SceneSpec  # noqa: E402
from learning.planner import NetworkPlanner  # noqa: E402
from solvers.control.types import AgentTask, Estimate, Observation  # noqa: E402

PERIOD = 0.1  # s, the planning period
HALF = dict(hist_width=32, lane_width=32, global_width=64, dec_width=32)  # half width
CARLA_LAYER = dict(lm_steps=20, step_size=1.0, damping=10.0)  # S = 20, alpha = 1


def timed(fn, calls: int, warmup: int) -> tuple[float, float, float]:
    """p50 and p99 of the wall time and p50 of the process CPU time of ``fn()`` (s).

    On a machine shared with other processes the wall time includes waiting for a core;
    the CPU time of this single-threaded process is what one dedicated core would take.
    """
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(calls):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return (
        float(np.percentile(wall, 50)),
        float(np.percentile(wall, 99)),
        float(np.percentile(cpu, 50)),
    )


def row(name: str, p50: float, p99: float, cpu50: float) -> str:
    r = PERIOD
    cpu = "n/a" if math.isnan(cpu50) else f"{cpu50 / r:.3f}"
    return f"| {name} | {1e3 * p50:.2f} | {1e3 * p99:.2f} | {p50 / r:.3f} | {p99 / r:.3f} | {cpu} |"


def missing(name: str, why: str) -> str:
    return f"| {name} | {why} | | | | |"


# ------------------------------------------------------------------------------ scenes
class _World:
    """The attributes a planner reads from a world (no simulation here)."""

    def __init__(self, scenario: str, tasks: list[AgentTask], dt: float = PERIOD):
        self.dataset_scenario, self.dt, self._tasks = scenario, dt, tasks
        self.n_agents = len(tasks)
        self.radii = np.array([t.radius for t in tasks])
        self.ego_task = tasks[0]

    def tasks(self) -> list[AgentTask]:
        return self._tasks


def crossing_tasks() -> tuple[list[AgentTask], np.ndarray]:
    """RPI geometry: robot (-3, 0) -> (3, 0), pedestrian from the circle across it."""
    a = math.radians(100.0)
    ps, pg = 3 * np.array([math.cos(a), math.sin(a)]), -3 * np.array([math.cos(a), math.sin(a)])
    tasks = [
        AgentTask(np.array([[-3.0, 0.0], [3.0, 0.0]]), 1.0, np.array([3.0, 0.0]), 0.25),
        AgentTask(np.stack([ps, pg]), 1.0, pg, 0.25),
    ]
    head = math.atan2(*(pg - ps)[::-1])
    x0 = np.array([[-3.0, 0.0, 1.0, 0.0], [ps[0], ps[1], 1.0, head]])
    return tasks, x0


def left_turn_tasks() -> tuple[list[AgentTask], np.ndarray]:
    """An unprotected left turn: the ego from the south turns west; a vehicle comes from the north."""
    arc = np.linspace(0.0, math.pi / 2, 12)  # radius 8 m, from (0, -8) heading north to (-8, 0)
    turn = np.stack([-8.0 + 8.0 * np.cos(arc), -8.0 + 8.0 * np.sin(arc)], 1)
    ego_path = np.concatenate([[[0.0, -30.0]], turn, [[-30.0, 0.0]]])
    other_path = np.array([[-3.5, 40.0], [-3.5, -40.0]])
    tasks = [
        AgentTask(ego_path, 8.0, ego_path[-1], 1.5),
        AgentTask(other_path, 10.0, other_path[-1], 1.5),
    ]
    x0 = np.array([[0.0, -20.0, 7.0, math.pi / 2], [-3.5, 30.0, 10.0, -math.pi / 2]])
    return tasks, x0


def cv_history(x0: np.ndarray, steps: int) -> np.ndarray:
    """``(N, steps, 4)``: constant-velocity past of the states ``x0`` (last = now)."""
    j = np.arange(-steps + 1, 1) * PERIOD
    h = np.repeat(x0[:, None], steps, 1).astype(float)
    h[..., 0] += j * x0[:, None, 2] * np.cos(x0[:, None, 3])
    h[..., 1] += j * x0[:, None, 2] * np.sin(x0[:, None, 3])
    return h


def observation(x0: np.ndarray, steps: int) -> tuple[Observation, Estimate]:
    h = cv_history(x0, steps)
    n = len(x0) - 1
    est = Estimate(x0[1:], np.repeat(np.eye(4)[None], n, 0), h[1:], np.ones((n, steps), bool))
    return Observation(0.0, x0[0], x0[1:, :2]), est


def left_turn_game(K: int = 60) -> PotentialGame:
    feats = [
        Goal(weight=1.0),
        PathFeature(points=12, weight=1.0),
        ReferenceVelocity(weight=0.6),
        Velocity(weight=0.05),
        Acceleration(weight=0.5),
        Jerk(weight=0.05),
        TurnRate(weight=1.0),
        TurnAcceleration(weight=0.1),
    ]
    agents = [AgentSpec(n, "unicycle", feats, radius=1.5) for n in ("sdv", "other")]
    return PotentialGame(GameSpec(agents, [Collision(weight=5.0)], horizon=K, dt=PERIOD))


def problems():
    """(name, scenario, game, goal decoder, tasks, x0) of the two sizes."""
    from scenarios.rpi import RPIScenario

    ct, cx = crossing_tasks()
    lt, lx = left_turn_tasks()
    return [
        ("RPI-sized (N=2, K=40, M=2)", "rpi", RPIScenario().game, "given", ct, cx),
        ("left-turn-sized (N=2, K=60, M=2)", "left_turn", left_turn_game(), "candidates", lt, lx),
    ]


# ------------------------------------------------------------------------------ parts
def bench_network(calls: int, warmup: int, history: int = 18) -> list[str]:
    out = []
    for name, scenario, game, decoder, tasks, x0 in problems():
        for kind in ("epo", "sc"):
            torch.manual_seed(0)
            extra = dict(CARLA_LAYER, goal_decoder=decoder) if kind == "epo" else {}
            cfg = ModelConfig(kind=kind, modes=2, **HALF, **extra)
            model = build_model(cfg, game)
            spec = SceneSpec(
                scenario=scenario,
                kind=kind,
                n_agents=game.N,
                history_steps=history + 1,
                horizon=game.K,
                dt=game.dt,
                reads_goals=kind == "epo" and decoder == "given",
            )
            planner = NetworkPlanner(model, spec)
            planner.reset(_World(scenario, tasks))
            obs, est = observation(x0, history + 1)
            p = planner.plan(obs, est)
            if not p.ok:
                raise RuntimeError(f"{name} {kind}: {p.message}")
            label = "network + game layer (S=20, alpha=1)" if kind == "epo" else "V-LSTM + SC"
            call = lambda pl=planner, o=obs, e=est: pl.plan(o, e)  # noqa: E731
            out.append(row(f"{label}, {name}", *timed(call, calls, warmup)))
    return out


def bench_oracle(calls: int, warmup: int) -> list[str]:
    try:
        from solvers.control.plan import GameOracle, PlannerOptions
    except ImportError as e:  # pragma: no cover - the oracle is another module's
        return [missing("game oracle", f"not available ({e})")]
    out = []
    for (name, _, _, _, tasks, x0), K in zip(problems(), (40, 60), strict=True):
        oracle = GameOracle(PlannerOptions(horizon=K))
        oracle.reset(_World("", tasks))
        obs, est = observation(x0, 19)
        p = oracle.plan(obs, est)  # the cold start (first_steps)
        if not p.ok:
            raise RuntimeError(f"oracle {name}: {p.message}")
        call = lambda pl=oracle, o=obs, e=est: pl.plan(o, e)  # noqa: E731
        out.append(row(f"game oracle (LM <= 20 steps, warm), {name}", *timed(call, calls, warmup)))
    return out


def bench_ukf(calls: int, warmup: int) -> list[str]:
    try:
        from solvers.control.estimate import UKFEstimator
    except ImportError as e:  # pragma: no cover
        return [missing("UKF update", f"not available ({e})")]
    ukf = UKFEstimator()
    rng = np.random.default_rng(0)
    _, x0 = crossing_tasks()
    t = [0.0]

    def measure() -> Observation:
        t[0] += PERIOD
        p = x0[1, :2] + t[0] * x0[1, 2] * np.array([math.cos(x0[1, 3]), math.sin(x0[1, 3])])
        return Observation(t[0], x0[0], (p + rng.normal(0, 0.2, 2))[None])

    name = "UKF update (1 observed agent, CTRV)"
    try:
        ukf.reset(measure(), PERIOD)
        return [row(name, *timed(lambda: ukf.update(measure()), calls, warmup))]
    except Exception as e:  # another module's, maybe in progress: report, do not stop
        return [missing(name, f"failed: {type(e).__name__}: {str(e)[:80]}")]


def bench_mpc(calls: int, warmup: int) -> list[str]:
    """The MPC step, timed by the tracking benchmark's own loop (``bench/bench_mpc.py``)."""
    path = ROOT / "bench" / "bench_mpc.py"
    if not path.exists():
        return [missing("MPC step", "not available (bench/bench_mpc.py missing)")]
    spec = importlib.util.spec_from_file_location("bench_mpc", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    from solvers.control import MPCTracker, VehicleModel

    out = []
    for vname, veh in (("bicycle", VehicleModel.highway()), ("unicycle", VehicleModel())):
        ms = mod._loop(MPCTracker(horizon=20), veh, calls, warm=warmup)[0] / 1e3
        p50, p99 = float(np.percentile(ms, 50)), float(np.percentile(ms, 99))
        out.append(row(f"MPC step ({vname}, N = 20; bench_mpc's loop)", p50, p99, math.nan))
    return out


def bench_filter(calls: int, warmup: int) -> list[str]:
    """The safety filter: its time per step in closed-loop left turns, and a QP step."""
    try:
        from scenarios.closed_loop import SimConfig, run_episode
        from solvers.control.safety import SafetyFilter
        from solvers.control.types import Command, Plan
        from solvers.control.vehicle import VehicleModel
    except ImportError as e:  # pragma: no cover
        return [missing("safety filter", f"not available ({e})")]
    late = dict(
        aggressiveness=(0.8, 1.0),
        margin=(2.0, -2.0),
        ego_distance=(7.0, 9.0),
        ego_speed=(4.5, 5.5),
        other_distance=(8.0, 12.0),
        other_speed=(0.5, 1.5),
    )
    cfg = SimConfig("left-turn", planner="oracle", tracker="mpc", world_options=late)
    wall, cpu = [], []
    for seed in range(3):
        world, est, planner, tracker = cfg.build()
        sf = cfg.build_filter()
        inner = sf.filter

        def timed_filter(*args, _inner=inner):
            t0, c0 = time.perf_counter(), time.process_time()
            out = _inner(*args)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            return out

        sf.filter = timed_filter
        run_episode(world, est, planner, tracker, seed, safety=sf, keep_log=False)
    out = [
        row(
            f"safety filter, every step of 3 closed-loop left turns ({len(wall)} steps)",
            float(np.percentile(wall, 50)),
            float(np.percentile(wall, 99)),
            float(np.percentile(cpu, 50)),
        )
    ]
    world = _World("", left_turn_tasks()[0])
    world.vehicle = VehicleModel.highway()
    world.footprint = (5.0, 2.0)
    ego = np.array([0.0, 0.0, 10.0, 0.0])
    other = np.array([20.0, 0.0, 0.0, math.pi])
    K = 30
    pred = np.zeros((1, 2, K, 4))
    pred[0, 0] = ego
    pred[0, 1] = other
    plan = Plan(0.0, PERIOD, np.tile(ego, (K, 1)), np.zeros((K, 2)), pred, np.ones(1))
    est = Estimate(other[None], np.zeros((1, 4, 4)), other[None, None], np.ones((1, 1), bool))
    obs = Observation(0.0, ego, other[None, :2])
    sf = SafetyFilter()
    sf.reset(world)

    def qp_step():
        sf.applied(np.array([1.0, 0.0]))
        c = sf.filter(obs, est, plan, Command(np.array([1.0, 0.0])))
        if c.info["safety"]["qp"] < 1:
            raise RuntimeError("the QP was not solved")

    out.append(row("safety filter, a step that solves its QP", *timed(qp_step, calls, warmup)))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="30 calls per row instead of 200")
    ap.add_argument("--calls", type=int, default=None)
    ap.add_argument("--warmup", type=int, default=5)
    args = ap.parse_args(argv)
    calls = args.calls or (30 if args.quick else 200)
    torch.set_num_threads(1)
    print(f"# planning latency on one core ({calls} calls per row after {args.warmup} warm-up)")
    print(f"torch {torch.__version__}, numpy {np.__version__}, period {1e3 * PERIOD:.0f} ms\n")
    print("| what | p50 ms | p99 ms | p50 / period | p99 / period | CPU p50 / period |")
    print("|---|---|---|---|---|---|")
    for part in (bench_network, bench_oracle, bench_ukf, bench_mpc, bench_filter):
        for line in part(calls, args.warmup):
            print(line, flush=True)


if __name__ == "__main__":
    main()
