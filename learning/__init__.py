"""Torch side: the differentiable game layer, networks, losses, metrics, training."""

from .control import SDVPlan, plan, sdv_strategy
from .layer import GameLayer, LayerOutput
from .models import ModelConfig, build_model

__all__ = [
    "GameLayer",
    "LayerOutput",
    "ModelConfig",
    "SDVPlan",
    "build_model",
    "plan",
    "sdv_strategy",
]
