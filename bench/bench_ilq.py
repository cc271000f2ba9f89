"""Time the iLQ feedback Nash solver (solvers.ilq) on RPI-like and N-player crossing games.

Not a test. Run from the repository root::

    .venv/bin/python bench/bench_ilq.py            # RPI-like N=2 K=40; N=3, 4 (K=40); N=3 K=100
    .venv/bin/python bench/bench_ilq.py --quick    # smoke run: fewer repeats, no K=100 row
    .venv/bin/python bench/bench_ilq.py --quick --k100   # the same with the K=100 row

Games (App. F.3 features: goal, velocity, acceleration, turn rate, soft bounds on speed,
acceleration and turn rate, pairwise collision at every step; unicycles, dt = 0.1 s):

* ``rpi``: robot from (-3, 0) to (3, 0), pedestrian from the circle of radius 3 at 100 deg
  to the opposite side (+10 deg jitter), speeds 1 m/s, bounds and weights of the RPI recipe
  (``scenarios/rpi/recipe.py`` defaults), collision weight 17.5 (middle of U(5, 30));
* ``circle-N``: ``N`` agents on a circle of radius 3 crossing to the opposite side, goals
  shifted 0.3 m sideways (``tests/helpers.crossing_spec``), collision weight 10.

Every solve starts from zero controls (collision terms active on the way) and runs to the
default tolerance ``max |a| <= 1e-5`` (``--tol`` changes it; ``--only-k100`` times only the
3-player, 100-step game). Paths:

* ``numpy``: the interpreted reference (Riccati recursion in numpy);
* ``C``: ``compiled=True``, one generated-C call per line-search trial (rollout,
  quadratization, Riccati recursion: :class:`solvers.fast_ilq.CompiledTrial`), built with
  :data:`solvers.fast_ilq.OPTIMIZE`;
* ``sep``: the compiled path as it was before the one-call trial, measured in the same
  run: the same generated functions called one by one from Python (rollout, three
  quadratization groups, Riccati), ``-O1`` (:func:`solvers.fast_ilq.compile_solver` with
  ``trial=False``);
* ``LM``: the potential minimizer by :func:`solvers.lm.solve_lm` with the structured
  backend (interpreted), same start.

Every path is compiled, or loaded from the disk cache, once before timing (``compile cpu
s``: CPU of this process and of the C compiler, ``C`` only; ``--fresh-cache`` compiles into
an empty cache folder, so it is the first-call figure). Times are medians over repeats
(paths take turns within each repeat) of the CPU time of the process (``time.process_time``:
less sensitive to other jobs on a shared machine than wall time, printed as ``wall``),
BLAS limited to one thread. The ratios are ``sep / C`` and ``LM / C`` (CPU). The compiled
paths must give the same controls as ``numpy`` (to 1e-8, checked). Building the CasADi
functions (once per game) is excluded and reported as ``build s``.
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

from epo_casadi import (  # noqa: E402
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
from solvers import fast_ilq  # noqa: E402
from solvers.ilq import ILQSolver, get_solver, solve_ilq  # noqa: E402
from solvers.lm import LMOptions, solve_lm  # noqa: E402


def _features(vmax: float, w_goal=3.0, w_vel=0.5, w_bound=5.0):
    return [
        Goal(weight=w_goal),
        Velocity(weight=w_vel),
        Acceleration(weight=1.0),
        VelocityBound(lower=0.0, upper=vmax, weight=w_bound),
        AccelerationBound(lower=-2.0, upper=2.0, weight=w_bound),
        TurnRate(weight=1.0),
        TurnRateBound(lower=-1.5, upper=1.5, weight=w_bound),
    ]


def rpi_game(K: int = 40) -> PotentialGame:
    phi, goal = np.deg2rad(100.0), np.deg2rad(290.0)
    ps, pg = 3 * np.array([np.cos(phi), np.sin(phi)]), 3 * np.array([np.cos(goal), np.sin(goal)])
    d = pg - ps
    agents = [
        AgentSpec("robot", "unicycle", _features(2.0), radius=0.25, x0=[-3, 0, 1, 0], goal=[3, 0]),
        AgentSpec("pedestrian", "unicycle", _features(1.6), radius=0.25,
                  x0=[ps[0], ps[1], 1.0, np.arctan2(d[1], d[0])], goal=pg.tolist()),
    ]  # fmt: skip
    return PotentialGame(GameSpec(agents, [Collision(weight=17.5)], horizon=K, dt=0.1))


def circle_game(N: int, K: int, offset: float = 0.3) -> PotentialGame:
    agents = []
    for i in range(N):
        ang = 2 * np.pi * i / N
        c, s = np.cos(ang), np.sin(ang)
        agents.append(
            AgentSpec(f"a{i}", "unicycle", _features(2.0, w_vel=0.5), radius=0.25,
                      x0=[3 * c, 3 * s, 1.0, ang + np.pi], goal=[-3 * c - offset * s, -3 * s + offset * c])
        )  # fmt: skip
    return PotentialGame(GameSpec(agents, [Collision(weight=10.0)], horizon=K, dt=0.1))


def _median_ms(ts):
    return 1e3 * float(np.median(ts))


def run(cases, repeats: int, with_lm: bool = True, tol: float = 1e-5):
    rows = []
    for name, game in cases:
        p = game.default_params()
        t = time.perf_counter()
        solver = get_solver(game)
        build = time.perf_counter() - t
        c0 = os.times()
        solver.compile()
        c1 = os.times()  # the C compiler runs in a child process
        compile_cpu = sum(c1[:4]) - sum(c0[:4])  # user, system, children user and system
        sep = ILQSolver(game)  # the separate calls, -O1 (before the one-call trial)
        fast_ilq.compile_solver(sep, optimize="-O1", trial=False)
        paths = {
            "numpy": lambda g=game, p=p: solve_ilq(g, p, options={"tol": tol}),
            "sep": lambda s=sep, p=p: s.solve(p, options={"tol": tol, "compiled": True}),
            "C": lambda g=game, p=p: solve_ilq(g, p, options={"tol": tol, "compiled": True}),
        }
        if with_lm:
            lm_opts = LMOptions(backend="structured", threads=1)
            paths["LM"] = lambda g=game, p=p, o=lm_opts: solve_lm(g, p, options=o)
        last = {k: f() for k, f in paths.items()}  # warm-up (and the results)
        times = {k: [] for k in paths}
        cpu = {k: [] for k in paths}
        for _ in range(repeats):
            for k, f in paths.items():
                t, c = time.perf_counter(), time.process_time()
                last[k] = f()
                cpu[k].append(time.process_time() - c)
                times[k].append(time.perf_counter() - t)
        r_np, r_c = last["numpy"], last["C"]
        assert np.allclose(r_np.controls, r_c.controls, atol=1e-8), name
        assert np.allclose(last["sep"].controls, r_c.controls, rtol=0, atol=1e-10), name
        row = {
            "game": name,
            "N": game.N,
            "K": game.K,
            "iters": int(r_c.iterations),
            "status": r_c.status.value,
            "build s": build,
            "compile cpu s": compile_cpu,
            "numpy ms": _median_ms(cpu["numpy"]),
            "sep ms": _median_ms(cpu["sep"]),
            "C ms": _median_ms(cpu["C"]),
            "C wall ms": _median_ms(times["C"]),
            "C ms/iter": _median_ms(cpu["C"]) / max(int(r_c.iterations), 1),
            "sep / C": _median_ms(cpu["sep"]) / _median_ms(cpu["C"]),
        }
        if with_lm:
            row["LM ms"] = _median_ms(cpu["LM"])
            row["LM iters"] = int(last["LM"].iterations)
            row["LM / C"] = row["LM ms"] / row["C ms"]
        rows.append(row)
        _print([row], header=len(rows) == 1)
    return rows


def _print(rows, header=True):
    cols = list(rows[0])
    fmt = {k: ("{:.2f}" if isinstance(rows[0][k], float) else "{}") for k in cols}
    if header:
        print(" | ".join(f"{c:>12s}" for c in cols))
        print("-|-".join("-" * 12 for _ in cols))
    for r in rows:
        print(" | ".join(f"{fmt[c].format(r[c]):>12s}" for c in cols), flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=15, help="timed repeats per game (median)")
    ap.add_argument("--quick", action="store_true", help="3 repeats, no K=100 row")
    ap.add_argument("--no-lm", action="store_true", help="skip the LM reference")
    ap.add_argument("--tol", type=float, default=1e-5, help="iLQ tolerance on max |a|")
    ap.add_argument("--only-k100", action="store_true", help="only the N=3, K=100 game")
    ap.add_argument("--k100", action="store_true", help="add the N=3, K=100 game to --quick")
    ap.add_argument(
        "--fresh-cache", action="store_true", help="compile into an empty cache (first call)"
    )
    a = ap.parse_args(argv)
    if a.fresh_cache:
        import tempfile

        os.environ["EPO_CACHE_DIR"] = tempfile.mkdtemp(prefix="epo_bench_ilq_")
    repeats = 3 if a.quick else a.repeats
    cases = [
        ("rpi", rpi_game(40)),
        ("circle-3", circle_game(3, 40)),
        ("circle-4", circle_game(4, 40)),
    ]
    if not a.quick or a.k100:
        cases.append(("circle-3", circle_game(3, 100)))
    if a.only_k100:
        cases = [("circle-3", circle_game(3, 100))]
    print(
        f"iLQ game solver, median CPU time of {repeats} repeats, start: zero controls, "
        f"tol {a.tol:g}, compiled with {fast_ilq.OPTIMIZE!r}"
    )
    run(cases, repeats, with_lm=not a.no_lm, tol=a.tol)


if __name__ == "__main__":
    main()
