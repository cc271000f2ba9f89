"""Symbolic views of a potential game: each term's formula with named symbols
(:func:`term_formula`; a feature's own ``formula()`` sees :class:`FormulaSymbols`, other
features are shown at the first step of a short horizon) and each agent's dynamics as the
update ``x_{k+1}`` of every state (:func:`dynamics_summary`)."""

from __future__ import annotations

import re
from collections.abc import Sequence

import casadi as ca

from ..game import PotentialGame, Term, agent_radius
from .terms import _check_game, format_steps


class _StepColumns:
    """``X[:, k]`` for a step *label* ``k`` (``"k"``, ``"k+1"``, ``"K"``): named symbols."""

    def __init__(self, names: Sequence[str], prefix: str):
        self._names, self._prefix, self._cols = tuple(names), prefix, {}

    def __getitem__(self, key):
        rows, k = key if isinstance(key, tuple) else (slice(None), key)
        k = str(k)
        if k not in self._cols:
            sub = k if re.fullmatch(r"\w+", k) else "{" + k + "}"
            syms = [ca.SX.sym(f"{self._prefix}{n}_{sub}") for n in self._names]
            self._cols[k] = ca.vertcat(*syms) if syms else ca.SX(0, 1)
        return self._cols[k][rows]


class FormulaSymbols:
    """What a feature's ``formula(s)`` sees of one agent (see :meth:`Feature.formula`).

    It mimics :class:`epo_casadi.features.AgentContext`: ``X[:, k]`` and ``U[:, k]`` take a
    step label (``"k"``, ``"k+1"``, ``K``) and return columns of symbols named after the
    dynamics' states and controls with the label as subscript (``v_k``; ``robot.v_k`` in
    a pair); ``refs`` maps a reference name (``goal``) to symbols named by the parameter
    entries (``goal.robot.x``); ``dynamics``, ``dt``, ``radius`` and ``agent`` are the
    agent's own. ``K`` is the label ``"K"``.
    """

    K = "K"

    def __init__(self, game: PotentialGame, i: int, qualify: bool = False):
        a = game.agents[i]
        prefix = f"{a.name}." if qualify else ""
        self.agent: str = a.name
        self.dynamics = a.dynamics
        self.dt: float = game.dt
        self.X = _StepColumns(a.dynamics.state_names, prefix)
        self.U = _StepColumns(a.dynamics.control_names, prefix)
        self._ref_names: dict[str, str] = {}
        self.refs: dict[str, ca.SX] = {}
        for r in a.refs():
            b = game.params[f"{r}.{a.name}"]
            self._ref_names[r] = b.name
            self.refs[r] = ca.vertcat(*[ca.SX.sym(e) for e in b.entries])
        #: the spec's number, or the symbol ``radius.<agent>`` of an agent with radius_param
        self.radius = agent_radius(a, self.refs)

    def ref_name(self, name: str) -> str:
        """The parameter block of a reference (``path`` -> ``path.robot``)."""
        return self._ref_names[name]


def _pretty(expr) -> str:
    """CasADi's printout of an expression, with ``max``/``min`` for ``fmax``/``fmin``."""
    if isinstance(expr, str):
        return expr
    s = str(expr)
    # inline shared numeric constants (CasADi prints "@1=0, max(@1,...)")
    while m := re.match(r"@(\d+)=(-?[0-9.]+(?:e[-+]?\d+)?), ", s):
        s = re.sub(rf"@{m.group(1)}\b", m.group(2), s[m.end() :])
    s = s.replace("fmax(", "max(").replace("fmin(", "min(")
    if s.startswith("(") and s.endswith(")") and _balanced(s[1:-1]):
        s = s[1:-1]
    return s


def _balanced(s: str) -> bool:
    depth = 0
    for ch in s:
        depth += (ch == "(") - (ch == ")")
        if depth < 0:
            return False
    return depth == 0


def _feature_of(game: PotentialGame, t: Term):
    if t.kind == "own":
        a = game.agents[game.agent_names.index(t.agents[0])]
        return next(f for f in a.features if f.key == t.feature)
    return next(pf for pf in game.spec.pair_features if pf.key == t.feature)


def _generic_residual(game: PotentialGame, t: Term, feature) -> tuple[str, str]:
    """The residual at the first step of a short horizon (features without ``formula``)."""
    from ..features import AgentContext

    Kf = min(game.K, 3)
    idx = [game.agent_names.index(a) for a in t.agents]
    ctxs = []
    for i in idx:
        a = game.agents[i]
        prefix = f"{a.name}." if t.kind == "pair" else ""
        X = ca.horzcat(
            *[
                ca.vertcat(*[ca.SX.sym(f"{prefix}{n}_{k}") for n in a.dynamics.state_names])
                for k in range(Kf + 1)
            ]
        )
        U = ca.horzcat(
            *[
                ca.vertcat(*[ca.SX.sym(f"{prefix}{n}_{k}") for n in a.dynamics.control_names])
                for k in range(Kf)
            ]
        )
        refs = {
            r: ca.vertcat(*[ca.SX.sym(e) for e in game.params[f"{r}.{a.name}"].entries])
            for r in a.refs()
        }
        ctxs.append(AgentContext(a.dynamics, X, U, game.dt, refs, agent_radius(a, refs)))
    steps = list(feature.steps(Kf))
    r = feature.residual(*ctxs)
    if not steps or r.shape[0] % len(steps):
        return _pretty(r), f"all rows with K = {Kf} (generic)"
    d = r.shape[0] // len(steps)
    return _pretty(r[:d]), f"at k = {steps[0]} with K = {Kf} (generic: no formula())"


def term_formula(game: PotentialGame, t: Term) -> dict:
    """The formula of one term: ``residual`` (``c`` with named symbols), ``formula``
    (``w * c`` with the weight parameter's name), ``steps`` (where ``k`` runs) and
    ``source`` (``"formula()"`` or the generic description)."""
    f = _feature_of(game, t)
    fn = getattr(f, "formula", None)
    expr = None
    if callable(fn):
        if t.kind == "own":
            expr = fn(FormulaSymbols(game, game.agent_names.index(t.agents[0])))
        else:
            a, b = (FormulaSymbols(game, game.agent_names.index(x), qualify=True) for x in t.agents)
            expr = fn(a, b)
    if expr is not None:
        c, source = _pretty(expr), "formula()"
    else:
        c, source = _generic_residual(game, t, f)
    return {
        "residual": c,
        "formula": f"{t.weight} * {c}"
        if c.startswith("[") or re.fullmatch(r"[\w.]+", c)
        else f"{t.weight} * ({c})",
        "steps": f"k = {format_steps(t.steps)}",
        "source": source,
    }


def _integrator(model) -> str:
    integ = getattr(model, "integrator", None)
    if integ is None and type(model).__module__ == "epo_casadi.dynamics":
        integ = "explicit Euler"
    return str(integ) if integ is not None else "not declared"


def _coupled_summary(game: PotentialGame, coupling) -> dict:
    """One entry of :func:`dynamics_summary` for a :class:`~epo_casadi.game.Coupling`:
    the joint model's update of every member's states, symbols named ``agent.state``."""
    members = [game.agents[game.agent_names.index(n)] for n in coupling.agents]
    states = [f"{a.name}.{s}" for a in members for s in a.dynamics.state_names]
    controls = [f"{a.name}.{c}" for a in members for c in a.dynamics.control_names]
    xs = [
        ca.vertcat(*[ca.SX.sym(f"{a.name}.{s}") for s in a.dynamics.state_names]) for a in members
    ]
    us = [
        ca.vertcat(*[ca.SX.sym(f"{a.name}.{c}") for c in a.dynamics.control_names]) for a in members
    ]
    nxt = ca.vertcat(*coupling.model.step(xs, us, game.dt))
    m = coupling.model
    return {
        "model": getattr(m, "name", type(m).__name__),
        "class": f"{type(m).__module__}.{type(m).__qualname__}",
        "agents": list(coupling.agents),
        "states": states,
        "controls": controls,
        "integrator": _integrator(m),
        "dt": game.dt,
        "update": {n: _pretty(nxt[j]) for j, n in enumerate(states)},
        "coupled": True,
        "member_models": [getattr(a.dynamics, "name", type(a.dynamics).__name__) for a in members],
    }


def dynamics_summary(game: PotentialGame) -> list[dict]:
    """The agents' dynamics, one entry per group of agents with equal models: ``model``
    (name), ``class``, ``agents``, ``states``, ``controls``, ``integrator`` (the model's
    ``integrator`` attribute, else ``"not declared"``), ``dt``, ``update`` (state name ->
    ``x_{k+1}`` with named symbols, from the model's own ``step``) and ``coupled``.

    Agents that a :class:`~epo_casadi.game.Coupling` steps together (``GameSpec.couplings``)
    get one entry per coupling instead, from the joint model's ``step`` (their own models'
    ``step`` is not used): ``coupled`` is True, states and controls are named
    ``agent.name`` (members in the coupling's order) and ``member_models`` names each
    member's own model (which still gives its sizes and state names)."""
    game = _check_game(game)
    groups: list[dict] = []
    seen: dict = {}
    joint = {n: c for c in game.spec.couplings for n in c.agents}
    for a in game.agents:
        if a.name in joint:
            c = joint[a.name]
            if a.name == c.agents[0]:  # one entry per coupling, where its first member is
                groups.append(_coupled_summary(game, c))
            continue
        d = a.dynamics
        try:
            key = d
            hash(key)
        except TypeError:
            key = id(d)
        if key in seen:
            seen[key]["agents"].append(a.name)
            continue
        x = ca.vertcat(*[ca.SX.sym(n) for n in d.state_names])
        u = ca.vertcat(*[ca.SX.sym(n) for n in d.control_names])
        nxt = d.step(x, u, game.dt)
        update = {n: _pretty(nxt[j]) for j, n in enumerate(d.state_names)}
        g = {
            "model": getattr(d, "name", type(d).__name__),
            "class": f"{type(d).__module__}.{type(d).__qualname__}",
            "agents": [a.name],
            "states": list(d.state_names),
            "controls": list(d.control_names),
            "integrator": _integrator(d),
            "dt": game.dt,
            "update": update,
            "coupled": False,
        }
        seen[key] = g
        groups.append(g)
    return groups
