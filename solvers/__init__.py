"""Numeric solvers on :class:`epo_casadi.PotentialGame`: LM, IPOPT, iLQ game, Nash certificate.

No torch here. Every solver returns :class:`solvers.result.SolveResult`.
"""

from .ilq import ILQOptions, solve_ilq
from .ipopt import IpoptOptions, IpoptSolver, solve_ipopt
from .lm import LMOptions, solve_lm
from .multimodal import MultiModalOptions, MultiModalResult, solve_multimodal
from .nash import NashCertificate, NashOptions, nash_certificate
from .result import SolveResult, Status
from .sqp import SQPOptions, SQPSolver, solve_sqp
from .structured import StructuredGN

__all__ = [
    "ILQOptions",
    "MultiModalOptions",
    "MultiModalResult",
    "solve_ilq",
    "solve_multimodal",
    "IpoptOptions",
    "IpoptSolver",
    "StructuredGN",
    "LMOptions",
    "NashCertificate",
    "NashOptions",
    "SolveResult",
    "Status",
    "nash_certificate",
    "solve_ipopt",
    "solve_lm",
    "SQPOptions",
    "SQPSolver",
    "solve_sqp",
]
