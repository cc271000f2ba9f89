"""bench/error_bands.py on hand-made run folders (the layout of bench/exid_tab2.sh): the
medians and ranges over seeds in the CSV against values computed by hand, the PNG, and the
errors of a missing or malformed input."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import error_bands  # noqa: E402

HEAD = ["run", "method", "minADE", "minFDE", "minSADE", "minSFDE", "OR", "OR_circle"]
OURS = "V-LSTM + Ours (goals: candidates)"


def _runs(tmp_path: Path) -> Path:
    """RUNS with three seeds of V-LSTM + SC and of ours, two of VIBES + SC, and CV."""
    runs = tmp_path / "runs"
    ev = runs / "eval-test"
    ev.mkdir(parents=True)
    rows = []
    # minADE by seed: SC 1.0, 3.0, 2.0 (median 2.0); ours 0.9, 0.8, 1.4 (median 0.9)
    for seed, (sc, ours) in enumerate(((1.0, 0.9), (3.0, 0.8), (2.0, 1.4))):
        rows.append(
            [
                runs / f"sc-vlstm-lr5e-4-s{seed}",
                "V-LSTM + SC",
                sc,
                2 * sc,
                sc + 1,
                5,
                0.1 * seed,
                0.4,
            ]
        )
        rows.append([runs / f"epo-vlstm-lr5e-4-s{seed}", OURS, ours, 2, 1, 4, 0.2, 0.4])
    for seed, v in enumerate((1.5, 2.5)):  # two runs: the median is their mean
        rows.append([runs / f"sc-vibes-lr5e-4-s{seed}", "VIBES + SC", v, v, v, v, v / 10, 0.4])
    rows.append(["cv", "CV", 2.0, 4.6, 2.0, 4.6, 0.15, 0.4])
    with open(ev / "results_runs.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(HEAD)
        w.writerows(rows)
    return runs


def _read(path: Path) -> dict[tuple[str, str], dict]:
    with open(path, newline="") as f:
        return {(r["metric"], r["method"]): r for r in csv.DictReader(f)}


def test_medians_and_ranges_by_hand(tmp_path):
    runs = _runs(tmp_path)
    assert error_bands.main([str(runs)]) == 0
    got = _read(runs / "error_bands.csv")
    assert len(got) == 5 * 4  # five metrics x four methods (OR_circle is not drawn)
    want = {
        ("minADE", "V-LSTM + SC"): ("V-LSTM", "+ SC", 3, 2.0, 1.0, 3.0),
        ("minFDE", "V-LSTM + SC"): ("V-LSTM", "+ SC", 3, 4.0, 2.0, 6.0),
        ("minSADE", "V-LSTM + SC"): ("V-LSTM", "+ SC", 3, 3.0, 2.0, 4.0),
        ("minSFDE", "V-LSTM + SC"): ("V-LSTM", "+ SC", 3, 5.0, 5.0, 5.0),
        ("OR", "V-LSTM + SC"): ("V-LSTM", "+ SC", 3, 0.1, 0.0, 0.2),
        ("minADE", OURS): ("V-LSTM", "+ Ours", 3, 0.9, 0.8, 1.4),
        ("minADE", "VIBES + SC"): ("VIBES", "+ SC", 2, 2.0, 1.5, 2.5),
        ("OR", "VIBES + SC"): ("VIBES", "+ SC", 2, 0.2, 0.15, 0.25),
        ("minSFDE", "CV"): ("CV", "baseline", 1, 4.6, 4.6, 4.6),
    }
    for key, (bb, model, n, med, lo, hi) in want.items():
        r = got[key]
        assert (r["backbone"], r["model"], int(r["runs"])) == (bb, model, n), key
        assert [float(r[k]) for k in ("median", "min", "max")] == pytest.approx([med, lo, hi]), key
    png = runs / "error_bands.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image

    h, w = matplotlib.image.imread(png).shape[:2]
    assert w > 3 * h  # five panels side by side


def test_eval_folder_and_out_prefix(tmp_path):
    runs = _runs(tmp_path)
    out = tmp_path / "fig" / "bands.v1"
    out.parent.mkdir()
    assert error_bands.main([str(runs / "eval-test"), "--out", str(out)]) == 0
    assert (tmp_path / "fig" / "bands.v1.csv").exists()
    assert (tmp_path / "fig" / "bands.v1.png").exists()


def test_split_method():
    assert error_bands.split_method(OURS) == ("V-LSTM", "+ Ours")
    assert error_bands.split_method("HiVT-M") == ("HiVT-M", "baseline")
    assert error_bands.split_method("VIBES + Ours (zero init)") == ("VIBES", "+ Ours (zero init)")


def test_missing_and_malformed_input(tmp_path, capsys):
    assert error_bands.main([str(tmp_path)]) == 2
    assert "results_runs.csv: no such file" in capsys.readouterr().err
    runs = _runs(tmp_path)
    p = runs / "eval-test" / "results_runs.csv"
    p.write_text(p.read_text().replace("3.0,6.0", "x,6.0"))
    assert error_bands.main([str(runs)]) == 2
    err = capsys.readouterr().err
    assert "V-LSTM + SC: a minADE cell is not a number" in err
    assert not (runs / "error_bands.csv").exists()
