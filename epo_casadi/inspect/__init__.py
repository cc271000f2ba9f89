"""Look inside a potential game: its energy terms, where the energy goes, and the
structure of its Jacobian. Text only (no plotting here; see ``scenarios.plotting``).

Everything reads :attr:`PotentialGame.terms` (one entry per residual block, see the
contract in :mod:`epo_casadi.game`) and the named functions ``term_energies``,
``agent_costs`` and ``jacobian``:

* :func:`term_rows` / :func:`term_table`: every term with its kind (own / pair), agents,
  feature, weight parameter and its default value, time steps, residual rows;
* :func:`energy_breakdown` / :func:`agent_breakdown` / :func:`breakdown_table`: per-term
  energy ``e_t = 1/2 ||r_t||^2`` and its share of ``E``, and per-agent costs ``C_i`` split
  into own and pair parts, at parameters ``p`` and a joint strategy ``u`` (arguments
  ``(game, p, u)``, the solvers' order; ``p=``, ``u=`` as keywords work too);
* :func:`jacobian_sparsity` / :func:`jacobian_pattern` / :func:`spy_text`: the
  structural nonzeros of ``J = dr/du`` (``n_r x n_u``), in total, per term and per agent,
  and a text picture of which terms touch which agents' controls;
* :func:`term_formula` (each feature's ``formula()``, else a generic display),
  :func:`dynamics_summary`, :func:`param_summary`, :func:`hessian_pattern` /
  :func:`hessian_sparsity` / :func:`hessian_spy_text` (Gauss-Newton ``J^T J``),
  :func:`term_series` (each term's value per time step at a solution);
* :func:`inspect_report`: all of it as one JSON-ready dict (schema ``epo-inspect/1``,
  docs/gamefiles.md), and :func:`report_text`, the text of ``epo inspect`` made from it.
"""

from __future__ import annotations

from .formulas import FormulaSymbols, dynamics_summary, term_formula
from .formulas import _feature_of as _feature_of
from .report import ENERGY_CONVENTION, inspect_report, param_summary, report_text
from .report import REPORT_FORMAT as REPORT_FORMAT
from .sparsity import (
    SPY_LEGEND,
    hessian_pattern,
    hessian_sparsity,
    hessian_spy_text,
    jacobian_pattern,
    jacobian_sparsity,
    spy_text,
)
from .terms import (
    agent_breakdown,
    breakdown_table,
    energy_breakdown,
    format_steps,
    term_rows,
    term_series,
    term_table,
)

__all__ = [
    "format_steps",
    "term_rows",
    "term_table",
    "energy_breakdown",
    "agent_breakdown",
    "breakdown_table",
    "jacobian_pattern",
    "jacobian_sparsity",
    "spy_text",
    "ENERGY_CONVENTION",
    "SPY_LEGEND",
    "FormulaSymbols",
    "term_formula",
    "dynamics_summary",
    "param_summary",
    "hessian_pattern",
    "hessian_sparsity",
    "hessian_spy_text",
    "term_series",
    "inspect_report",
    "report_text",
]
