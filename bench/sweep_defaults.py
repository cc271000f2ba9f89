"""Every solver's default options on a wider seeded family than tests/test_defaults.py.

    .venv/bin/python bench/sweep_defaults.py                       # seeds 10-69, all solvers
    .venv/bin/python bench/sweep_defaults.py --seeds 33 34 --solvers ilq
    .venv/bin/python bench/sweep_defaults.py --seeds 10 70 --solvers ilq --jsonl out.jsonl

Each seed draws one game of the family of ``tests.helpers.family_spec``: the layout
(crossing, intersection, merge), N = 2..6, unicycles or bicycles, a collision weight of 1 to
100 and whether a jerk term couples consecutive stages; every game starts in collision.
Every solver solves it from zero controls with its default options. A row is ``ok`` when
the solver says ``converged`` *and* a test computed here agrees: for LM, IPOPT and SQP the
potential's gradient ``|dE/du|_inf <= 1e-4 (1 + |E|)`` (as in tests/test_defaults.py); for
iLQ the sampled feedback-Nash check of :mod:`solvers.feedback_nash` passes. For iLQ the
row also gives ``info["stop"]`` and, for a solve that stopped at a kink (``stop`` =
``"kink"``, or ``"kink_equilibrium"`` when an equilibrium on the kink was certified), the
width and kink arguments of the blended solution and what the search for an equilibrium
on the kink found (docs/ilq.md, "Equilibria on a kink"). Every row gives wall and CPU
seconds of the solve; the summary the CPU per solver and of the whole process. It is a
sweep, not a test: IPOPT builds an exact-Hessian NLP per game (seconds for N = 6) and iLQ
takes up to 40 s on the hardest games, so the whole run takes several minutes on 2 shared
cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from epo_casadi import PotentialGame  # noqa: E402
from solvers.feedback_nash import check_ilq_result  # noqa: E402
from solvers.ilq import solve_ilq  # noqa: E402
from solvers.ipopt import solve_ipopt  # noqa: E402
from solvers.lm import solve_lm  # noqa: E402
from solvers.result import Status  # noqa: E402
from solvers.sqp import solve_sqp  # noqa: E402
from tests.helpers import family_spec  # noqa: E402

SOLVE = {"lm": solve_lm, "ipopt": solve_ipopt, "sqp": solve_sqp, "ilq": solve_ilq}


def draw(seed: int) -> tuple[str, tuple]:
    """The family game of ``seed``: its name and the arguments of ``family_spec``."""
    rng = np.random.default_rng(1000 + seed)
    layout = ["crossing", "intersection", "merge"][rng.integers(3)]
    N = int(rng.integers(2, 7))
    dyn = ["unicycle", "bicycle"][rng.integers(2)]
    w = float([1, 3, 10, 30, 100][rng.integers(5)])
    jerk = bool(rng.integers(2))
    name = f"{layout}-{N}-{dyn}-w{w:g}-s{seed}" + ("-jerk" if jerk else "")
    return name, (layout, N, dyn, w, seed, jerk)


def run(name: str, args: tuple, solver: str) -> dict:
    """Solve one game with one solver's defaults; the row of the sweep."""
    layout, N, dyn, w, seed, jerk = args
    g = PotentialGame(family_spec(layout, N, dyn, w, seed, jerk=jerk))
    p = g.default_params()
    t, c0 = time.perf_counter(), time.process_time()
    r = SOLVE[solver](g, p)
    dt, cpu = time.perf_counter() - t, time.process_time() - c0
    grad = float(np.abs(np.asarray(g.function("gradient")(r.controls, p))).max())
    rec = {
        "name": name,
        "solver": solver,
        "status": r.status.value,
        "iterations": int(r.iterations),
        "energy": float(r.energy),
        "grad": grad,
        "time_s": round(dt, 3),
        "cpu_s": round(cpu, 3),
    }
    if solver == "ilq":
        c = check_ilq_result(g, p, r)
        rec.update(
            stop=r.info["stop"],
            stationarity=float(r.info["stationarity"]),
            continuation=r.info["kink_continuation"],
            restart=r.info.get("restart"),
            feedback_nash=bool(c.ok),
        )
        if r.info.get("kink_equilibrium"):
            k = r.info["kink_equilibrium"]
            rec["kink"] = {"width": k["width"], "kinks": k["kinks"]}
            if k.get("equilibrium"):  # the search for an equilibrium on the kinks
                rec["kink"]["equilibrium"] = k["equilibrium"]
        rec["ok"] = r.status is Status.CONVERGED and bool(c.ok)
    else:
        rec["stop"] = str(r.info.get("stop", r.info.get("return_status")))
        rec["ok"] = r.status is Status.CONVERGED and grad <= 1e-4 * (1 + abs(float(r.energy)))
    return rec


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs=2, default=(10, 70), metavar=("FIRST", "END"))
    ap.add_argument("--solvers", default="lm,ilq,sqp,ipopt", help="comma-separated")
    ap.add_argument("--jsonl", help="also write every row as one JSON line to this file")
    args = ap.parse_args(argv)
    solvers = [s.strip() for s in args.solvers.split(",") if s.strip()]
    bad = [s for s in solvers if s not in SOLVE]
    if bad:
        ap.error(f"--solvers: unknown {bad}, expected some of {sorted(SOLVE)}")
    out = open(args.jsonl, "w") if args.jsonl else None  # noqa: SIM115
    ok = {s: 0 for s in solvers}
    cpu = {s: 0.0 for s in solvers}  # CPU seconds of the solves (not the checks or builds)
    c_start = time.process_time()
    fails: dict = {s: [] for s in solvers}
    n = 0
    for seed in range(*args.seeds):
        name, spec = draw(seed)
        n += 1
        for s in solvers:
            rec = run(name, spec, s)
            ok[s] += rec["ok"]
            cpu[s] += rec["cpu_s"]
            if not rec["ok"]:
                fails[s].append(f"{name} ({rec['status']}/{rec['stop']})")
            extra = f" stop={rec['stop']}" if s == "ilq" else ""
            print(
                f"{name:42s} {s:6s} {rec['status']:10s} it={rec['iterations']:4d} "
                f"E={rec['energy']:.4f} ok={rec['ok']} {rec['time_s']:.1f}s cpu {rec['cpu_s']:.1f}s"
                f"{extra}",
                flush=True,
            )
            if out:
                out.write(json.dumps(rec) + "\n")
                out.flush()
    if out:
        out.close()
    print()
    for s in solvers:
        print(
            f"{s:6s} ok {ok[s]} / {n}, solve CPU {cpu[s]:.1f} s"
            + (f"; not ok: {', '.join(fails[s])}" if fails[s] else "")
        )
    print(f"total CPU of this process {time.process_time() - c_start:.1f} s")


if __name__ == "__main__":
    main()
