"""The Tab. 2 experiment scripts (bench/exid_tab2.sh, bench/exid_tab2_table.py) on hand-made
run outputs: the table's mean ± std, the chosen rate and the best-epoch val minSADE."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import exid_tab2_table  # noqa: E402


def _write(path: Path, header: list[str], rows: list[list]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def test_table_from_runs(tmp_path, capsys):
    runs = []
    for seed, val in enumerate(([2.0, 1.5, 1.7], [1.9, 1.6, 1.4])):
        d = tmp_path / f"epo-vlstm-lr5e-4-s{seed}"
        d.mkdir()
        _write(d / "metrics.csv", ["epoch", "val_minSADE"], [[e + 1, v] for e, v in enumerate(val)])
        runs.append(d)
    head = ["run", "method", "minADE", "minFDE", "minSADE", "minSFDE", "OR", "OR_circle"]
    ours = "V-LSTM + Ours (goals: candidates)"
    _write(
        tmp_path / "results_runs.csv",
        head,
        [
            [runs[0], ours, 1.0, 2.0, 1.5, 3.0, 0.1, 0.4],
            [runs[1], ours, 2.0, 4.0, 2.5, 5.0, 0.3, 0.4],
            ["cv", "CV", 2.0, 4.6, 2.0, 4.6, 0.15, 0.4],
        ],
    )
    (tmp_path / "chosen.csv").write_text("epo-vlstm,5e-4,2e-4:1.6;5e-4:1.5\n")
    assert exid_tab2_table.main([str(tmp_path), str(tmp_path / "chosen.csv")]) == 0
    lines = capsys.readouterr().out.splitlines()
    ours_row = [c.strip() for c in lines[2].split("|")[1:-1]]
    # mean ± sample std of (1.5, 2.5) is 2.000 ± 0.707; val: best epochs 1.5 and 1.4
    assert ours_row[:3] == ["V-LSTM + Ours", "5e-4", "2"]
    assert ours_row[5] == "2.000 ± 0.707" and ours_row[7] == "0.200 ± 0.141"
    assert ours_row[9] == "1.450 ± 0.071"
    assert ours_row[10] == exid_tab2_table.PAPER["V-LSTM + Ours"]
    cv_row = [c.strip() for c in lines[3].split("|")[1:-1]]
    assert cv_row[:3] == ["CV", "-", "1"] and cv_row[5] == "2.000" and cv_row[9] == "-"


def test_driver_refuses_an_unknown_command():
    r = subprocess.run(
        ["bash", str(ROOT / "bench" / "exid_tab2.sh"), "fly"], capture_output=True, text=True
    )
    assert r.returncode == 2 and "expected train, eval or table" in r.stderr


def test_driver_grid_choice_and_resume(tmp_path):
    """`train` with a stand-in `epo` that writes metrics.csv: every rate of the grid at seed 0,
    the rate with the lowest best-epoch val minSADE chosen, seeds 1 and 2 at it, finished runs
    skipped on a rerun; `eval` passes exactly the chosen runs (and CV) to `epo evaluate`."""
    fake = tmp_path / "bin" / "epo"
    fake.parent.mkdir()
    # val minSADE by rate: 2e-4 -> 1.9, 5e-4 -> 1.2 (best, at epoch 2), 1e-3 -> 1.5
    fake.write_text(
        """#!/bin/bash
echo "$@" >> "$(dirname "$0")/calls.txt"
[ "$1" = evaluate ] && exit 0
while [ $# -gt 0 ]; do case $1 in --out) out=$2;; --lr) lr=$2;; --epochs) e=$2;; esac; shift; done
case $lr in 2e-4) v=1.9;; 5e-4) v=1.2;; *) v=1.5;; esac
mkdir -p "$out"; echo epoch,val_minSADE > "$out/metrics.csv"
awk -v e="$e" -v v="$v" 'BEGIN {for (i = 1; i <= e; i++) print i "," v + (i == 2 ? 0 : 0.1)}' \
  >> "$out/metrics.csv"
"""
    )
    fake.chmod(0o755)
    (tmp_path / "bin" / "python").symlink_to(sys.executable)
    runs = tmp_path / "runs"
    env = {"PATH": "/usr/bin:/bin", "EPO": str(fake), "EPOCHS": "3", "BACKBONES": "vibes"}
    env["MODELS"] = "sc"
    cmd = ["bash", str(ROOT / "bench" / "exid_tab2.sh"), "train", "data", str(runs)]
    for _ in range(2):  # the second call finds every run finished
        r = subprocess.run(cmd, capture_output=True, text=True, env=env)
        assert r.returncode == 0, r.stderr
    calls = (tmp_path / "bin" / "calls.txt").read_text().splitlines()
    names = sorted(Path(c.split("--out ")[1].split()[0]).name for c in calls)
    want = [f"sc-vibes-lr{lr}-s0" for lr in ("1e-3", "2e-4", "5e-4")]
    assert names == sorted(want + ["sc-vibes-lr5e-4-s1", "sc-vibes-lr5e-4-s2"])
    assert (runs / "chosen.csv").read_text().startswith("sc-vibes,5e-4,1e-3:1.5000;2e-4:1.9")
    r = subprocess.run(
        ["bash", str(ROOT / "bench" / "exid_tab2.sh"), "eval", "data", str(runs)],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 0, r.stderr
    ev = (tmp_path / "bin" / "calls.txt").read_text().splitlines()[-1].split()
    assert ev[0] == "evaluate" and ev[ev.index("--model") + 1] == "cv"
    assert sorted(Path(a).name for a in ev[1:4]) == [f"sc-vibes-lr5e-4-s{s}" for s in range(3)]


def _driver(cmd: str, runs: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    """``bench/exid_tab2.sh CMD data RUNS`` with the test's Python as the driver's."""
    bin_ = tmp_path / "bin"
    bin_.mkdir(exist_ok=True)
    if not (bin_ / "python").exists():
        (bin_ / "python").symlink_to(sys.executable)
    env = {"PATH": "/usr/bin:/bin", "EPO": str(bin_ / "epo")}
    script = str(ROOT / "bench" / "exid_tab2.sh")
    return subprocess.run(
        ["bash", script, cmd, "data", str(runs)], capture_output=True, text=True, env=env
    )


def test_driver_table_and_eval_before_their_inputs_are_one_line(tmp_path):
    """`table` before `eval` ended in a Python traceback, `eval` before `train` in a bash
    error; each is one line naming the missing file and the step to run, exit 2."""
    runs = tmp_path / "runs"
    runs.mkdir()
    for cmd, missing, step in (
        ("table", "eval-test/results_runs.csv", "eval"),
        ("eval", "chosen.csv", "train"),
    ):
        r = _driver(cmd, runs, tmp_path)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1, (r.returncode, r.stderr)
        assert lines[0].startswith("error: ") and str(runs / missing) in lines[0], lines
        assert f"bench/exid_tab2.sh {step}" in lines[0] and r.stdout == ""
    assert sorted(p.name for p in runs.iterdir()) == []  # nothing made by either


def test_table_with_a_missing_run_is_one_line(tmp_path, capsys):
    """A run named in results_runs.csv without its metrics.csv: one line, no partial table."""
    head = ["run", "method", "minADE", "minFDE", "minSADE", "minSFDE", "OR", "OR_circle"]
    gone = tmp_path / "sc-vlstm-lr5e-4-s0"
    _write(tmp_path / "results_runs.csv", head, [[gone, "V-LSTM + SC", 1, 2, 1, 2, 0.1, 0.1]])
    assert exid_tab2_table.main([str(tmp_path)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.strip() == f"error: {gone / 'metrics.csv'}: no such file"
    (tmp_path / "results_runs.csv").write_text("run,method\ncv,CV\n")
    assert exid_tab2_table.main([str(tmp_path)]) == 2
    assert "no column 'minADE'" in capsys.readouterr().err
