"""The closed loop: world, estimator, planner, tracker; episodes, metrics, parallel runs.

One episode (:func:`run_episode`, :mod:`~scenarios.closed_loop.loop`) is the loop of
:mod:`solvers.control.types`::

    obs = world.reset(seed)
    est = estimator.reset(obs, world.dt)
    while world.outcome() == "running":
        plan = planner.plan(obs, est)
        command = tracker.control(obs.ego, plan, obs.t) if usable(plan) else brake(obs.ego)
        command = safety.filter(obs, est, plan, command)   # the safety filter, if any
        obs = world.step(command.value)
        est = estimator.update(obs)

A plan that is not ``ok`` or not finite, or a planner or tracker that raises, never ends
the episode: the ego brakes (:func:`brake`: the strongest deceleration of the vehicle
model down to standstill, steering straight) and the event is logged. Every step records
the truth, the observation, the estimate, the plan (ego states and the predicted joint
modes with their probabilities), the command and the latencies of estimation, planning
and tracking (:class:`EpisodeLog`, :mod:`~scenarios.closed_loop.log`).

The package, by concern:

``roles``    the tables of planners, trackers, estimators and safety filters by name
             (:data:`PLANNERS`, :func:`register_planner`, ..., :data:`FILTERS`)
``config``   :class:`SimConfig`: scenario, roles and options; builds a fresh stack
``log``      :class:`EpisodeLog`, :class:`EpisodeResult`, :func:`usable`
``loop``     :func:`run_episode`, :func:`brake`
``metrics``  :func:`episode_metrics` (what each metric means is documented there)
``runner``   :func:`run_episodes`: parallel, written as they finish, resumable
``report``   :func:`summarize`, :func:`write_summary`, :func:`error_note`

Parallel runs (:func:`run_episodes`)
    Episode ``i`` uses seed ``seed + i`` and a stack built fresh from the configuration,
    so its result does not depend on the engine, the workers or the order. Episodes run on
    the engines of data generation (:mod:`scenarios.dataset`: a local process pool or
    Dask), at most :data:`MAX_EPISODES` per run (every episode's result is held for the
    summary). Results go to ``DIR/episodes/episode-NNNNN.json`` (written atomically,
    :func:`scenarios.files.write_atomic`; an unwritable folder or a full disk is one
    :class:`~epo_casadi.errors.OutputError`); one run writes into a folder at a time
    (:func:`scenarios.files.output_lock`). ``DIR/config.json`` records the configuration,
    the seed and, for a trained planner, what identifies its model (the checkpoint file,
    its SHA-256, epoch and step: ``config.model_checkpoint``); a run started again with the
    same record keeps every finished episode and runs the rest (and again the episodes that
    ended in ``"error"``), one with another record is refused naming the fields that
    differ, so episodes of two models (a run trained further in between) never mix. Within
    a run every worker checks that it loads the same checkpoint. ``DIR/summary.md`` and
    ``DIR/summary.csv`` hold the table over the episodes (``summary.md`` also says how many
    episodes ended in an error, and the first error), ``DIR/episodes.csv`` one row per
    episode.

The names below are imported from their modules on first use, so ``import
scenarios.closed_loop.roles`` (what ``epo simulate`` reads its choices from) does not load
the loop's numeric stack.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

#: public name -> the module of this package that defines it
_WHERE = {
    "EpisodeConfig": "config",
    "SimConfig": "config",
    "OUTCOMES": "log",
    "EpisodeLog": "log",
    "EpisodeResult": "log",
    "usable": "log",
    "brake": "loop",
    "run_episode": "loop",
    "episode_metrics": "metrics",
    "SUMMARY_COLUMNS": "report",
    "error_note": "report",
    "summarize": "report",
    "summary_markdown": "report",
    "write_summary": "report",
    "ESTIMATORS": "roles",
    "FILTERS": "roles",
    "PLANNERS": "roles",
    "TRACKERS": "roles",
    "register_estimator": "roles",
    "register_filter": "roles",
    "register_planner": "roles",
    "register_tracker": "roles",
    "MAX_EPISODES": "runner",
    "MAX_WORKERS": "runner",
    "RunReport": "runner",
    "load_log": "runner",
    "load_results": "runner",
    "run_episodes": "runner",
}

__all__ = [
    "EpisodeConfig",
    "SimConfig",
    "OUTCOMES",
    "EpisodeLog",
    "EpisodeResult",
    "usable",
    "brake",
    "run_episode",
    "episode_metrics",
    "SUMMARY_COLUMNS",
    "error_note",
    "summarize",
    "summary_markdown",
    "write_summary",
    "ESTIMATORS",
    "FILTERS",
    "PLANNERS",
    "TRACKERS",
    "register_estimator",
    "register_filter",
    "register_planner",
    "register_tracker",
    "MAX_EPISODES",
    "MAX_WORKERS",
    "RunReport",
    "load_log",
    "load_results",
    "run_episodes",
]  # the keys of _WHERE

if TYPE_CHECKING:  # the same names, for type checkers and documentation tools
    from .config import EpisodeConfig, SimConfig
    from .log import OUTCOMES, EpisodeLog, EpisodeResult, usable
    from .loop import brake, run_episode
    from .metrics import episode_metrics
    from .report import SUMMARY_COLUMNS, error_note, summarize, summary_markdown, write_summary
    from .roles import (
        ESTIMATORS,
        FILTERS,
        PLANNERS,
        TRACKERS,
        register_estimator,
        register_filter,
        register_planner,
        register_tracker,
    )
    from .runner import (
        MAX_EPISODES,
        MAX_WORKERS,
        RunReport,
        load_log,
        load_results,
        run_episodes,
    )


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_WHERE])
