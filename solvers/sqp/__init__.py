"""Gauss-Newton SQP on OSQP: the potential game with hard constraints.

Shapes and index order follow the contract in :mod:`epo_casadi.game`. The problem is ::

    min_u  E(u, p) = 1/2 ||r(u, p)||^2
    s.t.   lower_i <= u_{i,k} <= upper_i                (control_bounds, every k = 0..K-1)
           lower_i <= x_{i,k} <= upper_i                (state_bounds, every k = 1..K)
           |pos_a(x_{a,k}) - pos_b(x_{b,k})| >= r_a + r_b + margin
                                                        (collision=True: every pair, k = 1..K)

with the bounds in the shapes of :class:`solvers.ipopt.IpoptOptions` and the distance the
collision feature's (``epo_casadi.features.smooth_distance``). The soft terms of the game
(the collision penalty included) stay in ``E``.

One iteration, at the rolled-out iterate ``(x(u), u)``
    The QP is *stage-structured* (sparse): its variables are ``v = (dx, du)`` with ``dx``
    every state entry of stages ``k = 1..K`` (``dx_0 = 0``), and ::

        min_v  1/2 v' (G'G + mu_u) v + (G'r)' v         G = [R_x  R_u]: the partial Jacobian
        s.t.   dx_{k+1} = A_k dx_k + B_k du_k            of traj_residual(x, u, p)
               lower - u <= du <= upper - u
               lower - x <= dx <= upper - x
               d + D v >= r_a + r_b + margin             (the linearized distances)

    Eliminating ``dx`` gives the Gauss-Newton step of single shooting,
    ``min 1/2 ||r + J du||^2`` with ``J = R_x dx/du + R_u``, so without constraints the
    step is LM's with damping ``regularization``; kept in stage form, ``G'G`` and the
    constraint matrix are sparse (banded in time) where the condensed ``J'J`` is dense.
    The QP's structure (the sparsity of ``P`` and ``A``) depends only on the game and the
    options, so OSQP is set up **once** per :class:`SQPSolver` and every later QP, in this
    solve and in later calls, is an ``update(q, l, u, Px, Ax)`` of the same object,
    warm-started from the previous QP's primal and dual solution.

Step and merit
    ``u <- u + alpha du`` (rolled out again: the iterate stays dynamically feasible), with
    ``alpha`` from a backtracking (Armijo) line search on the l1 merit
    ``phi(u) = E(u) + nu * viol(u)``, ``viol`` the sum of all constraint violations and
    ``nu >= 1.1 max |y|`` (QP multipliers of the inequality rows, raised when needed).
    The regularization ``mu_u`` of the controls' block adapts like LM's damping: x10
    after a shortened step or a poor ratio of actual to predicted decrease, /10 (down to
    ``regularization``) after a good one; plain Gauss-Newton can diverge slowly near a
    minimizer with large residuals, the damped step does not. Where the predicted decrease
    is below what ``E`` resolves (``1e-9`` relative), the full step is taken and judged by
    the KKT error at the next point instead: if that is larger, the step is undone and
    ``mu_u`` raised (``stalled`` once it passes ``1e8``).

Statuses
    * ``CONVERGED``: the first-order (KKT) test holds: ``max |q + A'y| <= tol`` (the
      stationarity of the Lagrangian in ``v``, with the QP's multipliers ``y``),
      ``viol_inf <= feas_tol`` and complementarity ``max |y_j| slack_j <= tol``.
    * ``INFEASIBLE``: OSQP reports the QP primal or dual infeasible; OSQP's reason is
      ``info["qp_status"]`` and part of ``info["stop"]``.
    * ``MAX_ITER``: ``max_iter`` iterations without meeting the test.
    * ``STALLED``: the line search finds no decrease of the merit (or the step is
      negligible) while the KKT test fails.
    * ``NONFINITE``: NaN or inf in the energy, states or the QP's solution; ``FAILED``:
      another OSQP failure (non-convex, unsolved, interrupted). A QP stopped at OSQP's
      iteration limit still gives a step (``info["qp_status"]`` says so); the line search
      and the KKT test judge it.

A batch ``(B, n)`` is solved problem by problem (a loop) with the same OSQP object and
returned as one batched result, like :func:`solvers.ipopt.solve_ipopt`. Its
``equilibrium`` is that of a potential solve (:func:`solvers.result.potential_equilibrium`):
``potential minimum (coupled dynamics: not a Nash equilibrium)`` for a game with coupled
dynamics.

Modules
    :mod:`solvers.sqp.options` (:class:`SQPOptions`), :mod:`solvers.sqp.qp` (the
    stage-structured QP of one game: its CasADi functions, bounds, constraint violation,
    multipliers and KKT test, the OSQP set-up), :mod:`solvers.sqp.iteration` (one
    problem's SQP iteration: QP, first-order test, line search on the merit, the
    regularization), :mod:`solvers.sqp.solver` (:class:`SQPSolver`, the batch,
    :func:`solve_sqp`).
"""

from __future__ import annotations

from .options import SQPOptions
from .solver import SQPSolver, solve_sqp

__all__ = ["SQPOptions", "SQPSolver", "solve_sqp"]
