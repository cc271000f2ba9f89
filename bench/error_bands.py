"""Error bands of the Tab. 2 runs (paper App. G, Fig. "error bands"): median and range over seeds.

``python bench/error_bands.py RUNS [--out PREFIX]``: ``RUNS`` is the run folder of
``bench/exid_tab2.sh`` (its test scores ``RUNS/eval-test/results_runs.csv``, written by
``bench/exid_tab2.sh eval``) or that ``eval-test`` folder itself. The file is read with
``bench/exid_tab2_table.py``'s reader. Every method (``V-LSTM``, ``V-LSTM + SC``,
``V-LSTM + Ours (goals: candidates)``, ..., ``CV``) is split into its backbone and its model
(``baseline`` for a backbone alone, else what follows ``" + "``; the decoded-goals note is
dropped as in the table). For every metric (minADE, minFDE, minSADE, minSFDE, OR) and method
it writes the median, minimum and maximum over the method's runs (one per seed) to
``PREFIX.csv`` and draws ``PREFIX.png``: one panel per metric, x = backbone, one marker per
model at the median with horizontal lines at the minimum and maximum joined by a bar (as the
paper's figure: red + SC, blue + Ours). ``PREFIX`` defaults to ``RUNS/error_bands``.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from exid_tab2_table import METRICS, TableError, _rows  # noqa: E402

#: the metrics of the figure (the paper's: no circle overlap rate)
BAND_METRICS = METRICS[:5]
#: colour of every model (the paper's: red + SC, blue + Ours); others take the cycle's
COLOURS = {"+ SC": "tab:red", "+ Ours": "tab:blue", "+ TGL": "tab:green", "baseline": "tab:gray"}
CSV_HEAD = ["metric", "backbone", "model", "method", "runs", "median", "min", "max"]


def split_method(method: str) -> tuple[str, str]:
    """``(backbone, model)`` of a method label: ``"V-LSTM + Ours (goals: candidates)"`` ->
    ``("V-LSTM", "+ Ours")``, ``"VIBES"`` -> ``("VIBES", "baseline")``."""
    key = method.replace(" (goals: candidates)", "")
    backbone, plus, model = key.partition(" + ")
    return backbone, f"+ {model}" if plus else "baseline"


def results_file(runs: Path) -> Path:
    """``RUNS/eval-test/results_runs.csv``, or ``RUNS/results_runs.csv`` when ``RUNS`` is the
    evaluation folder itself."""
    own = runs / "results_runs.csv"
    return own if own.exists() else runs / "eval-test" / "results_runs.csv"


def bands(path: Path) -> list[dict]:
    """One row per (metric, method) of ``path`` (a ``results_runs.csv``): backbone, model,
    number of runs, median, min and max of the metric over the method's runs."""
    rows = _rows(path, "run", "method", *BAND_METRICS)
    if not rows:
        raise TableError(f"{path}: no runs")
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(r["method"], []).append(r)
    out = []
    for metric in BAND_METRICS:
        for method, rs in groups.items():
            try:
                v = [float(r[metric]) for r in rs if r.get(metric) not in (None, "")]
            except ValueError as e:
                raise TableError(
                    f"{path}: {method}: a {metric} cell is not a number ({e})"
                ) from None
            if not v:
                continue
            backbone, model = split_method(method)
            out.append(
                {
                    "metric": metric,
                    "backbone": backbone,
                    "model": model,
                    "method": method,
                    "runs": len(v),
                    "median": statistics.median(v),
                    "min": min(v),
                    "max": max(v),
                }
            )
    return out


def write_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, CSV_HEAD)
        w.writeheader()
        w.writerows(rows)


def draw(rows: list[dict], path: Path) -> None:
    """One panel per metric; x = backbone (order of appearance), one offset per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    backbones = list(dict.fromkeys(r["backbone"] for r in rows))
    models = list(dict.fromkeys(r["model"] for r in rows))
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colour = {m: COLOURS.get(m, cycle[i % len(cycle)]) for i, m in enumerate(models)}
    step = 0.7 / max(len(models), 1)
    fig, axes = plt.subplots(1, len(BAND_METRICS), figsize=(3.2 * len(BAND_METRICS), 3.4))
    for ax, metric in zip(axes, BAND_METRICS, strict=True):
        for j, model in enumerate(models):
            sel = [r for r in rows if r["metric"] == metric and r["model"] == model]
            if not sel:
                continue
            x = [backbones.index(r["backbone"]) + (j - (len(models) - 1) / 2) * step for r in sel]
            med = [r["median"] for r in sel]
            err = [[r["median"] - r["min"] for r in sel], [r["max"] - r["median"] for r in sel]]
            ax.errorbar(
                x, med, yerr=err, fmt="o", capsize=4, color=colour[model], label=model, ms=4
            )
        ax.set_xticks(range(len(backbones)), backbones)
        ax.set_xlim(-0.5, len(backbones) - 0.5)
        ax.set_title(metric)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("median and range (min, max) over seeds", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, help="run folder of bench/exid_tab2.sh (or its eval-test)")
    ap.add_argument("--out", type=Path, default=None, help="PREFIX of PREFIX.csv, PREFIX.png")
    a = ap.parse_args(argv)
    try:
        rows = bands(results_file(a.runs))
    except TableError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    prefix = str(a.out if a.out is not None else a.runs / "error_bands")
    write_csv(rows, Path(prefix + ".csv"))
    draw(rows, Path(prefix + ".png"))
    print(f"{prefix}.csv, {prefix}.png: {len(rows)} bands")
    return 0


if __name__ == "__main__":
    sys.exit(main())
