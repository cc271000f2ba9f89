"""The ego's vehicle model: one discrete step, its limits, and its exact Jacobians.

Two kinds, both on the state ``(x, y, v, theta)`` of :mod:`solvers.control.types`:

``"unicycle"``: command ``(a, omega)``; the explicit Euler step of
:class:`epo_casadi.dynamics.Unicycle`::

    x+ = x + v cos(theta) dt,  y+ = y + v sin(theta) dt,  v+ = v + a dt,  theta+ = theta + omega dt

``"bicycle"``: command ``(a, delta)`` (front steering angle); the kinematic bicycle that
highway-env 1.12.1 integrates in ``highway_env.vehicle.kinematics.Vehicle.step``, with the
centre of gravity half-way between the axles (``length / 2`` from each) and the slip angle
``beta = arctan(tan(delta) / 2)``::

    x+ = x + v cos(theta + beta) dt,  y+ = y + v sin(theta + beta) dt,
    theta+ = theta + v sin(beta) / (length / 2) dt,  v+ = v + a' dt

where ``a'`` is highway-env's speed clip: ``min(a, v_max - v)`` while ``v > v_max``,
``max(a, v_min - v)`` while ``v < v_min`` (the clipped value is kept for the remaining
sub-steps, as highway-env keeps it in the vehicle's action); highway-env does not clip the
steering angle inside ``Vehicle.step`` (its action space maps ``[-1, 1]`` onto
``[-pi/4, pi/4]``). ``substeps`` Euler steps of ``dt / substeps`` make one step of ``dt``
(highway-env's ``simulation_frequency / policy_frequency``).

No reversing (``no_reverse=True``, the default of :meth:`VehicleModel.highway`, which every
world's car uses): a car stops, it does not drive backwards. Before each sub-step of
``h = dt / substeps`` an acceleration that would take the speed below zero is raised to the
one that stops the car within the sub-step, ``a' = -v / h`` where ``v + a h < 0`` (applied
after highway-env's clip), so ``v >= 0`` after every step (a negative speed is brought to
zero in one step). The worlds apply the same rule to their ego
vehicle. In the step this is ``v+ = 0 where v + a h < 0, else v + a h`` (the positions
use the speed at the start of the sub-step, as before), so the speed is exactly zero, never
a rounding below it. Written with a strict ``<``, the derivative at a standing car with
``a = 0`` is that of the free model (``d v+ / d a = h``): a linearization at standstill
can still start the car. ``no_reverse=False`` is the plain model (highway-env's ``Vehicle`` with its
``MIN_SPEED`` of -40 m/s, a unicycle robot that may reverse).

The limits (``a_min``, ``a_max``, ``steer_max``, ``jerk_max``, ``steer_rate_max``) are what
the trackers respect; the step itself applies only the speed clip and the no-reversing
rule, as the world does.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from types import SimpleNamespace

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError, check_number

__all__ = ["VehicleModel", "KINDS"]

KINDS = ("unicycle", "bicycle")


#: the operations of :meth:`VehicleModel._integrate` on numpy arrays and CasADi expressions
_NUMPY = SimpleNamespace(
    where=np.where, fmin=np.minimum, fmax=np.maximum, cos=np.cos, sin=np.sin, tan=np.tan,
    atan=np.arctan,
)  # fmt: skip
_CASADI = SimpleNamespace(
    where=ca.if_else, fmin=ca.fmin, fmax=ca.fmax, cos=ca.cos, sin=ca.sin, tan=ca.tan,
    atan=ca.atan,
)  # fmt: skip


@dataclass(frozen=True)
class VehicleModel:
    """The ego's discrete dynamics and actuator limits (see the module docstring)."""

    kind: str = "unicycle"  #: "unicycle" (command a, omega) or "bicycle" (command a, delta)
    length: float = 5.0  #: bicycle: vehicle length (m), axles at +-length/2 from the CG
    a_min: float = -5.0  #: lowest acceleration command (m/s^2)
    a_max: float = 5.0  #: highest acceleration command (m/s^2)
    steer_max: float = math.pi / 4  #: |delta| (rad, bicycle) or |omega| (rad/s, unicycle)
    jerk_max: float = 10.0  #: |rate of the acceleration command| (m/s^3)
    steer_rate_max: float = 1.0  #: |rate of delta| (rad/s) or of omega (rad/s^2)
    v_min: float = -math.inf  #: highway-env's MIN_SPEED clip (-inf: none)
    v_max: float = math.inf  #: highway-env's MAX_SPEED clip (inf: none)
    substeps: int = 1  #: Euler sub-steps per step
    no_reverse: bool = False  #: a car: the speed never goes below zero (module docstring)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise SpecError("vehicle.kind", f"expected one of {KINDS}, got {self.kind!r}")
        check_number("vehicle.length", self.length, lo=0, lo_open=True)
        check_number("vehicle.a_min", self.a_min, hi=0)
        check_number("vehicle.a_max", self.a_max, lo=0)
        check_number("vehicle.steer_max", self.steer_max, lo=0, lo_open=True)
        if self.kind == "bicycle" and not self.steer_max < math.pi / 2:
            raise SpecError(
                "vehicle.steer_max", f"expected a steering angle in (0, pi/2), got {self.steer_max}"
            )
        check_number("vehicle.jerk_max", self.jerk_max, lo=0, lo_open=True)
        check_number("vehicle.steer_rate_max", self.steer_rate_max, lo=0, lo_open=True)
        for name in ("v_min", "v_max"):
            val = getattr(self, name)
            if not isinstance(val, (int, float)) or isinstance(val, bool) or math.isnan(val):
                raise SpecError(f"vehicle.{name}", f"expected a number or +-inf, got {val!r}")
        if not self.v_min < self.v_max:
            raise SpecError("vehicle.v_max", f"expected v_max > v_min, got {self.v_max}")
        check_number("vehicle.substeps", self.substeps, lo=1, integer=True)
        if not isinstance(self.no_reverse, bool):
            raise SpecError(
                "vehicle.no_reverse", f"expected true or false, got {self.no_reverse!r}"
            )

    @classmethod
    def highway(cls, **overrides) -> VehicleModel:
        """The bicycle with highway-env 1.12.1's defaults: ``Vehicle.LENGTH = 5``,
        ``MIN/MAX_SPEED = -+40``, ``ContinuousAction`` ranges ``a in [-5, 5]``,
        ``delta in [-pi/4, pi/4]``; and a car that does not reverse (``no_reverse=True``:
        what the worlds' ego does; ``no_reverse=False`` is highway-env's ``Vehicle`` as it
        is, which reverses down to -40 m/s)."""
        base = dict(kind="bicycle", length=5.0, a_min=-5.0, a_max=5.0, steer_max=math.pi / 4)
        base.update(v_min=-40.0, v_max=40.0, no_reverse=True)
        base.update(overrides)
        return cls(**base)

    # ------------------------------------------------------------------ limits
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(u_min, u_max)``, each ``(2,)``: the command box."""
        return (
            np.array([self.a_min, -self.steer_max]),
            np.array([self.a_max, self.steer_max]),
        )

    def rate_bounds(self, dt: float) -> np.ndarray:
        """``(2,)`` largest change of each command between two steps of ``dt``."""
        return np.array([self.jerk_max, self.steer_rate_max]) * dt

    def clip(self, u: np.ndarray, u_prev: np.ndarray | None = None, dt: float = 0.0) -> np.ndarray:
        """``u`` projected onto the box, and onto ``u_prev +- rate_bounds(dt)`` if given."""
        lo, hi = self.bounds()
        if u_prev is not None:
            r = self.rate_bounds(dt)
            lo, hi = np.maximum(lo, u_prev - r), np.minimum(hi, u_prev + r)
        return np.minimum(np.maximum(u, lo), hi)

    # ------------------------------------------------------------------ the step, once
    def _integrate(self, px, py, v, th, a, s, dt: float, m):
        """``substeps`` explicit steps of ``dt / substeps`` with the speed clip and the
        no-reversing rule, written once for numpy arrays and CasADi expressions (``m``:
        :data:`_NUMPY` / :data:`_CASADI`)."""
        h = dt / self.substeps
        for _ in range(self.substeps):  # a fixed, small number of sub-steps (not samples)
            if math.isfinite(self.v_max):
                a = m.where(v > self.v_max, m.fmin(a, self.v_max - v), a)
            if math.isfinite(self.v_min):
                a = m.where(v < self.v_min, m.fmax(a, self.v_min - v), a)
            v_next = v + a * h
            if self.no_reverse:  # stop within the sub-step rather than reverse
                v_next = m.where(v_next < 0, 0.0, v_next)
            if self.kind == "unicycle":
                px, py, v, th = (
                    px + v * m.cos(th) * h,
                    py + v * m.sin(th) * h,
                    v_next,
                    th + s * h,
                )
            else:
                beta = m.atan(0.5 * m.tan(s))
                px, py, v, th = (
                    px + v * m.cos(th + beta) * h,
                    py + v * m.sin(th + beta) * h,
                    v_next,
                    th + v * m.sin(beta) / (self.length / 2) * h,
                )
        return px, py, v, th

    # ------------------------------------------------------------------ numpy
    def step(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """One step of ``dt``: ``x`` ``(..., 4)``, ``u`` ``(..., 2)`` -> ``(..., 4)`` (float64)."""
        x = np.asarray(x, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        shape = np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
        px, py, v, th = (np.broadcast_to(x[..., i], shape) for i in range(4))
        a, s = (np.broadcast_to(u[..., i], shape) for i in range(2))
        px, py, v, th = self._integrate(px, py, v, th, a, s, dt, _NUMPY)
        return np.stack([px, py, v, th], axis=-1)

    def rollout(self, x0: np.ndarray, U: np.ndarray, dt: float) -> np.ndarray:
        """States ``(K, 4)`` after each of the commands ``U`` ``(K, 2)`` from ``x0`` ``(4,)``."""
        out = np.empty((len(U), 4))
        x = np.asarray(x0, dtype=np.float64)
        for k, u in enumerate(U):  # sequential by nature (a simulation, not a hot path)
            x = self.step(x, u, dt)
            out[k] = x
        return out

    def turn_rate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Heading rate ``(...)`` of state ``x`` under command ``u`` (rad/s)."""
        x, u = np.asarray(x, dtype=np.float64), np.asarray(u, dtype=np.float64)
        if self.kind == "unicycle":
            return np.broadcast_to(u[..., 1], np.broadcast_shapes(x.shape[:-1], u.shape[:-1]))
        beta = np.arctan(0.5 * np.tan(u[..., 1]))
        return x[..., 2] * np.sin(beta) / (self.length / 2)

    def from_unicycle(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Commands of this model with the same acceleration and turn rate as the unicycle
        command ``u`` ``(..., 2)`` at states ``x`` ``(..., 4)`` (bicycle: the steering angle
        whose slip gives ``omega`` at speed ``v``; 0 below 0.1 m/s; not clipped)."""
        x, u = np.asarray(x, dtype=np.float64), np.asarray(u, dtype=np.float64)
        shape = np.broadcast_shapes(x.shape[:-1], u.shape[:-1]) + (2,)
        if self.kind == "unicycle":
            return np.broadcast_to(u, shape).copy()
        v = x[..., 2]
        moving = np.abs(v) > 0.1
        sb = np.where(moving, u[..., 1] * (self.length / 2) / np.where(moving, v, 1.0), 0.0)
        beta = np.arcsin(np.clip(sb, -0.999, 0.999))
        delta = np.arctan(2.0 * np.tan(beta))
        return np.stack(np.broadcast_arrays(u[..., 0], delta), axis=-1).astype(np.float64)

    # ------------------------------------------------------------------ casadi
    def casadi_step(self, x, u, dt: float):
        """The same step on CasADi expressions ``x`` (4) and ``u`` (2)."""
        px, py, v, th = x[0], x[1], x[2], x[3]
        px, py, v, th = self._integrate(px, py, v, th, u[0], u[1], dt, _CASADI)
        return ca.vertcat(px, py, v, th)

    def function(self, dt: float) -> ca.Function:
        """``vehicle_step(x[4], u[2]) -> (x_next[4], A[4x4], B[4x2])``: the step and its exact
        Jacobians ``A = d x_next / d x``, ``B = d x_next / d u`` (cached per ``dt``)."""
        return _function(self, float(dt))


@functools.lru_cache(maxsize=64)
def _function(model: VehicleModel, dt: float) -> ca.Function:
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 2)
    xn = model.casadi_step(x, u, dt)
    return ca.Function(
        "vehicle_step",
        [x, u],
        [xn, ca.jacobian(xn, x), ca.jacobian(xn, u)],
        ["x", "u"],
        ["x_next", "A", "B"],
    )
