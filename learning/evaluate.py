"""Evaluation of trained runs and the CV baseline on a split; the paper-style table.

:func:`evaluate_model` scores one predictor on a :class:`learning.data.SceneDataset`
with :func:`learning.metrics.all_metrics`: minADE, minFDE (marginal), minSADE, minSFDE
and the overlap rate OR of the most likely joint mode (joint), in metres, averaged over
the samples. Joint models (ours, SC, CV) give scene probabilities ``softmax(logits)``;
the marginal V-LSTM gives per-agent probabilities, turned into joint scenes by
:func:`learning.metrics.marginal_to_joint` as in the paper. The agents' circles for OR are
each sample's ``radius`` where the dataset stores it and the game takes it as a parameter
(the readers of recorded data, exiD), else the dataset game's radii; on datasets with
vehicle sizes (``length``, ``width``: exiD layout, Waymo) ``OR`` uses oriented vehicle
boxes instead and ``OR_circle`` keeps the circles (:mod:`learning.scoring`); the table's
header says which. Padded agents (the batches' ``agents_mask`` False) count in no metric:
the means are over each sample's real agents, the overlap rate over pairs of real agents.

Focal agent: a dataset whose manifest says ``meta.focal_slot`` (an agent slot; 0 in the
readers of :mod:`scenarios.real`: the ETH/UCY focal pedestrian, the CITR vehicle, the first
agent of a Waymo pair) also gets :data:`learning.metrics.FOCAL_METRICS`: ``ADE_focal`` /
``FDE_focal`` (that agent's best of the M modes: the benchmark's best of 20 with M = 20) and
``ADE_focal_top1`` / ``FDE_focal_top1`` (its most likely mode).

Initial strategies: ours' output has the rollout of its learned initialization
(``init_pos``, before the game layer's ``S`` steps); it is scored with the same metrics,
reported with the prefix ``init_`` (``init_minSADE``, ...; :mod:`learning.scoring`): in
the per-run and per-method CSV files and in a second table, "Initial strategies", under
the main one. Models without one (the baselines, CV) have no such values.

Subsets (:func:`parse_subset`): ``subsets=["interacting"]`` or ``["min_distance<1"]``
scores the samples whose scalar per-sample field (shape ``()``, read for the call only:
:meth:`learning.data.SceneDataset.sample_field`) compares so with the number, beside the
whole split, from the same predictions (one pass of each model over the split).

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
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from epo_casadi.errors import SpecError
from scenarios.files import ensure_dir, write_atomic

from .baselines import ConstantVelocity
from .data import SceneDataset
from .metrics import FOCAL_METRICS
from .models import ModelConfig
from .scoring import (
    INIT_PREFIX,
    METRICS,
    evaluate_model,
    mean_metrics,
    overlap_shapes,
    predict,
    score_samples,
)
from .train import load_model, torch_threads

__all__ = [
    "METRICS",
    "FOCAL_METRICS",
    "SUBSET_ALIASES",
    "EvalReport",
    "RunResult",
    "Subset",
    "evaluate",
    "evaluate_model",
    "format_mean_std",
    "method_label",
    "parse_subset",
    "predict",
]

#: named subsets: name -> expression (:func:`parse_subset`)
SUBSET_ALIASES = {"interacting": "min_distance<1"}
_OPS = {
    "<": ("lt", np.less),
    "<=": ("le", np.less_equal),
    ">": ("gt", np.greater),
    ">=": ("ge", np.greater_equal),
    "==": ("eq", np.equal),
    "!=": ("ne", np.not_equal),
}
_SUBSET = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=|==|!=|<|>)\s*(\S+)\s*")


@dataclass(frozen=True)
class Subset:
    """Samples whose scalar field ``field`` compares by ``op`` with ``value``; ``name`` is
    the alias or the expression as given."""

    field: str
    op: str
    value: float
    name: str

    @property
    def text(self) -> str:
        """The expression, e.g. ``min_distance < 1``."""
        return f"{self.field} {self.op} {self.value:g}"

    @property
    def slug(self) -> str:
        """A file-name part: the alias, or e.g. ``min_distance_lt_1``."""
        if self.name in SUBSET_ALIASES:
            return self.name
        return f"{self.field}_{_OPS[self.op][0]}_{self.value:g}"

    def select(self, values: np.ndarray) -> np.ndarray:
        """Boolean mask of the samples of ``values`` (the field's ``(n,)``) in the subset."""
        with np.errstate(invalid="ignore"):
            return _OPS[self.op][1](np.asarray(values, np.float64), self.value)


def parse_subset(text: str) -> Subset:
    """``FIELD OP NUMBER`` (``OP`` one of ``< <= > >= == !=``, e.g. ``min_distance<1``) or a
    name of :data:`SUBSET_ALIASES` (``interacting`` = ``min_distance<1``: samples whose
    recorded agents come within 1 m of each other). Whether the field exists is checked
    against the dataset (:func:`evaluate`). A malformed expression is a
    :class:`SpecError` ``--subset``."""
    if not isinstance(text, str):
        raise SpecError("--subset", f"expected FIELD<NUMBER or a name, got {text!r}")
    expr = SUBSET_ALIASES.get(text.strip(), text)
    m = _SUBSET.fullmatch(expr)
    value = math.nan
    if m:
        try:
            value = float(m.group(3))
        except ValueError:
            m = None
    if not m or math.isnan(value):
        raise SpecError(
            "--subset",
            f"expected FIELD OP NUMBER (OP one of {' '.join(_OPS)}; e.g. 'min_distance<1') or "
            f"one of {sorted(SUBSET_ALIASES)}, got {text!r}",
        )
    return Subset(m.group(1), m.group(2), value, text.strip())


BACKBONES = {"vlstm": "V-LSTM", "vibes": "VIBES", "hivt": "HiVT-M"}


def method_label(cfg: ModelConfig | None, train=None) -> str:
    """Table label of a model: ``V-LSTM + Ours``, ``V-LSTM + SC``, ``V-LSTM``; ``CV`` for None.

    Runs with one label are one table row, so every setting that makes ours another method
    is in it: the ablations, another number of LM steps than the paper's 2, decoded goals,
    the implicit backward pass, another collision reach, the current lane as every mode's
    path where the goals are decoded candidates, an agent-weight decoder without batch norm.
    With the run's ``train`` (:class:`~learning.train_config.TrainConfig`), also the training
    loss where it is not the paper's for the model kind: other loss weights, or the
    imitation term summed over the future steps instead of averaged.
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
        if cfg.own_norm != ModelConfig.own_norm:
            label += " (no own batch norm)"  # runs saved before own_norm (learning.models)
    if train is not None:
        from .train_config import PAPER_LOSS_WEIGHTS

        w = train.loss_weights
        if w != PAPER_LOSS_WEIGHTS[cfg.kind]:
            label += f" (loss weights {w.imitation:g} / {w.goal:g} / {w.probability:g})"
        if train.imitation_reduction != "mean":
            label += f" (imitation: {train.imitation_reduction})"
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
    """Results of :func:`evaluate`; :meth:`markdown` is the paper-style table.

    ``circles``: where the overlap rate's circles come from (the table header's words);
    ``focal``: the focal agent's slot when the results carry :data:`FOCAL_METRICS`;
    ``subset`` / ``total``: a report on a subset of the split (its expression, the split's
    size); ``subsets``: the reports of the subsets of this one's split."""

    data_dir: str
    split: str
    results: list[RunResult] = field(default_factory=list)
    circles: str = "the game's radii"
    focal: int | None = None
    subset: Subset | None = None
    total: int | None = None
    subsets: list[EvalReport] = field(default_factory=list)

    def groups(self) -> list[tuple[str, list[RunResult]]]:
        """Results grouped by label, in order of appearance, CV last."""
        out: dict[str, list[RunResult]] = {}
        for r in self.results:
            out.setdefault(r.label, []).append(r)
        return sorted(out.items(), key=lambda kv: kv[0] == "CV")

    def metric_names(self) -> tuple[str, ...]:
        """:data:`METRICS`, plus ``OR_circle`` when OR used vehicle boxes and
        :data:`FOCAL_METRICS` when the results have them."""
        box = any("OR_circle" in r.metrics for r in self.results)
        focal = any("ADE_focal" in r.metrics for r in self.results)
        return METRICS + (("OR_circle",) if box else ()) + (FOCAL_METRICS if focal else ())

    def init_names(self) -> tuple[str, ...]:
        """The metrics of the initial strategies (:meth:`metric_names` prefixed ``init_``)
        that some result has; () when no result has any (no model with ``init_pos``)."""
        names = (INIT_PREFIX + k for k in self.metric_names())
        return tuple(k for k in names if any(k in r.metrics for r in self.results))

    def summary_rows(self) -> list[dict]:
        rows = []
        for label, rs in self.groups():
            row = {"method": label, "runs": len(rs), "samples": rs[0].samples}
            for k in self.metric_names() + self.init_names():
                v = [r.metrics.get(k, math.nan) for r in rs]
                row[f"{k}_mean"] = float(np.mean(v))
                row[f"{k}_std"] = float(np.std(v, ddof=1)) if len(v) > 1 else math.nan
            rows.append(row)
        return rows

    def markdown(self) -> str:
        """The table: one row per method, ``mean ± std`` over its runs; distances in metres.
        Each subset's table follows (:attr:`subsets`)."""
        n = self.results[0].samples if self.results else 0
        names = self.metric_names()
        orule = (
            "OR: oriented vehicle boxes (length x width, heading along the predicted motion); "
            f"OR_circle: circles of {self.circles}"
            if "OR_circle" in names
            else f"OR: circles of {self.circles}"
        )
        if "ADE_focal" in names:
            orule += (
                f". ADE_focal/FDE_focal: the focal agent (slot {self.focal}), best of the "
                "M modes; ADE_focal_top1/FDE_focal_top1: its most likely mode (joint models: "
                "the scene probability's argmax; marginal: its own mode probabilities)"
            )
        where = f"Split `{self.split}` of `{self.data_dir}` ({n} samples)"
        if self.subset is not None:
            s = self.subset
            named = f"`{s.name}` (`{s.text}`)" if s.name in SUBSET_ALIASES else f"`{s.text}`"
            where = (
                f"Subset {named} of split `{self.split}` of `{self.data_dir}` ({n} of "
                f"{self.total} samples)"
            )
        lines = [
            f"{where}. minADE/minFDE marginal, "
            "minSADE/minSFDE/OR joint; metres; lower is better; mean ± std (ddof 1) over runs. "
            f"{orule}.",
            "",
            *self._table(names, names),
        ]
        lines += self._init_table()
        return "\n".join(lines) + "\n" + "".join("\n" + sub.markdown() for sub in self.subsets)

    def _init_table(self) -> list[str]:
        """The lines of the initial strategies' table (methods with ``init_`` values), or []."""
        init = self.init_names()
        if not init:
            return []
        names = [k.removeprefix(INIT_PREFIX) for k in init]
        lines = [
            "",
            "Initial strategies (the rollout of the learned initialization, before the game "
            "layer's S steps; the modes ranked by the same scene probabilities), the same "
            "metrics:",
            "",
            *self._table(names, init, only_with=True),
        ]
        return lines

    def _table(self, names, keys, only_with: bool = False) -> list[str]:
        """Header and one row per method: columns ``names``, cells ``mean ± std`` of the
        metrics ``keys`` over its runs; ``only_with``: methods with none of ``keys`` left out."""
        lines = [
            "| Method | runs | " + " | ".join(names) + " |",
            "|---|---:|" + "---:|" * len(names),
        ]
        for label, rs in self.groups():
            if only_with and not any(k in r.metrics for r in rs for k in keys):
                continue
            cells = [format_mean_std([r.metrics.get(k, math.nan) for r in rs]) for k in keys]
            lines.append(f"| {label} | {len(rs)} | " + " | ".join(cells) + " |")
        return lines

    def write(self, prefix: str | os.PathLike) -> list[Path]:
        """``PREFIX.md`` (the tables), ``PREFIX.csv`` (per method), ``PREFIX_runs.csv`` (per
        run); for each subset ``PREFIX_<slug>.csv`` and ``PREFIX_<slug>_runs.csv``
        (:attr:`Subset.slug`, e.g. ``results_interacting_runs.csv``; rows with a ``subset``
        column, the expression).

        Each file is written atomically (:func:`scenarios.files.write_atomic`): a folder
        that cannot be written is one :class:`~epo_casadi.errors.OutputError` naming the
        file, and no partial file is left."""
        p = Path(prefix)
        ensure_dir(p.parent)
        md = p.with_name(p.name + ".md")
        write_atomic(md, self.markdown())
        paths = [md, *self._write_csv(p)]
        for sub in self.subsets:
            paths += sub._write_csv(p.with_name(f"{p.name}_{sub.subset.slug}"))
        return paths

    def _write_csv(self, p: Path) -> list[Path]:
        summ, runs = p.with_name(p.name + ".csv"), p.with_name(p.name + "_runs.csv")
        where = {} if self.subset is None else {"subset": self.subset.text}
        _csv(summ, [{**where, **row} for row in self.summary_rows()])
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
                    **where,
                    "samples": r.samples,
                    **r.metrics,
                    "seconds": round(r.seconds, 3),
                }
                for r in self.results
            ],
        )
        return [summ, runs]


def _csv(path: Path, rows: list[dict]) -> None:
    """``rows`` as CSV: the union of their keys as columns, in order of appearance (a run
    without initial strategies leaves the ``init_`` cells empty)."""
    buf = io.StringIO()
    if rows:
        keys = list(dict.fromkeys(k for r in rows for k in r))
        w = csv.DictWriter(buf, fieldnames=keys)
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
    subsets=(),
) -> EvalReport:
    """Score run directories (and CV with ``cv=True``) on ``split`` of ``data_dir``.

    A run given twice (the same folder after resolving links and ``..``) is refused
    with :class:`SpecError` (field ``runs``): it would count twice in its method's
    mean ± std. ``threads``: torch threads during the call
    (:func:`learning.train.torch_threads`). ``subsets``: expressions or names
    (:func:`parse_subset`) of subsets also scored (:attr:`EvalReport.subsets`); a field
    the dataset does not have as one number per sample is refused naming it
    (:class:`SpecError` ``--subset``), before any model runs. The focal metrics are
    reported when the manifest's ``meta.focal_slot`` names an agent slot.
    """
    subsets = [parse_subset(s) if isinstance(s, str) else s for s in subsets]
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
        return _evaluate(runs, data_dir, split, cv, batch_size, checkpoint, progress, subsets)


def focal_slot(data: SceneDataset) -> int | None:
    """The manifest's ``meta.focal_slot`` (an agent slot), or None without one; a value that
    is not a slot of the dataset's agents is a :class:`DatasetError` naming it."""
    from scenarios.dataset import MANIFEST, DatasetError

    v = (data.manifest.get("meta") or {}).get("focal_slot")
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < data.n_agents:
        raise DatasetError(
            f"{data.directory / MANIFEST}.meta.focal_slot",
            f"expected an agent slot in [0, {data.n_agents}), got {v!r}",
        )
    return v


def _evaluate(runs, data_dir, split, cv, batch_size, checkpoint, progress, subsets):
    data = SceneDataset(data_dir, split)
    try:
        if len(data) == 0:
            raise SpecError("split", f"split {split!r} of {data_dir} has no samples")
        scalars = data.scalar_fields()
        for s in subsets:
            if s.field not in scalars:
                raise SpecError(
                    "--subset",
                    f"{s.name!r}: no field {s.field!r} of one number per sample in {data_dir}; "
                    f"the scalar per-sample fields: {scalars}",
                )
        masks = [s.select(data.sample_field(s.field)) for s in subsets]
        game = data.game
        focal = focal_slot(data)
        _, circles = overlap_shapes(data)
        report = EvalReport(str(data_dir), split, circles=circles, focal=focal)
        report.subsets = [
            EvalReport(
                str(data_dir), split, circles=circles, focal=focal, subset=s, total=len(data)
            )
            for s in subsets
        ]

        def score(model, name, label, kind, seed, epoch):
            t0 = time.perf_counter()
            per = score_samples(model, data, batch_size, progress, focal)
            seconds = time.perf_counter() - t0
            for rep, sel in [(report, None), *zip(report.subsets, masks, strict=True)]:
                m = mean_metrics(per, sel)
                rep.results.append(
                    RunResult(name, label, kind, seed, epoch, int(m.pop("samples")), m, seconds)
                )

        for run in runs:
            model, cfg, ck = load_model(run, game, which=checkpoint)
            score(
                model,
                str(run),
                method_label(cfg.model, cfg),
                cfg.model.kind,
                cfg.seed,
                int(ck["epoch"]),
            )
        if cv:
            score(ConstantVelocity(game.K, data.modes), "cv", "CV", "cv", None, None)
    finally:
        data.close()
    return report
