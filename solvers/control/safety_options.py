"""The options of the safety filter of :mod:`solvers.control.safety`: :class:`SafetyOptions`
(horizon, box, margins, chance level, body shape, OSQP settings) checked when made, and the
bounds and tolerances they are checked against (:data:`MAX_HORIZON`, :data:`MAX_MODES`,
:data:`SHAPES`, :data:`MAX_ITER`, :data:`SPEED_TOL`, :data:`TURN_DISC`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from epo_casadi.errors import SpecError, check_bool, check_number, check_size

#: most filter steps (the QP has 6 x horizon unknowns)
MAX_HORIZON = 1000
#: most constrained modes
MAX_MODES = 100
#: how the other agents' bodies enter the collision constraints (``SafetyOptions.shape``)
SHAPES = ("box", "circles")
#: most OSQP iterations per solve
MAX_ITER = 1_000_000
#: m/s, rounding allowed on the speed bound in the check
SPEED_TOL = 1e-9
#: an estimate with a speed std (m/s) or heading std (rad) above these has not converged
_CV_SPEED_STD, _CV_HEADING_STD = 2.0, 0.5
#: rad, a heading this uncertain (at the quantile) makes a body the disc of all its headings
TURN_DISC = 0.5
#: rad, an agent behind within this heading difference drives the ego's way
_SAME_WAY = math.pi / 6


@dataclass(frozen=True)
class SafetyOptions:
    """Options of :class:`SafetyFilter` (unknown keys are an error)."""

    horizon: int = 20  #: steps of the world's dt checked and constrained, at most 1000
    threshold: float = 0.1  #: modes with at least this probability are constrained
    max_modes: int = 8  #: most plan modes constrained (the most likely first), at most 100
    constant_velocity: bool = False  #: constrain against the estimate's CV prediction too
    quantile: float = 0.99  #: chance-constraint quantile of the uncertainty, in [0.5, 1)
    max_inflation: float = 1.0  #: m, largest inflation by the uncertainty
    margin: float = 0.1  #: m, kept between the bodies on top of the inflation
    buffer: float = 0.02  #: m, QP tightening for the linearization error (not in the check)
    ignore_behind: bool = True  #: leave out agents right behind the ego going its way
    shape: str = "box"  #: the others' bodies: "box" (their rectangles) or "circles" (two each)
    tolerance: float = 1e-3  #: command change (fraction of the box width) that intervenes
    w_first: float = 100.0  #: weight of the first command's deviation (later ones: 1)
    iterations: int = 3  #: QP solves per period (re-linearized), 1 to 20
    eps_abs: float = 1e-3  #: OSQP absolute tolerance
    eps_rel: float = 1e-3  #: OSQP relative tolerance
    max_iter: int = 4000  #: OSQP iteration limit, at most 1,000,000
    warm_start: bool = True  #: warm-start OSQP from the shifted previous solution

    def __post_init__(self):
        p = "filter"
        object.__setattr__(
            self, "horizon", check_size(f"{p}.horizon", self.horizon, MAX_HORIZON, "QP size")
        )
        check_number(f"{p}.threshold", self.threshold, lo=0.0, hi=1.0)
        object.__setattr__(
            self, "max_modes", check_size(f"{p}.max_modes", self.max_modes, MAX_MODES, "QP size")
        )
        check_bool(f"{p}.constant_velocity", self.constant_velocity)
        check_number(f"{p}.quantile", self.quantile, lo=0.5, hi=1.0)
        if not self.quantile < 1.0:
            raise SpecError(f"{p}.quantile", f"expected a number in [0.5, 1), got {self.quantile}")
        check_number(f"{p}.max_inflation", self.max_inflation, lo=0.0)
        check_number(f"{p}.margin", self.margin, lo=0.0)
        check_number(f"{p}.buffer", self.buffer, lo=0.0)
        check_bool(f"{p}.ignore_behind", self.ignore_behind)
        if self.shape not in SHAPES:
            raise SpecError(f"{p}.shape", f"expected one of {SHAPES}, got {self.shape!r}")
        check_number(f"{p}.tolerance", self.tolerance, lo=0.0)
        check_number(f"{p}.w_first", self.w_first, lo=0.0, lo_open=True)
        object.__setattr__(
            self, "iterations", check_size(f"{p}.iterations", self.iterations, 20, "solve time")
        )
        check_number(f"{p}.eps_abs", self.eps_abs, lo=0, lo_open=True)
        check_number(f"{p}.eps_rel", self.eps_rel, lo=0)
        object.__setattr__(
            self, "max_iter", check_size(f"{p}.max_iter", self.max_iter, MAX_ITER, "solve time")
        )
        check_bool(f"{p}.warm_start", self.warm_start)
