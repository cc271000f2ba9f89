"""Torch side: the differentiable game layer, networks, losses, metrics, training."""

from .control import SDVPlan, plan, sdv_strategy
from .layer import GameLayer, LayerOutput
from .models import ModelConfig, build_model
from .tgl import TGLModel  # registers the 'tgl' model kind

__all__ = [
    "GameLayer",
    "LayerOutput",
    "ModelConfig",
    "SDVPlan",
    "TGLModel",
    "build_model",
    "plan",
    "sdv_strategy",
]
