"""The closed loop's vocabulary: observations, estimates, plans, commands and the four roles.

Every planning period (``dt``, 0.1 s by default) the loop runs, in this order::

    obs = world.reset(seed)                        # or world.step(command)
    est = estimator.update(obs)                    # filtered states of the observed agents
    plan = planner.plan(obs, est)                  # the ego's reference trajectory
    command = tracker.control(obs.ego, plan, obs.t)  # what the ego's actuators get

Agent ``0`` is the ego (the SDV / robot): it knows its own state exactly. The other
agents ``1..N-1`` are observed as noisy positions (``NaN`` rows while they drop out).

State convention of every plan and estimate: the unicycle state ``(x, y, v, theta)`` of
:mod:`epo_casadi.dynamics` (positions in metres in the world frame, speed in m/s,
heading in rad), whatever vehicle model the world simulates. Commands are in the
world's vehicle model (:class:`VehicleModel`): ``(a, omega)`` for a unicycle,
``(a, delta)`` (steering angle) for a bicycle.

No torch here (the network planner lives in :mod:`learning.planner` and implements
:class:`Planner`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = [
    "SENSOR_NOISE_STD",
    "AgentTask",
    "Observation",
    "Estimate",
    "Plan",
    "Command",
    "Estimator",
    "Planner",
    "Tracker",
    "World",
    "WorldBase",
    "world_member",
]


#: m, the default std of the simulated position sensors (``noise_std`` of the left turn and
#: the merge) and of the UKF's measurement model (``UKFOptions.meas_std``): one number, so
#: the filter's default matches the worlds' (the crossing's pedestrian sensor is finer)
SENSOR_NOISE_STD = 0.3


@dataclass(frozen=True)
class AgentTask:
    """What an agent is trying to do, as a game reads it.

    ``path``: ``(P, 2)`` reference polyline (lane centre line) in the world frame;
    ``speed``: desired speed on it (m/s, e.g. the lane's speed limit);
    ``goal``: ``(2,)`` end point; ``radius``: collision radius (m).
    The world gives the ego's task to every planner and the others' true tasks only to
    the oracle.
    """

    path: np.ndarray
    speed: float
    goal: np.ndarray
    radius: float


@dataclass(frozen=True)
class Observation:
    """What the ego perceives at time ``t``.

    ``ego``: ``(4,)`` exact ego state ``(x, y, v, theta)``;
    ``others``: ``(N-1, 2)`` measured positions of the other agents (``NaN`` rows while
    an agent is not observed).
    """

    t: float
    ego: np.ndarray
    others: np.ndarray


@dataclass(frozen=True)
class Estimate:
    """Filtered states of the other agents at the observation's time.

    ``states``: ``(N-1, 4)`` ``(x, y, v, theta)``; ``covariances``: ``(N-1, 4, 4)``;
    ``history``: ``(N-1, H+1, 4)`` filtered states of steps ``k-H .. k``, oldest first, the
    last row being ``states`` (what a network consumes; the datasets' ``history`` layout,
    ``H = 18`` in :mod:`scenarios.rpi`); ``valid``: ``(N-1, H+1)`` where the history is backed
    by measurements (not only prediction or the backward extrapolation before a track
    started). An agent not measured yet has ``NaN`` states and covariances.
    ``converged``: ``(N-1,)`` whether each track may be planned on as it is (the UKF: enough
    updates and a small position covariance, :class:`~solvers.control.estimate.UKFOptions`);
    ``None`` (an estimator that does not say) means every finite track has converged. The
    planners treat a track that has not converged conservatively (constant velocity, an
    inflated radius, no commitment of the passing order: :mod:`solvers.control.plan`).
    """

    states: np.ndarray
    covariances: np.ndarray
    history: np.ndarray
    valid: np.ndarray
    converged: np.ndarray | None = None


@dataclass(frozen=True)
class Plan:
    """The ego's reference from time ``t0``: states at ``t0 + dt * (k + 1)``.

    ``states``: ``(K, 4)`` unicycle states; ``controls``: ``(K, 2)`` unicycle controls
    ``(a, omega)`` that produce them from the state at ``t0``; ``predictions``:
    ``(M, N, K, 4)`` joint futures of all agents per mode (agent 0 = ego) or ``None``;
    ``probabilities``: ``(M,)`` or ``None``. ``ok`` is False when the planner failed
    (non-finite, solver failure); ``message`` says what happened; ``info`` holds extras
    (solver status, iterations, latency).
    """

    t0: float
    dt: float
    states: np.ndarray
    controls: np.ndarray
    predictions: np.ndarray | None = None
    probabilities: np.ndarray | None = None
    ok: bool = True
    message: str = "ok"
    info: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Command:
    """What the ego's actuators get: ``value`` ``(2,)`` in the world's vehicle model;
    ``fallback`` is True when a failure made the tracker brake instead; ``info`` holds
    extras (QP status, solve time)."""

    value: np.ndarray
    fallback: bool = False
    info: dict = field(default_factory=dict)


@runtime_checkable
class Estimator(Protocol):
    """Role of the closed loop that turns observations into filtered states of the others.

    ``reset(obs, dt)`` before an episode: starts one track per row of ``obs.others``
    (``dt``: the planning period in seconds, > 0) and returns the first :class:`Estimate`;
    ``update(obs)`` once per period afterwards, with the same number of rows (``NaN``
    rows while an agent is not observed). Both return an :class:`Estimate` of ``N - 1``
    agents in the unicycle state ``(x, y, v, theta)``. The built-in one is
    :class:`solvers.control.estimate.UKFEstimator`. Optional: ``use_map(road_map)``, called
    by the loop before ``reset`` with the world's ``road_map`` (or None): the lanes a new
    track's heading may start from.
    """

    def reset(self, obs: Observation, dt: float) -> Estimate: ...

    def update(self, obs: Observation) -> Estimate: ...


@runtime_checkable
class Planner(Protocol):
    """``reset(world)`` before an episode (an unusable world raises
    :class:`~epo_casadi.errors.SpecError`); ``plan(obs, est)`` once per period. ``plan``
    never raises: any failure, including a missing or malformed ``obs`` or ``est``, is a
    ``Plan(ok=False, message=...)`` (:func:`solvers.control.plan.failed_plan`)."""

    def reset(self, world: World) -> None: ...

    def plan(self, obs: Observation, est: Estimate) -> Plan: ...


@runtime_checkable
class Tracker(Protocol):
    """``reset(world)`` before an episode; ``control(ego, plan, t)`` once per period. Bad
    input (a failed or malformed plan, a non-finite ego state or time) gives a braking
    ``Command(fallback=True)`` and leaves the tracker's state unchanged; ``control`` before
    ``reset`` raises :class:`~epo_casadi.errors.SpecError`."""

    def reset(self, world: World) -> None: ...

    def control(self, ego: np.ndarray, plan: Plan, t: float) -> Command: ...


@runtime_checkable
class World(Protocol):
    """A simulated scene: every member the closed loop and its planners read.

    Required: ``dt`` (the planning period, s); ``vehicle``, the ego's model
    (:class:`solvers.control.vehicle.VehicleModel`); ``ego_task``, the ego's
    :class:`AgentTask`; ``n_agents``; ``radii`` ``(N,)``; the methods below.

    Optional, with the defaults of :class:`WorldBase` (a world may inherit them; the loop
    and the planners read them with :func:`world_member`, so a world that leaves them out
    gets the same defaults): ``name`` (the registry name, e.g. ``"left-turn"``),
    ``dataset_scenario`` (the dataset scenario whose scenes it plays, manifest
    ``scenario``), ``max_steps``, ``road_map`` (a :class:`scenarios.maps.RoadMap`, for
    figures and the estimator's lane prior), ``footprint`` (``(length, width)`` in m of
    every agent, all the same, e.g. the cars of the highway-env worlds; None: each agent is
    the circle of its ``radii`` entry), ``horizon`` / ``history`` (the steps a trained
    planner must predict / read, where the world states them), ``scene_field_names`` (the fields of a dataset scene built
    from its map, by :func:`scenarios.sim.scene_fields`) and :meth:`conflict_zone`.
    """

    dt: float
    vehicle: Any
    ego_task: AgentTask
    n_agents: int
    radii: np.ndarray
    name: str | None
    dataset_scenario: str | None
    max_steps: int
    road_map: Any
    footprint: tuple[float, float] | None
    horizon: int | None
    history: int | None
    scene_field_names: tuple[str, ...]

    def reset(self, seed: int) -> Observation: ...

    def step(self, command: np.ndarray) -> Observation: ...

    def truth(self) -> np.ndarray:
        """``(N, 4)`` true unicycle states of every agent (metrics, tests)."""
        ...

    def tasks(self) -> list[AgentTask]:
        """True tasks of every agent (the oracle's privilege)."""
        ...

    def outcome(self) -> str:
        """``"running"``, ``"success"``, ``"collision"``, ``"timeout"`` or ``"off_road"``."""
        ...

    def conflict_zone(self) -> tuple[float, float] | None:
        """The ego's arc-length interval ``(s_in, s_out)`` (m along ``ego_task.path``) of
        the zone it shares with the others (the metric ``time_to_clear``), or None."""
        ...


class WorldBase:
    """The defaults of :class:`World`'s optional members (see there)."""

    name: str | None = None
    dataset_scenario: str | None = None
    max_steps: int = 10**6
    road_map: Any = None
    footprint: tuple[float, float] | None = None
    horizon: int | None = None
    history: int | None = None
    scene_field_names: tuple[str, ...] = ()

    def conflict_zone(self) -> tuple[float, float] | None:
        return None


#: the optional members of World (their defaults are WorldBase's)
OPTIONAL_MEMBERS = (
    "name",
    "dataset_scenario",
    "max_steps",
    "road_map",
    "footprint",
    "horizon",
    "history",
    "scene_field_names",
    "conflict_zone",
)


def world_member(world: Any, name: str) -> Any:
    """``world.<name>`` for an optional :class:`World` member, or :class:`WorldBase`'s
    default (a method bound to ``world``) when the world leaves it out."""
    if name not in OPTIONAL_MEMBERS:
        raise KeyError(f"{name!r} is not an optional World member; read world.{name}")
    try:
        return getattr(world, name)
    except AttributeError:
        default = getattr(WorldBase, name)
        return default.__get__(world) if callable(default) else default
