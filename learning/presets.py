"""Named training settings of the paper's experiments (``epo train --preset NAME``).

A preset gives defaults of :class:`learning.train.TrainConfig` (batch size, learning rate,
loss weights, the imitation loss's reduction over the future steps) and of
:class:`learning.models.ModelConfig` (modes, goal decoder, the game layer's S, alpha,
lambda). Options given on the command line (``--batch-size``, ``--lr``, ``--loss-weights``,
``--imitation-reduction``, ``--modes``, ``--lm-steps``, ``--set FIELD=VALUE``) override the
preset's values.

``waymo`` (App. F, "Waymo Interactive" and the losses paragraph)
    batch size 32, Adam learning rate 1e-4, loss weights lambda_1 = lambda_2 = lambda_3 = 1,
    the imitation loss in the paper's form (App. F.4: squared distances summed over the
    future steps, ``imitation_reduction="sum"``), M = 6 joint modes, regressed goals (``goal_decoder="regress"``, ours only), S = 2 LM
    steps, alpha = 0.3, lambda = 10. The game's features (goal, vel, acc, jerk, turn rate,
    turn acceleration; collisions every 5th step) are the dataset's
    (``epo generate waymo``, :mod:`scenarios.real.waymo`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from epo_casadi.errors import SpecError

__all__ = ["PRESETS", "Preset", "get_preset"]

#: ModelConfig fields that only ours (kind "epo") accepts
_EPO_ONLY = ("goal_decoder", "collision_margin")


@dataclass(frozen=True)
class Preset:
    """Defaults of a training run: ``train`` (TrainConfig fields but ``model``, ``loss`` and
    ``imitation_reduction``), ``model`` (ModelConfig fields), ``loss`` (LossWeights fields)
    and ``imitation_reduction`` (TrainConfig's; None: its default, ``"mean"``)."""

    description: str
    train: Mapping = field(default_factory=dict)
    model: Mapping = field(default_factory=dict)
    loss: Mapping = field(default_factory=dict)
    imitation_reduction: str | None = None

    def model_fields(self, kind: str) -> dict:
        """The model defaults for ``kind`` (ours-only fields dropped for the baselines)."""
        return {k: v for k, v in self.model.items() if kind == "epo" or k not in _EPO_ONLY}


PRESETS: dict[str, Preset] = {
    "waymo": Preset(
        "the paper's Waymo setting (App. F): batch 32, lr 1e-4, loss weights 1/1/1, imitation "
        "loss summed over the steps, M = 6, regressed goals, S = 2, alpha 0.3, lambda 10",
        train={"batch_size": 32, "lr": 1e-4},
        model={
            "modes": 6,
            "goal_decoder": "regress",
            "lm_steps": 2,
            "step_size": 0.3,
            "damping": 10.0,
        },
        loss={"imitation": 1.0, "goal": 1.0, "probability": 1.0},
        imitation_reduction="sum",
    ),
}


def get_preset(name: str, field_name: str = "--preset") -> Preset:
    """The preset ``name``; an unknown name is a :class:`SpecError` listing the known ones."""
    if name not in PRESETS:
        raise SpecError(field_name, f"unknown preset {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name]
