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
    with SceneDataset(data, "test") as ds:  # the report holds evaluate_model's numbers
        model, _, _ = load_model(runs["vlstm"], ds.game)
        direct = evaluate_model(model, ds, batch_size=3)
    got = next(r for r in rep.results if r.kind == "vlstm").metrics
    for k in METRICS:
        assert got[k] == pytest.approx(direct[k], rel=1e-5, abs=1e-7)
    with pytest.raises(SpecError, match="split"):
        evaluate([runs["epo"]], data, "dev")
    with pytest.raises(SpecError, match="runs"):
        evaluate([], data)


@pytest.mark.parametrize("which", ["epo", "sc0", "cv"])
def test_show_predictions_writes_a_png(runs, tmp_path, which):
    run = "cv" if which == "cv" else runs[which]
    out = show_predictions(run, synthetic_dataset(), 2, tmp_path / f"{which}.png")
    assert out.read_bytes()[:8] == PNG and out.stat().st_size > 10_000
    with pytest.raises(SpecError, match="index"):
        show_predictions(run, synthetic_dataset(), 99, tmp_path / "x.png")
