"""Tracking: from the planner's reference trajectory to the ego's actuator command.

Two :class:`~solvers.control.types.Tracker` s, both on the world's vehicle model
(:class:`~solvers.control.vehicle.VehicleModel`, read from ``world.vehicle`` and ``world.dt``
at :meth:`reset`):

:class:`PIDTracker`: a speed loop (acceleration) and a heading / cross-track loop (turn rate,
converted to a steering angle for the bicycle), with feed-forward from the plan's controls,
conditional-integration anti-windup, and the output clipped to the command box and rates.

:class:`MPCTracker`: linear time-varying MPC. Every step the vehicle model is linearized
(exact CasADi Jacobians) along the reference over ``horizon`` steps and the tracking problem

    min  1/2 sum_k |x_k - r_k|^2_{Q_k} + 1/2 sum_k |u_k - ubar_k|^2_R + 1/2 sum_k |u_k - u_{k-1}|^2_S
    s.t. x_{k+1} = A_k x_k + B_k u_k + c_k,  u_min <= u_k <= u_max,
         |u_k - u_{k-1}| <= rate * dt  (u_{-1}: the command applied last),
         v_k >= min(0, vtop_k)  (k = 1..N: a hard state constraint, the ego never plans to
                                 reverse; vtop_k, :func:`speed_floor`, the highest speed the
                                 box and rates reach, below 0 only right after hard braking)

is solved as a sparse QP with OSQP (QP numbers that are not finite or beyond ``1e15`` are
never handed to it: the call falls back). ``Q_k`` weights the along-track and cross-track position
errors in the reference's frame (so its values change with the reference heading), the speed
and the heading. The QP is set up once per :meth:`reset` with a fixed sparsity pattern;
every step only its numbers change (``update(q, l, u, Px, Ax)``) and the previous solution,
shifted by one stage, warm-starts it. A reference that drives backwards is tracked at
standstill; an ego already reversing faster than ``a_max dt`` makes the QP infeasible and
the tracker falls back (braking, which raises the speed towards zero). The command's
``info["sequence"]`` holds the QP's ``N`` commands (the applied one first), the continuation
a safety filter (:mod:`solvers.control.safety`) checks.

:meth:`applied` tells a tracker the command the actuators got when a safety filter
changed it: the rate limits of the next call count from that command.

Reference alignment (both trackers): the plan's states are at ``t0 + dt_p (j + 1)`` and its
controls act on ``[t0 + dt_p j, t0 + dt_p (j + 1))``; the tracker samples them at
``t + dt k`` (linear interpolation, heading unwrapped; the state at ``t0`` is the first state
extrapolated back one period). A reference shorter than the horizon holds its last state
(with zero nominal command). The nominal unicycle controls become the vehicle's commands with
:meth:`VehicleModel.from_unicycle` and are clipped to the box.

Fallback: a plan with ``ok=False``, the wrong shapes or non-finite values, a non-finite ego
state or time, a PID command that comes out non-finite, or a QP that OSQP does not solve
yields a braking command
(``Command(fallback=True, info={"reason": ...})``): the acceleration that stops the vehicle
within a step, clipped to ``[a_min, a_max]`` (the jerk limit is waived: safety first), the
steering held. Trackers count them in ``fallbacks``. A fallback leaves the tracker's state
(integrators, previous errors, warm start) as it was before the call, so one bad input never
poisons later calls. :meth:`control` before :meth:`reset` raises :class:`SpecError`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import osqp
import scipy.sparse as sp

from epo_casadi.errors import SpecError, check_bool, check_number, check_size

from .types import Command, Plan
from .vehicle import VehicleModel

__all__ = [
    "PIDOptions",
    "PIDTracker",
    "MPCOptions",
    "MPCTracker",
    "reference",
    "speed_floor",
    "world_vehicle",
    "MAX_HORIZON",
]

#: most prediction steps of :class:`MPCTracker` (its QP has 6 x horizon unknowns)
MAX_HORIZON = 1000
#: most OSQP iterations per step of :class:`MPCTracker`
MAX_ITER = 1_000_000
#: largest magnitude of a QP number handed to OSQP (larger: the ego or plan is out of range)
_QP_LIMIT = 1e15
#: the upper bound of a one-sided row (v_k >= 0): OSQP's infinity is 1e30; this is within
#: _QP_LIMIT and far beyond any speed
_FREE = 1e15

_log = logging.getLogger(__name__)


def _options(cls, options, kw, prefix):
    if isinstance(options, cls):
        if kw:
            raise SpecError(prefix, "give either an options object or keywords, not both")
        return options
    d = {**dict(options or {}), **kw}
    known = set(cls.__dataclass_fields__)
    for k in d:
        if k not in known:
            raise SpecError(f"{prefix}.{k}", f"unknown option; expected one of {sorted(known)}")
    return cls(**d)


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _plan_problem(plan: Plan) -> str | None:
    """Why ``plan`` cannot be tracked, or None."""
    if not isinstance(plan, Plan):
        return f"expected a Plan, got {type(plan).__name__}"
    if not plan.ok:
        return f"plan failed: {plan.message}"
    S, U = np.asarray(plan.states), np.asarray(plan.controls)
    if S.ndim != 2 or S.shape[1] != 4 or len(S) < 1:
        return f"plan.states: expected shape (K, 4), got {S.shape}"
    if U.shape != (len(S), 2):
        return f"plan.controls: expected shape ({len(S)}, 2), got {U.shape}"
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(U))):
        return "plan has non-finite values"
    if not (math.isfinite(plan.t0) and math.isfinite(plan.dt) and plan.dt > 0):
        return f"plan.t0/dt: expected finite numbers with dt > 0, got {plan.t0}, {plan.dt}"
    return None


def _input_problem(ego: np.ndarray, plan: Plan, t) -> str | None:
    """Why ``control(ego, plan, t)`` cannot track, or None."""
    reason = _plan_problem(plan)
    if reason is None and not (ego.shape == (4,) and np.all(np.isfinite(ego))):
        reason = f"ego state: expected 4 finite numbers, got {ego!r}"
    if reason is None:
        ok = isinstance(t, (int, float, np.integer, np.floating)) and not isinstance(t, bool)
        if not (ok and math.isfinite(float(t))):
            reason = f"time t: expected a finite number, got {t!r}"
    return reason


def world_vehicle(world) -> tuple[VehicleModel, float]:
    """The world's ego ``vehicle`` (a :class:`VehicleModel`) and its period ``dt`` (> 0),
    checked (:class:`~epo_casadi.errors.SpecError` naming the member)."""
    vehicle, dt = getattr(world, "vehicle", None), getattr(world, "dt", None)
    if not isinstance(vehicle, VehicleModel):
        raise SpecError("world.vehicle", f"expected a VehicleModel, got {type(vehicle).__name__}")
    check_number("world.dt", dt, lo=0, lo_open=True)
    return vehicle, float(dt)


def reference(plan: Plan, t: float, dt: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The plan sampled for a tracker at time ``t``: states ``(n + 1, 4)`` at ``t + dt k``,
    ``k = 0..n``, and nominal unicycle controls ``(n, 2)`` on ``[t + dt k, t + dt (k+1))``
    (see the module docstring; the plan must be valid)."""
    S = np.asarray(plan.states, dtype=np.float64)
    U = np.asarray(plan.controls, dtype=np.float64)
    K, pdt = len(S), float(plan.dt)
    back = S[0] - np.array([S[0, 2] * math.cos(S[0, 3]), S[0, 2] * math.sin(S[0, 3]), 0, 0]) * pdt
    back[2] = S[0, 2] - U[0, 0] * pdt
    S = np.concatenate([back[None], S])
    S[:, 3] = np.unwrap(S[:, 3])
    tp = plan.t0 + pdt * np.arange(K + 1)
    tq = t + dt * np.arange(n + 1)
    R = np.stack([np.interp(tq, tp, S[:, i]) for i in range(4)], axis=1)
    j = np.floor((tq[:-1] - plan.t0) / pdt + 1e-9).astype(int)
    ubar = np.where((j < K)[:, None], U[np.clip(j, 0, K - 1)], 0.0)
    return R, ubar


def speed_floor(vehicle: VehicleModel, dt: float, n: int, v0: float, a_prev: float) -> np.ndarray:
    """``(n,)`` lower bounds of the speeds ``v_1..v_n`` in a QP with rate limits: ``0``,
    or the highest speed the box and the acceleration rate allow from ``v0`` after the
    command ``a_prev`` where even that is below zero (a car braking hard at a standstill
    cannot release its brake faster than the rate limit; the vehicle itself stops, the
    linear model would reverse). Not finite input: zeros."""
    if not (math.isfinite(v0) and math.isfinite(a_prev)):
        return np.zeros(n)
    r = vehicle.rate_bounds(dt)[0]
    a_top = np.minimum(vehicle.a_max, a_prev + r * np.arange(1, n + 1))
    return np.minimum(0.0, v0 + dt * np.cumsum(a_top))


class _TrackerBase:
    """Shared state: vehicle, period, last command, fallback counter."""

    vehicle: VehicleModel | None = None
    dt: float

    def _require_reset(self) -> None:
        if self.vehicle is None:
            raise SpecError(
                "tracker", f"{type(self).__name__}.control() called before reset(world)"
            )

    def _reset_common(self, world) -> None:
        self.vehicle, self.dt = world_vehicle(world)
        self.u_prev = np.zeros(2)
        self.fallbacks = 0
        self.steps = 0

    def applied(self, u: np.ndarray) -> None:
        """The command the actuators got this period (a safety filter may have changed the
        tracker's): the rate limits of the next call count from it (two finite numbers;
        anything else is ignored)."""
        self._require_reset()
        u = np.asarray(u, dtype=np.float64).reshape(-1)
        if u.shape == (2,) and np.all(np.isfinite(u)):
            self.u_prev = u.copy()

    def _brake(self, ego: np.ndarray, reason: str) -> Command:
        """Stop within a step if possible; steering held (see the module docstring)."""
        self.fallbacks += 1
        _log.info("%s fell back to braking: %s", type(self).__name__, reason)
        v = float(ego[2]) if np.all(np.isfinite(ego)) else 0.0
        lo, hi = self.vehicle.bounds()
        a = float(np.clip(-v / self.dt, lo[0], hi[0]))
        s = float(np.clip(self.u_prev[1], lo[1], hi[1]))
        self.u_prev = np.array([a, s])
        return Command(value=self.u_prev.copy(), fallback=True, info={"reason": reason})


# ====================================================================== PID
@dataclass(frozen=True)
class PIDOptions:
    """Gains of :class:`PIDTracker` (unknown keys are an error)."""

    kp_v: float = 1.5  #: speed loop: proportional gain (1/s)
    ki_v: float = 0.3  #: speed loop: integral gain (1/s^2)
    kd_v: float = 0.0  #: speed loop: derivative gain (-)
    k_lon: float = 0.5  #: along-track position error -> speed target (1/s)
    kp_h: float = 3.0  #: heading loop: proportional gain (1/s)
    ki_h: float = 0.2  #: heading loop: integral gain (1/s^2)
    kd_h: float = 0.1  #: heading loop: derivative gain (-)
    k_ct: float = 1.0  #: cross-track error -> heading correction atan(k_ct e / (|v| + v_soft))
    v_soft: float = 1.0  #: softening speed of the cross-track term (m/s)
    feedforward: bool = True  #: add the plan's acceleration and turn rate

    def __post_init__(self):
        for name in self.__dataclass_fields__:
            if name == "feedforward":
                check_bool("pid.feedforward", self.feedforward)
            elif name == "v_soft":
                check_number("pid.v_soft", self.v_soft, lo=0, lo_open=True)
            else:
                check_number(f"pid.{name}", getattr(self, name), lo=0)


class PIDTracker(_TrackerBase):
    """:class:`~solvers.control.types.Tracker`: two PID loops (see the module docstring)."""

    def __init__(self, options: PIDOptions | dict | None = None, **kw):
        self.options = _options(PIDOptions, options, kw, "pid")

    def reset(self, world) -> None:
        """Read ``world.vehicle`` and ``world.dt``; clear integrators and counters."""
        self._reset_common(world)
        self._iv = self._ih = 0.0
        self._ev_prev = self._eh_prev = None

    def control(self, ego: np.ndarray, plan: Plan, t: float) -> Command:
        """The command at time ``t`` for the ego state ``ego`` ``(4,)`` following ``plan``.

        Bad input (see the module docstring) brakes and leaves the loops' state unchanged."""
        self._require_reset()
        self.steps += 1
        ego = np.asarray(ego, dtype=np.float64)
        reason = _input_problem(ego, plan, t)
        if reason is not None:
            return self._brake(ego, reason)
        o, dt, veh = self.options, self.dt, self.vehicle
        with np.errstate(all="ignore"):
            R, ubar = reference(plan, float(t), dt, 1)
            r = R[0]
            c, s = math.cos(r[3]), math.sin(r[3])
            dx, dy = ego[0] - r[0], ego[1] - r[1]
            e_lon = -(c * dx + s * dy)  # > 0: the ego lags behind the reference point
            e_lat = -s * dx + c * dy  # > 0: the ego is left of the reference
            e_v = r[2] + o.k_lon * e_lon - ego[2]
            e_h = float(_wrap(r[3] - ego[3])) - math.atan(o.k_ct * e_lat / (abs(ego[2]) + o.v_soft))
            dv = 0.0 if self._ev_prev is None else (e_v - self._ev_prev) / dt
            dh = 0.0 if self._eh_prev is None else float(_wrap(e_h - self._eh_prev)) / dt
            ff = ubar[0] if o.feedforward else np.zeros(2)
            iv, ih = self._iv + e_v * dt, self._ih + e_h * dt
            a = ff[0] + o.kp_v * e_v + o.ki_v * iv + o.kd_v * dv
            w = ff[1] + o.kp_h * e_h + o.ki_h * ih + o.kd_h * dh
            raw = veh.from_unicycle(ego, np.array([a, w]))
            u = veh.clip(raw, self.u_prev, dt)
        if not np.all(np.isfinite([*raw, *u, e_v, e_h, iv, ih, e_lat, e_lon])):
            return self._brake(ego, "the PID command is not finite (the reference is out of reach)")
        # anti-windup: keep an integrator only while its loop is not pushed into saturation
        if not (u[0] != raw[0] and np.sign(raw[0] - u[0]) == np.sign(e_v)):
            self._iv = iv
        if not (u[1] != raw[1] and np.sign(raw[1] - u[1]) == np.sign(e_h * np.sign(ego[2] or 1))):
            self._ih = ih
        self._ev_prev, self._eh_prev = e_v, e_h
        self.u_prev = u
        return Command(value=u.copy(), info={"e_lat": e_lat, "e_lon": e_lon, "e_v": e_v})


# ====================================================================== MPC
@dataclass(frozen=True)
class MPCOptions:
    """Horizon, weights and solver settings of :class:`MPCTracker` (unknown keys: error)."""

    horizon: int = 20  #: prediction steps (of the world's dt), at most MAX_HORIZON (1000)
    q_lon: float = 1.0  #: along-track position error weight (1/m^2)
    q_lat: float = 10.0  #: cross-track position error weight (1/m^2)
    q_v: float = 1.0  #: speed error weight (s^2/m^2)
    q_theta: float = 5.0  #: heading error weight (1/rad^2)
    terminal: float = 5.0  #: factor on the state weights of the last stage
    r_a: float = 0.1  #: acceleration deviation from the nominal (s^4/m^2)
    r_steer: float = 1.0  #: steering (or turn rate) deviation from the nominal
    s_a: float = 1.0  #: acceleration change between steps
    s_steer: float = 10.0  #: steering (or turn rate) change between steps
    eps_abs: float = 1e-5  #: OSQP absolute tolerance
    eps_rel: float = 1e-5  #: OSQP relative tolerance
    max_iter: int = 4000  #: OSQP iteration limit, at most 1,000,000
    polish: bool = False  #: OSQP solution polishing
    warm_start: bool = True  #: warm-start from the shifted previous solution

    def __post_init__(self):
        object.__setattr__(
            self, "horizon", check_size("mpc.horizon", self.horizon, MAX_HORIZON, "QP size")
        )
        for name in ("q_lon", "q_lat", "q_v", "q_theta", "r_a", "r_steer", "s_a", "s_steer"):
            check_number(f"mpc.{name}", getattr(self, name), lo=0)
        if self.r_a + self.s_a <= 0 or self.r_steer + self.s_steer <= 0:
            raise SpecError("mpc.r_a", "expected r_a + s_a > 0 and r_steer + s_steer > 0")
        check_number("mpc.terminal", self.terminal, lo=0)
        check_number("mpc.eps_abs", self.eps_abs, lo=0, lo_open=True)
        check_number("mpc.eps_rel", self.eps_rel, lo=0)
        object.__setattr__(
            self, "max_iter", check_size("mpc.max_iter", self.max_iter, MAX_ITER, "solve time")
        )
        check_bool("mpc.polish", self.polish)
        check_bool("mpc.warm_start", self.warm_start)


def _csc(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, shape) -> tuple:
    """A CSC matrix with exactly these (unique) entries, zeros kept, and the permutation
    from the triplet order to its data order."""
    order = np.lexsort((rows, cols))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(cols, minlength=shape[1]))])
    M = sp.csc_matrix((vals[order], rows[order], indptr), shape=shape)
    return M, order


class MPCTracker(_TrackerBase):
    """:class:`~solvers.control.types.Tracker`: LTV MPC with OSQP (module docstring).

    Attributes after :meth:`control`: ``fallbacks``, ``steps``, ``setups`` (QP set-ups: one
    per reset, and a fresh one before the call after a QP that OSQP did not solve, so that
    numbers a failed update left behind never reach a later solve), ``solver`` (the ``osqp.OSQP`` object), ``last`` (the last QP's numbers:
    ``u`` ``(N, 2)``, ``x`` ``(N, 4)``, ``ref``, ``ubar``, ``A``, ``B``, ``c``, ``Q``).
    """

    def __init__(self, options: MPCOptions | dict | None = None, **kw):
        self.options = _options(MPCOptions, options, kw, "mpc")
        self.setups = 0
        self.solver = None

    # ------------------------------------------------------------------ set-up
    def reset(self, world) -> None:
        """Read the vehicle and period, build the QP's structure and set OSQP up (once)."""
        self._reset_common(world)
        o, N = self.options, self.options.horizon
        self._f = self.vehicle.function(self.dt).map(N)
        self.nu, self.nz = 2 * N, 6 * N
        iu = np.arange(2 * N).reshape(N, 2)  # u_k -> columns
        ix = 2 * N + np.arange(4 * N).reshape(N, 4)  # x_{k+1} -> columns (row k: x_{k+1})
        # ---- constraint matrix: dynamics (4N), box (2N), rates (2N), speeds v_k >= 0 (N)
        r_dyn = np.arange(4 * N).reshape(N, 4)
        I_r, I_c = r_dyn.ravel(), ix.ravel()
        B_r = np.repeat(r_dyn[:, :, None], 2, axis=2).ravel()
        B_c = np.repeat(iu[:, None, :], 4, axis=1).ravel()
        A_r = np.repeat(r_dyn[1:, :, None], 4, axis=2).ravel()
        A_c = np.repeat(ix[:-1, None, :], 4, axis=1).ravel()
        box_r, box_c = 4 * N + np.arange(2 * N), iu.ravel()
        rate_r1, rate_c1 = 6 * N + np.arange(2 * N), iu.ravel()
        rate_r2, rate_c2 = 6 * N + np.arange(2, 2 * N), iu[:-1].ravel()
        speed_r, speed_c = 8 * N + np.arange(N), ix[:, 2]
        self._A_rows = np.concatenate([I_r, B_r, A_r, box_r, rate_r1, rate_r2, speed_r])
        A_cols = np.concatenate([I_c, B_c, A_c, box_c, rate_c1, rate_c2, speed_c])
        self._A_const = np.concatenate(
            [np.ones(4 * N), np.ones(2 * N), np.ones(2 * N), -np.ones(2 * N - 2), np.ones(N)]
        )
        self._nB, self._nA = 8 * N, 16 * (N - 1)
        # ---- cost: Q_k blocks (entries 00, 01, 11, 22, 33) and the U block
        xq = ix.reshape(N, 4)
        Q_r = np.stack([xq[:, 0], xq[:, 0], xq[:, 1], xq[:, 2], xq[:, 3]], axis=1).ravel()
        Q_c = np.stack([xq[:, 0], xq[:, 1], xq[:, 1], xq[:, 2], xq[:, 3]], axis=1).ravel()
        Ud = iu.ravel()
        Uo_r, Uo_c = iu[:-1].ravel(), iu[1:].ravel()
        P_rows = np.concatenate([Q_r, Ud, Uo_r])
        P_cols = np.concatenate([Q_c, Ud, Uo_c])
        Rw = np.array([o.r_a, o.r_steer])
        Sw = np.array([o.s_a, o.s_steer])
        n_next = np.ones((N, 1))
        n_next[-1] = 0.0
        self._Rw, self._Sw = Rw, Sw
        self._U_diag = (Rw + Sw * (1.0 + n_next)).ravel()
        self._U_off = np.tile(-Sw, N - 1)
        self._stage_w = np.ones(N)
        self._stage_w[-1] = o.terminal
        # ---- initial numbers: the linearization at rest, heading 0
        x0 = np.zeros((N, 4))
        u0 = np.zeros((N, 2))
        _, A, B = self._linearize(x0, u0)
        Av = self._A_values(A, B)
        Pv = self._P_values(np.zeros(N))
        self._A, self._A_perm = _csc(self._A_rows, A_cols, Av, (9 * N, 6 * N))
        self._P, self._P_perm = _csc(P_rows, P_cols, Pv, (6 * N, 6 * N))
        self._setup()
        self.last: dict = {}

    def _setup(self) -> None:
        """A new OSQP object on the structure of :meth:`reset` (numbers at rest)."""
        o, N = self.options, self.options.horizon
        lo, hi = self._bounds(np.zeros(N * 4), np.zeros(2))
        self.solver = osqp.OSQP()
        self.solver.setup(
            self._P,
            np.zeros(6 * N),
            self._A,
            lo,
            hi,
            eps_abs=o.eps_abs,
            eps_rel=o.eps_rel,
            max_iter=o.max_iter,
            polishing=o.polish,
            warm_starting=o.warm_start,
            verbose=False,
        )
        self.setups += 1
        self._z = None
        self._stale = False

    # ------------------------------------------------------------------ numbers
    def _linearize(self, Xbar: np.ndarray, Ubar: np.ndarray):
        xn, A, B = self._f(Xbar.T, Ubar.T)
        N = self.options.horizon
        xn = np.asarray(xn).T
        A = np.asarray(A).reshape(4, N, 4).transpose(1, 0, 2)
        B = np.asarray(B).reshape(4, N, 2).transpose(1, 0, 2)
        return xn, A, B

    def _A_values(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        N = self.options.horizon
        c = self._A_const
        return np.concatenate([c[: 4 * N], -B.ravel(), -A[1:].ravel(), c[4 * N :]])

    def _P_values(self, theta: np.ndarray) -> np.ndarray:
        o = self.options
        ct, st = np.cos(theta), np.sin(theta)
        w = self._stage_w
        q00 = w * (o.q_lon * ct * ct + o.q_lat * st * st)
        q01 = w * (o.q_lon - o.q_lat) * ct * st
        q11 = w * (o.q_lon * st * st + o.q_lat * ct * ct)
        qv, qt = w * o.q_v, w * o.q_theta
        Q = np.stack([q00, q01, q11, qv, qt], axis=1).ravel()
        return np.concatenate([Q, self._U_diag, self._U_off])

    def _bounds(
        self, rhs: np.ndarray, u_prev: np.ndarray, v0: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        N = self.options.horizon
        umin, umax = self.vehicle.bounds()
        r = self.vehicle.rate_bounds(self.dt)
        v_floor = speed_floor(self.vehicle, self.dt, N, v0, u_prev[0])
        lo = np.concatenate([rhs, np.tile(umin, N), u_prev - r, np.tile(-r, N - 1), v_floor])
        hi = np.concatenate(
            [rhs, np.tile(umax, N), u_prev + r, np.tile(r, N - 1), _FREE * np.ones(N)]
        )
        return lo, hi

    # ------------------------------------------------------------------ step
    def control(self, ego: np.ndarray, plan: Plan, t: float) -> Command:
        """Solve the QP at time ``t`` from ``ego`` ``(4,)`` along ``plan``; its first command."""
        if self.solver is None:
            raise SpecError("tracker", "MPCTracker.control() called before reset(world)")
        self.steps += 1
        ego = np.asarray(ego, dtype=np.float64)
        reason = _input_problem(ego, plan, t)
        if reason is not None:
            return self._brake(ego, reason)
        o, N, veh = self.options, self.options.horizon, self.vehicle
        t_start = time.perf_counter()
        with np.errstate(all="ignore"):
            R, ubar_uni = reference(plan, float(t), self.dt, N)
            R[:, 3] += 2 * np.pi * np.round((ego[3] - R[0, 3]) / (2 * np.pi))
            ref = R[1:]
            Xbar = np.concatenate([ego[None], ref[:-1]])  # linearization points x_0..x_{N-1}
            ubar = veh.clip(veh.from_unicycle(Xbar, ubar_uni))
            xn, A, B = self._linearize(Xbar, ubar)
            c = xn - np.einsum("kij,kj->ki", A, Xbar) - np.einsum("kij,kj->ki", B, ubar)
            rhs = c.copy()
            rhs[0] += A[0] @ ego  # x_1 = A_0 x_0 + B_0 u_0 + c_0 with x_0 the ego state
            u_prev = self.u_prev
            lo, hi = self._bounds(rhs.ravel(), u_prev, float(ego[2]))
            Pv = self._P_values(ref[:, 3])
            w = self._stage_w[:, None]
            Qd = np.stack(
                [Pv[0 : 5 * N : 5], Pv[1 : 5 * N : 5], Pv[2 : 5 * N : 5]], axis=1
            )  # q00, q01, q11
            qx = np.empty((N, 4))
            qx[:, 0] = -(Qd[:, 0] * ref[:, 0] + Qd[:, 1] * ref[:, 1])
            qx[:, 1] = -(Qd[:, 1] * ref[:, 0] + Qd[:, 2] * ref[:, 1])
            qx[:, 2:] = -w * np.array([o.q_v, o.q_theta]) * ref[:, 2:]
            qu = -self._Rw * ubar
            qu[0] -= self._Sw * u_prev
            q = np.concatenate([qu.ravel(), qx.ravel()])
            Av = self._A_values(A, B)
        if not all(np.all(np.abs(v) <= _QP_LIMIT) for v in (q, lo, hi, Pv, Av)):
            # OSQP never sees them: a later, valid call solves as before
            self._z = None
            return self._brake(
                ego, "QP numbers not finite or beyond 1e15 (ego or plan out of range)"
            )
        if self._stale:  # the last QP was not solved: OSQP may hold broken numbers
            self._setup()
        t_update = time.perf_counter()
        self.solver.update(q=q, l=lo, u=hi, Px=Pv[self._P_perm], Ax=Av[self._A_perm])
        if o.warm_start and self._z is not None:
            zu = self._z[: 2 * N].reshape(N, 2)
            zx = self._z[2 * N :].reshape(N, 4)
            zs = np.concatenate(
                [
                    np.concatenate([zu[1:], zu[-1:]]).ravel(),
                    np.concatenate([zx[1:], zx[-1:]]).ravel(),
                ]
            )
            self.solver.warm_start(x=zs)
        t_solve = time.perf_counter()
        res = self.solver.solve(raise_error=False)
        t_end = time.perf_counter()
        timing = {
            "build": t_update - t_start,  # reference, linearization, QP numbers
            "update": t_solve - t_update,  # osqp update (+ refactorization) and warm start
            "solve": t_end - t_solve,
        }
        status = res.info.status
        self.last = {
            "ref": ref,
            "ubar": ubar,
            "Xbar": Xbar,
            "A": A,
            "B": B,
            "c": c,
            "status": status,
            "timing": timing,
        }
        solved = res.info.status_val in (
            osqp.SolverStatus.OSQP_SOLVED,
            osqp.SolverStatus.OSQP_SOLVED_INACCURATE,
        )
        if not solved or res.x is None or not np.all(np.isfinite(res.x)):
            self._z = None
            self._stale = True
            return self._brake(ego, f"QP not solved: {status}")
        self._z = res.x.copy()
        U = res.x[: 2 * N].reshape(N, 2)
        self.last.update(u=U.copy(), x=res.x[2 * N :].reshape(N, 4).copy())
        u = veh.clip(U[0], u_prev, self.dt)  # removes the solver-tolerance excess only
        self.u_prev = u
        seq = U.copy()
        seq[0] = u
        info = {
            "status": status,
            "iterations": res.info.iter,
            "timing": timing,
            "u_qp": U[0].copy(),
            "sequence": seq,  # the QP's commands, the applied one first (a safety filter's continuation)
        }
        return Command(value=u.copy(), info=info)
