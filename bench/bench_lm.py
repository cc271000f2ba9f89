"""Time one Levenberg-Marquardt step per problem: dense, structured and fused GN backends.

Not a test. Run from the repository root::

    .venv/bin/python bench/bench_lm.py            # N in {2, 4, 8, 12}, K = 40, batches 1 and 64
    .venv/bin/python bench/bench_lm.py --quick    # smoke run: N = 2, batches 1 and 16
    .venv/bin/python bench/bench_lm.py --agents 2 4 --paths struct struct-C fused fused-C numpy
    .venv/bin/python bench/bench_lm.py --agents 2 4 8 12 --horizons 20 40 80 160 \\
        --paths fused-C --plot docs/figures/lm_step_scaling.png   # scaling in N and K
    .venv/bin/python bench/bench_lm.py --agents 12 8 4 2 --batches 64 1 \\
        --paths struct-C fused-C-sx fused-C --repeats 7           # Riccati kernel: before/after

Games: ``N`` unicycles on a circle crossing to the opposite side (the construction of
``tests/helpers.crossing_spec``: goal, velocity, acceleration, turn rate, three soft
bounds, pairwise collision), horizon ``K``. Controls are small random perturbations, so
collision terms are active.

One step, per backend ``be`` and batch ``(U, P)`` (what :func:`solvers.lm.solve_lm` does
per iteration with adaptive damping)::

    lin = be.linearize(U, P); du = be.solve(lin, lam, -lin.gradient); be.energy(U + 0.3 du, P)

Paths: ``dense`` (:class:`DenseGN`, interpreted CasADi, one thread), ``dense-thr`` (the same
with ``map`` threads), ``struct`` (:class:`StructuredGN`, interpreted, one thread),
``struct-C`` (:class:`StructuredGN` with generated C, one thread), ``fused`` and ``fused-C``
(:class:`solvers.fast_gn.FusedGN`: the whole step as CasADi functions, interpreted or as
generated C, one thread; ``fused x struct`` columns give their speed-up over the matching
structured path; ``fused-C-sx`` and ``fused-C-kern`` are ``fused-C`` with the Riccati
step's dense elimination forced to unrolled SX or to the C kernel, ``schur_kernel=False``
or ``True``, where ``fused-C`` chooses by stage size), and the reference
``numpy``: J from the game's CasADi ``jacobian`` function (interpreted), ``r`` from
``residual``, then numpy ``J'J``, ``J'r``, Cholesky solve and ``energy``, one thread.
Times are medians over repeats (the paths take turns within each repeat) of wall-clock
and of process CPU time, divided by the batch size; BLAS is
limited to ``--blas-threads`` (default 1) so every path but ``dense-thr`` uses one core.
Dense paths at large batches are timed on ``--dense-cap`` problems of the batch (marked
``*``): their cost per problem does not shrink with the batch.

A last table divides each path's CPU time by the estimate ``K d^3`` FLOP at ``--flops``
(default 1e9) FLOP/s, ``d = nz + m`` the Riccati stage size (the leading term of the
structured step, constant 1: the stage's Riccati update forms ``FG' P FG``, a Cholesky
factor and ``Y'Y`` with a few ``d^3`` operations). ``--plot`` draws the log-log scaling of
``--plot-path`` against ``K`` and ``d`` with fitted slopes and the estimate.
"""

from __future__ import annotations

import argparse
import os
import sys
import time


def _parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--agents", type=int, nargs="+", default=[2, 4, 8, 12], help="numbers of agents N"
    )
    ap.add_argument(
        "--horizon", "--horizons", type=int, nargs="+", default=[40], help="horizons K (steps)"
    )
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64], help="batch sizes B")
    ap.add_argument(
        "--repeats", type=int, default=15, help="timed repeats per cell (median reported)"
    )
    ap.add_argument(
        "--cell-seconds",
        type=float,
        default=10.0,
        help="a path stops repeating after this many seconds in a cell (at least 3 repeats)",
    )
    ap.add_argument(
        "--dense-cap",
        type=int,
        default=8,
        help="time dense paths on at most this many problems of a batch (N >= 8)",
    )
    ap.add_argument(
        "--threads", type=int, default=None, help="threads of dense-thr (default: all cores)"
    )
    ap.add_argument(
        "--blas-threads", type=int, default=1, help="BLAS threads (set before numpy loads)"
    )
    ap.add_argument(
        "--paths",
        nargs="+",
        default=["dense", "dense-thr", "struct", "struct-C", "fused", "fused-C", "numpy"],
        choices=[
            "dense",
            "dense-thr",
            "struct",
            "struct-C",
            "fused",
            "fused-C",
            "fused-C-sx",
            "fused-C-kern",
            "numpy",
        ],
    )
    ap.add_argument(
        "--cache-dir",
        default=None,
        help="cache of compiled C (default: EPO_CACHE_DIR or ~/.cache/epo)",
    )
    ap.add_argument(
        "--quick", action="store_true", help="smoke run: N = 2, batches 1 and 16, 3 repeats"
    )
    ap.add_argument(
        "--plot",
        default=None,
        help="write the scaling figure of --plot-path (log-log time per problem and step "
        "against K and against the stage size, fitted slopes, the K d^3 estimate) to this PNG",
    )
    ap.add_argument("--plot-path", default="fused-C", help="the path the figure shows")
    ap.add_argument("--flops", type=float, default=1e9, help="FLOP/s of the estimate")
    args = ap.parse_args(argv)
    if args.quick:
        args.agents, args.batches, args.repeats = [2], [1, 16], 3
    if args.plot and args.plot_path not in args.paths:
        ap.error(f"--plot-path {args.plot_path} is not among --paths")
    return args


ARGS = _parse() if __name__ == "__main__" else None
if ARGS is not None:
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(ARGS.blas_threads)
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import numpy as np  # noqa: E402

from solvers.batch import BatchFunction, default_threads  # noqa: E402
from solvers.fast_gn import FusedGN  # noqa: E402
from solvers.lm import DenseGN  # noqa: E402
from solvers.structured import StructuredGN  # noqa: E402
from tests.helpers import crossing_game  # noqa: E402

STEP = 0.3  # step size of the trial point whose energy is evaluated
LAM = 10.0  # damping (the paper's)


class NumpyDenseGN:
    """The reference: J from CasADi's ``jacobian``, everything else plain numpy."""

    def __init__(self, game):
        self.game = game
        self.res = BatchFunction(game.function("residual"), 1)
        self.jac = BatchFunction(game.function("jacobian"), 1)
        self.en = BatchFunction(game.function("energy"), 1)

    def linearize(self, U, P):
        r = self.res(U, P)[0]
        J = self.jac.dense(0, self.jac(U, P)[0])
        return r, J, J.transpose(0, 2, 1) @ r[:, :, None], J.transpose(0, 2, 1) @ J

    def step(self, U, P, lam):
        r, J, g, A = self.linearize(U, P)
        n = A.shape[-1]
        A[:, np.arange(n), np.arange(n)] += lam[:, None]
        Lc = np.linalg.cholesky(A)
        du = -np.linalg.solve(Lc.transpose(0, 2, 1), np.linalg.solve(Lc, g))[..., 0]
        self.en(U + STEP * du, P)
        return du


def backend_step(be, U, P, lam):
    lin = be.linearize(U, P)
    du = be.solve(lin, lam, -lin.gradient)
    be.energy(U + STEP * du, P)
    return du


def time_round_robin(fns: dict, repeats: int, budget: float) -> dict:
    """Median wall and process-CPU seconds of each ``fns[name]()``.

    The paths take turns within every repeat, so load from other processes on a shared
    machine affects all of them alike. A path stops repeating once it has used ``budget``
    seconds and has at least 3 timings.
    """
    for fn in fns.values():
        fn()  # warm-up: builds mapped functions, allocates
    wall = {k: [] for k in fns}
    cpu = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            if len(wall[k]) >= 3 and sum(wall[k]) > budget:
                continue
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    return {k: (float(np.median(wall[k])), float(np.median(cpu[k])), len(wall[k])) for k in fns}


def inputs(game, B, seed=0):
    rng = np.random.default_rng(seed)
    U = 0.1 * rng.normal(size=(B, game.n_u))
    P = np.tile(game.default_params(), (B, 1)) * (1 + 0.05 * rng.uniform(-1, 1, size=(B, game.n_p)))
    return U, P, np.full(B, LAM)


def main(args) -> int:
    threads = args.threads or default_threads()
    rows, notes = [], []
    for N, K in [(n, k) for n in args.agents for k in args.horizon]:
        t0 = time.perf_counter()
        game = crossing_game(N=N, K=K)
        backends = {}
        if "dense" in args.paths:
            backends["dense"] = DenseGN(game, threads=1)
        if "dense-thr" in args.paths:
            backends["dense-thr"] = DenseGN(game, threads=threads)
        if "struct" in args.paths:
            backends["struct"] = StructuredGN(game, threads=1)
        if "struct-C" in args.paths:
            tc = time.perf_counter()
            backends["struct-C"] = StructuredGN(
                game, threads=1, compiled=True, cache_dir=args.cache_dir
            )
            notes.append(
                f"N={N}, K={K}: struct-C library ready in {time.perf_counter() - tc:.1f} s "
                "(compile on first use, then loaded from the cache)"
            )
        if "fused" in args.paths:
            backends["fused"] = FusedGN(game, threads=1)
            if backends["fused"].fallback:
                notes.append(
                    f"N={N}, K={K}: fused delegates to StructuredGN: {backends['fused'].fallback}"
                )
        for path, kern in (("fused-C", None), ("fused-C-sx", False), ("fused-C-kern", True)):
            if path not in args.paths:
                continue
            tc, cc, pc = time.perf_counter(), _child_cpu(), time.process_time()
            fc = backends[path] = FusedGN(
                game, threads=1, compiled=True, cache_dir=args.cache_dir, schur_kernel=kern
            )
            notes.append(
                f"N={N}, K={K}: {path} libraries ready in {time.perf_counter() - tc:.1f} s wall, "
                f"{_child_cpu() - cc:.1f} s compiler CPU (0: loaded from the cache), "
                f"{time.process_time() - pc:.1f} s CPU in this process"
                + (f"; delegates: {fc.fallback}" if fc.fallback else "")
                + ("; Schur kernel in C" if getattr(fc, "schur_kernel", False) else "")
                + (
                    f"; staged linearization, {fc.stage_groups} stage groups"
                    if fc.stage_groups
                    else ""
                )
            )
        ref = NumpyDenseGN(game) if "numpy" in args.paths else None
        print(
            f"# N={N}: {game} built in {time.perf_counter() - t0:.1f} s",
            file=sys.stderr,
            flush=True,
        )
        for B in args.batches:
            U, P, lam = inputs(game, B)
            fns, sizes, check = {}, {}, {}
            for name in args.paths:
                dense_like = name in ("dense", "dense-thr", "numpy")
                Bt = min(B, args.dense_cap) if dense_like and N >= 8 else B
                Ub, Pb, lb = U[:Bt], P[:Bt], lam[:Bt]
                if name == "numpy":
                    fns[name] = lambda r=ref, Ub=Ub, Pb=Pb, lb=lb: r.step(Ub, Pb, lb)  # noqa: E731
                else:
                    fns[name] = lambda be=backends[name], Ub=Ub, Pb=Pb, lb=lb: backend_step(
                        be, Ub, Pb, lb
                    )  # noqa: E731
                sizes[name] = Bt
                check[name] = fns[name]()[: min(Bt, 4)]
            timed = time_round_robin(fns, args.repeats, args.cell_seconds)
            cells = {}
            for name, (wall, cpu, n) in timed.items():
                Bt = sizes[name]
                cells[name] = (1e3 * wall / Bt, 1e3 * cpu / Bt, Bt < B, n)
                print(
                    f"#   B={B:3d} {name:9s} {1e3 * wall / Bt:9.4f} ms/problem (cpu {1e3 * cpu / Bt:.4f}, "
                    f"{n} repeats{f', timed on {Bt} problems' if Bt < B else ''})",
                    file=sys.stderr,
                    flush=True,
                )
            base = next(iter(check.values()))
            err = max(
                float(np.max(np.abs(v - base)) / max(np.max(np.abs(base)), 1e-300))
                for v in check.values()
            )
            rows.append((N, game.n_u, B, cells, err, K, stage_size(game)))
    print(table(rows, args.paths, threads, wall=True))
    print()
    print(table(rows, args.paths, threads, wall=False))
    print()
    print(estimate_table(rows, args.paths, args.flops))
    print()
    for n in notes:
        print(f"- {n}")
    print(
        "- `*`: timed on a sub-batch (`--dense-cap`); per-problem cost of dense paths does not fall with B."
    )
    print(
        "- `x ref` = numpy-reference time / path time (above 1: faster than the numpy dense reference)."
    )
    print(
        "- `max rel diff`: largest difference between the steps of all paths, relative to the largest entry."
    )
    if args.plot:
        plot_scaling(rows, args.plot_path, args.flops, args.plot)
        print(f"- figure: {args.plot}")
    return 0


def _child_cpu() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def stage_size(game) -> int:
    """``d = nz + m``: the Riccati stage size (augmented state plus joint controls)."""
    from solvers.structured import stage_layout

    return stage_layout(game).d


def estimate_table(rows, paths, flops):
    """Measured CPU time per problem and step beside the ``K d^3`` FLOP estimate."""
    head = ["N", "K", "d", "B", f"K d^3 / {flops:.0e} FLOP/s ms"] + [
        f"{p} / estimate" for p in paths
    ]
    out = [
        "Measured CPU time per problem and step over the estimate `K d^3` FLOP at "
        f"{flops:.0e} FLOP/s (constant 1; d = stage size):",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join("---:" for _ in head) + "|",
    ]
    for N, _, B, cells, _, K, d in rows:
        est = 1e3 * K * d**3 / flops
        vals = [f"{cells[p][1] / est:.2f}" for p in paths]
        out.append("| " + " | ".join([str(N), str(K), str(d), str(B), f"{est:.4f}"] + vals) + " |")
    return "\n".join(out)


def fit_slope(x, y) -> float:
    """Least-squares slope of ``log y`` against ``log x``."""
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def plot_scaling(rows, path, flops, png):
    """Log-log CPU ms per problem and step of ``path``: against K (one line per N and B)
    and against the stage size d (one line per K and B), fitted slopes in the legend,
    with the ``K d^3`` estimate dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = {(N, K, B): (cells[path][1], d) for N, _, B, cells, _, K, d in rows}
    Ns = sorted({k[0] for k in data})
    Ks = sorted({k[1] for k in data})
    Bs = sorted({k[2] for k in data})
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    marks = {b: m for b, m in zip(Bs, ["o", "s", "^", "v"], strict=False)}
    for N in Ns:
        for B in Bs:
            pts = [(K, data[N, K, B][0]) for K in Ks if (N, K, B) in data]
            if len(pts) < 2:
                continue
            x, y = map(np.array, zip(*pts, strict=True))
            (ln,) = axes[0].loglog(
                x, y, marker=marks[B], label=f"N={N}, B={B}: slope {fit_slope(x, y):.2f}"
            )
            if B == Bs[-1]:
                d = next(data[N, K, B][1] for K in Ks if (N, K, B) in data)
                axes[0].loglog(x, 1e3 * x * d**3 / flops, "--", color=ln.get_color(), lw=0.8)
    for K in Ks:
        for B in Bs:
            pts = [(data[N, K, B][1], data[N, K, B][0]) for N in Ns if (N, K, B) in data]
            if len(pts) < 2:
                continue
            x, y = map(np.array, zip(*pts, strict=True))
            (ln,) = axes[1].loglog(
                x, y, marker=marks[B], label=f"K={K}, B={B}: slope {fit_slope(x, y):.2f}"
            )
            if B == Bs[-1]:
                axes[1].loglog(x, 1e3 * K * x**3 / flops, "--", color=ln.get_color(), lw=0.8)
    axes[0].set_xlabel("horizon K")
    axes[1].set_xlabel("stage size d = nz + m")
    ds = sorted({v[1] for v in data.values()})
    for ax, ticks in ((axes[0], Ks), (axes[1], ds)):
        ax.set_xticks(ticks)
        ax.set_xticks([], minor=True)
        ax.set_xticklabels([str(t) for t in ticks])
    for ax in axes:
        ax.set_ylabel(f"{path}: CPU ms per problem and LM step")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(
        f"One LM step ({path}), crossing game; dashed: K d^3 FLOP at {flops:.0e} FLOP/s "
        f"(batch {Bs[-1]})",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)


def table(rows, paths, threads, wall=True):
    label = "wall-clock" if wall else "process CPU time (all threads)"
    names = {"dense-thr": f"dense-thr ({threads})"}
    head = ["N", "K", "n_u", "B"] + [f"{names.get(p, p)} ms" for p in paths]
    if "numpy" in paths:
        head += [f"{p} x ref" for p in paths if p != "numpy"]
    pairs = [
        (f, s)
        for f, s in (
            ("fused", "struct"),
            ("fused-C", "struct-C"),
            ("fused-C-sx", "struct-C"),
            ("fused-C-kern", "struct-C"),
            ("fused-C", "fused-C-sx"),
        )
        if {f, s} <= set(paths)
    ]
    head += [f"{f} x {s}" for f, s in pairs]
    head.append("max rel diff")
    out = [
        f"Median {label} per LM step per problem:",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join("---:" for _ in head) + "|",
    ]
    for N, n_u, B, cells, err, K, _ in rows:
        i = 0 if wall else 1
        vals = [f"{cells[p][i]:.4f}{'*' if cells[p][2] else ''}" for p in paths]
        if "numpy" in paths:
            vals += [f"{cells['numpy'][i] / cells[p][i]:.2f}" for p in paths if p != "numpy"]
        vals += [f"{cells[s][i] / cells[f][i]:.2f}" for f, s in pairs]
        out.append(
            "| " + " | ".join([str(N), str(K), str(n_u), str(B)] + vals + [f"{err:.1e}"]) + " |"
        )
    return "\n".join(out)


if __name__ == "__main__":
    sys.exit(main(ARGS))
