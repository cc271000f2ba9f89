"""Markdown table of an ``epo evaluate`` output beside the paper's Tab. 2 (exiD, M = 5).

``python bench/exid_tab2_table.py EVAL_DIR [CHOSEN_CSV]``: one row per method of
``EVAL_DIR/results_runs.csv`` (mean ± sample std over its runs), with the learning rate chosen
on validation and the validation minSADE of the runs' best epochs (from ``CHOSEN_CSV`` and each
run's ``metrics.csv``), and the paper's row (ADE / FDE / SADE / SFDE / OR). Used by
``bench/exid_tab2.sh table``.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from learning.evaluate import format_mean_std  # noqa: E402

#: the paper's Tab. 2 (exiD test split): minADE / minFDE / minSADE / minSFDE / OR
PAPER = {
    "V-LSTM": "1.25 / 3.64 / 1.98 / 3.90 / 0.031",
    "V-LSTM + SC": "0.82 / 1.95 / 1.07 / 2.63 / 0.010",
    "V-LSTM + TGL": "0.96 / 2.32 / 1.16 / 2.73 / 0.048",
    "V-LSTM + Ours": "0.80 / 1.89 / 0.99 / 2.37 / 0.008",
    "VIBES": "1.35 / 1.68 / 1.93 / 2.93 / 0.021",
    "VIBES + SC": "0.73 / 1.71 / 1.01 / 2.47 / 0.007",
    "VIBES + Ours": "0.83 / 1.99 / 0.99 / 2.40 / 0.006",
    "HiVT-M": "1.83 / 2.02 / 2.39 / 2.86 / 0.013",
    "HiVT-M + SC": "0.78 / 1.90 / 1.04 / 2.57 / 0.008",
    "HiVT-M + Ours": "0.83 / 1.97 / 1.03 / 2.48 / 0.007",
    "CV": "1.16 / 2.87 / 1.16 / 2.87 / 0.007",
}
METRICS = ("minADE", "minFDE", "minSADE", "minSFDE", "OR", "OR_circle")


class TableError(Exception):
    """An input of the table is missing or malformed (printed as one ``error:`` line)."""


def _rows(path: Path, *columns: str) -> list[dict]:
    """The rows of a CSV file with ``columns``; :class:`TableError` if it is missing or
    lacks one."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except FileNotFoundError:
        hint = " (run 'bench/exid_tab2.sh eval' first)" if path.name == "results_runs.csv" else ""
        raise TableError(f"{path}: no such file{hint}") from None
    except (OSError, csv.Error, UnicodeDecodeError) as e:
        raise TableError(f"{path}: unreadable ({e})") from None
    for c in columns:
        if rows and c not in rows[0]:
            raise TableError(f"{path}: no column {c!r}")
    return rows


def main(argv: list[str]) -> int:
    if not argv or len(argv) > 2:
        print(__doc__.strip().splitlines()[2], file=sys.stderr)
        return 2
    try:
        return _table(argv)
    except TableError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def _val(path: Path) -> float:
    """The best-epoch validation minSADE of a run's ``metrics.csv``."""
    rows = _rows(path, "val_minSADE")
    try:
        return min(float(x["val_minSADE"]) for x in rows)
    except ValueError as e:  # no rows, or a cell that is not a number
        raise TableError(f"{path}: no validation minSADE ({e})") from None


def _table(argv: list[str]) -> int:
    out = Path(argv[0])
    chosen = {}
    if len(argv) > 1 and Path(argv[1]).exists():
        with open(argv[1], newline="") as f:
            chosen = {r[0]: r[1] for r in csv.reader(f) if len(r) >= 2}
    rows = _rows(out / "results_runs.csv", "run", "method", *METRICS[:5])
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(r["method"], []).append(r)
    head = "| Method | lr | runs | " + " | ".join(METRICS) + " | val minSADE | paper |"
    lines = [head.replace("OR_circle", "OR (circles)").replace("| OR |", "| OR (boxes) |")]
    lines.append("|---|---:|---:|" + "---:|" * (len(METRICS) + 1) + "---|")
    for method, rs in groups.items():
        lr, val = "-", []
        for r in rs:
            if r["run"] == "cv":
                continue
            name = Path(r["run"]).name
            lr = chosen.get(name.rsplit("-lr", 1)[0], "?")
            val.append(_val(Path(r["run"]) / "metrics.csv"))
        try:
            cells = [
                format_mean_std([r[k] for r in rs if r.get(k) not in (None, "")]) for k in METRICS
            ]
        except ValueError as e:
            raise TableError(
                f"{out / 'results_runs.csv'}: {method}: a cell is not a number ({e})"
            ) from None
        key = method.replace(" (goals: candidates)", "")
        n = len(rs)
        lines.append(
            f"| {key} | {lr} | {n} | "
            + " | ".join(cells)
            + f" | {format_mean_std(val)} | {PAPER.get(key, '-')} |"
        )
    print("\n".join(lines))  # nothing is printed when an input is missing
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
