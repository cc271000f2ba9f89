"""The worked example of docs/extending.md, from a module outside the package, and
coupled dynamics (a joint linear model over two agents: a textbook LQ game).

The module (a lane-keeping feature with its own ``lane`` parameter block and an RK4
bicycle) is taken from the page itself, written to a temporary directory and imported
from there. References are computed another way: the RK4 rollout against the exact
circular arc and the exact straight-line motion, the lane term's energy by hand from the
rolled-out states, LM against IPOPT, the layer's gradient against central differences.
"""

from __future__ import annotations

import importlib
import re
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
import torch
import yaml

from epo_casadi import (
    Acceleration,
    AgentSpec,
    Collision,
    Coupling,
    GameSpec,
    Goal,
    PotentialGame,
    SpecError,
    TurnRate,
    Velocity,
    register_dynamics,
    register_feature,
)
from epo_casadi import inspect as ins
from epo_casadi.registry import DYNAMICS, FEATURES
from scenarios.gamefile import apply_settings, dump_game, load_game, parse_game, save_game
from solvers import nash_certificate, solve_ilq, solve_ipopt, solve_lm
from solvers.result import Equilibrium, Verdict

from .helpers import LinearJoint

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"
MODULE = "my_lanes"


def _example_source() -> str:
    text = DOC.read_text(encoding="utf-8")
    m = re.search(r"<!-- extending-example: my_lanes.py -->\s*```python\n(.*?)```", text, re.S)
    assert m, "docs/extending.md lost its example module"
    return m.group(1)


@pytest.fixture(scope="module")
def ext(tmp_path_factory):
    d = tmp_path_factory.mktemp("user_code")
    (d / f"{MODULE}.py").write_text(_example_source(), encoding="utf-8")
    sys.path.insert(0, str(d))
    try:
        mod = importlib.import_module(MODULE)
        assert Path(mod.__file__).parent == d  # really from outside the package
        yield mod
    finally:
        sys.path.remove(str(d))
        sys.modules.pop(MODULE, None)


def _spec(ext, K=15, lane=1.0):
    agents = [
        AgentSpec(
            "car",
            ext.RK4Bicycle(wheelbase=2.5),
            [
                Goal(weight=1.0),
                ext.LaneKeeping(lane_y=lane, weight=2.0),
                Acceleration(),
                TurnRate(),
            ],
            radius=0.5,
            x0=[0.0, 0.0, 2.0, 0.0],
            goal=[4.0, 0.0],
        ),
        AgentSpec(
            "ped",
            "unicycle",
            [Goal(weight=2.0), Acceleration(), TurnRate()],
            radius=0.3,
            x0=[3.0, -2.0, 0.5, 1.57],
            goal=[3.0, 2.0],
        ),
    ]
    return GameSpec(agents, [Collision(weight=5.0)], horizon=K, dt=0.1)


@pytest.fixture(scope="module")
def game(ext):
    return PotentialGame(_spec(ext))


def test_rk4_bicycle_matches_exact_motion(ext):
    """Constant steering at constant speed is a circle; constant acceleration on a
    straight line is a parabola (RK4 is exact there)."""
    dyn = ext.RK4Bicycle(wheelbase=2.5, substeps=2)
    f = dyn.f
    L, v, delta, dt = 2.5, 2.0, 0.2, 0.1
    x = np.array([1.0, -1.0, v, 0.3])
    for _ in range(20):
        x = np.asarray(f(x, [0.0, delta], dt)).ravel()
    t, w = 20 * dt, v * np.tan(delta) / L
    R = L / np.tan(delta)
    th = 0.3 + w * t
    exact = [1.0 + R * (np.sin(th) - np.sin(0.3)), -1.0 - R * (np.cos(th) - np.cos(0.3)), v, th]
    assert np.max(np.abs(x - exact)) < 1e-7
    y = np.asarray(f([0.0, 0.0, 1.0, 0.0], [0.5, 0.0], 0.4)).ravel()
    np.testing.assert_allclose(y, [0.4 + 0.25 * 0.16, 0.0, 1.2, 0.0], atol=1e-14)
    with pytest.raises(SpecError, match="substeps"):
        ext.RK4Bicycle(substeps=0)


def test_parameter_block_and_lane_energy(ext, game):
    b = game.params["lane.car"]
    assert (b.group, b.size, b.default, b.entries) == ("feature", 1, (1.0,), ("lane.car",))
    # after the references, before the weights
    groups = [blk.group for blk in game.params.blocks]
    assert groups.index("feature") > groups.index("goal")
    assert groups.index("feature") < groups.index("w_own")
    rng = np.random.default_rng(0)
    u = 0.3 * rng.standard_normal(game.n_u)
    p = game.default_params(lane__car=0.7)
    x = np.asarray(game.function("rollout")(u, p)).ravel()
    y = game.split_states(x)[0][1:, 1]
    e = np.asarray(game.function("term_energies")(u, p)).ravel()
    t = next(t for t in game.terms if t.feature == "lane_keeping")
    assert t.feature_type == "lane_keeping" and t.steps == tuple(range(1, 16))
    assert e[t.index] == pytest.approx(0.5 * 2.0**2 * np.sum((y - 0.7) ** 2), rel=1e-12)


def test_solve_lm_ipopt_ilq_certify_and_inspect(ext, game):
    p = game.default_params()
    lm = solve_lm(game, p)
    ip = solve_ipopt(game, p)
    assert lm.status.value == "converged" and ip.status.value == "converged"
    assert float(lm.energy) == pytest.approx(float(ip.energy), rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(lm.controls, ip.controls, atol=1e-4)
    il = solve_ilq(game, p)
    assert np.all(np.isfinite(il.controls)) and il.status.value in ("converged", "max_iter")
    cert = nash_certificate(game, p, lm.controls)
    assert cert.ok, cert.reasons
    # the lane moves the car: a lane at +1 vs at -1 pulls its path up vs down
    up = solve_lm(game, game.default_params(lane__car=1.0))
    down = solve_lm(game, game.default_params(lane__car=-1.0))
    y_up = game.split_states(up.states)[0][1:, 1]
    y_down = game.split_states(down.states)[0][1:, 1]
    assert y_up.mean() > 0.1 and y_down.mean() < -0.1
    # inspection reads the user's term and model
    rows = ins.term_rows(game)
    assert any(r["feature"] == "lane_keeping" and r["agents"] == ["car"] for r in rows) or any(
        r["feature"] == "lane_keeping" for r in rows
    )
    e = {r["feature"]: r for r in ins.energy_breakdown(game, p, lm.controls) if "car" in str(r)}
    assert "lane_keeping" in e
    t = next(t for t in game.terms if t.feature == "lane_keeping")
    formula = ins.term_formula(game, t)
    assert "lane.car" in formula["formula"] or "lane.car" in formula["residual"]
    dyn = next(d for d in ins.dynamics_summary(game) if d["agents"] == ["car"])
    assert dyn["model"] == "rk4_bicycle" and dyn["integrator"] == "RK4"


def test_train_one_step_predicting_the_lane(ext, game):
    from learning.layer import GameLayer
    from solvers import LMOptions

    torch.manual_seed(0)
    layer = GameLayer(game, LMOptions.paper())
    head = torch.nn.Linear(1, 1, dtype=torch.float64)
    feats = torch.ones(3, 1, dtype=torch.float64)
    target = torch.full((3,), 0.4, dtype=torch.float64)

    def loss_of(lane):
        p = layer.assemble_params(blocks={"lane.car": lane})
        y = layer(p).states[:, game.xoff[0] : game.xoff[1]].reshape(3, game.K + 1, 4)[:, 1:, 1]
        return (y.mean(dim=1) - target).square().mean()

    loss = loss_of(head(feats))
    loss.backward()
    g = head.bias.grad.item()
    # central difference of the loss in the predicted lane (all three problems move)
    h = 1e-6
    with torch.no_grad():
        lane0 = head(feats)
        fd = (loss_of(lane0 + h) - loss_of(lane0 - h)).item() / (2 * h)
    assert g == pytest.approx(fd, rel=1e-6, abs=1e-10)
    assert abs(g) > 1e-6
    opt = torch.optim.SGD(head.parameters(), lr=0.5)
    opt.step()
    assert loss_of(head(feats)).item() < loss.item()


def test_sc_rollout_runs_the_users_dynamics(ext, game):
    """The bridge the SC baseline uses rolls out the RK4 model like the game does."""
    from learning.bridge import GameRollout

    ro = GameRollout(game)
    rng = np.random.default_rng(1)
    x0 = torch.as_tensor(rng.standard_normal((2, game.N, 4)))
    U = torch.as_tensor(0.2 * rng.standard_normal((2, game.N, game.K, 2)))
    X = ro.states(x0, U)
    for b in range(2):
        p = game.params.defaults()
        p[game.params.group("x0")] = x0[b].reshape(-1).numpy()
        ref = np.asarray(game.function("rollout")(U[b].reshape(-1).numpy(), p)).ravel()
        np.testing.assert_allclose(X[b].reshape(-1).numpy(), ref, rtol=0, atol=1e-13)
    # the built-in unicycle against the Euler recursion written out in numpy (the
    # equations of the torch copy the SC baseline used before)
    uni = PotentialGame(
        GameSpec([AgentSpec(n, "unicycle", [Acceleration()]) for n in "ab"], horizon=6, dt=0.1)
    )
    xu = rng.standard_normal((3, 2, 4))
    Uu = rng.standard_normal((3, 2, 6, 2))
    got = GameRollout(uni).states(torch.as_tensor(xu), torch.as_tensor(Uu)).numpy()
    x = xu.copy()
    for k in range(6):
        px, py, v, th = np.moveaxis(x, -1, 0)
        a, w = Uu[..., k, 0], Uu[..., k, 1]
        x = np.stack(
            [px + v * np.cos(th) * 0.1, py + v * np.sin(th) * 0.1, v + a * 0.1, th + w * 0.1], -1
        )
        np.testing.assert_allclose(got[:, :, k + 1], x, rtol=0, atol=1e-12)
    xg = x0[:1].clone().requires_grad_()
    Ug = U[:1, :, :4].clone()  # a short horizon keeps gradcheck cheap
    g4 = PotentialGame(_spec(ext, K=4))
    ro4 = GameRollout(g4)
    assert torch.autograd.gradcheck(
        lambda a, b: ro4.states(a, b), (xg, Ug.requires_grad_()), eps=1e-6, atol=1e-7
    )


def test_game_file_with_module_class_names(ext, tmp_path, game):
    text = f"""
horizon: 15
dt: 0.1
agents:
  - name: car
    dynamics: {{type: "{MODULE}:RK4Bicycle", wheelbase: 2.5, substeps: 2}}
    radius: 0.5
    x0: [0.0, 0.0, 2.0, 0.0]
    goal: [4.0, 0.0]
    features:
      - {{type: goal, weight: 1.0}}
      - {{type: "{MODULE}:LaneKeeping", lane_y: 1.0, weight: 2.0}}
      - acceleration
      - turn_rate
  - name: ped
    dynamics: unicycle
    radius: 0.3
    x0: [3.0, -2.0, 0.5, 1.57]
    goal: [3.0, 2.0]
    features: [{{type: goal, weight: 2.0}}, acceleration, turn_rate]
pair_features:
  - {{type: collision, weight: 5.0}}
"""
    path = tmp_path / "lanes.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(SpecError, match="not allowed") as e:  # imports nothing unasked
        load_game(path)
    assert e.value.field == "agents[0].dynamics.type"
    gf = load_game(path, allow_imports=[MODULE])
    assert gf.spec == _spec(ext)  # the same game as the Python API's
    res = solve_lm(gf.game, gf.params)
    ref = solve_lm(game, game.default_params())
    np.testing.assert_allclose(res.controls, ref.controls, atol=1e-12)
    # --set moves the feature's own block
    p = apply_settings(gf.game, gf.params, ["lane.car=-0.5"])
    assert p[gf.game.params["lane.car"].start] == -0.5
    # round trip: dumped by module:Class, loads to the same spec (YAML and JSON)
    d = dump_game(gf)
    assert d["agents"][0]["dynamics"] == {
        "type": f"{MODULE}:RK4Bicycle",
        "wheelbase": 2.5,
        "substeps": 2,
    }
    assert d["agents"][0]["features"][1] == {
        "type": f"{MODULE}:LaneKeeping",
        "weight": 2.0,
        "lane_y": 1.0,
    }
    assert parse_game(yaml.safe_load(yaml.safe_dump(d)), allow_imports=MODULE).spec == gf.spec
    assert load_game(save_game(gf, tmp_path / "again.json"), [MODULE]).spec == gf.spec


def test_registered_names_in_game_files(ext, tmp_path):
    try:
        register_feature(ext.LaneKeeping)
        register_dynamics("rk4_bicycle", ext.RK4Bicycle)
        data = dump_game(_spec(ext))  # now written by the short names
        assert data["agents"][0]["dynamics"]["type"] == "rk4_bicycle"
        assert data["agents"][0]["features"][1]["type"] == "lane_keeping"
        assert parse_game(data).spec == _spec(ext)
    finally:
        FEATURES.unregister("lane_keeping")
        DYNAMICS.unregister("rk4_bicycle")
    assert "lane_keeping" not in FEATURES


def test_game_file_errors_name_the_field(ext, tmp_path, monkeypatch):
    base = {
        "horizon": 5,
        "dt": 0.1,
        "agents": [
            {
                "name": "car",
                "dynamics": "unicycle",
                "x0": [0, 0, 1, 0],
                "features": ["acceleration", {"type": f"{MODULE}:LaneKeeping"}],
            }
        ],
    }
    monkeypatch.setenv("EPO_ALLOW_IMPORT", f"{MODULE},no_such_pkg")  # no_such_pkg.lanes too
    bad = {**base}
    bad["agents"] = [{**base["agents"][0], "features": [{"type": "no_such_pkg.lanes:Lane"}]}]
    with pytest.raises(SpecError) as e:
        parse_game(bad)
    assert e.value.field == "agents[0].features[0].type"
    assert "cannot import 'no_such_pkg.lanes'" in e.value.message
    assert "ModuleNotFoundError" in e.value.message and "\n" not in str(e.value)
    bad["agents"] = [{**base["agents"][0], "features": [{"type": f"{MODULE}:RK4Bicycle"}]}]
    with pytest.raises(SpecError, match="subclass of epo_casadi.features.Feature") as e:
        parse_game(bad)
    assert e.value.field == "agents[0].features[0].type"
    bad["agents"] = [{**base["agents"][0], "dynamics": {"type": f"{MODULE}:LaneKeeping"}}]
    with pytest.raises(SpecError, match="subclass of epo_casadi.dynamics.Dynamics") as e:
        parse_game(bad)
    assert e.value.field == "agents[0].dynamics.type"
    bad["agents"] = [{**base["agents"][0], "dynamics": {"type": f"{MODULE}:Nope"}}]
    with pytest.raises(SpecError, match="has no attribute 'Nope'"):
        parse_game(bad)
    bad["agents"] = [
        {**base["agents"][0], "dynamics": {"type": f"{MODULE}:RK4Bicycle", "substeps": 0}}
    ]
    with pytest.raises(SpecError, match="substeps: expected an integer >= 1") as e:
        parse_game(bad)
    assert e.value.field == "agents[0].dynamics"
    assert parse_game(base).game.params["lane.car"].default == (0.0,)


# --------------------------------------------------------------------------------------
# coupled dynamics: a joint linear model over two agents (a textbook LQ game)
# --------------------------------------------------------------------------------------
def _tow_matrices(dt=0.2, k=0.8):
    """Two planar double integrators; the second's velocity is pulled towards the
    first's (a tow line): a truly coupled joint model."""
    a1 = np.eye(4)
    a1[0, 2] = a1[1, 3] = dt
    A = np.zeros((8, 8))
    A[:4, :4] = a1
    A[4:, 4:] = a1
    A[6, 6] = A[7, 7] = 1 - k * dt
    A[6, 2] = A[7, 3] = k * dt
    B = np.zeros((8, 4))
    B[2, 0] = B[3, 1] = dt
    B[6, 2] = B[7, 3] = dt
    return A, B


def _coupled_game(K=8):
    A, B = _tow_matrices()
    model = LinearJoint(tuple(map(tuple, A)), tuple(map(tuple, B)))
    feats = [Goal(weight=2.0), Velocity(weight=0.5), Acceleration(weight=1.0)]
    agents = [
        AgentSpec("truck", "double_integrator", feats, x0=[1.0, -1.0, 0.5, 0.2], goal=[0, 0]),
        AgentSpec("trailer", "double_integrator", feats, x0=[-1.0, 0.5, 0.0, -0.3], goal=[0, 0]),
    ]
    spec = GameSpec(agents, horizon=K, dt=0.2, couplings=[Coupling(("truck", "trailer"), model)])
    return PotentialGame(spec), A, B


def _feedback_nash_lq(A, B, K, x0, wg=2.0, wv=0.5, wa=1.0):
    """Feedback Nash of the LQ game by the coupled Riccati recursion (Basar & Olsder):
    player i's cost 1/2 sum_{k>=1} x'Q_ik x + 1/2 sum_k u_i'R_i u_i, quadratic values."""
    n_players, m = 2, 2
    Q, QK = [], []
    for i in range(n_players):
        Sv = np.zeros((2, 8))
        Sv[:, 4 * i + 2 : 4 * i + 4] = np.eye(2)
        Sp = np.zeros((2, 8))
        Sp[:, 4 * i : 4 * i + 2] = np.eye(2)
        Q.append(wv**2 * Sv.T @ Sv)
        QK.append(Q[-1] + wg**2 * Sp.T @ Sp)
    R = wa**2 * np.eye(m)
    Bs = [B[:, m * i : m * (i + 1)] for i in range(n_players)]
    P = list(QK)
    gains = []
    for _k in reversed(range(K)):
        M = np.block(
            [[(R if i == j else 0) + Bs[i].T @ P[i] @ Bs[j] for j in range(2)] for i in range(2)]
        )
        rhs = np.vstack([Bs[i].T @ P[i] @ A for i in range(2)])
        F = np.linalg.solve(M, rhs)
        Fs = [F[m * i : m * (i + 1)] for i in range(2)]
        Acl = A - sum(Bs[j] @ Fs[j] for j in range(2))
        P = [Q[i] + Fs[i].T @ R @ Fs[i] + Acl.T @ P[i] @ Acl for i in range(2)]
        gains.append(F)
    gains.reverse()
    x, U = np.asarray(x0, float), []
    for F in gains:
        u = -F @ x
        U.append(u)
        x = A @ x + B @ u
    return np.array(U)  # (K, 4): stage controls, players stacked


def test_coupled_rollout_lm_ipopt_ilq():
    from solvers import StructuredGN

    game, A, B = _coupled_game()
    assert game.coupled
    p = game.default_params()
    rng = np.random.default_rng(3)
    u = rng.standard_normal(game.n_u)
    # rollout against the joint linear recursion in numpy
    Ua, Ub = game.split_controls(u)
    x = np.concatenate([[1.0, -1.0, 0.5, 0.2], [-1.0, 0.5, 0.0, -0.3]])
    ref = [x]
    for k in range(game.K):
        x = A @ x + B @ np.concatenate([Ua[k], Ub[k]])
        ref.append(x)
    ref = np.array(ref)
    Xa, Xb = game.split_states(np.asarray(game.function("rollout")(u, p)).ravel())
    np.testing.assert_allclose(np.hstack([Xa, Xb]), ref, atol=1e-13)
    # LM (dense backend chosen for coupled games) and IPOPT: the least-squares optimum
    # (the residual is affine in u), a minimum of the potential
    J = np.asarray(ca.densify(game.function("jacobian")(np.zeros(game.n_u), p)))
    r0 = np.asarray(game.function("residual")(np.zeros(game.n_u), p)).ravel()
    u_star = np.linalg.lstsq(J, -r0, rcond=None)[0]
    lm, ip = solve_lm(game, p), solve_ipopt(game, p)
    np.testing.assert_allclose(lm.controls, u_star, atol=1e-8)
    np.testing.assert_allclose(ip.controls, u_star, atol=1e-6)
    # with coupled dynamics that minimum is no open-loop Nash equilibrium: the results say
    # so, and the certificate finds the truck's better response (the tow line lets the
    # truck's controls move the trailer, so C_truck - E depends on them)
    for res in (lm, ip):
        assert res.status.value == "converged" and res.equilibrium is Equilibrium.POTENTIAL_MINIMUM
    cert = nash_certificate(game, p, lm.controls)
    assert cert.verdict is Verdict.FAILS and cert.verdicts == (Verdict.FAILS, Verdict.PASSES)
    assert cert.best_response_gap[0] > 0.01 and cert.stationarity[0] > 0.1  # measured 0.034
    assert cert.stationarity[1] < 1e-6  # the trailer's own controls do not move the truck
    with pytest.raises(SpecError, match="coupled dynamics"):
        StructuredGN(game)
    # iLQ: the feedback Nash equilibrium of the LQ game (coupled Riccati in numpy)
    il = solve_ilq(game, p)
    assert il.status.value == "converged"
    Ua, Ub = game.split_controls(il.controls)
    U_ref = _feedback_nash_lq(A, B, game.K, ref[0])
    np.testing.assert_allclose(np.hstack([Ua, Ub]), U_ref, atol=1e-7)
    assert il.equilibrium is Equilibrium.FEEDBACK
    # the feedback equilibrium is another point than the potential minimum
    assert np.max(np.abs(il.controls - lm.controls)) > 1e-4


def test_coupling_is_checked():
    game, A, B = _coupled_game(K=2)
    model = game.spec.couplings[0].model
    agents = game.spec.agents
    with pytest.raises(SpecError, match="unknown agent 'car'") as e:
        GameSpec(agents, couplings=[Coupling(("truck", "car"), model)])
    assert e.value.field == "couplings[0].agents"
    with pytest.raises(SpecError, match="in two couplings"):
        GameSpec(
            agents,
            couplings=[
                Coupling(("truck", "trailer"), model),
                Coupling(("trailer", "truck"), model),
            ],
        )
    with pytest.raises(SpecError, match="two or more agent names"):
        Coupling(("truck",), model)
    with pytest.raises(SpecError, match="JointDynamics"):
        Coupling(("truck", "trailer"), "linear")
    bad = LinearJoint(tuple(map(tuple, A[:6, :6])), tuple(map(tuple, B[:6])))
    with pytest.raises(SpecError) as e:
        GameSpec(agents, couplings=[Coupling(("truck", "trailer"), bad)])
    assert e.value.field == "couplings[0].model" and "step()" in e.value.message
    with pytest.raises(SpecError, match="game files cannot hold coupled dynamics"):
        dump_game(game.spec)


def test_coupled_game_in_the_layer():
    """The layer solves a coupled game with the dense backend, as solve_lm does, and its
    gradient w.r.t. an initial state matches central differences."""
    from learning.layer import GameLayer
    from solvers import LMOptions

    game, _, _ = _coupled_game(K=5)
    opts = LMOptions.paper()
    layer = GameLayer(game, opts)
    p = torch.as_tensor(game.default_params()).requires_grad_()
    out = layer(p[None])
    ref = solve_lm(game, game.default_params(), options=opts)
    np.testing.assert_allclose(out.controls.detach().numpy()[0], ref.controls, atol=1e-12)
    i = game.params["x0.truck"].start
    out.states.sum().backward()
    h = 1e-6
    e = np.zeros(game.n_p)
    e[i] = h
    fd = (
        solve_lm(game, game.default_params() + e, options=opts).states.sum()
        - solve_lm(game, game.default_params() - e, options=opts).states.sum()
    ) / (2 * h)
    assert p.grad[i].item() == pytest.approx(fd, rel=1e-6)
