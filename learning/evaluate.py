"""Evaluation of trained runs and the CV baseline on a split; the paper-style table.

:func:`evaluate_model` scores one predictor on a :class:`learning.data.SceneDataset`
with :func:`learning.metrics.all_metrics`: minADE, minFDE (marginal), minSADE, minSFDE
and the overlap rate OR of the most likely joint mode (joint), in metres, averaged over
the samples. Joint models (ours, SC, CV) give scene probabilities ``softmax(logits)``;
the marginal V-LSTM gives per-agent probabilities, turned into joint scenes by
:func:`learning.metrics.marginal_to_joint` as in the paper. The agents' radii for OR come
from the dataset's game; on datasets with vehicle sizes (exiD layout: ``length``, ``width``)
``OR`` uses oriented vehicle boxes instead and ``OR_circle`` keeps the circles
(:mod:`learning.metrics`); the table's header says which. Padded agents (the batches'
``agents_mask`` False) count in no metric: the means are over each sample's real agents,
the overlap rate over pairs of real agents.

:func:`evaluate` scores run directories (written by :func:`learning.train.train`; their
``best.pt`` by default) and optionally CV on one split and returns an
:class:`EvalReport`. Runs are grouped by method label (:func:`method_label`: backbone,
kind and ablation flags, e.g. ``V-LSTM + Ours``): a group of several runs (seeds) is
reported as ``mean ± std`` (sample standard deviation, ``ddof = 1``, as for the paper's
three seeds), a single run as its value.
"""

from __future__ import annotations

import csv
import io
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from epo_casadi.errors import SpecError
from scenarios.files import ensure_dir, write_atomic

from .baselines import ConstantVelocity
from .data import SceneDataset
from .models import ModelConfig
from .scoring import METRICS, evaluate_model, predict
from .train import load_model, torch_threads

__all__ = [
    "METRICS",
    "EvalReport",
    "RunResult",
    "evaluate",
    "evaluate_model",
    "format_mean_std",
    "method_label",
    "predict",
]

BACKBONES = {"vlstm": "V-LSTM", "vibes": "VIBES", "hivt": "HiVT-M"}


def method_label(cfg: ModelConfig | None) -> str:
    """Table label of a model: ``V-LSTM + Ours``, ``V-LSTM + SC``, ``V-LSTM``; ``CV`` for None.

    Runs with one label are one table row, so every setting that makes ours another method
    is in it: the ablations, another number of LM steps than the paper's 2, decoded goals,
    the implicit backward pass, another collision reach, the current lane as every mode's
    path where the goals are decoded candidates.
    """
    if cfg is None:
        return "CV"
    b = BACKBONES.get(cfg.backbone, cfg.backbone)
    label = {"epo": f"{b} + Ours", "sc": f"{b} + SC", "vlstm": b, "tgl": f"{b} + TGL"}[cfg.kind]
    if cfg.kind == "epo":
        if not cfg.learned_init:
            label += " (zero init)"
        if not cfg.goal_features:
            label += " (no goal)"
        if cfg.lm_steps != ModelConfig.lm_steps:
            label += f" (S = {cfg.lm_steps})"
        if cfg.goal_decoder != "given":
            label += f" (goals: {cfg.goal_decoder})"
        if cfg.backward != "unrolled":
            label += f" ({cfg.backward})"
        if cfg.collision_margin is not None:
            label += f" (collision margin {cfg.collision_margin:g} m)"
        if cfg.lane_path != "goal" and cfg.goal_decoder == "candidates":
            label += " (current-lane path)"  # runs saved before lane_path (learning.models)
    return label


def format_mean_std(values, digits: int = 3) -> str:
    """``"m ± s"`` (sample std) for several values, ``"m"`` for one, ``"-"`` for none."""
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    if not v:
        return "-"
    if len(v) == 1:
        return f"{v[0]:.{digits}f}"
    return f"{np.mean(v):.{digits}f} ± {np.std(v, ddof=1):.{digits}f}"


@dataclass
class RunResult:
    """Metrics of one run (or CV) on one split."""

    name: str  #: run directory, or "cv"
    label: str  #: method label, see :func:`method_label`
    kind: str  #: "epo", "sc", "vlstm" or "cv"
    seed: int | None
    epoch: int | None  #: epoch of the evaluated checkpoint
    samples: int
    metrics: dict[str, float]
    seconds: float


@dataclass
class EvalReport:
    """Results of :func:`evaluate`; :meth:`markdown` is the paper-style table."""

    data_dir: str
    split: str
    results: list[RunResult] = field(default_factory=list)

    def groups(self) -> list[tuple[str, list[RunResult]]]:
        """Results grouped by label, in order of appearance, CV last."""
        out: dict[str, list[RunResult]] = {}
        for r in self.results:
            out.setdefault(r.label, []).append(r)
        return sorted(out.items(), key=lambda kv: kv[0] == "CV")

    def metric_names(self) -> tuple[str, ...]:
        """:data:`METRICS`, plus ``OR_circle`` when OR used vehicle boxes."""
        box = any("OR_circle" in r.metrics for r in self.results)
        return METRICS + (("OR_circle",) if box else ())

    def summary_rows(self) -> list[dict]:
        rows = []
        for label, rs in self.groups():
            row = {"method": label, "runs": len(rs), "samples": rs[0].samples}
            for k in self.metric_names():
                v = [r.metrics.get(k, math.nan) for r in rs]
                row[f"{k}_mean"] = float(np.mean(v))
                row[f"{k}_std"] = float(np.std(v, ddof=1)) if len(v) > 1 else math.nan
            rows.append(row)
        return rows

    def markdown(self) -> str:
        """The table: one row per method, ``mean ± std`` over its runs; distances in metres."""
        n = self.results[0].samples if self.results else 0
        names = self.metric_names()
        orule = (
            "OR: oriented vehicle boxes (length x width, heading along the predicted motion); "
            "OR_circle: circles of the game's radii"
            if "OR_circle" in names
            else "OR: circles of the game's radii"
        )
        lines = [
            f"Split `{self.split}` of `{self.data_dir}` ({n} samples). minADE/minFDE marginal, "
            "minSADE/minSFDE/OR joint; metres; lower is better; mean ± std (ddof 1) over runs. "
            f"{orule}.",
            "",
            "| Method | runs | " + " | ".join(names) + " |",
            "|---|---:|" + "---:|" * len(names),
        ]
        for label, rs in self.groups():
            cells = [format_mean_std([r.metrics.get(k, math.nan) for r in rs]) for k in names]
            lines.append(f"| {label} | {len(rs)} | " + " | ".join(cells) + " |")
        return "\n".join(lines) + "\n"

    def write(self, prefix: str | os.PathLike) -> list[Path]:
        """``PREFIX.md`` (table), ``PREFIX.csv`` (per method), ``PREFIX_runs.csv`` (per run).

        Each file is written atomically (:func:`scenarios.files.write_atomic`): a folder
        that cannot be written is one :class:`~epo_casadi.errors.OutputError` naming the
        file, and no partial file is left."""
        p = Path(prefix)
        ensure_dir(p.parent)
        md, summ, runs = (
            p.with_name(p.name + ".md"),
            p.with_name(p.name + ".csv"),
            p.with_name(p.name + "_runs.csv"),
        )
        write_atomic(md, self.markdown())
        _csv(summ, self.summary_rows())
        _csv(
            runs,
            [
                {
                    "run": r.name,
                    "method": r.label,
                    "kind": r.kind,
                    "seed": r.seed,
                    "epoch": r.epoch,
                    "split": self.split,
                    "samples": r.samples,
                    **r.metrics,
                    "seconds": round(r.seconds, 3),
                }
                for r in self.results
            ],
        )
        return [md, summ, runs]


def _csv(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    write_atomic(path, buf.getvalue())


def evaluate(
    runs,
    data_dir: str | os.PathLike,
    split: str = "test",
    cv: bool = False,
    batch_size: int = 64,
    checkpoint: str = "best",
    progress: bool = False,
    threads: int | None = 1,
) -> EvalReport:
    """Score run directories (and CV with ``cv=True``) on ``split`` of ``data_dir``.

    A run given twice (the same folder after resolving links and ``..``) is refused
    with :class:`SpecError` (field ``runs``): it would count twice in its method's
    mean ± std. ``threads``: torch threads during the call
    (:func:`learning.train.torch_threads`).
    """
    runs = [runs] if isinstance(runs, (str, os.PathLike)) else list(runs or [])
    if not runs and not cv:
        raise SpecError("runs", "expected at least one run directory (or cv=True)")
    seen: dict[Path, str] = {}
    for run in runs:
        key = Path(run).resolve()
        if key in seen:
            same = "" if str(run) == seen[key] else f" (also as {seen[key]})"
            raise SpecError(
                "runs",
                f"{run} is given twice{same}; a run counts once in its method's mean ± std, "
                "give each run folder once",
            )
        seen[key] = str(run)
    with torch_threads(threads):
        return _evaluate(runs, data_dir, split, cv, batch_size, checkpoint, progress)


def _evaluate(runs, data_dir, split, cv, batch_size, checkpoint, progress) -> EvalReport:
    data = SceneDataset(data_dir, split)
    if len(data) == 0:
        data.close()
        raise SpecError("split", f"split {split!r} of {data_dir} has no samples")
    game = data.game
    report = EvalReport(str(data_dir), split)
    try:
        for run in runs:
            model, cfg, ck = load_model(run, game, which=checkpoint)
            t0 = time.perf_counter()
            m = evaluate_model(model, data, batch_size, progress)
            report.results.append(
                RunResult(
                    str(run),
                    method_label(cfg.model),
                    cfg.model.kind,
                    cfg.seed,
                    int(ck["epoch"]),
                    int(m.pop("samples")),
                    m,
                    time.perf_counter() - t0,
                )
            )
        if cv:
            t0 = time.perf_counter()
            m = evaluate_model(ConstantVelocity(game.K, data.modes), data, batch_size, progress)
            report.results.append(
                RunResult(
                    "cv", "CV", "cv", None, None, int(m.pop("samples")), m, time.perf_counter() - t0
                )
            )
    finally:
        data.close()
    return report
