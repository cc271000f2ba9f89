"""The extension API (epo_casadi.registry): registration, resolution, user classes
accepted as instances everywhere, feature parameter blocks, import direction."""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import casadi as ca
import numpy as np
import pytest

from epo_casadi import (
    Acceleration,
    AgentSpec,
    Dynamics,
    Feature,
    GameSpec,
    Goal,
    PairFeature,
    ParamSpec,
    PotentialGame,
    SpecError,
    make_dynamics,
    make_feature,
    make_pair_feature,
    register_dynamics,
    register_feature,
    register_pair_feature,
)
from epo_casadi.registry import DYNAMICS, FEATURES, PAIR_FEATURES, allow_imports, load_class
from scenarios.gamefile import dump_game, parse_game
from solvers import solve_ipopt, solve_lm

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Offset(Feature):
    """``x_K - target`` on the first state, ``target`` a block of its own (2 entries)."""

    kind: ClassVar[str] = "offset"
    target: tuple[float, ...] = (0.5, -0.5)

    def params(self):
        return (ParamSpec("target", 2, self.target, entries=("x", "y")),)

    def steps(self, K):
        return [K]

    def residual(self, ctx):
        return ctx.X[0:2, ctx.K] - ctx.refs["target"]


@dataclass(frozen=True)
class Near(PairFeature):
    """Symmetric: squared distance of the final positions (pulls two agents together)."""

    kind: ClassVar[str] = "near"

    def steps(self, K):
        return [K]

    def residual(self, a, b):
        return a.X[0:2, a.K] - b.X[0:2, b.K]


@dataclass(frozen=True)
class Point(Dynamics):
    """A single integrator ``p' = u`` with a gain."""

    name = "point"
    state_names: tuple[str, ...] = ("x", "y")
    control_names: tuple[str, ...] = ("vx", "vy")
    gain: float = 1.0

    def step(self, x, u, dt):
        return x + self.gain * dt * u

    def acceleration(self, u):
        return u


@dataclass(frozen=True)
class Near2Own(Offset):
    kind: ClassVar[str] = "offset2"


@dataclass(frozen=True)
class NoResidual(Feature):
    kind: ClassVar[str] = "no_residual"


@dataclass(frozen=True)
class NoKind(Feature):
    def steps(self, K):
        return [K]

    def residual(self, ctx):
        return ctx.X[0, ctx.K]


@pytest.fixture
def clean():
    """Remove whatever a test registers."""
    before = {r: dict(r.table) for r in (FEATURES, PAIR_FEATURES, DYNAMICS)}
    yield
    for r, t in before.items():
        r.table.clear()
        r.table.update(t)


def _game(K=6):
    agents = [
        AgentSpec("a", Point(gain=2.0), [Offset(weight=2.0), Acceleration()], x0=[0, 0]),
        AgentSpec("b", Point(), [Goal(), Acceleration()], x0=[1, 1], goal=[2, 0]),
    ]
    return PotentialGame(GameSpec(agents, [Near(weight=0.5)], horizon=K, dt=0.5))


def test_unregistered_user_instances_are_accepted():
    """The issue's first complaint: a user's Feature instance used to be refused."""
    g = _game()
    assert [t.feature_type for t in g.terms] == [
        "offset",
        "acceleration",
        "goal",
        "acceleration",
        "near",
    ]
    assert g.params["target.a"].entries == ("target.a.x", "target.a.y")
    assert make_feature(Offset()) == Offset()
    assert make_pair_feature(Near()) == Near()
    assert make_dynamics(Point(gain=3.0)) == Point(gain=3.0)


def test_solution_matches_hand_computed_optimum():
    """Single integrators and quadratic terms: LM and IPOPT reach the linear
    least-squares optimum computed with numpy from the same (linear) residual."""
    g = _game()
    p = g.default_params(target__a=[1.5, -1.0])
    lm, ip = solve_lm(g, p), solve_ipopt(g, p)
    r = g.function("residual")
    J = np.asarray(ca.densify(g.function("jacobian")(np.zeros(g.n_u), p)))
    r0 = np.asarray(r(np.zeros(g.n_u), p)).ravel()
    u_star = np.linalg.lstsq(J, -r0, rcond=None)[0]  # residual is affine in u
    np.testing.assert_allclose(lm.controls, u_star, atol=1e-7)
    np.testing.assert_allclose(ip.controls, u_star, atol=1e-6)


def test_register_refuses_builtin_names_and_wrong_kinds(clean):
    with pytest.raises(SpecError, match="already the built-in feature Goal"):
        register_feature("goal", Offset)
    register_feature("goal", Offset, replace=True)
    assert FEATURES.table["goal"] is Offset
    FEATURES.unregister("goal")  # the built-in comes back
    assert FEATURES.table["goal"] is Goal
    with pytest.raises(SpecError, match="is a built-in feature"):
        FEATURES.unregister("goal")
    with pytest.raises(SpecError, match="subclass of epo_casadi.features.Feature"):
        register_feature("p", Point)
    with pytest.raises(SpecError, match="subclass of epo_casadi.dynamics.Dynamics"):
        register_dynamics("o", Offset)
    with pytest.raises(SpecError, match="subclass of epo_casadi.features.PairFeature"):
        register_pair_feature(Offset)
    with pytest.raises(SpecError, match="does not define steps, residual"):
        register_feature(NoResidual)
    with pytest.raises(SpecError, match="NoKind.kind must name the feature"):
        register_feature(NoKind)
    with pytest.raises(SpecError, match="expected 'package.module:Class'"):
        register_feature("x", "not an entry point")
    assert register_feature(Offset) is Offset and "offset" in FEATURES
    register_feature(Offset)  # the same class again is fine
    with pytest.raises(SpecError, match="already the registered feature Offset"):
        register_feature("offset", Near2Own)


def test_registered_and_module_class_names_resolve(clean):
    here = f"{__name__}:Offset"
    assert load_class(here) is Offset
    spec = {"type": here, "weight": 2.0, "target": [1.0, 2.0]}
    with pytest.raises(SpecError, match="not allowed") as e:  # a mapping imports nothing
        make_feature(spec)
    assert e.value.field == "feature.type" and f"--allow-import {__name__}" in e.value.message
    with allow_imports(__name__):
        f = make_feature(spec)
    assert f == Offset(weight=2.0, target=(1.0, 2.0))  # lists frozen to tuples
    assert f.to_dict() == {"type": here, "weight": 2.0, "target": [1.0, 2.0]}
    register_feature(Offset)
    assert make_feature("offset") == Offset()
    assert Offset().to_dict()["type"] == "offset"
    register_dynamics(Point)
    register_pair_feature("close", Near)
    assert make_dynamics({"type": "point", "gain": 2.0}) == Point(gain=2.0)
    assert Near().to_dict() == {"type": "close", "weight": 1.0}
    with pytest.raises(SpecError, match="unknown option") as e:
        make_feature({"type": "offset", "targett": 1})
    assert e.value.field == "feature"
    with pytest.raises(SpecError) as e:
        make_feature({"type": "nope"})
    assert e.value.field == "feature.type" and "package.module:Class" in e.value.message
    with pytest.raises(SpecError, match="ModuleNotFoundError") as e:
        with allow_imports("surely_missing_module"):
            make_dynamics({"type": "surely_missing_module:Thing"})
    assert e.value.field == "dynamics.type"


def test_game_file_round_trip_of_user_classes(clean):
    g = _game()
    d = dump_game(g.spec)
    assert d["agents"][0]["dynamics"] == {"type": f"{__name__}:Point", "gain": 2.0}
    assert d["pair_features"] == [{"type": f"{__name__}:Near", "weight": 0.5}]
    assert parse_game(d, allow_imports=[__name__]).spec == g.spec


def test_feature_parameter_blocks_are_checked():
    with pytest.raises(SpecError, match="reserved"):
        ParamSpec("goal", 2)
    with pytest.raises(SpecError, match="expected 2 finite numbers"):
        ParamSpec("t", 2, (1.0, float("nan")))
    with pytest.raises(SpecError, match="integer >= 1"):
        ParamSpec("t", 0)
    assert ParamSpec("t", 3, 1.5).default == (1.5, 1.5, 1.5)

    @dataclass(frozen=True)
    class Other(Offset):
        kind: ClassVar[str] = "other"

        def params(self):
            return (ParamSpec("target", 3),)

        def residual(self, ctx):
            return ctx.X[0, ctx.K] - ctx.refs["target"][2]

    @dataclass(frozen=True)
    class Broken(Offset):
        kind: ClassVar[str] = "broken"

        def residual(self, ctx):
            return ctx.X[0:2, ctx.K] - ca.SX.sym("z", 3)

    with pytest.raises(SpecError, match=r"residual\(\) fails .*Dimension mismatch") as e:
        AgentSpec("a", Point(), [Broken()], x0=[0, 0])
    assert e.value.field == "agents['a'].features[0]"
    with pytest.raises(SpecError, match="declared twice") as e:
        AgentSpec("a", Point(), [Offset(), Other()], x0=[0, 0])
    assert e.value.field == "agents['a'].features[1].params.target"
    # two features that declare the same block identically share it
    g = PotentialGame(
        GameSpec([AgentSpec("a", Point(), [Offset(), Offset(label="again")], x0=[0, 0])], horizon=2)
    )
    assert [b.name for b in g.params.blocks if b.group == "feature"] == ["target.a"]

    @dataclass(frozen=True)
    class ReadsLane(Offset):
        kind: ClassVar[str] = "reads_lane"

        def refs(self):
            return {"lane": 1}

    with pytest.raises(SpecError, match=r"unknown reference\(s\) \['lane'\].*params\(\)"):
        AgentSpec("a", Point(), [ReadsLane()], x0=[0, 0])


def test_generated_c_has_the_users_model(tmp_path):
    g = _game(K=3)
    src = Path(g.generate_c(str(tmp_path), ["rollout", "residual"], name="user_game"))
    text = src.read_text()
    assert "rollout" in text and "residual" in text


def test_import_arrows_point_one_way():
    """No two modules of the packages import each other, counting imports inside
    functions too (the circles lm <-> structured and train <-> evaluate are gone)."""
    mods: dict[str, Path] = {}
    for pkg in ("epo_casadi", "solvers", "scenarios", "learning"):
        for f in (ROOT / pkg).rglob("*.py"):
            name = ".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            mods[name] = f
    edges: dict[str, set[str]] = {}
    for name, f in mods.items():
        ispkg = f.name == "__init__.py"
        out = set()
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                out.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if ispkg else name.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                subs = {f"{mod}.{a.name}" for a in node.names} & set(mods)
                if len(subs) < len(node.names):  # a name defined in the module, not a submodule
                    out.add(mod)
                out.update(subs)
        edges[name] = {m for m in out if m in mods and m != name}
    both = sorted({tuple(sorted((a, b))) for a, bs in edges.items() for b in bs if a in edges[b]})
    assert both == []
    assert "solvers.lm" not in edges["solvers.structured"]
    assert "learning.train" in edges["learning.evaluate"]
    assert "learning.evaluate" not in edges["learning.train"]
