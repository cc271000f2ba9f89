"""Symbolic core: rollouts, features, derivatives, layout and symmetry of the potential game."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

from epo_casadi import (
    Acceleration,
    AccelerationBound,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    Jerk,
    Path,
    PotentialGame,
    ReferenceVelocity,
    SpecError,
    TurnAcceleration,
    TurnRate,
    TurnRateBound,
    Velocity,
    VelocityBound,
)
from epo_casadi.dynamics import DoubleIntegrator, KinematicBicycle, Unicycle, make_dynamics

from .helpers import crossing_game

RNG = np.random.default_rng(0)


# ------------------------------------------------------------------ dynamics / rollout
def _hand_rollout(model: str, x0, U, dt, L=2.7):
    """Explicit Euler written out per model, independently of epo_casadi."""
    xs = [np.array(x0, float)]
    for a, b in U:
        x, y, s3, s4 = xs[-1]
        if model == "unicycle":  # s3 = v, s4 = theta
            xs.append(
                [x + s3 * math.cos(s4) * dt, y + s3 * math.sin(s4) * dt, s3 + a * dt, s4 + b * dt]
            )
        elif model == "double_integrator":  # s3 = vx, s4 = vy
            xs.append([x + s3 * dt, y + s4 * dt, s3 + a * dt, s4 + b * dt])
        else:  # bicycle
            xs.append(
                [
                    x + s3 * math.cos(s4) * dt,
                    y + s3 * math.sin(s4) * dt,
                    s3 + a * dt,
                    s4 + s3 * math.tan(b) / L * dt,
                ]
            )
        xs[-1] = np.array(xs[-1])
    return np.array(xs)


@pytest.mark.parametrize("model", ["unicycle", "double_integrator", "bicycle"])
def test_rollout_matches_hand_computed(model):
    K, dt = 7, 0.2
    x0 = [0.5, -1.0, 1.2, 0.3]
    U = RNG.normal(size=(K, 2)) * 0.4
    g = PotentialGame(GameSpec([AgentSpec("a", model, [Acceleration()], x0=x0)], horizon=K, dt=dt))
    x = np.asarray(g.function("rollout")(U.reshape(-1), g.default_params())).ravel()
    np.testing.assert_allclose(
        g.split_states(x)[0], _hand_rollout(model, x0, U, dt), rtol=1e-13, atol=1e-13
    )


def test_rollout_two_agents_layout_is_agent_major():
    K = 4
    spec = GameSpec(
        [
            AgentSpec("a", "unicycle", [Acceleration()], x0=[0, 0, 1, 0]),
            AgentSpec("b", "double_integrator", [Acceleration()], x0=[5, 5, 0, -1]),
        ],
        horizon=K,
        dt=0.1,
    )
    g = PotentialGame(spec)
    Ua, Ub = RNG.normal(size=(K, 2)), RNG.normal(size=(K, 2))
    u = np.concatenate([Ua.ravel(), Ub.ravel()])
    np.testing.assert_array_equal(g.split_controls(u)[1], Ub)
    np.testing.assert_array_equal(g.join_controls([Ua, Ub]), u)
    x = np.asarray(g.function("rollout")(u, g.default_params())).ravel()
    Xa, Xb = g.split_states(x)
    np.testing.assert_allclose(Xa, _hand_rollout("unicycle", [0, 0, 1, 0], Ua, 0.1), atol=1e-13)
    np.testing.assert_allclose(
        Xb, _hand_rollout("double_integrator", [5, 5, 0, -1], Ub, 0.1), atol=1e-13
    )
    assert g.positions(x).shape == (2, K + 1, 2)


def test_dynamics_function_is_named():
    f = Unicycle().f
    assert (
        f.name() == "f_unicycle" and f.name_in() == ["x", "u", "dt"] and f.name_out() == ["x_next"]
    )
    assert make_dynamics({"type": "bicycle", "wheelbase": 3.0}) == KinematicBicycle(wheelbase=3.0)
    with pytest.raises(SpecError, match="dynamics.type"):
        make_dynamics("boat")
    with pytest.raises(SpecError, match="wheelbase"):
        KinematicBicycle(wheelbase=-1.0)


# ------------------------------------------------------------------ feature values
def _single(feature, model="unicycle", K=6, dt=0.1, **agent):
    spec = GameSpec([AgentSpec("a", model, [feature], **agent)], horizon=K, dt=dt)
    return PotentialGame(spec)


def _states(g, u, p):
    return g.split_states(np.asarray(g.function("rollout")(u, p)).ravel())[0]


def _r(g, u, p):
    return np.asarray(g.function("residual")(u, p)).ravel()


def test_feature_values_match_numpy():
    K, dt = 6, 0.1
    x0 = [0.0, 0.0, 1.0, 0.2]
    U = RNG.normal(size=(K, 2)) * 0.5
    u = U.ravel()
    X = _hand_rollout("unicycle", x0, U, dt)
    cases = {
        Goal(weight=2.0): 2.0 * (X[K, :2] - np.array([3.0, 1.0])),
        Velocity(): X[1:, 2],
        Acceleration(): U[:, 0],
        Jerk(): np.diff(U[:, 0]) / dt,
        TurnRate(): U[:, 1],
        TurnAcceleration(): np.diff(U[:, 1]) / dt,
        ReferenceVelocity(): X[1:, 2] - 1.3,
        VelocityBound(lower=0.9, upper=1.05): np.maximum(0, X[1:, 2] - 1.05)
        + np.maximum(0, 0.9 - X[1:, 2]),
        AccelerationBound(upper=0.2): np.maximum(0, U[:, 0] - 0.2),
        TurnRateBound(lower=-0.1, upper=0.1): np.maximum(0, U[:, 1] - 0.1)
        + np.maximum(0, -0.1 - U[:, 1]),
    }
    for feat, expected in cases.items():
        g = _single(feat, K=K, dt=dt, x0=x0, goal=[3.0, 1.0], vref=1.3)
        np.testing.assert_allclose(
            _r(g, u, g.default_params()), expected, rtol=1e-12, atol=1e-12, err_msg=feat.kind
        )


def _dist_polyline(q, pts):
    best = np.inf
    for a, b in zip(pts[:-1], pts[1:], strict=False):
        t = np.clip(np.dot(q - a, b - a) / np.dot(b - a, b - a), 0, 1)
        best = min(best, np.linalg.norm(q - (a + t * (b - a))))
    return best


def test_path_distance_matches_numpy():
    pts = np.array([[-1.0, 0.5], [1.0, 0.5], [2.0, 2.0], [2.0, 4.0]])
    g = _single(Path(), K=8, x0=[0, 0, 1.5, 0.6], path=pts.tolist())
    u = RNG.normal(size=g.n_u) * 0.3
    p = g.default_params()
    X = _states(g, u, p)
    expected = [_dist_polyline(X[k, :2], pts) for k in range(1, 9)]
    np.testing.assert_allclose(_r(g, u, p), expected, atol=1e-7)  # smooth distance: eps = 1e-9 m^2


def test_collision_values_and_steps():
    K = 10
    spec = GameSpec(
        [
            AgentSpec("a", "double_integrator", [Acceleration()], radius=0.5, x0=[0, 0, 1, 0]),
            AgentSpec("b", "double_integrator", [Acceleration()], radius=0.3, x0=[1.5, 0.2, -1, 0]),
        ],
        [Collision(every=3, weight=2.0, margin=0.1)],
        horizon=K,
        dt=0.1,
    )
    g = PotentialGame(spec)
    u = np.zeros(g.n_u)
    p = g.default_params()
    col = [t for t in g.terms if t.kind == "pair"][0]
    assert col.steps == (3, 6, 9) and col.agents == ("a", "b")
    x = np.asarray(g.function("rollout")(u, p)).ravel()
    Xa, Xb = g.split_states(x)
    d = np.linalg.norm(Xa[[3, 6, 9], :2] - Xb[[3, 6, 9], :2], axis=1)
    expected = 2.0 * np.maximum(0, 0.8 + 0.1 - d)
    assert expected.max() > 0  # the term is active in this configuration
    np.testing.assert_allclose(_r(g, u, p)[col.rows], expected, atol=1e-8)


def test_turn_rate_needs_a_heading():
    with pytest.raises(SpecError, match=r"features\[0\].*no heading"):
        AgentSpec("a", "double_integrator", [TurnRate()])


def test_bicycle_turn_rate_is_v_tan_delta_over_L():
    g = _single(TurnRate(), model=KinematicBicycle(wheelbase=2.0), K=4, x0=[0, 0, 3.0, 0])
    u = RNG.normal(size=g.n_u) * 0.2
    p = g.default_params()
    X = _states(g, u, p)
    U = u.reshape(4, 2)
    np.testing.assert_allclose(_r(g, u, p), X[:4, 2] * np.tan(U[:, 1]) / 2.0, rtol=1e-12)


# ------------------------------------------------------------------ derivatives vs finite differences
def _fd_jac(f, u, h=1e-6):
    cols = []
    for j in range(u.size):
        e = np.zeros_like(u)
        e[j] = h
        cols.append((f(u + e) - f(u - e)) / (2 * h))
    return np.stack(cols, axis=1)


ALL_OWN = [
    (Goal(), "unicycle"),
    (Velocity(), "unicycle"),
    (Acceleration(), "unicycle"),
    (Jerk(), "unicycle"),
    (TurnRate(), "unicycle"),
    (TurnAcceleration(), "bicycle"),
    (ReferenceVelocity(), "double_integrator"),
    (Path(), "unicycle"),
    (VelocityBound(lower=0.2, upper=0.9), "unicycle"),
    (AccelerationBound(lower=-0.1, upper=0.1), "double_integrator"),
    (TurnRateBound(lower=-0.1, upper=0.1), "bicycle"),
    (Velocity(), "double_integrator"),
    (Acceleration(), "bicycle"),
]


@pytest.mark.parametrize("feature,model", ALL_OWN, ids=[f"{f.kind}-{m}" for f, m in ALL_OWN])
def test_feature_jacobian_matches_finite_differences(feature, model):
    g = _single(
        feature,
        model=model,
        K=6,
        x0=[0.1, -0.2, 1.0, 0.4],
        goal=[2, 1],
        vref=0.7,
        path=[[-1, -1], [1, 0.3], [3, 0.5]],
    )
    rng = np.random.default_rng(1)
    u = rng.normal(size=g.n_u) * 0.5
    p = g.default_params()
    res = lambda v: _r(g, v, p)  # noqa: E731
    r0 = res(u)
    J = np.asarray(g.function("jacobian")(u, p).full())
    J_fd = _fd_jac(res, u)
    if "bound" in feature.kind:  # the bound is active somewhere, and no entry sits on its kink
        assert np.any(r0 > 1e-3) and np.all((r0 == 0) | (r0 > 1e-4))
    np.testing.assert_allclose(J, J_fd, rtol=1e-6, atol=1e-7)


def test_collision_jacobian_and_hessian_match_finite_differences():
    g = crossing_game(N=2, K=8, dt=0.4)
    rng = np.random.default_rng(2)
    u = rng.normal(size=g.n_u) * 0.1
    p = g.default_params()
    e = np.asarray(g.function("term_energies")(u, p)).ravel()
    col = [t for t in g.terms if t.kind == "pair"][0]
    assert e[col.index] > 0  # collision is active: agents head at each other
    J = np.asarray(g.function("jacobian")(u, p).full())
    np.testing.assert_allclose(J, _fd_jac(lambda v: _r(g, v, p), u), rtol=1e-6, atol=1e-7)
    grad = lambda v: np.asarray(g.function("gradient")(v, p)).ravel()  # noqa: E731
    H = np.asarray(g.function("hessian")(u, p).full())
    np.testing.assert_allclose(H, _fd_jac(grad, u, h=1e-5), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(H, H.T, atol=1e-10)
    r = _r(g, u, p)
    np.testing.assert_allclose(grad(u), J.T @ r, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        g.function("gn_hessian")(u, p).full(), J.T @ J, rtol=1e-12, atol=1e-12
    )
    assert float(g.function("energy")(u, p)) == pytest.approx(0.5 * r @ r, rel=1e-13)
    rr, Jd = g.function("lm_terms")(u, p)
    np.testing.assert_allclose(np.asarray(Jd), J, atol=0)
    np.testing.assert_allclose(np.asarray(rr).ravel(), r, atol=0)


def test_traj_functions_agree_with_single_shooting():
    g = crossing_game(N=3, K=6)
    u = RNG.normal(size=g.n_u) * 0.2
    p = g.default_params()
    x = np.asarray(g.function("rollout")(u, p)).ravel()
    np.testing.assert_allclose(
        np.asarray(g.function("traj_residual")(x, u, p)).ravel(), _r(g, u, p), atol=1e-14
    )
    np.testing.assert_allclose(
        np.asarray(g.function("traj_agent_costs")(x, u, p)).ravel(),
        np.asarray(g.function("agent_costs")(u, p)).ravel(),
        atol=1e-12,
    )


# ------------------------------------------------------------------ the game structure
def test_pair_feature_is_symmetric():
    """d(x_i, x_j) == d(x_j, x_i): swapping the agents' order gives the same pair energy."""
    a = AgentSpec("a", "unicycle", [Acceleration()], radius=0.4, x0=[0, 0, 1, 0])
    b = AgentSpec("b", "unicycle", [Acceleration()], radius=0.3, x0=[1.2, 0.1, 1, math.pi])
    g1 = PotentialGame(GameSpec([a, b], [Collision(weight=3.0)], horizon=8, dt=0.1))
    g2 = PotentialGame(GameSpec([b, a], [Collision(weight=3.0)], horizon=8, dt=0.1))
    Ua, Ub = RNG.normal(size=(8, 2)) * 0.3, RNG.normal(size=(8, 2)) * 0.3
    e1 = np.asarray(
        g1.function("term_energies")(g1.join_controls([Ua, Ub]), g1.default_params())
    ).ravel()
    e2 = np.asarray(
        g2.function("term_energies")(g2.join_controls([Ub, Ua]), g2.default_params())
    ).ravel()
    assert e1[-1] > 0
    assert e1[-1] == pytest.approx(e2[-1], rel=1e-13)


def test_agent_costs_and_pseudo_gradient_follow_theorem_1():
    """C_i = own_i + sum_j pair_ij, and dC_i/du_i = dE/du_i (potential game)."""
    g = crossing_game(N=3, K=6)
    u = RNG.normal(size=g.n_u) * 0.2
    p = g.default_params()
    e = np.asarray(g.function("term_energies")(u, p)).ravel()
    C_hand = [sum(e[t.index] for t in g.terms if name in t.agents) for name in g.agent_names]
    np.testing.assert_allclose(
        np.asarray(g.function("agent_costs")(u, p)).ravel(), C_hand, rtol=1e-13
    )
    assert sum(e) == pytest.approx(float(g.function("energy")(u, p)), rel=1e-13)
    np.testing.assert_allclose(
        g.function("pseudo_gradient")(u, p), g.function("gradient")(u, p), atol=1e-12
    )


def test_param_layout_names_pack_and_groups():
    g = crossing_game(N=2, K=5)
    L = g.params
    assert L.size == g.n_p == len(L.names)
    assert [b.name for b in L.blocks][:4] == ["x0.a0", "x0.a1", "goal.a0", "goal.a1"]
    assert "w.a0-a1.collision" in L and L["w.a0.goal"].default == (3.0,)
    p = L.pack({"goal.a1": [4.0, 5.0], "w.a0-a1.collision": 7.0})
    assert list(p[L["goal.a1"].slice]) == [4.0, 5.0] and p[L["w.a0-a1.collision"].start] == 7.0
    assert set(L.group("w_pair")) == {L["w.a0-a1.collision"].start}
    assert len(L.group("w_own")) == 14 and len(L.group("x0")) == 8
    np.testing.assert_array_equal(L.unpack(np.stack([p, p]))["goal.a1"], [[4, 5], [4, 5]])
    np.testing.assert_array_equal(g.default_params(goal__a1=[4, 5])[L["goal.a1"].slice], [4, 5])
    with pytest.raises(SpecError, match="goal.a1"):
        L.pack({"goal.a1": [1.0]})
    with pytest.raises(SpecError, match="unknown parameter block"):
        L.pack({"goal.zz": [1.0, 2.0]})
    with pytest.raises(SpecError, match="finite"):
        L.pack({"x0.a0": [np.nan, 0, 0, 0]})


def test_terms_cover_the_residual_exactly():
    g = crossing_game(N=3, K=7)
    rows = sorted((t.rows.start, t.rows.stop) for t in g.terms)
    assert rows[0][0] == 0 and rows[-1][1] == g.n_r
    assert all(a[1] == b[0] for a, b in zip(rows[:-1], rows[1:], strict=False))
    assert sum(t.kind == "pair" for t in g.terms) == 3
    for t in g.terms:
        assert t.size == len(t.steps) * (2 if t.feature_type == "goal" else 1)


@pytest.mark.parametrize(
    "make,field",
    [
        (lambda: AgentSpec("a", "unicycle", [Goal()], radius=-1.0), "radius"),
        (lambda: AgentSpec("a", "unicycle", [Goal()], x0=[0, 0, 1]), "x0"),
        (lambda: AgentSpec("a", "unicycle", [Goal()], goal=[0, math.nan]), "goal"),
        (lambda: AgentSpec("a", "unicycle", [{"type": "speed"}]), "features[0].type"),
        (lambda: AgentSpec("a", "unicycle", [{"type": "goal", "wieght": 1}]), "features[0]"),
        (lambda: AgentSpec("a", "unicycle", [Goal(), Goal()]), "features[1]"),
        (lambda: AgentSpec("a", "unicycle", [Path()]), "path"),
        (lambda: AgentSpec("a", "unicycle", [VelocityBound(lower=2, upper=1)]), "velocity_bound"),
        (lambda: AgentSpec("a.b", "unicycle", []), "agents.name"),
        (lambda: GameSpec([], horizon=5), "agents"),
        (lambda: GameSpec([AgentSpec("a"), AgentSpec("a")]), "agents.name"),
        (lambda: GameSpec([AgentSpec("a")], horizon=0), "horizon"),
        (lambda: GameSpec([AgentSpec("a")], dt=-0.1), "dt"),
        (lambda: GameSpec([AgentSpec("a")], [Collision(every=0)]), "collision.every"),
        (lambda: GameSpec([AgentSpec("a")], [Collision(margin=-0.1)]), "collision.margin"),
        (
            lambda: GameSpec(
                [AgentSpec("a"), AgentSpec("b")], [{"type": "collision", "pairs": [["a", "c"]]}]
            ),
            "pairs",
        ),
    ],
)
def test_bad_specs_name_the_field(make, field):
    with pytest.raises(SpecError) as ei:
        make()
    assert field in ei.value.field or field in str(ei.value)


def test_check_inputs_shapes_and_nan():
    g = crossing_game(N=2, K=5)
    u, p = g.zero_controls(), g.default_params()
    U, P = g.check_inputs(u, np.stack([p, p, p]))
    assert U.shape == (3, g.n_u) and P.shape == (3, g.n_p)
    with pytest.raises(SpecError, match="n_u"):
        g.check_inputs(u[:-1], p)
    bad = p.copy()
    bad[g.params["goal.a1"].start] = np.inf
    with pytest.raises(SpecError, match="goal.a1.x"):
        g.check_inputs(u, bad)
    with pytest.raises(SpecError, match="batch sizes"):
        g.check_inputs(np.zeros((2, g.n_u)), np.stack([p, p, p]))


def test_function_names_and_signatures():
    g = crossing_game(N=2, K=4)
    for name in PotentialGame.FUNCTIONS:
        f = g.function(name)
        assert f.name() == name
        assert f.name_in()[-2:] == ["u", "p"]
    with pytest.raises(SpecError, match="unknown function"):
        g.function("nope")


def test_spec_round_trips_through_dict():
    g = crossing_game(N=2, K=5)
    d = g.spec.to_dict()
    agents = [AgentSpec(**{k: v for k, v in a.items()}) for a in d["agents"]]
    spec2 = GameSpec(agents, d["pair_features"], horizon=d["horizon"], dt=d["dt"])
    g2 = PotentialGame(spec2)
    u = RNG.normal(size=g.n_u) * 0.3
    assert float(g2.function("energy")(u, g2.default_params())) == pytest.approx(
        float(g.function("energy")(u, g.default_params())), rel=1e-13
    )


def test_double_integrator_and_bicycle_agents_mix():
    spec = GameSpec(
        [
            AgentSpec(
                "car",
                KinematicBicycle(wheelbase=2.5),
                [Goal(), Acceleration(), TurnRate()],
                radius=1.0,
                x0=[0, 0, 5, 0],
                goal=[20, 0],
            ),
            AgentSpec(
                "ped",
                DoubleIntegrator(),
                [Goal(), Acceleration()],
                radius=0.3,
                x0=[10, -3, 0, 1],
                goal=[10, 3],
            ),
        ],
        [Collision()],
        horizon=10,
        dt=0.2,
    )
    g = PotentialGame(spec)
    assert g.nx == [4, 4] and g.n_u == 40
    assert "PotentialGame(N=2" in repr(g)


def test_generate_c_writes_compilable_source(tmp_path):
    """The exported C compiles with the system compiler and matches the interpreted graph."""
    import shutil
    import subprocess

    import casadi as ca

    g = crossing_game(N=2, K=5)
    src = g.generate_c(str(tmp_path), ["residual", "energy"], name="crossing")
    text = pathlib.Path(src).read_text()
    assert "residual" in text and "energy" in text
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler")
    lib = tmp_path / "crossing.so"
    subprocess.run([cc, "-shared", "-fPIC", "-O1", src, "-o", str(lib), "-lm"], check=True)
    f = ca.external("energy", str(lib))
    u = RNG.normal(size=g.n_u) * 0.3
    p = g.default_params()
    assert float(f(u, p)) == pytest.approx(float(g.function("energy")(u, p)), rel=1e-12)


def test_check_number_and_bool_name_the_field():
    from epo_casadi.errors import check_bool, check_number

    assert check_number("x", 0.5, lo=0, lo_open=True) == 0.5
    assert check_number("n", 3, lo=0, hi=12, integer=True) == 3
    for bad, kw, msg in [
        (0.0, {"lo": 0, "lo_open": True}, "> 0"),
        (-1, {"lo": 0}, ">= 0"),
        (2.5, {"integer": True}, "an integer"),
        (13, {"lo": 0, "hi": 12, "integer": True}, r"in \[0, 12\]"),
        (True, {}, "finite number"),
        (math.nan, {}, "finite number"),
    ]:
        with pytest.raises(SpecError, match=msg) as ei:
            check_number("opt.field", bad, **kw)
        assert ei.value.field == "opt.field"
    assert check_bool("b", False) is False
    with pytest.raises(SpecError, match="True or False"):
        check_bool("b", 1)


def test_specs_are_frozen_and_bounds_need_lower_below_upper():
    import dataclasses

    from epo_casadi import VelocityBound

    a = AgentSpec("a", "unicycle", [Acceleration()], x0=[0, 0, 1, 0])
    spec = GameSpec([a], horizon=3, dt=0.1)
    for obj, name in ((a, "radius"), (spec, "horizon")):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, name, getattr(obj, name))
    for lo, hi in ((1.0, 1.0), (2.0, 1.0)):  # lower == upper is an empty band too
        with pytest.raises(SpecError, match="lower < upper"):
            VelocityBound(lower=lo, upper=hi)
    assert VelocityBound(lower=1.0, upper=np.nextafter(1.0, 2.0)).upper > 1.0
