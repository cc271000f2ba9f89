"""The typed stop reason: every stop a solver sets is a :class:`StopReason` member, and a
result's JSON gives the same member back."""

import ast
import json
from pathlib import Path

import numpy as np
import pytest

from solvers.result import SolveResult, Status, StopReason, stop_reason

ROOT = Path(__file__).resolve().parents[1]
# the modules that set info["stop"] (solvers/sqp/iteration.py also sets "qp <OSQP status>")
SETTERS = ["solvers/lm.py", "solvers/ilq/iteration.py", "solvers/sqp/iteration.py"]


def _stop_values(tree: ast.AST) -> list[ast.expr]:
    """Every expression assigned to a stop: ``x.stop = v``, ``a, x.stop = s, v``,
    ``s.stop[m] = v``, a ``stop=v`` keyword and the ``stop`` argument of ``finish``."""
    out = []

    def is_stop(t):
        if isinstance(t, ast.Subscript):
            t = t.value
        return (isinstance(t, ast.Attribute) and t.attr == "stop") or (
            isinstance(t, ast.Name) and t.id == "stop"
        )

    def pair(target, value):
        if isinstance(target, ast.Tuple) and isinstance(value, ast.Tuple):
            for t, v in zip(target.elts, value.elts, strict=True):
                pair(t, v)
        elif isinstance(target, ast.Tuple) and isinstance(value, ast.IfExp):
            pair(target, value.body)
            pair(target, value.orelse)
        elif is_stop(target):
            out.append(value)

    for node in ast.walk(tree):
        if isinstance(node, ast.Assign):
            for t in node.targets:
                pair(t, node.value)
        elif isinstance(node, ast.Call):
            out.extend(k.value for k in node.keywords if k.arg == "stop")
            f = node.func
            if isinstance(f, ast.Attribute) and f.attr == "finish" and len(node.args) == 3:
                out.append(node.args[2])
    return out


def _members_or_list(expr: ast.expr) -> list[str]:
    """``_members`` of a list display's items, or of the expression (a count gives none)."""
    if isinstance(expr, ast.List):
        return [m for e in expr.elts for m in _members(e)]
    if isinstance(expr, ast.Constant) and isinstance(expr.value, int):
        return []
    return _members(expr)


def _members(expr: ast.expr) -> list[str]:
    """The ``StopReason.X`` names an expression gives; raises on a bare string literal."""
    if isinstance(expr, ast.IfExp):
        return _members(expr.body) + _members(expr.orelse)
    if isinstance(expr, ast.Call) and getattr(expr.func, "attr", "") == "array":
        return [
            m for e in ast.walk(expr.args[0]) if isinstance(e, ast.Attribute) for m in _members(e)
        ]
    if isinstance(expr, ast.Attribute) and getattr(expr.value, "id", "") == "StopReason":
        return [expr.attr]
    if isinstance(expr, ast.BinOp) and isinstance(expr.op, ast.Mult):  # [StopReason.X] * B
        return [m for e in (expr.left, expr.right) for m in _members_or_list(e)]
    if isinstance(expr, ast.JoinedStr):  # SQP's "qp <OSQP status>"
        assert ast.unparse(expr).startswith("f'qp "), ast.unparse(expr)
        return []
    if isinstance(expr, (ast.Name, ast.Attribute, ast.Subscript, ast.ListComp)):
        return []  # a stop passed on (a parameter, a record's field)
    raise AssertionError(f"stop set to {ast.unparse(expr)}, not a StopReason member")


def test_solvers_set_only_members():
    seen = set()
    for rel in SETTERS:
        tree = ast.parse((ROOT / rel).read_text())
        values = _stop_values(tree)
        assert values, rel
        for v in values:
            assert not (isinstance(v, ast.Constant) and isinstance(v.value, str)), (
                rel,
                ast.unparse(v),
            )
            names = _members(v)
            for n in names:
                assert n in StopReason.__members__, (rel, n)
            seen.update(names)
    assert seen == set(StopReason.__members__)  # every member is set by some solver


def test_str_behaviour():
    assert StopReason.FTOL == "ftol" and "ftol" == StopReason.FTOL
    assert StopReason.FTOL in {"ftol"} and "ftol" in {StopReason.FTOL: 1}
    assert str(StopReason.KINK) == "kink" and f"{StopReason.KINK}" == "kink"
    assert json.dumps({"stop": StopReason.TOL}) == '{"stop": "tol"}'
    a = np.array([StopReason.FTOL, StopReason.GTOL], dtype=object)
    assert (a == "ftol").tolist() == [True, False]
    assert np.isin(a, ("ftol", "max_damping")).tolist() == [True, False]


@pytest.mark.parametrize("member", list(StopReason))
def test_json_round_trip(member):
    back = json.loads(json.dumps({"stop": member}))["stop"]
    assert type(back) is str and stop_reason(back) is member


def test_stop_reason_keeps_unknown():
    assert stop_reason("qp primal infeasible") == "qp primal infeasible"
    assert stop_reason("an old word") == "an old word"
    assert stop_reason(None) is None and stop_reason(StopReason.KKT) is StopReason.KKT


def test_result_to_dict_round_trip():
    res = SolveResult(
        solver="lm",
        controls=np.zeros((2, 1)),
        states=np.zeros((2, 1)),
        energy=np.zeros(2),
        agent_costs=np.zeros((2, 1)),
        status=np.array([Status.CONVERGED, Status.STALLED], dtype=object),
        iterations=np.array([1, 2]),
        energy_history=np.zeros((3, 2)),
        grad_norm=np.zeros(2),
        wall_time=0.0,
        info={"stop": np.array([StopReason.GTOL, StopReason.FTOL], dtype=object)},
    )
    data = json.loads(json.dumps(res.to_dict()))
    assert data["info"]["stop"] == ["gtol", "ftol"]
    assert [stop_reason(s) for s in data["info"]["stop"]] == [StopReason.GTOL, StopReason.FTOL]
    assert res[1].info["stop"] is StopReason.FTOL


def test_solver_results_hold_members():
    """LM, iLQ, SQP and OLNE solves give members, and the ``epo solve`` JSON gives them
    back (OLNE's stops are returned, not assigned, so the source scan does not see them)."""
    from scenarios.commands.solve import result_dict
    from solvers.ilq import solve_ilq
    from solvers.lm import LMOptions, solve_lm
    from solvers.olne import solve_olne
    from solvers.sqp import solve_sqp
    from tests.test_lm import di_game

    g = di_game()
    p = g.default_params(goal__di=[2.0, -1.5])
    olne_short = solve_olne(g, p, options={"max_iter": 0, "start": "given"})
    assert olne_short.info["stop"] is StopReason.MAX_ITER
    for res in (
        solve_lm(g, p, options=LMOptions(ftol=0.0, gtol=1e-8)),
        solve_lm(g, p, options=LMOptions(ftol=0.0, gtol=1e-8, steps=2)),
        solve_ilq(g, p),
        solve_sqp(g, p),
        solve_olne(g, p),
        olne_short,
    ):
        stop = res.info["stop"]
        assert type(stop) is StopReason, (res.solver, stop)
        back = json.loads(json.dumps(result_dict(g, p, res)))["stop"]
        assert stop_reason(back) is stop
