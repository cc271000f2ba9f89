"""Learnable parameters per module of the exiD (or Waymo) models against the paper's figures.

Builds V-LSTM, V-LSTM + SC, V-LSTM + TGL and V-LSTM + Ours (``epo train``'s models:
:func:`learning.models.build_model` with ``ModelConfig(kind, modes=M)``, ours with
``goal_decoder="candidates"`` as ``bench/exid_tab2.sh`` trains it) for the game of an
exiD-layout dataset (N = 4 agents, K = 20 future steps, M = 5 modes) and prints the
trainable parameters of every submodule (the encoder's parts one by one), the totals and
the paper's totals (App. G, runtime and parameter table: 432,125 / 538,749 / 616,496 /
617,471). ``--setting waymo`` builds VIBES + SC and VIBES + Ours (goals regressed) for the
Waymo game (N = 2, K = 80, M = 6; paper: 1,183,687 and 852,786).

The game comes from ``--data DIR`` (a dataset's manifest) or, by default, from the
scenario's default recipe (no data needed: a model's sizes depend only on the game's
agents, horizon, controls and parameter layout, and ``M``). Every other setting is
:class:`learning.models.ModelConfig`'s default (paper App. F), overridable with
``--set FIELD=VALUE`` (numbers only).

Run ``python bench/param_counts.py`` (a few seconds); ``--csv FILE`` also writes the table.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torch import nn  # noqa: E402

from learning.models import ModelConfig, build_model, count_parameters  # noqa: E402

#: the paper's learnable parameters: (setting, label) -> total
PAPER = {
    ("exid", "V-LSTM"): 432_125,
    ("exid", "V-LSTM + SC"): 538_749,
    ("exid", "V-LSTM + TGL"): 616_496,
    ("exid", "V-LSTM + Ours"): 617_471,
    ("waymo", "VIBES + SC"): 1_183_687,
    ("waymo", "VIBES + Ours"): 852_786,
}

#: setting -> (label, ModelConfig overrides) of its models
MODELS = {
    "exid": (
        ("V-LSTM", {"kind": "vlstm"}),
        ("V-LSTM + SC", {"kind": "sc"}),
        ("V-LSTM + TGL", {"kind": "tgl"}),
        ("V-LSTM + Ours", {"kind": "epo", "goal_decoder": "candidates"}),
    ),
    "waymo": (
        ("VIBES + SC", {"kind": "sc", "backbone": "vibes"}),
        ("VIBES + Ours", {"kind": "epo", "backbone": "vibes", "goal_decoder": "regress"}),
    ),
}

#: the modules reported one by one (the encoder's parts; every other top-level module whole)
SPLIT = ("encoder",)


def setting_game(setting: str, data: str | None = None):
    """The game of ``data``'s manifest, or of the setting's default recipe."""
    from learning.data import dataset_game

    if data is not None:
        return dataset_game(data)
    if setting == "exid":
        from scenarios.exid import ExidRecipe

        return dataset_game({"scenario": "exid", "recipe": ExidRecipe().to_dict()})
    from scenarios.real.waymo.recipe import WaymoRecipe, game_from_recipe

    return game_from_recipe(WaymoRecipe().to_dict())


def setting_modes(setting: str, data: str | None = None) -> int:
    """``M`` of the dataset (its ``future`` field's first dimension) or of the setting."""
    if data is not None:
        from scenarios.dataset import read_manifest

        return int(read_manifest(data)["schema"]["future"]["shape"][0])
    return 5 if setting == "exid" else 6


def module_counts(model: nn.Module) -> dict[str, int]:
    """Trainable parameters of every top-level submodule (those of :data:`SPLIT` by part),
    in creation order; parameters held by a model itself (none here) under ``(own)``."""
    out: dict[str, int] = {}
    for name, child in model.named_children():
        if name in SPLIT:
            for part, sub in child.named_children():
                out[f"{name}.{part}"] = count_parameters(sub)
        else:
            out[name] = count_parameters(child)
    own = sum(p.numel() for p in model.parameters(recurse=False) if p.requires_grad)
    if own:
        out["(own)"] = own
    return out


def build(setting: str, overrides: dict, game, modes: int) -> dict[str, nn.Module]:
    """The setting's models (label -> model), layer execution left uncompiled (no effect on
    the parameters)."""
    models = {}
    for label, kw in MODELS[setting]:
        cfg = ModelConfig(modes=modes, layer_compiled="no", **{**kw, **overrides})
        models[label] = build_model(cfg, game)
    return models


def table(setting: str, models: dict[str, nn.Module]) -> list[list[str]]:
    """Rows ``[module, count per model...]``, then the totals, the paper's and the ratio."""
    counts = {label: module_counts(m) for label, m in models.items()}
    names: list[str] = []
    for c in counts.values():
        names += [n for n in c if n not in names]
    rows = [[n] + [f"{c[n]:,}" if n in c else "-" for c in counts.values()] for n in names]
    totals = {label: count_parameters(m) for label, m in models.items()}
    for label in models:  # the rows add up to the total (no parameter counted twice)
        if sum(counts[label].values()) != totals[label]:
            raise RuntimeError(f"{label}: the modules' counts do not add up to the total")
    paper = [PAPER.get((setting, label)) for label in models]
    rows.append(["total"] + [f"{t:,}" for t in totals.values()])
    rows.append(["paper"] + [f"{p:,}" if p else "-" for p in paper])
    rows.append(
        ["paper / ours"]
        + [f"{p / t:.2f}" if p else "-" for p, t in zip(paper, totals.values(), strict=True)]
    )
    return rows


def _value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--setting", choices=sorted(MODELS), default="exid")
    ap.add_argument("--data", default=None, help="dataset directory (default: the recipe's game)")
    ap.add_argument(
        "--set", action="append", default=[], metavar="FIELD=VALUE", help="ModelConfig field"
    )
    ap.add_argument("--csv", default=None, help="also write the table to this CSV file")
    a = ap.parse_args(argv)
    overrides = {k: _value(v) for k, v in (s.split("=", 1) for s in a.set)}
    game = setting_game(a.setting, a.data)
    modes = setting_modes(a.setting, a.data)
    models = build(a.setting, overrides, game, modes)
    rows = table(a.setting, models)
    head = ["module", *models]
    print(f"{a.setting}: N = {game.N}, K = {game.K}, M = {modes}")
    print("| " + " | ".join(head) + " |")
    print("|---|" + "---:|" * len(models))
    for r in rows:
        print("| " + " | ".join(r) + " |")
    if a.csv:
        with open(a.csv, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(head)
            w.writerows([[c.replace(",", "") for c in r] for r in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main())
