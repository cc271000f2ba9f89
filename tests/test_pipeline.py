"""The pipeline end to end, and the learning commands through the CLI (happy path, bad input)."""

from __future__ import annotations

import json
import shutil

import pytest

from learning.pipeline import run_pipeline
from scenarios.cli import main
from scenarios.dataset import read_manifest
from tests.test_models import TINY, synthetic_dataset

PNG = b"\x89PNG\r\n\x1a\n"
TINY_SET = [f"--set={k}={v}" for k, v in TINY.items()]
#: the pipeline on a tiny RPI set (3 main games), one epoch, tiny networks
SMALL = dict(
    samples=30,
    epochs=1,
    seed=0,
    workers=1,
    progress=False,
    recipe_overrides=dict(max_subgames=10, compiled=False, ground_truth="potential"),
    model_overrides=TINY,
)


def run(capsys, *args) -> tuple[int, str, str]:
    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def test_pipeline_end_to_end(tmp_path):
    lines = []
    res = run_pipeline(tmp_path / "p", **SMALL, echo=lines.append)
    counts = read_manifest(res.data_dir)["counts"]
    assert min(counts.values()) > 0 and 20 <= sum(counts.values()) <= 80, counts
    table = (tmp_path / "p" / "results.md").read_text()
    assert table == res.table
    for label in ("V-LSTM + Ours | 1 |", "V-LSTM + SC | 1 |", "CV | 1 |"):
        assert f"| {label}" in table
    for f in res.files:
        assert f.is_file(), f
    pngs = sorted(p.name for p in (tmp_path / "p" / "figures").iterdir())
    assert len(pngs) == 3 and all(
        (tmp_path / "p" / "figures" / n).read_bytes()[:8] == PNG for n in pngs
    )
    info = json.loads((tmp_path / "p" / "pipeline.json").read_text())
    assert set(info["seconds"]) == {
        "generate",
        "train_epo",
        "train_sc",
        "evaluate",
        "figures",
        "total",
    }
    assert lines[-1].startswith("results: ") and any(
        ln.startswith("| V-LSTM + Ours") for ln in "\n".join(lines).splitlines()
    )
    # run again: the data and both runs are finished, nothing is recomputed or rewritten
    written = sorted((tmp_path / "p").rglob("*.h5")) + [
        r / "checkpoint.pt" for r in res.runs.values()
    ]
    before = {f: f.stat().st_mtime_ns for f in written}
    again = run_pipeline(tmp_path / "p", **SMALL, echo=lambda s: None)
    assert again.table == res.table
    assert {f: f.stat().st_mtime_ns for f in written} == before


def test_cli_train_evaluate_show(capsys, tmp_path):
    data = synthetic_dataset()
    for kind in ("epo", "sc"):
        rc, out, err = run(
            capsys,
            "train",
            "--model",
            kind,
            "--data",
            data,
            "--out",
            tmp_path / kind,
            "--epochs",
            "1",
            "--batch-size",
            "4",
            "--lr",
            "1e-3",
            "--no-progress",
            *TINY_SET,
        )
        assert rc == 0, err
        assert out.startswith(f"{tmp_path / kind}: epoch 1, step 2, train loss ")
    rc, out, err = run(
        capsys,
        "evaluate",
        tmp_path / "epo",
        tmp_path / "sc",
        "--model",
        "cv",
        "--data",
        data,
        "--split",
        "val",
        "--out",
        tmp_path / "res",
    )
    assert rc == 0, err
    assert (
        "| V-LSTM + Ours | 1 |" in out
        and "| CV | 1 |" in out
        and (tmp_path / "res" / "results.md").is_file()
    )
    rc, out, err = run(capsys, "evaluate", "--model", "cv", "--data", data)
    assert rc == 0 and "| CV | 1 |" in out
    rc, out, err = run(
        capsys,
        "show-predictions",
        tmp_path / "epo",
        "--data",
        data,
        "--index",
        "1",
        "--out",
        tmp_path / "f.png",
    )
    assert rc == 0 and (tmp_path / "f.png").read_bytes()[:8] == PNG
    rc, out, _ = run(capsys, "--help")
    for cmd in ("train", "evaluate", "show-predictions", "pipeline"):
        assert cmd in out


def _one_error_line(rc, out, err, *words):
    assert rc == 2, (rc, out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], (w, lines[0])


def test_cli_bad_inputs_exit_2(capsys, tmp_path):
    data = synthetic_dataset()
    missing = tmp_path / "no-data"
    rc, out, err = run(capsys, "train", "--data", missing, "--out", tmp_path / "r", "--no-progress")
    _one_error_line(rc, out, err, str(missing), "no such dataset directory")
    rc, out, err = run(capsys, "evaluate", "--model", "cv", "--data", missing)
    _one_error_line(rc, out, err, str(missing))
    rc, out, err = run(capsys, "show-predictions", "cv", "--data", missing)
    _one_error_line(rc, out, err, str(missing))
    rc, out, err = run(capsys, "evaluate", "--model", "cv", "--data", data, "--split", "testing")
    _one_error_line(rc, out, err, "split", "'testing'")
    rc, out, err = run(
        capsys, "train", "--model", "transformer", "--data", data, "--out", tmp_path / "r"
    )
    _one_error_line(rc, out, err, "--model", "'transformer'")
    rc, out, err = run(capsys, "evaluate", "--model", "sc", "--data", data)
    _one_error_line(rc, out, err, "--model")
    rc, out, err = run(capsys, "train", "--data", data, "--out", tmp_path / "r", "--set", "widht=3")
    _one_error_line(rc, out, err, "--set", "widht")
    rc, out, err = run(capsys, "evaluate", "--data", data)
    _one_error_line(rc, out, err, "RUN")
    # a corrupt checkpoint: evaluate, show and a resumed train all refuse it
    rc, _, err = run(
        capsys,
        "train",
        "--model",
        "sc",
        "--data",
        data,
        "--out",
        tmp_path / "sc",
        "--epochs",
        "1",
        "--no-progress",
        *TINY_SET,
    )
    assert rc == 0, err
    (tmp_path / "sc" / "best.pt").write_bytes(b"\x00garbage")
    rc, out, err = run(capsys, "evaluate", tmp_path / "sc", "--data", data)
    _one_error_line(rc, out, err, str(tmp_path / "sc" / "best.pt"), "unreadable checkpoint")
    rc, out, err = run(capsys, "show-predictions", tmp_path / "sc", "--data", data)
    _one_error_line(rc, out, err, "best.pt")
    shutil.copy(tmp_path / "sc" / "best.pt", tmp_path / "sc" / "checkpoint.pt")
    rc, out, err = run(
        capsys,
        "train",
        "--model",
        "sc",
        "--data",
        data,
        "--out",
        tmp_path / "sc",
        "--epochs",
        "2",
        "--no-progress",
        *TINY_SET,
    )
    _one_error_line(rc, out, err, "checkpoint.pt", "unreadable checkpoint")
    rc, out, err = run(capsys, "evaluate", tmp_path / "nothing-here", "--data", data)
    _one_error_line(rc, out, err, "no such run directory")


@pytest.mark.parametrize("args", [["train", "--help"], ["pipeline", "--help"]])
def test_command_help(capsys, args):
    rc, out, _ = run(capsys, *args)
    assert rc == 0 and "--epochs" in out
