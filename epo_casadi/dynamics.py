"""Per-agent discrete-time dynamics ``x_next = f(x, u, dt)``.

The built-in models below integrate with explicit Euler; a user's model (a subclass of
:class:`Dynamics` in its own module, see :mod:`epo_casadi.registry` and
``docs/extending.md``) may integrate as it likes, e.g. RK4 substeps inside ``step``.

Every model exposes its step as a named :class:`casadi.Function`
``f(x, u, dt) -> x_next`` plus the semantic quantities the energy features read
(position, speed, longitudinal acceleration, turn rate), so that a feature such
as "velocity" means the same thing for a unicycle and a double integrator.

State and control layouts (index order inside one agent's vector):

=====================  ==========================  ===========================
model                  state ``x``                 control ``u``
=====================  ==========================  ===========================
``unicycle``           ``(x, y, v, theta)``        ``(a, omega)``
``double_integrator``  ``(x, y, vx, vy)``          ``(ax, ay)``
``bicycle``            ``(x, y, v, theta)``        ``(a, delta)`` (steer angle)
=====================  ==========================  ===========================

The unicycle is the dynamically extended unicycle of the paper (App. F.2,
its unicycle equation); the kinematic bicycle uses the rear-axle reference point with
wheelbase ``L``: ``theta' = v tan(delta) / L``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import casadi as ca

from .errors import SpecError
from .registry import DYNAMICS

__all__ = [
    "Dynamics",
    "JointDynamics",
    "Unicycle",
    "DoubleIntegrator",
    "KinematicBicycle",
    "make_dynamics",
]


@dataclass(frozen=True)
class Dynamics:
    """Base class: subclasses define ``state_names``, ``control_names`` and ``step``."""

    name = "dynamics"
    state_names: tuple[str, ...] = ()
    control_names: tuple[str, ...] = ()

    @property
    def nx(self) -> int:
        return len(self.state_names)

    @property
    def nu(self) -> int:
        return len(self.control_names)

    # --- symbolic model -------------------------------------------------------------
    def step(self, x, u, dt):  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def f(self) -> ca.Function:
        """``f(x, u, dt) -> x_next`` as a named CasADi function."""
        x = ca.SX.sym("x", self.nx)
        u = ca.SX.sym("u", self.nu)
        dt = ca.SX.sym("dt")
        return ca.Function(
            f"f_{self.name}", [x, u, dt], [self.step(x, u, dt)], ["x", "u", "dt"], ["x_next"]
        )

    # --- semantic quantities used by features ------------------------------------------
    def position(self, x):
        return x[0:2]

    def velocity(self, x):
        """Velocity residual: speed for heading models, ``(vx, vy)`` for integrators."""
        raise NotImplementedError

    def speed(self, x):
        raise NotImplementedError

    def acceleration(self, u):
        """Acceleration residual: longitudinal ``a`` or ``(ax, ay)``."""
        raise NotImplementedError

    def turn_rate(self, x, u):
        raise SpecError(
            "features", f"dynamics '{self.name}' has no heading, so turn-rate features do not apply"
        )

    def to_dict(self) -> dict:
        """``{"type": <registered name or module:Class>, <option>: value, ...}``."""
        d = {"type": DYNAMICS.type_name(type(self))}
        for f in fields(self):
            if f.init and f.name not in DYNAMICS.fixed:
                v = getattr(self, f.name)
                d[f.name] = _plain(v)
        return d


def _plain(v):
    """Tuples as lists, recursively (YAML and JSON writers take lists)."""
    return [_plain(x) for x in v] if isinstance(v, (tuple, list)) else v


@dataclass(frozen=True)
class Unicycle(Dynamics):
    """Dynamically extended unicycle (``"unicycle"``), explicit Euler.

    State ``(x, y, v, theta)``: position (m), speed along the heading (m/s), heading
    (rad); control ``(a, omega)``: longitudinal acceleration (m/s^2), turn rate (rad/s)::

        x' = x + v cos(theta) dt    y' = y + v sin(theta) dt
        v' = v + a dt               theta' = theta + omega dt

    The paper's dynamics (App. F.2, its unicycle equation). Features read velocity and
    speed ``v``, acceleration ``a`` and turn rate ``omega``. No options.
    """

    name = "unicycle"
    state_names: tuple[str, ...] = ("x", "y", "v", "theta")
    control_names: tuple[str, ...] = ("a", "omega")

    def step(self, x, u, dt):
        v, th = x[2], x[3]
        return ca.vertcat(
            x[0] + v * ca.cos(th) * dt, x[1] + v * ca.sin(th) * dt, v + u[0] * dt, th + u[1] * dt
        )

    def velocity(self, x):
        return x[2]

    def speed(self, x):
        return x[2]

    def acceleration(self, u):
        return u[0]

    def turn_rate(self, x, u):
        return u[1]


@dataclass(frozen=True)
class DoubleIntegrator(Dynamics):
    """Point mass in the plane (``"double_integrator"``), explicit Euler.

    State ``(x, y, vx, vy)``: position (m), velocity (m/s); control ``(ax, ay)``:
    acceleration (m/s^2)::

        x' = x + vx dt    y' = y + vy dt    vx' = vx + ax dt    vy' = vy + ay dt

    Features read the velocity as the two rows ``(vx, vy)``, the speed as
    ``sqrt(vx^2 + vy^2 + 1e-12)`` and the acceleration as ``(ax, ay)``; it has no heading,
    so turn-rate features are refused for it. No options.
    """

    name = "double_integrator"
    state_names: tuple[str, ...] = ("x", "y", "vx", "vy")
    control_names: tuple[str, ...] = ("ax", "ay")

    def step(self, x, u, dt):
        return ca.vertcat(x[0] + x[2] * dt, x[1] + x[3] * dt, x[2] + u[0] * dt, x[3] + u[1] * dt)

    def velocity(self, x):
        return x[2:4]

    def speed(self, x):
        return ca.sqrt(x[2] ** 2 + x[3] ** 2 + 1e-12)

    def acceleration(self, u):
        return u[0:2]


@dataclass(frozen=True)
class KinematicBicycle(Dynamics):
    """Kinematic bicycle about the rear axle (``"bicycle"``), explicit Euler.

    State ``(x, y, v, theta)``: rear-axle position (m), speed (m/s), heading (rad);
    control ``(a, delta)``: longitudinal acceleration (m/s^2), steering angle (rad)::

        x' = x + v cos(theta) dt    y' = y + v sin(theta) dt
        v' = v + a dt               theta' = theta + v tan(delta) / L dt

    ``wheelbase`` ``L`` (m, > 0; default 2.7). Features read velocity and speed ``v``,
    acceleration ``a`` and the turn rate ``v tan(delta) / L``.
    """

    name = "bicycle"
    state_names: tuple[str, ...] = ("x", "y", "v", "theta")
    control_names: tuple[str, ...] = ("a", "delta")
    wheelbase: float = 2.7

    def __post_init__(self):
        if not self.wheelbase > 0:
            raise SpecError(
                "wheelbase", f"must be a positive length in metres, got {self.wheelbase}"
            )

    def step(self, x, u, dt):
        v, th = x[2], x[3]
        return ca.vertcat(
            x[0] + v * ca.cos(th) * dt,
            x[1] + v * ca.sin(th) * dt,
            v + u[0] * dt,
            th + v * ca.tan(u[1]) / self.wheelbase * dt,
        )

    def velocity(self, x):
        return x[2]

    def speed(self, x):
        return x[2]

    def acceleration(self, u):
        return u[0]

    def turn_rate(self, x, u):
        return x[2] * ca.tan(u[1]) / self.wheelbase


DYNAMICS.bind(Dynamics, (Unicycle, DoubleIntegrator, KinematicBicycle))


@dataclass(frozen=True)
class JointDynamics:
    """Base of coupled dynamics: one model over several agents' states and controls.

    A subclass sets ``name`` and defines ``step(xs, us, dt) -> next states``: ``xs`` and
    ``us`` are lists of the member agents' state and control columns (in the order of
    :attr:`epo_casadi.game.Coupling.agents`), the result one next-state column per member
    (same sizes). Each member keeps its own :class:`Dynamics` for its sizes, state names
    and the semantic quantities features read (position, speed, ...); its own ``step`` is
    not used. Examples: a tow truck and its trailer, agents sharing a state, the linear
    ``x_{k+1} = A x_k + sum_i B_i u_{i,k}`` of textbook LQ games.
    """

    name = "joint"

    def step(self, xs, us, dt):  # pragma: no cover - abstract
        raise NotImplementedError


def make_dynamics(spec: str | dict | Dynamics) -> Dynamics:
    """Dynamics from a name (``"unicycle"``), a mapping (``{"type": "bicycle", "wheelbase": 3}``,
    ``{"type": "my_pkg.models:Boat"}``) or an instance of any :class:`Dynamics` subclass
    (see :mod:`epo_casadi.registry`)."""
    return DYNAMICS.construct(spec, "dynamics")
