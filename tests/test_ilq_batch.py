"""Many starts of one game at once (solvers.ilq.iteration.BatchSolve) against the per-start
solve (ILQSolver.solve), the reference.

Per start the batched iteration must give what solving that start alone gives: the same
status, stop, iteration count, accepted steps and histories, and the same trajectory,
gains and costs to 1e-10 (they are the same numbers: the same compiled functions on the
same inputs, the same exactly rounded merit, the same decisions). Games: the RPI model
game (App. F.3, two unicycles, K = 40) with the dataset recipe's options, and a crossing
of three unicycles with the solver's defaults (kink blending and the restart from the
open-loop equilibrium run per start) and without kink blending (every branch of the
batched iteration: line search, raised regularization, the judgement at the requested
regularization, the iteration cap). Starts: sinusoids of several amplitudes, which stop
at different iterations and for different reasons, and one far outside the game's range
that fails. The vector kernel (solvers.fast_ilq.CompiledWideTrial) and the mapped scalar
trial are both checked, and the kernel's arithmetic per SX operation on special values.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

from scenarios.rpi import RPIRecipe, RPIScenario
from solvers import fast_ilq
from solvers.codegen import BufferCall, compile_functions, compile_kernel
from solvers.ilq import ILQOptions, get_solver, solve_ilq
from solvers.ilq.iteration import BatchSolve, _exact_sums, _MappedTrial, batchable, solve_starts
from solvers.multimodal import sinusoid_sampler
from solvers.result import Status
from solvers.stages import to_stages

from .helpers import crossing_game

TOL = 1e-10


def _starts(g, p, n, seed, amplitudes):
    """``n`` sinusoid starts scaled by ``amplitudes`` (cycled), the last one far out."""
    rng = np.random.default_rng(seed)
    U = sinusoid_sampler(g, p, n, rng)
    U *= np.resize(np.asarray(amplitudes, float), n)[:, None]
    U[-1] = 1e150  # the rollout overflows: the start fails
    return U


def _reference(s, P, U, opts):
    return [s.solve(P[b], U[b], opts) for b in range(P.shape[0])]


def _assert_same(ref, got):
    assert len(ref) == len(got)
    for b, (a, c) in enumerate(zip(ref, got, strict=True)):
        where = f"start {b}"
        assert c.status is a.status, where
        assert c.info["stop"] == a.info["stop"], where
        assert int(c.iterations) == int(a.iterations), where
        assert c.equilibrium == a.equilibrium, where
        assert ("restart" in c.info) == ("restart" in a.info), where
        assert c.info["kink_continuation"] == a.info["kink_continuation"], where
        for key in ("step_sizes", "residual_history"):
            np.testing.assert_array_equal(c.info[key], a.info[key], err_msg=where)
        pairs = [
            (c.controls, a.controls),
            (c.states, a.states),
            (c.energy_history, a.energy_history),
            (c.agent_costs, a.agent_costs),
            (c.info["gains"], a.info["gains"]),
            (c.info["feedforward"], a.info["feedforward"]),
            (c.info["regularization"], a.info["regularization"]),
        ]
        for x, y in pairs:
            x, y = np.asarray(x, float), np.asarray(y, float)
            assert x.shape == y.shape, where
            fin = np.isfinite(y)
            assert np.array_equal(fin, np.isfinite(x)), where
            assert np.all(np.abs(x[fin] - y[fin]) <= TOL), where
        for x, y in ((c.info["stationarity"], a.info["stationarity"]), (c.grad_norm, a.grad_norm)):
            assert (math.isnan(x) and math.isnan(y)) or abs(x - y) <= TOL, where


@pytest.fixture(scope="module")
def rpi():
    """The RPI model game at a main game's parameters, the recipe's options, 9 starts."""
    sc = RPIScenario(RPIRecipe(ground_truth="potential"))
    g = sc.game
    p = sc.params(sc.sample_config(3, np.random.default_rng(3)))
    opts = sc.solver_options()
    s = get_solver(g, None, opts.hessian)
    s.compile()
    U = _starts(g, p, 9, 1, [1.0, 3.0, 10.0])
    P = np.ascontiguousarray(np.broadcast_to(p, (9, g.n_p)))
    return g, s, P, U, opts, _reference(s, P, U, opts)


def test_rpi_starts_stop_differently(rpi):
    """The set is a real test: starts converge at different iterations, others stop at the
    cap, the far one fails."""
    *_, ref = rpi
    conv = [int(r.iterations) for r in ref if r.status is Status.CONVERGED]
    assert len(set(conv)) >= 3
    assert any(r.status is Status.MAX_ITER for r in ref)
    assert ref[-1].status is not Status.CONVERGED


def test_rpi_batch_equals_per_start(rpi):
    g, s, P, U, opts, ref = rpi
    assert batchable(s, opts)
    _assert_same(ref, solve_starts(s, P, U, opts))
    batched = solve_ilq(g, P, U, opts)  # the batch entry point takes the same path
    np.testing.assert_array_equal(batched.iterations, [r.iterations for r in ref])
    assert list(batched.status) == [r.status for r in ref]


def test_rpi_mapped_scalar_trial_equals_per_start(rpi):
    """Without the vector kernel (the compiled trial mapped over the starts)."""
    _, s, P, U, opts, ref = rpi
    t0 = 0.0
    runs = BatchSolve(s, P, U, opts, s.backward, t0, trial=_MappedTrial(s)).run()
    got = [
        s._solve_once(P[b], U[b], opts, s.backward, opts.max_iter, t0, once=run)
        for b, run in enumerate(runs)
    ]
    _assert_same(ref, got)


def test_vector_kernel_outputs(rpi):
    """The kernel's outputs for 11 starts (two calls, the second padded) equal the compiled
    one-call trial's per start, and its per-start stats their definition."""
    g, s, P, U, opts, _ = rpi
    wide = fast_ilq.wide_trial(s)
    assert wide is not None
    ft = s._ftrial
    rng = np.random.default_rng(5)
    m = 11
    Ub = np.concatenate([U[:8], U[:3] * 2.0])
    _, Ustage = to_stages(g, None, Ub)
    X0 = np.zeros((m, (s.K + 1) * s.nx))
    PA = rng.normal(0.0, 0.1, (m, s.K * s.nu * (s.nxs + 1)))
    args = [
        np.tile(P[0][s._x0_idx], (m, 1)),
        X0,
        Ustage.reshape(m, -1),
        PA,
        rng.uniform(0.0, 1.0, (m, 1)),
        P[:1].repeat(m, axis=0),
        np.zeros((m, 1)),
        np.full((m, 1), 1e-8),
    ]
    args[1] = wide(*args)[0]  # start from rolled-out trajectories
    out = wide(*args)
    one = BufferCall(ft.call)
    for j in range(m):
        ref = [v.copy() for v in one(*[a[j] for a in args])]
        for k in range(5):
            np.testing.assert_array_equal(out[k][j], ref[k])
        a = ref[2].reshape(s.K, s.nu, s.nxs + 1)[:, :, -1]
        ok, good, res, asum, c_ok = out[5][j]
        assert ok == float(np.isfinite(ref[2]).all())
        assert good == float(np.isfinite(ref[0]).all() and np.isfinite(ref[1]).all())
        assert res == np.max(np.abs(a))
        assert math.isnan(asum) or asum == math.fsum((a * a).ravel().tolist())
        r2 = ref[4] ** 2
        assert c_ok == float(np.isfinite(r2).all() and r2.sum() < 1e300)


def test_exact_sums_are_fsum():
    rng = np.random.default_rng(0)
    rows = [rng.normal(size=400) ** 2, np.full(400, 0.1), np.zeros(5), np.array([1e300, 1e300])]
    # sums on a rounding boundary of float64 (1 + half an ulp, split over many terms)
    rows.append(np.concatenate([[1.0], np.full(64, 2.0**-59)]))
    rows.append(np.concatenate([[1.0], np.full(64, 2.0**-59), [2.0**-80]]))
    for x in rows:
        got = _exact_sums(x[None])[0]
        try:
            want = math.fsum(x.tolist())
        except OverflowError:
            want = math.inf
        assert got == want
    X = (rng.normal(size=(50, 37)) * 10.0 ** rng.uniform(-6, 6, (50, 37))) ** 2
    np.testing.assert_array_equal(_exact_sums(X), [math.fsum(r.tolist()) for r in X])


@pytest.fixture(scope="module")
def crossing():
    g = crossing_game(N=3, K=20, offset=0.5)
    p = g.default_params()
    U = _starts(g, p, 12, 0, [1.0, 5.0, 20.0, 40.0])
    P = np.ascontiguousarray(np.broadcast_to(p, (12, g.n_p)))
    return g, P, U


@pytest.mark.parametrize(
    "extra",
    [{}, {"kink_widths": (), "restart": False}, {"kink_widths": (), "adaptive_step": False}],
    ids=["defaults", "no-kinks", "no-secant"],
)
def test_crossing_batch_equals_per_start(crossing, extra):
    g, P, U = crossing
    opts = ILQOptions(compiled=True, max_iter=80, **extra)
    s = get_solver(g, None, opts.hessian)
    s.compile()
    assert batchable(s, opts)  # else solve_starts solves one start after the other
    ref = _reference(s, P, U, opts)
    stops = {str(r.info["stop"]) for r in ref}
    assert {"tol", "max_iter", "line_search", "regularized_only"} <= stops
    assert len({int(r.iterations) for r in ref if r.status is Status.CONVERGED}) >= 2
    if not extra:  # kink blending and restarts happened (per start, after the batch)
        assert any(r.info["kink_continuation"] for r in ref)
        assert any("restart" in r.info for r in ref)
    _assert_same(ref, solve_starts(s, P, U, opts))


def test_vector_arithmetic_per_operation():
    """Every SX operation the kernel writes, on 8 lanes, equals CasADi's compiled scalar
    code bit for bit on special values (signed zeros, infinities, NaN, subnormals)."""
    x, y = ca.SX.sym("x"), ca.SX.sym("y")
    exprs = [
        x + y, x - y, x * y, x / y, -x, x**2, 2 * x, 1 / x, ca.sqrt(x), ca.fabs(x),
        ca.fmax(x, y), ca.fmin(x, y), ca.sign(x), ca.sin(x), ca.cos(x), ca.tan(x),
        ca.atan2(x, y), ca.exp(x), ca.log(x), ca.tanh(x), x**y, x**3.5, x < y, x <= y,
        x == y, x != y, ca.logic_not(x), ca.logic_and(x, y), ca.logic_or(x, y),
        ca.if_else(x, y, 0), ca.floor(x), ca.ceil(x), ca.fmod(x, y), ca.copysign(x, y),
        ca.erf(x), ca.asin(x), ca.acos(x), ca.atan(x), ca.sinh(x), ca.cosh(x), ca.asinh(x),
        ca.acosh(x), ca.atanh(x), x * math.inf, y - math.inf, x + 0.1,
    ]  # fmt: skip
    f = ca.Function("epo_test_ops", [x, y], [ca.vertcat(*exprs)])
    so, _ = compile_kernel(fast_ilq.wide_function_external(f, "epo_test_wide"), "epo_test_wide")
    wide = ca.external("epo_test_wide", str(so))
    scalar = compile_functions([f], "epo_test_ops", optimize=fast_ilq.OPTIMIZE)["epo_test_ops"]
    vals = [0.0, -0.0, 1.0, -1.0, 0.5, -2.5, math.inf, -math.inf, math.nan, 1e-310, 1e308, 0.3]
    pairs = [(a, b) for a in vals for b in vals]
    W = fast_ilq.WIDE_LANES
    for c in range(0, len(pairs), W):
        chunk = (pairs[c : c + W] * W)[:W]
        X, Y = np.array([a for a, _ in chunk]), np.array([b for _, b in chunk])
        got = np.asarray(wide(X, Y)).reshape(W, -1)
        for lane in range(W):
            want = np.asarray(scalar(X[lane], Y[lane])).ravel()
            same = (want.view(np.int64) == got[lane].view(np.int64)) | (
                np.isnan(want) & np.isnan(got[lane])
            )
            assert same.all(), (chunk[lane], np.nonzero(~same)[0])


def test_unsupported_operation_is_refused():
    x = ca.SX.sym("x")
    f = ca.Function("f", [x], [ca.expm1(x)])
    with pytest.raises(fast_ilq.WideUnsupported, match="EXPM1"):
        fast_ilq.wide_function_source(f, "f")
