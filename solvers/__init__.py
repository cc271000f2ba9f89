"""Numeric solvers on :class:`epo_casadi.PotentialGame`: LM, IPOPT, iLQ game, Nash certificate.

No torch here. Every solver returns :class:`solvers.result.SolveResult` and is registered
once in the solver table :data:`solvers.registry.SOLVERS` (name, entry function, options,
equilibrium check), which the CLI, game files, ``epo compare`` and the multi-modal solver
read; :func:`solve_game` solves with a solver by name, :func:`register_solver` adds one.
A solve through the table that does not converge is solved again along the collision
weight (:mod:`solvers.continuation`, :func:`solve_with_continuation`).
"""

from .continuation import solve_with_continuation
from .ilq import ILQOptions, solve_ilq
from .ipopt import IpoptOptions, IpoptSolver, solve_ipopt
from .lm import LMOptions, solve_lm
from .multimodal import MultiModalOptions, MultiModalResult, solve_multimodal
from .nash import NashCertificate, NashOptions, nash_certificate
from .olne import OLNEOptions, solve_olne
from .registry import SOLVERS, SolverEntry, register_solver, solve_game, unregister_solver
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
    "OLNEOptions",
    "solve_olne",
    "solve_ipopt",
    "solve_lm",
    "SQPOptions",
    "SQPSolver",
    "solve_sqp",
    "SOLVERS",
    "SolverEntry",
    "register_solver",
    "unregister_solver",
    "solve_game",
    "solve_with_continuation",
]
