"""Options of the iLQ game solver (:class:`ILQOptions`) and their checks.

The method each option tunes is described in :mod:`solvers.ilq`; the defaults are the table
of docs/ilq.md ("Options").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from epo_casadi.errors import SpecError

from ..lm import MAX_STEPS

__all__ = ["HESSIANS", "LINE_SEARCHES", "ILQOptions"]

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
    #: when a solve ends in any status but 'converged', solve again along the collision
    #: weight (pair weights scaled up from 0.01, warm-started, then wider kink widths; solvers.continuation)
    continuation: bool = True

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
        if not isinstance(self.continuation, bool):
            raise SpecError(
                "ilq.continuation", f"expected True or False, got {self.continuation!r}"
            )
        if not isinstance(self.restart, bool):
            raise SpecError("ilq.restart", f"expected True or False, got {self.restart!r}")
        if not isinstance(self.kink_equilibrium, bool):
            raise SpecError(
                "ilq.kink_equilibrium", f"expected True or False, got {self.kink_equilibrium!r}"
            )
