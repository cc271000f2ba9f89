"""Scoring ours' initial strategies (``init_pos``) beside the optimized ones: the scorer,
the per-epoch validation columns, ``epo evaluate``'s table and CSV files, and the S-steps
figure script (bench/rpi_steps_plot.py) on hand-made run outputs."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from learning.data import SceneDataset
from learning.evaluate import EvalReport, RunResult, evaluate
from learning.models import ModelConfig
from learning.scoring import METRICS, evaluate_model, score_samples
from learning.train import TrainConfig, load_model, train
from tests.test_evaluate import _numpy_metrics
from tests.test_models import TINY, synthetic_dataset

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import rpi_steps_plot  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n"
INIT = tuple(f"init_{k}" for k in METRICS)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One epoch each: ours (S = 3, so that the layer moves the initial strategies) and SC."""
    root = tmp_path_factory.mktemp("runs")
    out = {}
    for kind, extra in (("epo", {"lm_steps": 3}), ("sc", {})):
        cfg = TrainConfig(
            model=ModelConfig(kind=kind, **TINY, **extra), epochs=1, batch_size=4, lr=1e-3
        )
        train(synthetic_dataset(), root / kind, cfg, progress=False)
        out[kind] = root / kind
    return out


def test_scorer_scores_the_initial_strategies(runs):
    """Against the metrics recomputed with numpy loops from their definitions on the
    model's ``init_pos``, one sample at a time, ranked by the same scene probabilities."""
    with SceneDataset(synthetic_dataset(), "test") as ds:
        model, _, _ = load_model(runs["epo"], ds.game)
        radii = np.array([a.radius for a in ds.game.agents])
        per = score_samples(model, ds, batch_size=3)
        ref = {"init": [], "opt": []}
        with torch.no_grad():
            for batch in ds.batches(1):
                out = model(batch)
                probs = torch.softmax(out["logits"], -1)[0].double().numpy()
                gt = batch["gt"][0].double().numpy()
                ref["init"].append(_numpy_metrics(out["init_pos"][0].double().numpy(), gt, probs, radii))  # fmt: skip
                ref["opt"].append(_numpy_metrics(out["pos"][0].double().numpy(), gt, probs, radii))
    assert set(INIT) <= set(per) and set(METRICS) <= set(per)
    for k in METRICS:
        init = np.array([m[k] for m in ref["init"]])
        opt = np.array([m[k] for m in ref["opt"]])
        np.testing.assert_allclose(per[f"init_{k}"], init, rtol=1e-5, atol=1e-6, err_msg=k)
        np.testing.assert_allclose(per[k], opt, rtol=1e-5, atol=1e-6, err_msg=k)
    # the regime the test claims: the layer's S = 3 steps moved the strategies
    assert np.abs(per["init_minSADE"] - per["minSADE"]).max() > 1e-4
    with SceneDataset(synthetic_dataset(), "test") as ds:
        m = evaluate_model(model, ds)
    assert m["init_minSADE"] == pytest.approx(
        np.mean([r["minSADE"] for r in ref["init"]]), rel=1e-5
    )


def test_models_without_initial_strategies_are_unchanged(runs):
    with SceneDataset(synthetic_dataset(), "test") as ds:
        model, _, _ = load_model(runs["sc"], ds.game)
        per = score_samples(model, ds)
    assert sorted(per) == sorted(METRICS)


def test_validation_columns_of_training(runs):
    """metrics.csv of ours has val_init_<metric>: the scorer's values of best.pt on val."""
    rows = {
        k: list(csv.DictReader((runs[k] / "metrics.csv").read_text().splitlines())) for k in runs
    }
    with SceneDataset(synthetic_dataset(), "val") as ds:
        model, _, _ = load_model(runs["epo"], ds.game)
        m = evaluate_model(model, ds)
    for k in METRICS:
        assert float(rows["epo"][-1][f"val_init_{k}"]) == pytest.approx(m[f"init_{k}"], rel=1e-6)
        assert float(rows["epo"][-1][f"val_{k}"]) == pytest.approx(m[k], rel=1e-6)
    assert not any(c.startswith("val_init_") for c in rows["sc"][0])


def test_evaluate_reports_the_initial_strategies(runs, tmp_path):
    data = synthetic_dataset()
    # SC first: its per-run row has no init_ columns, ours' row adds them
    rep = evaluate([runs["sc"], runs["epo"]], data, "val", cv=True)
    ours = next(r for r in rep.results if r.kind == "epo")
    with SceneDataset(data, "val") as ds:
        model, _, _ = load_model(runs["epo"], ds.game)
        direct = evaluate_model(model, ds)
    for k in INIT:
        assert ours.metrics[k] == pytest.approx(direct[k], rel=1e-6)
    for r in rep.results:
        if r.kind != "epo":
            assert not any(k.startswith("init_") for k in r.metrics), r.kind
    md = rep.markdown()
    lines = md.splitlines()
    i = next(j for j, ln in enumerate(lines) if ln.startswith("Initial strategies"))
    assert lines[i + 2] == "| Method | runs | minADE | minFDE | minSADE | minSFDE | OR |"
    body = [ln for ln in lines[i + 4 :] if ln.startswith("|")]
    assert [ln.split("|")[1].strip() for ln in body] == ["V-LSTM + Ours (S = 3)"]
    assert f"| {ours.metrics['init_minSADE']:.3f} |" in body[0]
    # the main table is the one it was
    assert lines[2] == "| Method | runs | minADE | minFDE | minSADE | minSFDE | OR |"
    md_path, summ, per_run = rep.write(tmp_path / "res")
    runs_csv = list(csv.DictReader(per_run.read_text().splitlines()))
    assert [r["kind"] for r in runs_csv] == ["sc", "epo", "cv"]
    assert float(runs_csv[1]["init_minSADE"]) == pytest.approx(ours.metrics["init_minSADE"])
    assert runs_csv[0]["init_minSADE"] == "" == runs_csv[2]["init_minSADE"]
    summary = {r["method"]: r for r in csv.DictReader(summ.read_text().splitlines())}
    init_mean = float(summary["V-LSTM + Ours (S = 3)"]["init_minSADE_mean"])
    assert init_mean == pytest.approx(ours.metrics["init_minSADE"])
    assert math.isnan(float(summary["V-LSTM + SC"]["init_minSADE_mean"]))


def test_init_table_mean_and_std_by_hand():
    def res(seed, init, opt):
        m = dict(zip(METRICS, opt, strict=True)) | {
            f"init_{k}": v for k, v in zip(METRICS, init, strict=True)
        }
        return RunResult(f"r{seed}", "V-LSTM + Ours", "epo", seed, 1, 10, m, 0.1)

    rep = EvalReport(
        "d",
        "val",
        [
            res(0, [0.1, 0.2, 0.3, 0.4, 0.0], [0.05, 0.1, 0.05, 0.1, 0.0]),
            res(1, [0.3, 0.4, 0.5, 0.6, 0.0], [0.05, 0.1, 0.05, 0.1, 0.0]),
        ],
    )
    last = rep.markdown().splitlines()[-1]
    # mean ± sample std of (0.1, 0.3): 0.200 ± 0.141; of (0.3, 0.5): 0.400 ± 0.141
    assert last == (
        "| V-LSTM + Ours | 2 | 0.200 ± 0.141 | 0.300 ± 0.141 | 0.400 ± 0.141 | "
        "0.500 ± 0.141 | 0.000 ± 0.000 |"
    )


# --------------------------------------------------------------------------------------
# bench/rpi_steps_plot.py on hand-made run outputs
# --------------------------------------------------------------------------------------
def _fake_runs(tmp_path: Path) -> Path:
    """Runs S in (1, 2, 4) x seeds (0, 1) with config.json, and an evaluate CSV with CV."""
    rows = []
    for S in (1, 2, 4):
        for seed in (0, 1):
            d = tmp_path / "runs" / f"S{S}-s{seed}"
            d.mkdir(parents=True)
            (d / "config.json").write_text(json.dumps({"train": {"model": {"lm_steps": S}}}))
            # optimized falls with S, initial rises; seed 1 is 0.01 above seed 0
            rows.append(
                [str(d), "ours", "epo", seed, 0.1 / S + 0.01 * seed, 0.05 * S + 0.01 * seed]
            )
    rows.append(["cv", "CV", "cv", "", 0.5, ""])
    ev = tmp_path / "eval-val"
    ev.mkdir()
    with open(ev / "results_runs.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run", "method", "kind", "seed", "minSADE", "init_minSADE"])
        w.writerows(rows)
    return ev / "results_runs.csv"


def test_steps_plot_writes_the_figure_and_the_means(tmp_path, capsys):
    results = _fake_runs(tmp_path)
    assert rpi_steps_plot.main([str(results), "--out", str(tmp_path / "fig.png")]) == 0
    png = tmp_path / "fig.png"
    assert png.read_bytes()[:8] == PNG and png.stat().st_size > 5_000
    rows = list(csv.DictReader((tmp_path / "fig.csv").read_text().splitlines()))
    per_run = [r for r in rows if r["seed"] != "mean"]
    assert [(int(r["S"]), r["seed"]) for r in per_run] == [
        (1, "0"), (1, "1"), (2, "0"), (2, "1"), (4, "0"), (4, "1"),
    ]  # fmt: skip
    mean = {int(r["S"]): r for r in rows if r["seed"] == "mean"}
    assert sorted(mean) == [1, 2, 4]
    for S in (1, 2, 4):  # mean of seed 0 and seed 0 + 0.01
        assert float(mean[S]["minSADE"]) == pytest.approx(0.1 / S + 0.005)
        assert float(mean[S]["init_minSADE"]) == pytest.approx(0.05 * S + 0.005)
    # relative run paths are read beside the CSV's folder; the default names
    text = results.read_text().replace(str(tmp_path / "runs"), "../runs")
    results.write_text(text)
    assert rpi_steps_plot.main([str(results)]) == 0
    assert (results.parent / "rpi_steps.png").is_file() and (
        results.parent / "rpi_steps.csv"
    ).is_file()
    # as a script, the figure drawn the same way
    done = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "rpi_steps_plot.py"), str(results), "--out",
         str(tmp_path / "cli.png")],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "cli.png").read_bytes()[:8] == PNG


def test_steps_plot_input_errors(tmp_path, capsys):
    assert rpi_steps_plot.main([str(tmp_path / "none.csv")]) == 2
    assert "no such file" in capsys.readouterr().err
    bad = tmp_path / "r.csv"
    bad.write_text("run,minSADE\nx,1\n")
    assert rpi_steps_plot.main([str(bad)]) == 2
    assert "init_minSADE" in capsys.readouterr().err
    bad.write_text("run,minSADE,init_minSADE\nmissing-run,1,2\n")
    assert rpi_steps_plot.main([str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "config.json" in err[0]


def test_steps_script_is_valid_bash_and_refuses_a_missing_dataset(tmp_path):
    sh = ROOT / "bench" / "rpi_steps.sh"
    assert subprocess.run(["bash", "-n", str(sh)], check=False).returncode == 0
    done = subprocess.run(
        ["bash", str(sh), str(tmp_path / "nodata"), str(tmp_path / "out")],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert done.returncode == 2 and "DATA" in done.stderr
    assert not (tmp_path / "out").exists()
