"""The network as a closed-loop planner (learning.planner.NetworkPlanner, load_planner).

References: the scenes the dataset code builds for the same trajectory (the synthetic
dataset's files, :meth:`scenarios.rpi.RPIScenario.pre_history` and the windowing of
``RPIScenario.run_unit``); a direct call of :func:`learning.control.plan` on the same scene;
a hand-written rigid transform for the agent frame.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from epo_casadi.errors import SpecError
from learning.checkpoint import CheckpointError
from learning.control import plan
from learning.data import SceneDataset
from learning.models import ModelConfig
from learning.observation import observation_scene
from learning.planner import NetworkPlanner, PlannerOptions, load_planner
from learning.train import TrainConfig, train
from scenarios.rpi import RPIRecipe, RPIScenario
from solvers.control.types import AgentTask, Estimate, Observation, Planner
from tests.test_models import RECIPE, TINY, synthetic_dataset

H = RECIPE["history"]  # 4: scenes hold H + 1 = 5 states per agent
DT = 0.1


class StubWorld:
    """The attributes of a World the planner reads; the goals of the synthetic scenes."""

    def __init__(self, goals, name="crossing", n_agents=2, dt=DT, **extra):
        self.name, self.n_agents, self.dt = name, n_agents, dt
        g = np.asarray(goals, float)
        self._tasks = [AgentTask(np.zeros((2, 2)), 1.0, g[i], 0.25) for i in range(len(g))]
        self.ego_task = self._tasks[0]
        self.__dict__.update(extra)

    def tasks(self):
        return self._tasks

    def reset(self, seed):  # pragma: no cover - not driven here
        raise NotImplementedError

    def step(self, command):  # pragma: no cover
        raise NotImplementedError

    def truth(self):  # pragma: no cover
        raise NotImplementedError

    def outcome(self):  # pragma: no cover
        return "running"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One-epoch tiny runs of every kind on the synthetic RPI dataset (horizon 10, H = 4)."""
    data = synthetic_dataset()
    root = tmp_path_factory.mktemp("planner-runs")
    out = {}
    # ours trained with the structured backend, so that the fused planner differs from it
    layer = {"layer_backend": "structured", "layer_compiled": "no"}
    for kind in ("epo", "sc", "vlstm"):
        cfg = TrainConfig(
            model=ModelConfig(kind=kind, **TINY, **(layer if kind == "epo" else {})),
            epochs=1,
            batch_size=8,
            lr=1e-3,
            val_split=None,
        )
        train(data, root / kind, cfg, progress=False)
        out[kind] = root / kind
    return out


@pytest.fixture(scope="module")
def sample():
    with SceneDataset(synthetic_dataset(), "train") as ds:
        return ds.read([3])


def _observe(ego_hist, others_hist, t=0.0):
    """Observation + Estimate whose filtered history is ``others_hist`` ``(N-1, T, 4)``."""
    others_hist = np.asarray(others_hist, float)
    obs = Observation(t, np.asarray(ego_hist[-1], float), others_hist[:, -1, :2])
    est = Estimate(
        others_hist[:, -1],
        np.repeat(np.eye(4)[None], len(others_hist), 0),
        others_hist,
        np.ones(others_hist.shape[:2], bool),
    )
    return obs, est


def _trajectory(seed=0, K=12):
    """A joint trajectory (K+1, 2, 4) of the RPI start configuration under smooth controls."""
    scen = RPIScenario(RPIRecipe(**RECIPE))
    rng = np.random.default_rng(seed)
    x = scen.sample_config(0, rng).x0.astype(float)
    X = [x]
    for k in range(K):
        u = np.stack([0.3 * np.cos(0.4 * k + np.arange(2)), 0.4 * np.sin(0.3 * k + np.arange(2))])
        px, py, v, th = x.T
        x = np.stack([px + DT * v * np.cos(th), py + DT * v * np.sin(th), v + DT * u[:, 0],
                      th + DT * u[:, 1]], 1)  # fmt: skip
        X.append(x)
    return scen, np.stack(X)


# ------------------------------------------------------------------------ the scene
def test_first_scene_equals_the_dataset_sample(runs, sample):
    """One observation: the extrapolated history and the goals of a stored sample."""
    hist, goals = sample["history"][0], sample["goals"][0]  # (H+1, 2, 4), (2, 2)
    planner = load_planner(runs["epo"], StubWorld(goals))
    assert planner.spec.history_steps == H + 1 and planner.spec.reads_goals
    obs, est = _observe(hist[-1:, 0], hist[-1:, 1:].transpose(1, 0, 2))
    scene, frame = planner.scene(obs, est)
    assert frame.identity
    np.testing.assert_allclose(scene["history"], hist, rtol=0, atol=2e-6)
    assert scene["history"].dtype == np.float32 and scene["goals"].dtype == np.float32
    np.testing.assert_array_equal(scene["goals"], goals)
    assert not scene["history_valid"][:-1].any() and scene["history_valid"][-1]


@pytest.mark.parametrize("style", ["growing", "fixed"])
def test_scenes_along_a_trajectory_equal_the_dataset_windows(runs, style):
    """Step by step, the planner's scene is ``traj[k : k + H + 1]`` of ``run_unit``, whether
    the estimator's history grows or has a fixed length with invalid leading entries."""
    scen, X = _trajectory()
    K = len(X) - 1
    traj = np.concatenate([scen.pre_history(X[0], H), X], axis=0)  # run_unit's construction
    valid = np.arange(-H, K + 1) >= 0
    planner = load_planner(runs["epo"], StubWorld([[3.0, 0.0], [-1.0, 2.0]]))
    L = H + 3
    for k in range(K + 1):
        if style == "growing":
            oh, ov = X[max(0, k - L + 1) : k + 1, 1:], None
        else:  # a fixed-length history, what a filter keeps: garbage before the first update
            oh = np.concatenate([np.full((L, 1, 4), 7.0), X[: k + 1, 1:]])[-L:]
            ov = (np.arange(-L + 1, 1) + k >= 0)[:, None]
        obs, est = _observe(X[: k + 1, 0], oh.transpose(1, 0, 2), t=k * DT)
        if ov is not None:
            est = replace(est, valid=ov.T)
        scene, _ = planner.scene(obs, est)
        np.testing.assert_allclose(scene["history"], traj[k : k + H + 1], rtol=0, atol=1e-5)
        np.testing.assert_array_equal(scene["history_valid"], valid[k : k + H + 1])


def test_agent_frame_is_the_rigid_transform():
    """Hand-computed: the agent frame puts agent 0 at the origin heading along x."""
    spec = _spec(frame="agent")
    ego = np.array([[0.8, 1.9, 1.2, 0.3], [1.0, 2.0, 1.5, math.pi / 2]])
    oth = np.array([[[2.0, 2.0, 1.0, -math.pi]] * 2])
    scene, frame = observation_scene(ego, oth, None, spec, goals=[[1.0, 5.0], [0.0, 0.0]])
    h = scene["history"].astype(float)
    np.testing.assert_allclose(h[-1, 0], [0, 0, 1.5, 0], atol=1e-6)
    np.testing.assert_allclose(h[-1, 1], [0.0, -1.0, 1.0, math.pi / 2], atol=1e-6)
    np.testing.assert_allclose(scene["goals"], [[3.0, 0.0], [-2.0, 1.0]], atol=1e-6)
    back = frame.states_out(h[-1])
    np.testing.assert_allclose(back[:, :3], np.array([ego[-1], oth[0, -1]])[:, :3], atol=1e-6)


def _spec(**kw):
    from learning.observation import SceneSpec

    base = dict(scenario="rpi", kind="epo", n_agents=2, history_steps=H + 1, horizon=10, dt=DT,
                reads_goals=True)  # fmt: skip
    return SceneSpec(**{**base, **kw})


# ------------------------------------------------------------------------ the plan
@pytest.mark.parametrize("kind", ["epo", "sc"])
@pytest.mark.parametrize("frame", ["world", "agent"])
def test_plan_is_the_most_likely_mode_in_the_world_frame(runs, sample, kind, frame):
    hist, goals = sample["history"][0], sample["goals"][0]
    world = StubWorld(goals)
    loaded = load_planner(runs[kind], world)
    assert isinstance(loaded, Planner)
    planner = NetworkPlanner(loaded.model, replace(loaded.spec, frame=frame))
    planner.reset(world)
    obs, est = _observe(hist[:, 0], hist[:, 1:].transpose(1, 0, 2), t=2.5)
    p = planner.plan(obs, est)
    assert p.ok, p.message
    assert p.t0 == 2.5 and p.dt == DT and p.states.shape == (10, 4) and p.controls.shape == (10, 2)
    planner.reset(world)
    scene, fr = planner.scene(obs, est)
    assert fr.identity == (frame == "world")
    batch = {k: torch.from_numpy(v)[None] for k, v in scene.items()}
    direct = plan(loaded.model, batch)
    want = fr.states_out(direct.states[0].double().numpy())
    np.testing.assert_allclose(p.states, want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(p.controls, direct.controls[0].double().numpy(), atol=1e-9)
    assert p.info["mode"] == int(direct.mode[0])
    assert p.predictions.shape == (2, 2, 10, 4)
    np.testing.assert_allclose(p.predictions[p.info["mode"], 0], p.states)
    np.testing.assert_allclose(p.probabilities.sum(), 1.0)
    assert p.probabilities[p.info["mode"]] == pytest.approx(float(direct.probability[0]), 1e-6)
    # the first planned state follows the unicycle from the current (world) state
    x = hist[-1, 0].astype(float)
    first = x + DT * np.array([x[2] * np.cos(x[3]), x[2] * np.sin(x[3]), *p.controls[0]])
    np.testing.assert_allclose(p.states[0], first, atol=2e-5)


def test_nan_output_and_bad_input_give_a_failed_plan(runs, sample):
    hist, goals = sample["history"][0], sample["goals"][0]
    world = StubWorld(goals)
    planner = load_planner(runs["epo"], world)
    obs, est = _observe(hist[:, 0], hist[:, 1:].transpose(1, 0, 2))
    bad = replace(est, history=np.full_like(est.history, np.nan))
    p = planner.plan(obs, bad)
    assert not p.ok and "not finite" in p.message and np.isnan(p.states).all()
    assert planner.plan(obs, est).ok
    with torch.no_grad():  # NaN scene probabilities: the model's output is not finite
        planner.model.prob[-1].bias.fill_(float("nan"))
    planner.reset(world)
    p = planner.plan(obs, est)
    assert not p.ok and "not finite" in p.message
    assert p.states.shape == (10, 4) and np.isnan(p.states).all() and np.isnan(p.controls).all()
    with torch.no_grad():  # NaN weights everywhere: the game layer refuses its parameters
        for q in planner.model.parameters():
            q.fill_(float("nan"))
    planner.reset(world)
    p = planner.plan(obs, est)
    assert not p.ok and "NaN" in p.message and np.isnan(p.states).all()


def test_others_goals_at_constant_velocity(runs, sample):
    hist, goals = sample["history"][0], sample["goals"][0]
    planner = load_planner(
        runs["epo"], StubWorld(goals), options={"others_goals": "constant_velocity"}
    )
    obs, est = _observe(hist[:, 0], hist[:, 1:].transpose(1, 0, 2))
    g = planner.goals(est)
    x = est.states[0]
    reach = x[2] * 10 * DT
    np.testing.assert_allclose(g[1], x[:2] + reach * np.array([np.cos(x[3]), np.sin(x[3])]))
    np.testing.assert_array_equal(g[0], goals[0])
    with pytest.raises(SpecError) as e:
        PlannerOptions.from_dict({"goals": "given"})
    assert e.value.field == "planner"


# ------------------------------------------------------------------------ refusals
def test_load_planner_refusals_name_the_field(runs, tmp_path, sample):
    goals = sample["goals"][0]
    ok = StubWorld(goals)
    with pytest.raises(CheckpointError) as e:
        load_planner(tmp_path / "nope", ok)
    assert e.value.where.endswith("nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError) as e:
        load_planner(tmp_path / "empty", ok)
    assert e.value.where.endswith("checkpoint.pt")
    with pytest.raises(SpecError) as e:
        load_planner(runs["vlstm"], ok)
    assert e.value.field == "model.kind"
    for world, field in [
        (StubWorld(goals, name="left-turn"), "world.scenario"),
        (StubWorld(goals, name=None), "world.scenario"),
        (StubWorld(goals, dataset_scenario="exid"), "world.scenario"),
        (StubWorld(np.zeros((3, 2)), n_agents=3), "world.n_agents"),
        (StubWorld(goals, dt=0.2), "world.dt"),
        (StubWorld(goals, horizon=40), "world.horizon"),
        (StubWorld(goals, history=18), "world.history"),
    ]:
        with pytest.raises(SpecError) as e:
            load_planner(runs["sc"], world)
        assert e.value.field == field, e.value
    with pytest.raises(SpecError) as e:
        load_planner(runs["sc"], ok, options={"others_goals": "oracle"})
    assert e.value.field == "planner.others_goals"


def test_run_stores_the_schema_and_older_runs_fall_back(runs, tmp_path, sample):
    """config.json names the history shape; a run without it reads the dataset manifest."""
    import shutil

    info = json.loads((runs["sc"] / "config.json").read_text())["data"]
    assert info["scenario"] == "rpi" and info["schema"]["history"] == [H + 1, 2, 4]
    old = tmp_path / "old"
    shutil.copytree(runs["sc"], old)
    cfg = json.loads((old / "config.json").read_text())
    del cfg["data"]["schema"], cfg["data"]["meta"]
    (old / "config.json").write_text(json.dumps(cfg))
    assert load_planner(old, StubWorld(sample["goals"][0])).spec.history_steps == H + 1


# ------------------------------------------------------------------------ closed loop
def test_a_closed_loop_crossing_episode_is_planned_by_the_network_and_repeats(runs):
    """The RPI-trained run drives the RPI crossing world (H6a's CrossingWorld) through the
    closed loop: every period planned by the network (no failed plan), the plan's first
    state the unicycle step from the exact ego state, and bit-identical for the same seed."""
    closed_loop = pytest.importorskip("scenarios.closed_loop")
    from scenarios.sim import make_world
    from solvers.control.estimate import UKFEstimator
    from solvers.control.track import PIDTracker

    world = make_world("crossing")
    planner = load_planner(runs["epo"], world)
    logs = []
    for _ in range(2):
        res = closed_loop.run_episode(
            world, UKFEstimator(history=H), planner, PIDTracker(), seed=1, max_steps=15
        )
        assert not [e for e in res.events if "plan" in str(e)], res.events
        logs.append(res.log)
    a, b = logs
    assert a.plan_ok.all() and len(a.t) >= 10
    np.testing.assert_array_equal(a.truth, b.truth)
    np.testing.assert_array_equal(a.plan_states, b.plan_states)
    x, s1 = a.obs_ego[:, None], a.plan_states[:, :1]
    first = x[..., :2] + DT * x[..., 2:3] * np.stack([np.cos(x[..., 3]), np.sin(x[..., 3])], -1)
    np.testing.assert_allclose(s1[..., :2], first, atol=1e-5)


def test_fused_layer_backend_plans_as_the_trained_backend(runs, sample):
    """Planning swaps ours' layer to the fused Gauss-Newton backend (one problem at a time
    is its strength); the plan equals the trained (structured) backend's to rounding."""
    from solvers.fast_gn import FusedGN
    from solvers.structured import StructuredGN

    hist, goals = sample["history"][0], sample["goals"][0]
    world = StubWorld(goals)
    fused = load_planner(runs["epo"], world)
    trained = load_planner(runs["epo"], world, layer_backend="model")
    assert isinstance(fused.model.layer.core.backend, FusedGN)
    assert isinstance(trained.model.layer.core.backend, StructuredGN)
    obs, est = _observe(hist[:, 0], hist[:, 1:].transpose(1, 0, 2), t=1.0)
    for p in (fused, trained):
        p.reset(world)
    a, b = fused.plan(obs, est), trained.plan(obs, est)
    assert a.ok and b.ok, (a.message, b.message)
    assert not np.allclose(a.controls, 0)  # a real plan, not a trivial one
    np.testing.assert_allclose(a.states, b.states, rtol=0, atol=1e-5)
    np.testing.assert_allclose(a.predictions, b.predictions, rtol=0, atol=1e-5)
    np.testing.assert_allclose(a.probabilities, b.probabilities, rtol=0, atol=1e-6)
    with pytest.raises(SpecError, match="planner.layer_backend"):
        load_planner(runs["epo"], world, layer_backend="fast")


# ------------------------------------------------------------------------ left turn
def test_left_turn_scenes_equal_the_dataset_samples():
    """Regression: a left-turn run once planned on scenes unlike its training data (the
    manifest states its frame in words, so the run was refused; headings wrapped per step
    where the dataset keeps them continuous with the current one in (-pi, pi], which flips
    the oncoming car's heading near pi; no lanes, paths, speed limits or goal candidates,
    so every plan failed). Reference: the generator's samples of one episode
    (:meth:`scenarios.left_turn.LeftTurnScenario.cut`), the world replayed from its stored
    seed and the planner fed the true states step by step."""
    from learning.observation import SceneSpec
    from scenarios import dataset as ds
    from scenarios.left_turn import LeftTurnRecipe, LeftTurnScenario, SDVPolicy, simulate
    from scenarios.sim import SCENARIO_FRAMES

    recipe = LeftTurnRecipe(
        episodes_per_geometry=1, episodes_per_shard=1, history=5, horizon=20,
        episode_steps=40, replay_extra=80, lane_points=6, goal_points=8,
    )  # fmt: skip
    sc = LeftTurnScenario(recipe)
    assert SCENARIO_FRAMES[sc.name] == "agent" and sc.meta()["frame"] not in ("world", "agent")
    unit = sc.run_unit(1, ds.unit_seed(0, 1))  # g1: val, not augmented
    world = sc.world("g1")
    world.reset(int(unit["world_seed"][0]))
    pol = SDVPolicy(world, recipe, "enter" if unit["intent"][0] else "wait")
    X = simulate(world, pol, recipe.episode_steps, until_outcome=recipe.replay_extra)[0].states
    H = recipe.history
    fields = ("history_valid", "lanes", "paths", "vref", "goal_candidates")
    spec = SceneSpec("left-turn", "sc", 2, H + 1, recipe.horizon, recipe.dt, frame="agent",
                     fields=fields, recipe=recipe.to_dict())  # fmt: skip
    planner = NetworkPlanner(torch.nn.Identity(), spec)
    planner.world = world
    near_pi = 0
    for k in range(len(unit["step"])):
        assert unit["step"][k] == k
        obs, est = _observe(
            X[k : k + 1, 0], X[max(0, k - H) : k + 1, 1:].transpose(1, 0, 2), k * DT
        )
        scene, frame = planner.scene(obs, est)
        np.testing.assert_allclose(frame.origin, X[k, 0, :2], atol=1e-12)
        np.testing.assert_array_equal(scene["history_valid"], unit["history_valid"][k])
        np.testing.assert_allclose(scene["history"], unit["history"][k], rtol=0, atol=1e-4)
        for f in fields[1:]:
            assert scene[f].dtype == np.float32 and scene[f].shape == unit[f].shape[1:], f
            np.testing.assert_allclose(scene[f], unit[f][k], rtol=0, atol=1e-4, err_msg=f)
        near_pi += abs(abs(unit["history"][k, -1, 1, 3]) - math.pi) < 0.3
    assert near_pi > 5  # the oncoming car's heading is near +-pi in many samples
