"""The options of the SQP solver (:func:`solvers.sqp.solve_sqp`)."""

from __future__ import annotations

from dataclasses import dataclass

from epo_casadi.errors import SpecError, check_bool, check_number

from ..ipopt import Bounds, _normalize_bounds
from ..lm import MAX_STEPS

__all__ = ["SQPOptions"]


@dataclass(frozen=True)
class SQPOptions:
    """Options of :func:`solve_sqp` (defaults: a tight solve without hard constraints).

    ``control_bounds`` / ``state_bounds``: as in :class:`solvers.ipopt.IpoptOptions`
    (``{agent: (lower list, upper list)}``, ``None``/``inf`` for no bound).
    """

    max_iter: int = 200  #: SQP iterations (QP solves with an accepted step)
    tol: float = 1e-7  #: KKT tolerance: stationarity and complementarity (inf-norms)
    feas_tol: float = 1e-7  #: largest constraint violation at a converged point
    control_bounds: Bounds | dict | None = None  #: hard bounds on u_{i,k}, per agent
    state_bounds: Bounds | dict | None = None  #: hard bounds on x_{i,k}, k = 1..K, per agent
    collision: bool = False  #: hard distance constraints for every pair at every step k = 1..K
    collision_margin: float = 0.0  #: safety distance (m) added to r_a + r_b in the constraint
    regularization: float = 1e-9  #: smallest mu_u on the controls' diagonal of the QP Hessian
    merit_penalty: float = 1.0  #: initial nu of the l1 merit (raised to 1.1 max |y|)
    armijo: float = 1e-4  #: sufficient-decrease factor of the line search
    backtrack: float = 0.5  #: factor on alpha after a rejected trial
    max_backtracks: int = 30  #: trials before the line search gives up (status stalled)
    step_tol: float = 1e-13  #: a step max|alpha du| <= step_tol (1 + max|u|) is negligible
    eps_abs: float = 1e-7  #: OSQP absolute tolerance
    eps_rel: float = 1e-7  #: OSQP relative tolerance
    qp_max_iter: int = 20000  #: OSQP iterations per QP
    polish: bool = True  #: OSQP solution polishing (an exact active-set step)
    #: when a solve ends in any status but 'converged', solve again along the collision
    #: weight (pair weights scaled up from 0.01, warm-started; solvers.continuation)
    continuation: bool = True

    def __post_init__(self):
        for name in ("max_iter", "max_backtracks", "qp_max_iter"):
            check_number(f"sqp.{name}", getattr(self, name), lo=0, hi=MAX_STEPS, integer=True)
        for name in ("tol", "feas_tol", "eps_abs", "eps_rel", "armijo", "merit_penalty"):
            check_number(f"sqp.{name}", getattr(self, name), lo=0, lo_open=True)
        for name in ("regularization", "collision_margin", "step_tol"):
            check_number(f"sqp.{name}", getattr(self, name), lo=0)
        check_number("sqp.backtrack", self.backtrack, lo=0, hi=1, lo_open=True)
        if self.backtrack >= 1:
            raise SpecError("sqp.backtrack", f"expected 0 < backtrack < 1, got {self.backtrack}")
        if self.armijo >= 0.5:
            raise SpecError("sqp.armijo", f"expected 0 < armijo < 0.5, got {self.armijo}")
        check_bool("sqp.collision", self.collision)
        check_bool("sqp.polish", self.polish)
        check_bool("sqp.continuation", self.continuation)
        object.__setattr__(
            self, "control_bounds", _normalize_bounds(self.control_bounds, "sqp.control_bounds")
        )
        object.__setattr__(
            self, "state_bounds", _normalize_bounds(self.state_bounds, "sqp.state_bounds")
        )

    def structure(self) -> tuple:
        """What decides the QP's sparsity (and the CasADi functions): the cache key."""
        return (self.control_bounds, self.state_bounds, self.collision, self.collision_margin)
