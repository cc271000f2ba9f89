"""The Peters ground truth of RPI (scenarios/rpi_peters.py, RPIRecipe(ground_truth="peters"))."""

from __future__ import annotations

import math

import numpy as np
import pytest

from epo_casadi.errors import SpecError
from scenarios import dataset as ds
from scenarios.cli import main
from scenarios.rpi import RPIRecipe, RPIScenario
from scenarios.rpi_peters import dbscan, solve_peters_modes
from solvers.feedback_nash import feedback_nash_check
from solvers.multimodal import sinusoid_sampler

# the 10 s Peters game with few solves, a short history and future: the mechanics
SHORT = dict(
    main_games=3,
    games_per_shard=1,
    horizon=10,
    history=4,
    n_samples=6,
    sub_samples=4,  # 2 warm starts + 2 samples: a lone solve is DBSCAN noise (min_points 2)
    max_subgames=2,
    compiled=False,
)


@pytest.fixture(scope="module")
def short():
    return RPIScenario(RPIRecipe(**SHORT))


def test_recipe_selection_and_validation():
    r = RPIRecipe()
    assert r.ground_truth == "peters" and (r.game_horizon, r.dt, r.horizon) == (100, 0.1, 40)
    assert r.speed0 == (0.0, 0.0) and r.n_samples == 100 and r.proximity_weight == (10.0, 50.0)
    assert RPIRecipe.from_dict(r.to_dict()) == r
    pot = RPIRecipe(ground_truth="potential")
    assert "game_horizon" not in pot.to_dict() and pot.to_dict()["ground_truth"] == "potential"
    assert RPIRecipe.from_dict(pot.to_dict()) == pot and pot.n_samples == 8
    with pytest.raises(SpecError, match=r"rpi\.game_horizon: applies to ground_truth='peters'"):
        RPIRecipe(ground_truth="potential", game_horizon=50)
    with pytest.raises(SpecError, match="rpi.ground_truth"):
        RPIRecipe(ground_truth="peter")
    with pytest.raises(SpecError, match="rpi.solver"):
        RPIRecipe(solver="lm")
    with pytest.raises(SpecError, match="rpi.game_horizon"):
        RPIRecipe(game_horizon=20)  # shorter than the predicted future (40)
    with pytest.raises(SpecError, match="rpi.proximity_radius"):
        RPIRecipe(proximity_radius=0.3)
    # the model's game stays the App. F.3 game at the future's horizon
    sc = RPIScenario(r)
    assert sc.game.K == 40 and sc.truth_game.K == 100
    assert sc.schema()["params"].shape == (sc.truth_game.n_p,)


def _numpy_costs(r, X, U, goals, headings, w_prox):
    """Hand-written player costs: X (N, K+1, 4) states (x, y, v, theta), U (N, K, 2) (a, omega)."""

    def gap(v, lo, hi):
        return np.where(v < lo, v - lo, np.where(v > hi, v - hi, 0.0))

    K = U.shape[1]
    turn = math.radians(r.turn_rate_bound)
    d = np.linalg.norm(X[0, 1:, :2] - X[1, 1:, :2], axis=-1)
    prox = w_prox * np.sum(np.where(d < r.proximity_radius, d - r.proximity_radius, 0.0) ** 2)
    out = []
    for i in range(2):
        a, om = U[i, :, 0], U[i, :, 1]
        v = X[i, 1:, 2]
        c = 0.5 * r.control_cost * np.sum(a**2 + om**2)
        c += r.bound_cost * np.sum(gap(om, -turn, turn) ** 2)
        c += r.bound_cost * np.sum(gap(a, -r.acceleration_bound, r.acceleration_bound) ** 2)
        c += 0.5 * r.speed_cost * np.sum(v**2) + r.bound_cost * np.sum(gap(v, *r.speed_bounds) ** 2)
        t = np.arange(K + 1) * r.dt
        last = t >= K * r.dt - 1.5 * r.dt - 1e-9  # the states of the last 1.5 dt
        dp = X[i, last, :2] - goals[i]
        dth = X[i, last, 3] - headings[i]
        c += 0.5 * r.goal_cost * (np.sum(dp**2) + np.sum(dth**2))
        out.append(c + prox)
    return np.array(out), prox


def test_costs_equal_hand_computed_values(short):
    r, g = short.recipe, short.truth_game
    K = g.K
    cfg = short.sample_config(0, np.random.default_rng(0))
    x0 = np.array([[-0.6, 0.0, -0.02, 0.1], [0.5, 0.3, 1.0, 2.5]])  # close: proximity active
    p = short.params(cfg, x0)
    rng = np.random.default_rng(1)
    U = np.stack([np.stack([rng.normal(0, 4, K), rng.normal(0, 0.4, K)], 1) for _ in range(2)])
    U[0, 0, 0] = -12.0  # beyond the acceleration bound, and v below its bound next
    u = g.join_controls(list(U))
    # independent rollout: forward Euler of the unicycle
    X = np.zeros((2, K + 1, 4))
    X[:, 0] = x0
    for k in range(K):
        x = X[:, k]
        X[:, k + 1] = np.stack(
            [
                x[:, 0] + r.dt * x[:, 2] * np.cos(x[:, 3]),
                x[:, 1] + r.dt * x[:, 2] * np.sin(x[:, 3]),
                x[:, 2] + r.dt * U[:, k, 0],
                x[:, 3] + r.dt * U[:, k, 1],
            ],
            1,
        )
    xs = g.function("rollout")(u, p).full().ravel()
    np.testing.assert_allclose(np.stack(g.split_states(xs)), X, rtol=1e-12, atol=1e-12)
    want, prox = _numpy_costs(r, X, U, cfg.goals, cfg.x0[:, 3], cfg.collision_weight)
    got = g.function("agent_costs")(u, p).full().ravel()
    np.testing.assert_allclose(got, want, rtol=1e-8)
    # the regime: proximity and every soft bound are active somewhere
    assert prox > 1.0 and X[0, 1, 2] < -0.05 and np.abs(U[:, :, 1]).max() > math.radians(10)
    assert abs(cfg.x0[1, 3] - math.atan2(*(cfg.goals[1] - cfg.x0[1, :2])[::-1])) < 1e-12


def test_dbscan_against_its_definition():
    # two groups on a line, a bridge-free gap, and an isolated point
    pts = np.array([0.0, 0.5, 1.0, 5.0, 5.4, 20.0])
    D = (pts[:, None] - pts[None]) ** 2  # squared distances, eps on them as in the recipe
    assert dbscan(D, 0.3, 2).tolist() == [0, 0, 0, 1, 1, -1]
    assert dbscan(D, 0.3, 3).tolist() == [0, 0, 0, -1, -1, -1]  # 5.0 and 5.4: too few
    rng = np.random.default_rng(0)
    P = rng.normal(0, 1, (40, 2)) + np.repeat([[0, 0], [6, 0]], 20, axis=0)
    D = np.sum((P[:, None] - P[None]) ** 2, axis=-1)
    lab = dbscan(D, 1.0, 3)
    core = (D < 1.0).sum(1) >= 3
    for i in range(40):  # definition: core neighbours share a label; noise is near no core
        nb = np.nonzero(D[i] < 1.0)[0]
        if core[i]:
            assert all(lab[j] == lab[i] for j in nb if core[j])
        if lab[i] < 0:
            assert not core[nb].any()
    assert np.array_equal(lab, dbscan(D, 1.0, 3))


def test_main_game_modes_are_feedback_nash(short):
    """Two main games of the 10 s game: the top mode passes the sampled feedback-Nash check
    of its own policy; a policy shifted off it fails; solving again gives the same modes."""
    sc, g, r = short, short.truth_game, short.recipe
    args = (sc.solver_options(), r.min_distance, r.dbscan_eps, r.dbscan_min_points)
    for i in (0, 1):
        cfg = sc.sample_config(i, np.random.default_rng(10 + i))
        p = sc.params(cfg)
        U0 = sinusoid_sampler(g, p, 3, np.random.default_rng(i))
        modes, info = solve_peters_modes(g, p, U0, *args)
        assert modes and info["min_dist"][info["kept"]].min() >= r.min_distance
        if i == 0:  # solves and clustering are deterministic
            again, info2 = solve_peters_modes(g, p, U0, *args)
            assert np.array_equal(info["labels"], info2["labels"])
            assert all(
                np.array_equal(a.states, b.states) for a, b in zip(modes, again, strict=True)
            )
        res = info["results"]
        m = modes[0]
        P, a = res.info["gains"][m.index], res.info["feedforward"][m.index]
        # the solves stop at max |a| <= ilq_tol = 1e-2: measured relative gains of the kept
        # policies 4e-8..5e-7; a feed-forward shifted by 0.05 gains 1e-4..4e-4
        opts = {"tol": 2e-6}
        ok = feedback_nash_check(g, p, m.states, m.controls, P, a, opts)
        assert ok.ok, ok.summary()
        bad = feedback_nash_check(g, p, m.states, m.controls, P, a + 0.05, opts)
        assert not bad.ok and bad.max_relative_gain > 10 * ok.max_relative_gain


def test_every_history_is_real(short):
    out = short.run_unit(0, ds.unit_seed(0, 0))
    n = len(out["step"])
    assert n >= 2 and out["history_valid"].all() and (out["step"] >= short.recipe.history).all()
    g = short.truth_game
    for s in range(n):
        blocks = g.params.unpack(out["params"][s])
        np.testing.assert_allclose(
            np.stack([blocks["x0.robot"], blocks["x0.pedestrian"]]),
            out["history"][s, -1],
            atol=1e-5,
        )
    mm = out["main_mode"]
    for s in range(n - 1):  # consecutive samples of one executed mode: the window shifts
        if mm[s] == mm[s + 1]:
            assert out["step"][s + 1] == out["step"][s] + 1
            np.testing.assert_allclose(out["history"][s + 1, :-1], out["history"][s, 1:])


class _NoSolve(RPIScenario):
    """TEST-ONLY: writes the real manifest and schema but solves no game (no samples)."""

    def run_unit(self, index, seed):
        return self._stack([])


def test_manifest_records_the_recipe_and_mixed_sets_are_refused(tmp_path, capsys):
    d = tmp_path / "rpi"
    ds.generate(_NoSolve(RPIRecipe(**SHORT)), d, seed=0, workers=1, progress=False)
    m = ds.read_manifest(d)
    assert m["recipe"]["ground_truth"] == "peters" and m["recipe"]["game_horizon"] == 100
    assert m["meta"]["param_names"] == list(RPIScenario(RPIRecipe(**SHORT)).truth_game.params.names)
    other = {k: v for k, v in SHORT.items() if k != "sub_samples"}
    with pytest.raises(ds.DatasetError, match=r"recipe field 'ground_truth' \('peters' there"):
        ds.generate(_NoSolve(RPIRecipe(**other, ground_truth="potential")), d, seed=0, workers=1)
    argv = ["generate", "rpi", "--out", str(d), "--samples", "3", "--no-progress"]
    argv += [f"--set={k}={v}" for k, v in other.items() if k != "main_games"]
    assert main([*argv, "--set=ground_truth=potential"]) != 0
    err = capsys.readouterr().err
    assert "Traceback" not in err and "ground_truth" in err and err.count("error:") == 1
