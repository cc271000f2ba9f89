"""Padded agents (``agents_mask``): no value of a pad reaches an output or a gradient of the
real agents, a scene without a pad gives the numbers computed without masks, the game layer
leaves a pad's controls at 0 and solves the real agents' game, the metrics count real agents
only, and a padded dataset trains.

The scenes are a three-unicycle crossing (:func:`tests.helpers.crossing_spec`, K = 6); the
padded slot is the middle one (agent 1) in scene 0 and the last one (agent 2) in scene 2;
scene 1 has every agent. Models and scenes are float64.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

import scenarios.plotting
from epo_casadi import GameSpec, PotentialGame
from epo_casadi.errors import SpecError
from learning.data import SceneDataset
from learning.layer import GameLayer
from learning.losses import goal_loss, marginal_loss, scene_loss
from learning.masks import (
    PAD_SPACING,
    active,
    agents_mask,
    neutral_scene,
    own_mask,
    pad_positions,
    pair_mask,
)
from learning.metrics import all_metrics, marginal_to_joint, min_ade, min_sade
from learning.models import ModelConfig, build_model
from learning.scoring import evaluate_model
from learning.show import show_predictions
from learning.train import PAPER_LOSS_WEIGHTS, TrainConfig, compute_loss, train
from scenarios.dataset import DatasetError, FieldSpec, generate
from scenarios.rpi import RPIRecipe
from solvers.lm import LMOptions
from tests.helpers import crossing_spec
from tests.test_models import RECIPE, TINY, SyntheticRPI, synthetic_dataset

K, H, N, B = 6, 4, 3, 3
#: scene 0: agent 1 (middle) padded; scene 1: all real; scene 2: agent 2 (last) padded
MASK = torch.tensor([[True, False, True], [True, True, True], [True, True, False]])
PADS = [(0, 1), (2, 2)]
EXTREMES = (1e30, -1e30, float("nan"), float("inf"))

#: (kind, extra settings): ours unrolled and implicit, with given, candidate and regressed
#: goals; the baselines
MODELS = {
    "epo": ("epo", {}),
    "epo-implicit": ("epo", {"backward": "implicit"}),
    "epo-candidates": ("epo", {"goal_decoder": "candidates"}),
    "epo-regress": ("epo", {"goal_decoder": "regress"}),
    "sc": ("sc", {}),
    "vlstm": ("vlstm", {}),
    "tgl": ("tgl", {}),
}


@pytest.fixture(scope="module")
def game() -> PotentialGame:
    return PotentialGame(crossing_spec(N=N, K=K))


def _batch(game, seed: int = 0) -> dict:
    """A float64 batch of B crossing scenes (agents moving, goals, candidates, sizes)."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.as_tensor(game.params.defaults()[game.params.group("x0")]).reshape(N, 4)
    t = torch.arange(-H, 1, dtype=torch.float64)[:, None] * game.dt
    hist = x0[None, None].repeat(B, H + 1, 1, 1)
    vel = torch.stack([torch.cos(x0[:, 3]), torch.sin(x0[:, 3])], -1) * x0[:, 2:3]
    hist[..., :2] += t[..., None] * vel + 0.05 * torch.randn(B, H + 1, N, 2, generator=g)
    goals = torch.as_tensor(game.params.defaults()[game.params.group("goal")]).reshape(N, 2)
    goals = goals[None].repeat(B, 1, 1) + 0.2 * torch.randn(B, N, 2, generator=g)
    steps = torch.arange(1, K + 1, dtype=torch.float64)[:, None] * game.dt
    gt = hist[:, -1, :, None, :2] + steps * vel[:, None] * 0.8
    gt_states = torch.cat([gt, hist[:, -1, :, None, 2:].expand(B, N, K, 2)], -1)
    cand = goals[:, :, None] + torch.randn(B, N, 5, 2, generator=g)
    return {
        "history": hist,
        "goals": goals,
        "goal_candidates": cand,
        "radius": torch.full((B, N), 0.25, dtype=torch.float64),
        "length": torch.full((B, N), 0.5, dtype=torch.float64),
        "width": torch.full((B, N), 0.4, dtype=torch.float64),
        "gt": gt,
        "gt_states": gt_states,
        "agents_mask": MASK.clone(),
    }


def _fill_pads(batch: dict, value: float) -> dict:
    """The batch with every per-agent value of every padded agent set to ``value``."""
    out = {k: v.clone() for k, v in batch.items()}
    for b, i in PADS:
        out["history"][b, :, i] = value
        for k in ("goals", "goal_candidates", "radius", "length", "width", "gt", "gt_states"):
            out[k][b, i] = value
    return out


def _model(game, name: str, mode: str = "train"):
    kind, extra = MODELS[name]
    torch.manual_seed(0)
    cfg = ModelConfig(kind=kind, modes=2, layer_compiled="no", **extra, **TINY)
    model = build_model(cfg, game).double()
    return model.train(mode == "train")


def _run(model, kind: str, batch: dict, mask=True):
    """Outputs, loss parts and the gradient of every parameter."""
    model.zero_grad(set_to_none=True)
    out = model(batch)
    m = batch.get("agents_mask") if mask else None
    parts = compute_loss(kind, out, batch["gt"], PAPER_LOSS_WEIGHTS[kind], m)
    parts["loss"].backward()
    grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    return out, parts, grads


def _assert_same(a: dict, b: dict, what: str):
    assert a.keys() == b.keys(), what
    for k in a:
        if isinstance(a[k], torch.Tensor):
            assert torch.equal(a[k], b[k]), f"{what}: {k}"


# ----------------------------------------------------------------------------- (a)
@pytest.mark.parametrize("mode", ["train", "eval"])
@pytest.mark.parametrize("name", list(MODELS))
def test_a_pad_changes_no_output_and_no_gradient(game, name, mode):
    """Every per-agent value of a pad set to 1e30, -1e30, NaN, inf in turn: every output
    (the pads' included: they are neutral), every loss part and the gradient of every model
    parameter are bitwise those with zeros in the pad."""
    kind = MODELS[name][0]
    model = _model(game, name, mode)
    base = _batch(game)
    out0, parts0, grads0 = _run(model, kind, _fill_pads(base, 0.0))
    assert torch.isfinite(parts0["loss"]) and len(grads0) > 10
    assert all(torch.isfinite(g).all() for g in grads0.values())
    assert torch.isfinite(out0["pos"]).all()
    # a pad stays at rest at its neutral position, with zero controls
    rest = pad_positions(base)
    for b, i in PADS:
        assert torch.equal(out0["pos"][b, :, i], rest[b, i].expand_as(out0["pos"][b, :, i]))
        if "controls" in out0:
            assert torch.equal(
                out0["controls"][b, :, i], torch.zeros_like(out0["controls"][b, :, i])
            )
    for value in EXTREMES:
        out, parts, grads = _run(model, kind, _fill_pads(base, value))
        _assert_same(out, out0, f"{name} outputs, pad {value}")
        _assert_same(parts, parts0, f"{name} loss, pad {value}")
        _assert_same(grads, grads0, f"{name} gradients, pad {value}")
    # the same change on a real agent does change the outputs (the test can fail)
    real = _fill_pads(base, 0.0)
    real["history"][0, :, 2, :2] += 0.5
    out, parts, _ = _run(model, kind, real)
    assert not torch.equal(out["pos"][0, :, 0], out0["pos"][0, :, 0])
    assert not torch.equal(parts["loss"], parts0["loss"])


# ----------------------------------------------------------------------------- (b)
@pytest.mark.parametrize("name", list(MODELS))
def test_b_all_real_mask_gives_the_numbers_without_it(game, name):
    kind = MODELS[name][0]
    model = _model(game, name)
    with_key = _batch(game)
    with_key["agents_mask"] = torch.ones(B, N, dtype=torch.bool)
    without = {k: v for k, v in with_key.items() if k != "agents_mask"}
    out0, parts0, grads0 = _run(model, kind, without, mask=False)
    out1, parts1, grads1 = _run(model, kind, with_key)
    _assert_same(out1, out0, f"{name} outputs")
    _assert_same(parts1, parts0, f"{name} loss")
    _assert_same(grads1, grads0, f"{name} gradients")
    assert neutral_scene(without) is without
    assert "agents_mask" not in neutral_scene(with_key)


# ----------------------------------------------------------------------------- (c)
def _real_game(game) -> PotentialGame:
    """The game of agents 0 and 2 alone (the real agents of scene 0)."""
    spec = game.spec
    agents = [spec.agents[0], spec.agents[2]]
    return PotentialGame(GameSpec(agents, list(spec.pair_features), horizon=K, dt=spec.dt))


def _layer_inputs(game):
    """Ours' decoded parameters and initial strategies of scene 0 (agent 1 padded)."""
    model = _model(game, "epo", "eval")
    batch = _fill_pads(_batch(game), float("nan"))
    with torch.no_grad():
        sc = neutral_scene(batch)
        z = model.encoder(sc)
        p = model.game_params(sc, z)[0].double()  # (M, n_p)
        u0 = model.initial_strategies(z, sc["agents_mask"])[0].double()
    return p, u0


def _options(backward: str, backend: str) -> LMOptions:
    if backward == "unrolled":
        return LMOptions.paper(backend=backend)
    return LMOptions(steps=50, step_size=1.0, damping=10.0, adaptive_damping=False, backend=backend)


@pytest.mark.parametrize("backend", ["structured", "dense", "fused"])
@pytest.mark.parametrize("backward", ["unrolled", "implicit"])
def test_c_layer_leaves_a_pad_at_rest_and_solves_the_real_agents_game(
    game, backward, backend, monkeypatch
):
    """A pad's weights are 0 and its initial strategy 0: its residual rows and Jacobian
    columns are exactly 0, its controls stay exactly 0, and the real agents' controls,
    states and gradients are those of the game without the pad."""
    p, u0 = _layer_inputs(game)
    L = game.params
    names = [b.name for b in L.blocks if b.group in ("w_own", "w_pair") and "a1" in b.name]
    assert len(names) == 9 and all(float(p[:, L[n].start].abs().max()) == 0 for n in names)
    pad_u = slice(int(game.uoff[1]), int(game.uoff[2]))
    assert float(u0[:, pad_u].abs().max()) == 0
    layer = GameLayer(game, _options(backward, backend), backward=backward)
    P = p.clone().requires_grad_()
    U0 = u0.clone().requires_grad_()

    def boom(*a, **k):
        raise AssertionError("the implicit backward fell back to the pseudo-inverse")

    monkeypatch.setattr(np.linalg, "pinv", boom)
    out = layer(P, U0)
    U = out.controls.detach()
    assert torch.equal(U[:, pad_u], torch.zeros_like(U[:, pad_u]))
    res, jac = game.function("residual"), game.function("jacobian")
    rows = [t.rows for t in game.terms if "a1" in t.agents]
    for m in range(p.shape[0]):
        r = np.array(res(U[m].numpy(), p[m].numpy())).ravel()
        J = np.array(jac(U[m].numpy(), p[m].numpy()))
        assert all(np.all(r[s] == 0) for s in rows)
        assert np.all(J[:, pad_u] == 0) and np.abs(r).max() > 0
    # the real agents' game alone: same controls, states and gradients
    g2 = _real_game(game)
    L2 = g2.params
    p2 = torch.zeros(p.shape[0], g2.n_p, dtype=torch.float64)
    for b in L2.blocks:
        p2[:, b.slice] = p[:, L[b.name].slice]
    ureal = np.r_[game.uoff[0] : game.uoff[1], game.uoff[2] : game.uoff[3]]
    xreal = np.r_[game.xoff[0] : game.xoff[1], game.xoff[2] : game.xoff[3]]
    P2 = p2.clone().requires_grad_()
    U02 = u0[:, ureal].clone().requires_grad_()
    out2 = GameLayer(g2, _options(backward, backend), backward=backward)(P2, U02)
    torch.testing.assert_close(out.controls[:, ureal], out2.controls, rtol=0, atol=1e-10)
    torch.testing.assert_close(out.states[:, xreal], out2.states, rtol=0, atol=1e-10)
    # a loss on every output, the pad's included: the pad's cotangents reach no real input
    w = torch.linspace(0.5, 1.5, game.n_x, dtype=torch.float64)
    (out.states * w).sum().backward()
    (out2.states * w[xreal]).sum().backward()
    assert torch.isfinite(P.grad).all() and torch.isfinite(U0.grad).all()
    for b in L2.blocks:
        torch.testing.assert_close(
            P.grad[:, L[b.name].slice], P2.grad[:, b.slice], atol=1e-8, rtol=0
        )
    torch.testing.assert_close(U0.grad[:, ureal], U02.grad, rtol=0, atol=1e-8)


def test_c_implicit_solve_decouples_a_zero_hessian_row():
    """The implicit backward's solve: a control with a zero Hessian row gets 0, the others
    the solution of the rest; equal to the pseudo-inverse (computed by numpy), where a
    plain solve of the whole system fails."""
    from learning.layer_core import _sym_solve

    rng = np.random.default_rng(0)
    A = rng.normal(size=(2, 4, 4))
    H = np.zeros((2, 5, 5))
    keep = [0, 1, 3, 4]
    H[:, np.ix_(keep, keep)[0], np.ix_(keep, keep)[1]] = A @ A.transpose(0, 2, 1) + np.eye(4)
    rhs = rng.normal(size=(2, 5))
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.solve(H, rhs[..., None])
    w = _sym_solve(H, rhs)
    ref = np.einsum("bij,bj->bi", np.linalg.pinv(H), rhs)
    np.testing.assert_allclose(w, ref, rtol=0, atol=1e-10)
    assert np.all(w[:, 2] == 0)


# ----------------------------------------------------------------------------- masks
def test_neutral_scene_places_pads_far_apart_and_pair_masks_follow_the_game(game):
    batch = _fill_pads(_batch(game), float("nan"))
    sc = neutral_scene(batch)
    pos = pad_positions(batch)
    real_x = batch["history"][..., 0][MASK[:, None].expand(B, H + 1, N)]
    for b, i in PADS:
        assert torch.equal(sc["history"][b, :, i, :2], pos[b, i].expand(H + 1, 2))
        assert torch.equal(sc["history"][b, :, i, 2:], torch.zeros(H + 1, 2, dtype=torch.float64))
        assert torch.equal(sc["goals"][b, i], pos[b, i])
        assert torch.equal(sc["gt"][b, i], pos[b, i].expand(K, 2))
        assert float(sc["radius"][b, i]) == 1.0
        assert pos[b, i, 0] >= real_x.max() + PAD_SPACING
    for k, v in sc.items():
        if v.is_floating_point():
            assert torch.isfinite(v).all(), k
    # real agents untouched; the other slots' positions are distinct too
    assert torch.equal(sc["history"][1], batch["history"][1])
    assert len(set(pos[0, :, 0].tolist())) == N
    m = agents_mask(batch)
    assert pair_mask(game, m).tolist() == [
        [False, True, False],  # a0-a1, a0-a2, a1-a2
        [True, True, True],
        [True, False, False],
    ]
    assert own_mask(game, m).shape == (B, len(game.params.group("w_own")))
    assert own_mask(game, m)[0].tolist() == [True] * 7 + [False] * 7 + [True] * 7
    assert active(torch.ones(2, 3, dtype=torch.bool)) is None
    with pytest.raises(SpecError, match="agents_mask"):
        agents_mask({"history": batch["history"], "agents_mask": torch.ones(B, N + 1)})


# ----------------------------------------------------------------------------- (d)
def _metric_case(pad_value: float):
    """One scene, 2 modes, agents 0 and 2 real 5 m apart, agent 1 a pad that sits on agent 0
    in mode 0, predicted at ``-pad_value`` in mode 1, with ground truth ``pad_value``.

    Mode 0: agent 0 exact, agent 2 1 m off; mode 1: agent 0 2 m off, agent 2 exact."""
    T = 2
    gt = torch.zeros(1, 3, T, 2, dtype=torch.float64)
    gt[0, 0, :, 0] = torch.tensor([0.0, 1.0])
    gt[0, 2, :, 0] = torch.tensor([0.0, 1.0])
    gt[0, 2, :, 1] = 5.0
    gt[0, 1] = pad_value
    pred = gt[:, None].repeat(1, 2, 1, 1, 1)
    pred[0, 0, 2, :, 1] += 1.0
    pred[0, 1, 0, :, 1] += 2.0
    pred[0, 0, 1] = gt[0, 0]  # the pad overlaps agent 0 in mode 0
    pred[0, 1, 1] = -pad_value  # far off its ground truth in mode 1
    mask = torch.tensor([[True, False, True]])
    return pred, gt, mask


@pytest.mark.parametrize("pad_value", [1e3, *EXTREMES])
def test_d_metrics_count_real_agents_and_real_pairs_only(pad_value):
    pred, gt, mask = _metric_case(pad_value)
    probs = torch.tensor([[0.7, 0.3]], dtype=torch.float64)
    radii = torch.full((3,), 0.25, dtype=torch.float64)
    boxes = {
        "length": torch.tensor([[0.5, pad_value, 0.5]], dtype=torch.float64),
        "width": torch.tensor([[0.4, pad_value, 0.4]], dtype=torch.float64),
        "start": gt[:, :, 0] - torch.tensor([1.0, 0.0], dtype=torch.float64),
        "heading0": torch.zeros(1, 3, dtype=torch.float64),
    }
    m = all_metrics(pred, gt, probs, radii, mask=mask, boxes=boxes)
    # by hand: per agent the best mode is exact (0); mode 0 averages (0 + 1) / 2 = 0.5,
    # mode 1 (2 + 0) / 2 = 1; the real agents stay 5 m apart
    hand = {"minADE": 0.0, "minFDE": 0.0, "minSADE": 0.5, "minSFDE": 0.5, "OR": 0.0}
    hand["OR_circle"] = 0.0
    assert {k: float(v) for k, v in m.items()} == hand
    real = [0, 2]
    alone = all_metrics(
        pred[:, :, real],
        gt[:, real],
        probs,
        radii[real],
        boxes={k: v[:, real] for k, v in boxes.items()},
    )
    assert {k: float(v) for k, v in alone.items()} == hand
    # without the mask the pad would dominate: an overlap with agent 0, a far-off error
    finite = _metric_case(1e3)
    unmasked = all_metrics(finite[0], finite[1], probs, radii)
    assert float(unmasked["OR"]) == 1.0 and float(min_ade(finite[0], finite[1])) > 0
    assert float(min_sade(finite[0], finite[1], mask)) == 0.5


@pytest.mark.parametrize("pad_value", [0.0, *EXTREMES])
def test_d_marginal_joint_scenes_ignore_the_pads_probabilities(pad_value):
    pred, gt, mask = _metric_case(0.0)
    probs = torch.tensor([[[0.9, 0.1], [pad_value, 0.5], [0.2, 0.8]]], dtype=torch.float64)
    joint, p = marginal_to_joint(pred, probs, mask)
    # joint mode 0: agent 0's mode 0 with agent 2's mode 1 (both exact); products 0.72, 0.02
    torch.testing.assert_close(p, torch.tensor([[0.72, 0.02]], dtype=torch.float64) / 0.74)
    assert torch.equal(joint[0, 0, 0], gt[0, 0]) and torch.equal(joint[0, 0, 2], gt[0, 2])
    m = all_metrics(pred, gt, probs, torch.full((3,), 0.25), mask=mask)
    assert float(m["minSADE"]) == 0.0 and float(m["OR"]) == 0.0


@pytest.mark.parametrize("pad_value", [0.0, *EXTREMES])
def test_d_losses_average_over_real_agents(pad_value):
    pred, gt, mask = _metric_case(pad_value)
    pred = pred.clone().requires_grad_()
    logits = torch.tensor([[0.2, -0.1]], dtype=torch.float64)
    real = [0, 2]
    got = scene_loss(pred, logits, gt, mask=mask)
    ref = scene_loss(pred[:, :, real], logits, gt[:, real])
    for k in got:
        assert got[k].item() == pytest.approx(ref[k].item(), abs=1e-15), k
    # by hand: mode 0 = (0 + 1) / 2 (squared error 1 on agent 2), the best
    assert got["imitation"].item() == 0.5
    got["loss"].backward()
    assert torch.isfinite(pred.grad).all() and float(pred.grad[:, :, 1].abs().max()) == 0
    mlog = torch.zeros(1, 3, 2, dtype=torch.float64)
    mlog[0, 1] = pad_value
    mg = marginal_loss(pred, mlog, gt, mask=mask)
    mr = marginal_loss(pred[:, :, real], mlog[:, real], gt[:, real])
    assert mg["loss"].item() == pytest.approx(mr["loss"].item(), abs=1e-15)
    # goal losses: regressed goals and candidates
    goals = pred[:, :, :, -1].detach()
    out = {"decoded_goals": True, "goals": goals}
    gl = goal_loss(out, gt, mask)
    assert float(gl) == pytest.approx(
        float(goal_loss({**out, "goals": goals[:, :, real]}, gt[:, real]))
    )
    cand = gt[:, :, -1:, :].repeat(1, 1, 3, 1) + torch.tensor([0.0, 1.0, 2.0])[:, None]
    glog = torch.zeros(1, 3, 3, dtype=torch.float64)
    glog[0, 1] = pad_value
    out = {"decoded_goals": True, "goal_logits": glog, "goal_candidates": cand}
    sel = {"decoded_goals": True, "goal_logits": glog[:, real], "goal_candidates": cand[:, real]}
    assert float(goal_loss(out, gt, mask)) == pytest.approx(float(goal_loss(sel, gt[:, real])))
    assert np.isfinite(float(goal_loss(out, gt, mask)))


# ----------------------------------------------------------------------------- (e)
class PaddedRPI(SyntheticRPI):
    """TEST-ONLY: the synthetic RPI set with ``agents_mask``: agent 1 is a pad in every
    sample of odd step, its per-agent arrays set to 1e30 (an extreme a reader never writes)."""

    def schema(self):
        return {**super().schema(), "agents_mask": FieldSpec((2,), "bool", "False: padding")}

    def _stack(self, rows):
        for row in rows:
            pad = row["step"] % 2 == 1
            row["agents_mask"] = np.array([True, not pad])
            if pad:
                for k in ("history", "future", "future_controls"):  # agent axis 1
                    row[k] = np.array(row[k], dtype=float)
                    row[k][:, 1] = 1e30
                row["goals"] = np.array(row["goals"], dtype=float)
                row["goals"][1] = 1e30
        return super()._stack(rows)


@pytest.fixture(scope="module")
def padded_dataset(tmp_path_factory):
    d = tmp_path_factory.mktemp("padded") / "data"
    generate(PaddedRPI(RPIRecipe(**RECIPE), 8), d, seed=0, workers=1, progress=False)
    return d


def test_e_dataset_batches_carry_agents_mask(padded_dataset, tmp_path):
    with SceneDataset(padded_dataset, "train") as ds:
        b = ds.batch(np.arange(8))
    assert b["agents_mask"].dtype == torch.bool and b["agents_mask"].shape == (8, 2)
    assert b["agents_mask"][:, 0].all()
    assert b["agents_mask"][:, 1].tolist() == [s % 2 == 0 for s in range(8)]
    pads = b["history"].permute(0, 2, 1, 3)[~b["agents_mask"]]  # (pads, H+1, 4) as written
    assert pads.shape[0] == 4 and float(pads.min()) == pytest.approx(1e30, rel=1e-6)
    with SceneDataset(synthetic_dataset(), "train") as ds:  # no field: all True
        assert ds.batch([0, 1])["agents_mask"].tolist() == [[True, True]] * 2
    bad = tmp_path / "bad"
    shutil.copytree(padded_dataset, bad)
    man = json.loads((bad / "manifest.json").read_text())
    man["schema"]["agents_mask"]["shape"] = [3]
    (bad / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(DatasetError, match=r"schema\.agents_mask.*\(2,\)"):
        SceneDataset(bad, "train")


@pytest.mark.parametrize("kind", ["epo", "sc", "vlstm", "tgl"])
def test_e_a_padded_batch_trains_in_train_and_eval_mode(padded_dataset, kind):
    with SceneDataset(padded_dataset, "train") as ds:
        batch, game = ds.batch(np.arange(8)), ds.game
    torch.manual_seed(0)
    model = build_model(ModelConfig(kind=kind, layer_compiled="no", **TINY), game)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    for mode in (True, False):
        model.train(mode)
        parts = compute_loss(
            kind, model(batch), batch["gt"], PAPER_LOSS_WEIGHTS[kind], batch["agents_mask"]
        )
        assert torch.isfinite(parts["loss"]), mode
        opt.zero_grad()
        parts["loss"].backward()
        grads = [p.grad for p in model.parameters() if p.grad is not None]
        assert grads and all(torch.isfinite(g).all() for g in grads)
        opt.step()
    with SceneDataset(padded_dataset, "val") as val:
        m = evaluate_model(model, val, batch_size=4)
    assert all(np.isfinite(m[k]) for k in ("minADE", "minSADE", "OR")), m


def test_e_train_runs_and_the_figure_draws_real_agents_only(padded_dataset, tmp_path, monkeypatch):
    cfg = TrainConfig(
        model=ModelConfig(kind="epo", layer_compiled="no", **TINY),
        epochs=1,
        batch_size=3,
        lr=1e-3,
    )
    res = train(padded_dataset, tmp_path / "run", cfg, progress=False)
    row = res.history[-1]
    assert res.steps == 3
    assert all(np.isfinite(row[k]) for k in ("train_loss", "val_minADE", "val_minSADE", "val_OR"))
    figs = []
    monkeypatch.setattr(scenarios.plotting, "save_figure", lambda fig, *a, **k: figs.append(fig))
    for run in (tmp_path / "run", "cv"):
        show_predictions(run, padded_dataset, 1, tmp_path / "x.png", split="train")  # agent 1 a pad
    assert len(figs) == 2  # one figure each: ours and CV
    for fig in figs:
        ax = fig.axes[0]
        labels = [ln.get_label() for ln in ax.get_lines()]
        assert sum(lb.endswith(" history") for lb in labels) == 1  # the pad is not drawn
        for ln in ax.get_lines():
            assert np.abs(np.asarray(ln.get_xydata(), float)).max() < 1e3, ln.get_label()
        x0, x1 = ax.get_xlim()
        assert x1 - x0 < 1e3
    assert len(figs[0].axes) == 2  # ours: the scene and the real agent's own weights


def test_goal_decoder_batch_norm_counts_real_agents_only(game):
    """In training mode the goal decoder's batch statistics come from the real agents: a
    scene of pads only added to the batch changes no other scene's goal logits."""
    model = _model(game, "epo-candidates", "train")
    base = _fill_pads(_batch(game), 0.0)
    extra = {k: torch.cat([v, v[:1]]) for k, v in base.items()}
    extra["agents_mask"][-1] = False
    with torch.no_grad():
        outs = []
        for b in (base, extra):
            sc = neutral_scene(b)
            outs.append(model.decode_goals(sc, model.encoder(sc)))
    torch.testing.assert_close(
        outs[1]["goal_logits"][:B], outs[0]["goal_logits"], rtol=0, atol=1e-12
    )
    assert torch.equal(outs[1]["goal_logits"][B:], torch.zeros_like(outs[1]["goal_logits"][B:]))


def _without_pad(batch: dict, b: int, i: int) -> dict:
    """Scene ``b`` of ``batch`` with agent slot ``i`` removed (no ``agents_mask``): the same
    real agents, recorded without padding."""
    keep = [j for j in range(N) if j != i]
    out = {}
    for k, v in batch.items():
        if k == "agents_mask":
            continue
        v = v[b : b + 1]
        out[k] = v[:, :, keep] if k == "history" else v[:, keep]
    return out


@pytest.mark.parametrize("backbone", ["vlstm", "vibes", "hivt"])
def test_real_agents_encode_as_if_the_pad_were_not_there(game, backbone):
    """The encoders' attention never reads a pad: the real agents' features of a padded
    scene equal those of the same scene recorded without the pad's slot (an unpadded run on
    fewer agents), and so do V-LSTM's outputs (its parameters do not depend on ``N``)."""
    torch.manual_seed(0)
    cfg = ModelConfig(kind="vlstm", modes=2, backbone=backbone, **TINY)
    model = build_model(cfg, game).double().eval()
    two = build_model(cfg, _real_game(game)).double().eval()
    two.load_state_dict(model.state_dict())
    batch = _fill_pads(_batch(game), float("nan"))
    with torch.no_grad():
        z = model.encoder(neutral_scene(batch))
        out = model(batch)
        for b, i in PADS:
            keep = [j for j in range(N) if j != i]
            alone = _without_pad(batch, b, i)
            torch.testing.assert_close(z[b, keep], two.encoder(alone)[0], rtol=0, atol=1e-12)
            ref = two(alone)
            torch.testing.assert_close(out["pos"][b, :, keep], ref["pos"][0], rtol=0, atol=1e-12)
            assert torch.equal(z[b, i], torch.zeros_like(z[b, i]))
