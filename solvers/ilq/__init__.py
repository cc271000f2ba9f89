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
    until then): the first trial ``eps`` comes from a secant on ``a``
    (:func:`solvers.ilq.iteration._secant_step`),
    and, when the residual has kinks (``max``/``min``: collision, bounds), their curvature
    is blended over the widths ``kink_widths`` in turn (:func:`solvers.ilq.kinks._smooth_kinks`; the gains
    switch at a kink, so ``a`` and the merit jump there), each width after the previous one
    converged, then the exact kinks again, where convergence is judged (docs/ilq.md). When
    a width converged with kink arguments inside its band and, at the last width or the
    exact kinks, no step passes at the requested regularization, the solve stops
    ``STALLED`` with ``info['stop'] = 'kink'``: the blended solution sits on a kink, where
    the one-sided curvatures give different gains, so no exact-kink iterate nearby has
    ``a = 0``. The blended solution is returned (``info['kink_equilibrium']``: width, kink
    arguments, blended policy and a message; ``P``, ``a`` and ``stationarity`` at the exact
    kinks). With ``kink_equilibrium`` (the default) the solver then looks for an
    equilibrium *on* the kinks (:func:`solvers.ilq.kinks.kink_equilibrium`): curvatures
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
    default, because the first call of each structure compiles (``-O3`` vector code; the
    compile times are in docs/ilq.md).

Modules
    :mod:`solvers.ilq.options` (:class:`ILQOptions`), :mod:`solvers.ilq.quadratize`
    (step 1), :mod:`solvers.ilq.riccati` (step 2, numpy and generated C),
    :mod:`solvers.ilq.rollout` (step 3), :mod:`solvers.ilq.iteration` (one solve: line
    search, regularization, kink continuation), :mod:`solvers.ilq.kinks` (blended kinks
    and equilibria on them), :mod:`solvers.ilq.solver` (:class:`ILQSolver`, the restart,
    :func:`solve_ilq`).
"""

from __future__ import annotations

from ..stages import from_stages, to_stages
from .options import ILQOptions
from .solver import ILQSolver, get_solver, solve_ilq

__all__ = ["ILQOptions", "ILQSolver", "get_solver", "solve_ilq", "to_stages", "from_stages"]
