"""Estimation of the observed agents: one filterpy unscented Kalman filter per agent.

Each agent other than the ego (:class:`~solvers.control.types.Observation`, ``others``) is
measured as a noisy position ``z = (x, y) + N(0, meas_std^2 I)`` once per period ``dt``;
a row with a ``NaN`` is a dropout (the filter only predicts). A measurement with an
infinite coordinate, or farther than ``max_position`` (m, default ``1e6``) from the origin, is
rejected as an outlier and handled like a dropout (the filter only predicts; it is counted in
:attr:`UKFEstimator.rejected` and its ``valid`` entry is False); so is one whose update
would leave the filter's state or covariance non-finite. The estimate is therefore never
``NaN`` for a track that has started, whatever the measurements. The motion model is one of

``"ctrv"`` (default): state ``(x, y, v, theta, omega)``, constant turn rate and velocity::

    x+ = x + v/omega (sin(theta + omega dt) - sin(theta)),  y+ = y + v/omega (cos(theta) - cos(theta + omega dt)),
    v+ = v,  theta+ = theta + omega dt,  omega+ = omega          (straight-line limit for |omega| < 1e-6)

``"unicycle"``: state ``(x, y, v, theta)``, constant speed and heading (explicit Euler).

Process noise: white longitudinal acceleration ``N(0, accel_std^2)`` and, for ``"ctrv"``, white
yaw acceleration ``N(0, turn_std^2)`` (for ``"unicycle"``: white turn rate ``N(0, turn_std^2)``),
held over a period and mapped through ``G`` (``Q = G diag(accel_std^2, turn_std^2) G^T``, with
``G`` evaluated at the current heading). Headings are wrapped to ``(-pi, pi]`` in the residuals,
and the sigma-point mean of the heading is the circular mean.

Initialization: a track starts with its first measurement and is *tentative* until it has
``init_points`` measurements; until then (and to start the filter) the state is a least
squares constant-velocity fit of the measurements so far, with the fit's covariance mapped to
``(v, theta)`` by its Jacobian: from two measurements on, speed and heading come from their
difference (one measurement: speed 0 with ``init_speed_std``, heading unknown, std pi).
Where a map is known (:meth:`UKFEstimator.use_map`, the world's ``road_map``) and the first
measurement lies on a lane (within half its width plus ``2 meas_std`` of its centre line),
the lane's direction there, ``theta_lane``, is a prior on the heading with std
``sigma_l = lane_heading_std``: one measurement starts with that heading; from two on, the
fitted velocity (std ``sigma_v`` per axis) is tested against the lane: it is *not* following
the lane when its component along the lane is below ``-4 sigma_v`` or its component across
exceeds ``4 sqrt(sigma_v^2 + (along sigma_l)^2)`` (a 4-sigma gate: a car on its lane is
taken off it in about 1 start in 10^4); otherwise the fit's heading
``theta_fit`` (std ``sigma_f``) is fused with the lane's, ``theta = theta_lane + w
wrap(theta_fit - theta_lane)`` with ``w = sigma_l^2 / (sigma_l^2 + sigma_f^2)`` and variance
``w sigma_f^2``, and the speed is the fitted velocity along ``theta``, at least 0. The
fused heading is off the lane's by at most ``w pi``; a slow car, whose few noisy
measurements say little about its direction (``sigma_f`` large), so starts along its lane
instead of at heading 0 or at the direction of two noisy points. Of several lanes within
reach, the nearest the fit agrees with is used; none: the fit alone. An agent never
measured yet has ``NaN`` states and covariances.

Speeds are kept non-negative: a speed estimate that a measurement or a prediction takes
below zero is set to zero (the agents are cars and people, who stop rather than reverse;
flipping the heading instead would turn a waiting car around).

Convergence (``Estimate.converged``): a track has converged once it has incorporated at least
``converged_updates`` measurements and the trace of its position covariance is at most
``converged_trace`` (m^2); a track predicted through dropouts can fall back to unconverged.

The history (``Estimate.history``, ``(N-1, H+1, 4)``) holds the filtered states of steps
``k-H .. k`` as the filter had them then (oldest first, the last row is the current estimate),
the same layout as the datasets' ``history`` (:mod:`scenarios.rpi`, ``H = 18``: 1.8 s at
0.1 s). Rows before a track started are the constant-velocity backward extrapolation of its
oldest estimate, as the datasets do; ``valid`` is True only on rows where a measurement was
incorporated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from epo_casadi.errors import SpecError, check_number, check_size

from .types import SENSOR_NOISE_STD, Estimate, Observation

__all__ = ["UKFOptions", "UKFEstimator", "MOTION_MODELS", "MAX_HISTORY", "MAX_INIT_POINTS"]

MOTION_MODELS = ("ctrv", "unicycle")
#: most past periods in ``Estimate.history`` (an (N-1, H+1, 4) array rebuilt every step)
MAX_HISTORY = 1000
#: most measurements of a track's constant-velocity start fit
MAX_INIT_POINTS = 100
#: standard deviations of the fitted velocity beyond which a track is not following a lane
_GATE = 4.0


@dataclass(frozen=True)
class UKFOptions:
    """Options of :class:`UKFEstimator` (unknown keys are an error)."""

    model: str = "ctrv"  #: motion model: "ctrv" or "unicycle"
    #: position measurement noise std (m), per axis: the worlds' default sensor noise
    #: (solvers.control.types.SENSOR_NOISE_STD, 0.3 m)
    meas_std: float = SENSOR_NOISE_STD
    accel_std: float = 2.0  #: process noise: longitudinal acceleration std (m/s^2)
    turn_std: float = 0.5  #: process noise: yaw acceleration (ctrv, rad/s^2) or turn rate std
    history: int = 18  #: H, past periods in Estimate.history (plus the current one), <= 1000
    init_points: int = 3  #: measurements fitted before the filter starts (2 to 100)
    init_speed_std: float = 10.0  #: speed std (m/s) of a track with a single measurement
    init_turn_std: float = 0.5  #: ctrv: std of the initial turn rate (rad/s)
    alpha: float = 1.0  #: Merwe sigma-point spread (1 with kappa 0: no negative weights)
    beta: float = 2.0  #: Merwe prior knowledge parameter (2 for Gaussians)
    max_position: float = 1e6  #: m, measurements farther from the origin are outliers
    lane_prior: bool = True  #: start a track's heading from the lane it is on (use_map)
    lane_heading_std: float = 0.1  #: rad, std of a car's heading about its lane's direction
    converged_updates: int = 5  #: measurements before a track counts as converged (1 to 100)
    converged_trace: float = 0.5  #: m^2, largest trace of the position covariance of a
    #: converged track

    def __post_init__(self):
        if self.model not in MOTION_MODELS:
            raise SpecError("ukf.model", f"expected one of {MOTION_MODELS}, got {self.model!r}")
        check_number("ukf.meas_std", self.meas_std, lo=0, lo_open=True)
        check_number("ukf.accel_std", self.accel_std, lo=0, lo_open=True)
        check_number("ukf.turn_std", self.turn_std, lo=0, lo_open=True)
        object.__setattr__(
            self, "history", check_size("ukf.history", self.history, MAX_HISTORY, "memory", lo=0)
        )
        object.__setattr__(
            self,
            "init_points",
            check_size("ukf.init_points", self.init_points, MAX_INIT_POINTS, "fit size", lo=2),
        )
        check_number("ukf.init_speed_std", self.init_speed_std, lo=0, lo_open=True)
        check_number("ukf.init_turn_std", self.init_turn_std, lo=0, lo_open=True)
        check_number("ukf.alpha", self.alpha, lo=0, lo_open=True, hi=1)
        check_number("ukf.beta", self.beta, lo=0)
        check_number("ukf.max_position", self.max_position, lo=0, lo_open=True, hi=1e12)
        if not isinstance(self.lane_prior, bool):
            raise SpecError("ukf.lane_prior", f"expected true or false, got {self.lane_prior!r}")
        check_number("ukf.lane_heading_std", self.lane_heading_std, lo=0, lo_open=True, hi=math.pi)
        object.__setattr__(
            self,
            "converged_updates",
            check_size(
                "ukf.converged_updates", self.converged_updates, MAX_INIT_POINTS, "updates", lo=1
            ),
        )
        check_number("ukf.converged_trace", self.converged_trace, lo=0, lo_open=True)

    @classmethod
    def from_dict(cls, d: dict | None) -> UKFOptions:
        """Options from a mapping; an unknown key raises :class:`SpecError`."""
        d = dict(d or {})
        known = set(cls.__dataclass_fields__)
        for k in d:
            if k not in known:
                raise SpecError(f"ukf.{k}", f"unknown option; expected one of {sorted(known)}")
        return cls(**d)


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = np.subtract(a, b)
    d[..., 3] = _wrap(d[..., 3])
    return d


def _mean(sigmas: np.ndarray, wm: np.ndarray) -> np.ndarray:
    x = wm @ sigmas
    x[3] = math.atan2(wm @ np.sin(sigmas[:, 3]), wm @ np.cos(sigmas[:, 3]))
    return x


def _fx_ctrv(s: np.ndarray, dt: float) -> np.ndarray:
    x, y, v, th, w = s
    if abs(w) > 1e-6:
        x += v / w * (math.sin(th + w * dt) - math.sin(th))
        y += v / w * (math.cos(th) - math.cos(th + w * dt))
    else:
        x += v * math.cos(th) * dt
        y += v * math.sin(th) * dt
    return np.array([x, y, v, th + w * dt, w])


def _fx_unicycle(s: np.ndarray, dt: float) -> np.ndarray:
    x, y, v, th = s
    return np.array([x + v * math.cos(th) * dt, y + v * math.sin(th) * dt, v, th])


def _hx(s: np.ndarray) -> np.ndarray:
    return s[:2]


def _positive_speed(x: np.ndarray, P: np.ndarray) -> None:
    """In place: a negative speed becomes zero (cars stop, they do not reverse)."""
    if x[2] < 0:
        x[2] = 0.0


def _lane_directions(lanes, point: np.ndarray, reach: float) -> list[tuple[float, float]]:
    """``(distance, heading)`` of every lane centre line ``(centre (P, 2), width)`` within
    ``width / 2 + reach`` of ``point``, nearest first (the heading of the closest segment)."""
    out = []
    for centre, width in lanes:
        a, b = centre[:-1], centre[1:]
        ab = b - a
        L2 = np.maximum(np.einsum("sj,sj->s", ab, ab), 1e-18)
        t = np.clip(np.einsum("sj,sj->s", point - a, ab) / L2, 0.0, 1.0)
        d = np.hypot(*(a + t[:, None] * ab - point).T)
        j = int(np.argmin(d))
        if d[j] <= 0.5 * width + reach:
            out.append((float(d[j]), math.atan2(ab[j, 1], ab[j, 0])))
    return sorted(out)


def _repair(P: np.ndarray) -> np.ndarray:
    """The nearest symmetric matrix with eigenvalues >= 1e-9 (round-off repair)."""
    w, V = np.linalg.eigh(0.5 * (P + P.T))
    return (V * np.maximum(w, 1e-9)) @ V.T


def _guarded(step, f: UnscentedKalmanFilter, *args) -> None:
    """Run a filter step on a symmetrized covariance; if its Cholesky factorization still
    fails (round-off made it indefinite), repair the covariance and run it again."""
    f.P = 0.5 * (f.P + f.P.T)
    x, P = f.x.copy(), f.P.copy()
    try:
        step(*args)
    except np.linalg.LinAlgError:
        f.x, f.P = x, _repair(P)
        step(*args)


class UKFEstimator:
    """:class:`~solvers.control.types.Estimator`: a filterpy UKF per observed agent.

    ``UKFEstimator(options)`` or ``UKFEstimator(meas_std=0.3, ...)``; see the module
    docstring for the model. :meth:`reset` starts tracks at the first observation,
    :meth:`update` advances one period. ``rejected`` counts the measurements rejected as
    outliers since :meth:`reset` (module docstring).
    """

    def __init__(self, options: UKFOptions | dict | None = None, **kw):
        if isinstance(options, UKFOptions):
            if kw:
                raise SpecError("ukf", "give either an options object or keywords, not both")
            self.options = options
        else:
            self.options = UKFOptions.from_dict({**dict(options or {}), **kw})
        self.nx = 5 if self.options.model == "ctrv" else 4
        self.dt: float | None = None
        self._lanes: list[tuple[np.ndarray, float]] = []

    def use_map(self, road_map) -> None:
        """The lanes a new track's heading may start from (module docstring): any object with
        ``lanes``, each with a ``centre`` polyline ``(P, 2)`` and a ``width`` (m), e.g. a
        :class:`scenarios.maps.RoadMap`; None (or ``lane_prior=False``): no prior. Kept
        across episodes until set again."""
        self._lanes = []
        lanes = getattr(road_map, "lanes", None) if road_map is not None else None
        if lanes is None:
            return
        if isinstance(lanes, dict):
            lanes = list(lanes.values())
        for ln in lanes:
            c = np.asarray(ln.centre, dtype=np.float64).reshape(-1, 2)
            if len(c) >= 2 and np.all(np.isfinite(c)):
                self._lanes.append((c, float(ln.width)))

    # ------------------------------------------------------------------ helpers
    def _new_filter(self, dt: float) -> UnscentedKalmanFilter:
        o = self.options
        pts = MerweScaledSigmaPoints(
            self.nx, alpha=o.alpha, beta=o.beta, kappa=0.0, subtract=_residual
        )
        fx = _fx_ctrv if o.model == "ctrv" else _fx_unicycle
        f = UnscentedKalmanFilter(
            dim_x=self.nx,
            dim_z=2,
            dt=dt,
            hx=_hx,
            fx=fx,
            points=pts,
            x_mean_fn=_mean,
            residual_x=_residual,
        )
        f.R = np.eye(2) * o.meas_std**2
        return f

    def _process_noise(self, theta: float) -> np.ndarray:
        o, dt = self.options, self.dt
        c, s = math.cos(theta), math.sin(theta)
        G = np.zeros((self.nx, 2))
        G[:3, 0] = 0.5 * dt * dt * c, 0.5 * dt * dt * s, dt
        if self.nx == 5:
            G[3:, 1] = 0.5 * dt * dt, dt
        else:
            G[3, 1] = dt
        return G @ np.diag([o.accel_std**2, o.turn_std**2]) @ G.T

    def _fit(
        self, times: np.ndarray, zs: np.ndarray, t: float, lanes=()
    ) -> tuple[np.ndarray, np.ndarray]:
        """Constant-velocity least squares fit of measurements ``zs`` at ``times``, as a
        state at ``t`` and its covariance (filter dimension), with the heading prior of the
        nearest agreeing lane of ``lanes`` (``(distance, heading)``, module docstring)."""
        o = self.options
        sl2 = o.lane_heading_std**2
        m = np.zeros(self.nx)
        P = np.zeros((self.nx, self.nx))
        if self.nx == 5:
            P[4, 4] = o.init_turn_std**2
        if len(times) == 1:
            m[:2] = zs[0]
            P[0, 0] = P[1, 1] = o.meas_std**2
            P[2, 2], P[3, 3] = o.init_speed_std**2, np.pi**2
            if lanes:
                m[3], P[3, 3] = lanes[0][1], sl2
            return m, P
        X = np.stack([np.ones_like(times), times - t], axis=1)  # position at t, velocity
        XtX_inv = np.linalg.inv(X.T @ X)
        coef = XtX_inv @ X.T @ zs  # (2, 2): rows (p, vel), columns (x, y)
        p, vel = coef
        C = o.meas_std**2 * XtX_inv  # the same for x and y (independent axes)
        # covariance of (px, py, vx, vy)
        Cp = np.zeros((4, 4))
        Cp[np.ix_([0, 2], [0, 2])] = C
        Cp[np.ix_([1, 3], [1, 3])] = C
        speed = float(np.hypot(*vel))
        th = math.atan2(vel[1], vel[0])
        J = np.zeros((4, 4))
        J[0, 0] = J[1, 1] = 1.0
        sp = max(speed, 1e-3)
        J[2, 2:] = vel / sp
        J[3, 2:] = np.array([-vel[1], vel[0]]) / sp**2
        Pc = J @ Cp @ J.T
        Pc[3, 3] = min(Pc[3, 3], np.pi**2)  # a slow track's heading is simply unknown
        for _, th_lane in lanes:  # nearest first: the first lane the fit agrees with
            u = np.array([math.cos(th_lane), math.sin(th_lane)])
            along, across = float(vel @ u), float(vel @ [-u[1], u[0]])
            sv = math.sqrt(C[1, 1])  # the fitted velocity's std, per axis
            if along < -_GATE * sv or abs(across) > _GATE * math.hypot(
                sv, abs(along) * o.lane_heading_std
            ):
                continue  # clearly against the lane, or across it: not following it
            w = sl2 / (sl2 + Pc[3, 3])
            th = float(_wrap(th_lane + w * float(_wrap(th - th_lane))))
            c, si = math.cos(th), math.sin(th)
            speed = max(float(vel @ [c, si]), 0.0)
            Pc[2, 2] = C[1, 1]  # the fit's velocity variance, along any direction
            Pc[3, 3] = w * Pc[3, 3]
            Pc[2, 3] = Pc[3, 2] = 0.0
            Pc[:2, 2:] = Pc[2:, :2] = 0.0
            Pc[:2, 2] = C[0, 1] * np.array([c, si])
            Pc[2, :2] = Pc[:2, 2]
            break
        m[:4] = p[0], p[1], speed, th
        P[:4, :4] = Pc
        # the accelerations the fit ignored over its time span
        span = float(times.max() - times.min())
        P[2, 2] += (o.accel_std * span) ** 2 / 3.0
        if self.nx == 4:
            P[3, 3] = min(P[3, 3] + (o.turn_std**2) * span * self.dt, np.pi**2)
        return m, P

    # ------------------------------------------------------------------ protocol
    def reset(self, obs: Observation, dt: float) -> Estimate:
        """Start one track per row of ``obs.others`` (``NaN`` rows start later)."""
        check_number("ukf.dt", dt, lo=0, lo_open=True)
        self.dt = float(dt)
        z = self._others(obs)
        n = len(z)
        H1 = self.options.history + 1
        self._k = 0
        self._filters: list[UnscentedKalmanFilter | None] = [None] * n
        self._meas: list[list[tuple[float, np.ndarray]]] = [[] for _ in range(n)]
        self._x = np.full((n, self.nx), np.nan)
        self._P = np.full((n, self.nx, self.nx), np.nan)
        self._hist = np.full((n, H1, 4), np.nan)
        self._valid = np.zeros((n, H1), dtype=bool)
        self._n = n
        self._updates = np.zeros(n, dtype=int)  # measurements incorporated per track
        self._prior: list[list[tuple[float, float]]] = [[] for _ in range(n)]
        self.rejected = 0
        return self._incorporate(z)

    def update(self, obs: Observation) -> Estimate:
        """Advance all tracks by one period and incorporate ``obs.others``."""
        if self.dt is None:
            raise SpecError("estimator", "update() called before reset()")
        z = self._others(obs)
        if len(z) != self._n:
            raise SpecError(
                "observation.others", f"expected {self._n} rows as at reset, got {len(z)}"
            )
        self._k += 1
        self._hist = np.roll(self._hist, -1, axis=1)
        self._valid = np.roll(self._valid, -1, axis=1)
        for i, f in enumerate(self._filters):  # a handful of agents
            if f is not None:
                f.Q = self._process_noise(f.x[3])
                _guarded(f.predict, f)
                _positive_speed(f.x, f.P)
                self._x[i], self._P[i] = f.x, f.P
        return self._incorporate(z)

    # ------------------------------------------------------------------ internals
    @staticmethod
    def _others(obs: Observation) -> np.ndarray:
        z = np.asarray(obs.others, dtype=np.float64)
        if z.ndim != 2 or z.shape[1] != 2:
            raise SpecError("observation.others", f"expected shape (N-1, 2), got {z.shape}")
        return z

    def _incorporate(self, z: np.ndarray) -> Estimate:
        o, t = self.options, self._k * self.dt
        with np.errstate(all="ignore"):
            seen = np.all(np.isfinite(z), axis=1)
            near = np.hypot(z[:, 0], z[:, 1]) <= o.max_position
            outlier = ~np.any(np.isnan(z), axis=1) & ~(seen & near)  # NaN: a dropout
        self.rejected += int(outlier.sum())
        seen &= ~outlier
        for i in np.flatnonzero(seen):
            f = self._filters[i]
            if f is not None:
                x, P = f.x.copy(), f.P.copy()
                try:
                    with np.errstate(all="ignore"):
                        _guarded(f.update, f, z[i])
                    good = bool(np.all(np.isfinite(f.x)) and np.all(np.isfinite(f.P)))
                except (ValueError, np.linalg.LinAlgError):
                    good = False
                if not good:  # an update that breaks the filter is an outlier too
                    f.x, f.P = x, P
                    self.rejected += 1
                    seen[i] = False
                    continue
                f.x[3] = _wrap(f.x[3])
                _positive_speed(f.x, f.P)
                self._x[i], self._P[i] = f.x, f.P
                self._updates[i] += 1
                continue
            if not self._meas[i] and o.lane_prior and self._lanes:
                self._prior[i] = _lane_directions(self._lanes, z[i], 2.0 * o.meas_std)
            self._meas[i].append((t, z[i].copy()))
            self._updates[i] += 1
            times = np.array([m[0] for m in self._meas[i]])
            zs = np.array([m[1] for m in self._meas[i]])
            self._x[i], self._P[i] = self._fit(times, zs, t, self._prior[i])
            if len(times) >= o.init_points:
                f = self._new_filter(self.dt)
                f.x, f.P = self._x[i].copy(), self._P[i].copy()
                self._filters[i] = f
        self._hist[:, -1] = self._x[:, :4]
        self._valid[:, -1] = seen
        states = self._x[:, :4].copy()
        cov = self._P[:, :4, :4].copy()
        with np.errstate(invalid="ignore"):
            trace = cov[:, 0, 0] + cov[:, 1, 1]
            converged = (self._updates >= o.converged_updates) & (trace <= o.converged_trace)
        return Estimate(
            states=states,
            covariances=cov,
            history=self._history(),
            valid=self._valid.copy(),
            converged=converged,
        )

    def _history(self) -> np.ndarray:
        """History with the rows before each track's start extrapolated backward."""
        h = self._hist.copy()
        have = np.all(np.isfinite(h), axis=2)  # (n, H+1)
        H1 = h.shape[1]
        first = np.where(have.any(axis=1), np.argmax(have, axis=1), H1)  # first row with data
        rows = np.arange(H1)
        for i in np.flatnonzero((first > 0) & (first < H1)):  # agents with a late start
            x0 = h[i, first[i]]
            back = (first[i] - rows[: first[i]]) * self.dt
            h[i, : first[i], 0] = x0[0] - x0[2] * np.cos(x0[3]) * back
            h[i, : first[i], 1] = x0[1] - x0[2] * np.sin(x0[3]) * back
            h[i, : first[i], 2:] = x0[2:]
        return h
