"""The summary of a run: one row over its episodes (:func:`summarize`), as Markdown and
CSV, ``episodes.csv`` with one row per episode, and the error note (:func:`write_summary`)."""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from scenarios.files import write_atomic

from .log import OUTCOMES, EpisodeResult

__all__ = [
    "SUMMARY_COLUMNS",
    "EPISODE_COLUMNS",
    "summarize",
    "summary_markdown",
    "error_note",
    "write_summary",
]

#: (column, header, format) of the summary table
SUMMARY_COLUMNS = (
    ("config", "configuration", "{}"),
    ("episodes", "episodes", "{:d}"),
    ("success_rate", "success", "{:.2f}"),
    ("collision_rate", "collision", "{:.2f}"),
    ("timeout_rate", "timeout", "{:.2f}"),
    ("off_road_rate", "off road", "{:.2f}"),
    ("error_rate", "error", "{:.2f}"),
    ("intervention_rate", "intervention", "{:.3f}"),
    ("min_distance", "min dist (m)", "{:.2f}"),
    ("time_to_clear", "clear (s)", "{:.2f}"),
    ("progress", "progress (m)", "{:.1f}"),
    ("rms_jerk", "RMS jerk (m/s^3)", "{:.2f}"),
    ("plan_p50_ms", "plan p50 (ms)", "{:.1f}"),
    ("plan_p99_ms", "plan p99 (ms)", "{:.1f}"),
    ("rtf", "RTF", "{:.2f}"),
    ("fallbacks", "fallbacks", "{:d}"),
    ("filter_fallbacks", "filter fallbacks", "{:d}"),
    ("filter_uncertified", "uncertified", "{:d}"),
    ("filter_p99_ms", "filter p99 (ms)", "{:.1f}"),
    ("min_speed", "min speed (m/s)", "{:.2f}"),
    ("order_switches", "order switches", "{:.1f}"),
    ("reyields_in_zone", "re-yields in zone", "{:d}"),
)


def _nanmean(values) -> float:
    a = np.asarray([v for v in values if v is not None], dtype=float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else math.nan


def summarize(results: Sequence[EpisodeResult], label: str = "") -> dict:
    """One summary row over ``results``: rates of every outcome, means of the metrics
    (over the episodes where a metric is defined), latency percentiles over all steps
    pooled, the mean real-time factor, the total number of fallbacks, the safety filter's
    intervention rate (pooled over steps) and fallbacks (:func:`_filter_summary`), the lowest ego speed
    of all episodes, the mean number of passing-order switches and the total number of
    steps that re-yielded inside the conflict zone (``n/a`` where no episode defines
    them)."""
    n = len(results)
    row: dict[str, Any] = {"config": label, "episodes": n}
    for o in OUTCOMES:
        row[f"{o}_rate"] = sum(r.outcome == o for r in results) / n if n else math.nan
    ms = [r.metrics for r in results if r.outcome != "error"]
    for k in ("min_distance", "time_to_clear", "progress", "rms_jerk", "rtf"):
        row[k] = _nanmean(m.get(k) for m in ms)
    pooled = np.concatenate([np.asarray(r.plan_ms, dtype=float) for r in results] or [[]])
    pooled = pooled[np.isfinite(pooled)]
    row["plan_p50_ms"] = float(np.percentile(pooled, 50)) if pooled.size else math.nan
    row["plan_p99_ms"] = float(np.percentile(pooled, 99)) if pooled.size else math.nan
    row["fallbacks"] = int(sum(int(m.get("fallbacks", 0) or 0) for m in ms))
    row.update(_filter_summary(ms))
    speeds = [m.get("min_speed") for m in ms]
    speeds = [v for v in speeds if v is not None and math.isfinite(v)]
    row["min_speed"] = float(min(speeds)) if speeds else math.nan
    row["order_switches"] = _nanmean(m.get("order_switches") for m in ms)
    counts = [m.get("reyields_in_zone") for m in ms]
    counts = [int(c) for c in counts if c is not None and math.isfinite(c)]
    row["reyields_in_zone"] = int(sum(counts)) if counts else math.nan
    return row


def _filter_summary(ms: Sequence[dict]) -> dict:
    """The safety filter's columns: the intervention rate over all steps pooled (episodes
    weighted by their steps), the total fallbacks and uncertified fallbacks, and the mean of
    the episodes' filter p99 (ms); ``n/a`` / 0 when no episode ran a filter."""
    rated = [
        m
        for m in ms
        if m.get("intervention_rate") is not None and math.isfinite(m["intervention_rate"])
    ]
    steps = sum(int(m.get("steps", 0) or 0) for m in rated)
    hits = sum(float(m["intervention_rate"]) * int(m.get("steps", 0) or 0) for m in rated)
    return {
        "intervention_rate": hits / steps if steps else math.nan,
        "filter_fallbacks": int(sum(int(m.get("filter_fallbacks", 0) or 0) for m in ms)),
        "filter_uncertified": int(sum(int(m.get("filter_uncertified", 0) or 0) for m in ms)),
        "filter_p99_ms": _nanmean(m.get("filter_p99_ms") for m in ms),
    }


def _cell(fmt: str, v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return fmt.format(v)


def summary_markdown(rows: Sequence[dict]) -> str:
    """The summary rows as a Markdown table (``n/a`` where a metric is undefined)."""
    head = "| " + " | ".join(h for _, h, _ in SUMMARY_COLUMNS) + " |"
    sep = "|" + "|".join("---" if k == "config" else "---:" for k, _, _ in SUMMARY_COLUMNS) + "|"
    lines = [head, sep]
    for row in rows:
        lines.append("| " + " | ".join(_cell(f, row.get(k)) for k, _, f in SUMMARY_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def _csv(rows: Sequence[dict], columns: Sequence[str]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for row in rows:
        vals = []
        for c in columns:
            v = row.get(c)
            if isinstance(v, float) and not math.isfinite(v):
                v = ""
            vals.append("" if v is None else v)
        w.writerow(vals)
    return buf.getvalue()


EPISODE_COLUMNS = (
    "index",
    "seed",
    "outcome",
    "min_distance",
    "time_to_clear",
    "progress",
    "rms_jerk",
    "plan_p50_ms",
    "plan_p99_ms",
    "rtf",
    "fallbacks",
    "intervention_rate",
    "filter_fallbacks",
    "filter_uncertified",
    "filter_p50_ms",
    "filter_p99_ms",
    "min_speed",
    "reverse_distance",
    "order_switches",
    "reyields_in_zone",
    "message",
)


def error_note(results: Sequence[EpisodeResult]) -> str | None:
    """``"2 of 5 episodes ended in an error; the first, episode 1 (seed 1): ..."``, or None
    when none did."""
    errors = [r for r in results if r.outcome == "error"]
    if not errors:
        return None
    e = errors[0]
    return (
        f"{len(errors)} of {len(results)} episodes ended in an error; the first, episode "
        f"{e.index} (seed {e.seed}): {e.message}"
    )


def write_summary(directory: str | os.PathLike, results: Sequence[EpisodeResult], summary: dict):
    """Write ``summary.md``, ``summary.csv`` and ``episodes.csv`` atomically.

    ``summary.md`` is the table, then (when episodes ended in an error) one line saying how
    many and the first error (:func:`error_note`)."""
    d = Path(directory)
    note = error_note(results)
    md = summary_markdown([summary]) + (f"\n{note}\n" if note else "")
    write_atomic(d / "summary.md", md)
    write_atomic(d / "summary.csv", _csv([summary], [k for k, _, _ in SUMMARY_COLUMNS]))
    rows = [
        {
            "index": r.index,
            "seed": r.seed,
            "outcome": r.outcome,
            "message": r.message,
            **{k: r.metrics.get(k) for k in EPISODE_COLUMNS[3:-1]},
        }
        for r in results
    ]
    write_atomic(d / "episodes.csv", _csv(rows, EPISODE_COLUMNS))
