"""Networks, data loading and the CV baseline: output shapes, masks, ground truth, errors.

:class:`SyntheticRPI` is a TEST-ONLY stand-in generator: RPI's game, schema and file
format, but every future is the rollout of smooth random controls (or of zero controls:
straight lines at constant speed) from a state near the RPI start, so a dataset is written
in milliseconds without solving a game. The other learning tests import
:func:`synthetic_dataset` from here.
"""

from __future__ import annotations

import atexit
import functools
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from epo_casadi.errors import SpecError
from learning.baselines import ConstantVelocity, constant_velocity
from learning.data import SceneDataset, dataset_game, ground_truth
from learning.losses import marginal_loss, scene_loss
from learning.metrics import all_metrics
from learning.models import ModelConfig, build_model
from scenarios.dataset import DatasetError, SplitReader, generate
from scenarios.rpi import RPIRecipe, RPIScenario

#: tiny networks for fast tests
TINY = dict(hist_width=8, hist_layers=1, lane_width=8, global_width=16, heads=2, dec_width=16)
#: a short game: horizon 10 (the layer is 4x cheaper than at 40), history 4
RECIPE = dict(main_games=3, games_per_shard=1, horizon=10, history=4, ground_truth="potential")


class SyntheticRPI(RPIScenario):
    """TEST-ONLY: RPI files and game; futures are rollouts of random (or zero) controls."""

    def __init__(self, recipe, per_unit: int = 8, straight: bool = False):
        super().__init__(recipe)
        self.per_unit, self.straight = per_unit, straight

    def __getstate__(self):
        return {"recipe": self.recipe, "per_unit": self.per_unit, "straight": self.straight}

    def __setstate__(self, state):
        self.__dict__.update(state)

    def run_unit(self, index, seed):
        r = self.recipe
        rng = np.random.default_rng(seed)
        cfg = self.sample_config(index, rng)
        M, K, H = r.modes, r.horizon, r.history
        rows = []
        for k in range(self.per_unit):
            x = cfg.x0.copy()
            x[:, :2] += rng.normal(0, 0.3, (2, 2)) + 0.1 * k * np.stack(
                [np.cos(x[:, 3]), np.sin(x[:, 3])], 1
            )
            fut = np.zeros((M, 2, K, 4))
            ctl = np.zeros((M, 2, K, 2))
            for m in range(M):
                if not self.straight:
                    t = np.arange(K) * r.dt
                    ctl[m, :, :, 0] = rng.normal(0, 0.5, (2, 1)) * np.cos(t)
                    ctl[m, :, :, 1] = (
                        (0.6 if m else -0.6) * rng.uniform(0.2, 1.0, (2, 1)) * np.sin(0.5 + t)
                    )
                xs = x.copy()
                for s in range(K):
                    xs = xs + r.dt * np.stack(
                        [
                            xs[:, 2] * np.cos(xs[:, 3]),
                            xs[:, 2] * np.sin(xs[:, 3]),
                            ctl[m, :, s, 0],
                            ctl[m, :, s, 1],
                        ],
                        1,
                    )
                    fut[m, :, s] = xs
            hist = np.concatenate([self.pre_history(x, H), x[None]])
            rows.append(
                {
                    "history": hist,
                    "history_valid": np.arange(-H, 1) >= -k,
                    "future": fut,
                    "future_controls": ctl,
                    "mode_share": np.full(M, 1 / M),
                    "mode_valid": np.ones(M, bool),
                    "goals": cfg.goals,
                    "params": self.params(cfg, x),
                    "collision_weight": cfg.collision_weight,
                    "main_game": index,
                    "main_mode": 0,
                    "main_share": 1.0,
                    "step": k,
                    "gt_mode": k % M,
                }
            )
        return self._stack(rows)


_ROOT = Path(tempfile.mkdtemp(prefix="epo-learning-tests-"))
atexit.register(shutil.rmtree, _ROOT, ignore_errors=True)


@functools.cache
def synthetic_dataset(straight: bool = False, per_unit: int = 8, horizon: int = 10) -> Path:
    """A finished synthetic dataset (3 main games: one per split), written once per process."""
    d = _ROOT / f"synthetic-{int(straight)}-{per_unit}-{horizon}"
    recipe = RPIRecipe(**{**RECIPE, "horizon": horizon})
    generate(
        SyntheticRPI(recipe, per_unit, straight), d, seed=int(straight), workers=1, progress=False
    )
    return d


def scene_batch(n: int = 4):
    with SceneDataset(synthetic_dataset(), "train") as ds:
        return ds.batch(np.arange(n)), ds.game


# ----------------------------------------------------------------------------- models
@pytest.mark.parametrize("kind", ["epo", "sc", "vlstm", "cv"])
def test_output_shapes(kind):
    batch, game = scene_batch(4)
    B, N, K, M = 4, game.N, game.K, 2
    torch.manual_seed(0)
    model = (
        ConstantVelocity(K, M)
        if kind == "cv"
        else build_model(ModelConfig(kind=kind, modes=M, **TINY), game)
    )
    out = model(batch)
    assert out["pos"].shape == (B, M, N, K, 2) and out["pos"].dtype == torch.float32
    assert torch.isfinite(out["pos"]).all()
    if kind == "vlstm":
        assert out["marginal_logits"].shape == (B, N, M) and "logits" not in out
    else:
        assert out["logits"].shape == (B, M) and torch.isfinite(out["logits"]).all()
    if kind in ("epo", "sc"):
        x0 = batch["history"][:, -1]  # (B, N, 4): the first step follows the unicycle from x0
        v, th = x0[..., 2], x0[..., 3]
        first = x0[..., :2] + game.dt * torch.stack([v * torch.cos(th), v * torch.sin(th)], -1)
        torch.testing.assert_close(
            out["pos"][:, :, :, 0], first[:, None].expand(B, M, N, 2), atol=1e-5, rtol=0
        )
        assert out["states"].shape == (B, M, N, K, 4) and out["controls"].shape == (B, M, N, K, 2)
    if kind == "epo":
        p, L = out["params"], game.params
        assert p.shape == (B, M, game.n_p) and out["status"].shape == (B, M)
        assert (p[..., L.group("w_own")] > 0).all() and (p[..., L.group("w_pair")] > 0).all()
        for i, a in enumerate(game.agent_names):
            torch.testing.assert_close(p[..., L[f"x0.{a}"].slice], x0[:, None, i].expand(B, M, 4))
            torch.testing.assert_close(
                p[..., L[f"goal.{a}"].slice], batch["goals"][:, None, i].expand(B, M, 2)
            )
        assert out["init_pos"].shape == (B, M, N, K, 2)
    if kind != "cv":  # gradients reach every network part but the (unused) lane encoder
        model.zero_grad()
        logits = out.get("logits", out.get("marginal_logits"))
        (out["pos"].square().mean() + logits.square().mean()).backward()
        missing = [
            n
            for n, q in model.named_parameters()
            if q.grad is None and not n.startswith(("encoder.lane", "encoder.lane_proj"))
        ]  # no lanes in RPI
        assert not missing, missing


def test_epo_ablations():
    batch, game = scene_batch(2)
    torch.manual_seed(0)
    m = build_model(ModelConfig(kind="epo", learned_init=False, goal_features=False, **TINY), game)
    out = m(batch)
    goal = [game.params[f"w.{a}.goal"].start for a in game.agent_names]
    assert (out["params"][..., goal] == 0).all()
    # zero initial strategies: the initial rollout is the constant-speed, constant-heading path
    x0 = batch["history"][:, -1]
    t = torch.arange(1, game.K + 1, dtype=torch.float32)[:, None] * game.dt
    vel = torch.stack([x0[..., 2] * torch.cos(x0[..., 3]), x0[..., 2] * torch.sin(x0[..., 3])], -1)
    line = x0[..., None, :2] + t * vel[..., None, :]
    torch.testing.assert_close(
        out["init_pos"], line[:, None].expand_as(out["init_pos"]), atol=1e-5, rtol=0
    )


def test_model_config_errors_name_the_field():
    for kw, field in [
        ({"kind": "gan"}, "model.kind"),
        ({"backbone": "x"}, "model.backbone"),
        ({"modes": 0}, "model.modes"),
        ({"global_width": 30, "heads": 4}, "model.heads"),
        ({"step_size": 0.0}, "model.step_size"),
        ({"backward": "adjoint"}, "model.backward"),
    ]:
        with pytest.raises(SpecError) as e:
            ModelConfig(**kw)
        assert e.value.field == field


# ----------------------------------------------------------------------------- masks
def test_loss_and_metric_masks_ignore_masked_agents():
    torch.manual_seed(0)
    B, M, N, T = 3, 2, 2, 5
    gt = torch.randn(B, N, T, 2)
    pos = gt[:, None].repeat(1, M, 1, 1, 1)
    pos[:, :, 1] += 100.0  # agent 1 is far off in every mode
    logits, mlog = torch.zeros(B, M), torch.zeros(B, N, M)
    mask = torch.tensor([[True, False]] * B)
    assert scene_loss(pos, logits, gt, mask=mask)["imitation"].item() == 0.0
    assert scene_loss(pos, logits, gt)["imitation"].item() > 1e3
    assert marginal_loss(pos, mlog, gt, mask=mask)["imitation"].item() == 0.0
    m = all_metrics(pos, gt, torch.softmax(logits, -1), torch.full((N,), 0.25), mask=mask)
    for k in ("minADE", "minFDE", "minSADE", "minSFDE", "OR"):
        assert (m[k] == 0).all(), k


# ----------------------------------------------------------------------------- data
def test_ground_truth_picks_gt_mode_or_mode_zero():
    fut = np.arange(3 * 2 * 1 * 2 * 4, dtype=np.float32).reshape(3, 2, 1, 2, 4)
    gt_mode = np.array([1, 0, 1], np.int8)
    g = ground_truth(fut, gt_mode)
    assert g.shape == (3, 1, 2, 4)
    for b in range(3):
        np.testing.assert_array_equal(g[b], fut[b, gt_mode[b]])
    np.testing.assert_array_equal(ground_truth(fut), fut[:, 0])
    torch.testing.assert_close(
        ground_truth(torch.from_numpy(fut), torch.from_numpy(gt_mode)), torch.from_numpy(g)
    )
    with pytest.raises(DatasetError, match="gt_mode"):
        ground_truth(fut, np.array([0, 2, 0]))


def test_dataset_batches_memory_and_streaming_agree():
    d = synthetic_dataset()
    with (
        SceneDataset(d, "train", in_memory=True) as a,
        SceneDataset(d, "train", in_memory=False) as b,
    ):
        assert a.in_memory and not b.in_memory and len(a) == len(b) == 8
        assert (a.n_agents, a.history_steps, a.modes, a.horizon) == (2, 5, 2, 10)
        ba = list(a.batches(3, shuffle=True, seed=1, epoch=2))
        bb = list(b.batches(3, shuffle=True, seed=1, epoch=2))
        assert [len(x["index"]) for x in ba] == [3, 3, 2]
        for x, y in zip(ba, bb, strict=True):
            assert (
                x.keys()
                == y.keys()
                == {"history", "goals", "history_valid", "agents_mask", "gt", "gt_states", "index"}
            )
            for k in x:
                torch.testing.assert_close(x[k], y[k], rtol=0, atol=0)
        idx = torch.cat([x["index"] for x in ba]).tolist()
        assert sorted(idx) == list(range(8)) and idx != list(range(8))
        assert (a.order(True, 1, 2) == b.order(True, 1, 2)).all()
        assert (a.order(True, 1, 2) != a.order(True, 1, 3)).any()
        x = ba[0]
        assert x["history"].shape == (3, 5, 2, 4) and x["gt"].shape == (3, 2, 10, 2)
        with SplitReader(d, "train") as r:  # the gt is future[gt_mode]
            raw = r.read(x["index"].numpy())
        gm = raw["gt_mode"].astype(int)
        np.testing.assert_array_equal(x["gt_states"].numpy(), raw["future"][np.arange(3), gm])
        assert set(gm) == {0, 1}
        one = a[5]
        assert one["history"].shape == (5, 2, 4) and int(one["index"]) == 5


def test_dataset_errors_name_the_field(tmp_path):
    with pytest.raises(DatasetError, match="no such dataset directory"):
        SceneDataset(tmp_path / "nope", "train")
    with pytest.raises(SpecError) as e:
        SceneDataset(synthetic_dataset(), "training")
    assert e.value.field == "split"
    bad = tmp_path / "bad"
    shutil.copytree(synthetic_dataset(), bad)
    m = json.loads((bad / "manifest.json").read_text())
    del m["schema"]["future"]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(DatasetError, match=r"manifest\.json\.schema\.future: missing"):
        SceneDataset(bad, "train")
    m["scenario"] = "mars"
    with pytest.raises(DatasetError, match="no game known for scenario 'mars'"):
        dataset_game(m)
    with SceneDataset(synthetic_dataset(), "train") as ds, pytest.raises(SpecError, match="index"):
        ds.batch([8])


# ----------------------------------------------------------------------------- CV
def test_cv_extrapolates_the_last_displacement():
    hist = torch.zeros(1, 3, 2, 4)
    hist[0, :, 0, :2] = torch.tensor([[0.0, 0.0], [0.5, 0.25], [1.0, 0.5]])
    hist[0, :, 1, :2] = torch.tensor([[3.0, 3.0], [3.0, 3.0], [3.0, 3.0]])
    pos = constant_velocity(hist, 4)
    assert pos.shape == (1, 2, 4, 2)
    torch.testing.assert_close(
        pos[0, 0], torch.tensor([[1.5, 0.75], [2.0, 1.0], [2.5, 1.25], [3.0, 1.5]]), rtol=0, atol=0
    )
    torch.testing.assert_close(pos[0, 1], torch.full((4, 2), 3.0), rtol=0, atol=0)
    out = ConstantVelocity(4, 3)({"history": hist})
    assert out["pos"].shape == (1, 3, 2, 4, 2) and (out["logits"] == 0).all()
    assert (constant_velocity(hist[:, -1:], 2) == hist[:, -1:, :, None, :2].squeeze(1)).all()
    with pytest.raises(SpecError, match="horizon"):
        ConstantVelocity(0)


def test_collision_margin_sets_the_reach_of_ours_game_only():
    """``collision_margin`` moves the reach of ours' collision term to ``r_i + r_j + margin``
    (checked against the hinge by hand at a fixed separation); the dataset's game, its
    radii (the overlap rate's) and the other energy terms stay as they were."""
    _, game = scene_batch(2)
    cfg = ModelConfig(kind="epo", collision_margin=1.0, **TINY)
    model = build_model(cfg, game)
    assert build_model(ModelConfig(kind="epo", **TINY), game).game is game
    assert model.game is not game and np.array_equal(model.game.radii(), game.radii())
    # both agents standing still 1.2 m apart, zero controls, pair weight 3
    p = game.default_params()
    L = game.params
    for name, val in [("x0.robot.x", 0.0), ("x0.pedestrian.x", 1.2), ("x0.robot.v", 0.0)]:
        p[L.names.index(name)] = val
    p[L.names.index("x0.pedestrian.y")] = p[L.names.index("x0.robot.y")]
    p[L.names.index("x0.pedestrian.v")] = 0.0
    p[L.names.index("w.robot-pedestrian.collision")] = 3.0
    u = np.zeros(game.n_u)
    e_new = np.asarray(model.game.function("term_energies")(u, p)).ravel()
    e_old = np.asarray(game.function("term_energies")(u, p)).ravel()
    reach = float(np.sum(game.radii())) + 1.0  # 0.25 + 0.25 + 1.0 = 1.5 m
    hinge = reach - np.sqrt(1.2**2 + 1e-9)
    expected = 0.5 * game.K * (3.0 * hinge) ** 2  # every stage k = 1..K
    diff = e_new - e_old
    assert np.isclose(diff.sum(), expected, rtol=1e-12)
    assert np.count_nonzero(np.abs(diff) > 1e-12) == 1  # only the collision term changed
    with pytest.raises(SpecError) as e:
        ModelConfig(kind="sc", collision_margin=1.0)
    assert e.value.field == "model.collision_margin"
