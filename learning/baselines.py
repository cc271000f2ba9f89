"""Baselines that need no training: the constant-velocity (CV) predictor (paper Sec. 5).

CV takes each agent's last velocity from its two last observed positions,
``v = (p_H - p_{H-1}) / dt``, and extrapolates it: ``p_{H+t} = p_H + t dt v`` for
``t = 1..T`` (``dt`` cancels: the future advances by the last displacement per step).
It predicts one future per agent; to be scored like the multi-modal models it repeats it
as ``M`` identical joint modes with uniform probabilities (the minimum over identical
modes is the one mode's error, and the most likely mode is mode 0). With a single
history step the velocity is zero.

The predictor has the models' interface (:mod:`learning.models`): ``forward(scene)`` on
the scene dict returns ``pos`` ``(B, M, N, T, 2)`` and joint ``logits`` ``(B, M)``. A padded
agent (``agents_mask`` False) is extrapolated from its neutral history
(:func:`learning.masks.neutral_scene`): it stays at rest, far from the real agents.
"""

from __future__ import annotations

import torch
from torch import nn

from epo_casadi.errors import SpecError

from .masks import neutral_scene

__all__ = ["ConstantVelocity", "constant_velocity"]


def constant_velocity(history: torch.Tensor, horizon: int) -> torch.Tensor:
    """CV extrapolation of ``history`` ``(B, H+1, N, >=2)``: positions ``(B, N, T, 2)``."""
    if history.ndim != 4 or history.shape[-1] < 2:
        raise SpecError("history", f"expected shape (B, H+1, N, >=2), got {tuple(history.shape)}")
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise SpecError("horizon", f"expected an integer >= 1, got {horizon!r}")
    p = history[..., :2]
    last = p[:, -1]  # (B, N, 2)
    step = last - p[:, -2] if p.shape[1] > 1 else torch.zeros_like(last)
    t = torch.arange(1, horizon + 1, dtype=p.dtype, device=p.device)[None, None, :, None]
    return last[:, :, None] + t * step[:, :, None]


class ConstantVelocity(nn.Module):
    """CV as a predictor: ``M`` identical joint modes, uniform probabilities, no parameters."""

    kind = "cv"

    def __init__(self, horizon: int, modes: int = 1):
        super().__init__()
        if isinstance(modes, bool) or not isinstance(modes, int) or modes < 1:
            raise SpecError("modes", f"expected an integer >= 1, got {modes!r}")
        constant_velocity(torch.zeros(1, 2, 1, 2), horizon)  # validates horizon
        self.horizon, self.modes = horizon, modes

    def forward(self, scene: dict) -> dict:
        # a padded agent (agents_mask False) stays at its neutral position (learning.masks)
        pos = constant_velocity(neutral_scene(scene)["history"], self.horizon)  # (B, N, T, 2)
        B = pos.shape[0]
        return {
            "pos": pos[:, None].expand(B, self.modes, *pos.shape[1:]),
            "logits": torch.zeros(B, self.modes, dtype=pos.dtype, device=pos.device),
        }
