"""Benchmark of the differentiable game layer (learning/layer.py); not part of the tests.

Three parts, each printed as a table (times are medians over ``--repeats`` runs after one
warm-up run; forward + backward of ``loss = mean(x^2) + mean(u^2)``):

1. RPI setting (paper App. F.3: N = 2, K = 40, dt = 0.1, M = 2 modes x batch 32 = 64
   problems, S = 2, alpha = 0.3, lambda = 10; features goal, velocity, acceleration,
   velocity/acceleration/turn-rate bounds, turn rate; collision every step) and the same
   game with N in {4, 8, 12}. The layer with each Gauss-Newton backend (dense;
   structured; structured + generated C for the backend and the layer's VJP functions;
   fused, :class:`solvers.fast_gn.FusedGN`, interpreted and + generated C, where it does
   not delegate to the structured backend)
   next to a plain-torch unrolled LM (the same energy re-implemented in torch, ``J`` by
   ``torch.func.vmap(jacrev)``, ``torch.linalg.solve``, autograd through everything) and,
   if it is installed, Theseus (``theseus-ai`` 0.2.3, ``AutoDiffCostFunction`` on the same
   torch residual, dense Cholesky, unrolled backward). Before timing, each torch variant
   is checked against the layer (outputs and gradients).
2. Paper runtime grid (App. G, Fig. "runtime"): exiD-like games (K = 20, dt = 0.2; goal,
   lane, reference velocity, velocity, acceleration, jerk, turn rate, turn acceleration;
   collision every 5th step) with M = 4 modes per sample, N in {2, 4, 8, 12} x S in
   {1, 2, 4, 8, 12}, and M in {1, 2, 4, 8, 12} at N = 4, S = 4: seconds per sample (one
   sample = M problems, batch of one sample, as the paper's per-sample figure) next to the
   paper's numbers (RTX 3090 GPU + Ryzen 9 5900X, whole model).

3. One LM step's VJP (``--part vjp``): CPU per problem and step of the monolithic
   ``lm_step_vjp`` (interpreted; generated C with ``--compile-monolithic`` where it is
   below ``MAX_COMPILED_INSTRUCTIONS``) and of the stage-wise one
   (:mod:`solvers.fast_vjp`, interpreted and generated C) for RPI (N = 2, 4, K = 40), the
   left-turn game (N = 2, K = 60) and the exiD game (N = 4, K = 20), with their largest
   relative difference; with ``--train-data DIR`` (a left-turn dataset) also a training
   step (batch 16, S = 20, fused + C backend) with either VJP.

Run ``python bench/bench_layer.py`` (all) or ``--quick`` (smaller grid, fewer repeats).
Threads: ``--threads`` (default: all usable cores) for CasADi and torch.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
# numpy's BLAS threads (dense backend only) must be fixed before numpy is imported. One by
# default: on a shared 2-core machine, 2 OpenBLAS threads that wait for each other while
# another process holds a core made the dense variant up to 10x slower and erratic.
if "--blas-threads" in sys.argv:
    _n = sys.argv[sys.argv.index("--blas-threads") + 1]
else:
    _n = "1"
os.environ.setdefault("OPENBLAS_NUM_THREADS", _n)  # numpy's BLAS; torch keeps its own threads

import numpy as np  # noqa: E402
import torch  # noqa: E402

from epo_casadi import (  # noqa: E402
    Acceleration,
    AccelerationBound,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    Jerk,
    PotentialGame,
    ReferenceVelocity,
    TurnAcceleration,
    TurnRate,
    TurnRateBound,
    Velocity,
    VelocityBound,
)
from epo_casadi import Path as PathFeature  # noqa: E402
from learning.layer import GameLayer  # noqa: E402
from solvers.lm import DenseGN, LMOptions  # noqa: E402

PAPER_GRID = {  # App. G, seconds per sample, rows S, columns N (M = 4)
    1: {2: 0.08, 4: 0.09, 8: 0.11, 12: 0.12},
    2: {2: 0.10, 4: 0.12, 8: 0.14, 12: 0.14},
    4: {2: 0.16, 4: 0.17, 8: 0.21, 12: 0.26},
    8: {2: 0.25, 4: 0.27, 8: 0.31, 12: 0.32},
    12: {2: 0.35, 4: 0.36, 8: 0.45, 12: 0.46},
}
PAPER_MODES = {1: 0.169, 2: 0.170, 4: 0.172, 8: 0.174, 12: 0.175}  # N = 4, S = 4


# --------------------------------------------------------------------------------------
# Games
# --------------------------------------------------------------------------------------
def rpi_spec(N: int, K: int = 40, dt: float = 0.1) -> GameSpec:
    """RPI-like game: N unicycles on a circle of radius 3 m, each heading across."""
    agents = []
    for i in range(N):
        ang = 2 * math.pi * i / N
        c, s = math.cos(ang), math.sin(ang)
        feats = [
            Goal(weight=3.0),
            Velocity(weight=0.5),
            Acceleration(weight=1.0),
            VelocityBound(lower=0.0, upper=2.0, weight=5.0),
            AccelerationBound(lower=-2.0, upper=2.0, weight=5.0),
            TurnRate(weight=1.0),
            TurnRateBound(lower=-1.5, upper=1.5, weight=5.0),
        ]
        agents.append(
            AgentSpec(
                f"a{i}",
                "unicycle",
                feats,
                radius=0.25,
                x0=[3 * c, 3 * s, 1.0, ang + math.pi],
                goal=[-3 * c, -3 * s],
            )
        )
    return GameSpec(agents, [Collision(weight=10.0)], horizon=K, dt=dt)


def exid_spec(N: int, K: int = 20, dt: float = 0.2) -> GameSpec:
    """exiD-like highway game: N vehicles on three lanes (r = L/2 = 2.25 m)."""
    agents = []
    for i in range(N):
        lane = i % 3
        y = 3.5 * lane
        x = 12.0 * (i // 3) + 4.0 * lane
        feats = [
            Goal(weight=1.0),
            PathFeature(weight=1.0),
            ReferenceVelocity(weight=1.0),
            Velocity(weight=0.1),
            Acceleration(weight=1.0),
            Jerk(weight=0.5),
            TurnRate(weight=1.0),
            TurnAcceleration(weight=0.5),
        ]
        agents.append(
            AgentSpec(
                f"v{i}",
                "unicycle",
                feats,
                radius=2.25,
                x0=[x, y, 20.0, 0.0],
                goal=[x + 80.0, y],
                vref=20.0,
                path=[[x - 10, y], [x + 200, y]],
            )
        )
    return GameSpec(agents, [Collision(weight=5.0, every=5)], horizon=K, dt=dt)


def problems(game: PotentialGame, shape: tuple[int, ...], seed: int = 0):
    """Random instances: perturbed start states and goals, small random initial strategies."""
    rng = np.random.default_rng(seed)
    P = np.broadcast_to(game.default_params(), (*shape, game.n_p)).copy()
    for a in game.agent_names:
        b = game.params[f"x0.{a}"]
        P[..., b.start : b.start + 2] += 0.3 * rng.normal(size=(*shape, 2))
        P[..., b.start + 3] += 0.1 * rng.normal(size=shape)
        g = game.params[f"goal.{a}"]
        P[..., g.start : g.start + 2] += 0.3 * rng.normal(size=(*shape, 2))
    U = 0.1 * rng.normal(size=(*shape, game.n_u))
    return P, U


# --------------------------------------------------------------------------------------
# The RPI energy in plain torch (same residuals as the CasADi game, other order)
# --------------------------------------------------------------------------------------
class TorchRPI:
    """``r(u, p)`` of :func:`rpi_spec` games for one problem, in torch (for vmap/jacrev)."""

    def __init__(self, game: PotentialGame):
        self.game = game
        self.N, self.K, self.dt = game.N, game.K, game.dt
        lay = game.params
        names = game.agent_names
        self.x0 = torch.tensor([lay[f"x0.{a}"].start for a in names])
        self.goal = torch.tensor([lay[f"goal.{a}"].start for a in names])
        kinds = [
            "goal",
            "velocity",
            "acceleration",
            "velocity_bound",
            "acceleration_bound",
            "turn_rate",
            "turn_rate_bound",
        ]
        self.w = {k: torch.tensor([lay[f"w.{a}.{k}"].start for a in names]) for k in kinds}
        self.pairs = [(i, j) for i in range(self.N) for j in range(i + 1, self.N)]
        self.pi = torch.tensor([i for i, _ in self.pairs])
        self.pj = torch.tensor([j for _, j in self.pairs])
        self.wc = torch.tensor(
            [lay[f"w.{names[i]}-{names[j]}.collision"].start for i, j in self.pairs]
        )
        self.rad = 2 * game.agents[0].radius

    def rollout(self, u, p):
        """States ``(N, K+1, 4)`` from ``u`` ``(n_u,)`` (components kept apart in the loop)."""
        U = u.reshape(self.N, self.K, 2)
        acc, om = U[:, :, 0].unbind(1), U[:, :, 1].unbind(1)
        x0 = p[self.x0[:, None] + torch.arange(4)]
        x, y, v, th = x0.unbind(1)
        xs, ys, vs, ths = [x], [y], [v], [th]
        dt = self.dt
        for k in range(self.K):
            x, y, v, th = (
                x + v * torch.cos(th) * dt,
                y + v * torch.sin(th) * dt,
                v + acc[k] * dt,
                th + om[k] * dt,
            )
            xs.append(x)
            ys.append(y)
            vs.append(v)
            ths.append(th)
        return torch.stack([torch.stack(c, dim=1) for c in (xs, ys, vs, ths)], dim=2)

    def residual(self, u, p):
        X = self.rollout(u, p)
        U = u.reshape(self.N, self.K, 2)
        w = {k: p[i][:, None] for k, i in self.w.items()}
        g = p[self.goal[:, None] + torch.arange(2)]
        v, a, om = X[:, 1:, 2], U[:, :, 0], U[:, :, 1]
        relu = torch.relu
        parts = [
            w["goal"] * (X[:, -1, :2] - g),
            w["velocity"] * v,
            w["acceleration"] * a,
            w["velocity_bound"] * (relu(v - 2.0) + relu(0.0 - v)),
            w["acceleration_bound"] * (relu(a - 2.0) + relu(-2.0 - a)),
            w["turn_rate"] * om,
            w["turn_rate_bound"] * (relu(om - 1.5) + relu(-1.5 - om)),
        ]
        d = X[self.pi, 1:, :2] - X[self.pj, 1:, :2]
        dist = torch.sqrt((d * d).sum(-1) + 1e-9)
        parts.append(p[self.wc][:, None] * relu(self.rad - dist))
        return torch.cat([q.reshape(-1) for q in parts])

    def positions_states(self, u, p):
        X = self.rollout(u, p)  # agent-major, as the game's x
        return X.reshape(-1)


def torch_unrolled_lm(model: TorchRPI, U0, P, steps, alpha, lam):
    """Plain-torch unrolled LM (fixed damping), autograd through every step."""
    res = model.residual
    # forward-mode columns: n_u < n_r, and faster here than vmap(jacrev) (Theseus' default)
    jac = torch.func.vmap(torch.func.jacfwd(res, argnums=0))
    vres = torch.func.vmap(res)
    U = U0
    n = U.shape[-1]
    eye = torch.eye(n, dtype=U.dtype)
    for _ in range(steps):
        J = jac(U, P)
        r = vres(U, P)
        A = J.transpose(1, 2) @ J + lam * eye
        g = (J.transpose(1, 2) @ r[..., None])[..., 0]
        du = torch.linalg.solve(A, -g)
        U = U + alpha * du
    X = torch.func.vmap(model.positions_states)(U, P)
    return U, X


def theseus_layer(model: TorchRPI, B: int, steps, alpha, lam):
    """A TheseusLayer on the same residual, or the reason it cannot be built."""
    try:
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import theseus as th
    except Exception as e:  # noqa: BLE001 - report any import failure
        return None, f"theseus not importable: {type(e).__name__}: {e}"
    g = model.game
    u = th.Vector(g.n_u, name="u", dtype=torch.float64)
    p = th.Variable(torch.zeros(B, g.n_p, dtype=torch.float64), name="p")
    vres = torch.func.vmap(model.residual)

    def err(optim_vars, aux_vars):
        return vres(optim_vars[0].tensor, aux_vars[0].tensor)

    w = th.ScaleCostWeight(torch.tensor(1.0, dtype=torch.float64))
    cost = th.AutoDiffCostFunction(
        [u], err, g.n_r, cost_weight=w, aux_vars=[p], autograd_mode="vmap", name="energy"
    )
    obj = th.Objective(dtype=torch.float64)
    obj.add(cost)
    opt = th.LevenbergMarquardt(
        obj,
        th.CholeskyDenseSolver,
        max_iterations=steps,
        step_size=alpha,
        abs_err_tolerance=0.0,
        rel_err_tolerance=0.0,
    )
    layer = th.TheseusLayer(opt)
    kw = {
        "damping": lam,
        "adaptive_damping": False,
        "backward_mode": "unroll",
        "track_best_solution": False,
        "verbose": False,
    }

    def run(U0, P):
        sol, _ = layer.forward({"u": U0, "p": P}, optimizer_kwargs=kw)
        U = sol["u"]
        return U, torch.func.vmap(model.positions_states)(U, P)

    return run, th.__version__


# --------------------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------------------
def timed(fn, U0, P, repeats, best=False):
    """Median (or, with ``best``, smallest) forward and backward seconds of ``fn(U0, P)``.

    ``best`` picks the run with the smallest forward + backward time.
    """
    fw, bw = [], []
    for i in range(repeats + 1):
        u = U0.detach().clone().requires_grad_()
        p = P.detach().clone().requires_grad_()
        t0 = time.perf_counter()
        U, X = fn(u, p)
        t1 = time.perf_counter()
        loss = X.square().mean() + U.square().mean()
        loss.backward()
        t2 = time.perf_counter()
        if i:  # first run is a warm-up
            fw.append(t1 - t0)
            bw.append(t2 - t1)
    if best:
        i = int(np.argmin(np.add(fw, bw)))
        return fw[i], bw[i]
    return statistics.median(fw), statistics.median(bw)


def cpu_time(fn, U0, P, repeats):
    """Median process CPU seconds (all threads) of one forward + backward of ``fn(U0, P)``.

    On a shared machine the wall time includes waiting for a core; the CPU time does not.
    """
    out = []
    for i in range(repeats + 1):
        u = U0.detach().clone().requires_grad_()
        p = P.detach().clone().requires_grad_()
        c0 = time.process_time()
        U, X = fn(u, p)
        (X.square().mean() + U.square().mean()).backward()
        if i:  # first run is a warm-up
            out.append(time.process_time() - c0)
    return statistics.median(out)


def grads(fn, U0, P):
    u = U0.detach().clone().requires_grad_()
    p = P.detach().clone().requires_grad_()
    U, X = fn(u, p)
    (X.square().mean() + U.square().mean()).backward()
    return U.detach(), X.detach(), u.grad, p.grad


def layer_fn(layer):
    def fn(u, p):
        out = layer(p, u)
        return out.controls, out.states

    return fn


def backends(game, threads, with_dense=True):
    from solvers.fast_gn import FusedGN
    from solvers.structured import StructuredGN

    out = {}
    if with_dense:
        out["dense"] = (DenseGN(game, threads=threads), False)
    out["structured"] = (StructuredGN(game, threads=threads), False)
    out["structured+C"] = (StructuredGN(game, threads=threads, compiled=True), True)
    fused = FusedGN(game, threads=threads)
    if fused.fallback is None:  # else it delegates to StructuredGN: nothing new to time
        out["fused"] = (fused, False)
        out["fused+C"] = (FusedGN(game, threads=threads, compiled=True), True)
    return out


def progress(msg):
    print(f"  ... {msg}", file=sys.stderr, flush=True)


def fmt(t):
    return f"{t * 1e3:9.1f}" if t is not None else "        -"


def dense_bytes(game, B):
    return B * game.n_r * game.n_u * 8 * 2  # J and its transpose copy in the dense paths


def bench_rpi(args):
    print("\n== 1. RPI setting: 64 problems (batch 32 x M 2), S = 2, alpha = 0.3, lambda = 10 ==")
    print(
        "times in ms per batch of 64 problems (median of --repeats, and the best run); ratio = plain torch / this (medians)"
    )
    opts = LMOptions.paper(threads=args.threads)
    Ns = args.rpi_n or ([2, 4] if args.quick else [2, 4, 8, 12])
    rows = []
    for N in Ns:
        game = PotentialGame(rpi_spec(N))
        P, U = problems(game, (32, 2), seed=N)
        Pt, Ut = torch.tensor(P.reshape(64, -1)), torch.tensor(U.reshape(64, -1))
        mem = dense_bytes(game, 64)
        dense_ok = mem < args.max_dense_gb * 2**30
        res: dict[str, tuple] = {}
        layer_err: dict[str, float] = {}
        layer_cpu: dict[str, float] = {}
        ref = None
        t_build = time.perf_counter()
        bes = backends(game, args.threads, with_dense=dense_ok)
        t_build = time.perf_counter() - t_build
        for name, (be, compiled) in bes.items():
            progress(f"N={N} layer [{name}]")
            layer = GameLayer(game, opts, backend=be, compiled=compiled)
            fn = layer_fn(layer)
            got = grads(fn, Ut, Pt)
            if ref is None:
                ref = got
            layer_err[name] = max(
                float((a - b).abs().max() / (b.abs().max() + 1e-30))
                for a, b in zip(got, ref, strict=True)
            )
            layer_cpu[name] = cpu_time(fn, Ut, Pt, args.repeats)
            res[name] = timed(fn, Ut, Pt, args.repeats), timed(fn, Ut, Pt, args.repeats, best=True)
        torch_rows = {}
        model = TorchRPI(game)
        e_t = 0.5 * torch.func.vmap(model.residual)(Ut[:2], Pt[:2]).square().sum(1)
        e_c = np.array(
            [
                float(game.function("energy")(U.reshape(64, -1)[b], P.reshape(64, -1)[b]))
                for b in range(2)
            ]
        )
        assert np.allclose(e_t.numpy(), e_c, rtol=1e-12), (e_t, e_c)
        candidates = {}
        if dense_ok and (N <= args.max_torch_n):
            candidates["plain torch"] = lambda u, p, m=model: torch_unrolled_lm(
                m, u, p, opts.steps, opts.step_size, opts.damping
            )
            if not args.no_theseus:
                try:
                    run, info = theseus_layer(model, 64, opts.steps, opts.step_size, opts.damping)
                except Exception as e:  # noqa: BLE001 - report and go on
                    run, info = None, f"building the TheseusLayer failed: {type(e).__name__}: {e}"
                if run is None:
                    print(f"  Theseus skipped: {info}")
                else:
                    candidates[f"theseus {info}"] = run
        for name, fn in candidates.items():
            progress(f"N={N} {name}")
            try:
                got = grads(fn, Ut, Pt)
                err = [
                    float((a - b).abs().max() / (b.abs().max() + 1e-30))
                    for a, b in zip(got, ref, strict=True)
                ]
                torch_rows[name] = (timed(fn, Ut, Pt, max(1, args.repeats // 2)), max(err))
            except Exception as e:  # noqa: BLE001 - report and go on
                print(f"  {name} failed for N={N}: {type(e).__name__}: {str(e)[:200]}")
        rows.append((N, game, res, torch_rows, dense_ok, mem, t_build))
        fastest = "fused+C" if "fused+C" in bes else "structured+C"
        be, compiled = bes[fastest]
        split = breakdown(game, be, compiled, args, Pt, Ut)
        print(
            f"\nN = {N}: n_u = {game.n_u}, n_r = {game.n_r}, backend build {t_build:.1f} s, "
            f"load average {os.getloadavg()[0]:.1f}"
            + (
                ""
                if dense_ok
                else f"; dense J would need {mem / 2**30:.1f} GB: dense/plain torch skipped"
            )
        )
        if not candidates:
            print(f"  (torch baselines skipped for N = {N}: --max-torch-n {args.max_torch_n})")
        print(
            f"  {'variant':28s} {'fwd ms':>9s} {'bwd ms':>9s} {'total ms':>9s}   vs plain torch   "
            "max rel. diff to layer (u, x, du_init, dp)   [layer: CPU ms, median]"
        )
        print(f"  {'':28s} {'median':>9s} {'median':>9s} {'med/best':>9s}")
        base = next((t for n, (t, _) in torch_rows.items() if n == "plain torch"), None)
        for name, ((f, b), (fb, bb)) in res.items():
            ratio = f"{(base[0] + base[1]) / (f + b):8.1f}x" if base else "        -"
            print(
                f"  layer [{name:19s}] {fmt(f)} {fmt(b)} {fmt(f + b)}   {ratio}        "
                f"{layer_err[name]:.1e}   cpu {layer_cpu[name] * 1e3:.1f}"
            )
            print(f"  {'':28s} {'':9s} {'':9s} {fmt(fb + bb)}   (best of {args.repeats})")
        for name, ((f, b), err) in torch_rows.items():
            ratio = f"{(base[0] + base[1]) / (f + b):8.1f}x" if base else "        -"
            print(f"  {name:28s} {fmt(f)} {fmt(b)} {fmt(f + b)}   {ratio}        {err:.1e}")
        print(f"  where the time goes, layer [{fastest}], ms per call of the layer:")
        print("\n".join(split))
    return rows


class _Clock:
    """Accumulates seconds per (phase, name) for :func:`breakdown`."""

    def __init__(self):
        self.phase = "fwd"
        self.t: dict[tuple[str, str], float] = {}

    def wrap(self, name, fn):
        def timed_call(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                key = (self.phase, name)
                self.t[key] = self.t.get(key, 0.0) + time.perf_counter() - t

        return timed_call


def breakdown(game, be, compiled, args, P, U):
    """Where the time of one forward + backward goes: per part, the median over repeats (ms)."""
    clock = _Clock()
    layer = GameLayer(game, LMOptions.paper(threads=args.threads), backend=be, compiled=compiled)
    for m in ("linearize", "solve", "energy"):
        setattr(be, m, clock.wrap(f"backend.{m}", getattr(be, m)))
    core = layer.core
    for m in ("rollout", "rollout_vjp", "step_vjp"):
        f = getattr(core, m)
        wrapped = clock.wrap(f"casadi.{m}", f)
        setattr(core, m, type("W", (), {"__call__": staticmethod(wrapped), "dense": f.dense})())
    runs = []
    for i in range(args.repeats + 1):
        clock.t.clear()
        u = U.detach().clone().requires_grad_()
        p = P.detach().clone().requires_grad_()
        clock.phase = "fwd"
        t0 = time.perf_counter()
        out = layer(p, u)
        t1 = time.perf_counter()
        clock.phase = "bwd"
        (out.states.square().mean() + out.controls.square().mean()).backward()
        t2 = time.perf_counter()
        if i:
            runs.append(({"fwd": t1 - t0, "bwd": t2 - t1}, dict(clock.t)))
    for m in ("linearize", "solve", "energy"):  # undo the instance patches
        delattr(be, m)
    lines = []
    for ph in ("fwd", "bwd"):
        names = sorted({k[1] for _, t in runs for k in t if k[0] == ph})
        parts = {n: statistics.median(t.get((ph, n), 0.0) for _, t in runs) for n in names}
        rest = statistics.median(
            tot[ph] - sum(v for k, v in t.items() if k[0] == ph) for tot, t in runs
        )
        total = statistics.median(tot[ph] for tot, _ in runs)
        cells = ", ".join(
            f"{k} {v * 1e3:.1f}" for k, v in sorted(parts.items(), key=lambda kv: -kv[1])
        )
        lines.append(f"  {ph}: {total * 1e3:.1f} ms = {cells}, torch/numpy glue {rest * 1e3:.1f}")
    return lines


def bench_grid(args):
    print(
        "\n== 2. Paper runtime grid (App. G): exiD-like, K = 20, dt = 0.2, per sample (M problems) =="
    )
    print(
        "seconds per sample, best of --repeats: this layer forward (inference) / forward + backward, "
        "[paper: RTX 3090, whole model, inference]"
    )
    from solvers.structured import StructuredGN

    Ns = [2, 4] if args.quick else [2, 4, 8, 12]
    Ss = [1, 2] if args.quick else [1, 2, 4, 8, 12]
    Ms = [1, 4] if args.quick else [1, 2, 4, 8, 12]
    reps = args.repeats
    games, layers = {}, {}

    def layer_for(N, S):
        if N not in games:
            t = time.perf_counter()
            games[N] = (PotentialGame(exid_spec(N)), None)
            be = StructuredGN(games[N][0], threads=args.threads, compiled=args.compiled)
            games[N] = (games[N][0], be)
            print(
                f"  (N = {N}: n_u = {games[N][0].n_u}, n_r = {games[N][0].n_r}, "
                f"backend {'dense fallback' if be.fallback else 'structured'}"
                f"{' + C' if args.compiled else ''}, built in {time.perf_counter() - t:.1f} s)"
            )
        game, be = games[N]
        key = (N, S)
        if key not in layers:
            layers[key] = GameLayer(
                game,
                LMOptions.paper(steps=S, threads=args.threads),
                backend=be,
                compiled=args.compiled,
            )
        return game, layers[key]

    def one(N, S, M):
        game, layer = layer_for(N, S)
        P, U = problems(game, (M,), seed=100 + N)
        Pt, Ut = torch.tensor(P), torch.tensor(U)
        fw = []
        with torch.no_grad():
            for i in range(reps + 1):
                t = time.perf_counter()
                layer(Pt, Ut)
                if i:
                    fw.append(time.perf_counter() - t)
        f, b = timed(layer_fn(layer), Ut, Pt, reps, best=True)
        return min(fw), f + b

    table = {}
    for S in Ss:
        for N in Ns:
            table[S, N] = one(N, S, 4)
    print(
        f"\n  M = 4; rows S, columns N; cell: fwd / fwd+bwd [paper]; load {os.getloadavg()[0]:.1f}"
    )
    print("  S \\ N " + "".join(f"{N:>26d}" for N in Ns))
    for S in Ss:
        cells = "".join(
            f"   {table[S, N][0]:6.3f} / {table[S, N][1]:6.3f} [{PAPER_GRID[S][N]:.2f}]" for N in Ns
        )
        print(f"  {S:5d} {cells}")
    print("\n  N = 4, S = 4; columns M; cell: fwd / fwd+bwd [paper]")
    mt = {M: one(4, 4, M) for M in Ms}
    print("  " + "".join(f"{M:>27d}" for M in Ms))
    print(
        "  " + "".join(f"   {mt[M][0]:6.3f} / {mt[M][1]:6.3f} [{PAPER_MODES[M]:.3f}]" for M in Ms)
    )
    return table, mt


# --------------------------------------------------------------------------------------
# 3. One step's VJP: monolithic vs stage-wise (solvers/fast_vjp.py)
# --------------------------------------------------------------------------------------
def vjp_games():
    """(label, game) of part 3: RPI (N = 2 and 4, K = 40), the left-turn dataset game
    (N = 2, K = 60, path terms), the exiD dataset game (N = 4, K = 20, collision every 5th
    step)."""
    from scenarios.exid import ExidRecipe, ExidScenario
    from scenarios.left_turn import LeftTurnRecipe, LeftTurnScenario

    return [
        ("RPI N=2 K=40", PotentialGame(rpi_spec(2))),
        ("RPI N=4 K=40", PotentialGame(rpi_spec(4))),
        ("left-turn N=2 K=60", LeftTurnScenario(LeftTurnRecipe()).game),
        ("exiD N=4 K=20", ExidScenario(ExidRecipe()).game),
    ]


def _per_problem(f, args_in, reps):
    """Median CPU seconds per problem of one batched call of ``f``, and its outputs."""
    from solvers.batch import BatchFunction

    bf = BatchFunction(f, 1)
    out = bf(*args_in)
    ts = []
    for _ in range(reps):
        c0 = time.process_time()
        bf(*args_in)
        ts.append(time.process_time() - c0)
    return statistics.median(ts) / args_in[0].shape[0], out


def bench_vjp(args):
    from learning.layer_core import MAX_COMPILED_INSTRUCTIONS, layer_functions
    from solvers.codegen import compile_functions
    from solvers.fast_vjp import staged_step_vjp, staged_vjp_info

    print("\n== 3. One LM step's VJP (learning/layer.py unrolled backward), batch of 16 ==")
    print(
        "CPU ms per problem and step (median of --repeats, one thread); cc: seconds of "
        "compiler wall time (first build; a cached library loads in ms); monolithic C only up "
        f"to {MAX_COMPILED_INSTRUCTIONS:,} instructions (with --compile-monolithic); "
        "mono/staged C: the faster monolithic (C, else interpreted) over staged C"
    )
    print(
        f"{'game':22s} {'instr mono':>10s} {'groups':>6s} {'mono interp':>11s} "
        f"{'mono C':>8s} {'staged interp':>13s} {'staged C':>9s} {'cc mono':>8s} "
        f"{'cc staged':>9s} {'mono/staged C':>13s} {'max rel err':>11s}"
    )
    B = 16
    for label, game in vjp_games():
        progress(f"vjp {label}")
        rng = np.random.default_rng(0)
        P, _ = problems(game, (B,), seed=1)
        U, DU, Z = (0.3 * rng.normal(size=(B, game.n_u)) for _ in range(3))
        xs = (U, P, DU, Z)
        mono = layer_functions(game, "lm_step_vjp")
        staged = staged_step_vjp(game)

        t_mi, ref = _per_problem(mono, xs, args.repeats)
        t_si, _ = _per_problem(staged, xs, args.repeats)
        w0 = time.perf_counter()
        sc = compile_functions([staged], f"epo_bench_vjp_staged_n{game.N}_k{game.K}")
        t_comp = time.perf_counter() - w0
        t_sc, got = _per_problem(sc[staged.name()], xs, 5 * args.repeats)
        err = max(
            float(np.max(np.abs(a - b)) / np.max(np.abs(b))) for a, b in zip(got, ref, strict=True)
        )
        t_mc = t_mcomp = None
        if mono.n_instructions() <= MAX_COMPILED_INSTRUCTIONS and args.compile_monolithic:
            progress(f"vjp {label}: compiling the monolithic VJP")
            w0 = time.perf_counter()
            mc = compile_functions([mono], f"epo_bench_vjp_mono_n{game.N}_k{game.K}")
            t_mcomp = time.perf_counter() - w0
            t_mc, _ = _per_problem(mc[mono.name()], xs, 5 * args.repeats)
        ratio = (t_mc if t_mc is not None else t_mi) / t_sc
        print(
            f"{label:22s} {mono.n_instructions():10,d} {staged_vjp_info(game)['groups']:6d} "
            f"{t_mi * 1e3:11.3f} {'-' if t_mc is None else f'{t_mc * 1e3:.3f}':>8s} "
            f"{t_si * 1e3:13.3f} {t_sc * 1e3:9.3f} "
            f"{'-' if t_mcomp is None else f'{t_mcomp:.1f}':>8s} {t_comp:9.1f} "
            f"{ratio:13.1f} {err:11.1e}",
            flush=True,
        )
    if args.train_data:
        bench_vjp_train(args)


def bench_vjp_train(args):
    """A left-turn training step (batch 16, S = 20, alpha = 1) with the fused + C backend:
    the layer's VJP monolithic (interpreted: too large to compile) vs staged in C."""
    from learning.data import SceneDataset
    from learning.models import ModelConfig, build_model
    from learning.train import PAPER_LOSS_WEIGHTS, compute_loss, torch_threads

    ds = SceneDataset(args.train_data, "train")
    b = ds.batch(np.arange(16))
    cfg = ModelConfig(
        kind="epo",
        lm_steps=20,
        step_size=1.0,
        goal_decoder="candidates",
        hist_width=32,
        lane_width=32,
        global_width=64,
        dec_width=32,
        layer_backend="fused",
        layer_compiled="yes",
    )
    torch.manual_seed(0)
    m = build_model(cfg, ds.game)
    layers = {"staged": m.layer}
    layers["monolithic"] = GameLayer(
        ds.game, m.layer.options, backward="unrolled", compiled=True, vjp="monolithic"
    )
    print(
        f"\n   left-turn training step ({args.train_data}, batch 16, M = {cfg.modes}, S = 20): "
        "CPU s (median of --repeats after a warm-up), one thread"
    )
    res = {}
    for name in ("monolithic", "staged"):
        m.layer = layers[name]
        fw, tot = [], []
        with torch_threads(1):
            for i in range(args.repeats + 1):
                m.zero_grad()
                c0 = time.process_time()
                out = m(b)
                c1 = time.process_time()
                parts = compute_loss("epo", out, b["gt"], PAPER_LOSS_WEIGHTS["epo"])
                parts["loss"].backward()
                if i:
                    fw.append(c1 - c0)
                    tot.append(time.process_time() - c0)
        res[name] = (statistics.median(fw), statistics.median(tot))
        print(
            f"   VJP {name:10s} (layer.vjp={m.layer.vjp}, interpreted={m.layer.interpreted}): "
            f"forward {res[name][0]:.3f} s, forward + backward {res[name][1]:.3f} s",
            flush=True,
        )
    print(f"   step CPU monolithic / staged: {res['monolithic'][1] / res['staged'][1]:.2f}x")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller grid and fewer repeats")
    ap.add_argument(
        "--repeats", type=int, default=None, help="timed runs per cell (default 5, quick 3)"
    )
    ap.add_argument(
        "--threads", type=int, default=None, help="CasADi/torch threads (default: all cores)"
    )
    ap.add_argument(
        "--torch-threads",
        type=int,
        default=None,
        help="torch intra-op threads (default: --threads)",
    )
    ap.add_argument(
        "--blas-threads", type=int, default=1, help="numpy BLAS threads (dense backend; default 1)"
    )
    ap.add_argument("--part", choices=["all", "rpi", "grid", "vjp"], default="all")
    ap.add_argument(
        "--train-data",
        default=None,
        help="vjp part: a left-turn dataset folder; adds a training step (batch 16, S = 20)",
    )
    ap.add_argument(
        "--compile-monolithic",
        action="store_true",
        help="vjp part: also compile the monolithic VJPs (exiD: about a minute at -O0)",
    )
    ap.add_argument("--no-theseus", action="store_true", help="skip the Theseus comparison")
    ap.add_argument(
        "--rpi-n", type=int, nargs="+", default=None, help="numbers of agents of part 1"
    )
    ap.add_argument(
        "--max-torch-n",
        type=int,
        default=4,
        help="largest N for the torch baselines (N = 4 already takes ~1 min per run)",
    )
    ap.add_argument(
        "--max-dense-gb", type=float, default=3.0, help="skip dense paths needing more memory"
    )
    ap.add_argument(
        "--no-compile",
        dest="compiled",
        action="store_false",
        help="grid: interpreted CasADi instead of generated C",
    )
    args = ap.parse_args(argv)
    if args.repeats is None:
        args.repeats = 3 if args.quick else 5
    if args.threads is None:
        args.threads = (
            len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        )
    tt = args.threads if args.torch_threads is None else args.torch_threads
    if torch.get_num_threads() != tt:
        # (only when it changes: with torch 2.13 CPU here, set_num_threads(2) on a process
        # already at 2 threads made batched torch.linalg.solve fail inside MKL and hang)
        torch.set_num_threads(tt)
    print(
        f"bench_layer: torch {torch.__version__}, {args.threads} CasADi threads, "
        f"{torch.get_num_threads()} torch threads, {os.environ['OPENBLAS_NUM_THREADS']} numpy BLAS "
        f"threads, repeats {args.repeats}{', quick' if args.quick else ''}; load average "
        f"{os.getloadavg()[0]:.1f} on {len(os.sched_getaffinity(0))} cores"
    )
    if args.part in ("all", "rpi"):
        bench_rpi(args)
    if args.part in ("all", "grid"):
        bench_grid(args)
    if args.part in ("all", "vjp"):
        bench_vjp(args)


if __name__ == "__main__":
    main()
