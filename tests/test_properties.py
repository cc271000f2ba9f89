"""Properties checked on generated inputs (hypothesis): game-file round trips, the symmetry
of pair terms, the parameter layout.

Runs are small (``max_examples`` 20-25, derandomized, no deadline) to keep the suite fast;
the metric invariances are in tests/test_metrics.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from epo_casadi import (
    Acceleration,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    Jerk,
    PotentialGame,
    ReferenceVelocity,
    TurnRate,
    Velocity,
    VelocityBound,
)
from scenarios.gamefile import dump_game, parse_game

from .helpers import crossing_game

SETTINGS = settings(max_examples=20, deadline=None, derandomize=True, database=None)

finite = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False)
positive = st.floats(0.05, 10.0, allow_nan=False, allow_infinity=False)

# features that every dynamics accepts, and those that need a heading
COMMON = {
    "goal": lambda w: Goal(weight=w),
    "velocity": lambda w: Velocity(weight=w),
    "acceleration": lambda w: Acceleration(weight=w),
    "velocity_bound": lambda w: VelocityBound(lower=0.0, upper=2.0, weight=w),
    "reference_velocity": lambda w: ReferenceVelocity(weight=w),
}
HEADING = {"turn_rate": lambda w: TurnRate(weight=w)}
NX = {"unicycle": 4, "double_integrator": 4, "bicycle": 4}


@st.composite
def agents(draw, name):
    dyn = draw(st.sampled_from(["unicycle", "double_integrator", "bicycle"]))
    pool = dict(
        COMMON, **(HEADING if dyn != "double_integrator" else {"jerk": lambda w: Jerk(weight=w)})
    )
    kinds = draw(st.lists(st.sampled_from(sorted(pool)), min_size=1, max_size=4, unique=True))
    feats = [pool[k](draw(positive)) for k in kinds]
    return AgentSpec(
        name,
        {"type": "bicycle", "wheelbase": draw(st.floats(1.0, 3.0))} if dyn == "bicycle" else dyn,
        feats,
        radius=draw(st.floats(0.0, 1.0)),
        x0=draw(st.lists(finite, min_size=NX[dyn], max_size=NX[dyn])),
        goal=draw(st.lists(finite, min_size=2, max_size=2)),
        vref=draw(positive),
    )


@st.composite
def specs(draw):
    n = draw(st.integers(1, 3))
    ags = [draw(agents(f"a{i}")) for i in range(n)]
    K = draw(st.integers(2, 6))
    pairs = [Collision(weight=draw(positive), every=draw(st.integers(1, K)))] if n > 1 else []
    return GameSpec(ags, pairs, horizon=K, dt=draw(st.floats(0.01, 0.5)))


@SETTINGS
@given(specs(), st.sampled_from(["yaml", "json"]))
def test_game_file_round_trip(spec, fmt):
    """dump -> text -> parse gives the same spec, parameters and energy."""
    data = dump_game(spec)
    if fmt == "json":
        text = json.dumps(data, allow_nan=False)
        back = json.loads(text)
    else:
        back = yaml.safe_load(yaml.safe_dump(data, sort_keys=False))
    gf = parse_game(back)
    assert gf.spec == spec
    game = PotentialGame(spec)
    np.testing.assert_array_equal(gf.params, game.default_params())
    assert dump_game(gf.spec) == data  # a fixed point
    u = np.random.default_rng(0).normal(scale=0.3, size=game.n_u)
    e1 = float(game.function("energy")(u, game.default_params()))
    e2 = float(gf.game.function("energy")(u, gf.params))
    assert e1 == e2


# ----------------------------------------------------------------------------- pair symmetry
def _pair_games():
    feats = [Acceleration(), TurnRate()]
    a = AgentSpec("a", "unicycle", feats, radius=0.4, x0=[0, 0, 1, 0])
    b = AgentSpec("b", "unicycle", feats, radius=0.7, x0=[1, 0, 1, 3.1])
    mk = lambda ags: PotentialGame(GameSpec(ags, [Collision(weight=2.0)], horizon=5, dt=0.2))  # noqa: E731
    return mk([a, b]), mk([b, a])


PAIR_GAMES = None


@SETTINGS
@given(
    st.lists(finite, min_size=4, max_size=4),
    st.lists(finite, min_size=4, max_size=4),
    st.integers(0, 2**31 - 1),
    positive,
)
def test_pair_terms_are_symmetric_in_the_agents(xa, xb, seed, w):
    """Swapping the agents' order (and their controls, initial states) leaves the pair
    energy, the potential and each agent's cost unchanged."""
    global PAIR_GAMES
    if PAIR_GAMES is None:
        PAIR_GAMES = _pair_games()
    g1, g2 = PAIR_GAMES
    rng = np.random.default_rng(seed)
    Ua, Ub = rng.normal(scale=0.5, size=(2, g1.K, 2))
    p1 = g1.params.pack({"x0.a": xa, "x0.b": xb, "w.a-b.collision": w})
    p2 = g2.params.pack({"x0.a": xa, "x0.b": xb, "w.b-a.collision": w})
    u1, u2 = g1.join_controls([Ua, Ub]), g2.join_controls([Ub, Ua])
    e1 = np.asarray(g1.function("term_energies")(u1, p1)).ravel()
    e2 = np.asarray(g2.function("term_energies")(u2, p2)).ravel()
    pair1 = [t.index for t in g1.terms if t.kind == "pair"]
    pair2 = [t.index for t in g2.terms if t.kind == "pair"]
    assert e1[pair1] == pytest.approx(e2[pair2], rel=1e-12, abs=1e-300)
    assert float(g1.function("energy")(u1, p1)) == pytest.approx(
        float(g2.function("energy")(u2, p2)), rel=1e-12
    )
    c1 = np.asarray(g1.function("agent_costs")(u1, p1)).ravel()
    c2 = np.asarray(g2.function("agent_costs")(u2, p2)).ravel()
    np.testing.assert_allclose(c1, c2[::-1], rtol=1e-12)


# ----------------------------------------------------------------------------- layout
LAYOUT_GAMES = {}


def _layout_game(N, K):
    if (N, K) not in LAYOUT_GAMES:
        LAYOUT_GAMES[N, K] = crossing_game(N=N, K=K)
    return LAYOUT_GAMES[N, K]


@SETTINGS
@given(st.integers(2, 3), st.integers(2, 4), st.data())
def test_parameter_layout_pack_unpack(N, K, data):
    g = _layout_game(N, K)
    L = g.params
    # blocks tile 0..n_p without gaps or overlaps, and the groups partition them
    starts = [b.start for b in L.blocks]
    assert starts == sorted(starts) and starts[0] == 0
    assert all(a.start + a.size == b.start for a, b in zip(L.blocks, L.blocks[1:], strict=False))
    assert L.blocks[-1].start + L.blocks[-1].size == L.size == g.n_p == len(L.names)
    groups = np.concatenate([L.group(gr) for gr in L.GROUPS])
    assert sorted(groups.tolist()) == list(range(L.size))
    # pack then unpack returns what was packed; other blocks keep their defaults
    chosen = data.draw(st.lists(st.sampled_from([b.name for b in L.blocks]), unique=True))
    values = {
        n: data.draw(st.lists(finite, min_size=L[n].size, max_size=L[n].size)) for n in chosen
    }
    p = L.pack(values)
    back = L.unpack(p)
    for b in L.blocks:
        expect = values[b.name] if b.name in values else b.default
        np.testing.assert_array_equal(back[b.name], np.asarray(expect, dtype=float))
    # batched unpack is the per-row unpack
    P = np.stack([p, L.defaults()])
    for name, v in L.unpack(P).items():
        np.testing.assert_array_equal(v[0], back[name])
        np.testing.assert_array_equal(v[1], L[name].default)
