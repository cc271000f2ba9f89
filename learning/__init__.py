"""Torch side: the differentiable game layer, networks, losses, metrics, training."""

from .layer import GameLayer, LayerOutput
from .models import ModelConfig, build_model

__all__ = ["GameLayer", "LayerOutput", "ModelConfig", "build_model"]
