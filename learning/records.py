"""The records of a training run besides its checkpoints (:mod:`learning.train`).

``metrics.csv`` (:func:`write_csv`: one row per epoch, atomically written), ``loss.png``
(:func:`plot_history`: training loss parts and validation minADE/minSADE per epoch) and
``tb/`` (:func:`tensorboard_writer`: TensorBoard events; the ``tensorboard`` package,
imported on first use; :func:`predictions_image`: the predictions figure of an epoch).
"""

from __future__ import annotations

import csv
import io
import math
import os
import warnings
from pathlib import Path

from scenarios.files import write_atomic

__all__ = ["plot_history", "predictions_image", "tensorboard_writer", "write_csv"]


def write_csv(path: Path, rows: list[dict]) -> None:
    """``rows`` as a CSV file (the union of their keys as columns, in order of appearance)."""
    if not rows:
        return
    keys = list(rows[0])
    for r in rows[1:]:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    w.writerows(rows)
    write_atomic(path, buf.getvalue())


def plot_history(rows: list[dict], out_png: str | os.PathLike, title: str = "") -> None:
    """Training loss parts and validation minADE/minSADE per epoch (matplotlib, Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.6))
    FigureCanvasAgg(fig)
    a1, a2 = fig.subplots(1, 2)
    ep = [r["epoch"] for r in rows]
    parts = [("train_loss", "-o"), ("train_imitation", "--"), ("train_probability", ":")]
    if all(r.get("train_goal", 0) > 0 for r in rows):  # a goal decoder's loss
        parts.append(("train_goal", "-."))
    for k, style in parts:
        a1.plot(ep, [r[k] for r in rows], style, label=k.replace("train_", ""))
    a1.set_yscale("log")
    a1.set_xlabel("epoch")
    a1.set_title("training loss")
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    for k in ("val_minADE", "val_minSADE", "val_minFDE", "val_minSFDE"):
        vals = [r.get(k, math.nan) for r in rows]
        if any(math.isfinite(v) for v in vals):
            a2.plot(ep, vals, "-o", ms=3, label=k[4:])
    a2.set_xlabel("epoch")
    a2.set_ylabel("m")
    a2.set_title("validation")
    if a2.lines:
        a2.legend(fontsize=8)
    a2.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    write_atomic(out_png, lambda f: fig.savefig(f, format="png", dpi=100))


def predictions_image(run_dir: Path, data_dir: Path, split: str, index: int = 0):
    """The predictions figure of sample ``index`` of ``split`` for the run's latest
    checkpoint, as ``epo show-predictions RUN --checkpoint last`` draws it
    (:func:`learning.show.show_predictions`): an ``(H, W, 3)`` uint8 array."""
    import tempfile

    import numpy as np
    from matplotlib.image import imread

    from .show import show_predictions

    with tempfile.TemporaryDirectory(prefix="epo-tb-") as tmp:
        png = show_predictions(
            run_dir, data_dir, index, Path(tmp) / "predictions.png", split=split,
            checkpoint="last",
        )  # fmt: skip
        rgba = imread(png)
    rgb = rgba[..., :3]
    return (rgb * 255).round().astype(np.uint8) if rgb.dtype.kind == "f" else rgb


def tensorboard_writer(log_dir: Path, purge_step: int):
    """A SummaryWriter (events after ``purge_step`` dropped: a resumed run's) when
    tensorboard is installed, else None."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from torch.utils.tensorboard import SummaryWriter
    except Exception:  # not installed (ImportError) or broken: TensorBoard is optional
        return None
    return SummaryWriter(str(log_dir), purge_step=purge_step)
