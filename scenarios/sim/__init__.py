"""Simulated worlds for the closed loop (:class:`solvers.control.types.World`), no torch.

``make_world(name, **options)`` builds one by name:

``"left-turn"``  :class:`~scenarios.sim.left_turn.LeftTurnWorld`, highway-env
``"merge"``      :class:`~scenarios.sim.merge.MergeWorld`, highway-env
``"crossing"``   :class:`~scenarios.sim.crossing.CrossingWorld`, our own small simulation

The world modules (and highway-env behind them) are imported on first use, so
``import scenarios.sim`` stays light.

What a trained planner needs to know of the scenes a world plays lives here and in the
worlds: :func:`world_scenario` (the dataset scenario of a world), :func:`dataset_frame`
(the frame a dataset's samples are stored in) and :func:`scene_fields` (the fields of a
scene built from the world's map, by the dataset scenario that owns the scene's layout).
"""

from __future__ import annotations

import importlib

from epo_casadi.errors import SpecError

__all__ = [
    "WORLDS",
    "FRAMES",
    "SCENARIO_FRAMES",
    "make_world",
    "world_class",
    "world_scenario",
    "dataset_frame",
    "SCENE_BUILDERS",
    "scene_fields",
]

#: scenario name -> "module:Class"
WORLDS = {
    "left-turn": "scenarios.sim.left_turn:LeftTurnWorld",
    "merge": "scenarios.sim.merge:MergeWorld",
    "crossing": "scenarios.sim.crossing:CrossingWorld",
}

#: frames a dataset may store its samples in (manifest ``meta.frame``): ``"world"``, or
#: ``"agent"`` (agent 0 at the origin with ``x`` along its current heading)
FRAMES = ("world", "agent")

#: the frame of a dataset scenario whose manifest states ``meta.frame`` in words rather than
#: as one of :data:`FRAMES` (left-turn: "SDV at the origin, x along its heading, ...")
SCENARIO_FRAMES = {"left-turn": "agent"}

#: dataset scenario -> "module:function" building the map fields of its scenes in the closed
#: loop, ``f(world, obs, est, frame, recipe) -> {field: array}`` (the scenario owns its layout)
SCENE_BUILDERS = {"left-turn": "scenarios.left_turn:closed_loop_scene_fields"}


def scene_fields(world, obs, est, frame, recipe) -> dict:
    """The fields of a dataset scene that a trained planner cannot build from the
    observation and the estimate itself (the world's ``scene_field_names``: e.g. lanes and
    goal candidates from the map), built by the :data:`SCENE_BUILDERS` entry of the world's
    dataset scenario (:func:`world_scenario`), as numpy arrays without the batch axis,
    exactly as the dataset's generator writes them; ``{}`` for a scenario without one.
    ``frame`` maps world points to the scene's frame (``frame.points_in(p)``); ``recipe``:
    the run's dataset recipe (a mapping or None)."""
    entry = SCENE_BUILDERS.get(world_scenario(world))
    if entry is None:
        return {}
    module, fn = entry.split(":")
    return getattr(importlib.import_module(module), fn)(world, obs, est, frame, recipe)


def world_class(name: str) -> type:
    """The class of the world ``name`` (its module imported now)."""
    if name not in WORLDS:
        raise SpecError("scenario", f"unknown scenario {name!r}; valid: {', '.join(WORLDS)}")
    module, cls = WORLDS[name].split(":")
    return getattr(importlib.import_module(module), cls)


def make_world(name: str, **options):
    """The world ``name`` with ``options`` (the fields of its options dataclass).

    Unknown names and options raise :class:`~epo_casadi.errors.SpecError` naming them and
    the valid ones."""
    return world_class(name)(**options)


def world_scenario(world) -> str | None:
    """The dataset scenario (manifest ``scenario``) ``world`` plays: its
    ``dataset_scenario``; for a world that declares none, that of the registered world of
    its ``name`` (``"crossing"``: ``"rpi"``), else its ``name``; None when it names
    nothing."""
    from solvers.control.types import world_member

    v = world_member(world, "dataset_scenario")
    if isinstance(v, str):
        return v
    name = world_member(world, "name")
    if not isinstance(name, str):
        return None
    if name in WORLDS:
        v = world_member(world_class(name), "dataset_scenario")
    return v if isinstance(v, str) else name


def dataset_frame(scenario: str, stated) -> str:
    """The frame of a dataset's samples: ``stated`` (manifest ``meta.frame``) when it is
    one of :data:`FRAMES`, else the scenario's :data:`SCENARIO_FRAMES` entry, else
    ``stated`` as it is."""
    if stated in FRAMES:
        return stated
    return SCENARIO_FRAMES.get(scenario, stated)
