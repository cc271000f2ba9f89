"""The RPI scenario (App. E.1 / F.3) and the ``epo generate`` / ``epo data`` commands."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from epo_casadi.errors import SpecError
from scenarios import dataset as ds
from scenarios.cli import main
from scenarios.rpi import AGENTS, SAMPLES_PER_GAME, RPIRecipe, RPIScenario

# a tiny recipe: short horizon and history, few solves, at most 3 subgames per main mode
TINY = dict(
    main_games=3,
    games_per_shard=1,
    history=4,
    n_samples=4,
    max_subgames=3,
    compiled=False,
    ground_truth="potential",  # this file tests the potential ground truth (rpi_peters: Peters)
)
TINY_SET = [f"--set={k}={v}" for k, v in TINY.items() if k != "main_games"]


@pytest.fixture(scope="module")
def tiny():
    return RPIScenario(RPIRecipe(**TINY))


def test_recipe_defaults_and_validation():
    r = RPIRecipe.full(ground_truth="potential")
    assert (r.horizon, r.history, r.modes, r.dt, r.radius, r.circle) == (40, 18, 2, 0.1, 0.25, 3.0)
    assert r.main_games * SAMPLES_PER_GAME >= 60_000 and r.split == (0.8, 0.1, 0.1)
    assert RPIRecipe.from_dict(r.to_dict()) == r
    json.dumps(r.to_dict())
    small = RPIRecipe.for_samples(600, ground_truth="potential")
    assert small.main_games == 20 and small.games_per_shard == 1
    assert RPIRecipe.for_samples(60_000, ground_truth="potential").games_per_shard == 20
    assert RPIRecipe.for_samples(1, ground_truth="potential").main_games == 3
    with pytest.raises(SpecError, match=r"rpi: unknown recipe field\(s\) \['horizn'\]"):
        RPIRecipe.from_dict({"horizn": 3})
    with pytest.raises(SpecError, match="rpi.main_games"):
        RPIRecipe(main_games=2, ground_truth="potential")
    with pytest.raises(SpecError, match="rpi.solver"):
        RPIRecipe(solver="newton", ground_truth="potential")
    with pytest.raises(SpecError, match="rpi.collision_weight"):
        RPIRecipe(collision_weight=(5.0, 1.0), ground_truth="potential")
    with pytest.raises(SpecError, match="rpi.split"):
        RPIRecipe(split=(0.5, 0.1, 0.1), ground_truth="potential")
    with pytest.raises(SpecError, match="samples"):
        RPIRecipe.for_samples(0)


def test_game_has_the_app_f3_features(tiny):
    g = tiny.game
    own = [
        "goal",
        "velocity",
        "acceleration",
        "velocity_bound",
        "acceleration_bound",
        "turn_rate",
        "turn_rate_bound",
    ]
    for a in AGENTS:
        assert [t.feature for t in g.terms if t.agents == (a,)] == own
    (col,) = [t for t in g.terms if t.kind == "pair"]
    assert col.feature == "collision" and col.steps == tuple(range(1, g.K + 1))  # every step
    assert [a.radius for a in g.agents] == [0.25, 0.25] and g.dt == 0.1 and g.K == 40
    assert RPIScenario().game_spec().horizon == 40


def test_configurations(tiny):
    r = tiny.recipe
    seen_w = []
    for i in range(200):
        c = tiny.sample_config(i, np.random.default_rng(i))
        ped = c.x0[1, :2]
        assert np.isclose(np.hypot(*ped), 3.0) and np.isclose(np.hypot(*c.goals[1]), 3.0)
        assert np.allclose(c.x0[0, :2], r.robot_start) and np.allclose(c.goals[0], r.robot_goal)
        # outside the excluded arc around the robot start (angle pi)
        assert abs(abs(c.ped_start_angle) - math.pi) >= math.radians(r.exclude) - 1e-9
        off = (c.ped_goal_angle - c.ped_start_angle) % (2 * math.pi) - math.pi  # 0: straight across
        assert abs(off) <= math.radians(r.goal_jitter) + 1e-9
        assert r.collision_weight[0] <= c.collision_weight <= r.collision_weight[1]
        for n in range(2):  # heading straight to the goal at speed0
            d = c.goals[n] - c.x0[n, :2]
            assert np.isclose(c.x0[n, 3], math.atan2(d[1], d[0])) and c.x0[n, 2] == r.speed0[n]
        seen_w.append(c.collision_weight)
    assert np.ptp(seen_w) > 0.8 * (r.collision_weight[1] - r.collision_weight[0])  # uniform spread
    p = tiny.params(c)
    names = tiny.game.params.names
    assert p[names.index("w.robot-pedestrian.collision")] == c.collision_weight


def test_passed_and_pre_history(tiny):
    head_on = np.array([[-1.0, 0, 1, 0], [1.0, 0, 1, math.pi]])
    assert not tiny.passed(head_on)
    apart = np.array([[1.0, 0, 1, 0], [-1.0, 0, 1, math.pi]])
    assert tiny.passed(apart)
    x0 = np.array([[0.0, 0, 2, 0], [1.0, 1, 1, math.pi / 2]])
    h = tiny.pre_history(x0, 3)
    assert h.shape == (3, 2, 4)
    assert np.allclose(h[:, 0, 0], [-0.6, -0.4, -0.2]) and np.allclose(h[:, 1, 1], [0.7, 0.8, 0.9])
    assert np.allclose(h[:, :, 2:], x0[None, :, 2:])


@pytest.fixture(scope="module")
def unit(tiny):
    """The first main game (seed 0) with at least 2 samples (some yield none: every solve
    of the main game hit the iteration cap or collided)."""
    for i in range(6):
        out = tiny.run_unit(i, ds.unit_seed(0, i))
        if len(out["step"]) >= 2:
            return out
    raise AssertionError("no main game of the tiny recipe produced samples")


def test_unit_samples_are_consistent(tiny, unit):
    r, g = tiny.recipe, tiny.game
    n = len(unit["step"])
    shapes = {k: v.shape for k, v in unit.items()}
    assert shapes["history"] == (n, r.history + 1, 2, 4) and shapes["future"] == (
        n,
        2,
        2,
        r.horizon,
        4,
    )
    assert shapes["future_controls"] == (n, 2, 2, r.horizon, 2) and shapes["params"] == (n, g.n_p)
    for s in range(n):
        k = int(unit["step"][s])
        assert unit["history_valid"][s].tolist() == [j >= 0 for j in range(k - r.history, k + 1)]
        xk = unit["history"][s, -1]
        assert not tiny.passed(xk)
        p = unit["params"][s]
        assert np.allclose(g.params.unpack(p)["x0.robot"], xk[0]) and np.allclose(
            g.params.unpack(p)["x0.pedestrian"], xk[1]
        )
        valid, share = unit["mode_valid"][s], unit["mode_share"][s]
        assert valid[0] and 0 < share[0] <= 1 and share.sum() <= 1 + 1e-6
        assert (0 < share[1] <= share[0]) if valid[1] else share[1] == 0
        for m in range(2):
            # the future is the rollout of the stored controls from the current state
            u = g.join_controls([unit["future_controls"][s, m, i].astype(float) for i in range(2)])
            x = g.function("rollout")(u, p).full().ravel()
            fut = np.stack([st[1:] for st in g.split_states(x)])
            assert np.allclose(fut, unit["future"][s, m], atol=1e-4)
        if not valid[1]:
            assert np.array_equal(unit["future"][s, 1], unit["future"][s, 0])
    # consecutive steps of one executed main mode: the history shifts by one step
    mm = unit["main_mode"]
    for s in range(n - 1):
        if mm[s] == mm[s + 1]:
            assert unit["step"][s + 1] == unit["step"][s] + 1
            assert np.allclose(unit["history"][s + 1, :-1], unit["history"][s, 1:])
    assert len(np.unique(unit["main_game"])) == 1 and len(np.unique(unit["collision_weight"])) == 1


def test_unit_is_deterministic(tiny, unit):
    i = int(unit["main_game"][0])
    again = tiny.run_unit(i, ds.unit_seed(0, i))
    assert all(np.array_equal(unit[k], again[k]) for k in unit)


def test_generate_verify_show_via_cli(tmp_path, capsys):
    d = tmp_path / "rpi"
    args = [
        "generate",
        "rpi",
        "--out",
        str(d),
        "--samples",
        "3",
        "--workers",
        "1",
        "--no-progress",
        *TINY_SET,
    ]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "samples/s" in out
    m = ds.read_manifest(d)
    assert (
        m["complete"]
        and m["recipe"]["main_games"] == 3
        and m["recipe"]["horizon"] == 40
        and m["recipe"]["n_samples"] == 4
    )
    assert m["meta"]["param_names"][:4] == [
        "x0.robot.x",
        "x0.robot.y",
        "x0.robot.v",
        "x0.robot.theta",
    ]
    assert main(["data", "verify", str(d)]) == 0
    assert capsys.readouterr().out.startswith("ok:")
    test = ds.load_split(d, "test")
    train = ds.load_split(d, "train")
    assert test["future"].shape[1:] == (2, 2, 40, 4) and test["history"].shape[1:] == (5, 2, 4)
    assert not set(test["main_game"].tolist()) & set(train["main_game"].tolist())
    png = tmp_path / "fig.png"
    assert main(["data", "show", str(d), "--split", "test", "--index", "0", "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # running again on the finished set writes nothing
    assert main(args) == 0
    assert "0 shard(s) written, 3 kept" in capsys.readouterr().out

    # bad input: an error line naming the field, non-zero exit, no traceback (click's
    # usage errors add the usage lines above their one "Error:" line)
    def fails(argv, *needles):
        code = main(argv)
        err = capsys.readouterr().err
        assert code != 0, argv
        assert "Traceback" not in err, err
        lines = [ln for ln in err.splitlines() if ln.lower().startswith("error:")]
        assert len(lines) == 1, err
        for s in needles:
            assert s in lines[0], (s, err)

    fails(["data", "verify", str(tmp_path / "nope")], "no such dataset directory")
    fails(
        ["data", "show", str(tmp_path / "nope"), "--index", "0", "--out", str(png)],
        "no such dataset directory",
    )
    fails(["data", "show", str(d), "--split", "testing", "--out", str(png)], "--split")
    fails(
        ["data", "show", str(d), "--split", "test", "--index", "100000", "--out", str(png)],
        "index:",
        "[0,",
    )
    fails(["generate", "rpi", "--out", str(tmp_path / "x"), "--samples", "0"], "--samples")
    fails(["generate", "rpi", "--out", str(tmp_path / "x"), "--set", "horizn=3"], "horizn")
    fails(
        ["generate", "rpi", "--out", str(tmp_path / "x"), "--samples", "9", "--set", "horizn=3"],
        "horizn",
    )
    fails(
        ["generate", "rpi", "--out", str(tmp_path / "x"), "--set", "n_samples=0"], "rpi.n_samples"
    )
    fails(["generate", "rpi", "--out", str(tmp_path / "x"), "--workers", "0"], "--workers")
    fails(
        ["generate", "rpi", "--out", str(d), "--samples", "3", "--seed", "1", *TINY_SET],
        "different seed",
    )
    shard = d / m["splits"]["test"]["shards"][0]
    shard.write_bytes(b"not an hdf5 file")
    fails(["data", "verify", str(d)], shard.name, "checksum")
    fails(["data", "show", str(d), "--split", "test", "--out", str(png)], shard.name)


def test_engines_give_identical_shards(tmp_path):
    """One process, a spawned pool of 2, a dask LocalCluster and a killed-and-resumed run
    write the same bytes."""
    distributed = pytest.importorskip("distributed")
    sc = RPIScenario(RPIRecipe(**TINY))
    ds.generate(sc, tmp_path / "one", seed=2, workers=1, progress=False)
    ds.generate(sc, tmp_path / "pool", seed=2, workers=2, progress=False)
    # one thread per worker: a process's solver buffers are not shared between threads
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        ds.generate(sc, tmp_path / "dask", seed=2, engine="dask", client=client, progress=False)

    def kill(name):  # a generation killed right after its first shard
        raise KeyboardInterrupt(name)

    with pytest.raises(KeyboardInterrupt):
        ds.generate(sc, tmp_path / "resumed", seed=2, workers=1, progress=False, on_shard=kill)
    assert len(ds.read_manifest(tmp_path / "resumed")["shards"]) == 1
    rep = ds.generate(sc, tmp_path / "resumed", seed=2, workers=1, progress=False)
    assert len(rep.shards_kept) == 1 and len(rep.shards_written) == 2
    ref = ds.read_manifest(tmp_path / "one")
    assert sum(ref["counts"].values()) > 0
    for other in ("pool", "dask", "resumed"):
        m = ds.read_manifest(tmp_path / other)
        assert m["shards"] == ref["shards"], other
        assert ds.verify(tmp_path / other).ok


def test_ground_truth_mode_is_the_executed_one(unit):
    """At k = 0 the subgame is the main game: the ground truth is the executed main mode."""
    gt, mm, valid = unit["gt_mode"], unit["main_mode"], unit["mode_valid"]
    assert all(valid[s, gt[s]] for s in range(len(gt)))
    first = unit["step"] == 0
    assert first.any()
    np.testing.assert_array_equal(gt[first], mm[first])


def test_ground_truth_keeps_the_agents_apart(tiny, unit):
    """The collision margin keeps the ground-truth futures free of overlaps (dist >= 2 r)."""
    gt = unit["future"][np.arange(len(unit["gt_mode"])), unit["gt_mode"]]
    dist = np.linalg.norm(gt[:, 0, :, :2] - gt[:, 1, :, :2], axis=-1)
    assert dist.min() >= 2 * tiny.recipe.radius


def test_model_game_reach_follows_the_ground_truth():
    """The model game's collision term acts where the demonstrations' interaction does: with
    the Peters ground truth, up to its proximity radius (1.5 m = 2 * 0.25 m + 1.0 m)."""
    peters = RPIRecipe(ground_truth="peters")
    assert peters.proximity_radius == 1.5 and peters.radius == 0.25
    assert peters.collision_margin == pytest.approx(1.0, abs=1e-15)
    assert RPIRecipe(ground_truth="potential").collision_margin == 0.15
    assert RPIRecipe(ground_truth="peters", collision_margin=0.15).collision_margin == 0.15
    assert RPIRecipe(ground_truth="peters", proximity_radius=0.5).collision_margin == 0.0
    assert RPIRecipe.from_dict(peters.to_dict()) == peters
    (col,) = RPIScenario(peters).game_spec().pair_features
    assert col.margin == pytest.approx(1.0, abs=1e-15)
    with pytest.raises(SpecError, match="rpi.collision_margin"):
        RPIRecipe(ground_truth="potential", collision_margin=-0.1)
