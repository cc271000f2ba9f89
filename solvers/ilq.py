"""Iterative linear-quadratic (iLQ) solver for general-sum feedback Nash games.

The method of Fridovich-Keil et al. (ICRA 2020), written from the math. Shapes and index
order of ``u``, ``x`` and ``p`` follow the contract in :mod:`epo_casadi.game`.

Stage vectors
    The recursion works on *joint stage vectors*: ``X_k = (x_{0,k}, ..., x_{N-1,k})``
    (``nx = sum_i nx_i`` entries, agent-major) and ``U_k = (u_{0,k}, ..., u_{N-1,k})``
    (``nu = sum_i nu_i``). :func:`to_stages` and :func:`from_stages` convert between the
    flat game layout and ``X (K+1, nx)``, ``U (K, nu)``.

Player costs
    Player ``i`` minimizes ``C_i(x, u, p)``, a function of the whole free trajectory.
    By default ``C_i`` is component ``i`` of ``game.function('traj_agent_costs')``; any
    ``casadi.Function`` ``(x, u, p) -> C`` (``N`` entries, game layout) can be passed
    instead (``costs=``), so the costs need not form a potential.

One iteration, around the current trajectory ``(X, U)`` (rolled out, so feasible)
    1. *Linearize* the joint dynamics, ``dX_{k+1} = A_k dX_k + B_k dU_k`` (block-diagonal
       per agent, except where ``GameSpec(couplings=...)`` steps several agents with one
       joint model, ``PotentialGame.stage_step``), and *quadratize* every player's cost:
       the exact CasADi gradient of ``C_i`` w.r.t. ``(U_k, X_k)`` and the diagonal stage
       blocks of a Hessian (``ILQOptions.hessian``):

       * ``"exact"``: the exact Hessian of ``C_i`` (any costs);
       * ``"gauss_newton"``: ``J_i'J_i``, ``J_i`` the exact Jacobian of the residual rows of
         the terms that make up ``C_i = 1/2 |r_i|^2`` (game costs only). Positive
         semi-definite, so every player's LQ problem stays convex;
       * ``"auto"`` (default): Gauss-Newton for the game's costs, exact for custom ones.
         On the crossing games of the tests, exact Hessians with the shift below do not
         converge (the collision distance has negative curvature, the value Hessians turn
         indefinite and grow), Gauss-Newton converges in 7-13 iterations (docs/ilq.md).

       **Costs that couple consecutive stages** (``jerk``, ``turn_acceleration``): the
       variables of stage ``k-1`` that such rows involve are carried as extra states
       ``Y_k = (U_{k-1}, X_{k-1})[aug]`` (:attr:`ILQSolver.aug`), so the cost is
       stage-additive in ``(X_k, Y_k)`` and the Hessian blocks between stage ``k-1`` and
       ``k`` are kept exactly (at stage ``k``, against ``Y_k``). Only blocks between stages
       further apart are dropped (:attr:`ILQSolver.dropped_cross_stage`; none for the
       built-in features). Without such costs ``Y`` is empty and nothing changes.
    2. *Solve the LQ game's feedback Nash equilibrium* by the coupled Riccati recursion.
       With the homogeneous stage vector ``w = (dU, dX, 1)`` and player ``i``'s stage
       cost ``1/2 w' L_ik w``, value ``1/2 (dX, 1)' Z_ik (dX, 1)`` (``Z_iK = L_iK``) and
       ``Phi_k = [[B_k, A_k, 0], [0, 0, 1]]``, at stage ``k = K-1..0``::

           T_i = L_ik + Phi_k' Z_i,k+1 Phi_k                  (player i's Q-function)
           rows u_i of T_i:   T_i[u_i, u] (P, a) = T_i[u_i, (x, 1)]    for every player i
           dU = -P dX - a,    Z_ik = Psi' T_i Psi,    Psi = [[-P, -a], [I, 0], [0, 1]]

       The stacked rows form one ``nu x nu`` linear system for all players' gains ``P``
       (``nu x nx``) and feed-forward terms ``a`` (``nu``).
    3. *Roll out* the nonlinear dynamics with the feedback policy
       ``U_k = Ubar_k - P_k (X_k - Xbar_k) - Q_k (Y_k - Ybar_k) - eps a_k``. ``eps`` starts
       at ``step_size`` and is multiplied by ``backtrack`` while the rollout is non-finite,
       leaves the trust region ``max |X - Xbar| <= max_state_step`` or
       (``line_search="residual"``, the default) its merit ``m = RMS(a)`` fails
       ``m_trial <= (1 - 0.1 eps) max(last `memory` merits)`` (one backward pass per trial;
       an accepted trial's pass serves the next iteration, so full steps cost nothing
       extra). The merit is the feedback-Nash residual, valid for general-sum costs; the
       potential is not a merit here (a feedback equilibrium does not minimize it).

    After the first failed line search two safeguards switch on (the fast path is untouched
    until then): the first trial ``eps`` comes from a secant on ``a`` (:func:`_secant_step`),
    and, when the residual has kinks (``max``/``min``: collision, bounds), their curvature
    is blended over the widths ``kink_widths`` in turn (:func:`_smooth_kinks`; the gains
    switch at a kink, so ``a`` and the merit jump there), each width after the previous one
    converged, then the exact kinks again, where convergence is judged (docs/ilq.md). When
    a width converged with kink arguments inside its band and, at the last width or the
    exact kinks, no step passes at the requested regularization, the solve stops
    ``STALLED`` with ``info['stop'] = 'kink'``: the blended solution sits on a kink, where
    the one-sided curvatures give different gains, so no exact-kink iterate nearby has
    ``a = 0``. The blended solution is returned (``info['kink_equilibrium']``: width, kink
    arguments, blended policy and a message; ``P``, ``a`` and ``stationarity`` at the exact
    kinks). With ``kink_equilibrium`` (the default) the solver then looks for an
    equilibrium *on* the kinks (:meth:`ILQSolver._kink_equilibrium`): curvatures
    ``theta_j^2``, ``theta_j in [0, 1]`` (the hinge's generalized Hessian), and a trajectory
    with those kink arguments at 0 and ``max |a| <= tol``, whose policy passes the
    feedback-Nash check (:mod:`solvers.feedback_nash`); found, the result is ``CONVERGED``
    with ``info['stop'] = 'kink_equilibrium'`` and that point's policy.

    The iteration stops when ``max |a| <= tol`` at the requested regularization (status
    ``CONVERGED``; ``STALLED`` when no step passes the line search up to the regularization
    cap or the tolerance holds only with raised regularization; ``info['stop']``). Such a
    ``line_search`` or ``regularized_only`` stall, with the game's own costs, restarts once
    from the open-loop equilibrium (``solve_lm`` from the same start; ``restart``) within the
    same ``max_iter``; the restart's result is kept when it converged or stopped at a
    ``kink``, else the first one (``info['restart']``). The feed-forward
    term is the change of the controls a full step would make at fixed state, and ``a = 0``
    at every stage is the first-order feedback Nash condition: with everybody following
    ``U(X) = U* - P (X - X*)``, no player lowers its cost to first order by deviating at
    one stage. (``P`` comes from the quadratization without the dynamics' second
    derivatives, so the policy is a first-order, iLQR-like, approximation of the true
    feedback equilibrium's; the trajectory condition ``a = 0`` itself is exact.)

Regularization
    A player's stage problem is well posed when its own block ``H_ii = T_i[u_i, u_i]`` is
    positive definite. ``regularization`` ``mu0 >= 0`` is always added to ``H_ii`` (a
    proximal term ``mu0/2 |du_i|^2`` in player ``i``'s cost). When a pivot of ``H_ii``
    (``LDL'``, no pivoting) is below ``min_curvature``, ``mu = max(min_curvature - g,
    min_curvature) + max(-g, 0)`` is added on top, ``g`` the Gershgorin lower bound of its
    eigenvalues: the block becomes positive definite with negative curvature mirrored
    (a concave direction gets curvature of its own size, not a near-singular one). If the
    coupled system is still singular, every player's block at that stage gets ``10x`` more
    until it solves. When a backward pass still fails, or no step passes the line search,
    the global ``mu`` is raised ``10x`` (at least to ``1e-4``, at most ``1e8``) and the
    iteration retried; it is lowered ``10x`` after each accepted step (back to ``mu0``
    below ``1e-4``). The shifts enter the value recursion too (a
    consistent regularized LQ game). ``result.info`` reports them: ``regularization``
    ``(K, N)`` of the last backward pass and ``max_regularization`` over the solve.

Result (:class:`solvers.result.SolveResult`, ``solver='ilq'``)
    ``energy`` is the potential ``E(u, p)`` of the game when the costs are the game's own,
    ``nan`` with custom costs (and so is ``grad_norm``, the inf-norm of ``dE/du``, which a
    feedback equilibrium does not make zero). ``agent_costs`` are the ``C_i`` that were
    solved. ``info['gains']`` ``(K, nu, nx)`` and ``info['feedforward']`` ``(K, nu)`` are
    ``P`` and ``a`` at the returned trajectory, ``info['gains_prev']`` ``(K, nu, na)`` the
    gains ``Q`` on the carried variables ``Y`` (``na = 0`` without cross-stage costs;
    ``info['prev_variables']`` their positions in ``(U_{k-1}, X_{k-1})``): the feedback
    policy ``U_k = U*_k - P_k (X_k - X*_k) - Q_k (Y_k - Y*_k) - a_k`` (``a ~ 0`` when
    converged).
    ``info['stationarity']`` is the final ``max |a|``, ``info['residual_history']`` the
    same per iteration, ``info['step_sizes']`` the accepted ``eps`` (``0``: a retry with
    more regularization).

Speed
    The CasADi functions are built once per game, costs and Hessian mode, and cached on the
    game: one call returns the costs, the stage Hessian nonzeros and the dynamics Jacobians
    (``Function.map`` over stages), one call rolls out the feedback policy; numpy scatters
    the nonzeros with precomputed indices. The Riccati recursion runs in numpy (players
    stacked, the reference). With ``compiled=True`` everything per stage is generated C,
    compiled once per game structure and cached on disk (:mod:`solvers.codegen`, needs a C
    compiler), so Python runs a few calls per iteration and none per stage: the Riccati
    recursion as one stage function folded over the horizon (``Function.mapaccum``; a
    singular stage falls back to numpy), the rollout likewise, and the quadratization as
    stage functions found from the graph and mapped over the stages
    (:mod:`solvers.fast_ilq`); with the game's costs one generated call per line-search
    trial runs all three (``fast_ilq.CompiledTrial``). The compiled path equals the
    interpreted one to rounding (``tests/test_ilq_fast.py``); it is an option, not the
    default, because the first call of each structure compiles for about 1.5 to 10 s
    (``-O3`` vector code; docs/ilq.md).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame

from .codegen import BufferCall as _Call
from .lm import MAX_STEPS, check_options
from .result import SolveResult, Status
from .stages import _stage_index, from_stages, to_stages  # noqa: F401 (re-exported)

__all__ = ["ILQOptions", "ILQSolver", "get_solver", "solve_ilq", "to_stages", "from_stages"]

LINE_SEARCHES = ("none", "residual")
HESSIANS = ("auto", "gauss_newton", "exact")


def _num(name, v, lo=None, hi=None, strict_lo=False, integer=False):
    ok = isinstance(v, (int, float)) and not isinstance(v, bool)
    if integer:
        ok = ok and isinstance(v, int)
    ok = ok and not (isinstance(v, float) and math.isnan(v))
    if ok and lo is not None:
        ok = v > lo if strict_lo else v >= lo
    if ok and hi is not None:
        ok = v <= hi
    if not ok:
        rng = []
        if lo is not None:
            rng.append(f"{'>' if strict_lo else '>='} {lo}")
        if hi is not None:
            rng.append(f"<= {hi}")
        kind = "an integer" if integer else "a number"
        raise SpecError(f"ilq.{name}", f"expected {kind} {' and '.join(rng)}, got {v!r}")


@dataclass(frozen=True)
class ILQOptions:
    """iLQ game options (defaults: a converging standalone solve)."""

    max_iter: int = 500  #: maximum number of iterations (backward pass + accepted forward pass)
    tol: float = 1e-5  #: converged when max |a| (feed-forward, control units) <= tol
    hessian: str = "auto"  #: "gauss_newton", "exact"; "auto": GN for game costs, else exact
    step_size: float = 1.0  #: first trial eps on the feed-forward term in every iteration
    line_search: str = "residual"  #: "residual": merit max|a| must drop (non-monotone); "none"
    memory: int = 5  #: residual line search: compare with the largest of the last `memory` merits
    backtrack: float = 0.5  #: factor on eps after a rejected trial step
    max_backtracks: int = 10  #: rejected trials before regularization is raised instead
    max_state_step: float = math.inf  #: trust region: largest |X_new - X| (elementwise) accepted
    regularization: float = 0.0  #: mu0 >= 0 always added to every player's own block H_ii
    min_curvature: float = 1e-8  #: smallest allowed pivot of H_ii before a shift is added
    adaptive_step: bool = True  #: first trial eps from a secant on a (damps oscillation)
    #: widths over which the curvature of the residual's kinks (max/min) is blended, used in
    #: turn after the line search fails at the exact kinks; () never blends (docs/ilq.md)
    kink_widths: tuple = (1e-2, 1e-3, 1e-4)
    #: after a 'stalled' solve (stop 'line_search' or 'regularized_only') with the game's own
    #: costs, solve once more from the open-loop equilibrium (LM on the potential from the
    #: same start), within the same max_iter; kept if it converges or stops at a kink
    restart: bool = True
    #: when a solve stops at a kink ('kink'), look for an equilibrium on it: kink curvatures
    #: from the generalized Hessian that give a = 0 with the kink arguments at 0, whose
    #: policy passes the feedback-Nash check; 'converged' if found (docs/ilq.md)
    kink_equilibrium: bool = True
    compiled: bool = False  #: per-stage work as generated C (needs a C compiler; cached on disk)

    def __post_init__(self):
        _num("max_iter", self.max_iter, 0, MAX_STEPS, integer=True)
        _num("tol", self.tol, 0)
        if self.hessian not in HESSIANS:
            raise SpecError("ilq.hessian", f"expected one of {HESSIANS}, got {self.hessian!r}")
        _num("step_size", self.step_size, 0, 1, strict_lo=True)
        if self.line_search not in LINE_SEARCHES:
            raise SpecError(
                "ilq.line_search", f"expected one of {LINE_SEARCHES}, got {self.line_search!r}"
            )
        _num("backtrack", self.backtrack, 0, strict_lo=True)
        if not self.backtrack < 1:
            raise SpecError("ilq.backtrack", f"expected 0 < backtrack < 1, got {self.backtrack!r}")
        _num("max_backtracks", self.max_backtracks, 0, integer=True)
        _num("memory", self.memory, 1, integer=True)
        _num("max_state_step", self.max_state_step, 0, strict_lo=True)
        _num("regularization", self.regularization, 0)
        if not math.isfinite(self.regularization):
            raise SpecError(
                "ilq.regularization", f"expected a finite number >= 0, got {self.regularization!r}"
            )
        _num("min_curvature", self.min_curvature, 0)
        if not math.isfinite(self.min_curvature):
            raise SpecError(
                "ilq.min_curvature", f"expected a finite number >= 0, got {self.min_curvature!r}"
            )
        kw = self.kink_widths
        if isinstance(kw, (list, tuple)):
            kw = tuple(kw)
            object.__setattr__(self, "kink_widths", kw)
        ok = isinstance(kw, tuple) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
            for v in kw
        )
        if not ok or any(b >= a for a, b in zip(kw, kw[1:], strict=False)):
            raise SpecError(
                "ilq.kink_widths",
                f"expected a decreasing list of finite numbers > 0, got {self.kink_widths!r}",
            )
        if not isinstance(self.adaptive_step, bool):
            raise SpecError(
                "ilq.adaptive_step", f"expected True or False, got {self.adaptive_step!r}"
            )
        if not isinstance(self.compiled, bool):
            raise SpecError("ilq.compiled", f"expected True or False, got {self.compiled!r}")
        if not isinstance(self.restart, bool):
            raise SpecError("ilq.restart", f"expected True or False, got {self.restart!r}")
        if not isinstance(self.kink_equilibrium, bool):
            raise SpecError(
                "ilq.kink_equilibrium", f"expected True or False, got {self.kink_equilibrium!r}"
            )


# --------------------------------------------------------------------------------------
# layout helpers
# --------------------------------------------------------------------------------------
# --------------------------------------------------------------------------------------
# the solver object
# --------------------------------------------------------------------------------------
class ILQSolver:
    """iLQ game solver for one game and one set of player costs (functions built once).

    ``costs``: ``None`` (the game's ``traj_agent_costs``) or a ``casadi.Function``
    ``(x, u, p) -> C`` with ``C`` of ``N`` entries, in the layout of :mod:`epo_casadi.game`.
    ``hessian``: ``"gauss_newton"`` (game costs only: ``J_i'J_i`` of player ``i``'s
    residual rows, positive semi-definite), ``"exact"`` or ``"auto"`` (Gauss-Newton for the
    game's costs, exact for custom ones). The object holds work arrays and CasADi buffers:
    one solve at a time (not thread-safe; use one solver per thread).
    """

    def __init__(
        self, game: PotentialGame, costs: ca.Function | None = None, hessian: str = "auto"
    ):
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        if hessian not in HESSIANS:
            raise SpecError("ilq.hessian", f"expected one of {HESSIANS}, got {hessian!r}")
        self.game = game
        self.custom_costs = costs is not None
        if hessian == "auto":
            hessian = "exact" if self.custom_costs else "gauss_newton"
        if hessian == "gauss_newton" and self.custom_costs:
            raise SpecError(
                "ilq.hessian",
                "'gauss_newton' needs the game's own (sum-of-squares) costs; use 'exact' with custom costs",
            )
        self.hessian = hessian
        self.costs = self._check_costs(game, costs)
        K, N = game.K, game.N
        self.K, self.N = K, N
        self.nx = int(sum(game.nx))
        self.nu = int(sum(game.nu))
        self.n = self.nu + self.nx + 1
        self.xidx, self.uidx = _stage_index(game)
        self.uo = np.concatenate([[0], np.cumsum(game.nu)]).astype(int)
        self.xo = np.concatenate([[0], np.cumsum(game.nx)]).astype(int)
        self._build_quadratize()
        self._build_rollout()
        self._build_riccati_indices()
        self._compiled: _CompiledRiccati | None = None
        self._cquad = None  # solvers.fast_ilq.CompiledQuadratize after compile(), if it applies
        self._croll = None  # solvers.fast_ilq.CompiledRollout after compile()
        self._ftrial = None  # solvers.fast_ilq.CompiledTrial after compile(), game costs only
        self._grad = None  # the potential's gradient (result's grad_norm), on first use
        self.quad_backend = "interpreted"  #: quadratization used with compiled=True
        self.kink_width = 0.0  #: blend width of the kinks' curvature in the current solve
        self._kink_quad = None  # (quadratize, kinks) with blended kinks; False: no kinks
        self.kink_pins = None  #: per-kink slopes (>= 0: pinned, < 0: blended) or None
        self._pin_quad = None  # quadratize(X, U, p, w, s), built on first need

    @property
    def has_kinks(self) -> bool:
        """Whether the game's residual has kinks (``max``/``min``) whose curvature the
        solver can blend (Gauss-Newton only; built on first call)."""
        if self._kink_quad is None:
            self._kink_quad = self._build_kink_quad() or False
        return bool(self._kink_quad)

    def kinks_within(self, X, U, p, width: float) -> int:
        """Number of kink arguments (``b - a`` of the residual's ``max(a, b)``, ``a - b`` of
        ``min(a, b)``) within ``width / 2`` of their kink at ``(X, U)``."""
        if width <= 0 or not self.has_kinks:
            return 0
        (zk,) = self._kink_quad[1](X, U, p)
        return int(np.count_nonzero(np.abs(zk) < 0.5 * width))

    def _build_kink_quad(self, pinned: bool = False):
        """``(quadratize(X, U, p, w), kinks(X, U, p))`` with the kinks' curvature blended over
        ``w`` (:func:`_smooth_kinks`), or ``None``. Same outputs as ``ilq_quadratize``: the
        gradients, costs, energy and dynamics are exact, only the Hessian blocks change (on
        the exact blocks' sparsity). ``pinned``: ``quadratize(X, U, p, w, s)``, kink ``j``
        with ``s_j >= 0`` at Gauss-Newton curvature ``s_j^2`` (equilibria on a kink)."""
        if self.hessian != "gauss_newton":
            return None
        smooth = _smooth_kinks(self.game.function("traj_residual"), pinned=pinned)
        if smooth is None:
            return None
        Xs, Us, p, x_flat, u_flat, z, C, E, grads, player_rows, hess_sel, phi_out = self._blend_sym
        w = ca.SX.sym("w")
        s_in = [ca.SX.sym("s", smooth.size1_in(smooth.n_in() - 1))] if pinned else []
        rb, zk = smooth(x_flat, u_flat, p, w, *s_in)
        outs = []
        for grad, rows_i, (sp, sel) in zip(grads, player_rows, hess_sel, strict=True):
            outs.append(ca.densify(grad))
            if rows_i:
                J = ca.jacobian(rb[rows_i], z)
                H = ca.project(ca.mtimes(J.T, J), sp)
            else:
                H = ca.SX(sp)
            outs.append(H.nz[sel.tolist()] if sel.size else ca.SX(0, 1))
        quad = ca.Function(
            "ilq_quadratize_kinks", [Xs, Us, p, w, *s_in], [C, E, ca.vertcat(*outs), phi_out]
        )
        kinks = ca.Function("ilq_kinks", [Xs, Us, p], [zk])
        return _Call(quad), _Call(kinks)

    # ---- checks ---------------------------------------------------------------------------
    @staticmethod
    def _check_costs(game, costs):
        if costs is None:
            return game.function("traj_agent_costs")
        if not isinstance(costs, ca.Function):
            raise SpecError(
                "costs", f"expected a casadi.Function (x, u, p) -> C, got {type(costs).__name__}"
            )
        want = [(game.n_x, 1), (game.n_u, 1), (game.n_p, 1)]
        got = [(costs.size1_in(i), costs.size2_in(i)) for i in range(costs.n_in())]
        if costs.n_in() != 3 or got != want:
            raise SpecError("costs", f"expected inputs (x, u, p) of sizes {want}, got {got}")
        if costs.n_out() < 1 or costs.numel_out(0) != game.N:
            raise SpecError(
                "costs",
                f"expected a first output with N = {game.N} entries, got shape {costs.size_out(0)}",
            )
        if costs.is_a("MXFunction"):
            try:
                costs = costs.expand()
            except RuntimeError as e:
                raise SpecError("costs", f"the MX function cannot be expanded to SX: {e}") from None
        return costs

    # ---- symbolic builders ------------------------------------------------------------------
    def _joint_step(self, X, U):
        # the game's own stage map: each agent's dynamics, or its coupling's joint model
        return self.game.stage_step(X, U)

    def _build_quadratize(self):
        g, K, N, nx, nu, n = self.game, self.K, self.N, self.nx, self.nu, self.n
        Xs = ca.SX.sym("X", nx, K + 1)
        Us = ca.SX.sym("U", nu, K)
        p = ca.SX.sym("p", g.n_p)
        x_flat = ca.vertcat(*[ca.vec(Xs[self.xo[i] : self.xo[i + 1], :]) for i in range(N)])
        u_flat = ca.vertcat(*[ca.vec(Us[self.uo[i] : self.uo[i + 1], :]) for i in range(N)])
        C = ca.reshape(self.costs(x_flat, u_flat, p), N, 1)
        # stage-major variables z = (U_0, X_0, U_1, X_1, ..., U_{K-1}, X_{K-1}, X_K)
        zs = []
        for k in range(K):
            zs += [Us[:, k], Xs[:, k]]
        zs.append(Xs[:, K])
        z = ca.vertcat(*zs)
        nz = z.shape[0]
        stage_of = np.concatenate(
            [np.full(nu + nx, k) for k in range(K)] + [np.full(nx, K)]
        ).astype(int)
        pos_in = np.concatenate(
            [np.arange(nu + nx) for _ in range(K)] + [nu + np.arange(nx)]
        ).astype(int)
        n_stage = K * N * n * n
        r_all = (
            g.function("traj_residual")(x_flat, u_flat, p)
            if self.hessian == "gauss_newton"
            else None
        )
        grads, hessians, player_rows = [], [], []
        for i in range(N):
            if self.hessian == "gauss_newton":
                rows_i = [
                    r
                    for t in g.terms
                    if g.agent_names[i] in t.agents
                    for r in range(t.rows.start, t.rows.stop)
                ]
                ri = r_all[rows_i] if rows_i else ca.SX(0, 1)
                J = ca.jacobian(ri, z)
                H, grad = ca.mtimes(J.T, J), ca.mtimes(J.T, ri)
                player_rows.append(rows_i)
            else:
                H, grad = ca.hessian(C[i], z)
            rows, cols = (np.asarray(v, dtype=int) for v in H.sparsity().get_triplet())
            grads.append(grad)
            hessians.append((H, rows, cols))
        # Hessian entries between consecutive stages (jerk, turn_acceleration): the earlier
        # stage's variables they involve are carried into the next stage as extra states Y
        lag = [stage_of[r] - stage_of[c] for _, r, c in hessians]
        prev = np.unique(
            np.concatenate(
                [pos_in[c[d == 1]] for (_, r, c), d in zip(hessians, lag, strict=True)] + [[]]
            )
        ).astype(int)
        self.aug = prev  # positions in (U_k, X_k) of the carried variables Y_{k+1}
        self.na = int(prev.size)
        self.nxs = nx + self.na  # Riccati state (X_k, Y_k)
        self.n = n = nu + self.nxs + 1
        ypos = np.full(nu + nx, -1)
        ypos[prev] = nu + nx + np.arange(self.na)
        n_stage = K * N * n * n
        outs, src, tgt, hess_sel = [], [], [], []
        off = 0
        self.dropped_cross_stage = 0
        for i, (grad, (H, rows, cols)) in enumerate(zip(grads, hessians, strict=True)):
            # gradient -> last row and last column of player i's stage matrices
            outs.append(ca.densify(grad))
            for a_, b_ in ((pos_in, np.full(nz, n - 1)), (np.full(nz, n - 1), pos_in)):
                src.append(off + np.arange(nz))
                tgt.append(self._lam_index(stage_of, i, a_, b_, n_stage))
            off += nz
            # Hessian nonzeros inside a stage block, and between a stage and the one before
            # it (placed at stage k against Y_k); blocks further apart are dropped
            d = stage_of[rows] - stage_of[cols]
            sel = np.nonzero(np.abs(d) <= 1)[0]
            outs.append(H.nz[sel.tolist()] if sel.size else ca.SX(0, 1))
            hess_sel.append((H.sparsity(), sel))
            rs, cs, ds = rows[sel], cols[sel], d[sel]
            ka = np.maximum(stage_of[rs], stage_of[cs])
            pa = np.where(ds == -1, ypos[pos_in[rs]], pos_in[rs])
            pb = np.where(ds == 1, ypos[pos_in[cs]], pos_in[cs])
            src.append(off + np.arange(sel.size))
            tgt.append(self._lam_index(ka, i, pa, pb, n_stage))
            off += sel.size
            self.dropped_cross_stage += int(rows.size - sel.size)
        # dynamics Jacobians per stage, packed into Phi[k] = [[B_k, A_k, 0], [0, 0, 1]]
        xk, uk = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        nxt = self._joint_step(xk, uk)
        Ja, Jb = ca.jacobian(nxt, xk), ca.jacobian(nxt, uk)
        lin = ca.Function("ilq_lin", [xk, uk], [Ja, Jb])
        A_all, B_all = (lin.map(K) if K > 1 else lin)(Xs[:, :K], Us)
        ra, cA = (np.asarray(v, dtype=int) for v in Ja.sparsity().get_triplet())
        rb, cB = (np.asarray(v, dtype=int) for v in Jb.sparsity().get_triplet())
        # nonzeros of a mapped output are stage-major (each stage's column block in turn)
        A_nz = ca.reshape(A_all.nz[:], Ja.nnz(), K)
        B_nz = ca.reshape(B_all.nz[:], Jb.nnz(), K)
        phi_out = ca.vec(ca.vertcat(B_nz, A_nz))
        stage0 = np.concatenate([rb * n + cB, ra * n + nu + cA])
        self._phi_pattern = stage0  # flat entries of one Phi[k] that change with the trajectory
        self._phi_tgt = (
            (np.arange(K)[:, None] * ((self.nxs + 1) * n) + stage0[None])
            .reshape(-1)
            .astype(np.intp)
        )
        r_traj = None
        if self.custom_costs:
            E = ca.SX(np.nan)
        else:
            r_traj = g.function("traj_residual")(x_flat, u_flat, p)
            E = 0.5 * ca.sumsqr(r_traj)
        self.quad = _Call(
            ca.Function(
                "ilq_quadratize",
                [Xs, Us, p],
                [C, E, ca.vertcat(*outs), phi_out],
                ["X", "U", "p"],
                ["C", "E", "lam_nz", "phi_nz"],
            )
        )
        self._lam_src = np.concatenate(src).astype(np.intp)
        self._lam_tgt = np.concatenate(tgt).astype(np.intp)
        # the symbolic pieces, for the compiled stage-split quadratization (solvers.fast_ilq)
        self._quad_sym = (Xs, Us, p, C, E, ca.vertcat(*outs), phi_out, r_traj)
        # for the quadratization with blended kinks, built when a solve first needs it
        self._blend_sym = (Xs, Us, p, x_flat, u_flat, z, C, E, grads, player_rows, hess_sel)
        self._blend_sym += (phi_out,)
        self.Lam = np.zeros(n_stage + N * n * n)  # stages 0..K-1, then the terminal stage
        self.Phi = np.zeros((K, self.nxs + 1, n))
        self.Phi[:, self.nxs, n - 1] = 1.0
        self.Phi[:, nx + np.arange(self.na), prev] = 1.0  # Y_{k+1} = (U_k, X_k)[aug]

    def _lam_index(self, k, i, a, b, n_stage):
        """Flat index into ``self.Lam`` of entry ``(a, b)`` of player ``i`` at stage ``k``.

        Stages ``k < K`` fill ``(K, N, n, n)``; stage ``K`` fills the terminal ``(N, n, n)``
        block after it (its ``(x, 1)`` rows and columns, same positions as other stages).
        """
        n, N = self.n, self.N
        k = np.asarray(k)
        return np.where(k < self.K, ((k * N + i) * n + a) * n + b, n_stage + (i * n + a) * n + b)

    def _build_rollout(self):
        K, nx, nu, nxs = self.K, self.nx, self.nu, self.nxs
        x0 = ca.SX.sym("x0", nx)
        Xr = ca.SX.sym("Xr", nx, K + 1)
        Ur = ca.SX.sym("Ur", nu, K)
        PA = ca.SX.sym("PA", (nxs + 1) * nu, K)
        eps = ca.SX.sym("eps")
        x = x0
        X, U = [x0], []
        dy = ca.SX.zeros(self.na)  # deviation of the carried variables Y_k (none at k = 0)
        aug = self.aug.tolist()
        for k in range(K):
            pa = ca.reshape(PA[:, k], nxs + 1, nu).T  # row-major (nu, nxs+1) block of stage k
            dx = ca.vertcat(x - Xr[:, k], dy)
            u = Ur[:, k] - ca.mtimes(pa[:, :nxs], dx) - eps * pa[:, nxs]
            if self.na:
                dy = ca.vertcat(u - Ur[:, k], x - Xr[:, k])[aug]
            x = self._joint_step(x, u)
            X.append(x)
            U.append(u)
        self.roll = _Call(
            ca.Function(
                "ilq_rollout",
                [x0, Xr, Ur, PA, eps],
                [ca.horzcat(*X), ca.horzcat(*U)],
                ["x0", "Xr", "Ur", "PA", "eps"],
                ["X", "U"],
            )
        )
        blocks = [self.game.params[f"x0.{a}"] for a in self.game.agent_names]
        self._x0_idx = np.concatenate(
            [np.arange(b.start, b.start + b.size) for b in blocks]
        ).astype(np.intp)

    def _build_riccati_indices(self):
        N, nu, nx, n = self.N, self.nu, self.nxs, self.n
        owner = np.concatenate([np.full(self.game.nu[i], i) for i in range(N)]).astype(np.intp)
        self._row_p, self._row_r = owner, np.arange(nu, dtype=np.intp)
        self._own_diag = (owner, np.arange(nu, dtype=np.intp), np.arange(nu, dtype=np.intp))
        self._Psi = np.zeros((n, nx + 1))
        self._Psi[nu:, :] = np.eye(nx + 1)
        self._term = np.r_[nu + np.arange(nx), n - 1].astype(np.intp)
        # own 2x2 blocks (every agent with two controls): flat indices of h00, h11, h01, h10
        self._own2 = None
        if all(m == 2 for m in self.game.nu):
            u0 = self.uo[:-1]
            base = np.arange(N) * n * n
            self._own2 = np.stack(
                [
                    base + u0 * n + u0,
                    base + (u0 + 1) * n + u0 + 1,
                    base + u0 * n + u0 + 1,
                    base + (u0 + 1) * n + u0,
                ]
            ).astype(np.intp)

    # ---- numeric pieces ---------------------------------------------------------------------
    def rollout(self, p, Xr, Ur, PA, eps, compiled: bool = False):
        """Closed-loop rollout ``U_k = Ur_k - P_k (X_k - Xr_k) - eps a_k``: ``(X, U)``.

        ``compiled``: the generated-C stage fold when :meth:`compile` built it.
        """
        if compiled and self._croll is not None:
            X, U = self._croll(p[self._x0_idx], Xr, Ur, PA, eps)
        else:
            X, U = self.roll(p[self._x0_idx], Xr, Ur, PA, eps)
        return X.reshape(self.K + 1, self.nx).copy(), U.reshape(self.K, self.nu).copy()

    def quadratize(self, X, U, p, compiled: bool = False):
        """Costs ``C`` and energy ``E`` at ``(X, U)``; fills ``self.Lam`` and ``self.Phi``.

        ``compiled``: with the generated-C stage functions when :meth:`compile` built them
        (:mod:`solvers.fast_ilq`), else the interpreted trajectory function.
        """
        if self.kink_pins is not None:  # kinks at given slopes (an equilibrium on a kink)
            C, E, lam, phi = self._pin_quad(X, U, p, self.kink_width, self.kink_pins)
        elif self.kink_width > 0:  # blended kinks (interpreted; only after a failed search)
            C, E, lam, phi = self._kink_quad[0](X, U, p, self.kink_width)
        elif compiled and self._cquad is not None:
            return self._cquad(X, U, p)
        else:
            C, E, lam, phi = self.quad(X, U, p)
        self.Lam[self._lam_tgt] = lam[self._lam_src]
        self.Phi.reshape(-1)[self._phi_tgt] = phi
        return C.copy(), float(E[0])

    def _trial_fn(self, compiled: bool):
        """The one-call trial (rollout, quadratization, Riccati: :class:`solvers.fast_ilq.
        CompiledTrial`) where :meth:`quadratize` would use the compiled stage functions with
        the game's costs, else ``None``."""
        if compiled and self.kink_pins is None and self.kink_width <= 0:
            return self._ftrial
        return None

    def _own_shift(self, T, delta):
        """Shift per player so that its own block ``T_i[u_i, u_i]`` has pivots >= delta.

        ``0`` when the ``LDL'`` pivots are all ``>= delta``, else ``max(delta - g, delta)``
        with ``g`` the Gershgorin lower bound of the block's eigenvalues.
        """
        if self._own2 is not None:  # closed-form pivots of 2x2 blocks
            h00, h11, h01, h10 = T.reshape(-1)[self._own2]
            with np.errstate(divide="ignore", invalid="ignore"):
                ok = (h00 >= delta) & (h11 - h01 * h10 / h00 >= delta)
            if ok.all():
                return None
            gersh = np.minimum(h00 - np.abs(h01), h11 - np.abs(h10))
            return np.where(ok, 0.0, _shift(gersh, delta))
        mu = np.zeros(self.N)
        for i in range(self.N):
            s = slice(self.uo[i], self.uo[i + 1])
            H = T[i, s, s]
            if not _pivots_ok(H, delta):
                d = np.diag(H)
                gersh = np.min(d - (np.sum(np.abs(H), axis=1) - np.abs(d))) if d.size else 0.0
                mu[i] = _shift(gersh, delta)
        return mu if mu.any() else None

    def backward(self, mu0: float, delta: float):
        """Coupled Riccati recursion on ``self.Lam``/``self.Phi``.

        Returns ``(PA, mu, ok)``: ``PA (K, nu, nx+1)`` holds ``[P_k | a_k]``, ``mu (K, N)``
        the shift added to each player's own block (``mu0`` included), ``ok`` False when
        a stage could not be solved (non-finite numbers).
        """
        if self._compiled is not None:
            return self._compiled.backward(mu0, delta)
        K, N, nu, nx, n = self.K, self.N, self.nu, self.nxs, self.n
        Lam = self.Lam[: K * N * n * n].reshape(K, N, n, n)
        LamK = self.Lam[K * N * n * n :].reshape(N, n, n)
        t = self._term
        Z = LamK[:, t[:, None], t[None, :]]
        PA = np.empty((K, nu, nx + 1))
        mus = np.full((K, N), float(mu0))
        Psi = self._Psi
        od, rp, rr = self._own_diag, self._row_p, self._row_r
        ok = True
        with np.errstate(all="ignore"):
            for k in range(K - 1, -1, -1):
                Ph = self.Phi[k]
                T = Ph.T @ (Z @ Ph)
                T += Lam[k]
                if mu0:
                    T[od] += mu0
                mu = self._own_shift(T, delta)
                if mu is not None:
                    T[od] += mu[rp]
                    mus[k] += mu
                extra = 0.0
                for _ in range(20):  # singular coupled system: shift every own block more
                    rows = T[rp, rr]
                    try:
                        pa = np.linalg.solve(rows[:, :nu], rows[:, nu:])
                        if np.isfinite(pa).all():
                            break
                    except np.linalg.LinAlgError:
                        pass
                    step = max(10.0 * extra, delta, 1e-8)
                    T[od] += step - extra
                    extra = step
                else:
                    ok = False
                    break
                mus[k] += extra
                PA[k] = pa
                Psi[:nu] = -pa
                Z = Psi.T @ (T @ Psi)
            if ok and not np.isfinite(Z).all():
                ok = False
        return PA, mus, ok

    def compile(self) -> ILQSolver:
        """Build the generated-C paths used with ``compiled=True``.

        The Riccati recursion (:class:`_CompiledRiccati`), the rollout (a stage folded over
        the horizon) and, where the costs split into stage functions, the quadratization
        (:mod:`solvers.fast_ilq`; :attr:`quad_backend` is then ``"compiled"``). All are
        cached on disk per structure.
        """
        if self._compiled is None:
            from . import fast_ilq

            fast_ilq.compile_solver(self)  # one library; also the one-call trial (_ftrial)
        return self

    def riccati_fold(self) -> _CompiledRiccati:
        """The generated Riccati recursion of this solver, built but not compiled
        (:func:`solvers.fast_ilq.compile_solver` compiles it into the solver's library)."""
        return _CompiledRiccati(self, compile_now=False)

    # ---- the solve ------------------------------------------------------------------------
    def solve(
        self, p: np.ndarray, u0: np.ndarray | None = None, options: ILQOptions | dict | None = None
    ) -> SolveResult:
        """Solve one problem: ``p (n_p,)``, ``u0 (n_u,)`` (zeros if None)."""
        opts = check_options(ILQOptions, options, "ilq")
        if opts.hessian not in ("auto", self.hessian):
            raise SpecError(
                "ilq.hessian",
                f"this solver was built with hessian={self.hessian!r}, options ask for {opts.hessian!r}",
            )
        if opts.compiled:
            self.compile()
        backward = (
            self.backward if opts.compiled or self._compiled is None else self._numpy_backward
        )
        t0 = time.perf_counter()
        g = self.game
        U0, P = g.check_inputs(g.zero_controls() if u0 is None else u0, p)
        if U0.shape[0] != 1:
            raise SpecError("u0/p", "ILQSolver.solve takes one problem; solve_ilq takes a batch")
        res = self._solve_once(P[0], U0[0], opts, backward, opts.max_iter, t0)
        if not (
            opts.restart
            and not self.custom_costs
            and res.status is Status.STALLED
            and res.info["stop"] in _RESTART_STOPS
            and res.iterations < opts.max_iter
        ):
            return res
        # iLQ's own safeguards failed (typically far from an equilibrium, in collision):
        # start once more from the open-loop equilibrium, the potential's minimizer
        from .lm import solve_lm

        lm = solve_lm(g, P[0], U0[0])
        again = self._solve_once(
            P[0], np.asarray(lm.controls), opts, backward, opts.max_iter - int(res.iterations), t0
        )
        info = {"at": int(res.iterations), "stop": res.info["stop"], "lm_status": lm.status.value}
        # the restart's result when it converged or found a kink equilibrium, else the first
        keep = again if again.status is Status.CONVERGED or again.info["stop"] == "kink" else res
        return dataclasses.replace(
            keep,
            iterations=np.int64(int(res.iterations) + int(again.iterations)),
            wall_time=time.perf_counter() - t0,
            info={**keep.info, "restart": {**info, "result": again.info["stop"]}},
        )

    def _solve_once(self, p, u0, opts, backward, max_iter, t0) -> SolveResult:
        """One iLQ solve of problem ``p (n_p,)`` from ``u0 (n_u,)``, at most ``max_iter``
        iterations (the iteration of the module docstring)."""
        g = self.game
        _, Ubar = to_stages(g, None, u0)
        Xbar, Ubar = self.rollout(
            p,
            np.zeros((self.K + 1, self.nx)),
            Ubar,
            np.zeros((self.K, self.nu, self.nxs + 1)),
            0.0,
            opts.compiled,
        )
        mu0, delta = float(opts.regularization), float(opts.min_curvature)
        mu_run = mu0  # raised 10x when a backward or forward pass fails, lowered after success

        def linearize(X, U, lin=None):
            if lin is not None:  # computed by the one-call trial (solvers.fast_ilq)
                C, E, PA, mu, ok = lin
            elif self._trial_fn(opts.compiled) is not None:
                C, E, PA, mu, ok = self._ftrial(p, X, U, None, 0.0, mu_run, delta)[2:]
            else:
                C, E = self.quadratize(X, U, p, opts.compiled)
                PA, mu, ok = backward(mu_run, delta)
            a = np.ascontiguousarray(PA[:, :, -1])  # gathered once (feed-forward terms)
            res = float(np.max(np.abs(a))) if self.K else 0.0
            finite = ok and math.isfinite(res) and bool(np.isfinite(C).all())
            # RMS of a; math.fsum is exactly rounded, so the merit (and every accept/reject
            # decision) does not depend on summation order, SIMD alignment or BLAS threads
            a2 = (a * a).ravel().tolist()
            merit = math.sqrt(math.fsum(a2) / len(a2)) if a2 else 0.0
            return C, E, PA, mu, res if finite else math.inf, merit if finite else math.inf

        def bump():
            nonlocal mu_run
            if mu_run >= _MAX_MU:
                return False
            mu_run = max(10.0 * mu_run, _MIN_MU)
            return True

        def relinearize(X, U):
            lin = linearize(X, U)
            while not math.isfinite(lin[4]) and bump():
                lin = linearize(X, U)
            return lin

        # kink continuation (ILQOptions.kink_widths): off until the line search fails
        widths = list(opts.kink_widths)
        self.kink_width = 0.0
        continuation: list = []  # (iteration, width) at every change of the width

        def set_width(w):
            self.kink_width = float(w)
            continuation.append((it, self.kink_width))

        it = 0
        on_kink = None  # (X, U, width, max |a|): converged while blended, kinks in the band
        failed_width = 0.0
        C, E, PA, mu, res, merit = relinearize(Xbar, Ubar)
        status = Status.MAX_ITER if math.isfinite(res) else Status.NONFINITE
        stop = "max_iter" if math.isfinite(res) else "nonfinite"
        hist_E, hist_res, steps = [E], [res], []
        merits = [merit]  # merits (RMS of a) at the current regularization, newest last
        eps_next = float(opts.step_size)  # first trial step of the next iteration
        max_mu = _max(mu)
        resets = 0
        rescue = False  # the secant step: only after a line search has failed
        while status is Status.MAX_ITER:
            if res <= opts.tol:
                if mu_run <= mu0 and self.kink_width > 0:
                    # converged with blended kinks: the next (smaller) width, then the exact
                    # kinks; a width whose band holds no kink argument changes nothing
                    w = self.kink_width
                    inside = self.kinks_within(Xbar, Ubar, p, w) > 0
                    nxt = [v for v in widths if v < w] if inside else []
                    if inside:  # a blended solution with kinks in its band
                        on_kink = (Xbar, Ubar, w, res)
                    set_width(nxt[0] if nxt else 0.0)
                    if inside:
                        C, E, PA, mu, res, merit = relinearize(Xbar, Ubar)
                        merits, eps_next = [merit], float(opts.step_size)
                    continue
                if mu_run <= mu0:  # the tolerance holds at the requested regularization
                    status, stop = Status.CONVERGED, "tol"
                    break
                # judged with the regularization the user asked for, never a raised one
                mu_run = mu0
                lin = linearize(Xbar, Ubar)
                resets += 1
                if not math.isfinite(lin[4]):
                    status, stop = Status.STALLED, "singular"
                    break
                if lin[4] > opts.tol and resets > _MAX_RESETS:
                    # the tolerance only holds with raised regularization: not a feedback
                    # Nash point of the game that was asked for
                    C, E, PA, mu, res, merit = lin
                    status, stop = Status.STALLED, "regularized_only"
                    break
                C, E, PA, mu, res, merit = lin
                merits = [merit]
                continue
            if it >= max_iter:
                break
            ref = max(merits[-opts.memory :])
            eps, accepted = eps_next, None
            a_old = PA[:, :, -1]
            for _trial in range(opts.max_backtracks + 1):
                ft, flin = self._trial_fn(opts.compiled), None
                with np.errstate(all="ignore"):
                    if ft is not None and opts.line_search == "residual":
                        Xn, Un, *flin = ft(p, Xbar, Ubar, PA, eps, mu_run, delta)
                    else:
                        Xn, Un = self.rollout(p, Xbar, Ubar, PA, eps, opts.compiled)
                    good = bool(np.isfinite(Xn).all() and np.isfinite(Un).all())
                    if good and opts.max_state_step < math.inf:
                        good = float(np.max(np.abs(Xn - Xbar))) <= opts.max_state_step
                lin = None
                if good and opts.line_search == "residual":
                    lin = linearize(Xn, Un, flin)
                    good = lin[5] <= (1.0 - _ARMIJO * eps) * ref
                if good:
                    accepted = (Xn, Un, lin, eps)
                    break
                eps *= opts.backtrack
            it += 1
            if accepted is None:  # from now on the first trial step adapts (a secant)
                rescue = opts.adaptive_step
            if (
                accepted is None
                and widths
                and not continuation
                and mu_run <= mu0
                and self.has_kinks
            ):
                # no usable step at the exact kinks: blend their curvature and go on
                set_width(widths[0])
                lin, eps = relinearize(Xbar, Ubar), 0.0
                merits, eps_next = [], float(opts.step_size)
            elif (
                accepted is None
                and on_kink is not None
                and mu_run <= mu0
                and self.kink_width <= widths[-1]
            ):
                # converged with the kinks blended (kinks inside the band), and at the last
                # width or the exact kinks no step passes: the solution sits on a kink, where
                # the one-sided curvatures give different gains (docs/ilq.md)
                failed_width = self.kink_width
                Xbar, Ubar = on_kink[0], on_kink[1]
                status, stop = Status.STALLED, "kink"
                break
            elif accepted is None:  # no usable step: more regularization, same trajectory
                if not bump():
                    status, stop = Status.STALLED, "line_search"
                    if mu_run > mu0:  # report max |a| at the requested regularization
                        mu_run = mu0
                        lin = linearize(Xbar, Ubar)
                        if math.isfinite(lin[4]):
                            C, E, PA, mu, res, merit = lin
                    break
                lin, eps = relinearize(Xbar, Ubar), 0.0
                merits = []
                eps_next = float(opts.step_size)
            else:
                Xbar, Ubar, lin, eps = accepted
                eps_next = float(opts.step_size)
                if rescue and lin is not None and mu_run <= mu0:
                    eps_next = _secant_step(a_old, lin[2][:, :, -1], eps, eps_next)
                if mu_run > mu0:  # success: lower the regularization again
                    mu_run = mu_run / 10.0 if mu_run / 10.0 >= _MIN_MU else mu0
                    mu_run = max(mu_run, mu0)
                    merits = []
                if lin is None or not math.isfinite(lin[4]):
                    lin = relinearize(Xbar, Ubar)
            C, E, PA, mu, res, merit = lin
            merits.append(merit)
            steps.append(eps)
            hist_E.append(E)
            hist_res.append(res)
            max_mu = max(max_mu, _max(mu))
            if not math.isfinite(res):
                status, stop = Status.NONFINITE, "nonfinite"
        if self.kink_width > 0:  # stopped while blended: report max |a| at the exact kinks
            set_width(0.0)
            mu_run = mu0
            lin = linearize(Xbar, Ubar)
            if math.isfinite(lin[4]):
                C, E, PA, mu, res, merit = lin
        kink_info = None
        if stop == "kink":  # the blended solution, reported (P, a, max |a|) at the exact kinks
            X1, U1, w, res_w = on_kink
            self.kink_width = w
            (zk,) = self._kink_quad[1](X1, U1, p)
            z = np.array(zk, float).ravel()
            sel = np.flatnonzero(np.abs(z) < 0.5 * w)
            kink_info = {
                "width": w,
                "stationarity": res_w,
                "kinks": [(int(i), float(z[i]), float(z[i] / w + 0.5)) for i in sel],
            }
            at = "the exact kinks" if failed_width == 0 else f"w = {failed_width:g}"
            kink_info["message"] = (
                f"no feedback equilibrium at the exact kinks: max |a| <= tol only with the kinks' "
                f"curvature blended over w = {w:g} ({len(sel)} kink argument(s) inside the band, "
                f"|z| <= {float(np.max(np.abs(z[sel]))):.1e}), and at {at} no step passes the "
                f"line search: the blended solution keeps kink arguments inside the band, so the "
                f"equilibrium likely sits on a kink, where the one-sided curvatures give "
                f"different gains"
            )
            kink_info["failed_width"] = failed_width
            # the blended policy (passes the sampled feedback-Nash check on the family games)
            PAw = linearize(X1, U1)[2]
            kink_info["gains"] = PAw[:, :, : self.nx].copy()
            kink_info["gains_prev"] = PAw[:, :, self.nx : self.nxs].copy()
            kink_info["feedforward"] = PAw[:, :, self.nxs].copy()
            self.kink_width = 0.0
            C, E, PA, mu, res, merit = linearize(X1, U1)
            kink_info["exact_stationarity"] = res
            kink_info["certified"] = False
            if opts.kink_equilibrium:  # an equilibrium on the kink (docs/ilq.md)
                theta = np.clip([t for _, _, t in kink_info["kinks"]], 0.0, 1.0)
                eq = self._kink_equilibrium(p, U1, sel, theta, opts, backward)
                kink_info["equilibrium"] = _kink_summary(eq, opts.tol)
                it += eq["iterations"]  # the pinned solves' iterations
                if eq["ok"]:
                    kink_info["certified"] = True
                    kink_info["message"] = kink_info["equilibrium"]["message"]
                    Xbar, Ubar = eq["X"], eq["U"]
                    C, E, PA, mu, res = eq["C"], eq["E"], eq["PA"], eq["mu"], eq["stationarity"]
                    status, stop = Status.CONVERGED, "kink_equilibrium"
        x, u = from_stages(g, Xbar, Ubar)
        grad_norm = math.nan
        if not self.custom_costs:
            if self._grad is None:  # buffers bound once (a plain call converts to DM)
                self._grad = _Call(g.function("gradient"))
            grad_norm = float(np.max(np.abs(self._grad(u, p)[0]))) if g.n_u else 0.0
        return SolveResult(
            solver="ilq",
            controls=u,
            states=x,
            energy=np.float64(E),
            agent_costs=np.asarray(C, float).reshape(-1),
            status=status,
            iterations=np.int64(it),
            energy_history=np.asarray(hist_E, float),
            grad_norm=np.float64(grad_norm),
            wall_time=time.perf_counter() - t0,
            info={
                "gains": PA[:, :, : self.nx].copy(),
                "gains_prev": PA[:, :, self.nx : self.nxs].copy(),
                "prev_variables": self.aug.copy(),
                "feedforward": PA[:, :, self.nxs].copy(),
                "stationarity": res,
                "stop": stop,
                "residual_history": np.asarray(hist_res, float),
                "step_sizes": np.asarray(steps, float),
                "regularization": mu,
                "max_regularization": max_mu,
                "kink_continuation": continuation,
                "kink_equilibrium": kink_info,
                "hessian": self.hessian,
                "custom_costs": self.custom_costs,
                "backend": "compiled" if opts.compiled else "numpy",
                "options": opts,
            },
        )

    def _kink_equilibrium(self, p, U1, sel, theta, opts, backward) -> dict:
        """An equilibrium on the kinks ``sel`` near the blended solution ``U1`` (stages).

        Pinned solves (:attr:`kink_pins`: kink ``j`` of ``sel`` at Gauss-Newton curvature
        ``theta_j^2``, the other kinks exact, to ``tol / 100``) and Newton steps on
        ``theta`` (:func:`_kink_newton`) until every ``|z_j| <= 1e-2 min(kink_widths)``
        (at most ``_PIN_BUDGET`` pinned iterations); then ``max |a|`` with those curvatures at the
        requested regularization and the feedback-Nash check of the policy
        (:mod:`solvers.feedback_nash`). A dict: ``ok`` and the figures, or ``ok = False``
        and a ``reason`` when no such point was found (docs/ilq.md, "Equilibria on a
        kink")."""
        from .feedback_nash import feedback_nash_check

        g = self.game
        if self._pin_quad is None:
            self._pin_quad = self._build_kink_quad(pinned=True)[0]
        zfun = self._kink_quad[1]
        m = int(zfun.f.size1_out(0))
        ztol = 1e-2 * min(opts.kink_widths)
        sub = dataclasses.replace(
            opts, kink_widths=(), restart=False, tol=1e-2 * opts.tol, max_iter=_PIN_ITER
        )
        total = 0

        def pinned(sel, th, u):
            nonlocal total
            if total >= _PIN_BUDGET:
                raise _KinkBudget
            pins = np.full(m, -1.0)
            pins[sel] = th
            self.kink_pins = pins
            try:
                r = self._solve_once(p, u, sub, backward, sub.max_iter, time.perf_counter())
            finally:
                self.kink_pins = None
            total += int(r.iterations)
            X, U = to_stages(g, r.states, r.controls)
            (zk,) = zfun(X, U, p)
            ok = r.status is Status.CONVERGED
            return r, np.asarray(zk, float).ravel()[sel], ok

        sel = np.asarray(sel, int).copy()
        try:
            found = _kink_newton(pinned, sel, theta, from_stages(g, None, U1)[1], ztol)
        except _KinkBudget:
            found = f"the pinned solves used up {_PIN_BUDGET} iterations"
        if not isinstance(found, tuple):
            why = found or (
                "a pinned solve failed, or the Newton steps on theta did not bring the kink "
                f"arguments to |z| <= {ztol:g}"
            )
            return {"ok": False, "iterations": total, "reason": why}
        r, sel, th, z = found
        # max |a| with those curvatures at the requested regularization (a fresh pass)
        X, U = to_stages(g, r.states, r.controls)
        self.kink_pins = np.full(m, -1.0)
        self.kink_pins[sel] = th
        try:
            C, E = self.quadratize(X, U, p, opts.compiled)
            PA, mu, fin = backward(float(opts.regularization), float(opts.min_curvature))
        finally:
            self.kink_pins = None
        res = float(np.max(np.abs(PA[:, :, -1]))) if self.K else 0.0
        check = feedback_nash_check(
            g,
            p,
            r.states,
            r.controls,
            PA[:, :, : self.nx],
            PA[:, :, self.nxs],
            gains_prev=PA[:, :, self.nx : self.nxs],
            prev_variables=self.aug,
        )
        return {
            "ok": bool(fin and res <= opts.tol and check.ok),
            "result": r,
            "X": X,
            "U": U,
            "C": C,
            "E": E,
            "PA": PA,
            "mu": mu,
            "stationarity": res,
            "kinks": sel,
            "theta": th,
            "z": z,
            "iterations": total,
            "check": check,
        }

    def _numpy_backward(self, mu0, delta):
        compiled, self._compiled = self._compiled, None
        try:
            return self.backward(mu0, delta)
        finally:
            self._compiled = compiled


_MAX_MU = 1e8  # largest global regularization the adaptive retries reach
_MIN_MU = 1e-4  # first raised regularization; below it, a lowered one returns to mu0
_RESTART_STOPS = ("line_search", "regularized_only")  # stalled solves that restart
_MAX_RESETS = 2  # returns to the requested regularization before a solve is called stalled
_MIN_STEP = 1e-2  # smallest first trial step the secant predicts (relative to step_size)
_ARMIJO = 0.1  # sufficient decrease of the merit per unit step: (1 - c eps) x reference
_PIN_ITER = 120  # iterations of one pinned solve (kinks at fixed curvature; linear rate)
_KINK_NEWTON = 8  # Newton steps on the kinks' blend fractions theta (z(theta) ~ linear)
_THETA_FD = 1e-3  # step of theta in the finite-difference Jacobian of z(theta)
_PIN_BUDGET = 1500  # pinned iterations of one search for an equilibrium on a kink
_KINK_HALVINGS = 4  # halvings of a Newton step on theta before the search gives up


def _smooth_kinks(f: ca.Function, pinned: bool = False) -> ca.Function | None:
    """``f`` (an SX function) with the curvature of its kinks blended over a width ``w``.

    Returns ``(f's inputs, w) -> (r, z)``: ``r`` is ``f`` with every ``fmax(a, b) = a +
    relu(b - a)`` replaced by ``a + g(b - a)`` (``fmin(a, b) = a - relu(a - b)`` likewise),
    ``g' = clip(z / w + 1/2, 0, 1)``: equal to ``relu`` (values and derivatives) outside
    ``|z| < w/2``, a quadratic blend inside, ``relu`` itself at ``w = 0``; ``z`` are the
    kink arguments ``b - a`` (``a - b`` for ``fmin``). ``None`` when ``f`` has no kink, is
    not an SX function or holds operations not replayed here (calls).

    ``pinned``: one more input ``s`` (one entry per kink): kink ``j`` with ``s_j >= 0``
    has the slope ``s_j`` in ``r``'s Jacobian whatever its argument (``r`` itself is then
    not ``f``'s: only the Jacobian is used, for Gauss-Newton curvature ``s_j^2``), the
    others are blended over ``w`` as above (``w = 0``: exact).
    """
    if not f.is_a("SXFunction"):
        return None
    ops = [f.instruction_id(k) for k in range(f.n_instructions())]
    if ca.OP_FMAX not in ops and ca.OP_FMIN not in ops:
        return None
    zs, ws = ca.SX.sym("z"), ca.SX.sym("w")
    h = 0.5 * ws
    inner = (zs + h) ** 2 / (2 * ca.fmax(ws, 1e-300))
    blend = ca.if_else(zs <= -h, 0, ca.if_else(zs >= h, zs, inner))
    # one call per kink (evaluated symbolically in C++ and inlined into the new graph)
    relu = ca.Function("smooth_relu", [zs, ws], [blend])
    ins = [ca.SX.sym(f"i{i}", f.sparsity_in(i)) for i in range(f.n_in())]
    w_in = ca.SX.sym("w")
    out_nz = [[ca.SX(0)] * f.nnz_out(i) for i in range(f.n_out())]
    kinks, pins = [], []
    work: dict = {}
    for k, op in enumerate(ops):
        a, o = f.instruction_input(k), f.instruction_output(k)
        if op == ca.OP_CONST:
            work[o[0]] = ca.SX(f.instruction_constant(k))
        elif op == ca.OP_INPUT:
            work[o[0]] = ins[a[0]].nz[a[1]]
        elif op == ca.OP_OUTPUT:
            out_nz[o[0]][o[1]] = work[a[0]]
        elif op in (ca.OP_FMAX, ca.OP_FMIN):
            x, y = work[a[0]], work[a[1]]
            z = y - x if op == ca.OP_FMAX else x - y
            kinks.append(z)
            g = relu(z, w_in)
            if pinned:
                pins.append(ca.SX.sym(f"s{len(pins)}"))
                g = ca.if_else(pins[-1] >= 0, pins[-1] * z, g)
            work[o[0]] = x + g if op == ca.OP_FMAX else x - g
        elif len(a) == 2 and len(o) == 1:
            work[o[0]] = ca.SX.binary(op, work[a[0]], work[a[1]])
        elif len(a) == 1 and len(o) == 1:
            work[o[0]] = ca.SX.unary(op, work[a[0]])
        else:  # calls or other multi-argument operations
            return None
    outs = [
        ca.SX(f.sparsity_out(i), ca.vertcat(*nz)) if nz else ca.SX(f.sparsity_out(i))
        for i, nz in enumerate(out_nz)
    ]
    if len(outs) != 1:
        return None
    if pinned:
        s_in = ca.vertcat(*pins)
        return ca.Function(f.name() + "_pinned", [*ins, w_in, s_in], [outs[0], ca.vertcat(*kinks)])
    return ca.Function(f.name() + "_kinks", [*ins, w_in], [outs[0], ca.vertcat(*kinks)])


def _kink_newton(pinned, sel, theta, u0, ztol):
    """Newton steps on the blend fractions ``theta`` of the kinks ``sel`` until every kink
    argument ``|z_j| <= ztol``: ``pinned(sel, theta, u) -> (result, z, ok)`` solves with
    those kinks at fixed curvature ``theta^2`` from ``u``. The Jacobian of ``z(theta)`` by
    finite differences, then Broyden updates; steps halved until the pinned solve
    converges and ``max |z|`` drops; a kink whose ``theta`` would leave ``[0, 1]`` is
    released (exact curvature). ``(result, sel, theta, z)`` or ``None``."""
    th = np.asarray(theta, float).copy()
    r, z, ok = pinned(sel, th, u0)
    if not ok:
        return None
    J = None
    for _ in range(_KINK_NEWTON):
        if _max_abs(z) <= ztol:
            break
        if J is None:  # finite differences of z(theta), one pinned solve per kink
            J = np.empty((th.size, th.size))
            for j in range(th.size):
                h = -_THETA_FD if th[j] > 0.5 else _THETA_FD
                t2 = th.copy()
                t2[j] += h
                _, z2, ok2 = pinned(sel, t2, r.controls)
                if not ok2:
                    return None
                J[:, j] = (z2 - z) / h
        try:
            step = np.linalg.solve(J, z)
        except np.linalg.LinAlgError:
            return None
        if not np.isfinite(step).all():
            return None
        keep = (th - step >= 0) & (th - step <= 1)
        if not keep.all():  # theta leaves [0, 1]: that kink is released (exact
            sel, th, J = sel[keep], th[keep], None  # curvature), the others stay
            r, z, ok = pinned(sel, th, r.controls)
            if not ok:
                return None
            continue
        for _half in range(_KINK_HALVINGS):  # damped: the pinned solve converges, |z| drops
            r2, z2, ok2 = pinned(sel, th - step, r.controls)
            if ok2 and _max_abs(z2) < _max_abs(z):
                break
            step = 0.5 * step
        else:
            return None
        J += np.outer(z2 - z + J @ step, -step) / float(step @ step)  # Broyden update
        th, r, z = th - step, r2, z2
    if _max_abs(z) > ztol:
        return None
    return r, sel, th, z


class _KinkBudget(Exception):
    """The pinned solves of one search used up ``_PIN_BUDGET`` iterations."""


def _max_abs(v) -> float:
    return float(np.max(np.abs(v))) if np.size(v) else 0.0


def _kink_summary(eq: dict, tol: float) -> dict:
    """``info["kink_equilibrium"]["equilibrium"]``: what the search for an equilibrium on
    the kinks found (:meth:`ILQSolver._kink_equilibrium`)."""
    if "reason" in eq:
        return {
            "ok": False,
            "iterations": eq["iterations"],
            "message": f"no equilibrium on the kinks: {eq['reason']}",
        }
    c = eq["check"]
    kinks = [
        (int(i), float(t), float(z))
        for i, t, z in zip(eq["kinks"], eq["theta"], eq["z"], strict=True)
    ]
    out = {
        "ok": eq["ok"],
        "kinks": kinks,  # (index, theta, z): curvature theta^2 of kink argument z
        "stationarity": eq["stationarity"],
        "feedback_nash": bool(c.ok),
        "feedback_nash_gain": float(c.max_relative_gain),
        "iterations": eq["iterations"],
    }
    th = ", ".join(f"{t:.4f}" for _, t, _ in kinks)
    zmax = max((abs(z) for _, _, z in kinks), default=0.0)
    if eq["ok"]:
        out["message"] = (
            f"feedback equilibrium on {len(kinks)} kink(s): max |a| {eq['stationarity']:.1e} <= "
            f"tol with the kinks' Gauss-Newton curvature theta^2 (theta {th}, an element of "
            f"the hinge's generalized Hessian) at |z| <= {zmax:.1e}; the feedback-Nash check "
            f"passes (largest relative gain {c.max_relative_gain:.1e})"
        )
    else:
        why = []
        if not eq["stationarity"] <= tol:
            why.append(f"max |a| {eq['stationarity']:.1e} > tol {tol:g}")
        if not c.ok:
            why.append(f"the feedback-Nash check fails ({c.max_relative_gain:.1e})")
        if not why:
            why.append("the pass with those curvatures is not finite")
        out["message"] = f"no equilibrium on the kinks (theta {th}): " + "; ".join(why)
    return out


def _secant_step(a_old, a_new, eps, cap):
    """First trial step of the next iteration from the last accepted one (a secant).

    Along the last direction the feed-forward went from ``a_old`` to ``a_new`` with step
    ``eps``; with ``rho = <a_new, a_old> / |a_old|^2`` the linear model
    ``a(e) = (1 - e (1 - rho) / eps) a_old`` vanishes at ``e = eps / (1 - rho)`` (at most
    ``cap``). An iteration that overshoots (``a`` flips sign: ``rho = -0.97`` gives about
    half a step) is damped; after a damped step the model is refitted (``rho ~ 0``: it
    fitted, keep the step; ``rho = 1/2``: twice the step). After a full step only a clear
    overshoot (``rho < -1/4``) damps, so an iteration that converges with full steps keeps
    them.
    """
    den = float(np.vdot(a_old, a_old))
    if not den > 0:
        return cap
    rho = float(np.vdot(a_new, a_old)) / den
    if not (math.isfinite(rho) and rho < 1.0) or (eps >= cap and rho >= -0.25):
        return cap
    return min(cap, max(_MIN_STEP * cap, eps / (1.0 - rho)))


def _max(a):
    a = np.asarray(a, float)
    m = float(a.max()) if a.size else 0.0
    if math.isfinite(m):  # the common case, without the masked copy
        return m
    a = a[np.isfinite(a)]
    return float(a.max()) if a.size else 0.0


def _shift(g, delta):
    """Shift of an own block with Gershgorin bound ``g`` that failed the pivot test.

    ``delta - g`` lifts the smallest eigenvalue to ``>= delta``; negative curvature is
    mirrored on top (``+ |g|``), so a concave direction gets curvature of its own size
    instead of a near-singular ``delta`` (which would give gains of order ``1/delta``).
    """
    return np.maximum(delta - g, delta) + np.maximum(-g, 0.0)


def _pivots_ok(H, delta):
    try:
        L = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        return False
    return bool(np.min(np.diag(L)) ** 2 >= delta) if L.size else True


class _CompiledRiccati:
    """The backward recursion as one generated-C function: a stage folded over ``K`` stages.

    The stage function does the numpy recursion's algebra in CasADi SX with the structural
    zeros of ``L_ik`` and ``Phi_k`` (union pattern over stages) and the same own-block shift
    (closed ``LDL'`` pivots, Gershgorin). The symmetric products ``T_i = L_ik + Phi' Z Phi``
    and ``Z_ik = Psi' T_i Psi`` are computed on their upper triangle and mirrored
    (:func:`_sym_product`: 14.7k instead of 23.3k instructions for 3 unicycles, compile
    2.3 s instead of 3.9 s of CPU at ``-O1``; ``-O2``/``-O3`` took twice as long to compile
    and ran within 10 %). A stage whose coupled system is singular is not
    retried inside; the caller sees non-finite gains and the numpy recursion takes over.
    """

    def __init__(self, s: ILQSolver, compile_now: bool = True):
        from .codegen import compile_functions

        self.s = s
        K, N, nu, nx, n = s.K, s.N, s.nu, s.nxs, s.n
        # union pattern of the stage matrices L_ik (k < K), per player
        lt = s._lam_tgt[s._lam_tgt < K * N * n * n]
        rem = lt % (N * n * n)
        pats = []
        for i in range(N):
            e = np.unique(rem[(rem // (n * n)) == i] % (n * n))
            r, c = e // n, e % n
            order = np.lexsort((r, c))  # column-major, CasADi's nonzero order
            pats.append((r[order], c[order]))
        self._lam_cols = np.concatenate(
            [i * n * n + r * n + c for i, (r, c) in enumerate(pats)]
        ).astype(np.intp)
        pr = s._phi_pattern // n
        pc = s._phi_pattern % n
        order = np.lexsort((pr, pc))
        # entries of Phi_k equal to 1 at every stage (the identity in A_k of the built-in
        # models) are numbers in the stage function, not inputs: a product with 1 is
        # exact, so nothing changes by a bit (14.0k instead of 14.7k instructions for 3
        # unicycles)
        one = _ones_at_every_stage(s._quad_sym[6], K, s._phi_pattern.size)[order]
        self._phi_cols = s._phi_pattern[order][~one].astype(np.intp)
        pr, pc = pr[order], pc[order]

        Zin = ca.SX.sym("Z", nx + 1, N * (nx + 1))
        lam = ca.SX.sym("lam", self._lam_cols.size)
        phi = ca.SX.sym("phi", self._phi_cols.size)
        mu0 = ca.SX.sym("mu0")
        delta = ca.SX.sym("delta")
        Ph = ca.SX(ca.Sparsity.triplet(nx + 1, n, pr[~one].tolist(), pc[~one].tolist()), phi)
        ones_r = [s.nx + m for m in range(s.na)] + [nx] + pr[one].tolist()
        ones_c = [int(c) for c in s.aug] + [n - 1] + pc[one].tolist()
        Ph = Ph + ca.SX(ca.Sparsity.triplet(nx + 1, n, ones_r, ones_c), ca.SX.ones(len(ones_r)))
        Ts, off, mus = [], 0, []
        for i, (r, c) in enumerate(pats):
            L = ca.SX(ca.Sparsity.triplet(n, n, r.tolist(), c.tolist()), lam[off : off + r.size])
            off += r.size
            Z = Zin[:, i * (nx + 1) : (i + 1) * (nx + 1)]
            T = L + _sym_product(Ph, ca.mtimes(Z, Ph))
            s0, s1 = int(s.uo[i]), int(s.uo[i + 1])
            H = T[s0:s1, s0:s1] + mu0 * ca.SX.eye(s1 - s0)
            piv = _ldl_pivots(H)
            ok = piv[0] >= delta
            for d in piv[1:]:
                ok = ca.logic_and(ok, d >= delta)
            gersh = _gershgorin(H)
            mu = ca.if_else(ok, 0, ca.fmax(delta - gersh, delta) + ca.fmax(-gersh, 0))
            mus.append(mu0 + mu)
            D = ca.SX(n, n)
            D[s0:s1, s0:s1] = (mu0 + mu) * ca.SX.eye(s1 - s0)
            Ts.append(T + D)
        rows = ca.vertcat(*[Ts[i][int(s.uo[i]) : int(s.uo[i + 1]), :] for i in range(N)])
        PA = ca.solve(rows[:, :nu], rows[:, nu:])
        Psi = ca.vertcat(-PA, ca.SX.eye(nx + 1))
        Zout = []
        for T in Ts:
            Zout.append(_sym_product(Psi, ca.mtimes(T, Psi)))
        stage = ca.Function(
            "ilq_riccati_stage",
            [Zin, lam, phi, mu0, delta],
            [ca.horzcat(*Zout), ca.vec(PA.T), ca.vertcat(*mus)],
        )
        self.n_instructions = stage.n_instructions()
        # The fold over K stages is a loop in the generated C around one stage function, so
        # compile time does not grow with K (the library is cached per structure, K included:
        # folding a K-independent compiled stage in CasADi's VM cost 0.8 us more per stage)
        acc = stage.mapaccum("ilq_riccati", K)  # CasADi may nest and rename it for large K
        self.acc = ca.Function("ilq_riccati", acc.mx_in(), acc.call(acc.mx_in()))
        self.call = None
        if compile_now:  # else solvers.fast_ilq.compile_solver compiles it with the rest
            self.attach(compile_functions([self.acc], "ilq_riccati", optimize="-O1"))

    def attach(self, lib: dict) -> None:
        """Use the compiled fold ``lib['ilq_riccati']``."""
        self.call = _Call(lib["ilq_riccati"])

    def backward(self, mu0, delta):
        s = self.s
        K, N, nu, nx, n = s.K, s.N, s.nu, s.nxs, s.n
        Lam = s.Lam[: K * N * n * n].reshape(K, N * n * n)
        LamK = s.Lam[K * N * n * n :].reshape(N, n, n)
        t = s._term
        Z = LamK[:, t[:, None], t[None, :]]  # (N, nx+1, nx+1) -> column-major (nx+1, N(nx+1))
        Zc = np.ascontiguousarray(Z.transpose(0, 2, 1)).reshape(-1)
        lam = Lam[::-1][:, self._lam_cols]
        phi = s.Phi.reshape(K, -1)[::-1][:, self._phi_cols]
        _, PA, mu = self.call(Zc, lam, phi, np.full(K, float(mu0)), np.full(K, float(delta)))
        PA = PA.reshape(K, nu, nx + 1)[::-1].copy()
        mu = mu.reshape(K, N)[::-1].copy()
        ok = bool(np.isfinite(PA).all())
        if not ok:  # singular stage: the numpy recursion retries with larger shifts
            return s._numpy_backward(mu0, delta)
        return PA, mu, ok


def _ones_at_every_stage(phi_out, K: int, m: int) -> np.ndarray:
    """Which of the ``m`` trajectory-dependent entries of ``Phi_k`` are the constant 1 at
    every stage ``k`` of ``phi_out`` (``K m`` SX entries, stage-major)."""
    return np.array(
        [all(phi_out[k * m + j].is_one() for k in range(K)) for j in range(m)], dtype=bool
    )


def _sym_product(A, B):
    """``A' B`` for a product known to be symmetric: the upper triangle, mirrored.

    Every entry ``a <= b`` is one dot product of columns; ``(b, a)`` reuses it, so the
    stage function does about half the work of ``mtimes(A.T, B)`` (and ``Z`` and ``T`` are
    exactly symmetric).
    """
    m = A.shape[1]
    out = ca.SX(m, m)
    for a in range(m):
        for b in range(a, m):
            v = ca.dot(A[:, a], B[:, b])
            out[a, b] = v
            if a != b:
                out[b, a] = v
    return out


def _ldl_pivots(H):
    """Pivots of the ``LDL'`` factorization (no pivoting) of a small symmetric SX matrix."""
    m = H.shape[0]
    A = [[H[i, j] for j in range(m)] for i in range(m)]
    piv = []
    for j in range(m):
        d = A[j][j]
        piv.append(d)
        for i in range(j + 1, m):
            f = A[i][j] / d
            for c in range(j + 1, m):
                A[i][c] = A[i][c] - f * A[j][c]
    return piv


def _gershgorin(H):
    m = H.shape[0]
    lows = []
    for i in range(m):
        off = 0
        for j in range(m):
            if j != i:
                off = off + ca.fabs(H[i, j])
        lows.append(H[i, i] - off)
    g = lows[0]
    for v in lows[1:]:
        g = ca.fmin(g, v)
    return g


# --------------------------------------------------------------------------------------
# entry function
# --------------------------------------------------------------------------------------
def get_solver(
    game: PotentialGame, costs: ca.Function | None = None, hessian: str = "auto"
) -> ILQSolver:
    """The cached :class:`ILQSolver` of ``game``, ``costs`` and ``hessian``, built on first use."""
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    # The entry keeps ``costs`` alive, so its id is not reused while cached.
    key = ("ilq", None if costs is None else id(costs), hessian)
    costs_, solver = game.cached(key, lambda: (costs, ILQSolver(game, costs, hessian)))
    if costs_ is not costs:  # pragma: no cover - guarded by keeping costs alive
        raise RuntimeError("iLQ solver cache returned another cost function")
    return solver


def solve_ilq(
    game: PotentialGame,
    p: np.ndarray,
    u0: np.ndarray | None = None,
    options: ILQOptions | dict | None = None,
    costs: ca.Function | None = None,
) -> SolveResult:
    """Local feedback Nash equilibrium of ``game`` by iLQ (see the module docstring).

    ``p``: ``(n_p,)`` or ``(B, n_p)``; ``u0``: ``(n_u,)`` or ``(B, n_u)`` (zeros if None);
    ``costs``: ``None`` (the game's agent costs) or a ``casadi.Function (x, u, p) -> C``.
    A batch is solved problem by problem and returned as one batched result.
    """
    opts = check_options(ILQOptions, options, "ilq")
    solver = get_solver(game, costs, opts.hessian)
    single = np.ndim(p) == 1 and (u0 is None or np.ndim(u0) == 1)
    if single:
        return solver.solve(p, u0, opts)
    U, P = game.check_inputs(game.zero_controls() if u0 is None else u0, p)
    t0 = time.perf_counter()
    rs = [solver.solve(P[b], U[b], opts) for b in range(U.shape[0])]
    return _stack(rs, time.perf_counter() - t0)


def _stack(rs: list[SolveResult], wall: float) -> SolveResult:
    S = max(r.energy_history.shape[0] for r in rs)
    hist = np.stack(
        [np.pad(r.energy_history, (0, S - r.energy_history.shape[0]), mode="edge") for r in rs],
        axis=1,
    )
    status = np.empty(len(rs), dtype=object)
    status[:] = [r.status for r in rs]
    info: dict = {}
    for key in ("gains", "gains_prev", "feedforward", "regularization"):
        info[key] = np.stack([r.info[key] for r in rs])
    for key in ("stationarity", "max_regularization"):
        info[key] = np.array([r.info[key] for r in rs])
    info["residual_history"] = [r.info["residual_history"] for r in rs]
    info["step_sizes"] = [r.info["step_sizes"] for r in rs]
    info["custom_costs"] = rs[0].info["custom_costs"]
    info["options"] = rs[0].info["options"]
    return SolveResult(
        solver="ilq",
        controls=np.stack([r.controls for r in rs]),
        states=np.stack([r.states for r in rs]),
        energy=np.array([r.energy for r in rs], float),
        agent_costs=np.stack([r.agent_costs for r in rs]),
        status=status,
        iterations=np.array([r.iterations for r in rs]),
        energy_history=hist,
        grad_norm=np.array([r.grad_norm for r in rs], float),
        wall_time=wall,
        info=info,
    )
