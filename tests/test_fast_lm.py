"""FusedGN (the structured LM step as generated CasADi code) against the interpreted paths.

References: the interpreted :class:`solvers.structured.StructuredGN` (numpy Riccati loop
over stages) and :class:`solvers.lm.DenseGN` (dense ``J`` from CasADi's Jacobian, Cholesky
of ``J'J + lambda D``). The fused backend forms neither the dense ``J`` nor a Python loop
over stages; equal linearizations, steps, energies and statuses (to 1e-12 relative to the
largest entry of the reference) on games with lagged stage coupling (jerk, turn
acceleration, second differences), bicycles, double integrators and 2 to 4 agents with
active collisions show that its generated recursion is the same linear algebra.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from epo_casadi import PotentialGame
from epo_casadi.errors import SpecError
from learning.layer import GameLayer
from solvers.fast_gn import MAX_STAGE_SIZE, FusedGN, FusedLinearization
from solvers.lm import DenseGN, LMOptions, _merge, make_backend, solve_lm
from solvers.result import Status
from solvers.structured import StructuredGN
from tests.helpers import crossing_game
from tests.test_layer import collision_energy, head_on_spec
from tests.test_layer import inputs as layer_inputs
from tests.test_structured import (
    COUPLED,
    GAMES,
    TotalAcceleration,
    _batch,
    _two_agent_game,
)

TOL = 1e-12

FAST_GAMES = {**GAMES, "crossing_n4": lambda: crossing_game(N=4, K=30, offset=0.1)}


def _close(a, b, rtol=TOL):
    """Equal up to ``rtol`` relative to the largest entry of the reference."""
    scale = max(float(np.max(np.abs(b))), 1e-300)
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)


def _collision_rows(game) -> np.ndarray:
    return np.concatenate(
        [np.arange(t.rows.start, t.rows.stop) for t in game.terms if t.feature == "collision"]
        or [np.zeros(0, dtype=int)]
    )


def _inputs(name, game, B, seed):
    """``_batch`` of test_structured; crossing games get small controls and parameter
    changes, so that the agents meet near the centre and the collision terms are active."""
    U, P, lam = _batch(game, B=B, seed=seed)
    if name.startswith("crossing"):
        P0 = game.default_params()
        U, P = 0.05 * U, P0 + 0.1 * (P - P0)
    return U, P, lam


@pytest.fixture(scope="module", params=sorted(FAST_GAMES))
def case(request):
    game = FAST_GAMES[request.param]()
    fb = FusedGN(game, threads=1)
    assert fb.fallback is None and fb.delegate is None  # the generated path really runs
    return request.param, game, fb, StructuredGN(game, threads=1), DenseGN(game, threads=1)


@pytest.mark.parametrize("B", [1, 5])
def test_linearization_matches_structured_and_dense(case, B):
    name, game, fb, sb, db = case
    U, P, _ = _inputs(name, game, B, seed=1)
    lf, ls, ld = fb.linearize(U, P), sb.linearize(U, P), db.linearize(U, P)
    assert isinstance(lf, FusedLinearization)
    rows = _collision_rows(game)
    if name.startswith("crossing"):  # the regime the test claims: collisions are active
        assert np.all(np.abs(lf.r[:, rows]).max(axis=1) > 1e-3), name
    for a, s, d in ((lf.r, ls.r, ld.r), (lf.energy, ls.energy, ld.energy)):
        _close(a, s)
        _close(a, d)
    _close(lf.gradient, ls.gradient)
    _close(lf.gradient, ld.gradient)
    _close(lf.diag_jtj(), ls.diag_jtj())
    _close(lf.diag_jtj().reshape(B, -1), np.einsum("bii->bi", ld.JtJ)[:, sb._u_index])


@pytest.mark.parametrize("ellipsoidal", [False, True])
@pytest.mark.parametrize("B", [1, 4])
def test_step_matches_structured_and_dense(case, ellipsoidal, B):
    name, game, fb, sb, db = case
    U, P, lam = _inputs(name, game, B, seed=2)
    lf, ls, ld = fb.linearize(U, P), sb.linearize(U, P), db.linearize(U, P)
    xf = fb.solve(lf, lam, -lf.gradient, ellipsoidal)
    xs = sb.solve(ls, lam, -ls.gradient, ellipsoidal)
    xd = DenseGN.solve(ld, lam, -ld.gradient, ellipsoidal)
    assert np.abs(xs).max() > 1e-3  # a real step
    _close(xf, xs)
    _close(xf, xd, rtol=1e-11)  # dense Cholesky of J'J: up to 5e-12 (ellipsoidal, lags of 2)
    rhs = np.random.default_rng(3).normal(size=U.shape)  # any right-hand side (the layer's VJP)
    _close(fb.solve(lf, lam, rhs), sb.solve(ls, lam, rhs))
    _close(fb.energy(U + 0.3 * xf, P), sb.energy(U + 0.3 * xs, P))


@pytest.mark.parametrize(
    "opts",
    [LMOptions(steps=15), LMOptions.paper(), LMOptions(steps=10, ellipsoidal=True)],
    ids=["adaptive", "paper", "ellipsoidal"],
)
@pytest.mark.parametrize("B", [1, 3])
def test_solve_lm_fused_equals_structured(opts, B):
    game = _two_agent_game("unicycle", COUPLED, K=20)
    _, P, _ = _batch(game, B=B, seed=4)
    runs = {}
    for name, cls in (("structured", StructuredGN), ("fused", FusedGN)):
        o = LMOptions(**{**opts.__dict__, "backend": name})
        assert type(make_backend(game, o)) is cls  # options.backend picks the backend
        runs[name] = solve_lm(game, P, options=o)
    rs, rf = runs["structured"], runs["fused"]
    _close(rf.controls, rs.controls)
    _close(rf.energy, rs.energy)
    _close(rf.energy_history, rs.energy_history)
    np.testing.assert_array_equal(rf.iterations, rs.iterations)
    assert list(rf.status) == list(rs.status)
    assert np.all(rf.energy < rf.energy_history[0] - 1e-3)  # the solve did something


def test_merge_and_select_of_frozen_problems():
    game = crossing_game(N=2, K=20)
    fb, dg = FusedGN(game, threads=1), DenseGN(game, threads=1)
    U, P, lam = _batch(game, B=3, seed=5)
    a, b = fb.linearize(U, P), fb.linearize(U + 0.1, P)
    keep = np.array([True, False, True])
    merged = _merge(a, b, keep)  # solve_lm's merge: the fused linearization's select
    assert isinstance(merged, FusedLinearization)
    ref = _merge(dg.linearize(U, P), dg.linearize(U + 0.1, P), keep)
    _close(fb.solve(merged, lam, -merged.gradient), dg.solve(ref, lam, -ref.gradient), 1e-10)
    _close(merged.J, ref.J)  # the lazy dense view of the merged iterate


def test_singular_problem_is_nonfinite_and_others_finish():
    """Zero damping, one problem with exactly zero columns of J: NONFINITE, the other
    converges as when solved alone (as test_structured checks for the other backends)."""
    game = _two_agent_game("unicycle", ["goal", "acceleration", "turn_rate"], K=8, pair=False)
    P = np.tile(game.default_params(), (2, 1))
    for name in ("w.a.acceleration", "w.a.turn_rate", "w.b.acceleration", "w.b.turn_rate"):
        P[1, game.params[name].start] = 0.0
    opts = LMOptions(backend="fused", damping=0.0, min_damping=0.0, steps=30)
    res = solve_lm(game, P, options=opts)
    assert res.status[1] is Status.NONFINITE
    np.testing.assert_array_equal(res.controls[1], 0.0)
    alone = solve_lm(game, P[0], options=LMOptions(**{**opts.__dict__, "backend": "structured"}))
    assert res.status[0] is alone.status is Status.CONVERGED
    np.testing.assert_allclose(res.controls[0], alone.controls, rtol=0, atol=1e-12)


def test_overflowing_problem_has_the_same_status_as_structured():
    """A weight of 1e200 overflows the energy of one problem: NONFINITE at its start with
    both backends, the others converge to the same iterate."""
    game = crossing_game(N=2, K=20)
    P = np.tile(game.default_params(), (3, 1))
    P[1, game.params["w.a0.goal"].start] = 1e200
    runs = [
        solve_lm(game, P, options=LMOptions(backend=b, steps=20)) for b in ("structured", "fused")
    ]
    rs, rf = runs
    assert (
        list(rf.status)
        == list(rs.status)
        == [
            Status.CONVERGED,
            Status.NONFINITE,
            Status.CONVERGED,
        ]
    )
    np.testing.assert_array_equal(rf.iterations, rs.iterations)
    _close(rf.controls, rs.controls)


def test_delegates_when_rows_couple_every_stage_or_stages_are_large():
    game = _two_agent_game("unicycle", ["goal", "acceleration", TotalAcceleration()], K=10)
    fb = FusedGN(game, threads=1)
    assert fb.fallback is not None and isinstance(fb.delegate, StructuredGN)
    U, P, lam = _batch(game, seed=6)
    lf, ld = fb.linearize(U, P), DenseGN(game, threads=1).linearize(U, P)
    _close(fb.solve(lf, lam, -lf.gradient), DenseGN.solve(ld, lam, -ld.gradient), 1e-10)
    big = crossing_game(N=5, K=3)  # d = 5 * 4 + 5 * 2 = 30 > MAX_STAGE_SIZE
    fb = FusedGN(big, threads=1)
    assert MAX_STAGE_SIZE < 30 and "stage size" in fb.fallback
    U, P, lam = _batch(big, B=2, seed=7)
    lf, ls = fb.linearize(U, P), StructuredGN(big, threads=1).linearize(U, P)
    _close(fb.solve(lf, lam, -lf.gradient), StructuredGN.solve(fb.delegate, ls, lam, -ls.gradient))


def test_bad_rhs_shape_and_unknown_backend_are_errors():
    game = crossing_game(N=2, K=10)
    fb = FusedGN(game, threads=1)
    U, P, lam = _batch(game, B=2)
    with pytest.raises(ValueError, match="rhs"):
        fb.solve(fb.linearize(U, P), lam, np.zeros((2, game.n_u + 1)))
    with pytest.raises(ValueError, match="lm.backend.*fused"):
        LMOptions(backend="fast")


@pytest.mark.skipif(
    not any(shutil.which(c) for c in ("gcc", "cc", "clang")), reason="no C compiler"
)
@pytest.mark.parametrize("name", ["head_on", "double_integrator"])
def test_compiled_equals_interpreted(tmp_path, name):
    """Generated C of the staged form (one SX function per stage, called K times) against
    the interpreted unrolled graph: the same arithmetic, so the same numbers. The double
    integrator's dynamics Jacobians are all constants (no FG input at all)."""
    game = PotentialGame(head_on_spec(K=8)) if name == "head_on" else GAMES[name]()
    fi = FusedGN(game, threads=1)
    assert fi.fallback is None
    assert (name == "double_integrator") == (fi._sizes()[2] == 0)
    fc = FusedGN(game, threads=1, compiled=True, cache_dir=str(tmp_path))
    assert fc.stage_groups == 0  # small: the one-graph linearization
    assert not fc.schur_kernel  # small: the SX Riccati step
    libs = lambda: sorted(f.name.rsplit("_", 1)[0] for f in tmp_path.glob("epo_*.so"))  # noqa: E731
    # one library per function; the sweep and diag(J'J) only when first needed
    assert libs() == [f"epo_{f}_n2_k{game.K}" for f in ("energy", "fused_linearize", "fused_solve")]
    U, P, lam = _batch(game, B=3, seed=8)
    li, lc = fi.linearize(U, P), fc.linearize(U, P)
    _close(lc.gradient, li.gradient)
    _close(fc.solve(lc, lam, -lc.gradient), fi.solve(li, lam, -li.gradient))
    rhs = np.random.default_rng(9).normal(size=U.shape)  # on the kept factorization
    _close(fc.solve(lc, lam, rhs), fi.solve(li, lam, rhs))
    assert len(libs()) == 4 and "fused_sweep" in libs()[3]
    _close(fc.solve(lc, lam, rhs, True), fi.solve(li, lam, rhs, True))
    assert len(libs()) == 5
    _close(fc.energy(U, P), fi.energy(U, P))


@pytest.mark.skipif(
    not any(shutil.which(c) for c in ("gcc", "cc", "clang")), reason="no C compiler"
)
@pytest.mark.parametrize("name", ["head_on", "unicycle_jerk_turn_acc", "second_difference"])
def test_staged_linearization_equals_the_one_graph(tmp_path, monkeypatch, name):
    """The staged linearization (stage functions mapped over groups of equal stages, the
    form compiled for larger games) against the interpreted one-graph function; the
    threshold is lowered so that small games take it. Lags of one and two stages give
    windows of two and three stages and several groups."""
    import solvers.fast_gn as fast_gn

    game = PotentialGame(head_on_spec(K=8)) if name == "head_on" else GAMES[name]()
    fi = FusedGN(game, threads=1)
    monkeypatch.setattr(fast_gn, "STAGED_MIN_INSTRUCTIONS", 0)
    fc = FusedGN(game, threads=1, compiled=True, cache_dir=str(tmp_path))
    assert 3 <= fc.stage_groups <= fast_gn.MAX_STAGE_GROUPS
    U, P, lam = _batch(game, B=3, seed=11)
    li, lc = fi.linearize(U, P), fc.linearize(U, P)
    for field in ("r", "energy", "gradient", "H", "FG"):
        _close(getattr(lc, field), getattr(li, field))
    _close(fc.energy(U, P), fi.energy(U, P))
    _close(fc.solve(lc, lam, -lc.gradient), fi.solve(li, lam, -li.gradient))
    monkeypatch.setattr(fast_gn, "MAX_STAGE_GROUPS", 1)  # too many groups: the one graph
    fo = FusedGN(game, threads=1, compiled=True, cache_dir=str(tmp_path))
    assert fo.stage_groups == 0
    _close(fo.linearize(U, P).gradient, li.gradient)


@pytest.mark.skipif(
    not any(shutil.which(c) for c in ("gcc", "cc", "clang")), reason="no C compiler"
)
def test_compiled_beyond_the_interpreted_stage_size(tmp_path, monkeypatch):
    """With compiled=True only the staged graphs are built, so stage sizes above
    MAX_STAGE_SIZE are allowed (up to MAX_STAGE_SIZE_COMPILED). The limit is lowered here so
    that a small game takes that path; interpreted, the same game is delegated."""
    import solvers.fast_gn as fast_gn

    game = PotentialGame(head_on_spec(K=8))
    ref = FusedGN(game, threads=1)
    monkeypatch.setattr(fast_gn, "MAX_STAGE_SIZE", 4)
    assert FusedGN(game, threads=1).delegate is not None
    fc = FusedGN(game, threads=1, compiled=True, cache_dir=str(tmp_path))
    assert fc.fallback is None and fc.layout.d > fast_gn.MAX_STAGE_SIZE
    U, P, lam = _batch(game, B=2, seed=10)
    li, lc = ref.linearize(U, P), fc.linearize(U, P)
    for ell in (False, True):
        _close(fc.solve(lc, lam, -lc.gradient, ell), ref.solve(li, lam, -li.gradient, ell))
    _close(lc.diag_jtj(), li.diag_jtj())


@pytest.mark.skipif(
    not any(shutil.which(c) for c in ("gcc", "cc", "clang")), reason="no C compiler"
)
@pytest.mark.parametrize("m, nz", [(3, 5), (4, 8)])
def test_schur_kernel_against_numpy(tmp_path, m, nz):
    """The hand-written C elimination of one Riccati stage (Cholesky of Q_uu, Y = C^{-1}
    Q_uz, P = Q_zz - Y'Y from the packed lower triangle of Q) against numpy's Cholesky and
    solve; m = 3 leaves a remainder in the kernel's four-way unrolled update."""
    import casadi as ca

    from solvers.codegen import CompilerError, compile_kernel
    from solvers.fast_gn import schur_kernel_source

    name, src = schur_kernel_source(m, nz)
    so, obj = compile_kernel(src, name, tmp_path)
    assert so.exists() and obj.exists() and compile_kernel(src, name, tmp_path) == (so, obj)
    f = ca.external(name, str(so))
    d = m + nz
    A = np.random.default_rng(13).normal(size=(d, d))
    Q = A @ A.T + 0.5 * np.eye(d)
    q = np.concatenate([Q[j:, j] for j in range(d)])  # packed lower, column-major
    Pv, fac = (np.asarray(v).ravel() for v in f(q))
    C = np.linalg.cholesky(Q[nz:, nz:])
    Y = np.linalg.solve(C, Q[nz:, :nz])
    P = Q[:nz, :nz] - Y.T @ Y
    _close(Pv, np.concatenate([P[j:, j] for j in range(nz)]))
    _close(fac[: m * (m + 1) // 2], np.concatenate([C[j:, j] for j in range(m)]))
    _close(fac[m * (m + 1) // 2 :], Y.reshape(-1, order="F"))
    with pytest.raises(CompilerError, match="epo_bad"):
        compile_kernel("this is not C", "epo_bad", tmp_path)


@pytest.mark.skipif(
    not any(shutil.which(c) for c in ("gcc", "cc", "clang")), reason="no C compiler"
)
def test_schur_kernel_equals_the_unrolled_recursion(tmp_path):
    """The compiled solve with the Riccati step's dense elimination in C (the default from
    SCHUR_KERNEL_MIN_STAGE_SIZE on; forced here on a small game with active collisions, so
    that it compiles in seconds) against the interpreted unrolled SX recursion and the
    structured backend: steps with identity and ellipsoidal damping and a further
    right-hand side on the kept factorization (the sweeps read the kernel's factor)."""
    game = PotentialGame(head_on_spec(K=8))
    fi, sb = FusedGN(game, threads=1), StructuredGN(game, threads=1)
    fk = FusedGN(game, threads=1, compiled=True, cache_dir=str(tmp_path), schur_kernel=True)
    assert fk.schur_kernel and fk.fallback is None
    assert any(f.name.startswith("epo_schur_") for f in tmp_path.glob("*.o"))
    U, P, lam = _batch(game, B=3, seed=12)
    assert (collision_energy(game, U, P) > 0.1).all()  # active
    li, lk, ls = fi.linearize(U, P), fk.linearize(U, P), sb.linearize(U, P)
    for ell in (False, True):
        step = fk.solve(lk, lam, -lk.gradient, ell)
        _close(step, fi.solve(li, lam, -li.gradient, ell))
        _close(step, sb.solve(ls, lam, -ls.gradient, ell))
    rhs = np.random.default_rng(14).normal(size=U.shape)
    _close(fk.solve(lk, lam, rhs, True), fi.solve(li, lam, rhs, True))
    with pytest.raises(SpecError, match="schur_kernel"):
        FusedGN(game, threads=1, schur_kernel=True)  # needs compiled=True
    with pytest.raises(SpecError, match="schur_kernel"):
        FusedGN(game, threads=1, compiled=True, schur_kernel="yes")


def test_layer_gradcheck_with_the_fused_backend():
    """The unrolled layer through FusedGN (every solve in its generated recursion, the
    backward pass's too) against float64 finite differences, with active collisions, and
    the same gradients as through the interpreted structured backend."""
    game = PotentialGame(head_on_spec(K=8))
    layer = GameLayer(game, LMOptions.paper(backend="fused", threads=1))
    assert isinstance(layer.core.backend, FusedGN) and layer.core.backend.delegate is None
    u0, w_own, w_pair, goal, x0 = layer_inputs(layer)
    p = layer.assemble_params(goal=goal).detach().numpy()
    assert (collision_energy(game, u0.detach().numpy(), p) > 0.1).all()  # active

    def f(u0, w_own, w_pair, goal, x0):
        out = layer(layer.assemble_params(w_own=w_own, w_pair=w_pair, goal=goal, x0=x0), u0)
        return out.controls, out.states

    assert torch.autograd.gradcheck(f, (u0, w_own, w_pair, goal, x0))
    ref = GameLayer(game, LMOptions.paper(threads=1))  # structured: the same gradients
    assert isinstance(ref.core.backend, StructuredGN)
    leaves = (u0, w_own, w_pair, goal, x0)
    out_f = f(*leaves)[1].square().sum()
    pr = ref.assemble_params(w_own=w_own, w_pair=w_pair, goal=goal, x0=x0)
    out_s = ref(pr, u0).states.square().sum()
    for a, b in zip(
        torch.autograd.grad(out_f, leaves), torch.autograd.grad(out_s, leaves), strict=True
    ):
        assert a.abs().max() > 0
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12 * float(b.abs().max()))
