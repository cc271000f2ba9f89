"""TGL baseline (Geiger & Straehle 2021): a convex energy with hard constraints, solved by OSQP.

TGL learns a game whose potential is a *linear combination of convex features*,
``E_w(u) = sum_j w_j c_j(u)``, solved to convergence and differentiated by the implicit
function theorem (paper Sec. 2, Tab. 1: "Convex, GB, IFT"; hard inequality constraints).
Here every problem (one scene mode) is the quadratic program

    minimize_z  1/2 z' P z + q' z     subject to  l <= A z <= u,     z = (U, s),

in all agents' controls ``U`` ``(N, K, 2)`` (acceleration, turn rate; index order of the
contract in :mod:`epo_casadi.game`) and one slack ``s >= 0`` per collision check:

Dynamics
    each unicycle is linearized around its constant-velocity rollout from the current state
    (``v_k = v_0``, ``theta_k = theta_0``), which makes positions, speeds and headings affine
    in ``U`` (:func:`linear_dynamics`); the explicit Euler steps of the game otherwise.
Features (weights predicted per agent and mode, non-negative)
    goal ``||p_K - g||^2`` (predicted goal ``g``), speed tracking
    ``sum_k (v_k - v_ref)^2`` (predicted ``v_ref``), acceleration ``sum a^2``, turn rate
    ``sum omega^2``, jerk ``sum ((a_{k+1} - a_k) / dt)^2``; per agent pair the slack
    ``sum s^2``. Acceleration, turn-rate and slack weights get a floor of
    :data:`WEIGHT_FLOOR`, so ``P`` is positive definite and the solution unique.
Hard constraints
    acceleration and turn-rate boxes (the game's ``acceleration_bound`` /
    ``turn_rate_bound`` features, else :data:`DEFAULT_BOUNDS`), speed within the game's
    ``velocity_bound`` (widened to contain ``v_0``, so ``U = 0`` is always feasible), and
    the linearized collision half-space at the game's collision steps
    ``n' (p_i,k - p_j,k) + s >= r_i + r_j + margin``, ``s >= 0``, with ``n`` the unit
    direction between the two agents on their reference rollouts. The QP is always
    feasible and strictly convex.

Solve and derivatives (:func:`solve_qp`, :class:`QPFunction`)
    OSQP 1.1.3 (``eps = 1e-4``, no scaling: measured ~6x fewer iterations here) solves each
    problem: a Python loop over the ``B`` problems, in the solve call only, one OSQP object
    per batch whose matrices are updated in place. Its multipliers give an active set that
    a batched primal-dual active-set iteration in float64 corrects until the KKT conditions
    hold to rounding (stationarity by construction; feasibility and the multipliers' signs
    checked): a certificate of optimality independent of OSQP's tolerance. Problems not
    certified are solved again by OSQP at ``1e-9`` with polishing, then iterated once more;
    one still not certified keeps OSQP's iterate, reports it in ``status`` and gets no
    gradient. The backward pass reuses the LU factors of the final KKT system
    ``[[P, A_a'], [A_a, -I_inactive]]`` (implicit function theorem on the KKT conditions):
    ``K v = [dL/dz, 0]`` gives ``dL/dq = -v_z``, ``dL/dP = -(v_z z' + z v_z')/2`` and
    ``dL/dl``, ``dL/du`` ``= v_lambda`` on the active lower/upper rows. OSQP's own
    ``adjoint_derivative_compute`` (present in 1.1.3) is not used: it works one problem at a
    time on OSQP's approximate active set.

:class:`TGLModel` is ``--model tgl``: a backbone (:mod:`learning.backbones`, V-LSTM by
default), decoders for the feature weights and the references (goal, reference speed)
of every agent and mode, the QP layer, and the scene-probability decoder of the other
scene models; trained with the scene loss like V-LSTM + SC.

A padded agent (scene ``agents_mask`` False, :mod:`learning.masks`) starts from the neutral
scene (at rest, far from every real agent), gets zero feature weights (only the
:data:`WEIGHT_FLOOR` of its acceleration and turn rate, which keeps ``P`` positive definite),
zero reference offsets (its goal is its position, its reference speed 0) and zero pair
weights (the slack floor only): its own block of ``q`` is zero, its collision half-spaces are
inactive (it is :data:`learning.masks.PAD_SPACING` away), so its controls are 0 and the real
agents' problem is the one without it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import osqp
import scipy.sparse as sp
import torch
from torch import nn

from epo_casadi.errors import SpecError
from epo_casadi.features import AccelerationBound, Collision, TurnRateBound, VelocityBound
from epo_casadi.game import PotentialGame

from . import masks as _masks
from .models import _Base, mlp

__all__ = [
    "DEFAULT_BOUNDS",
    "OWN_FEATURES",
    "QPFunction",
    "QPStatus",
    "TGLModel",
    "TGLProblem",
    "linear_dynamics",
    "solve_qp",
]

#: TGL's per-agent features, in the order of the weight vector
OWN_FEATURES = ("goal", "velocity", "acceleration", "turn_rate", "jerk")
#: lower bound added to the acceleration, turn-rate and slack weights (strict convexity)
WEIGHT_FLOOR = 1e-3
#: control boxes when the game has no bound features: acceleration (m/s^2), turn rate (rad/s)
DEFAULT_BOUNDS = {"acceleration": (-3.0, 3.0), "turn_rate": (-1.5, 1.5)}
_INF = 1e20  # OSQP's infinity is 1e30; any |bound| >= this is "no bound"


class QPStatus:
    """Per-problem status codes of :func:`solve_qp`."""

    SOLVED = 0  #: OSQP solved and the active-set KKT refinement was consistent
    OSQP_ONLY = 1  #: OSQP solved; its solution kept (refinement inconsistent)
    FAILED = 2  #: OSQP did not solve the problem (its iterate is returned)


# --------------------------------------------------------------------------------------
# the batched QP and its implicit derivatives
# --------------------------------------------------------------------------------------
def _csc_pattern(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSC ``indptr``, ``indices`` of a boolean pattern, and the flat positions of its entries."""
    cols, rows = np.nonzero(mask.T)  # entries sorted by column, then row
    indptr = np.zeros(mask.shape[1] + 1, dtype=np.int64)
    np.add.at(indptr, cols + 1, 1)
    return np.cumsum(indptr), rows.astype(np.int64), rows * mask.shape[1] + cols


def _osqp_solve(P, q, A, lo, hi, eps: float, max_iter: int, polish: bool = False):
    """OSQP on every problem of a batch (numpy float64). Returns ``z``, ``y``, ``ok``."""
    B, n = q.shape
    m = A.shape[1]
    pmask = np.triu(np.any(P != 0, axis=0) | np.eye(n, dtype=bool))
    amask = np.any(A != 0, axis=0)
    p_ptr, p_ind, p_pos = _csc_pattern(pmask)
    a_ptr, a_ind, a_pos = _csc_pattern(amask)
    Pf, Af = P.reshape(B, -1), A.reshape(B, -1)
    lo, hi = np.clip(lo, -1e30, 1e30), np.clip(hi, -1e30, 1e30)
    solver = osqp.OSQP()
    solver.setup(
        sp.csc_matrix((Pf[0, p_pos], p_ind, p_ptr), shape=(n, n)),
        q[0],
        sp.csc_matrix((Af[0, a_pos], a_ind, a_ptr), shape=(m, n)),
        lo[0],
        hi[0],
        verbose=False,
        polishing=polish,  # solve_qp's active-set iteration makes the solution exact
        scaling=0,  # measured: ~6x fewer ADMM iterations on these problems than the default 10
        eps_abs=eps,
        eps_rel=eps,
        max_iter=max_iter,
    )
    z = np.zeros((B, n))
    y = np.zeros((B, m))
    ok = np.zeros(B, dtype=bool)
    solved = osqp.SolverStatus.OSQP_SOLVED
    for b in range(B):  # the only loop over problems: one OSQP solve each
        if b:
            solver.update(Px=Pf[b, p_pos], Ax=Af[b, a_pos], q=q[b], l=lo[b], u=hi[b])
        res = solver.solve(raise_error=False)
        ok[b] = res.info.status_val == solved
        if res.x is not None and np.all(np.isfinite(res.x)):
            z[b], y[b] = res.x, res.y
    return z, y, ok


def _kkt(P, A, act, inact):
    """The active-set KKT matrices ``[[P, A_a'], [A_a, -diag(inactive)]]`` ``(B, n+r, n+r)``."""
    B, r, n = A.shape
    K = P.new_zeros(B, n + r, n + r)
    Aa = A * act[..., None].to(A.dtype)
    K[:, :n, :n] = P
    K[:, n:, :n] = Aa
    K[:, :n, n:] = Aa.transpose(1, 2)
    K[:, n:, n:].diagonal(dim1=1, dim2=2).copy_(-inact.to(A.dtype))
    return K


def _active_sets(y, lo, hi):
    """Active lower / upper rows from OSQP's multipliers ``y`` (negative: lower bound)."""
    ytol = 1e-6 * (1 + y.abs().amax(1, keepdim=True))
    lower = (y < -ytol) & (lo > -_INF)
    upper = (y > ytol) & (hi < _INF) & ~lower
    return lower, upper


def _active_set_iteration(P, q, A, lo, hi, lower, upper, steps: int) -> dict:
    """Batched primal-dual active-set steps: solve the KKT system of the active rows (the
    rows active in some problem, ``-1`` on the diagonal where inactive), add violated rows,
    drop rows whose multiplier has the wrong sign; stop when every problem is certified."""
    B, n = q.shape
    ptol = 1e-9 * (1 + lo.abs().clamp(max=1e6) + hi.abs().clamp(max=1e6))
    for _ in range(steps):
        act = lower | upper
        rows = torch.nonzero(act.any(0)).flatten()
        a_r, lo_r, up_r = act[:, rows], lower[:, rows], upper[:, rows]
        K = _kkt(P, A[:, rows], a_r, ~a_r)
        b = torch.where(lo_r, lo[:, rows], torch.where(up_r, hi[:, rows], 0.0))
        LU, piv, info = torch.linalg.lu_factor_ex(K)
        sol = torch.linalg.lu_solve(LU, piv, torch.cat([-q, b], 1)[..., None])[..., 0]
        z, lam = sol[:, :n], sol[:, n:]
        Az = (A @ z[..., None])[..., 0]
        viol_lo = (Az < lo - ptol) & ~lower
        viol_hi = (Az > hi + ptol) & ~upper
        ltol = 1e-9 * (1 + lam.abs().amax(1, keepdim=True))
        drop = torch.zeros_like(lower)
        drop[:, rows] = (lo_r & (lam > ltol)) | (up_r & (lam < -ltol))
        finite = torch.isfinite(sol).all(1) & (info == 0)
        done = finite & ~(viol_lo | viol_hi | drop).any(1)
        if bool(done.all()):
            break
        todo = (~done & finite)[:, None]
        lower = torch.where(todo, (lower & ~drop) | viol_lo, lower)
        upper = torch.where(todo, (upper & ~drop) | viol_hi, upper)
    return {"z": z, "done": done, "lower": lower, "upper": upper, "rows": rows, "lu": (LU, piv)}


def solve_qp(
    P,
    q,
    A,
    lo,
    hi,
    eps: float = 1e-4,
    max_iter: int = 4000,
    active_set_steps: int = 5,
    fallback: bool = True,
) -> dict:
    """Solve ``min 1/2 z'Pz + q'z s.t. lo <= Az <= hi`` for a batch (torch float64, no grad).

    OSQP (tolerance ``eps``, at most ``max_iter`` iterations) solves each problem; its
    multipliers give a first active set, which a batched primal-dual active-set iteration
    (at most ``active_set_steps`` KKT solves) corrects until the KKT conditions hold to
    rounding: stationarity (by construction), feasibility and the multipliers' signs. A
    certified point is the optimum whatever OSQP's accuracy. Problems not certified
    (``fallback``) are solved again by OSQP at tolerance ``1e-9`` with its polishing, and
    the iteration runs once more.

    Returns ``z`` ``(B, n)``, the active masks ``lower``/``upper`` ``(B, m)``, ``rows`` (the
    constraint rows of the final KKT system), its LU factors ``lu`` and ``status`` ``(B,)``
    (:class:`QPStatus`; not certified: OSQP's iterate).
    """
    dev, f64 = q.device, torch.float64
    P, q, A, lo, hi = (t.detach().to(f64) for t in (P, q, A, lo, hi))
    data = [t.cpu().numpy() for t in (P, q, A, lo, hi)]
    z0, y0, ok = _osqp_solve(*data, eps=eps, max_iter=max_iter)
    z0 = torch.as_tensor(z0, device=dev, dtype=f64)
    y0 = torch.as_tensor(y0, device=dev, dtype=f64)
    ok = torch.as_tensor(ok, device=dev)
    lower, upper = _active_sets(y0, lo, hi)
    res = _active_set_iteration(P, q, A, lo, hi, lower, upper, active_set_steps)
    if fallback and not bool(res["done"].all()):
        idx = torch.nonzero(~res["done"]).flatten()
        sub = [d[idx.cpu().numpy()] for d in data]
        z1, y1, ok1 = _osqp_solve(*sub, eps=1e-9, max_iter=max(max_iter, 20000), polish=True)
        z0[idx] = torch.as_tensor(z1, device=dev, dtype=f64)
        y0[idx] = torch.as_tensor(y1, device=dev, dtype=f64)
        ok[idx] = torch.as_tensor(ok1, device=dev)
        lower, upper = res["lower"].clone(), res["upper"].clone()
        lower[idx], upper[idx] = _active_sets(y0[idx], lo[idx], hi[idx])
        res = _active_set_iteration(P, q, A, lo, hi, lower, upper, active_set_steps)
    done = res["done"]
    status = torch.full(done.shape, QPStatus.SOLVED, dtype=torch.long, device=dev)
    status[~done] = QPStatus.OSQP_ONLY
    status[~done & ~ok] = QPStatus.FAILED
    return {
        "z": torch.where(done[:, None], res["z"], z0),
        "lower": res["lower"],
        "upper": res["upper"],
        "rows": res["rows"],
        "lu": res["lu"],
        "status": status,
    }


class QPFunction(torch.autograd.Function):
    """``z, status = QPFunction.apply(P, q, A, lo, hi)``: batched QP solutions, IFT gradients.

    ``P`` ``(B, n, n)`` symmetric positive definite, ``q`` ``(B, n)``, ``A`` ``(B, m, n)``
    (treated as data: no gradient), ``lo``, ``hi`` ``(B, m)``. Gradients flow to ``P``,
    ``q``, ``lo`` and ``hi`` (see the module docstring); ``status`` ``(B,)`` is
    :class:`QPStatus` (no gradient).
    """

    @staticmethod
    def forward(ctx, P, q, A, lo, hi):
        out = solve_qp(P, q, A, lo, hi)
        ctx.lu, ctx.rows = out["lu"], out["rows"]
        ctx.lower, ctx.upper = out["lower"], out["upper"]
        ctx.status = out["status"]
        ctx.dtypes = (P.dtype, q.dtype, lo.dtype, hi.dtype)
        z = out["z"]
        ctx.save_for_backward(z)
        ctx.mark_non_differentiable(out["status"])
        return z.to(q.dtype), out["status"]

    @staticmethod
    def backward(ctx, gz, _gstatus=None):
        (z,) = ctx.saved_tensors
        LU, piv = ctx.lu
        B, n = z.shape
        rows = ctx.rows
        rhs = torch.cat([gz.to(z.dtype), z.new_zeros(B, len(rows))], 1)
        v = torch.linalg.lu_solve(LU, piv, rhs[..., None], adjoint=True)[..., 0]
        # a problem without a certified solution gets no gradient
        v = torch.where((ctx.status != QPStatus.SOLVED)[:, None], torch.zeros_like(v), v)
        vz = v[:, :n]
        vl = z.new_zeros(ctx.lower.shape)
        vl[:, rows] = v[:, n:]
        gP = -0.5 * (vz[:, :, None] * z[:, None, :] + z[:, :, None] * vz[:, None, :])
        gq = -vz
        glo = torch.where(ctx.lower, vl, torch.zeros_like(vl))
        ghi = torch.where(ctx.upper, vl, torch.zeros_like(vl))
        dP, dq, dlo, dhi = ctx.dtypes
        return gP.to(dP), gq.to(dq), None, glo.to(dlo), ghi.to(dhi)


def qp_layer(P, q, A, lo, hi) -> tuple[torch.Tensor, torch.Tensor]:
    """``(z, status)``: :class:`QPFunction` on a batch; ``status`` ``(B,)`` (:class:`QPStatus`)."""
    return QPFunction.apply(P, q, A, lo, hi)


# --------------------------------------------------------------------------------------
# the TGL problem of a game
# --------------------------------------------------------------------------------------
def linear_dynamics(x0: torch.Tensor, K: int, dt: float) -> dict:
    """The unicycle linearized around the constant-velocity rollout from ``x0`` ``(B, N, 4)``.

    Returns affine maps of the controls ``U`` ``(B, N, K, 2)`` (flattened per agent,
    ``(a_0, omega_0, a_1, ...)``): ``pos = pos_c + J_pos @ U_i`` with ``pos_c`` ``(B, N, K, 2)``
    and ``J_pos`` ``(B, N, K, 2, 2K)``; ``v = v_0 + J_v @ U_i`` (``J_v`` ``(K, 2K)``, the same
    for every agent) and ``theta = theta_0 + J_th @ U_i``, for steps ``k = 1..K``. Exact for
    the explicit Euler unicycle of the game to first order in ``U`` around ``U = 0``.
    """
    dev, dtp = x0.device, x0.dtype
    k = torch.arange(1, K + 1, device=dev, dtype=dtp)[:, None]  # steps 1..K
    lidx = torch.arange(K, device=dev, dtype=dtp)[None]  # control index l
    S = dt * dt * (k - 1 - lidx).clamp(min=0)  # (K, K): d pos_k / d(a_l or v0*omega_l)
    T = dt * (lidx <= k - 1).to(dtp)  # (K, K): d v_k / d a_l, d theta_k / d omega_l
    c, s, v0 = torch.cos(x0[..., 3]), torch.sin(x0[..., 3]), x0[..., 2]  # (B, N)
    d0 = torch.stack([c, s], -1)[..., None, :]  # (B, N, 1, 2)
    pos_c = x0[..., None, :2] + (k * dt) * v0[..., None, None] * d0  # (B, N, K, 2)
    J = x0.new_zeros(*x0.shape[:2], K, 2, 2 * K)
    # a_l moves along the heading d0 = (c, s); omega_l along n0 = (-s, c), scaled by v0
    J[..., 0, 0::2] = S * c[..., None, None]
    J[..., 1, 0::2] = S * s[..., None, None]
    J[..., 0, 1::2] = -S * (v0 * s)[..., None, None]
    J[..., 1, 1::2] = S * (v0 * c)[..., None, None]
    Jv = x0.new_zeros(K, 2 * K)
    Jv[:, 0::2] = T
    Jt = x0.new_zeros(K, 2 * K)
    Jt[:, 1::2] = T
    return {"pos_c": pos_c, "J_pos": J, "J_v": Jv, "J_th": Jt}


def _bounds(agent, cls, default):
    for f in agent.features:
        if isinstance(f, cls):
            return float(f.lower), float(f.upper)
    return default


@dataclass(frozen=True)
class TGLProblem:
    """The fixed structure of TGL's QP for a game: sizes, bounds, radii, collision checks.

    ``from_game`` reads the game (unicycles only): agents, horizon ``K``, step ``dt``,
    control and speed bounds from its bound features, radii, and the collision feature's
    pairs, steps (``every``) and margin (no collision feature: no slack, no half-spaces).
    """

    N: int
    K: int
    dt: float
    accel: tuple[float, float]
    turn: tuple[float, float]
    speed: tuple[tuple[float, float], ...]  #: per agent (lower, upper); +-inf if unbounded
    radii: tuple[float, ...]
    pairs: tuple[tuple[int, int], ...]
    steps: tuple[int, ...]  #: collision steps k in 1..K
    margin: float

    @classmethod
    def from_game(cls, game: PotentialGame) -> TGLProblem:
        spec = game.spec
        for i, a in enumerate(spec.agents):
            names = tuple(a.dynamics.state_names)
            if names != ("x", "y", "v", "theta") or game.nu[i] != 2:
                raise SpecError(
                    f"agents[{i}].dynamics",
                    f"TGL linearizes the unicycle (x, y, v, theta) with controls (a, omega); "
                    f"got states {names} and {game.nu[i]} controls",
                )
        a0 = spec.agents[0]
        accel = _bounds(a0, AccelerationBound, DEFAULT_BOUNDS["acceleration"])
        turn = _bounds(a0, TurnRateBound, DEFAULT_BOUNDS["turn_rate"])
        speed = tuple(_bounds(a, VelocityBound, (-np.inf, np.inf)) for a in spec.agents)
        col = [pf for pf in spec.pair_features if isinstance(pf, Collision)]
        pairs, steps, margin = (), (), 0.0
        if col:
            pairs = tuple(spec.pairs_of(col[0]))
            steps = tuple(col[0].steps(game.K))
            margin = float(col[0].margin)
        return cls(
            N=game.N,
            K=game.K,
            dt=float(spec.dt),
            accel=accel,
            turn=turn,
            speed=speed,
            radii=tuple(float(a.radius) for a in spec.agents),
            pairs=pairs,
            steps=steps,
            margin=margin,
        )

    @property
    def n_controls(self) -> int:
        return self.N * self.K * 2

    @property
    def n_slack(self) -> int:
        return len(self.pairs) * len(self.steps)

    def build(
        self,
        x0: torch.Tensor,
        w_own: torch.Tensor,
        w_pair: torch.Tensor,
        goals,
        vref,
        radii: torch.Tensor | None = None,
    ) -> dict:
        """QP data ``P, q, A, lo, hi`` ``(B, ...)`` (float64) and the linear dynamics.

        ``x0`` ``(B, N, 4)`` current states (data); ``w_own`` ``(B, N, 5)`` non-negative
        weights of :data:`OWN_FEATURES`; ``w_pair`` ``(B, n_pairs)``; ``goals`` ``(B, N, 2)``;
        ``vref`` ``(B, N)``; ``radii`` ``(B, N)`` each problem's collision radii (None: the
        game's, :attr:`radii`). ``P`` and ``q`` are differentiable in the weights and references.
        The energy is ``sum_f w_f ||R_f U_i - t_f||^2``: ``P`` is block diagonal (one
        ``2K x 2K`` block per agent, a diagonal for the slacks).
        """
        f64 = torch.float64
        x0, w_own, w_pair = x0.to(f64), w_own.to(f64), w_pair.to(f64)
        goals, vref = goals.to(f64), vref.to(f64)
        lin = linear_dynamics(x0.detach(), self.K, self.dt)
        P, q = self._cost(x0, w_own, w_pair, goals, vref, lin)
        A_rows, lo_rows, hi_rows = self._bound_rows(x0, lin)
        if self.n_slack:
            collisions = self._collision_rows(x0, lin, radii)
            for rows, more in zip((A_rows, lo_rows, hi_rows), collisions, strict=True):
                rows.extend(more)
        return {
            "P": P,
            "q": q,
            "A": torch.cat(A_rows, 1),
            "lo": torch.cat(lo_rows, 1),
            "hi": torch.cat(hi_rows, 1),
            "lin": lin,
        }

    def _cost(self, x0, w_own, w_pair, goals, vref, lin) -> tuple[torch.Tensor, torch.Tensor]:
        """``P`` ``(B, n, n)`` and ``q`` ``(B, n)`` of the energy (float64 inputs)."""
        N, K, dt = self.N, self.K, self.dt
        B = x0.shape[0]
        f64 = torch.float64
        nu, C, K2 = self.n_controls, self.n_slack, 2 * K
        n = nu + C
        eye = torch.eye(K2, dtype=f64, device=x0.device)
        Jg = lin["J_pos"][:, :, -1]  # (B, N, 2, 2K): final position
        Jv = lin["J_v"]  # (K, 2K)
        D = (eye[2::2] - eye[0:-2:2]) / dt  # jerk rows (a_{k+1} - a_k) / dt, (K-1, 2K)
        # R'R of the features whose rows do not depend on the state: speed, a, omega, jerk
        grams = torch.stack([Jv.T @ Jv, eye[0::2].T @ eye[0::2], eye[1::2].T @ eye[1::2], D.T @ D])
        w = w_own.clone()
        w[..., 2:4] = w[..., 2:4] + WEIGHT_FLOOR
        blocks = 2 * (
            w[..., 0, None, None] * (Jg.transpose(-1, -2) @ Jg)
            + (w[..., 1:, None, None] * grams).sum(2)
        )  # (B, N, 2K, 2K)
        tg = goals - lin["pos_c"][:, :, -1]  # (B, N, 2)
        tv = (vref - x0[..., 2])[..., None] * Jv.sum(0)  # (B, N, 2K): J_v' (v_ref - v_0) 1
        qa = -2 * (
            w[..., 0, None] * (Jg.transpose(-1, -2) @ tg[..., None])[..., 0] + w[..., 1, None] * tv
        )
        P = x0.new_zeros(B, n, n)
        for i in range(N):
            P[:, i * K2 : (i + 1) * K2, i * K2 : (i + 1) * K2] = blocks[:, i]
        q = torch.cat([qa.reshape(B, nu), x0.new_zeros(B, C)], 1)
        if C:
            ws = 2 * (w_pair + WEIGHT_FLOOR).repeat_interleave(len(self.steps), dim=1)
            P[:, nu:, nu:] = torch.diag_embed(ws)
        return P, q

    def _bound_rows(self, x0, lin) -> tuple[list, list, list]:
        """Constraint rows ``(A, lo, hi)`` of the control bounds and the speed limits."""
        N, K = self.N, self.K
        B = x0.shape[0]
        f64 = torch.float64
        nu, C, K2 = self.n_controls, self.n_slack, 2 * K
        n = nu + C
        Jv = lin["J_v"]  # (K, 2K)
        A_rows, lo_rows, hi_rows = [], [], []
        ctrl = torch.eye(nu, n, dtype=f64, device=x0.device)
        A_rows.append(ctrl[0::2].expand(B, -1, -1))  # accelerations of all agents
        lo_rows.append(x0.new_full((B, nu // 2), self.accel[0]))
        hi_rows.append(x0.new_full((B, nu // 2), self.accel[1]))
        A_rows.append(ctrl[1::2].expand(B, -1, -1))  # turn rates
        lo_rows.append(x0.new_full((B, nu // 2), self.turn[0]))
        hi_rows.append(x0.new_full((B, nu // 2), self.turn[1]))
        for i in range(N):
            lo_v, hi_v = self.speed[i]
            if not (np.isfinite(lo_v) or np.isfinite(hi_v)):
                continue
            Av = x0.new_zeros(B, K, n)
            Av[..., i * K2 : (i + 1) * K2] = Jv
            v0 = x0[:, i, 2:3].detach().expand(B, K)
            A_rows.append(Av)  # v_k - v_0 within [min(lo, v0), max(hi, v0)] - v0
            lo_rows.append(torch.clamp(lo_v - v0, max=0.0) if np.isfinite(lo_v) else v0 * 0 - _INF)
            hi_rows.append(torch.clamp(hi_v - v0, min=0.0) if np.isfinite(hi_v) else v0 * 0 + _INF)
        return A_rows, lo_rows, hi_rows

    def _collision_rows(self, x0, lin, radii) -> tuple[list, list, list]:
        """Constraint rows ``(A, lo, hi)`` of the linearized collision constraints with their
        slacks, and of ``s >= 0`` (only for games with pairs)."""
        K = self.K
        B = x0.shape[0]
        f64 = torch.float64
        dev = x0.device
        nu, C, K2 = self.n_controls, self.n_slack, 2 * K
        n = nu + C
        S = len(self.steps)
        ks = torch.as_tensor(self.steps, device=dev) - 1
        pc, J = lin["pos_c"][:, :, ks], lin["J_pos"][:, :, ks]  # (B, N, S, 2[, 2K])
        Ac = x0.new_zeros(B, C, n)
        lc = x0.new_zeros(B, C)
        for c, (i, j) in enumerate(self.pairs):
            if radii is None:
                reach = self.radii[i] + self.radii[j] + self.margin
            else:
                reach = (radii[:, i] + radii[:, j]).to(f64)[:, None] + self.margin
            d = pc[:, i] - pc[:, j]  # (B, S, 2) on the reference rollouts
            nrm = d.norm(dim=-1, keepdim=True)
            e = torch.tensor([1.0, 0.0], dtype=f64, device=dev)
            nv = torch.where(nrm > 1e-9, d / nrm.clamp(min=1e-9), e)  # (B, S, 2)
            r = slice(c * S, (c + 1) * S)
            Ac[:, r, i * K2 : (i + 1) * K2] = (nv[..., None] * J[:, i]).sum(2)
            Ac[:, r, j * K2 : (j + 1) * K2] = -(nv[..., None] * J[:, j]).sum(2)
            lc[:, r] = reach - (nv * d).sum(-1)
        Ac[:, :, nu:] = torch.eye(C, dtype=f64, device=dev)
        eye_n = torch.eye(n, dtype=f64, device=dev)
        return (
            [Ac, eye_n[nu:].expand(B, -1, -1)],  # the constraints, then s >= 0
            [lc, x0.new_zeros(B, C)],
            [x0.new_full((B, C), _INF), x0.new_full((B, C), _INF)],
        )

    def trajectory(self, x0: torch.Tensor, z: torch.Tensor, lin: dict) -> dict:
        """States ``(B, N, K, 4)`` and controls ``(B, N, K, 2)`` of the linear model at ``z``."""
        B = z.shape[0]
        N, K = self.N, self.K
        U = z[:, : self.n_controls].reshape(B, N, 2 * K)
        pos = lin["pos_c"].to(z.dtype) + (lin["J_pos"].to(z.dtype) @ U[:, :, None, :, None])[..., 0]
        v = x0[..., 2:3].to(z.dtype) + U @ lin["J_v"].to(z.dtype).T
        th = x0[..., 3:4].to(z.dtype) + U @ lin["J_th"].to(z.dtype).T
        states = torch.cat([pos, v[..., None], th[..., None]], -1)
        return {
            "states": states,
            "controls": U.reshape(B, N, K, 2),
            "slack": z[:, self.n_controls :],
        }


# --------------------------------------------------------------------------------------
# the model
# --------------------------------------------------------------------------------------
class TGLModel(_Base):
    """Backbone + TGL: weights and references per agent and mode -> QP -> joint trajectories.

    Output: ``pos`` ``(B, M, N, K, 2)``, ``states`` ``(B, M, N, K, 4)`` (the linear
    model's), ``controls`` ``(B, M, N, K, 2)``, ``logits`` ``(B, M)`` (scene
    probabilities), ``weights`` ``(B, M, N, 5)`` (:data:`OWN_FEATURES`), ``pair_weights``
    ``(B, M, n_pairs)``, ``goals`` ``(B, M, N, 2)``, ``vref`` ``(B, M, N)``, ``status``
    ``(B * M,)`` (:class:`QPStatus`).
    """

    def __init__(self, cfg, game: PotentialGame):
        super().__init__(cfg, game)
        self.problem = TGLProblem.from_game(game)
        self.radius_param = any(a.radius_param for a in game.spec.agents)
        W, M, w, N = cfg.global_width, cfg.modes, cfg.dec_width, self.N
        nf = len(OWN_FEATURES)
        self.own_dec = nn.Sequential(mlp(W, w, M * nf), nn.Softplus())
        self.n_pairs = len(self.problem.pairs)
        self.pair_dec = nn.Sequential(
            mlp(N * W, w, M * max(self.n_pairs, 1), norm="layer"), nn.Softplus()
        )
        # references: goal offset from the constant-velocity end point (2), speed change (1)
        self.ref_dec = mlp(W, w, M * 3, norm="layer")

    def forward(self, scene: dict) -> dict:
        scene = _masks.neutral_scene(scene)
        mask = scene.get("agents_mask")  # only where the scene has a pad
        z = self.encoder(scene)
        B, M, N, K = z.shape[0], self.cfg.modes, self.N, self.K
        pr = self.problem
        x0 = scene["history"][:, -1].to(z.dtype)  # (B, N, 4)
        w_own = self.own_dec(z).reshape(B, N, M, -1).permute(0, 2, 1, 3)  # (B, M, N, 5)
        w_pair = self.pair_dec(z.reshape(B, -1)).reshape(B, M, -1)[..., : self.n_pairs]
        ref = self.ref_dec(z).reshape(B, N, M, 3).permute(0, 2, 1, 3)  # (B, M, N, 3)
        if mask is not None:  # a pad: zero weights and references (it stays at rest)
            w_own = _masks.where_agents(mask, w_own, 0.0, agent_dim=2)
            ref = _masks.where_agents(mask, ref, 0.0, agent_dim=2)
            keep = _masks.pairs_mask(pr.pairs, mask)[:, None]
            w_pair = torch.where(keep, w_pair, torch.zeros((), dtype=w_pair.dtype))
        heading = torch.stack([torch.cos(x0[..., 3]), torch.sin(x0[..., 3])], -1)
        cv_end = x0[..., :2] + K * pr.dt * x0[..., 2:3] * heading  # (B, N, 2)
        goals = cv_end[:, None] + ref[..., :2]
        vref = x0[:, None, :, 2] + ref[..., 2]
        xx = x0[:, None].expand(B, M, N, 4).reshape(B * M, N, 4)
        radii = None  # a game with radius parameters: each scene's radii (e.g. L / 2)
        if self.radius_param and "radius" in scene:
            radii = scene["radius"].detach().double()[:, None].expand(B, M, N).reshape(B * M, N)
        qp = pr.build(
            xx,
            w_own.reshape(B * M, N, -1),
            w_pair.reshape(B * M, -1),
            goals.reshape(B * M, N, 2),
            vref.reshape(B * M, N),
            radii,
        )
        zq, status = qp_layer(qp["P"], qp["q"], qp["A"], qp["lo"], qp["hi"])
        traj = pr.trajectory(xx.double(), zq, qp["lin"])
        x = traj["states"].to(z.dtype).reshape(B, M, N, K, 4)
        pos = x[..., :2]
        return {
            "pos": pos,
            "states": x,
            "controls": traj["controls"].to(z.dtype).reshape(B, M, N, K, 2),
            "logits": self.scene_logits(z, pos),
            "weights": w_own,
            "pair_weights": w_pair,
            "goals": goals,
            "vref": vref,
            "status": status,
        }
