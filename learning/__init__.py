"""Torch side: the differentiable game layer, networks, losses, metrics, training.

The names below are imported on first use (``from learning import GameLayer`` imports
:mod:`learning.layer` then): ``import learning`` imports no submodule, and a user of the
layer or the models does not import the closed-loop planner (:mod:`learning.planner`) nor
the TGL model (:mod:`learning.tgl`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

#: public name -> the module of this package that defines it
_EXPORTS = {
    "GameLayer": "layer",
    "LayerOutput": "layer",
    "ModelConfig": "models",
    "build_model": "models",
    "SDVPlan": "control",
    "plan": "control",
    "sdv_strategy": "control",
    "TGLModel": "tgl",
}

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

if TYPE_CHECKING:
    from .control import SDVPlan, plan, sdv_strategy
    from .layer import GameLayer, LayerOutput
    from .models import ModelConfig, build_model
    from .tgl import TGLModel


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})
