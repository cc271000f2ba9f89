"""The compiled-code cache (solvers.codegen) trusts no file it did not check.

A library is loaded only when its bytes match the digest recorded when it was built; a
planted library (a copy of another cached one, digest file included, or garbage), a
truncated one or one without a digest is compiled again, and a cache folder that others
can write to, or that belongs to someone else, is refused in one line. The functions are
one-instruction CasADi functions, so each compile takes a fraction of a second.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import casadi as ca
import pytest

import solvers.ipopt as ipopt_mod
from epo_casadi import PotentialGame
from solvers import codegen
from solvers.codegen import CacheError, compile_functions, compile_kernel
from solvers.ipopt import IpoptSolver
from tests.helpers import crossing_spec

pytestmark = pytest.mark.skipif(
    not any(shutil.which(c) for c in ("gcc", "cc", "clang")), reason="no C compiler"
)

ROOT = Path(__file__).resolve().parents[1]


def scaled(k: float) -> ca.Function:
    """``f(x) = k x``: every such function is named ``f``, so a library of one would load
    as another's without complaint."""
    x = ca.SX.sym("x")
    return ca.Function("f", [x], [k * x])


def lib_path(f: ca.Function, name: str, folder: Path) -> Path:
    """Where the cache keeps the library of ``f`` (without building it)."""
    return codegen._plan([f], name, folder, "auto")[-1]


def digest_file(lib: Path) -> Path:
    return lib.with_name(lib.name + ".sha256")


@pytest.fixture
def compiles(monkeypatch) -> list:
    """Every compiler process started (the library's path is the command's ``-o``)."""
    started = []
    popen = subprocess.Popen

    class Counting(popen):
        def __init__(self, cmd, *a, **k):
            started.append(cmd)
            super().__init__(cmd, *a, **k)

    monkeypatch.setattr(subprocess, "Popen", Counting)
    return started


def test_a_fresh_build_records_a_digest_that_verifies(tmp_path, compiles):
    lib = lib_path(scaled(2.0), "epo_rel_fresh", tmp_path)
    f = compile_functions([scaled(2.0)], "epo_rel_fresh", tmp_path)["f"]
    assert float(f(1.5)) == 3.0 and len(compiles) == 1
    recorded = digest_file(lib).read_text().split()
    expected = hashlib.sha256(lib.name.encode() + b"\0" + lib.read_bytes()).hexdigest()
    assert recorded == [expected, lib.name]
    assert codegen._is_intact(lib)
    codegen._verified.clear()  # as in a new process: the bytes are hashed again
    assert codegen._is_intact(lib)
    assert float(compile_functions([scaled(2.0)], "epo_rel_fresh", tmp_path)["f"](1.0)) == 2.0
    assert len(compiles) == 1  # loaded from the cache, not compiled again
    # no temporary file or folder is left: the library, its digest and its lock file
    lock = lib.with_name(f".{lib.name}.lock")
    assert sorted(tmp_path.iterdir()) == sorted([lib, digest_file(lib), lock])


def test_a_planted_copy_of_another_library_is_rebuilt(tmp_path, compiles):
    """The copy of a valid library of another function (same symbol name ``f``), with its
    digest file, put where the library of ``3 x`` belongs: loading it would give 2 x."""
    compile_functions([scaled(2.0)], "epo_rel_plant", tmp_path)
    other = lib_path(scaled(2.0), "epo_rel_plant", tmp_path)
    target = lib_path(scaled(3.0), "epo_rel_plant", tmp_path)
    shutil.copyfile(other, target)
    if digest_file(other).exists():
        shutil.copyfile(digest_file(other), digest_file(target))
    f = compile_functions([scaled(3.0)], "epo_rel_plant", tmp_path)["f"]
    assert float(f(1.0)) == 3.0
    assert len(compiles) == 2 and target.read_bytes() != other.read_bytes()
    assert codegen._is_intact(target)


def test_garbage_or_a_missing_digest_is_rebuilt(tmp_path, compiles):
    target = lib_path(scaled(4.0), "epo_rel_junk", tmp_path)
    target.write_bytes(b"\x7fELF" + os.urandom(3000))  # no digest file
    assert float(compile_functions([scaled(4.0)], "epo_rel_junk", tmp_path)["f"](1.0)) == 4.0
    assert len(compiles) == 1 and codegen._is_intact(target)
    # a library of an older version (no digest file) is compiled again, not trusted
    digest_file(target).unlink()
    codegen._verified.clear()
    assert float(compile_functions([scaled(4.0)], "epo_rel_junk", tmp_path)["f"](2.0)) == 8.0
    assert len(compiles) == 2 and codegen._is_intact(target)


def test_a_truncated_library_is_rebuilt_without_a_crash(tmp_path):
    """In a fresh process (which has not loaded the library): its truncated file, with the
    digest of the whole one beside it, used to crash Python or fail in dlopen."""
    script = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        import casadi as ca
        from solvers.codegen import compile_functions
        x = ca.SX.sym("x")
        f = compile_functions([ca.Function("f", [x], [5.0 * x])], "epo_rel_trunc", sys.argv[1])
        print(float(f["f"](2.0)))
        """
    )
    run = [sys.executable, "-c", script, str(tmp_path)]
    first = subprocess.run(run, capture_output=True, text=True, timeout=120)
    assert first.returncode == 0 and first.stdout.strip() == "10.0", first.stderr
    lib = lib_path(scaled(5.0), "epo_rel_trunc", tmp_path)
    whole = lib.read_bytes()
    lib.write_bytes(whole[: len(whole) // 3])
    again = subprocess.run(run, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and again.stdout.strip() == "10.0", again.stderr
    assert lib.stat().st_size == len(whole)
    assert codegen._is_intact(lib)


def test_a_kernel_object_is_checked_before_it_is_linked(tmp_path):
    src = "int epo_rel_kernel(int a) { return 2 * a; }\n"
    so, obj = compile_kernel(src, "epo_rel_kernel", tmp_path)
    good = obj.read_bytes()
    obj.write_bytes(b"junk")  # a planted object would be linked into other libraries
    codegen._verified.clear()
    so2, obj2 = compile_kernel(src, "epo_rel_kernel", tmp_path)
    assert (so2, obj2) == (so, obj) and obj.read_bytes() == good
    assert codegen._is_intact(so) and codegen._is_intact(obj)


def test_concurrent_builds_of_one_library_compile_it_once(tmp_path, compiles):
    start = threading.Barrier(2)
    results, errors = [], []

    def build():
        start.wait()
        try:
            results.append(
                float(compile_functions([scaled(6.0)], "epo_rel_two", tmp_path)["f"](1.0))
            )
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=build) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and results == [6.0, 6.0]
    assert len(compiles) == 1


@pytest.mark.parametrize("mode", [0o777, 0o770, 0o702])
def test_a_cache_folder_others_can_write_is_refused(tmp_path, monkeypatch, compiles, mode):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(mode)
    monkeypatch.setenv("EPO_CACHE_DIR", str(shared))
    with pytest.raises(CacheError) as e:
        compile_functions([scaled(7.0)], "epo_rel_shared")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{shared}: refusing")
    assert f"chmod go-w {shared}" in msg and f"mode {mode:o}" in msg
    assert compiles == [] and list(shared.iterdir()) == []  # nothing built, nothing loaded
    with pytest.raises(CacheError):  # an explicit folder too
        codegen.cache_dir(shared)


def test_a_cache_folder_of_another_user_is_refused(tmp_path):
    folder = tmp_path / "theirs"
    folder.mkdir(mode=0o755)
    if os.geteuid() != 0:
        pytest.skip("changing a folder's owner needs root")
    os.chown(folder, os.geteuid() + 4242, -1)
    with pytest.raises(CacheError, match=r"belongs to user id \d+, not to you"):
        compile_functions([scaled(8.0)], "epo_rel_theirs", folder)


def test_a_new_cache_folder_is_private(tmp_path, monkeypatch):
    monkeypatch.setenv("EPO_CACHE_DIR", str(tmp_path / "a" / "cache"))
    d = codegen.cache_dir()
    assert d == tmp_path / "a" / "cache" and d.stat().st_mode & 0o077 == 0


def test_the_ipopt_disk_cache_refuses_a_shared_folder(tmp_path, monkeypatch):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    monkeypatch.setenv("EPO_CACHE_DIR", str(shared))
    monkeypatch.setattr(ipopt_mod, "DISK_CACHE_MIN_WORK", 0)
    with pytest.raises(CacheError, match="chmod go-w"):
        IpoptSolver(PotentialGame(crossing_spec(K=4)), {"cache": True})
    assert list(shared.iterdir()) == []
    off = IpoptSolver(PotentialGame(crossing_spec(K=4)), {"cache": False})
    assert off.setup_source == "built"  # with the cache off the folder is not used
