"""What one closed-loop run is: :class:`SimConfig` (scenario, planner, tracker, estimator
and their options), which builds a fresh stack from the role tables
(:mod:`scenarios.closed_loop.roles`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

from epo_casadi.errors import SpecError, check_bool, short_repr

from .roles import ESTIMATORS, FILTERS, PLANNERS, TRACKERS

__all__ = ["EpisodeConfig", "SimConfig"]


class EpisodeConfig(Protocol):
    """What :func:`~scenarios.closed_loop.run_episodes` needs: a picklable description
    that builds a fresh stack."""

    def to_dict(self) -> dict: ...

    def build(self) -> tuple[Any, Any, Any, Any]:
        """``(world, estimator, planner, tracker)``, new objects."""
        ...

    # optional: ``build_filter() -> filter or None``, the safety filter between the tracker
    # and the world (:meth:`SimConfig.build_filter`); a configuration without it runs none


@dataclass(frozen=True)
class SimConfig:
    """One closed-loop configuration: scenario and its options, planner, tracker, estimator.

    ``planner``, ``tracker`` and ``estimator`` are names of the role tables
    (:data:`~scenarios.closed_loop.roles.PLANNERS`: ``"oracle"`` / ``"cv"``,
    :mod:`solvers.control.plan`, options :class:`~solvers.control.plan.PlannerOptions`;
    ``"model"`` / ``"sc"``, a trained run in ``model`` loaded by
    ``learning.planner.load_planner``; :data:`~scenarios.closed_loop.roles.TRACKERS`:
    ``"pid"`` / ``"mpc"``, :mod:`solvers.control.track`;
    :data:`~scenarios.closed_loop.roles.ESTIMATORS`: ``"ukf"``); ``world_options`` go to
    ``scenarios.sim.make_world(scenario, **world_options)``. ``model_checkpoint``: what
    identifies the trained model (``NetworkPlanner.identity``: checkpoint file, SHA-256,
    epoch, step); when set, :meth:`build` refuses a run directory whose checkpoint is
    another (:func:`~scenarios.closed_loop.run_episodes` sets it from the first build:
    :meth:`pinned`). :meth:`to_dict` records ``estimator`` only when it is not
    ``"ukf"``, so every record of a UKF run reads the same.

    ``safety_filter`` (on by default, for every planner and tracker): the safety filter
    ``filter`` (a name of :data:`~scenarios.closed_loop.roles.FILTERS`, ``"qp"``:
    :class:`solvers.control.safety.SafetyFilter`, options ``filter_options``) stands
    between the tracker and the world (:meth:`build_filter`); ``False`` runs without it
    (for studies). :meth:`to_dict` always records ``safety_filter`` and, with the filter
    on, its options (and its name when it is not ``"qp"``).
    """

    scenario: str
    planner: str = "oracle"
    tracker: str = "mpc"
    model: str | None = None
    world_options: dict = field(default_factory=dict)
    planner_options: dict = field(default_factory=dict)
    tracker_options: dict = field(default_factory=dict)
    estimator_options: dict = field(default_factory=dict)
    model_checkpoint: dict | None = None
    estimator: str = "ukf"
    safety_filter: bool = True
    filter: str = "qp"
    filter_options: dict = field(default_factory=dict)

    def __post_init__(self):
        role = PLANNERS.role(self.planner)
        TRACKERS.role(self.tracker)
        ESTIMATORS.role(self.estimator)
        FILTERS.role(self.filter)
        check_bool("safety_filter", self.safety_filter)
        if not self.safety_filter and self.filter_options:
            raise SpecError(
                "filter_options",
                "the safety filter is off (safety_filter false): its options would do nothing",
            )
        if role.needs_model and not self.model:
            raise SpecError("model", f"planner {self.planner!r} needs a trained run directory")
        if self.model is not None and not role.needs_model:
            users = " and ".join(repr(n) for n in PLANNERS.needing_model())
            raise SpecError(
                "model", f"a model is only used by the planners {users}, not {self.planner!r}"
            )
        for name in (
            "world_options",
            "planner_options",
            "tracker_options",
            "estimator_options",
            "filter_options",
        ):
            if not isinstance(getattr(self, name), dict):
                raise SpecError(name, f"expected a mapping, got {getattr(self, name)!r}")

    def to_dict(self) -> dict:
        return (
            {
                "scenario": self.scenario,
                "planner": self.planner,
                "tracker": self.tracker,
                "model": self.model,
                "world_options": dict(self.world_options),
                "planner_options": dict(self.planner_options),
                "tracker_options": dict(self.tracker_options),
                "estimator_options": dict(self.estimator_options),
            }
            | ({"estimator": self.estimator} if self.estimator != "ukf" else {})
            | {"safety_filter": self.safety_filter}
            | ({"filter": self.filter} if self.safety_filter and self.filter != "qp" else {})
            | ({"filter_options": dict(self.filter_options)} if self.safety_filter else {})
            | ({"model_checkpoint": dict(self.model_checkpoint)} if self.model_checkpoint else {})
        )

    def pinned(self, planner) -> SimConfig:
        """This configuration with ``model_checkpoint`` set from a built network planner's
        ``identity`` (unchanged for the other planners or when already set)."""
        ident = getattr(planner, "identity", None)
        if self.model_checkpoint is not None or not isinstance(ident, dict):
            return self
        return replace(self, model_checkpoint=dict(ident))

    @property
    def label(self) -> str:
        return f"{self.scenario} {self.planner}+{self.tracker}" + (
            "+filter" if self.safety_filter else ""
        )

    def build_filter(self):
        """A fresh safety filter from :data:`~scenarios.closed_loop.roles.FILTERS`, or None
        with ``safety_filter=False``."""
        return FILTERS.build(self.filter, self) if self.safety_filter else None

    def build(self):
        """``(world, estimator, planner, tracker)``, new objects from the role tables."""
        from scenarios.sim import make_world

        world = make_world(self.scenario, **self.world_options)
        estimator = ESTIMATORS.build(self.estimator, self)
        tracker = TRACKERS.build(self.tracker, self)
        if PLANNERS.role(self.planner).needs_model:
            if not Path(self.model).is_dir():
                raise SpecError("model", f"no trained run directory at {self.model!r}")
            planner = PLANNERS.build(self.planner, self)
            _check_identity(self.model, self.model_checkpoint, getattr(planner, "identity", None))
        else:
            planner = PLANNERS.build(self.planner, self)
        return world, estimator, planner, tracker


def _check_identity(model: str, want: dict | None, got: dict | None) -> None:
    """Refuse a loaded model that is not the one the run recorded (``model_checkpoint``)."""
    if want is None or got is None:
        return
    for k in ("checkpoint", "sha256", "epoch", "step"):
        if want.get(k) != got.get(k):
            raise SpecError(
                f"model_checkpoint.{k}",
                f"the run recorded {short_repr(want.get(k))}, the model at {model} now has "
                f"{short_repr(got.get(k))}: its checkpoint changed (trained further?); "
                "simulate it into another --out",
            )
