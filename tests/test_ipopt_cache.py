"""The IPOPT set-up cache (solvers.ipopt): the Hessian of the Lagrangian is built once per
game structure and, with ``cache=True`` (off by default), kept on disk.

References: a fresh build with the cache off (the same solution to 1e-12 and the same
iteration count), a second Python process (it must load, not build: the build counter and
the reported source say so), a corrupted file (detected by its checksum and rebuilt) and
structure changes (another horizon, another feature: a new file, never the old one).
"""

from __future__ import annotations

import dataclasses
import io
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import solvers.ipopt as ipopt_mod
from epo_casadi import PotentialGame
from solvers.ipopt import IpoptSolver

from .helpers import crossing_spec

K = 8


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    """An empty cache folder, and every game large enough to be cached."""
    folder = tmp_path / "cache"
    monkeypatch.setenv("EPO_CACHE_DIR", str(folder))
    monkeypatch.setattr(ipopt_mod, "DISK_CACHE_MIN_WORK", 0)
    return folder


def files(folder: Path) -> list[Path]:
    return sorted(folder.glob("ipopt_hess_*.bin"))


def solve(game: PotentialGame, **opts):
    opts.setdefault("cache", True)  # the disk cache is opt-in
    s = IpoptSolver(game, opts)
    p = game.default_params()
    return s, s.solve(p, 0.05 * np.ones(game.n_u))


@pytest.mark.parametrize(
    "opts",
    [
        {},
        {
            "hessian": "gn",
            "state_bounds": {"a0": ([None, None, 0.0, None], [None, None, 1.2, None])},
        },
    ],
    ids=["exact", "gn+state_bounds"],
)
def test_cached_solver_gives_the_fresh_solution(cache, opts):
    spec = crossing_spec(K=K, offset=0.3)
    s1, r1 = solve(PotentialGame(spec), **opts)
    assert s1.setup_source == "built" and len(files(cache)) == 1
    s2, r2 = solve(PotentialGame(spec), **opts)  # a new game object: only the disk can help
    assert s2.setup_source == "disk"
    s3, r3 = solve(PotentialGame(spec), cache=False, **opts)
    assert s3.setup_source == "built"
    assert r1.status.value == "converged"
    for r in (r2, r3):
        np.testing.assert_allclose(r.controls, r1.controls, rtol=0, atol=1e-12)
        assert r.iterations == r1.iterations
        np.testing.assert_allclose(r.energy, r1.energy, rtol=1e-14)
    # the stored Hessian is the freshly built one, entry by entry, at a random point
    rng = np.random.default_rng(0)
    game = s1.game
    args = [rng.normal(size=game.n_u), game.default_params(), 1.3, rng.normal(size=s1.lbg.size)]
    h_disk = np.asarray(s2.hess_lag(*args).full())
    h_new = np.asarray(ipopt_mod._build_hessian(game, s1._g, s1.options.hessian)(*args).full())
    np.testing.assert_allclose(h_disk, h_new, rtol=0, atol=0)
    # the result reports the set-up
    for s, r in ((s1, r1), (s2, r2)):
        assert r.info["setup_source"] == s.setup_source
        assert r.info["setup_s"] == s.setup_s and s.setup_s > 0


SCRIPT = textwrap.dedent(
    """
    import numpy as np
    import solvers.ipopt as m
    from epo_casadi import PotentialGame
    from tests.helpers import crossing_spec
    m.DISK_CACHE_MIN_WORK = 0
    game = PotentialGame(crossing_spec(K={K}, offset=0.3))
    s = m.IpoptSolver(game, {{"cache": True}})
    r = s.solve(game.default_params())
    print(s.setup_source, m.CACHE_STATS["built"], m.CACHE_STATS["disk"], r.iterations)
    np.save({out!r}, r.controls)
    """
)


def test_a_second_process_loads_instead_of_building(tmp_path):
    env = dict(os.environ, EPO_CACHE_DIR=str(tmp_path / "cache"))
    root = Path(__file__).resolve().parents[1]
    outs = []
    for n in range(2):
        out = str(tmp_path / f"u{n}.npy")
        proc = subprocess.run(
            [sys.executable, "-c", SCRIPT.format(K=K, out=out)],
            cwd=root,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 0, proc.stderr
        outs.append(proc.stdout.split())
        if n == 1:
            np.testing.assert_allclose(
                np.load(out), np.load(str(tmp_path / "u0.npy")), rtol=0, atol=1e-12
            )
    source0, built0, disk0, it0 = outs[0]
    source1, built1, disk1, it1 = outs[1]
    assert (source0, built0, disk0) == ("built", "1", "0")
    assert (source1, built1, disk1) == ("disk", "0", "1")  # the build path was not taken
    assert it0 == it1


@pytest.mark.parametrize("damage", ["flip", "truncate", "garbage"])
def test_a_corrupted_cache_file_is_rebuilt(cache, damage):
    spec = crossing_spec(K=K, offset=0.3)
    _, r1 = solve(PotentialGame(spec))
    (path,) = files(cache)
    data = bytearray(path.read_bytes())
    if damage == "flip":
        data[len(data) // 2] ^= 0x55  # one byte inside the compressed payload
    elif damage == "truncate":
        data = data[: len(data) // 3]
    else:
        data = bytearray(b"not a cache file at all")
    path.write_bytes(bytes(data))
    before = dict(ipopt_mod.CACHE_STATS)
    with pytest.warns(UserWarning, match="unusable"):
        s2, r2 = solve(PotentialGame(spec))
    assert s2.setup_source == "rebuilt"
    assert ipopt_mod.CACHE_STATS["rebuilt"] == before["rebuilt"] + 1
    assert ipopt_mod.CACHE_STATS["disk"] == before["disk"]
    np.testing.assert_allclose(r2.controls, r1.controls, rtol=0, atol=1e-12)
    # the file was replaced by an intact one
    s3, r3 = solve(PotentialGame(spec))
    assert s3.setup_source == "disk"
    np.testing.assert_allclose(r3.controls, r1.controls, rtol=0, atol=1e-12)


def test_a_structure_change_does_not_reuse_the_cache(cache):
    spec = crossing_spec(K=K, offset=0.3)
    solve(PotentialGame(spec))
    assert len(files(cache)) == 1
    # parameter values (weights, start, goals) are not structure: the file is reused
    s, _ = solve(PotentialGame(crossing_spec(K=K, offset=0.8, collision_weight=3.0)))
    assert s.setup_source == "disk"
    # another horizon, another feature set, another Hessian kind: a new build each
    changed = [
        crossing_spec(K=K + 1, offset=0.3),
        dataclasses.replace(spec, pair_features=()),
    ]
    for n, sp in enumerate(changed):
        s, r = solve(PotentialGame(sp))
        assert s.setup_source == "built"
        assert len(files(cache)) == 2 + n
        assert r.status.value == "converged"
    s, _ = solve(PotentialGame(spec), hessian="gn")
    assert s.setup_source == "built" and len(files(cache)) == 4


def test_small_games_and_cache_off_write_nothing(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv("EPO_CACHE_DIR", str(folder))
    game = PotentialGame(crossing_spec(K=K))
    assert game.n_u * game.function("energy").n_instructions() < ipopt_mod.DISK_CACHE_MIN_WORK
    solve(game)  # below the size limit: built, not stored
    monkeypatch.setattr(ipopt_mod, "DISK_CACHE_MIN_WORK", 0)
    s, _ = solve(PotentialGame(crossing_spec(K=K)), cache=False)
    assert s.setup_source == "built"
    assert not folder.exists() or not files(folder)


def test_the_disk_cache_is_off_by_default(tmp_path, monkeypatch):
    """Loading a stored Hessian took as long as building it (docs/solvers.md), so nothing
    is read or written unless ``cache=True``."""
    folder = tmp_path / "cache"
    monkeypatch.setenv("EPO_CACHE_DIR", str(folder))
    monkeypatch.setattr(ipopt_mod, "DISK_CACHE_MIN_WORK", 0)
    assert ipopt_mod.IpoptOptions().cache is False
    s = IpoptSolver(PotentialGame(crossing_spec(K=K)))
    assert s.setup_source == "built"
    assert not folder.exists() or not files(folder)


def test_cache_option_is_checked():
    from epo_casadi import SpecError

    with pytest.raises(SpecError, match="ipopt.cache"):
        ipopt_mod.IpoptOptions(cache="yes")


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_lines_on_a_terminal_only(cache, monkeypatch):
    monkeypatch.setattr(ipopt_mod, "PROGRESS_MIN_WORK", 0)
    term = _Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    solve(PotentialGame(crossing_spec(K=K)))
    lines = term.getvalue().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("epo: building the IPOPT Hessian (exact) for 2 agents")
    assert lines[1].startswith("epo: IPOPT Hessian built in ") and str(cache) in lines[1]
    pipe = io.StringIO()  # not a terminal: silent
    monkeypatch.setattr(sys, "stderr", pipe)
    solve(PotentialGame(crossing_spec(K=K + 2)))
    assert pipe.getvalue() == ""
