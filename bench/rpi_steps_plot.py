"""minSADE of the initial and optimized strategies against the number of LM steps S.

``python bench/rpi_steps_plot.py RESULTS_RUNS_CSV [--out PNG] [--csv CSV]``: reads the
per-run CSV of ``epo evaluate`` (``results_runs.csv``: columns ``run``, ``seed``,
``minSADE``, ``init_minSADE``) of ours' runs, takes each run's S from its ``config.json``
(``train.model.lm_steps``; the ``run`` path as written, else relative to the CSV's folder)
and draws the paper's figure (App. G.3): minSADE against S, red the initial strategies, blue
the optimized ones; thin lines one per seed, thick lines with markers their mean. Writes the
PNG (default ``rpi_steps.png`` beside the CSV) and a CSV (default: the PNG's name with
``.csv``) of one row per run and one ``mean`` row per S. Used by ``bench/rpi_steps.sh``.
Rows without ``init_minSADE`` (runs of models without initial strategies, CV) are left out.
An input error is one ``error:`` line and exit status 2.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

COLUMNS = ("S", "seed", "run", "init_minSADE", "minSADE")


class PlotError(Exception):
    """An input of the figure is missing or malformed (printed as one ``error:`` line)."""


def _number(row: dict, key: str, where: str) -> float:
    try:
        v = float(row[key])
    except (KeyError, TypeError, ValueError):
        raise PlotError(
            f"{where}: expected a number in column {key!r}, got {row.get(key)!r}"
        ) from None
    return v


def _steps(run: str, base: Path) -> int:
    """S of a run: ``train.model.lm_steps`` of its config.json."""
    for d in (Path(run), base / run):
        cfg = d / "config.json"
        if cfg.is_file():
            try:
                return int(json.loads(cfg.read_text())["train"]["model"]["lm_steps"])
            except (ValueError, KeyError, TypeError) as e:
                raise PlotError(f"{cfg}: no train.model.lm_steps ({e})") from None
    raise PlotError(f"run {run!r}: no config.json (looked in {run} and {base / run})")


def read_rows(results: Path) -> list[dict]:
    """One dict per run of ``results`` with ``init_minSADE`` (:data:`COLUMNS`), sorted by S
    and seed."""
    if not results.is_file():
        raise PlotError(f"{results}: no such file (the results_runs.csv of epo evaluate)")
    with open(results, newline="") as f:
        reader = csv.DictReader(f)
        missing = {"run", "minSADE", "init_minSADE"} - set(reader.fieldnames or ())
        if missing:
            raise PlotError(f"{results}: missing column(s) {sorted(missing)}")
        rows = []
        for i, r in enumerate(reader, start=2):
            if not r.get("init_minSADE"):
                continue  # a model without initial strategies
            where = f"{results}:{i}"
            rows.append(
                {
                    "S": _steps(r["run"], results.parent),
                    "seed": r.get("seed", ""),
                    "run": r["run"],
                    "init_minSADE": _number(r, "init_minSADE", where),
                    "minSADE": _number(r, "minSADE", where),
                }
            )
    if not rows:
        raise PlotError(f"{results}: no run with init_minSADE (ours' runs)")
    return sorted(rows, key=lambda r: (r["S"], str(r["seed"])))


def means(rows: list[dict]) -> list[dict]:
    """One row per S: the mean over its runs (``seed`` ``"mean"``)."""
    by = defaultdict(list)
    for r in rows:
        by[r["S"]].append(r)
    return [
        {
            "S": s,
            "seed": "mean",
            "run": "",
            "init_minSADE": sum(r["init_minSADE"] for r in rs) / len(rs),
            "minSADE": sum(r["minSADE"] for r in rs) / len(rs),
        }
        for s, rs in sorted(by.items())
    ]


def write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)


def plot(rows: list[dict], mean_rows: list[dict], out_png: Path) -> None:
    """The figure: minSADE against S (log2 axis), red initial, blue optimized."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 3.4))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    seeds = defaultdict(list)
    for r in rows:
        seeds[r["seed"]].append(r)
    for rs in seeds.values():  # thin: one line per seed
        s = [r["S"] for r in rs]
        ax.plot(s, [r["minSADE"] for r in rs], "-", color="tab:blue", alpha=0.3, lw=1)
        ax.plot(s, [r["init_minSADE"] for r in rs], "-", color="tab:red", alpha=0.3, lw=1)
    s = [r["S"] for r in mean_rows]
    n = len(seeds)
    tag = f" (mean of {n} seeds)" if n > 1 else ""
    ax.plot(s, [r["minSADE"] for r in mean_rows], "-o", color="tab:blue", label="Optimized" + tag)
    ax.plot(s, [r["init_minSADE"] for r in mean_rows], "-o", color="tab:red",
            label="Initialization" + tag)  # fmt: skip
    ax.set_xscale("log", base=2)
    ax.set_xticks(s, [str(v) for v in s])
    ax.set_xlabel("optimization steps S")
    ax.set_ylabel("minSADE (m), validation")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_png, dpi=120)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="results_runs.csv of epo evaluate --split val")
    ap.add_argument("--out", type=Path, default=None, help="PNG (default: rpi_steps.png beside)")
    ap.add_argument("--csv", type=Path, default=None, help="CSV (default: the PNG's, .csv)")
    a = ap.parse_args(argv)
    out = a.out if a.out is not None else a.results.parent / "rpi_steps.png"
    table = a.csv if a.csv is not None else out.with_suffix(".csv")
    try:
        rows = read_rows(a.results)
        mean_rows = means(rows)
        if not all(math.isfinite(r[k]) for r in rows for k in ("minSADE", "init_minSADE")):
            raise PlotError(f"{a.results}: a minSADE is not finite")
        out.parent.mkdir(parents=True, exist_ok=True)
        write_csv(table, rows + mean_rows)
        plot(rows, mean_rows, out)
    except (PlotError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out}, {table}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
