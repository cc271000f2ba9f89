"""The recorded-data experiment scripts (bench/real_tables.sh, bench/real_tables.py) with a
stand-in ``epo`` and hand-made run outputs: datasets made once per scene, the learning-rate
grid at seed 0 and the chosen rate's seeds 1 and 2, finished runs skipped, ``eval`` scoring
exactly the chosen runs with CV and the interacting subset, the table's mean ± std per scene
and the average of the five scenes."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import real_tables  # noqa: E402

SCRIPT = str(ROOT / "bench" / "real_tables.sh")
#: a stand-in epo: logs its arguments; generate writes a complete manifest; train writes
#: metrics.csv whose val minSADE depends on the rate (5e-4 best, at epoch 2)
FAKE = """#!/bin/bash
echo "$@" >> "$(dirname "$0")/calls.txt"
cmd=$1
while [ $# -gt 0 ]; do case $1 in --out) out=$2;; --lr) lr=$2;; --epochs) e=$2;; esac; shift; done
case $cmd in
generate) mkdir -p "$out"; echo '{"complete": true}' > "$out/manifest.json" ;;
train)
  case $lr in 1e-4) v=1.9;; 5e-4) v=1.2;; *) v=1.5;; esac
  mkdir -p "$out"; echo epoch,val_minSADE > "$out/metrics.csv"
  awk -v e="$e" -v v="$v" 'BEGIN {for (i = 1; i <= e; i++) print i "," v + (i == 2 ? 0 : 0.1)}' \\
    >> "$out/metrics.csv" ;;
esac
exit 0
"""


def _bin(tmp_path: Path) -> Path:
    b = tmp_path / "bin"
    b.mkdir(exist_ok=True)
    (b / "epo").write_text(FAKE)
    (b / "epo").chmod(0o755)
    if not (b / "python").exists():
        (b / "python").symlink_to(sys.executable)
    return b


def _run(tmp_path, *args, **env) -> subprocess.CompletedProcess:
    b = _bin(tmp_path)
    full = {"PATH": "/usr/bin:/bin", "EPO": str(b / "epo"), "EPOCHS": "3", **env}
    return subprocess.run(["bash", SCRIPT, *args], capture_output=True, text=True, env=full)


def _calls(tmp_path) -> list[list[str]]:
    f = tmp_path / "bin" / "calls.txt"
    return [ln.split() for ln in f.read_text().splitlines()] if f.exists() else []


def _opt(call: list[str], name: str) -> str:
    return call[call.index(name) + 1]


def test_driver_refuses_an_unknown_command_and_unknown_scenes(tmp_path):
    r = _run(tmp_path, "fly")
    assert r.returncode == 2 and "expected data, train, eval, table or cost" in r.stderr
    r = _run(tmp_path, "data", "d", "r", SCENES="eth mars")
    assert r.returncode == 2 and r.stderr.strip() == (
        "error: SCENES: expected some of eth hotel univ zara1 zara2, got 'mars'"
    )


def test_driver_data_train_eval_and_resume(tmp_path):
    data, runs = tmp_path / "data", tmp_path / "runs"
    env = {"SCENES": "eth hotel", "MODELS": "vlstm epo"}
    for _ in range(2):  # the second call finds every dataset complete
        r = _run(tmp_path, "data", str(data), str(runs), **env)
        assert r.returncode == 0, r.stderr
    gen = [c for c in _calls(tmp_path) if c[0] == "generate"]
    assert [(c[1], Path(_opt(c, "--out")).relative_to(data).as_posix()) for c in gen] == [
        ("eth-ucy", "eth_ucy/eth"),
        ("eth-ucy", "eth_ucy/hotel"),
        ("vci", "citr"),
    ]
    assert [_opt(c, "--test-scene") for c in gen[:2]] == ["eth", "hotel"]
    for _ in range(2):  # the second call finds every run finished
        r = _run(tmp_path, "train", str(data), str(runs), **env)
        assert r.returncode == 0, r.stderr
    tr = [c for c in _calls(tmp_path) if c[0] == "train"]
    names = sorted(Path(_opt(c, "--out")).relative_to(runs).as_posix() for c in tr)
    want = []
    for t, models in (("eth_ucy/eth", ("vlstm", "epo")), ("eth_ucy/hotel", ("vlstm", "epo"))):
        for m in models:
            want += [f"{t}/{m}-lr{lr}-s0" for lr in ("1e-4", "5e-4", "1e-3")]
            want += [f"{t}/{m}-lr5e-4-s{s}" for s in (1, 2)]
    want += [f"citr/epo-lr{lr}-s0" for lr in ("1e-4", "5e-4", "1e-3")]
    want += [f"citr/epo-lr5e-4-s{s}" for s in (1, 2)]  # no V-LSTM on CITR
    assert names == sorted(want)
    for c in tr:
        where = Path(_opt(c, "--out")).relative_to(runs).parts[0]
        assert _opt(c, "--modes") == ("6" if where == "citr" else "20")
        assert ("goal_decoder=regress" in c) == (_opt(c, "--model") == "epo")
        assert _opt(c, "--threads") == "1" and _opt(c, "--epochs") == "3"
    chosen = (runs / "eth_ucy" / "eth" / "chosen.csv").read_text().splitlines()
    assert chosen == ["vlstm,5e-4,1e-3:1.5000;1e-4:1.9000;5e-4:1.2000", chosen[1]]
    r = _run(tmp_path, "eval", str(data), str(runs), **env)
    assert r.returncode == 0, r.stderr
    ev = [c for c in _calls(tmp_path) if c[0] == "evaluate"]
    assert len(ev) == 3
    for c, t in zip(ev, ("eth_ucy/eth", "eth_ucy/hotel", "citr"), strict=True):
        assert _opt(c, "--model") == "cv" and _opt(c, "--subset") == "interacting"
        assert _opt(c, "--data") == str(data / t) and _opt(c, "--out") == str(
            runs / t / "eval-test"
        )
        got = sorted(Path(a).name for a in c[1:] if a.startswith(str(runs)) and "-lr" in a)
        models = ("vlstm", "epo") if t != "citr" else ("epo",)
        assert got == sorted(f"{m}-lr5e-4-s{s}" for m in models for s in range(3))


def test_driver_steps_before_their_inputs_are_one_line(tmp_path):
    runs, data = tmp_path / "runs", tmp_path / "data"
    for cmd, missing, step in (
        ("train", data / "eth_ucy" / "eth", "data"),
        ("eval", runs / "eth_ucy" / "eth" / "chosen.csv", "train"),
    ):
        r = _run(tmp_path, cmd, str(data), str(runs))
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1, (cmd, r.stderr)
        assert (
            lines[0].startswith(f"error: {missing}") and f"bench/real_tables.sh {step}" in lines[0]
        )
    r = _run(tmp_path, "table", str(data), str(runs))
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().startswith(f"error: {runs}: neither eth_ucy/ nor citr/")


# --------------------------------------------------------------------------------------
# the table from hand-made results
# --------------------------------------------------------------------------------------
HEAD = ["run", "method", "minADE", "minFDE", "minSADE", "minSFDE", "OR", *real_tables.FOCAL]


def _write(path: Path, rows: list[list]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(HEAD)
        w.writerows(rows)


def _row(run, method, ade, fde=2.0, sade=1.0, orate=0.1):
    # minADE, minFDE, minSADE, minSFDE, OR, ADE_focal, FDE_focal, top-1 ADE, top-1 FDE
    return [run, method, 0.5, 1.0, sade, 2 * sade, orate, ade, fde, ade + 1, fde + 1]


def test_table_per_scene_and_the_average(tmp_path, capsys):
    runs = tmp_path / "runs"
    ours = "V-LSTM + Ours (goals: regress)"
    for k, s in enumerate(real_tables.SCENES):
        ev = runs / "eth_ucy" / s / "eval-test"
        rows = [_row(f"r/epo-lr5e-4-s{i}", ours, 0.1 * (k + 1) + 0.1 * i) for i in range(3)]
        rows.append(_row("cv", "CV", 1.0 + k, 2.0 + k))
        _write(ev / "results_runs.csv", rows)
        _write(ev / "results_interacting_runs.csv", [_row("cv", "CV", 3.0, 4.0, orate=0.5)])
    pub = tmp_path / "pub.csv"
    pub.write_text(
        "dataset,method,scene,ADE,FDE,source,protocol\n"
        "eth_ucy,Some model,eth,0.5,1.0,A paper (2020) Tab. 1,best of 20\n"
    )
    assert real_tables.main(["table", str(runs), str(pub)]) == 0
    out = capsys.readouterr().out.splitlines()
    sub = out.index("ETH/UCY, the interacting subset (min_distance < 1 m):")
    cells = {
        (c[0], c[1]): c
        for c in ([x.strip() for x in ln.split("|")[1:-1]] for ln in out[:sub] if ln[:2] == "| ")
    }
    # eth: ADE 0.1, 0.2, 0.3 -> 0.20 ± 0.10; top-1 ADE 1.1, 1.2, 1.3 -> 1.20 ± 0.10
    assert cells[("V-LSTM + Ours", "eth")][2:5] == [
        "3",
        "0.20 ± 0.10 / 2.00 ± 0.00",
        "1.20 ± 0.10 / 3.00 ± 0.00",
    ]
    # the average of the five scene means: (0.2 + 0.3 + 0.4 + 0.5 + 0.6) / 5 = 0.40
    assert cells[("V-LSTM + Ours", "avg")][3] == "0.40 / 2.00"
    assert cells[("CV", "avg")][3] == "3.00 / 4.00" and cells[("CV", "zara2")][3] == "5.00 / 6.00"
    assert cells[("Some model", "eth")][2:] == ["0.5 / 1.0", "A paper (2020) Tab. 1", "best of 20"]
    assert any(ln.startswith("| CV | avg | - | 3.00 / 4.00 |") for ln in out[sub:])
    assert "| 0.50 |" in next(ln for ln in out[sub:] if ln.startswith("| CV | eth |"))


def test_table_with_a_missing_scene_is_one_line(tmp_path, capsys):
    runs = tmp_path / "runs"
    _write(runs / "eth_ucy" / "eth" / "eval-test" / "results_runs.csv", [_row("cv", "CV", 1.0)])
    assert real_tables.main(["table", str(runs)]) == 2
    out, err = capsys.readouterr()
    missing = runs / "eth_ucy" / "hotel" / "eval-test" / "results_runs.csv"
    assert out == "" and err.strip().startswith(f"error: {missing}: no such file")
    assert real_tables.main(["cost", str(runs), "3"]) == 2
    assert "BATCHES: expected more than 5" in capsys.readouterr().err


def test_published_numbers_cite_a_source_and_a_protocol():
    """Every row of bench/real_published.csv names its source (paper, table) and protocol."""
    rows = list(csv.DictReader((ROOT / "bench" / "real_published.csv").read_text().splitlines()))
    head = (ROOT / "bench" / "real_published.csv").read_text().splitlines()[0].split(",")
    assert head == ["dataset", "method", "scene", "ADE", "FDE", "source", "protocol"]
    for r in rows:
        assert r["source"].strip() and r["protocol"].strip(), r
        assert r["scene"] in (*real_tables.SCENES, "avg"), r
        float(r["ADE"]), float(r["FDE"])
