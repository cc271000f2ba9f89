"""Code named by a data file runs only when the user allows it (epo_casadi.registry).

A game file's ``module:Class`` type imports its module only when the module (or a package
above it) is allowed: ``--allow-import`` on the game-file commands, ``$EPO_ALLOW_IMPORT``,
``allow_imports`` / ``load_game(allow_imports=...)`` in Python. Anything else is one
``error:`` line naming the field and how to allow it, and the module is not imported
(its top-level code leaves a marker file when it runs). Whatever an allowed module raises
at import (``SystemExit(0)`` too) is one line as well.
"""

from __future__ import annotations

import itertools
import sys
import textwrap
from pathlib import Path

import pytest

from epo_casadi import SpecError, make_feature, register_feature
from epo_casadi.registry import FEATURES, allow_imports, allowed_imports, load_class
from scenarios.gamefile import load_game, parse_game
from tests.helpers import cli, one_error_line

FEATURE_SOURCE = """
import pathlib
from dataclasses import dataclass
from typing import ClassVar

from epo_casadi import Feature

pathlib.Path(__file__).with_name(__name__ + ".ran").write_text("imported")


@dataclass(frozen=True)
class Home(Feature):
    kind: ClassVar[str] = "home"

    def steps(self, K):
        return [K]

    def residual(self, ctx):
        return ctx.X[0:2, ctx.K]
"""

_ids = itertools.count()


@pytest.fixture
def user(tmp_path, monkeypatch):
    """A module of the user's with a feature ``Home``, on ``sys.path`` under a fresh name
    (``.name``); ``.ran()`` says whether its top-level code ran; ``.game`` a game file
    naming it as the second feature of agent 0."""
    monkeypatch.delenv("EPO_ALLOW_IMPORT", raising=False)
    code = tmp_path / "code"
    code.mkdir()
    name = f"epo_rel_user_{next(_ids)}"
    (code / f"{name}.py").write_text(FEATURE_SOURCE, encoding="utf-8")
    monkeypatch.syspath_prepend(str(code))

    class User:
        pass

    u = User()
    u.name, u.dir = name, code
    u.ran = lambda: (code / f"{name}.ran").exists()
    u.game = write_game(tmp_path / "games" / "g.yaml", f"{name}:Home")
    yield u
    sys.modules.pop(name, None)


def write_game(path: Path, feature_type: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        textwrap.dedent(
            f"""
            horizon: 4
            dt: 0.1
            agents:
              - name: a
                dynamics: unicycle
                x0: [1.0, 0.0, 0.5, 0.0]
                features: [acceleration, {{type: "{feature_type}", weight: 1.0}}]
            """
        ),
        encoding="utf-8",
    )
    return path


FIELD = "agents[0].features[1].type"


@pytest.mark.parametrize(
    "command",
    [
        ["solve", "{game}"],
        ["solve", "{game}", "--modes", "2", "--solver", "lm"],
        ["inspect", "{game}"],
        ["export", "{game}", "--format", "casadi", "--out", "{tmp}/export"],
        ["compare", "{game}", "--out", "{tmp}/cmp"],
        ["compare", "{games}", "--out", "{tmp}/cmp"],  # a folder of game files
    ],
    ids=["solve", "solve-modes", "inspect", "export", "compare", "compare-dir"],
)
def test_game_file_commands_import_nothing_unasked(capsys, tmp_path, user, command):
    args = [a.format(game=user.game, games=user.game.parent, tmp=tmp_path) for a in command]
    rc, out, err = cli(capsys, *args)
    line = one_error_line(
        rc, err, FIELD, "not allowed", f"--allow-import {user.name}", "EPO_ALLOW_IMPORT"
    )
    assert f"'{user.name}:Home'" in line
    assert not user.ran() and user.name not in sys.modules
    assert not (tmp_path / "export").exists() and not (tmp_path / "cmp").exists()


def test_allowed_by_the_option_the_environment_or_python(capsys, tmp_path, monkeypatch, user):
    rc, out, err = cli(capsys, "inspect", user.game, "--allow-import", user.name)
    assert rc == 0, err
    assert user.ran() and "home" in out
    rc, out, err = cli(capsys, "solve", user.game, "--allow-import", f"other,{user.name}")
    assert rc == 0 and "lm: converged" in out, err
    assert allowed_imports() == ()  # the option held for that command only
    with pytest.raises(SpecError, match="not allowed"):
        load_game(user.game)
    monkeypatch.setenv("EPO_ALLOW_IMPORT", f" other , {user.name}")
    assert load_game(user.game).spec.agents[0].features[1].kind == "home"
    rc, _, err = cli(capsys, "solve", user.game)
    assert rc == 0, err
    monkeypatch.delenv("EPO_ALLOW_IMPORT")
    assert load_game(user.game, allow_imports=[user.name]).game.n_u == 8
    with allow_imports(user.name):
        assert make_feature({"type": f"{user.name}:Home"}).kind == "home"
    with pytest.raises(SpecError, match="not allowed") as e:
        make_feature({"type": f"{user.name}:Home"})  # a mapping, like a file
    assert e.value.field == "feature.type"


def test_a_package_allows_its_submodules_only(tmp_path, monkeypatch):
    monkeypatch.delenv("EPO_ALLOW_IMPORT", raising=False)
    root = tmp_path / "code"
    pkg = root / "epo_rel_pkg"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "lanes.py").write_text(FEATURE_SOURCE)
    (root / "epo_rel_pkg2.py").write_text(FEATURE_SOURCE)
    monkeypatch.syspath_prepend(str(root))
    try:
        data = {
            "horizon": 3,
            "dt": 0.1,
            "agents": [{"name": "a", "dynamics": "unicycle", "x0": [0, 0, 0, 0]}],
        }
        data["agents"][0]["features"] = [{"type": "epo_rel_pkg.lanes:Home"}]
        assert parse_game(data, allow_imports=["epo_rel_pkg"]).spec.agents[0].features
        data["agents"][0]["features"] = [{"type": "epo_rel_pkg2:Home"}]  # not a submodule
        with pytest.raises(SpecError, match="not allowed"):
            parse_game(data, allow_imports=["epo_rel_pkg"])
        assert "epo_rel_pkg2" not in sys.modules
        data["agents"][0]["features"] = [{"type": "epo_rel_pkg:Home"}]  # the package itself
        with pytest.raises(SpecError, match="not allowed"):
            parse_game(data, allow_imports=["epo_rel_pkg.lanes"])
    finally:
        for m in ("epo_rel_pkg", "epo_rel_pkg.lanes", "epo_rel_pkg2"):
            sys.modules.pop(m, None)


def test_registered_names_and_the_users_own_register_calls_need_no_allowance(user):
    before = dict(FEATURES.table)
    try:
        cls = register_feature(f"{user.name}:Home")  # the caller's own code: its choice
        assert cls.kind == "home" and user.ran()
        write_game(user.game, "home")
        assert load_game(user.game).spec.agents[0].features[1].kind == "home"
        assert load_class(f"{user.name}:Home") is cls  # a direct call is the caller's too
    finally:
        FEATURES.table.clear()
        FEATURES.table.update(before)


@pytest.mark.parametrize(
    "raises, shown",
    [
        ("raise SystemExit(0)", "SystemExit: 0"),
        ("raise SystemExit('bye')", "SystemExit: bye"),
        ("class Boom(BaseException):\n    pass\nraise Boom('deep')", "Boom: deep"),
        ("raise RuntimeError('broken\\nsecond line')", "RuntimeError: broken"),
    ],
    ids=["exit0", "exit-text", "base-exception", "two-lines"],
)
def test_whatever_an_allowed_module_raises_is_one_line(capsys, tmp_path, user, raises, shown):
    (user.dir / f"{user.name}.py").write_text(raises + "\n", encoding="utf-8")
    rc, out, err = cli(capsys, "solve", user.game, "--allow-import", user.name)
    line = one_error_line(rc, err, FIELD, f"cannot import '{user.name}'", shown)
    assert "second line" not in line and out == ""


def test_keyboard_interrupt_at_import_is_not_swallowed(user):
    (user.dir / f"{user.name}.py").write_text("raise KeyboardInterrupt\n", encoding="utf-8")
    with pytest.raises(KeyboardInterrupt):
        load_game(user.game, allow_imports=[user.name])


@pytest.mark.parametrize("bad", ["1pkg", "a-b", "pkg..x", "pkg:Class"])
def test_malformed_allowances_are_one_line(capsys, monkeypatch, user, bad):
    rc, _, err = cli(capsys, "solve", user.game, "--allow-import", bad)
    one_error_line(rc, err, "--allow-import", "expected a module name")
    monkeypatch.setenv("EPO_ALLOW_IMPORT", bad)
    rc, _, err = cli(capsys, "inspect", user.game)
    one_error_line(rc, err, "EPO_ALLOW_IMPORT", "expected a module name")
    assert not user.ran()
    with pytest.raises(SpecError) as e:
        with allow_imports(123):
            pass
    assert e.value.field == "allow_imports"
