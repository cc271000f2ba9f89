"""The closed loop's roles by name: one table each for planners, trackers and estimators.

A :class:`Roles` table maps a name to a factory ``factory(config) -> role`` that builds a
fresh object from a :class:`~scenarios.closed_loop.config.SimConfig` (its
``planner_options``, ``tracker_options``, ``estimator_options``, ``scenario`` and
``model``). An entry may also be a ``"package.module:function"`` string: the module is
imported the first time the name is built, so this package imports neither the trained
planners' torch stack nor anything else it does not run. The built-ins::

    planners    model, sc (learning.planner: a trained run in ``config.model``),
                oracle, cv (solvers.control.plan)
    trackers    pid, mpc (solvers.control.track)
    estimators  ukf (solvers.control.estimate)
    filters     qp (solvers.control.safety: the safety filter between tracker and world)

A user's own planner is one registration, ``register_planner("mine", factory)`` (a name
already in the table is refused); ``epo simulate --planner`` offers the table's names. Episodes run in worker processes build their stack there, so a factory used with
``workers > 1`` must be registered by a module the worker imports (or be given as a
``"module:function"`` string).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from epo_casadi.errors import SpecError, short_repr
from epo_casadi.registry import NAME_RE, load_class

__all__ = [
    "Role",
    "Roles",
    "PLANNERS",
    "TRACKERS",
    "ESTIMATORS",
    "FILTERS",
    "register_planner",
    "register_tracker",
    "register_estimator",
    "register_filter",
]


@dataclass
class Role:
    """One table entry: ``factory`` (a callable, or ``"module:function"`` until first
    built), ``needs_model`` (the role loads a trained run named by ``config.model``)."""

    factory: Callable[[Any], Any] | str
    needs_model: bool = False


class Roles:
    """Name -> :class:`Role` of one kind (``what``: ``"planner"``, ``"tracker"``, ...)."""

    def __init__(self, what: str, entries: Iterable[tuple[str, Role]] = ()):
        self.what = what
        self.table: dict[str, Role] = dict(entries)

    def names(self) -> list[str]:
        """The registered names, in registration order."""
        return list(self.table)

    def __contains__(self, name: object) -> bool:
        return name in self.table

    def needing_model(self) -> list[str]:
        """The names whose role loads a trained run."""
        return [n for n, r in self.table.items() if r.needs_model]

    def register(self, name: str, factory: Callable | str, *, needs_model: bool = False) -> None:
        """Add ``name``; a name already registered is refused (:class:`SpecError`)."""
        where = f"register_{self.what}"
        if not isinstance(name, str) or not NAME_RE.match(name.replace("-", "_")):
            raise SpecError(f"{where}.name", f"expected a name, got {short_repr(name)}")
        if not (callable(factory) or isinstance(factory, str)):
            raise SpecError(
                f"{where}.factory", f"expected a callable or 'module:function', got {factory!r}"
            )
        if name in self.table:
            raise SpecError(
                f"{where}.name", f"{name!r} is already a registered {self.what}; pick another"
            )
        self.table[name] = Role(factory, bool(needs_model))

    def role(self, name: str) -> Role:
        """The entry of ``name``; an unknown name is a :class:`SpecError` listing the valid."""
        if name not in self.table:
            raise SpecError(self.what, f"expected one of {self.names()}, got {name!r}")
        return self.table[name]

    def factory(self, name: str) -> Callable[[Any], Any]:
        """The factory of ``name``, its module imported now if it was given as a string."""
        role = self.role(name)
        if isinstance(role.factory, str):
            role.factory = load_class(role.factory, self.what)
        return role.factory

    def build(self, name: str, config: Any) -> Any:
        """A fresh role object: ``factory(config)``."""
        return self.factory(name)(config)


# ---- the built-ins ------------------------------------------------------------------------
def _oracle(config):
    from solvers.control.plan import GameOracle

    return GameOracle(config.planner_options)


def _constant_velocity(config):
    from solvers.control.plan import ConstantVelocityPlanner

    return ConstantVelocityPlanner(config.planner_options)


def _pid(config):
    from solvers.control.track import PIDTracker

    return PIDTracker(**config.tracker_options)


def _mpc(config):
    from solvers.control.track import MPCTracker

    return MPCTracker(**config.tracker_options)


def _ukf(config):
    from solvers.control.estimate import UKFEstimator

    return UKFEstimator(**config.estimator_options)


def _qp_filter(config):
    from solvers.control.safety import SafetyFilter

    return SafetyFilter(**config.filter_options)


#: planners: ``model`` (ours) and ``sc`` are trained runs, built by :mod:`learning.planner`
PLANNERS = Roles(
    "planner",
    [
        ("model", Role("learning.planner:model_planner", needs_model=True)),
        ("oracle", Role(_oracle)),
        ("cv", Role(_constant_velocity)),
        ("sc", Role("learning.planner:sc_planner", needs_model=True)),
    ],
)
#: trackers of the ego's plan
TRACKERS = Roles("tracker", [("pid", Role(_pid)), ("mpc", Role(_mpc))])
#: estimators of the other agents' states
ESTIMATORS = Roles("estimator", [("ukf", Role(_ukf))])
#: safety filters between the tracker and the world: ``filter(obs, est, plan, command)``
FILTERS = Roles("filter", [("qp", Role(_qp_filter))])


def register_planner(name: str, factory: Callable | str, *, needs_model: bool = False) -> None:
    """Register a planner: ``factory(config) -> Planner``; ``needs_model``: it loads the
    trained run ``config.model`` (which the configuration then requires)."""
    PLANNERS.register(name, factory, needs_model=needs_model)


def register_tracker(name: str, factory: Callable | str) -> None:
    """Register a tracker: ``factory(config) -> Tracker``."""
    TRACKERS.register(name, factory)


def register_estimator(name: str, factory: Callable | str) -> None:
    """Register an estimator: ``factory(config) -> Estimator``."""
    ESTIMATORS.register(name, factory)


def register_filter(name: str, factory: Callable | str) -> None:
    """Register a safety filter: ``factory(config)`` returns an object with ``reset(world)``
    and ``filter(obs, est, plan, command) -> Command`` (``plan`` None when the plan was not
    usable), as :class:`solvers.control.safety.SafetyFilter`."""
    FILTERS.register(name, factory)
