"""The SQP solver of :mod:`solvers.sqp`: :class:`SQPSolver` (the QP of one game and
structure, and the solve of a batch, problem by problem) and :func:`solve_sqp`."""

from __future__ import annotations

import time

import numpy as np

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame

from ..lm import check_options
from ..result import (
    SolveResult,
    demote_nonfinite,
    grad_inf_norm,
    padded_histories,
    per_problem,
    potential_equilibrium,
)
from .iteration import SQPRun
from .options import SQPOptions
from .qp import StagedQP

__all__ = ["SQPSolver", "solve_sqp"]


class SQPSolver(StagedQP):
    """The SQP of one game and one :class:`SQPOptions` structure; OSQP set up once.

    ``solver.solve(p, u0, options)`` solves one problem or a batch (a loop). Attributes:
    ``n_v`` (QP variables), ``n_c`` (QP constraint rows), ``setups`` (OSQP set-ups so far:
    1 after the first solve, whatever the number of solves), ``qp`` (the ``osqp.OSQP``).
    The QP and its numbers are :class:`~solvers.sqp.qp.StagedQP`'s; one problem's
    iteration is :class:`~solvers.sqp.iteration.SQPRun`.
    """

    def prepare(self, p: np.ndarray, u0: np.ndarray | None = None) -> SQPSolver:
        """Evaluate the QP's functions once at ``(u0, p)`` and set OSQP up (if not yet):
        the whole first-call cost, so that a timed solve afterwards is the solve alone."""
        g = self.game
        U0, P = g.check_inputs(g.zero_controls() if u0 is None else u0, p)
        u = U0[0].copy()
        if self.u_idx.size:
            u[self.u_idx] = np.clip(u[self.u_idx], self.u_lo, self.u_hi)
        Px, q, Ax, _E, x, d = (a.copy() for a in self._lin(u, P[0], self.options.regularization))
        self._eval_merit(u, P[0])
        if self.qp is None:
            self._setup(Px, q, Ax, *self._bounds(u, x, d))
        return self

    # ---- the solve ------------------------------------------------------------------------
    def solve(
        self, p: np.ndarray, u0: np.ndarray | None = None, options: SQPOptions | dict | None = None
    ) -> SolveResult:
        """Solve for ``p`` (``(n_p,)`` or ``(B, n_p)``) from ``u0`` (zeros if None).

        ``options`` may change the numbers (tolerances, line search, OSQP tolerances) but
        not the structure (bounds, collision) this solver was built for.
        """
        opts = check_options(SQPOptions, options, "sqp") if options is not None else self.options
        if opts.structure() != self.options.structure():
            raise SpecError(
                "sqp",
                "these options change the QP's structure (bounds or collision); "
                "use solve_sqp or a new SQPSolver",
            )
        game = self.game
        t0 = time.perf_counter()
        single = np.ndim(p) == 1 and (u0 is None or np.ndim(u0) == 1)
        U0, P = game.check_inputs(game.zero_controls() if u0 is None else u0, p)
        with np.errstate(over="ignore", invalid="ignore"):
            runs = [SQPRun(self, U0[b].copy(), P[b], opts).run() for b in range(U0.shape[0])]
        res = _stack(game, runs, time.perf_counter() - t0, opts)
        return res[0] if single else res


def _stack(game: PotentialGame, runs: list[dict], wall: float, opts: SQPOptions) -> SolveResult:
    B = len(runs)
    U = np.stack([r["u"] for r in runs])
    Pm = np.stack([r["p"] for r in runs])
    X = np.empty((B, game.n_x))
    E = np.empty(B)
    C = np.empty((B, game.N))
    G = np.empty((B, game.n_u))
    roll = game.function("rollout")
    for b in range(B):  # one problem at a time, like the solve itself
        X[b] = np.asarray(roll(U[b], Pm[b])).ravel()
        E[b] = float(game.function("energy")(U[b], Pm[b]))
        C[b] = np.asarray(game.function("agent_costs")(U[b], Pm[b])).ravel()
        G[b] = np.asarray(game.function("gradient")(U[b], Pm[b])).ravel()
    status = np.empty(B, dtype=object)
    status[:] = [r["status"] for r in runs]
    status = demote_nonfinite(status, E[:, None], X, C, U)
    kkt = {k: np.array([r["kkt"][k] for r in runs]) for k in runs[0]["kkt"]}
    return SolveResult(
        solver="sqp",
        controls=U,
        states=X,
        energy=E,
        agent_costs=C,
        status=status,
        iterations=np.array([r["iter"] for r in runs], dtype=int),
        energy_history=padded_histories([r["history"] for r in runs], E),
        grad_norm=grad_inf_norm(G),
        wall_time=wall,
        info={
            "stop": np.array([r["stop"] for r in runs], dtype=object),
            "qp_status": np.array([r["qp_status"] for r in runs], dtype=object),
            "kkt_stationarity": kkt["stationarity"],
            "max_violation": kkt["violation"],
            "kkt_complementarity": kkt["complementarity"],
            "kkt_history": per_problem(runs, "kkt_history"),
            "step_sizes": per_problem(runs, "step_sizes"),
            "qp_iterations": per_problem(runs, "qp_iterations"),
            "qp_polish": per_problem(runs, "polish"),
            "regularization_history": per_problem(runs, "mu"),
            "merit_penalty": np.array([r["merit_penalty"] for r in runs]),
            "multipliers": np.stack([r["y"] for r in runs]),
            "options": opts,
        },
        equilibrium=potential_equilibrium(game.coupled),
    )


def _solver_for(game: PotentialGame, opts: SQPOptions) -> SQPSolver:
    return game.cached(("sqp", opts.structure()), lambda: SQPSolver(game, opts))


def solve_sqp(
    game: PotentialGame,
    p: np.ndarray,
    u0: np.ndarray | None = None,
    options: SQPOptions | dict | None = None,
) -> SolveResult:
    """Minimize the potential of ``game`` under hard constraints by Gauss-Newton SQP (OSQP).

    ``p``: ``(n_p,)`` or ``(B, n_p)`` (the same argument name and order as every solver); ``u0``: ``(n_u,)`` or ``(B, n_u)`` (zeros if
    None). ``options``: :class:`SQPOptions` or a dict of its fields (unknown keys raise
    :class:`~epo_casadi.errors.SpecError`). The solver (CasADi functions and the OSQP
    object) is built once per game and constraint structure and reused by later calls,
    which update and warm-start the same QP. See the module docstring for the statuses.
    """
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    opts = check_options(SQPOptions, options, "sqp")
    return _solver_for(game, opts).solve(p, u0, opts)
