"""Parameter counts of the exiD models (bench/param_counts.py) against counts computed by hand
from the layer sizes of paper App. F, the App. F widths, depths and normalizations the
models build, and the loading of weights saved before ``ModelConfig.own_norm`` existed."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import param_counts  # noqa: E402

from learning.models import ModelConfig, build_model, count_parameters  # noqa: E402

N, K, M, NU = 4, 20, 5, 2  # exiD (paper App. E): 4 agents, 4 s at 0.2 s, 5 modes, (a, omega)


def linear(i: int, o: int) -> int:
    return i * o + o  # weight and bias


def norm(width: int) -> int:
    return 2 * width  # LayerNorm / BatchNorm1d: weight and bias (running stats are buffers)


def lstm(d: int, h: int, layers: int) -> int:
    """torch.nn.LSTM: per layer W_ih (4h x d_l), W_hh (4h x h), b_ih and b_hh (4h each)."""
    total = 0
    for layer in range(layers):
        d_l = d if layer == 0 else h
        total += 4 * h * d_l + 4 * h * h + 4 * h + 4 * h
    return total


def mlp3(i: int, w: int, o: int, n: bool) -> int:
    """Three linear layers of width ``w`` (ReLU), a norm after each hidden one if ``n``."""
    return linear(i, w) + linear(w, w) + linear(w, o) + (2 * norm(w) if n else 0)


def attention(w: int) -> int:
    return 3 * w * w + 3 * w + linear(w, w)  # in-projection of q, k, v and the out-projection


@pytest.fixture(scope="module")
def game():
    return param_counts.setting_game("exid")


@pytest.fixture(scope="module")
def models(game):
    return param_counts.build("exid", {}, game, M)


def test_the_exid_game_has_the_papers_sizes(game):
    assert (game.N, game.K, game.nu[0], param_counts.setting_modes("exid")) == (N, K, NU, M)


def test_counts_by_hand(models, game):
    """Every module of V-LSTM and of ours against the formula of its layers (App. F widths:
    history LSTM depth 3 width 64 on (start xy, end xy, time); lane PointNet 3 layers width
    64; global graph width 128; decoders 3 layers width 64; scene probability 16 M)."""
    W, h, w = 128, 64, 64
    n_own = len(game.params.group("w_own")) // N  # 8 exiD features (App. F.3)
    n_pair = len(game.params.group("w_pair"))  # one collision weight per pair
    assert (n_own, n_pair) == (8, N * (N - 1) // 2)
    enc = {
        "encoder.lstm": lstm(5, h, 3),
        "encoder.lane": linear(4, 64) + norm(64) + linear(64, 64) + norm(64) + linear(64, 64),
        "encoder.agent_proj": linear(h, W),
        "encoder.lane_proj": linear(64, W),
        "encoder.attn": attention(W),
        "encoder.norm": norm(W),
    }
    assert enc["encoder.lstm"] == 84_736  # 4*64*(5+64+2) + 2 * 4*64*(64+64+2)
    vlstm = {**enc, "traj_dec": mlp3(W, w, M * K * 2, True), "cls_dec": mlp3(W, w, M, False)}
    p = 16 * M
    prob = linear(N * W + N * K * 2, p) + norm(p) + linear(p, p) + norm(p) + linear(p, 1)
    ours = {
        **enc,
        "prob": prob,
        "goal_dec": mlp3(W + 2, w, 1, True),  # [z_i, candidate - position_i] -> logit
        "own_dec": mlp3(W, w, M * n_own, True),  # batch norm (App. F)
        "pair_dec": mlp3(N * W, w, M * n_pair, True),
        "init_dec": mlp3(W, w, M * K * NU, True),
        "layer": 0,
    }
    sc = {**enc, "prob": prob, "ctrl_dec": mlp3(W, w, M * K * NU, True)}
    for label, want in (("V-LSTM", vlstm), ("V-LSTM + SC", sc), ("V-LSTM + Ours", ours)):
        got = param_counts.module_counts(models[label])
        assert got == want, label
        assert count_parameters(models[label]) == sum(want.values()), label
    assert count_parameters(models["V-LSTM"]) == 214_989


def _linears(seq: nn.Module) -> list[nn.Linear]:
    return [m for m in seq.modules() if isinstance(m, nn.Linear)]


def _norms(seq: nn.Module) -> set[type]:
    return {type(m) for m in seq.modules() if isinstance(m, (nn.LayerNorm, nn.BatchNorm1d))}


def test_app_f_widths_depths_and_norms(models, game):
    ours = models["V-LSTM + Ours"]
    enc = ours.encoder
    assert (enc.lstm.num_layers, enc.lstm.hidden_size, enc.lstm.input_size) == (3, 64, 5)
    assert [m.out_features for m in _linears(enc.lane)] == [64, 64, 64]
    assert enc.attn.embed_dim == 128 and not hasattr(enc, "attn2")  # V-LSTM: one layer
    for name in ("goal_dec", "own_dec", "pair_dec", "init_dec"):
        outs = [m.out_features for m in _linears(getattr(ours, name))]
        assert len(outs) == 3 and outs[:2] == [64, 64], name
    assert [m.out_features for m in _linears(ours.prob)] == [16 * M, 16 * M, 1]
    # App. F: batch norm in the goal, agent weight and scene probability decoders; layer
    # norm in the interaction weight and initial strategy decoders and the lane encoder
    for name in ("goal_dec", "own_dec", "prob"):
        assert _norms(getattr(ours, name)) == {nn.BatchNorm1d}, name
    for mod in (ours.pair_dec, ours.init_dec, enc.lane):
        assert _norms(mod) == {nn.LayerNorm}
    vibes = build_model(ModelConfig(modes=M, backbone="vibes", layer_compiled="no"), game)
    assert vibes.encoder.attn2.embed_dim == 128  # the two-stage graph
    hivt = build_model(ModelConfig(modes=M, backbone="hivt", layer_compiled="no"), game)
    loc = hivt.encoder.local
    assert (len(loc.encoder.layers), loc.width) == (3, 64)  # transformer depth 3, width 64


def test_own_decoder_sees_only_the_real_agents(models):
    """With batch norm the agent-weight decoder runs on the real agents' rows: a pad's
    recorded values change no real agent's weights, in training mode too."""
    from learning.masks import own_mask

    ours = models["V-LSTM + Ours"]
    torch.manual_seed(0)
    z = torch.randn(3, N, 128)
    mask = torch.ones(3, N, dtype=torch.bool)
    mask[1, 3] = False
    scene = {"history": torch.randn(3, 10, N, 4), "agents_mask": mask}
    scene["goals"] = torch.randn(3, N, 2)
    ours.train()
    try:
        goals = torch.randn(3, M, N, 2)
        p1 = ours.game_params(scene, z, goals)
        z2 = z.clone()
        z2[1, 3] = 100.0
        p2 = ours.game_params(scene, z2, goals)
    finally:
        ours.eval()
    idx = ours.own_idx
    keep = own_mask(ours.game, mask)[:, None].expand(3, M, -1)
    assert torch.equal(p1[..., idx][keep], p2[..., idx][keep])
    assert not bool(keep.all()) and torch.equal(p1[..., idx][~keep], p2[..., idx][~keep])


def test_weights_saved_without_own_norm(game, tmp_path):
    """Weights of an agent-weight decoder without batch norm (``own_norm="none"``, every run
    saved before the field existed) load into that model and are refused with one message
    naming ``own_norm`` by the default one; a run whose saved config lacks the field loads
    with ``own_norm="none"``, one whose config says "batch" fails with that message."""
    from learning.checkpoint import CHECKPOINT_FORMAT, CheckpointError, save_checkpoint
    from learning.data import game_summary
    from learning.train import TrainConfig, load_model

    kw = dict(kind="epo", modes=M, goal_decoder="candidates", layer_compiled="no")
    torch.manual_seed(0)
    old = build_model(ModelConfig(own_norm="none", **kw), game)
    assert count_parameters(old) == count_parameters(build_model(ModelConfig(**kw), game)) - 256
    state = old.state_dict()
    build_model(ModelConfig(own_norm="none", **kw), game).load_state_dict(state)
    with pytest.raises(RuntimeError, match="own_norm 'none'"):
        build_model(ModelConfig(**kw), game).load_state_dict(state)
    config = TrainConfig(model=ModelConfig(own_norm="none", **kw)).to_dict()
    del config["model"]["own_norm"]  # as written before the field existed
    run = tmp_path / "run"
    run.mkdir()
    ck = {"format": CHECKPOINT_FORMAT, "config": config, "game": game_summary(game)}
    save_checkpoint({**ck, "data": {}, "model": state, "epoch": 1}, run / "checkpoint.pt")
    model, cfg, _ = load_model(run, game, "last")  # a saved run without the field: "none"
    assert cfg.model.own_norm == "none"
    assert torch.equal(model.own_dec[0][2].weight, state["own_dec.0.2.weight"])
    config["model"]["own_norm"] = "batch"  # weights without the norm under a config with it
    save_checkpoint(
        {**ck, "config": config, "data": {}, "model": state, "epoch": 1}, run / "checkpoint.pt"
    )
    with pytest.raises(CheckpointError) as e:
        load_model(run, game, "last")
    assert "own_norm 'none'" in str(e.value) and "checkpoint.pt" in str(e.value)
    assert len(str(e.value).splitlines()) == 1


def test_bench_prints_the_table(capsys):
    assert param_counts.main([]) == 0
    out = capsys.readouterr().out
    total = next(line for line in out.splitlines() if line.startswith("| total |"))
    assert "214,989" in total
    assert "| paper | 432,125 | 538,749 | 616,496 | 617,471 |" in out
