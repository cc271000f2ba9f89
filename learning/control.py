"""The self-driving vehicle's (SDV's) strategy for control (paper Sec. 4.3).

Ours predicts ``M`` joint strategies of all agents and their scene probabilities. For
control, the SDV executes its own controls of the most likely joint mode (receding
horizon: the first control, or the first few, then predict again).
:func:`sdv_strategy` extracts them from a model output; :func:`plan` runs a model on a
scene batch in evaluation mode and does the same. Agent ``0`` is the SDV by convention
(the robot in RPI).

Works for every model that predicts joint controls (``"epo"``, ``"sc"``); the marginal
V-LSTM predicts positions per agent only and has no strategy to execute. The same model
as a closed-loop planner of a simulated world is :mod:`learning.planner`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from epo_casadi.errors import SpecError

__all__ = ["SDVPlan", "sdv_strategy", "plan"]


@dataclass(frozen=True)
class SDVPlan:
    """One agent's strategy in the most likely joint mode of every scene of a batch."""

    controls: torch.Tensor  #: (B, K, nu) controls u_1..u_K (unicycle: acceleration, turn rate)
    states: torch.Tensor  #: (B, K, nx) the states they lead to (x_1..x_K)
    mode: torch.Tensor  #: (B,) index of the most likely joint mode
    probability: torch.Tensor  #: (B,) its scene probability
    agent: int  #: the agent index

    @property
    def first_control(self) -> torch.Tensor:
        """``(B, nu)``: the control to apply now (receding horizon)."""
        return self.controls[:, 0]


def sdv_strategy(out: dict, agent: int = 0) -> SDVPlan:
    """The strategy of ``agent`` in the most likely joint mode of a model output.

    ``out`` is the dict of :class:`~learning.models.EPOModel` or
    :class:`~learning.models.SCModel` (``controls`` ``(B, M, N, K, nu)``, ``states``
    ``(B, M, N, K, nx)``, ``logits`` ``(B, M)``). Ties go to the lower mode index.
    """
    if "controls" not in out or "logits" not in out:
        raise SpecError(
            "model",
            "the output has no joint controls and scene probabilities (the marginal V-LSTM "
            "predicts positions only); use the 'epo' or 'sc' model",
        )
    U, X, logits = out["controls"], out["states"], out["logits"]
    B, M, N = U.shape[:3]
    if isinstance(agent, bool) or not isinstance(agent, int) or not 0 <= agent < N:
        raise SpecError("agent", f"expected an agent index in [0, {N}), got {agent!r}")
    probs = torch.softmax(logits.detach(), dim=-1)
    mode = probs.argmax(dim=-1)
    b = torch.arange(B, device=U.device)
    return SDVPlan(
        controls=U[b, mode, agent],
        states=X[b, mode, agent],
        mode=mode,
        probability=probs[b, mode],
        agent=agent,
    )


@torch.no_grad()
def plan(model: nn.Module, scene: dict, agent: int = 0) -> SDVPlan:
    """Run ``model`` on ``scene`` in evaluation mode and return ``agent``'s strategy
    (:func:`sdv_strategy`). The model's training flag is restored afterwards."""
    was = model.training
    model.eval()
    try:
        out = model(scene)
    finally:
        model.train(was)
    return sdv_strategy(out, agent)
