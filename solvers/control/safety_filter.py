"""The safety filter itself (:class:`SafetyFilter`), documented in
:mod:`solvers.control.safety`: per period it builds the obstacles and their chance margins from
the plan and the estimate, checks the tracker's command over the horizon, solves the QP that
keeps it clear (OSQP, set up once per structure) and falls back to the braking sequence when no
certified command is found."""

from __future__ import annotations

import logging
import math
import time
from statistics import NormalDist

import numpy as np
import osqp
import scipy.sparse as sp

from epo_casadi.errors import SpecError

from .safety_geometry import (
    _MATH,
    _cv,
    _heading,
    _Path,
    _rollout_function,
    _sample,
    _steer_scalar,
    _wrap,
    body_shapes,
)
from .safety_options import (
    _CV_HEADING_STD,
    _CV_SPEED_STD,
    _SAME_WAY,
    SPEED_TOL,
    TURN_DISC,
    SafetyOptions,
)
from .track import _csc, _options, reference, speed_floor, world_vehicle
from .types import Command, Plan
from .vehicle import VehicleModel

# the logger keeps the name of the module that documents the filter
_log = logging.getLogger("solvers.control.safety")


# ====================================================================== the filter
class SafetyFilter:
    """The safety filter between tracker and actuators (see the module docstring).

    ``SafetyFilter(horizon=20)`` or with a :class:`SafetyOptions`; :meth:`reset` before an
    episode, :meth:`filter` once per period. :meth:`filter` never raises on bad input: a
    command that is not two finite numbers is replaced by the fallback."""

    def __init__(self, options: SafetyOptions | dict | None = None, **kw):
        self.options = _options(SafetyOptions, options, kw, "filter")
        self.vehicle: VehicleModel | None = None
        self.setups = 0
        self.solver = None
        self._z_q = NormalDist().inv_cdf(self.options.quantile)
        self.last: dict = {}

    # ------------------------------------------------------------------ set-up
    def reset(self, world) -> None:
        """Read the vehicle, period, footprints and the ego's path; clear the counters."""
        vehicle, dt = world_vehicle(world)
        self.vehicle, self.dt = vehicle, dt
        self.ego_points, self.ego_radius, self.shapes = body_shapes(world, self.options.shape)
        self._np = min(len(self.ego_points), 2)  # QP rows per pair: the nearest two points
        self.n_others = int(world.n_agents) - 1
        task = world.ego_task
        self.path = _Path(task.path)
        self.v_task = float(task.speed) if math.isfinite(float(task.speed)) else 0.0
        N = self.options.horizon
        self._f = vehicle.function(self.dt).map(N)
        self._roll = _rollout_function(vehicle, self.dt, N, floor=False)
        self._roll_floor = _rollout_function(vehicle, self.dt, N, floor=True)
        lo, hi = vehicle.bounds()
        self._W = 1.0 / (hi - lo) ** 2
        self.u_prev = np.zeros(2)
        self.steps = self.interventions = self.fallbacks = self.uncertified = 0
        self.qp_iterations = 0
        self._cache: tuple | None = None  # the last usable predictions (pred, t0, dt, probs)
        self._slots = 0  # constraint slots of the QP structure (modes x others)
        self.solver = None
        self._prev = None  # the last period's sequence, when it met the constraints
        self.last = {}

    def applied(self, u: np.ndarray) -> None:
        """The command the actuators got (the rates of the next period count from it)."""
        u = np.asarray(u, dtype=float).reshape(-1)
        if u.shape == (2,) and np.all(np.isfinite(u)):
            self.u_prev = u.copy()

    # ------------------------------------------------------------------ constraints
    def _obstacles(self, obs, est, plan, times: np.ndarray):
        """Constrained modes: states ``(Mc, N-1, H, 4)`` (NaN: not constrained), their labels,
        and the position covariances ``(N-1, H, 2, 2)``."""
        o, J, H = self.options, self.n_others, len(times)
        t = float(obs.t)
        pred = None
        if isinstance(plan, Plan) and plan.predictions is not None:
            P = np.asarray(plan.predictions, dtype=float)
            w = plan.probabilities
            w = np.ones(len(P)) if w is None else np.asarray(w, dtype=float).reshape(-1)
            ok = P.ndim == 4 and P.shape[1] == J + 1 and P.shape[3] == 4 and P.shape[2] >= 1
            ok = ok and w.shape == (len(P),) and np.isfinite(plan.t0) and plan.dt > 0
            if ok:
                self._cache = (P[:, 1:], float(plan.t0), float(plan.dt), w)
        if self._cache is not None:
            pred, t0, pdt, w = self._cache
            w = np.where(np.isfinite(w) & (w > 0), w, 0.0)
            w = w / w.sum() if w.sum() > 0 else np.full(len(w), 1.0 / len(w))
            order = np.argsort(-w, kind="stable")
            keep = [int(i) for i in order if w[i] >= o.threshold or i == order[0]]
            keep = keep[: o.max_modes]
            modes = [_sample(pred[i], t0, pdt, times) for i in keep]
            labels: list = keep
        else:
            modes, labels = [], []
        states = cov = None
        if est is not None:
            try:
                states = np.asarray(est.states, dtype=float).reshape(J, 4)
                cov = np.asarray(est.covariances, dtype=float).reshape(J, 4, 4)
            except (AttributeError, ValueError, TypeError):
                states = cov = None
        tau = times - t
        S = np.zeros((J, H, 2, 2))
        self._sig_h = np.zeros(J)
        if states is not None:
            C3 = np.where(np.isfinite(cov[:, :3, :3]), cov[:, :3, :3], 0.0)
            Jk = np.zeros((J, H, 2, 3))
            Jk[..., 0, 0] = Jk[..., 1, 1] = 1.0
            th = np.where(np.isfinite(states[:, 3]), states[:, 3], 0.0)
            Jk[..., 0, 2] = tau[None] * np.cos(th)[:, None]
            Jk[..., 1, 2] = tau[None] * np.sin(th)[:, None]
            S = np.einsum("jhab,jbc,jhdc->jhad", Jk, C3, Jk)
            var_h = cov[:, 3, 3]
            self._sig_h = np.sqrt(np.where(np.isfinite(var_h) & (var_h > 0), var_h, 0.0))
            if o.constant_velocity or not modes:  # CV: asked for, or nothing else predicted
                x = states.copy()
                var_v, var_t = cov[:, 2, 2], cov[:, 3, 3]
                bad = ~(
                    np.isfinite(var_v)
                    & np.isfinite(var_t)
                    & (var_v <= _CV_SPEED_STD**2)
                    & (var_t <= _CV_HEADING_STD**2)
                )
                x[bad, 2] = 0.0
                modes.append(_cv(x[:, None, :], np.broadcast_to(tau, (J, H))))
                labels.append("cv")
        X = np.stack(modes) if modes else np.zeros((0, J, H, 4))
        if o.ignore_behind and states is not None and len(X):
            X[:, self._behind(obs.ego, states)] = np.nan
        return X, labels, S

    def _turned_bodies(self) -> np.ndarray:
        """The others' bodies ``(N-1, 3)`` for their heading's uncertainty: from ``z
        sigma_theta`` = :data:`TURN_DISC` on (a standing car, whose heading nothing
        measures) a body is the disc of radius ``rho + r`` (``rho = sqrt(a^2 + b^2)``, any
        heading); below, its rectangle as estimated."""
        a, b, r = self.shapes.T
        rho = np.hypot(a, b)
        phi = self._z_q * self._sig_h
        disc = phi >= TURN_DISC
        return np.stack(
            [np.where(disc, 0.0, a), np.where(disc, 0.0, b), np.where(disc, r + rho, r)], axis=1
        )

    def _behind(self, ego: np.ndarray, states: np.ndarray) -> np.ndarray:
        """``(N-1,)`` agents right behind the ego going its way (module docstring)."""
        h = _heading(np.array(ego[3]))
        d = states[:, :2] - ego[:2]
        along = d @ h
        lateral = np.abs(d @ np.array([-h[1], h[0]]))
        band = np.abs(self.ego_points[:, 1]).max() + self.ego_radius + self.shapes[:, 1:].sum(1)
        same = np.abs(_wrap(states[:, 3] - ego[3])) < _SAME_WAY
        with np.errstate(invalid="ignore"):
            return (along < 0) & (lateral < band) & same  # False where not finite

    def _geometry(self, X: np.ndarray):
        """For the ego states ``X`` ``(H, 4)`` and every (mode, other agent, step)
        ``(Mc, N-1, H)``: the chosen unit normal ``n`` ``(..., 2)``, the support ``s(n)`` of
        the other's inflated body (its farthest reach along ``n``:
        ``n' q + a |n' h| + b |n' h_perp| + r + min(z sqrt(n' S n), max_inflation)``) and
        ``min_i n' P_i - r_0 - s(n)`` over the ego's points ``P_i`` (see :meth:`clearance`)."""
        z, cap = self._z_q, self.options.max_inflation
        g = _heading(X[:, 3])  # (H, 2)
        gp = np.stack([-g[:, 1], g[:, 0]], axis=-1)
        v = self.ego_points
        P = X[:, None, :2] + v[None, :, :1] * g[:, None] + v[None, :, 1:] * gp[:, None]
        Q = self._obs  # (Mc, J, H, 4)
        a, b, r = (self._bodies[None, :, None, i] for i in range(3))  # (1, J, 1)
        h = _heading(Q[..., 3])  # (Mc, J, H, 2)
        hp = np.stack([-h[..., 1], h[..., 0]], axis=-1)
        S = np.broadcast_to(self._S[None], Q.shape[:3] + (2, 2))
        D = P[None, None] - Q[..., None, :2]  # (Mc, J, H, P, 2): ego points from q

        def value(n):
            sig = np.sqrt(np.maximum(np.einsum("...a,...ab,...b->...", n, S, n), 0.0))
            reach = (
                a * np.abs(np.einsum("...a,...a->...", n, h))
                + b * np.abs(np.einsum("...a,...a->...", n, hp))
                + r
                + np.minimum(z * sig, cap)
            )
            return np.einsum("...a,...pa->...p", n, D).min(axis=-1) - self.ego_radius - reach, reach

        shape = Q.shape[:3] + (2,)
        cands = [h, -h, hp, -hp]
        cands += [np.broadcast_to(w, shape) for w in (g, -g, gp, -gp)]
        c0 = X[:, :2][None, None] - Q[..., :2]
        cands.append(c0 / np.maximum(np.linalg.norm(c0, axis=-1, keepdims=True), 1e-12))
        # the normals at the closest points of the bare rectangle to each ego point
        ux = np.einsum("...pa,...a->...p", D, h)
        uy = np.einsum("...pa,...a->...p", D, hp)
        wx, wy = (
            ux - np.clip(ux, -a[..., None], a[..., None]),
            uy - np.clip(uy, -b[..., None], b[..., None]),
        )
        wn = np.maximum(np.hypot(wx, wy), 1e-12)
        for i in range(len(v)):
            ni = (wx[..., i] / wn[..., i])[..., None] * h + (wy[..., i] / wn[..., i])[
                ..., None
            ] * hp
            cands.append(np.where((wn[..., i] > 1e-9)[..., None], ni, h))
        best_n, (best_v, best_r) = cands[0], value(cands[0])
        for c in cands[1:]:
            val, reach = value(c)
            better = val > best_v
            best_n = np.where(better[..., None], c, best_n)
            best_v, best_r = np.where(better, val, best_v), np.where(better, reach, best_r)
        support = best_r + np.einsum("...a,...a->...", best_n, Q[..., :2])
        return best_n, support, best_v

    def clearance(self, X: np.ndarray) -> np.ndarray:
        """``(Mc, N-1, H)`` signed clearances of the ego states ``X`` ``(H, 4)`` to the last
        period's constrained modes (``inf`` where not constrained): the largest, over a few
        unit normals ``n``, of ``min_i n' (P_i - q) - r_0 - a |n' h| - b |n' h_perp| - r -
        min(z sqrt(n' S n), max_inflation) - margin``, with ``P_i`` the ego's points
        (corners, or circle centres of radius ``r_0``) and ``(a, b, r)`` the other's rounded
        rectangle at ``q`` with heading ``h``. Each unit ``n`` is a separating direction, so
        each gives a lower bound of the exact clearance (the maximum over all ``n``: the
        distance from the ego's body to the other's grown by the capped uncertainty
        ellipse, or minus the penetration); the candidates are both bodies' axes, the
        centre-to-centre direction and the normals at the points of the other's rectangle
        closest to the ego's points. The check asks for ``>= 0``."""
        if self._obs.shape[0] == 0:
            return np.full((0, self.n_others, len(X)), np.inf)
        *_, val = self._geometry(X)
        c = val - self.options.margin
        return np.where(np.isfinite(c), c, np.inf)

    def _check(self, X: np.ndarray) -> tuple[bool, float]:
        """Whether the rollout ``X`` ``(H, 4)`` meets every constraint; its smallest clearance."""
        c = self.clearance(X)
        cmin = float(c.min()) if c.size else math.inf
        ok = bool(np.all(X[:, 2] >= -SPEED_TOL) and cmin >= 0.0 and np.all(np.isfinite(X)))
        return ok, cmin

    # ------------------------------------------------------------------ sequences
    def _rollout(self, ego: np.ndarray, U: np.ndarray, floor: bool = False):
        """States ``(H, 4)`` after the commands ``U`` ``(H, 2)`` on the vehicle model; with
        ``floor`` each acceleration that would take the speed below zero is first raised to
        the one that stops it (at most ``a_max``). Returns the states and the commands."""
        fn = self._roll_floor if floor else self._roll
        X, Uf = fn(np.asarray(ego, dtype=float), np.asarray(U, dtype=float).T)
        return np.asarray(X).T.copy(), np.asarray(Uf).T.copy()

    def _nominal(self, ego: np.ndarray, plan, command: np.ndarray, info: dict, t: float):
        """The nominal sequence ``(H, 2)`` (module docstring, step 1)."""
        veh, dt, N = self.vehicle, self.dt, self.options.horizon
        U = np.empty((N, 2))
        U[0] = command
        n = 1
        seq = info.get("sequence") if isinstance(info, dict) else None
        if seq is not None:
            seq = np.asarray(seq, dtype=float)
            if seq.ndim == 2 and seq.shape[1] == 2 and len(seq) > 1 and np.all(np.isfinite(seq)):
                n = min(len(seq), N)
                U[1:n] = veh.clip(seq[1:n])
        if n >= N:
            return U
        usable = isinstance(plan, Plan) and plan.ok
        if usable:
            S, C = np.asarray(plan.states), np.asarray(plan.controls)
            usable = (
                S.ndim == 2
                and S.shape[1:] == (4,)
                and C.shape == (len(S), 2)
                and len(S) > 0
                and np.all(np.isfinite(S))
                and np.all(np.isfinite(C))
                and math.isfinite(plan.t0)
                and math.isfinite(plan.dt)
                and plan.dt > 0
            )
        lo, hi = veh.bounds()
        if usable:
            _, ubar = reference(plan, t, dt, N)
        x = [float(v) for v in ego]
        for k in range(N):  # sequential by nature (each command from the state it meets)
            if k >= n:
                v = x[2]
                if usable:
                    a, s = ubar[k, 0], _steer_scalar(veh, v, ubar[k, 1])
                else:  # brake to a stop, steering held
                    a = max(veh.a_min, -v / dt) if v > 0 else min(veh.a_max, -v / dt)
                    s = U[k - 1, 1]
                U[k] = min(max(a, lo[0]), hi[0]), min(max(s, lo[1]), hi[1])
            x = list(veh._integrate(*x, U[k, 0], U[k, 1], dt, _MATH))
        return U

    #: the fallback candidates in the order they are tried: (name, acceleration target as
    #: a factor of a_min (braking) or of a_max (going), steering: "lane" or "straight")
    FALLBACKS = (
        ("brake", -1.0, "lane"),
        ("brake_half", -0.5, "lane"),
        ("hold", 0.0, "lane"),
        ("go", 1.0, "lane"),
        ("brake_straight", -1.0, "straight"),
    )

    def _fallback(self, ego: np.ndarray):
        """The fallback candidates (module docstring, step 3): the chosen commands, states,
        whether certified, its smallest clearance, its name."""
        veh, dt, N = self.vehicle, self.dt, self.options.horizon
        rate = veh.steer_rate_max * dt
        smax = veh.steer_max
        path = self.path
        finite = bool(np.all(np.isfinite(ego)))
        seg0 = path.segment(np.asarray(ego[:2], dtype=float)) if finite else 0
        best = None
        for name, factor, steering in self.FALLBACKS:
            target = factor * (veh.a_max if factor > 0 else -veh.a_min)
            U = np.empty((N, 2))
            x = [float(v) for v in ego] if finite else [0.0, 0.0, 0.0, 0.0]
            steer = min(max(float(self.u_prev[1]), -smax), smax)
            seg = seg0
            for k in range(N):  # sequential by nature (pure pursuit on the ego's path)
                v = x[2]
                if target <= 0:
                    a = max(target, -v / dt) if v > 0 else min(veh.a_max, -v / dt)
                else:
                    a = min(max((self.v_task - v) / dt, min(0.0, veh.a_min)), target)
                if steering == "lane":
                    look = max(3.0, abs(v))
                    seg, s = path.advance(seg, x[0], x[1])
                    tx, ty = path.point_from(seg, s + look)
                    alpha = math.atan2(ty - x[1], tx - x[0]) - x[3]
                    alpha = (alpha + math.pi) % (2 * math.pi) - math.pi
                    want = _steer_scalar(veh, v, v * 2.0 * math.sin(alpha) / look)
                else:
                    want = 0.0
                steer = min(max(want, steer - rate, -smax), steer + rate, smax)
                U[k, 0], U[k, 1] = a, steer
                x = list(veh._integrate(*x, a, steer, dt, _MATH))
            X, _ = self._rollout(ego if finite else np.zeros(4), U)
            ok, cmin = self._check(X) if finite else (False, -math.inf)
            if ok:
                return U, X, True, cmin, name
            if best is None or cmin > best[3]:
                best = (U, X, False, cmin, name)
        return best

    # ------------------------------------------------------------------ the QP
    def _setup(self, slots: int) -> None:
        """OSQP on the structure of ``slots`` (modes x others) constraint slots: the QP in
        the commands alone (the linearized states eliminated), rows ``box (2N)``, ``rates
        (2N)``, ``speeds (N)``, ``collision (N x slots x P)``; the speed and collision rows
        of step ``k`` (state ``x_{k+1}``) depend on ``u_0..u_k``."""
        o, N, nP = self.options, self.options.horizon, self._np
        rows = [np.arange(2 * N), 2 * N + np.arange(2 * N), 2 * N + np.arange(2, 2 * N)]
        cols = [np.arange(2 * N), np.arange(2 * N), np.arange(2 * N - 2)]
        lower = np.arange(2 * N)[None, :] < 2 * (np.arange(N)[:, None] + 1)  # (N, 2N)
        self._lower_speed = lower
        self._lower_coll = np.repeat(lower[:, None, :], slots * nP, axis=1)
        r_speed = 4 * N + np.arange(N)
        r_coll = 5 * N + np.arange(N * slots * nP).reshape(N, slots * nP)
        kk, jj = np.nonzero(lower)
        rows.append(r_speed[kk])
        cols.append(jj)
        kk, ss, jj = np.nonzero(self._lower_coll)
        rows.append(r_coll[kk, ss])
        cols.append(jj)
        A_rows, A_cols = np.concatenate(rows), np.concatenate(cols)
        self._m = 5 * N + N * slots * nP
        self._A, self._A_perm = _csc(A_rows, A_cols, np.ones(len(A_rows)), (self._m, 2 * N))
        Pd = 100.0 * np.tile(self._W, N)  # x100: OSQP converges faster on this scale
        Pd[:2] *= o.w_first
        self._Pd = Pd
        self.solver = osqp.OSQP()
        self.solver.setup(
            sp.diags(Pd, format="csc"),
            np.zeros(2 * N),
            self._A,
            np.full(self._m, -np.inf),
            np.full(self._m, np.inf),
            eps_abs=o.eps_abs,
            eps_rel=o.eps_rel,
            max_iter=o.max_iter,
            polishing=False,
            warm_starting=o.warm_start,
            adaptive_rho_interval=25,
            verbose=False,
        )
        self.setups += 1
        self._slots = slots
        self._y = None  # the last solution's duals (a warm start of the same structure)

    def _collision_rows(self, Xroll: np.ndarray, Mc: int, J: int):
        """``(coef, lb)``, ``(N, slots, P, 3)`` and ``(N, slots, P)``: the collision rows of the
        QP linearized along the rollout ``Xroll`` (their coefficients on ``x, y, theta`` of
        ``x_{k+1}``, their lower bounds; unused slots and rows of non-finite geometry are
        ``0 >= -inf``)."""
        o, N, nP, S = self.options, self.options.horizon, self._np, self._slots
        # collision rows (k, slot = m * J + j, ego point i): n' P_i(x_{k+1}) >= s(n) + r_0 +
        # margin + buffer, P_i(x) = p + R(theta) v_i linearized in theta at the rollout
        coef = np.zeros((N, S, nP, 3))
        lb = np.full((N, S, nP), -np.inf)
        if Mc:
            n, support, _ = self._geometry(Xroll)  # (Mc, J, N, ...)
            v = self.ego_points
            th = Xroll[:, 3]
            ct, st = np.cos(th)[:, None], np.sin(th)[:, None]
            Rv = np.stack([v[:, 0] * ct - v[:, 1] * st, v[:, 0] * st + v[:, 1] * ct], -1)
            dR = np.stack([-v[:, 0] * st - v[:, 1] * ct, v[:, 0] * ct - v[:, 1] * st], -1)
            nRv = np.einsum("mjha,hpa->mjhp", n, Rv)
            dth = np.einsum("mjha,hpa->mjhp", n, dR)
            if nP < len(v):  # the points nearest the other body along n (the box: 2 of 4)
                pick = np.argsort(nRv, axis=-1)[..., :nP]
                nRv = np.take_along_axis(nRv, pick, axis=-1)
                dth = np.take_along_axis(dth, pick, axis=-1)
            bound = (
                support[..., None]
                + self.ego_radius
                + o.margin
                + o.buffer
                - nRv
                + dth * th[None, None, :, None]
            )
            valid = np.isfinite(bound) & np.isfinite(dth)
            tr = (2, 0, 1, 3)  # (Mc, J, N, P) -> (N, Mc * J, P)
            nx = np.broadcast_to(n[..., None, 0], valid.shape)
            ny = np.broadcast_to(n[..., None, 1], valid.shape)
            parts = [
                np.where(valid, w, 0.0).transpose(tr).reshape(N, Mc * J, nP) for w in (nx, ny, dth)
            ]
            coef[:, : Mc * J] = np.stack(parts, axis=-1)
            lb[:, : Mc * J] = np.where(valid, bound, -np.inf).transpose(tr).reshape(N, Mc * J, nP)
        return coef, lb

    def _solve_qp(self, ego: np.ndarray, Ubar: np.ndarray, Unom: np.ndarray, Xroll: np.ndarray):
        """One QP linearized along ``(Xroll, Ubar)`` and warm-started there; its commands
        ``(N, 2)`` or None, and OSQP's status."""
        o, N, veh, nP = self.options, self.options.horizon, self.vehicle, self._np
        Mc, J = self._obs.shape[:2]
        slots = max(Mc * J, 1)
        if self.solver is None or slots > self._slots:
            self._setup(slots)
        S = self._slots
        Xbar = np.concatenate([ego[None], Xroll[:-1]])
        xn, A, B = self._f(Xbar.T, Ubar.T)
        xn = np.asarray(xn).T
        A = np.asarray(A).reshape(4, N, 4).transpose(1, 0, 2)
        B = np.asarray(B).reshape(4, N, 2).transpose(1, 0, 2)
        c = xn - np.einsum("kij,kj->ki", A, Xbar) - np.einsum("kij,kj->ki", B, Ubar)
        # x_{k+1} = F_k + G_k U (the linearized dynamics rolled out from the ego state)
        F = np.empty((N, 4))
        G = np.zeros((N, 4, 2 * N))
        f, g = ego, np.zeros((4, 2 * N))
        for k in range(N):  # sequential by nature (a recursion over the horizon)
            f = A[k] @ f + c[k]
            g = A[k] @ g
            g[:, 2 * k : 2 * k + 2] += B[k]
            F[k], G[k] = f, g
        umin, umax = veh.bounds()
        r = veh.rate_bounds(self.dt)
        lo = np.full(self._m, -np.inf)
        hi = np.full(self._m, np.inf)
        lo[: 2 * N], hi[: 2 * N] = np.tile(umin, N), np.tile(umax, N)
        lo[2 * N : 2 * N + 2], hi[2 * N : 2 * N + 2] = self.u_prev - r, self.u_prev + r
        lo[2 * N + 2 : 4 * N], hi[2 * N + 2 : 4 * N] = np.tile(-r, N - 1), np.tile(r, N - 1)
        floor = speed_floor(veh, self.dt, N, float(ego[2]), float(self.u_prev[0]))
        lo[4 * N : 5 * N] = floor - F[:, 2]
        coef, lb = self._collision_rows(Xroll, Mc, J)
        coef = coef.reshape(N, S * nP, 3)
        Gp = G[:, [0, 1, 3], :]  # (N, 3, 2N): x, y, theta
        lo[5 * N :] = (
            lb.reshape(N, S * nP) - np.einsum("ksc,kc->ks", coef, F[:, [0, 1, 3]])
        ).ravel()
        M = np.einsum("ksc,kcj->ksj", coef, Gp)
        Av = np.concatenate(
            [
                np.ones(2 * N),
                np.ones(2 * N),
                -np.ones(2 * N - 2),
                G[:, 2, :][self._lower_speed],
                M[self._lower_coll],
            ]
        )
        qv = -(self._Pd * Unom.ravel())
        if not (np.all(np.isfinite(Av)) and np.all(np.isfinite(qv)) and not np.any(np.isnan(lo))):
            return None, "QP numbers not finite"
        self.solver.update(q=qv, l=lo, u=hi, Ax=Av[self._A_perm])
        if o.warm_start:
            if self._y is not None:
                self.solver.warm_start(x=Ubar.ravel(), y=self._y)
            else:
                self.solver.warm_start(x=Ubar.ravel())
        res = self.solver.solve(raise_error=False)
        self.qp_iterations += int(res.info.iter)
        status = str(res.info.status)
        solved = res.info.status_val in (
            osqp.SolverStatus.OSQP_SOLVED,
            osqp.SolverStatus.OSQP_SOLVED_INACCURATE,
        )
        if not solved or res.x is None or not np.all(np.isfinite(res.x)):
            self._y = None
            return None, status
        self._y = res.y.copy() if res.y is not None and np.all(np.isfinite(res.y)) else None
        return res.x.reshape(N, 2).copy(), status

    # ------------------------------------------------------------------ the step
    def filter(self, obs, est, plan, command: Command) -> Command:
        """What the actuators get this period: ``command`` (the tracker's) filtered against
        the constraints (module docstring); ``plan`` may be None or failed."""
        if self.vehicle is None:
            raise SpecError("filter", "SafetyFilter.filter() called before reset(world)")
        tic = time.perf_counter()
        o, N, veh, dt = self.options, self.options.horizon, self.vehicle, self.dt
        self.steps += 1
        ego = np.asarray(obs.ego, dtype=float).reshape(4)
        t = float(obs.t)
        u_nom = np.asarray(getattr(command, "value", np.full(2, np.nan)), dtype=float).reshape(-1)
        info_in = dict(getattr(command, "info", {}) or {})
        times = t + dt * np.arange(1, N + 1)
        self._obs, labels, self._S = self._obstacles(obs, est, plan, times)
        self._bodies = self._turned_bodies()
        self.last = {
            "times": times,
            "obstacles": self._obs,
            "ego_points": self.ego_points,
            "ego_radius": self.ego_radius,
            "shapes": self.shapes,
            "bodies": self._bodies,
            "cov": self._S,
            "z": self._z_q,
            "modes": labels,
        }
        qp, status, reason = 0, "", ""
        fallback = False
        span = veh.bounds()[1] - veh.bounds()[0]
        good = u_nom.shape == (2,) and np.all(np.isfinite(u_nom)) and np.all(np.isfinite(ego))
        if good:
            u_nom = veh.clip(u_nom)
            Unom = self._nominal(ego, plan, u_nom, info_in, t)
            X, _ = self._rollout(ego, Unom)
            ok, cmin = self._check(X)
            U = Unom
            if ok:
                status, reason = "nominal safe", "the nominal sequence meets the constraints"
            else:
                fb = self._fallback(ego)
                Ubar, Xroll = self._linearization(ego, fb)
                for _ in range(o.iterations):
                    Uq, status = self._solve_qp(ego, Ubar, Unom, Xroll)
                    qp += 1
                    if Uq is None:
                        reason = f"QP not solved: {status}"
                        break
                    Xq, Uq = self._rollout(ego, self._clip_chain(Uq), floor=True)
                    ok, cmin = self._check(Xq)
                    if ok:
                        U, X = Uq, Xq
                        reason = "QP solution"
                        if np.all(np.abs(U[0] - u_nom) <= o.tolerance * span):
                            # within the tolerance: the nominal command itself, if it checks
                            Us = U.copy()
                            Us[0] = u_nom
                            Xs, _ = self._rollout(ego, Us)
                            ok_s, c_s = self._check(Xs)
                            if ok_s:
                                U, X, cmin = Us, Xs, c_s
                                reason = "QP solution, the nominal command kept"
                        break
                    Ubar, Xroll = Uq, Xq
                    reason = f"QP solution fails the check (clearance {cmin:.3f} m)"
        else:
            reason = f"command not two finite numbers: {u_nom!r}"
            ok, fb = False, None
        if not ok:
            fallback = True
            U, X, ok, cmin, name = fb if fb is not None else self._fallback(ego)
            reason = f"{reason}; fallback {name}" + ("" if ok else " (not certified)")
            self.fallbacks += 1
            self.uncertified += not ok
            _log.info("safety filter fell back: %s", reason)
        u = U[0].copy()
        changed = bool(fallback or not good or np.any(np.abs(u - u_nom) > o.tolerance * span))
        self.interventions += changed
        self.u_prev = u.copy()
        self._prev = U.copy() if ok else None
        info = {
            **info_in,
            "safety": {
                "intervened": changed,
                "fallback": fallback,
                "certified": bool(ok),
                "reason": reason,
                "nominal": u_nom.copy(),
                "sequence": U,
                "states": X,
                "clearance": cmin,
                "modes": labels,
                "qp": qp,
                "status": status,
                "seconds": time.perf_counter() - tic,
            },
        }
        was_fallback = bool(getattr(command, "fallback", False))
        return Command(value=u, fallback=fallback or was_fallback, info=info)

    def _linearization(self, ego: np.ndarray, fb: tuple):
        """Where the QP is linearized when the nominal sequence is unsafe: the last period's
        sequence shifted by one step where it still meets the constraints, else the
        fallback's candidate (never the nominal rollout, which may have driven through an
        obstacle and would put the half-planes on its far side)."""
        prev = self._prev
        if prev is not None:
            Xs, Us = self._rollout(ego, np.concatenate([prev[1:], prev[-1:]]), floor=True)
            if self._check(Xs)[0]:
                return Us, Xs
        return fb[0], fb[1]

    def _clip_chain(self, U: np.ndarray) -> np.ndarray:
        """``U`` projected onto the box and the rates, step by step from ``u_prev``."""
        veh, dt = self.vehicle, self.dt
        out = np.empty_like(U)
        prev = self.u_prev
        for k in range(len(U)):
            out[k] = veh.clip(U[k], prev, dt)
            prev = out[k]
        return out
