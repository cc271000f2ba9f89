"""The learning rate of a group of runs, chosen on validation: the rate whose seed-0 run has
the lowest best-epoch validation minSADE, among the runs ``RUNS/GROUP-lrRATE-s0`` that
finished ``EPOCHS`` epochs. Prints the rate and records it with every candidate's score in
``RUNS/chosen.csv`` (one row per group). Used by ``bench/exid_tab2.sh`` and
``bench/real_tables.sh`` (under a lock, since two drivers may share RUNS).

    python bench/choose_lr.py RUNS GROUP EPOCHS
"""

from __future__ import annotations

import csv
import glob
import sys


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print("usage: choose_lr.py RUNS GROUP EPOCHS", file=sys.stderr)
        return 2
    runs, group, epochs = argv[0], argv[1], int(argv[2])
    best = {}
    for d in sorted(glob.glob(f"{runs}/{group}-lr*-s0")):
        try:
            with open(f"{d}/metrics.csv") as f:
                rows = list(csv.DictReader(f))
        except FileNotFoundError:
            continue
        if len(rows) >= epochs:
            best[d.rsplit("-lr", 1)[1][: -len("-s0")]] = min(float(r["val_minSADE"]) for r in rows)
    if not best:
        print(
            f"error: {runs}/{group}-lr*-s0: no finished run to choose a learning rate from",
            file=sys.stderr,
        )
        return 2
    lr = min(best, key=best.get)
    path = f"{runs}/chosen.csv"
    rows = []
    if glob.glob(path):
        with open(path, newline="") as f:
            rows = [r for r in csv.reader(f) if r and r[0] != group]
    rows.append([group, lr, ";".join(f"{k}:{v:.4f}" for k, v in sorted(best.items()))])
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    print(lr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
