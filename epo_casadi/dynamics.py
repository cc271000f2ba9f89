"""Per-agent discrete-time dynamics ``x_next = f(x, u, dt)`` (explicit Euler).

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
Eq. (8)); the kinematic bicycle uses the rear-axle reference point with
wheelbase ``L``: ``theta' = v tan(delta) / L``.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca

from .errors import SpecError

__all__ = ["Dynamics", "Unicycle", "DoubleIntegrator", "KinematicBicycle", "make_dynamics"]


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
        return {"type": self.name}


@dataclass(frozen=True)
class Unicycle(Dynamics):
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

    def to_dict(self) -> dict:
        return {"type": self.name, "wheelbase": self.wheelbase}


_MODELS = {"unicycle": Unicycle, "double_integrator": DoubleIntegrator, "bicycle": KinematicBicycle}


def make_dynamics(spec: str | dict | Dynamics) -> Dynamics:
    """Dynamics from a name (``"unicycle"``), a dict (``{"type": "bicycle", "wheelbase": 3}``) or itself."""
    if isinstance(spec, Dynamics):
        return spec
    if isinstance(spec, str):
        spec = {"type": spec}
    if not isinstance(spec, dict) or "type" not in spec:
        raise SpecError("dynamics", f"expected a model name or a mapping with 'type', got {spec!r}")
    kind = spec["type"]
    if kind not in _MODELS:
        raise SpecError("dynamics.type", f"expected one of {sorted(_MODELS)}, got {kind!r}")
    extra = {k: v for k, v in spec.items() if k != "type"}
    allowed = {"wheelbase"} if kind == "bicycle" else set()
    unknown = set(extra) - allowed
    if unknown:
        raise SpecError("dynamics", f"unknown option(s) {sorted(unknown)} for '{kind}'")
    return _MODELS[kind](**extra)
