"""Every solver's defaults on seeded families of games, before and after the continuation.

    .venv/bin/python bench/sweep_defaults.py --hard                # the hard subset (below)
    .venv/bin/python bench/sweep_defaults.py --hard --full         # the whole hard grid
    .venv/bin/python bench/sweep_defaults.py                       # seeds 10-69, all solvers
    .venv/bin/python bench/sweep_defaults.py --seeds 33 34 --solvers ilq
    .venv/bin/python bench/sweep_defaults.py --seeds 10 70 --solvers ilq --jsonl out.jsonl

Two families, both of ``tests.helpers.family_spec``; every game starts in collision:

* ``--hard``: the bicycle intersection, ``family_spec("intersection", N, "bicycle", w,
  seed, K)``: N = 6 and 8 vehicles, collision weights ``w`` 1 to 300, horizons K = 20 to
  200. :data:`HARD_SUBSET` (N = 6 at K = 20 and 60 with w = 1, 10, 100, 300; N = 8 at
  K = 20 with w = 10 and 300; seed 0) fits a run of about half an hour on 2 shared cores;
  ``--full`` runs :data:`HARD_GRID` (N = 6, 8 x w = 1, 3, 10, 30, 100, 300 x K = 20, 60,
  100, 200), hours, and IPOPT's exact Hessian at N = 6, K = 200 alone takes minutes and
  gigabytes to build.
* ``--seeds FIRST END`` (default): one game per seed, drawing the layout (crossing,
  intersection, merge), N = 2..6, unicycles or bicycles, a collision weight of 1 to 100
  and whether a jerk term couples consecutive stages; K = 25.

Every solver solves each game from zero controls with its registered defaults
(:func:`solvers.registry.solve_game`); IPOPT's NLP is built before (the set-up, timed
apart). The default includes the continuation fallback
(:mod:`solvers.continuation`); one solve gives both columns: *before* is the first
attempt (``info["attempts"][0]``, or the result itself when it converged at once), *after*
the result. A row is ``ok`` when the status is ``converged`` *and* the checks computed
here agree: for LM, IPOPT, SQP and OLNE the potential's gradient ``|dE/du|_inf <= 1e-4 (1 +
|E|)`` (as in tests/test_defaults.py) and the Nash certificate's verdict ``passes`` (not
``unknown``); for iLQ the sampled feedback-Nash check of :mod:`solvers.feedback_nash`
passes; an iLQ row also gives ``info["stop"]``, the feedback residual, the restart and,
for a solve that stopped at a kink, the width and kink arguments of the blended solution
and what the search for an equilibrium on the kink found (docs/ilq.md, "Equilibria on a
kink"). A first attempt that did not converge is not ok before; one that converged is the
result, with the same verdict. Times are the CPU and wall seconds of the solve (the
set-up and the checks not included; before: the first attempt's); the summary gives each
solver's ok counts before and after, its times before and after and their ratios, and the share of games on which every solver is
ok, as a Markdown table.
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
from solvers.registry import SOLVERS, solve_game  # noqa: E402
from solvers.result import Status  # noqa: E402
from tests.helpers import family_spec  # noqa: E402

SOLVER_NAMES = ("lm", "ipopt", "ilq", "sqp", "olne")
DEFAULT_SOLVERS = "lm,ilq,sqp,ipopt"

#: the whole hard grid (``--hard --full``): (N, collision weight, K), seed 0
HARD_GRID = tuple(
    (N, w, K)
    for N in (6, 8)
    for K in (20, 60, 100, 200)
    for w in (1.0, 3.0, 10.0, 30.0, 100.0, 300.0)
)
#: the documented subset (``--hard``): about half an hour on 2 shared cores
HARD_SUBSET = tuple((6, w, K) for K in (20, 60) for w in (1.0, 10.0, 100.0, 300.0)) + tuple(
    (8, w, 20) for w in (10.0, 300.0)
)


def draw(seed: int) -> tuple[str, tuple]:
    """The family game of ``seed``: its name and the arguments of ``family_spec``."""
    rng = np.random.default_rng(1000 + seed)
    layout = ["crossing", "intersection", "merge"][rng.integers(3)]
    N = int(rng.integers(2, 7))
    dyn = ["unicycle", "bicycle"][rng.integers(2)]
    w = float([1, 3, 10, 30, 100][rng.integers(5)])
    jerk = bool(rng.integers(2))
    name = f"{layout}-{N}-{dyn}-w{w:g}-s{seed}" + ("-jerk" if jerk else "")
    return name, (layout, N, dyn, w, seed, 25, jerk)


def hard(N: int, w: float, K: int, seed: int = 0) -> tuple[str, tuple]:
    """The hard family's game: its name and the arguments of ``family_spec``."""
    return f"intersection-{N}-bicycle-w{w:g}-K{K}-s{seed}", (
        "intersection",
        N,
        "bicycle",
        w,
        seed,
        K,
        False,
    )


def _check(solver: str, g: PotentialGame, p: np.ndarray, r) -> dict:
    """The checks of the module docstring on result ``r`` (a usable, finite one)."""
    if SOLVERS[solver].equilibrium == "feedback":
        from solvers.feedback_nash import check_ilq_result

        c = check_ilq_result(g, p, r)
        return {
            "verdict": str(getattr(c, "verdict", "passes" if c.ok else "fails")),
            "first_order": True,
        }
    from solvers.nash import nash_certificate

    grad = float(np.abs(np.asarray(g.function("gradient")(r.controls, p))).max())
    c = nash_certificate(g, p=p, u=r.controls)
    return {
        "verdict": str(c.verdict),
        "first_order": grad <= 1e-4 * (1 + abs(float(r.energy))),
        "grad": grad,
    }


def run(name: str, args: tuple, solver: str, game_cache: dict) -> dict:
    """Solve one game with one solver's defaults; the row of the sweep."""
    layout, N, dyn, w, seed, K, jerk = args
    if name not in game_cache:
        game_cache.clear()  # one game at a time (the big ones hold their NLPs)
        g = PotentialGame(family_spec(layout, N, dyn, w, seed, K=K, jerk=jerk))
        game_cache[name] = (g, g.default_params())
    g, p = game_cache[name]
    entry = SOLVERS[solver]
    opts = entry.make_options(None)
    t = time.perf_counter()
    if solver == "ipopt":  # its NLP, built before the timed solve (SQP's prepare is not
        # used: a solve from zero controls after it took 15x the CPU of a fresh one here)
        entry.prepare(g, p, g.zero_controls(), opts)
    setup = time.perf_counter() - t
    t, c0 = time.perf_counter(), time.process_time()
    r = solve_game(g, p, solver=solver)
    dt, cpu = time.perf_counter() - t, time.process_time() - c0
    attempts = r.info.get("attempts") or []
    first = attempts[0] if attempts else None
    rec = {
        "name": name,
        "solver": solver,
        "N": N,
        "w": w,
        "K": K,
        "status": r.status.value,
        "stop": str(r.info.get("stop", r.info.get("return_status"))),
        "iterations": int(r.iterations),
        "energy": float(r.energy),
        "setup_s": round(setup, 3),
        "time_s": round(dt, 3),
        "cpu_s": round(cpu, 3),
        "first_status": first["status"] if first else r.status.value,
        "first_time_s": round(first["seconds"], 3) if first else round(dt, 3),
        "first_cpu_s": round(first["cpu_seconds"], 3) if first else round(cpu, 3),
        "attempts": attempts,
    }
    if solver == "ilq":  # how iLQ stopped (docs/ilq.md, "Equilibria on a kink")
        rec.update(stationarity=float(r.info["stationarity"]), restart=r.info.get("restart"))
        k = r.info.get("kink_equilibrium")
        if k:
            rec["kink"] = {"width": k["width"], "kinks": k["kinks"]}
            if k.get("equilibrium"):
                rec["kink"]["equilibrium"] = k["equilibrium"]
    usable = r.status is Status.CONVERGED and np.isfinite(float(r.energy))
    chk = _check(solver, g, p, r) if usable else {"verdict": None, "first_order": False}
    rec.update(verdict=chk["verdict"], first_order=chk["first_order"])
    rec["ok"] = bool(usable and chk["verdict"] == "passes" and chk["first_order"])
    rec["ok_before"] = rec["ok"] and not attempts
    return rec


def _table(solvers, rows, names) -> str:
    """The summary: per solver, ok and seconds before and after, as a Markdown table."""
    lines = [
        "| solver | ok before | ok after | CPU s before | CPU s after | after / before "
        "| wall s before | wall s after | after / before |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    n = len(names)

    def ratio(a, b):
        return f"{a / b:.2f}" if b > 0 else "n/a"

    for s in solvers:
        rs = [r for r in rows if r["solver"] == s]
        cb, ca = sum(r["first_cpu_s"] for r in rs), sum(r["cpu_s"] for r in rs)
        wb, wa = sum(r["first_time_s"] for r in rs), sum(r["time_s"] for r in rs)
        lines.append(
            f"| {s} | {sum(r['ok_before'] for r in rs)} / {n} | {sum(r['ok'] for r in rs)} / {n} "
            f"| {cb:.1f} | {ca:.1f} | {ratio(ca, cb)} | {wb:.1f} | {wa:.1f} | {ratio(wa, wb)} |"
        )
    every_b = sum(all(r["ok_before"] for r in rows if r["name"] == g) for g in names)
    every_a = sum(all(r["ok"] for r in rows if r["name"] == g) for g in names)
    lines.append(
        f"\nevery solver ok: before {every_b} / {n} ({100 * every_b / max(n, 1):.0f} %), "
        f"after {every_a} / {n} ({100 * every_a / max(n, 1):.0f} %)"
    )
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs=2, default=(10, 70), metavar=("FIRST", "END"))
    ap.add_argument("--hard", action="store_true", help="the bicycle intersection, N = 6 and 8")
    ap.add_argument("--full", action="store_true", help="with --hard: the whole grid (hours)")
    ap.add_argument("--solvers", default=DEFAULT_SOLVERS, help="comma-separated")
    ap.add_argument("--jsonl", help="also write every row as one JSON line to this file")
    args = ap.parse_args(argv)
    solvers = [s.strip() for s in args.solvers.split(",") if s.strip()]
    bad = [s for s in solvers if s not in SOLVER_NAMES]
    if bad:
        ap.error(f"--solvers: unknown {bad}, expected some of {list(SOLVER_NAMES)}")
    if args.full and not args.hard:
        ap.error("--full goes with --hard")
    if args.hard:
        games = [hard(*c) for c in (HARD_GRID if args.full else HARD_SUBSET)]
    else:
        games = [draw(seed) for seed in range(*args.seeds)]
    out = open(args.jsonl, "w") if args.jsonl else None  # noqa: SIM115
    c_start, t_start = time.process_time(), time.perf_counter()
    rows: list[dict] = []
    cache: dict = {}
    for name, spec in games:
        for s in solvers:
            rec = run(name, spec, s, cache)
            rows.append(rec)
            tries = len(rec["attempts"])
            print(
                f"{name:36s} {s:6s} {rec['first_status']:9s} -> {rec['status']:9s} "
                f"({tries} solves) it={rec['iterations']:5d} E={rec['energy']:.4g} "
                f"check={rec['verdict']} ok {rec['ok_before']}->{rec['ok']} "
                f"CPU {rec['first_cpu_s']:.1f}s -> {rec['cpu_s']:.1f}s (set-up {rec['setup_s']:.1f}s wall)",
                flush=True,
            )
            if out:
                out.write(json.dumps(rec) + "\n")
                out.flush()
    if out:
        out.close()
    print()
    print(_table(solvers, rows, [n for n, _ in games]))
    for s in solvers:
        bad = [
            f"{r['name']} ({r['status']}, {r['verdict']})"
            for r in rows
            if r["solver"] == s and not r["ok"]
        ]
        if bad:
            print(f"{s}: not ok after: {', '.join(bad)}")
    print(
        f"total: {time.perf_counter() - t_start:.0f} s wall, {time.process_time() - c_start:.0f} s "
        "CPU of this process"
    )


if __name__ == "__main__":
    main()
