"""Simulated worlds for the closed loop (:class:`solvers.control.types.World`), no torch.

``make_world(name, **options)`` builds one by name:

``"left-turn"``  :class:`~scenarios.sim.left_turn.LeftTurnWorld`, highway-env
``"merge"``      :class:`~scenarios.sim.merge.MergeWorld`, highway-env
``"crossing"``   :class:`~scenarios.sim.crossing.CrossingWorld`, our own small simulation

The world modules (and highway-env behind them) are imported on first use, so
``import scenarios.sim`` stays light.
"""

from __future__ import annotations

import importlib

from epo_casadi.errors import SpecError

__all__ = ["WORLDS", "make_world"]

#: scenario name -> "module:Class"
WORLDS = {
    "left-turn": "scenarios.sim.left_turn:LeftTurnWorld",
    "merge": "scenarios.sim.merge:MergeWorld",
    "crossing": "scenarios.sim.crossing:CrossingWorld",
}


def make_world(name: str, **options):
    """The world ``name`` with ``options`` (the fields of its options dataclass).

    Unknown names and options raise :class:`~epo_casadi.errors.SpecError` naming them and
    the valid ones."""
    if name not in WORLDS:
        raise SpecError("scenario", f"unknown scenario {name!r}; valid: {', '.join(WORLDS)}")
    module, cls = WORLDS[name].split(":")
    return getattr(importlib.import_module(module), cls)(**options)
