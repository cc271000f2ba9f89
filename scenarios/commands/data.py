"""``epo data``: check and look at a generated dataset.

``epo data verify DIR`` checks the manifest, completeness, sha256 checksums, shapes,
counts, that no work unit (main game) is in two splits, that every shard is listed in
exactly its own split and that every shard file belongs to this dataset, split and units
(:func:`scenarios.dataset.verify`); ``epo data show DIR --split test --index I --out
fig.png`` draws one sample: history, the predicted modes, goals. The figure is written
atomically (:func:`scenarios.plotting.save_figure`): an unwritable folder is one ``cannot write`` line.
"""

from __future__ import annotations

from pathlib import Path

import click

from epo_casadi.errors import EpoError


@click.group("data")
def data():
    """Verify or show a generated dataset."""


@data.command("verify")
@click.argument("directory", type=click.Path(path_type=Path))
@click.option("--no-checksums", is_flag=True, help="Skip the sha256 checks (faster).")
def verify_cmd(directory: Path, no_checksums: bool):
    """Check counts, checksums and splits of the dataset in DIRECTORY."""
    from scenarios.dataset import verify

    rep = verify(directory, checksums=not no_checksums)
    if not rep.ok:
        raise EpoError(rep.summary())
    click.echo(rep.summary())


@data.command("show")
@click.argument("directory", type=click.Path(path_type=Path))
@click.option(
    "--split", type=click.Choice(["train", "val", "test"]), default="test", show_default=True
)
@click.option(
    "--index",
    type=int,
    default=0,
    show_default=True,
    help="Sample index in the split, 0 to its size - 1 (negative indices are refused).",
)
@click.option(
    "--out",
    "out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("sample.png"),
    show_default=True,
)
def show_cmd(directory: Path, split: str, index: int, out: Path):
    """Draw one sample (history, modes, goals) to a PNG (or another image format by
    the suffix of --out); the figure is written atomically."""
    from scenarios.dataset import MANIFEST, DatasetError, SplitReader
    from scenarios.plotting import check_image_path

    check_image_path(out, "--out")  # before any reading
    with SplitReader(directory, split) as r:
        s = r[index]
        meta = r.manifest.get("meta", {})
    missing = [k for k in ("history", "future") if k not in s]
    if missing:
        raise DatasetError(
            f"{directory / MANIFEST}.schema.{missing[0]}",
            "missing; data show draws a sample's history and future",
        )
    plot_sample(s, out, title=f"{directory.name} {split}[{index}]", agents=meta.get("agents"))
    click.echo(f"wrote {out}")


def plot_sample(s: dict, out: Path, title: str = "", agents=None) -> None:
    """Figure of one RPI-style sample: dotted history, solid modes (width ~ share), goals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    hist, fut = s["history"], s["future"]
    N = hist.shape[1]
    agents = agents or [f"agent {i}" for i in range(N)]
    colors = ["black", "tab:pink", "tab:blue", "tab:green"]
    mode_colors = ["tab:red", "tab:blue", "tab:orange", "tab:green"]
    fig, ax = plt.subplots(figsize=(6, 6))
    for lane in s.get("lanes", ()):  # map polylines (left-turn datasets)
        ax.plot(lane[:, 0], lane[:, 1], "-", color="0.85", lw=6, zorder=0)
    for i in range(N):
        valid = s.get("history_valid", np.ones(len(hist), bool))
        ax.plot(hist[~valid, i, 0], hist[~valid, i, 1], ":", color=colors[i % 4], alpha=0.3)
        ax.plot(
            hist[valid, i, 0],
            hist[valid, i, 1],
            ":",
            color=colors[i % 4],
            lw=2,
            label=f"{agents[i]} history",
        )
        ax.plot(*hist[-1, i, :2], "o", color=colors[i % 4], ms=8)
        if "goals" in s:
            ax.plot(*s["goals"][i], "*", color=colors[i % 4], ms=14, mec="grey")
    for m in range(fut.shape[0]):
        if "mode_valid" in s and not s["mode_valid"][m]:
            continue
        share = float(s["mode_share"][m]) if "mode_share" in s else 1.0
        for i in range(N):
            xy = np.concatenate([hist[-1:, i, :2], fut[m, i, :, :2]])
            ax.plot(
                xy[:, 0],
                xy[:, 1],
                "-",
                color=mode_colors[m % 4],
                lw=1 + 3 * share,
                label=f"mode {m} ({share:.2f})" if i == 0 else None,
            )
    info = []
    for k in ("main_game", "step", "collision_weight", "gt_mode"):
        if k in s:
            info.append(f"{k} {float(s[k]):.3g}")
    ax.set_title(f"{title}\n{', '.join(info)}", fontsize=9)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    from scenarios.plotting import save_figure

    try:
        save_figure(fig, out, "--out", dpi=100, bbox_inches="tight")
    finally:
        plt.close(fig)
