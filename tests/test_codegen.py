"""Generated C (solvers.codegen) against CasADi's interpreter; the on-disk cache.

Only small functions are compiled here (a 2-agent game with K = 6 or 20 steps), so the
module stays within seconds.
"""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from epo_casadi.errors import SpecError
from solvers import codegen
from solvers.batch import BatchFunction
from solvers.codegen import CompilerError, compile_functions, find_compiler
from solvers.lm import DenseGN
from solvers.structured import StructuredGN
from tests.helpers import crossing_game

pytestmark = pytest.mark.skipif(
    not any(shutil.which(c) for c in ("gcc", "cc", "clang")), reason="no C compiler"
)


@pytest.fixture(scope="module")
def small_game():
    return crossing_game(N=2, K=6)


def _random_inputs(game, B=5, seed=0):
    rng = np.random.default_rng(seed)
    U = rng.normal(size=(B, game.n_u))
    P = np.tile(game.default_params(), (B, 1)) * (1 + 0.2 * rng.uniform(-1, 1, size=(B, game.n_p)))
    return U, P


def test_compiled_equals_interpreted(small_game, tmp_path):
    names = ["residual", "jacobian", "energy", "rollout"]
    funcs = [small_game.function(n) for n in names]
    compiled = compile_functions(funcs, "epo_test_small", tmp_path)
    assert sorted(compiled) == sorted(names)
    U, P = _random_inputs(small_game)
    for f in funcs:
        c = compiled[f.name()]
        assert c.sparsity_out(0) == f.sparsity_out(0)
        assert [c.name_in(i) for i in range(c.n_in())] == ["u", "p"]
        ref = BatchFunction(f, 1)(U, P)[0]
        got = BatchFunction(c, 2)(U, P)[0]  # mapped with threads, like the solvers do
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)))


def test_cache_is_reused_and_keyed_by_content(small_game, tmp_path, monkeypatch):
    f = small_game.function("energy")
    compile_functions([f], "epo_test_cache", tmp_path)
    libs = sorted(tmp_path.glob("epo_test_cache_*.so"))
    assert len(libs) == 1
    mtime = libs[0].stat().st_mtime_ns

    def no_compiler(*a, **k):
        raise AssertionError("compiled again although the library is cached")

    monkeypatch.setattr(subprocess, "run", no_compiler)
    monkeypatch.setattr(subprocess, "Popen", no_compiler)
    again = compile_functions([f], "epo_test_cache", tmp_path)["energy"]
    assert libs[0].stat().st_mtime_ns == mtime
    U, P = _random_inputs(small_game, B=1)
    assert float(again(U[0], P[0])) == pytest.approx(float(f(U[0], P[0])), rel=1e-12)
    monkeypatch.undo()
    # another expression graph (one more step) gives another file; equal graphs share one
    compile_functions([crossing_game(N=2, K=7).function("energy")], "epo_test_cache", tmp_path)
    compile_functions([crossing_game(N=2, K=6).function("energy")], "epo_test_cache", tmp_path)
    assert len(sorted(tmp_path.glob("epo_test_cache_*.so"))) == 2


def test_cache_dir_from_environment(small_game, tmp_path, monkeypatch):
    monkeypatch.setenv("EPO_CACHE_DIR", str(tmp_path / "envcache"))
    compile_functions([small_game.function("energy")], "epo_test_env")
    assert list((tmp_path / "envcache").glob("epo_test_env_*.so"))


def test_missing_compiler_is_a_clear_error(small_game, tmp_path, monkeypatch):
    monkeypatch.setenv("CC", "no-such-compiler-xyz")
    with pytest.raises(CompilerError, match="no C compiler found"):
        find_compiler()
    with pytest.raises(CompilerError, match="compiled=False"):
        compile_functions([small_game.function("energy")], "epo_test_nocc", tmp_path)


def test_libraries_compile_in_parallel(small_game, tmp_path, monkeypatch):
    """compile_libraries runs one compiler per missing library, at most as many at once as
    usable cores, loads each library and reports a failing compile naming its file."""
    names = ["residual", "energy", "rollout"]
    libs = [([small_game.function(n)], f"epo_test_par_{n}") for n in names]
    running, peak = [], [0]
    popen = subprocess.Popen

    class Counting(popen):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            running.append(self)
            peak[0] = max(peak[0], sum(p.poll() is None for p in running))

    monkeypatch.setattr(subprocess, "Popen", Counting)
    monkeypatch.setattr(codegen, "_usable_cores", lambda: 2)
    out = codegen.compile_libraries(libs, tmp_path)
    assert len(running) == 3 and 1 <= peak[0] <= 2
    U, P = _random_inputs(small_game, B=2)
    for n, lib in zip(names, out, strict=True):
        f = small_game.function(n)
        ref, got = BatchFunction(f, 1)(U, P)[0], BatchFunction(lib[n], 1)(U, P)[0]
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)))
    assert len(list(tmp_path.glob("epo_test_par_*.so"))) == 3
    codegen.compile_libraries(libs, tmp_path)  # cached: no compiler runs
    assert len(running) == 3
    monkeypatch.setattr(codegen, "_flags", lambda funcs, optimize: ["-fno-such-flag-xyz"])
    with pytest.raises(CompilerError, match=r"compiling epo_test_bad\.c failed"):
        codegen.compile_libraries([([small_game.function("energy")], "epo_test_bad")], tmp_path)
    assert not list(tmp_path.glob("epo_test_bad*.so"))


def test_bad_arguments(small_game, tmp_path):
    f = small_game.function("energy")
    with pytest.raises(SpecError, match="unique"):
        compile_functions([f, f], "epo_test_dup", tmp_path)
    with pytest.raises(SpecError, match="identifier"):
        compile_functions([f], "not a name", tmp_path)
    with pytest.raises(SpecError, match="optimize"):
        compile_functions([f], "epo_test_opt", tmp_path, optimize="-O9")
    assert codegen._flags([f], "auto")[0] == "-O1"


def test_structured_compiled_equals_interpreted(tmp_path):
    game = crossing_game(N=2, K=20, offset=0.3)
    sc = StructuredGN(game, threads=1, compiled=True, cache_dir=tmp_path)
    si = StructuredGN(game, threads=1)
    U, P = _random_inputs(game, B=4, seed=1)
    U *= 0.3
    a, b = sc.linearize(U, P), si.linearize(U, P)
    for name in ("r", "gradient", "H", "FG"):
        ref = getattr(b, name)
        np.testing.assert_allclose(
            getattr(a, name), ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref))
        )
    np.testing.assert_allclose(sc.energy(U, P), si.energy(U, P), rtol=1e-12)
    lam = np.array([0.1, 1.0, 10.0, 3.0])
    ld = DenseGN(game, threads=1).linearize(U, P)
    ref = DenseGN.solve(ld, lam, -ld.gradient)
    np.testing.assert_allclose(
        sc.solve(a, lam, -a.gradient), ref, rtol=1e-9, atol=1e-9 * np.max(np.abs(ref))
    )
