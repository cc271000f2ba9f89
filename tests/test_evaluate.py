"""Evaluation: CV exactness, the mean ± std table, runs of every kind, the predictions figure."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from epo_casadi.errors import SpecError
from learning.baselines import ConstantVelocity
from learning.data import SceneDataset
from learning.evaluate import (
    EvalReport,
    RunResult,
    evaluate,
    evaluate_model,
    format_mean_std,
    method_label,
)
from learning.metrics import all_metrics
from learning.models import ModelConfig
from learning.show import show_predictions
from learning.train import TrainConfig, load_model, train
from tests.test_models import TINY, synthetic_dataset

PNG = b"\x89PNG\r\n\x1a\n"
METRICS = ("minADE", "minFDE", "minSADE", "minSFDE", "OR")


def test_cv_is_exact_on_a_straight_line_example():
    # two agents at constant velocity, far apart; all values exact in binary floating point
    k = torch.arange(-4, 11, dtype=torch.float32)  # steps -4..10; 0 is the current one
    a = torch.stack([-3 + 0.25 * k, torch.zeros_like(k)], -1)
    b = torch.stack([torch.full_like(k, 2.0), -3 + 0.5 * k], -1)
    traj = torch.stack([a, b], 1)  # (15, 2, 2)
    hist = torch.zeros(1, 5, 2, 4)
    hist[0, :, :, :2] = traj[:5]
    gt = traj[5:].permute(1, 0, 2)[None]  # (1, N, T, 2)
    out = ConstantVelocity(10, 2)({"history": hist})
    m = all_metrics(out["pos"], gt, torch.softmax(out["logits"], -1), torch.tensor([0.25, 0.25]))
    for key in METRICS:
        assert m[key].item() == 0.0, key


def test_cv_on_a_straight_line_dataset():
    # futures of zero controls are straight lines at constant speed: CV's only error is float32 rounding
    data = synthetic_dataset(straight=True)
    rep = evaluate([], data, "test", cv=True)
    (r,) = rep.results
    assert r.label == "CV" and r.samples == 8
    for key in ("minADE", "minFDE", "minSADE", "minSFDE"):
        assert r.metrics[key] < 1e-5, (key, r.metrics[key])
    assert rep.markdown().splitlines()[-1].startswith("| CV | 1 | 0.000 | 0.000 | 0.000 | 0.000 |")


def _result(label, seed, values):
    return RunResult(
        f"run-{label}-{seed}",
        label,
        "epo",
        seed,
        3,
        10,
        dict(zip(METRICS, values, strict=True)),
        0.1,
    )


def test_table_mean_and_std_over_seeds(tmp_path):
    rep = EvalReport(
        "data/rpi",
        "test",
        [
            _result("CV", None, [1.0, 2.0, 1.0, 2.0, 0.5]),
            _result("V-LSTM + Ours", 0, [0.8, 1.9, 1.0, 2.4, 0.01]),
            _result("V-LSTM + Ours", 1, [0.82, 1.91, 1.02, 2.38, 0.008]),
            _result("V-LSTM + Ours", 2, [0.81, 1.90, 0.99, 2.36, 0.009]),
            _result("V-LSTM + SC", 0, [0.9, 2.0, 1.1, 2.7, 0.02]),
        ],
    )
    lines = rep.markdown().splitlines()
    assert lines[0].startswith("Split `test` of `data/rpi` (10 samples).")
    assert lines[2] == "| Method | runs | minADE | minFDE | minSADE | minSFDE | OR |"
    assert lines[3] == "|---|---:|---:|---:|---:|---:|---:|"
    assert (
        lines[4]
        == "| V-LSTM + Ours | 3 | 0.810 ± 0.010 | 1.903 ± 0.006 | 1.003 ± 0.015 | 2.380 ± 0.020 | 0.009 ± 0.001 |"
    )
    assert lines[5] == "| V-LSTM + SC | 1 | 0.900 | 2.000 | 1.100 | 2.700 | 0.020 |"
    assert lines[6] == "| CV | 1 | 1.000 | 2.000 | 1.000 | 2.000 | 0.500 |"  # CV last
    assert format_mean_std([1.0, 2.0]) == "1.500 ± 0.707" and format_mean_std([]) == "-"
    md, summ, runs = rep.write(tmp_path / "res")
    assert md.read_text() == rep.markdown()
    rows = list(csv.DictReader(summ.read_text().splitlines()))
    assert [r["method"] for r in rows] == ["V-LSTM + Ours", "V-LSTM + SC", "CV"]
    assert float(rows[0]["minADE_mean"]) == pytest.approx(0.81) and float(
        rows[0]["minADE_std"]
    ) == pytest.approx(0.01)
    assert len(list(csv.DictReader(runs.read_text().splitlines()))) == 5


def test_method_labels():
    assert method_label(ModelConfig(kind="epo")) == "V-LSTM + Ours"
    assert method_label(ModelConfig(kind="sc", backbone="vibes")) == "VIBES + SC"
    assert method_label(ModelConfig(kind="vlstm")) == "V-LSTM"
    assert (
        method_label(ModelConfig(kind="epo", learned_init=False, goal_features=False))
        == "V-LSTM + Ours (zero init) (no goal)"
    )
    assert method_label(None) == "CV"
    assert (
        method_label(ModelConfig(kind="epo", lm_steps=10, goal_decoder="candidates"))
        == "V-LSTM + Ours (S = 10) (goals: candidates)"
    )
    assert method_label(ModelConfig(kind="epo", backward="implicit")) == "V-LSTM + Ours (implicit)"
    assert (
        method_label(ModelConfig(kind="epo", collision_margin=1.0))
        == "V-LSTM + Ours (collision margin 1 m)"
    )
    # ours with the current lane for every mode (runs saved before lane_path) is its own row
    old = dict(kind="epo", goal_decoder="candidates", lane_path="current")
    assert (
        method_label(ModelConfig(**old)) == "V-LSTM + Ours (goals: candidates) (current-lane path)"
    )
    assert method_label(ModelConfig(kind="epo", lane_path="current")) == "V-LSTM + Ours"
    # the training loss is part of the method where it is not the paper's for the kind
    from learning.losses import LossWeights
    from learning.train_config import PAPER_LOSS_WEIGHTS, TrainConfig

    for kind in ("epo", "sc"):
        m = ModelConfig(kind=kind)
        base = method_label(m)
        assert method_label(m, TrainConfig(model=m)) == base
        paper = TrainConfig(model=m, loss=PAPER_LOSS_WEIGHTS[kind])
        assert method_label(m, paper) == base
    m = ModelConfig(kind="epo")
    other = TrainConfig(model=m, loss=LossWeights(1.0, 1.0, 1.0), imitation_reduction="sum")
    assert method_label(m, other) == "V-LSTM + Ours (loss weights 1 / 1 / 1) (imitation: sum)"
    sc = ModelConfig(kind="sc")
    assert (
        method_label(sc, TrainConfig(model=sc, loss=PAPER_LOSS_WEIGHTS["epo"]))
        == "V-LSTM + SC (loss weights 1 / 0.1 / 0.1)"
    )


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One epoch each: ours, SC with seeds 0 and 1, V-LSTM marginal."""
    root = tmp_path_factory.mktemp("runs")
    out = {}
    for name, kind, seed in [
        ("epo", "epo", 0),
        ("sc0", "sc", 0),
        ("sc1", "sc", 1),
        ("vlstm", "vlstm", 0),
    ]:
        cfg = TrainConfig(
            model=ModelConfig(kind=kind, **TINY), epochs=1, batch_size=4, lr=1e-3, seed=seed
        )
        train(synthetic_dataset(), root / name, cfg, progress=False)
        out[name] = root / name
    return out


def test_runs_trained_with_another_loss_are_their_own_row(runs, tmp_path):
    data = synthetic_dataset()
    cfg = TrainConfig(
        model=ModelConfig(kind="sc", **TINY),
        epochs=1,
        batch_size=4,
        lr=1e-3,
        seed=0,
        imitation_reduction="sum",
    )
    train(data, tmp_path / "sc_sum", cfg, progress=False)
    rep = evaluate([runs["sc0"], runs["sc1"], tmp_path / "sc_sum"], data, "test", cv=False)
    assert [(g, len(rs)) for g, rs in rep.groups()] == [
        ("V-LSTM + SC", 2),
        ("V-LSTM + SC (imitation: sum)", 1),
    ]


def test_evaluate_runs_of_every_kind(runs, tmp_path):
    data = synthetic_dataset()
    rep = evaluate(list(runs.values()), data, "test", cv=True)
    assert [(g, len(rs)) for g, rs in rep.groups()] == [
        ("V-LSTM + Ours", 1),
        ("V-LSTM + SC", 2),
        ("V-LSTM", 1),
        ("CV", 1),
    ]
    sc = [r for r in rep.results if r.kind == "sc"]
    assert [r.seed for r in sc] == [0, 1] and sc[0].metrics != sc[1].metrics
    row = next(ln for ln in rep.markdown().splitlines() if ln.startswith("| V-LSTM + SC |"))
    assert row.count("±") == 5
    for r in rep.results:
        assert r.samples == 8 and all(np.isfinite(r.metrics[k]) for k in METRICS)
        assert (
            r.metrics["minSADE"] >= r.metrics["minADE"] - 1e-6
        )  # a joint minimum is never below the marginal one
    # independent reference: the model run one sample at a time, the metrics recomputed
    # with numpy loops from their definitions (marginal model: joint scenes by ordering
    # each agent's modes by its probability)
    for name, kind in (("vlstm", "vlstm"), ("epo", "epo")):
        with SceneDataset(data, "test") as ds:
            model, _, _ = load_model(runs[name], ds.game)
            model.eval()
            radii = np.array([a.radius for a in ds.game.agents])
            per_sample = []
            with torch.no_grad():
                for batch in ds.batches(1):
                    out = model(batch)
                    logits = out["marginal_logits" if "marginal_logits" in out else "logits"]
                    probs = torch.softmax(logits, -1)[0].double().numpy()
                    per_sample.append(
                        _numpy_metrics(
                            out["pos"][0].double().numpy(),
                            batch["gt"][0].double().numpy(),
                            probs,
                            radii,
                        )  # fmt: skip
                    )
            direct = evaluate_model(model, ds, batch_size=3)  # batches of 3, 3 and 2
        ref = {k: np.mean([m[k] for m in per_sample]) for k in METRICS}
        got = next(r for r in rep.results if r.kind == kind).metrics
        assert len(per_sample) == 8 == direct["samples"] and ref["minADE"] > 1e-3
        for k in METRICS:
            assert got[k] == pytest.approx(ref[k], rel=1e-5, abs=1e-6), (name, k)
            assert direct[k] == pytest.approx(ref[k], rel=1e-5, abs=1e-6), (name, k)
    with pytest.raises(SpecError, match="split"):
        evaluate([runs["epo"]], data, "dev")
    with pytest.raises(SpecError, match="runs"):
        evaluate([], data)


def _numpy_metrics(pos, gt, probs, radii):
    """One sample's metrics from their definitions: ``pos`` (M, N, T, 2), ``gt`` (N, T, 2),
    ``probs`` joint (M,) or marginal (N, M), ``radii`` (N,)."""
    M, N, T, _ = pos.shape
    d = np.sqrt(((pos - gt[None]) ** 2).sum(-1))  # (M, N, T)
    ade = np.mean([min(d[m, i].mean() for m in range(M)) for i in range(N)])
    fde = np.mean([min(d[m, i, T - 1] for m in range(M)) for i in range(N)])
    if probs.ndim == 2:  # marginal: joint mode m takes every agent's m-th most likely mode
        order = [sorted(range(M), key=lambda m, i=i: -probs[i, m]) for i in range(N)]
        pos = np.stack([np.stack([pos[order[i][m], i] for i in range(N)]) for m in range(M)])
        joint = np.array([np.prod([probs[i, order[i][m]] for i in range(N)]) for m in range(M)])
        probs = joint / joint.sum()
        d = np.sqrt(((pos - gt[None]) ** 2).sum(-1))
    sade = min(d[m].mean() for m in range(M))
    sfde = min(d[m, :, T - 1].mean() for m in range(M))
    best = pos[int(np.argmax(probs))]
    overlap = any(
        np.linalg.norm(best[i, t] - best[j, t]) < radii[i] + radii[j]
        for i in range(N)
        for j in range(i + 1, N)
        for t in range(T)
    )
    return {"minADE": ade, "minFDE": fde, "minSADE": sade, "minSFDE": sfde, "OR": float(overlap)}


@pytest.mark.parametrize("which", ["epo", "sc0", "cv"])
def test_show_predictions_writes_a_png(runs, tmp_path, which):
    run = "cv" if which == "cv" else runs[which]
    out = show_predictions(run, synthetic_dataset(), 2, tmp_path / f"{which}.png")
    assert out.read_bytes()[:8] == PNG and out.stat().st_size > 10_000
    with pytest.raises(SpecError, match="index"):
        show_predictions(run, synthetic_dataset(), 99, tmp_path / "x.png")


def test_evaluate_cli_out_directory_and_choices(tmp_path, capsys):
    """`epo evaluate --out DIR` writes DIR/results.*; the old file form still works with a
    deprecation message; --split and --model are choices."""
    from scenarios.cli import main

    base = ["evaluate", "--model", "cv", "--data", str(synthetic_dataset())]
    assert main([*base, "--out", str(tmp_path / "res")]) == 0
    md = (tmp_path / "res" / "results.md").read_text()
    assert md.startswith("Split `test`") and "| CV | 1 |" in md
    assert (tmp_path / "res" / "results_runs.csv").exists()
    capsys.readouterr()
    assert main([*base, "--out", str(tmp_path / "old.md")]) == 0
    assert "deprecated" in capsys.readouterr().err
    assert (tmp_path / "old.md").read_text() == md and (tmp_path / "old_runs.csv").exists()
    assert main([*base, "--split", "dev"]) == 2
    assert "'dev' is not one of 'train', 'val', 'test'" in capsys.readouterr().err
    assert main(["evaluate", "--model", "lstm", "--data", str(synthetic_dataset())]) == 2
    assert "'lstm' is not 'cv'" in capsys.readouterr().err


def test_empty_split_warns():
    """Closes: an empty split giving `minADE nan` without a word."""
    with SceneDataset(synthetic_dataset(), "test") as ds:
        ds.batches = lambda batch_size: iter(())
        with pytest.warns(UserWarning, match="split 'test' of .* has no samples"):
            m = evaluate_model(ConstantVelocity(ds.game.K, ds.modes), ds)
    assert m["samples"] == 0 and np.isnan(m["minADE"])
