"""Tables and costs of the recorded-data experiments (``bench/real_tables.sh``; docs/real_data.md,
"Experiments").

``python bench/real_tables.py table RUNS [PUBLISHED_CSV]``: from ``RUNS/eth_ucy/<scene>/eval-test``
(``epo evaluate`` of the chosen runs and CV, with ``--subset interacting``) one markdown
table per ETH/UCY metric block: per method the focal agent's best-of-20 and top-1 ADE / FDE
per scene and the average of the five scenes (mean ± sample std over the 3 seeds of each
scene; the average of the scene means), the joint minSADE / minSFDE / OR, the same on the
interacting subset, and the published numbers of ``PUBLISHED_CSV`` (``bench/real_published.csv``)
beside them; then the CITR table from ``RUNS/citr/eval-test``. A missing input is one
``error:`` line (exit status 2), and nothing is printed.

``python bench/real_tables.py cost DATA [BATCHES] [KINDS]``: the measured seconds of one
training epoch of each model (``vlstm sc epo``, M = 20, batch 32, ``--threads 1``, default
widths, ours with ``goal_decoder=regress``) on the train split of ``DATA``: ``BATCHES``
optimizer steps (default 30; the first 5 are warm-up and not counted) through
:func:`learning.train.train`, scaled to the split's batches, plus one validation pass over
the val split.
"""

from __future__ import annotations

import csv
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from learning.evaluate import format_mean_std  # noqa: E402
from scenarios.real.eth_ucy import SCENES  # noqa: E402

#: method labels of the runs (``learning.evaluate.method_label``) -> table rows, in order
METHODS = {
    "CV": "CV",
    "V-LSTM": "V-LSTM",
    "V-LSTM + SC": "V-LSTM + SC",
    "V-LSTM + Ours (goals: regress)": "V-LSTM + Ours",
}
FOCAL = ("ADE_focal", "FDE_focal", "ADE_focal_top1", "FDE_focal_top1")
JOINT = ("minSADE", "minSFDE", "OR")


class TableError(Exception):
    """An input of the table is missing or malformed (printed as one ``error:`` line)."""


def _rows(path: Path, *columns: str) -> list[dict]:
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except FileNotFoundError:
        raise TableError(f"{path}: no such file (run 'bench/real_tables.sh eval' first)") from None
    except (OSError, csv.Error, UnicodeDecodeError) as e:
        raise TableError(f"{path}: unreadable ({e})") from None
    for c in columns:
        if rows and c not in rows[0]:
            raise TableError(f"{path}: no column {c!r}")
    return rows


def _values(path: Path, columns) -> dict[str, dict[str, list[float]]]:
    """Method row -> metric -> the values of its runs in ``path`` (a results_runs.csv)."""
    out: dict[str, dict[str, list[float]]] = {}
    for r in _rows(path, "method", *columns):
        row = METHODS.get(r["method"], r["method"])
        for k in columns:
            try:
                v = float(r[k])
            except (TypeError, ValueError):
                raise TableError(f"{path}: {r['method']}: {k} is not a number ({r[k]!r})") from None
            out.setdefault(row, {}).setdefault(k, []).append(v)
    return out


def published(path: Path | None) -> dict[tuple[str, str], dict]:
    """``(method, scene)`` -> the row of the published numbers' CSV (``bench/real_published.csv``:
    method, scene, metric columns, source, protocol)."""
    if path is None or not Path(path).exists():
        return {}
    return {(r["method"], r["scene"]): r for r in _rows(Path(path), "method", "scene", "source")}


def _cell(vals: list[float] | None) -> str:
    return format_mean_std(vals or [], 2)


def eth_ucy_table(runs: Path, pub: dict, subset: str | None = None) -> list[str]:
    """Markdown lines: per method and scene ``ADE/FDE`` best of 20 and top-1 (focal agent),
    minSADE / minSFDE / OR, then the average of the scenes; ``subset`` the subset's file."""
    cols = FOCAL + JOINT
    name = "results_runs.csv" if subset is None else f"results_{subset}_runs.csv"
    per = {s: _values(runs / "eth_ucy" / s / "eval-test" / name, cols) for s in SCENES}
    methods = [m for m in METHODS.values() if any(m in per[s] for s in SCENES)]
    methods += sorted({m for s in SCENES for m in per[s]} - set(methods))
    head = "| Method | scene | runs | ADE / FDE (best of 20) | ADE / FDE (top 1) | minSADE | minSFDE | OR |"
    lines = [head, "|---|---|---:|---|---|---:|---:|---:|"]
    for m in methods:
        means: dict[str, list[float]] = {k: [] for k in cols}
        for s in (*SCENES, "avg"):
            if s == "avg":
                v = {
                    k: ([float(sum(means[k]) / len(means[k]))] if len(means[k]) == 5 else [])
                    for k in cols
                }
                n = "-"
            else:
                v = per[s].get(m, {})
                n = str(len(v.get("ADE_focal", [])))
                for k in cols:
                    if v.get(k):
                        means[k].append(sum(v[k]) / len(v[k]))
            c = {k: _cell(v.get(k)) for k in cols}
            lines.append(
                f"| {m} | {s} | {n} | {c['ADE_focal']} / {c['FDE_focal']} | "
                f"{c['ADE_focal_top1']} / {c['FDE_focal_top1']} | {c['minSADE']} | "
                f"{c['minSFDE']} | {c['OR']} |"
            )
    if subset is None and pub:
        lines += [
            "",
            "Published (best of 20 unless the protocol says otherwise; sources below):",
            "",
        ]
        lines += ["| Method | scene | ADE / FDE | source | protocol |", "|---|---|---|---|---|"]
        for (m, s), r in sorted(
            pub.items(),
            key=lambda kv: (
                kv[0][0],
                (*SCENES, "avg").index(kv[0][1]) if kv[0][1] in (*SCENES, "avg") else 9,
            ),
        ):
            if r.get("dataset", "eth_ucy") != "eth_ucy":
                continue
            lines.append(
                f"| {m} | {s} | {r['ADE']} / {r['FDE']} | {r['source']} | {r['protocol']} |"
            )
    return lines


def citr_table(runs: Path) -> list[str]:
    cols = ("minADE", "minFDE", "minSADE", "minSFDE", "OR", "ADE_focal", "FDE_focal")
    v = _values(runs / "citr" / "eval-test" / "results_runs.csv", cols)
    lines = [
        "| Method | runs | minADE | minFDE | minSADE | minSFDE | OR | vehicle ADE / FDE |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for m, vals in v.items():
        c = {k: _cell(vals.get(k)) for k in cols}
        lines.append(
            f"| {m} | {len(vals['minADE'])} | {c['minADE']} | {c['minFDE']} | {c['minSADE']} | "
            f"{c['minSFDE']} | {c['OR']} | {c['ADE_focal']} / {c['FDE_focal']} |"
        )
    return lines


def table(argv: list[str]) -> int:
    runs = Path(argv[0])
    pub = published(Path(argv[1]) if len(argv) > 1 else None)
    sets = [s for s in ("eth_ucy", "citr") if (runs / s).is_dir()]
    if not sets:
        raise TableError(
            f"{runs}: neither eth_ucy/ nor citr/ (run 'bench/real_tables.sh train' first)"
        )
    out: list[str] = []
    if "eth_ucy" in sets:
        out += ["ETH/UCY, leave one scene out, test splits (metres; mean ± std over 3 seeds):", ""]
        out += eth_ucy_table(runs, pub)
        out += ["", "ETH/UCY, the interacting subset (min_distance < 1 m):", ""]
        out += eth_ucy_table(runs, pub, "interacting")
    if "citr" in sets:
        out += ["", "CITR, test clips (metres; mean ± std over 3 seeds):", ""] if out else []
        out += citr_table(runs)
    print("\n".join(out))  # nothing is printed when an input is missing
    return 0


def cost(argv: list[str]) -> int:
    """Seconds of one training epoch per model (module docstring)."""
    from learning.data import SceneDataset
    from learning.models import ModelConfig, build_model
    from learning.scoring import evaluate_model
    from learning.train import TrainConfig, torch_threads, train

    data = Path(argv[0])
    steps = int(argv[1]) if len(argv) > 1 else 30
    kinds = argv[2].split() if len(argv) > 2 else ["vlstm", "sc", "epo"]
    warm = 5
    if steps <= warm:
        raise TableError(f"BATCHES: expected more than {warm} (the warm-up steps), got {steps}")
    with SceneDataset(data, "train") as tr:
        n_train, game = len(tr), tr.game
    with SceneDataset(data, "val") as va:
        n_val = len(va)
    batches = -(-n_train // 32)
    print(f"{data}: train {n_train} samples ({batches} batches of 32), val {n_val}")
    print("| model | s / batch | s / epoch (train) | s / val pass | s / epoch |")
    print("|---|---:|---:|---:|---:|")

    class Stop(Exception):
        pass

    for kind in kinds:
        over = {"goal_decoder": "regress"} if kind == "epo" else {}
        mc = ModelConfig(kind=kind, modes=20, **over)
        stamps: list[float] = []

        def on_step(step, parts, stamps=stamps):
            stamps.append(time.perf_counter())
            if step >= steps:
                raise Stop

        with tempfile.TemporaryDirectory() as tmp:
            cfg = TrainConfig(model=mc, epochs=1, batch_size=32, lr=1e-4, seed=0, val_split=None)
            try:
                train(data, Path(tmp) / kind, cfg, progress=False, on_step=on_step, threads=1)
            except Stop:
                pass
        per = (stamps[-1] - stamps[warm - 1]) / (len(stamps) - warm)
        with torch_threads(1), SceneDataset(data, "val") as va:
            model = build_model(mc, game)
            t0 = time.perf_counter()
            evaluate_model(model, va, batch_size=64)
            val = time.perf_counter() - t0
        print(
            f"| {kind} | {per:.3f} | {per * batches:.0f} | {val:.0f} | {per * batches + val:.0f} |",
            flush=True,
        )
    return 0


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in ("table", "cost") or len(argv) < 2:
        print(
            "usage: python bench/real_tables.py table RUNS [PUBLISHED_CSV] | cost DATA [BATCHES] [KINDS]",
            file=sys.stderr,
        )
        return 2
    try:
        return table(argv[1:]) if argv[0] == "table" else cost(argv[1:])
    except TableError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
