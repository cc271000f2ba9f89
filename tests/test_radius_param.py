"""Per-agent collision radii as parameters (``AgentSpec.radius_param``).

References computed another way: a game with the same radii as fixed numbers (rebuilt from
its spec), the collision energy's derivative with respect to a radius by hand from the
distances, and central finite differences in float64.
"""

from __future__ import annotations

import numpy as np
import pytest

from epo_casadi.errors import SpecError
from epo_casadi.features import Acceleration, Collision, Goal, TurnRate
from epo_casadi.game import AgentSpec, GameSpec, PotentialGame
from solvers.multimodal import min_clearance

K, DT, W_COL = 8, 0.25, 10.0


def _game(radii, param, n=3, every=1):
    """n unicycles heading into each other near the origin; radius of agent i ``radii[i]``."""
    agents = []
    for i in range(n):
        ang = 2 * np.pi * i / n
        x0 = [2.0 * np.cos(ang), 2.0 * np.sin(ang), 1.5, ang + np.pi]
        goal = [-3.0 * np.cos(ang), -3.0 * np.sin(ang)]
        agents.append(
            AgentSpec(
                f"a{i}",
                "unicycle",
                [Goal(), Acceleration(), TurnRate()],
                radius=float(radii[i]),
                radius_param=param[i],
                x0=x0,
                goal=goal,
            )
        )
    return PotentialGame(GameSpec(agents, [Collision(weight=W_COL, every=every)], horizon=K, dt=DT))


U = np.random.default_rng(0).normal(scale=0.2, size=3 * 2 * K)


def test_parameter_radius_equals_the_game_with_that_number():
    """Defaults give the fixed game's energy bit for bit; other radii in ``p`` give the
    energy, residual and gradient of a game built with those numbers."""
    base = [0.5, 0.7, 0.9]
    g_param = _game(base, [True, False, True])
    assert list(g_param.params.group("radius")) == [
        g_param.params["radius.a0"].start,
        g_param.params["radius.a2"].start,
    ]
    p = g_param.params.defaults()
    g_fixed = _game(base, [False] * 3)
    for fn in ("energy", "residual", "gradient"):
        a = np.asarray(g_param.function(fn)(U, p))
        b = np.asarray(g_fixed.function(fn)(U, g_fixed.params.defaults()))
        np.testing.assert_array_equal(a, b)
    new = [1.3, 0.7, 0.4]
    p2 = g_param.params.pack({"radius.a0": new[0], "radius.a2": new[2]})
    ref = _game(new, [False] * 3)
    E_ref = float(ref.function("energy")(U, ref.params.defaults()))
    assert E_ref > float(g_fixed.function("energy")(U, g_fixed.params.defaults())) + 1e-3
    for fn in ("energy", "residual", "gradient"):
        np.testing.assert_allclose(
            np.asarray(g_param.function(fn)(U, p2)),
            np.asarray(ref.function(fn)(U, ref.params.defaults())),
            rtol=1e-13,
            atol=1e-13,
        )
    np.testing.assert_array_equal(g_param.radii(p2), new)
    np.testing.assert_array_equal(g_param.radii(np.stack([p, p2])), [base, new])
    np.testing.assert_array_equal(g_fixed.radii(), base)


def test_energy_derivative_in_a_radius_by_hand_and_by_differences():
    """With the weighted residual ``w * max(0, r_0 + r_j - d)`` and ``E = 1/2 |r|^2``,
    dE/dr_0 = w^2 * sum over pairs (0, j) and steps of max(0, r_0 + r_j - d): the hinge's
    derivative from the rollout's distances, and a central difference."""
    g = _game([0.8, 0.8, 0.8], [True] * 3)
    p = g.params.defaults()
    x = np.asarray(g.function("rollout")(U, p)).ravel()
    pos = g.positions(x)  # (N, K+1, 2)
    expect = 0.0
    for j in (1, 2):
        d = np.linalg.norm(pos[0, 1:] - pos[j, 1:], axis=-1)
        expect += W_COL**2 * np.maximum(0.0, 1.6 - d).sum()
    assert expect > 0.1  # the hinge is active
    i = g.params["radius.a0"].start
    E = g.function("energy")

    def energy(r):
        q = p.copy()
        q[i] = r
        return float(E(U, q))

    h = 1e-6
    fd = (energy(0.8 + h) - energy(0.8 - h)) / (2 * h)
    # the smooth distance adds 1e-9 m^2 under the root; the hand value uses the exact norm
    assert fd == pytest.approx(expect, rel=1e-6)


def test_many_pairs_use_the_shared_pair_function():
    """From PAIR_FUNCTION_MIN pairs on the pair terms go through one CasADi function per
    signature; mixed fixed and parameter radii still equal the fixed game's."""
    n = 7  # 21 pairs > PotentialGame.PAIR_FUNCTION_MIN
    assert n * (n - 1) // 2 >= PotentialGame.PAIR_FUNCTION_MIN
    base = np.linspace(0.3, 0.9, n)
    mix = [bool(i % 2) for i in range(n)]
    g = _game(base, mix, n=n, every=2)
    new = base.copy()
    new[1::2] += 0.5
    p = g.params.pack({f"radius.a{i}": new[i] for i in range(1, n, 2)})
    ref = _game(new, [False] * n, n=n, every=2)
    u = np.random.default_rng(1).normal(scale=0.2, size=g.n_u)
    np.testing.assert_allclose(
        np.asarray(g.function("residual")(u, p)),
        np.asarray(ref.function("residual")(u, ref.params.defaults())),
        rtol=1e-13,
        atol=1e-13,
    )
    states = np.asarray(g.function("rollout")(u, p)).ravel()
    np.testing.assert_allclose(min_clearance(g, states, p), min_clearance(ref, states), rtol=1e-13)


def test_spec_round_trip_and_bad_values():
    g = _game([0.5, 0.5, 0.5], [True, False, False])
    d = g.spec.agents[0].to_dict()
    assert d["radius_param"] is True and "radius_param" not in g.spec.agents[1].to_dict()
    assert AgentSpec(**{**d, "features": list(g.spec.agents[0].features)}).radius_param
    with pytest.raises(SpecError, match="radius_param"):
        AgentSpec("a", "unicycle", [Goal()], radius_param="yes")


def test_game_file_key(tmp_path):
    from scenarios.gamefile import dump_game, parse_game

    g = _game([0.5, 0.6, 0.7], [False, True, False])
    data = dump_game(g.spec)
    g2 = parse_game(data).game
    assert g2.params.names == g.params.names and g2.spec.agents[1].radius_param
    data["agents"][1]["radius_param"] = 3
    with pytest.raises(SpecError, match=r"agents\[1\]\.radius_param"):
        parse_game(data)


def test_inspect_shows_the_radius_parameter():
    from epo_casadi.inspect import term_formula

    g = _game([0.5, 0.6, 0.7], [True, True, False])
    pair = {t.agents: t for t in g.terms if t.kind == "pair"}
    f01 = term_formula(g, pair[("a0", "a1")])["residual"]
    f02 = term_formula(g, pair[("a0", "a2")])["residual"]
    assert "radius.a0" in f01 and "radius.a1" in f01, f01
    assert "radius.a0" in f02 and "radius.a2" not in f02 and "0.7" in f02, f02
