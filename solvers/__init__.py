"""Numeric solvers on :class:`epo_casadi.PotentialGame`: LM, IPOPT, iLQ game, Nash certificate.

No torch here. Every solver returns :class:`solvers.result.SolveResult`.
"""

from .lm import LMOptions, solve_lm
from .result import SolveResult, Status

__all__ = ["LMOptions", "SolveResult", "Status", "solve_lm"]
