"""bench/choose_lr.py, the learning-rate choice of the experiment drivers, on hand-made runs."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = str(ROOT / "bench" / "choose_lr.py")


def _run(d: Path, scores: list[float]) -> None:
    d.mkdir(parents=True)
    rows = [{"epoch": i + 1, "val_minSADE": s} for i, s in enumerate(scores)]
    with open(d / "metrics.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["epoch", "val_minSADE"])
        w.writeheader()
        w.writerows(rows)


def _choose(runs: Path, group: str, epochs: int):
    return subprocess.run(
        [sys.executable, SCRIPT, str(runs), group, str(epochs)], capture_output=True, text=True
    )


def test_lowest_best_epoch_among_finished_seed0_runs(tmp_path):
    runs = tmp_path / "runs"
    _run(runs / "epo-lr1e-3-s0", [0.9, 0.5, 0.6])  # best epoch 0.5
    _run(runs / "epo-lr5e-4-s0", [0.8, 0.7, 0.4])  # best epoch 0.4: chosen
    _run(runs / "epo-lr2e-4-s0", [0.1, 0.2])  # unfinished (2 of 3 epochs): not a candidate
    (runs / "epo-lr1e-4-s0").mkdir()  # started, no metrics yet
    _run(runs / "epo-lr5e-4-s1", [0.01, 0.01, 0.01])  # another seed: not a candidate
    _run(runs / "sc-lr1e-3-s0", [0.2, 0.2, 0.2])
    (runs / "chosen.csv").write_text("sc,1e-3,1e-3:0.2000\nepo,1e-3,old\n")
    r = _choose(runs, "epo", 3)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "5e-4\n"
    rows = list(csv.reader((runs / "chosen.csv").read_text().splitlines()))
    assert rows == [["sc", "1e-3", "1e-3:0.2000"], ["epo", "5e-4", "1e-3:0.5000;5e-4:0.4000"]]


def test_no_finished_run_is_one_error_line(tmp_path):
    runs = tmp_path / "runs"
    _run(runs / "epo-lr1e-3-s0", [0.9])
    r = _choose(runs, "epo", 3)
    assert r.returncode == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "epo-lr*-s0" in lines[0]
    assert not (runs / "chosen.csv").exists()
