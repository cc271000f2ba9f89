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

import re
from collections.abc import Sequence

import casadi as ca
import numpy as np

from .errors import SpecError
from .game import PotentialGame, Term, agent_radius

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


def format_steps(steps: Sequence[int]) -> str:
    """Compact time steps: ``"40"``, ``"1..40"``, ``"5,10,..,40"``, ``"0,3,7"``, ``"-"`` (none)."""
    s = [int(k) for k in steps]
    if not s:
        return "-"
    if len(s) == 1:
        return str(s[0])
    d = s[1] - s[0]
    if d > 0 and all(b - a == d for a, b in zip(s, s[1:], strict=False)):
        if d == 1:
            return f"{s[0]}..{s[-1]}"
        if len(s) == 2:
            return f"{s[0]},{s[1]}"
        return f"{s[0]},{s[1]},..,{s[-1]}"
    if len(s) <= 6:
        return ",".join(map(str, s))
    return ",".join(map(str, s[:3])) + ",..," + ",".join(map(str, s[-2:]))


def _check_game(game) -> PotentialGame:
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    return game


def _label(t: Term) -> str:
    return t.feature if t.feature == t.feature_type else f"{t.feature} ({t.feature_type})"


def term_rows(game: PotentialGame) -> list[dict]:
    """One dict per term: ``index, kind, agents, feature, feature_type, weight,
    weight_default, steps, n_steps, size, rows`` (``rows`` as ``(start, stop)``)."""
    game = _check_game(game)
    defaults = game.params.defaults()
    out = []
    for t in game.terms:
        out.append(
            {
                "index": t.index,
                "kind": t.kind,
                "agents": list(t.agents),
                "feature": t.feature,
                "feature_type": t.feature_type,
                "weight": t.weight,
                "weight_default": float(defaults[game.params[t.weight].start]),
                "steps": format_steps(t.steps),
                "n_steps": len(t.steps),
                "size": t.size,
                "rows": (t.rows.start, t.rows.stop),
            }
        )
    return out


def _table(
    header: Sequence[str], rows: Sequence[Sequence[str]], right: Sequence[bool]
) -> list[str]:
    widths = [
        max(len(h), *(len(r[c]) for r in rows)) if rows else len(h) for c, h in enumerate(header)
    ]

    def line(cells):
        return "  ".join(
            c.rjust(w) if r else c.ljust(w) for c, w, r in zip(cells, widths, right, strict=True)
        ).rstrip()

    return [line(header), line(["-" * w for w in widths]), *(line(r) for r in rows)]


def term_table(game: PotentialGame) -> str:
    """Text table of every energy term (see :func:`term_rows`), with a summary line."""
    rows = term_rows(game)
    header = [
        "#",
        "kind",
        "agents",
        "feature",
        "weight parameter",
        "default",
        "steps",
        "size",
        "rows",
    ]
    right = [True, False, False, False, False, True, False, True, False]
    body = [
        [
            str(r["index"]),
            r["kind"],
            "-".join(r["agents"]),
            r["feature"]
            if r["feature"] == r["feature_type"]
            else f"{r['feature']} ({r['feature_type']})",
            r["weight"],
            f"{r['weight_default']:g}",
            r["steps"],
            str(r["size"]),
            f"{r['rows'][0]}:{r['rows'][1]}",
        ]
        for r in rows
    ]
    g = game
    title = (
        f"{len(rows)} energy terms; N = {g.N} agents, K = {g.K} steps of {g.dt:g} s, "
        f"n_u = {g.n_u} controls, n_p = {g.n_p} parameters, n_r = {g.n_r} residuals"
    )
    return "\n".join([title, *_table(header, body, right)])


def _eval(game: PotentialGame, name: str, p, u) -> np.ndarray:
    U, P = game.check_inputs(u, p)
    if U.shape[0] != 1:
        raise SpecError("u/p", f"expected one problem, got a batch of {U.shape[0]}")
    return np.asarray(game.function(name)(U[0], P[0]), dtype=float).reshape(-1)


def energy_breakdown(game: PotentialGame, p: np.ndarray, u: np.ndarray) -> list[dict]:
    """Per-term energy at parameters ``p`` and strategy ``u``: the :func:`term_rows` fields
    plus ``energy`` (``1/2 ||r_t||^2``) and ``share`` (``energy / E``; 0 when ``E = 0``)."""
    game = _check_game(game)
    e = _eval(game, "term_energies", p, u)
    total = float(e.sum())
    out = []
    for row, et in zip(term_rows(game), e, strict=True):
        row["energy"] = float(et)
        row["share"] = float(et / total) if total > 0 else 0.0
        out.append(row)
    return out


def agent_breakdown(game: PotentialGame, p: np.ndarray, u: np.ndarray) -> list[dict]:
    """Per-agent cost ``C_i`` at ``(p, u)``, split into ``own`` and ``pair`` energy.

    ``cost`` comes from the game's ``agent_costs`` function, ``own``/``pair`` from
    ``term_energies`` (``cost = own + pair``; pair terms count for both agents).
    """
    game = _check_game(game)
    e = _eval(game, "term_energies", p, u)
    C = _eval(game, "agent_costs", p, u)
    out = []
    for i, a in enumerate(game.agent_names):
        own = sum(float(e[t.index]) for t in game.terms if t.kind == "own" and a in t.agents)
        pair = sum(float(e[t.index]) for t in game.terms if t.kind == "pair" and a in t.agents)
        out.append({"agent": a, "cost": float(C[i]), "own": own, "pair": pair})
    return out


def breakdown_table(
    game: PotentialGame, p: np.ndarray, u: np.ndarray, top: int | None = None
) -> str:
    """Text tables: per-term energy and share (largest first; ``top`` rows if given),
    then per-agent costs."""
    rows = energy_breakdown(game, p=p, u=u)
    total = sum(r["energy"] for r in rows)
    order = sorted(rows, key=lambda r: -r["energy"])
    shown = order if top is None else order[:top]
    body = [
        [
            str(r["index"]),
            r["kind"],
            "-".join(r["agents"]),
            r["feature"]
            if r["feature"] == r["feature_type"]
            else f"{r['feature']} ({r['feature_type']})",
            f"{r['energy']:.6g}",
            f"{100 * r['share']:.1f}%",
        ]
        for r in shown
    ]
    lines = [f"energy E = {total:.6g} (sum of {len(rows)} terms, largest first)"]
    lines += _table(
        ["#", "kind", "agents", "feature", "energy", "share"],
        body,
        [True, False, False, False, True, True],
    )
    if len(shown) < len(rows):
        rest = sum(r["energy"] for r in order[len(shown) :])
        lines.append(f"... {len(rows) - len(shown)} more terms with {rest:.6g} in total")
    lines.append("")
    lines.append("agent costs C_i = own + pair (pair terms count for both agents)")
    ab = agent_breakdown(game, p=p, u=u)
    lines += _table(
        ["agent", "C_i", "own", "pair"],
        [[a["agent"], f"{a['cost']:.6g}", f"{a['own']:.6g}", f"{a['pair']:.6g}"] for a in ab],
        [False, True, True, True],
    )
    return "\n".join(lines)


def jacobian_pattern(game: PotentialGame) -> np.ndarray:
    """Boolean ``(n_r, n_u)`` array of the structural nonzeros of ``J = dr/du``."""
    game = _check_game(game)
    sp = game.jacobian_sparsity()
    rows, cols = sp.get_triplet()
    out = np.zeros((game.n_r, game.n_u), dtype=bool)
    out[np.asarray(rows, dtype=int), np.asarray(cols, dtype=int)] = True
    return out


def jacobian_sparsity(game: PotentialGame) -> dict:
    """Structural sparsity of ``J = dr/du``.

    Keys: ``shape`` ``(n_r, n_u)``, ``nnz``, ``density`` (``nnz / (n_r n_u)``),
    ``terms`` (per term: ``index``, ``nnz``), ``agents`` (per agent: ``agent``, ``nnz`` in
    its control columns). Structural means "may be nonzero": a soft bound or collision
    term that is inactive at some ``u`` still counts.
    """
    return _sparsity(_check_game(game))


def _sparsity(game: PotentialGame) -> dict:
    A = _jacobian_csr(game)
    n_r, n_u = A.shape
    nnz = int(A.nnz)
    row_nnz = np.concatenate([[0], np.cumsum(np.diff(A.indptr))])
    col_nnz = np.concatenate([[0], np.cumsum(np.bincount(A.indices, minlength=n_u))])
    return {
        "shape": (n_r, n_u),
        "nnz": nnz,
        "density": nnz / (n_r * n_u) if n_r * n_u else 0.0,
        "terms": [
            {"index": t.index, "nnz": int(row_nnz[t.rows.stop] - row_nnz[t.rows.start])}
            for t in game.terms
        ],
        "agents": [
            {"agent": a, "nnz": int(col_nnz[game.uoff[i + 1]] - col_nnz[game.uoff[i]])}
            for i, a in enumerate(game.agent_names)
        ],
    }


def spy_text(game: PotentialGame, width: int = 60) -> str:
    """A text spy of ``J`` with one line per term and ``width`` column cells.

    Each cell covers a range of controls; its character is the share of nonzeros in
    that (term rows x control columns) block: ``' '`` none, ``.`` up to a third, ``:``
    up to two thirds, ``#`` more. The header marks where each agent's controls start.
    """
    game = _check_game(game)
    if not isinstance(width, int) or width < 4:
        raise SpecError("width", f"expected an integer >= 4, got {width!r}")
    A = _jacobian_csr(game)
    n_u = game.n_u
    width = max(1, min(width, n_u))
    edges = np.linspace(0, n_u, width + 1).round().astype(int)
    labels = [f"{t.index:>3d} {'-'.join(t.agents)}.{t.feature}" for t in game.terms]
    lw = max((len(s) for s in labels), default=0)
    head = [" "] * width
    for i, a in enumerate(game.agent_names):
        c = int(np.searchsorted(edges, game.uoff[i], side="right") - 1)
        txt = "|" + a
        for j, ch in enumerate(txt):
            if c + j < width and (j == 0 or head[c + j] == " "):
                head[c + j] = ch
    lines = [f"{'term':<{lw}} {''.join(head)}"]
    cell_w = np.diff(edges)
    nonempty = cell_w > 0
    for t, lab in zip(game.terms, labels, strict=True):
        # share of nonzeros per (term rows x cell columns) block, one numpy pass per term
        counts = np.zeros(width)
        col = np.asarray(A[t.rows.start : t.rows.stop].sum(axis=0)).ravel()
        counts[nonempty] = np.add.reduceat(col, edges[:-1][nonempty])
        size = t.size * cell_w
        frac = np.divide(counts, size, out=np.zeros(width), where=size > 0)
        cells = [" " if f == 0 else "." if f <= 1 / 3 else ":" if f <= 2 / 3 else "#" for f in frac]
        lines.append(f"{lab:<{lw}} {''.join(cells)}")
    sp = _sparsity(game)
    lines.append(
        f"J = dr/du: {sp['shape'][0]} x {sp['shape'][1]}, {sp['nnz']} structural nonzeros "
        f"(density {sp['density']:.3f}); columns: controls, agent-major then time"
    )
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------
# Formulas, dynamics, parameters, Hessian pattern, values over time, the whole report
# ----------------------------------------------------------------------------------------
#: The energy convention, stated once by every report.
ENERGY_CONVENTION = (
    "E(u, p) = 1/2 sum_t ||w_t c_t(u, p)||^2 = 1/2 ||r(u, p)||^2: each term t is its weight "
    "parameter w_t times its residual c_t, so the weight enters squared (doubling w_t "
    "multiplies the term's energy by 4)"
)

#: What the characters of the text spy pictures mean.
SPY_LEGEND = (
    "legend: each cell is a block of entries; ' ' no structural nonzero, '.' up to 1/3 of "
    "the block's entries, ':' up to 2/3, '#' more"
)

REPORT_FORMAT = "epo-inspect/1"


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
    from .features import AgentContext

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


def param_summary(game: PotentialGame, p: np.ndarray | None = None) -> list[dict]:
    """Every block of the parameter vector: ``name, group, start, size, entries, values``
    (at ``p``; the defaults when ``p`` is None) and ``default``."""
    game = _check_game(game)
    P = game.params.defaults() if p is None else game.check_inputs(game.zero_controls(), p)[1][0]
    return [
        {
            "name": b.name,
            "group": b.group,
            "start": b.start,
            "size": b.size,
            "entries": list(b.entries),
            "values": [float(v) for v in P[b.slice]],
            "default": [float(v) for v in b.default],
        }
        for b in game.params.blocks
    ]


def _jacobian_csr(game: PotentialGame):
    """The pattern of ``J`` as a boolean CSR matrix (kept with the game: many readers)."""

    def build():
        import scipy.sparse as sps

        rows, cols = game.jacobian_sparsity().get_triplet()
        data = np.ones(len(rows), dtype=bool)
        return sps.csr_matrix((data, (rows, cols)), shape=(game.n_r, game.n_u))

    return game.cached(("inspect", "jacobian_csr"), build)


def hessian_pattern(game: PotentialGame):
    """Structural pattern of the Gauss-Newton Hessian ``J^T J`` (``n_u x n_u``), from the
    pattern of ``J``: entry ``(a, b)`` may be nonzero iff some residual row depends on both
    controls ``a`` and ``b``. A ``scipy.sparse`` CSR boolean matrix (50 agents: 15 million
    entries, a few seconds). The exact Hessian adds second derivatives of the residuals,
    which couple only controls that already share a row, so its pattern lies inside this one.
    """
    game = _check_game(game)

    def build():
        A = _jacobian_csr(game)
        H = (A.T @ A).tocsr()
        H.eliminate_zeros()
        return H

    return game.cached(("inspect", "gn_hessian_pattern"), build)


def hessian_sparsity(game: PotentialGame, H=None) -> dict:
    """``shape``, ``nnz``, ``density`` of :func:`hessian_pattern` and ``agent_blocks``: the
    nonzeros of each ``(agent_i, agent_j)`` block (``N x N`` list, row and column order of
    :attr:`PotentialGame.agent_names`)."""
    game = _check_game(game)
    H = hessian_pattern(game) if H is None else H
    n = game.n_u
    coo = H.tocoo()
    ai = np.searchsorted(game.uoff, coo.row, side="right") - 1
    aj = np.searchsorted(game.uoff, coo.col, side="right") - 1
    blocks = np.zeros((game.N, game.N), dtype=np.int64)
    np.add.at(blocks, (ai, aj), 1)
    nnz = int(H.nnz)
    return {
        "kind": "Gauss-Newton J^T J",
        "shape": (n, n),
        "nnz": nnz,
        "density": nnz / (n * n) if n else 0.0,
        "agent_blocks": blocks.tolist(),
    }


def _cell_edges(n: int, width: int) -> np.ndarray:
    width = max(1, min(width, n))
    return np.linspace(0, n, width + 1).round().astype(int)


def hessian_spy_text(game: PotentialGame, width: int = 24, H=None) -> str:
    """A text spy of the Gauss-Newton Hessian pattern (``width x width`` cells; characters
    as in :data:`SPY_LEGEND`); ``|name`` marks where an agent's controls start."""
    game = _check_game(game)
    if not isinstance(width, int) or width < 4:
        raise SpecError("width", f"expected an integer >= 4, got {width!r}")
    H = hessian_pattern(game) if H is None else H
    edges = _cell_edges(game.n_u, width)
    w = len(edges) - 1
    coo = H.tocoo()
    ci = np.searchsorted(edges, coo.row, side="right") - 1
    cj = np.searchsorted(edges, coo.col, side="right") - 1
    counts = np.zeros((w, w))
    np.add.at(counts, (ci, cj), 1)
    sizes = np.outer(np.diff(edges), np.diff(edges))
    frac = np.divide(counts, sizes, out=np.zeros((w, w)), where=sizes > 0)
    starts = {
        int(np.searchsorted(edges, game.uoff[i], side="right") - 1): a
        for i, a in enumerate(game.agent_names)
    }
    head = [" "] * w
    for c, a in starts.items():
        for j, ch in enumerate("|" + a):
            if c + j < w and (j == 0 or head[c + j] == " "):
                head[c + j] = ch
    lw = max((len(a) for a in game.agent_names), default=0) + 1
    lines = [f"{'':<{lw}} {''.join(head)}"]
    for r in range(w):
        lab = ("|" + starts[r]) if r in starts else ""
        cells = "".join(
            " " if f == 0 else "." if f <= 1 / 3 else ":" if f <= 2 / 3 else "#" for f in frac[r]
        )
        lines.append(f"{lab:<{lw}} {cells}")
    return "\n".join(lines)


def term_series(game: PotentialGame, p: np.ndarray, u: np.ndarray) -> list[dict]:
    """Each term's value over time at ``(p, u)``: ``index``, ``steps`` (the time steps, a
    list), ``energy`` (per step ``1/2 ||w c_k||^2``; ``None`` when the term's rows do not
    split evenly over its steps), ``active`` (steps with a nonzero value) and ``total``."""
    game = _check_game(game)
    r = _eval(game, "residual", p, u)
    out = []
    for t in game.terms:
        rr = r[t.rows]
        n = len(t.steps)
        if n and rr.size % n == 0:
            e = 0.5 * np.sum(rr.reshape(n, -1) ** 2, axis=1)
            per = [float(v) for v in e]
            active = [int(k) for k, v in zip(t.steps, e, strict=True) if v > 0]
        else:
            per, active = None, [int(k) for k in t.steps] if np.any(rr != 0) else []
        out.append(
            {
                "index": t.index,
                "steps": [int(k) for k in t.steps],
                "energy": per,
                "active": active,
                "total": float(0.5 * rr @ rr),
            }
        )
    return out


def _finite(v):
    return float(v) if np.isfinite(v) else None


def inspect_report(
    game: PotentialGame,
    p: np.ndarray | None = None,
    u: np.ndarray | None = None,
    *,
    source: str | None = None,
    hessian: bool = True,
) -> dict:
    """Everything :func:`report_text` prints, as one JSON-ready dict (schema
    ``epo-inspect/1``, documented in docs/gamefiles.md): the energy convention, sizes,
    dynamics, parameters (values at ``p``), terms with formulas, Jacobian and (``hessian``)
    Gauss-Newton Hessian sparsity, and with a solution ``u`` its energy per term, agent
    costs, each term's value over time, states and controls per agent."""
    game = _check_game(game)
    p = game.params.defaults() if p is None else np.asarray(p, dtype=float).reshape(-1)
    pv = param_summary(game, p)
    rows = term_rows(game)
    for row, t in zip(rows, game.terms, strict=True):
        row["weight_value"] = float(p[game.params[t.weight].start])
        row["step_list"] = [int(k) for k in t.steps]
        row["rows"] = list(row["rows"])
        row.update({k: v for k, v in term_formula(game, t).items() if k != "steps"})
    jac = jacobian_sparsity(game)
    jac["shape"] = list(jac["shape"])
    rep: dict = {
        "format": REPORT_FORMAT,
        "energy_convention": ENERGY_CONVENTION,
        "sizes": {
            "N": game.N,
            "K": game.K,
            "dt": game.dt,
            "n_u": game.n_u,
            "n_x": game.n_x,
            "n_p": game.n_p,
            "n_r": game.n_r,
            "terms": len(game.terms),
        },
        "agents": list(game.agent_names),
        "dynamics": dynamics_summary(game),
        "params": pv,
        "terms": rows,
        "jacobian": jac,
        "hessian": None,
        "solution": None,
    }
    if source is not None:
        rep["game"] = source
    if hessian:
        hs = hessian_sparsity(game)
        hs["shape"] = list(hs["shape"])
        rep["hessian"] = hs
    if u is not None:
        U, _ = game.check_inputs(u, p)
        u = U[0]
        e = _eval(game, "term_energies", p, u)
        total = float(e.sum())
        series = term_series(game, p=p, u=u)
        x = _eval(game, "rollout", p, u)
        X, Uc = game.split_states(x), game.split_controls(u)
        rep["solution"] = {
            "energy": _finite(total),
            "terms": [
                {
                    "index": s["index"],
                    "energy": _finite(et),
                    "share": float(et / total) if total > 0 else 0.0,
                    "steps": s["steps"],
                    "energy_per_step": s["energy"],
                    "active_steps": s["active"],
                }
                for s, et in zip(series, e, strict=True)
            ],
            "agent_costs": agent_breakdown(game, p=p, u=u),
            "states": {a: X[i].tolist() for i, a in enumerate(game.agent_names)},
            "controls": {a: Uc[i].tolist() for i, a in enumerate(game.agent_names)},
            "state_names": {a.name: list(a.dynamics.state_names) for a in game.agents},
            "control_names": {a.name: list(a.dynamics.control_names) for a in game.agents},
        }
    return rep


def _fmt_values(v: Sequence[float], limit: int = 8) -> str:
    s = [f"{x:.6g}" for x in v]
    if len(s) > limit:
        s = s[: limit - 2] + ["..."] + s[-1:]
    return s[0] if len(v) == 1 else "[" + ", ".join(s) + "]"


def report_text(game: PotentialGame, rep: dict, *, spy: bool = True, top: int | None = None) -> str:
    """The text of ``epo inspect`` from :func:`inspect_report`'s dict (same numbers)."""
    game = _check_game(game)
    sz = rep["sizes"]
    L = [
        f"{sz['terms']} energy terms; N = {sz['N']} agents, K = {sz['K']} steps of "
        f"{sz['dt']:g} s, n_u = {sz['n_u']} controls, n_p = {sz['n_p']} parameters, "
        f"n_r = {sz['n_r']} residuals",
        f"energy: {rep['energy_convention']}",
        "",
        "dynamics (x_{k+1} = f(x_k, u_k, dt), states and controls per agent in this order):",
    ]
    for g in rep["dynamics"]:
        ag = g["agents"]
        who = ", ".join(ag) if len(ag) <= 6 else f"{ag[0]}, ..., {ag[-1]} ({len(ag)} agents)"
        joint = " (coupled: one joint model steps these agents)" if g.get("coupled") else ""
        L.append(
            f"  {g['model']} [{who}]{joint}: states ({', '.join(g['states'])}), controls "
            f"({', '.join(g['controls'])}), integrator {g['integrator']}, dt = {g['dt']:g} s"
        )
        for s, e in g["update"].items():
            L.append(f"    {s}+ = {e}")
    L += ["", f"parameters p ({sz['n_p']} entries; value at p, and the default where it differs):"]
    L += _table(
        ["block", "group", "entries", "value"],
        [
            [
                b["name"],
                b["group"],
                f"{b['start']}:{b['start'] + b['size']}",
                _fmt_values(b["values"])
                + (
                    "" if b["values"] == b["default"] else f" (default {_fmt_values(b['default'])})"
                ),
            ]
            for b in rep["params"]
        ],
        [False, False, False, False],
    )
    L += ["", "terms (weight at p; r rows; formula of the weighted residual w * c, k over steps):"]
    body = [
        [
            str(r["index"]),
            r["kind"],
            "-".join(r["agents"]),
            _label_row(r),
            r["weight"],
            f"{r['weight_value']:g}",
            r["steps"],
            str(r["size"]),
            f"{r['rows'][0]}:{r['rows'][1]}",
        ]
        for r in rep["terms"]
    ]
    L += _table(
        ["#", "kind", "agents", "feature", "weight parameter", "value", "steps", "size", "rows"],
        body,
        [True, False, False, False, False, True, False, True, False],
    )
    L += ["", "formulas:"]
    for r in _distinct_formulas(rep["terms"]):
        L.append(f"  {r['index']:>3} {r['formula']}   ({r['steps_k']}{r['note']})")
    sol = rep["solution"]
    if sol is not None:
        L += ["", _solution_text(rep, top)]
    L.append("")
    jac = rep["jacobian"]
    if spy:
        L.append(spy_text(game))
        L.append(
            SPY_LEGEND + "; rows: terms (index agents.feature); columns: controls, "
            "'|name' where an agent's controls start"
        )
    else:
        L.append(
            f"J = dr/du: {jac['shape'][0]} x {jac['shape'][1]}, {jac['nnz']} structural nonzeros "
            f"(density {jac['density']:.3f})"
        )
    hs = rep["hessian"]
    if hs is not None:
        L.append("")
        L.append(
            f"H = J^T J (Gauss-Newton Hessian pattern): {hs['shape'][0]} x {hs['shape'][1]}, "
            f"{hs['nnz']} structural nonzeros (density {hs['density']:.3f}); blocks "
            "coupling two agents come from pair terms only"
        )
        if spy:
            L.append(hessian_spy_text(game))
            L.append(SPY_LEGEND + "; rows and columns: controls")
    return "\n".join(L)


def _label_row(r: dict) -> str:
    return (
        r["feature"]
        if r["feature"] == r["feature_type"]
        else f"{r['feature']} ({r['feature_type']})"
    )


def _distinct_formulas(terms: list[dict]) -> list[dict]:
    """One line per term, but pair terms with one formula up to the agents' names once."""
    out, seen = [], {}
    for r in terms:
        if r["kind"] == "pair":
            a, b = r["agents"]
            key = (r["feature"], r["residual"].replace(f"{a}.", "A.").replace(f"{b}.", "B."))
            if key in seen:
                seen[key]["n"] += 1
                continue
        d = {
            "index": r["index"],
            "formula": r["formula"],
            "steps_k": f"k = {r['steps']}",
            "note": "" if r["source"] == "formula()" else f"; residual {r['source']}",
            "n": 1,
        }
        out.append(d)
        if r["kind"] == "pair":
            seen[key] = d
    for d in out:
        if d["n"] > 1:
            d["note"] += f"; the same for {d['n'] - 1} more pairs"
    return out


def _solution_text(rep: dict, top: int | None) -> str:
    sol = rep["solution"]
    terms = {r["index"]: r for r in rep["terms"]}
    E = sol["energy"]
    rows = sorted(sol["terms"], key=lambda s: -(s["energy"] or 0.0))
    shown = rows if top is None else rows[:top]
    L = [
        f"energy E = {E:.6g} (sum of {len(rows)} terms, largest first)"
        if E is not None
        else "energy E = none (non-finite)"
    ]
    body = []
    for s in shown:
        r = terms[s["index"]]
        per = s["energy_per_step"]
        if per:
            kmax = s["steps"][int(np.argmax(per))]
            peak = f"{max(per):.6g} at k = {kmax}"
        else:
            peak = "-"
        body.append(
            [
                str(s["index"]),
                r["kind"],
                "-".join(r["agents"]),
                _label_row(r),
                "none" if s["energy"] is None else f"{s['energy']:.6g}",
                f"{100 * s['share']:.1f}%",
                format_steps(s["active_steps"]),
                peak,
            ]
        )
    L += _table(
        ["#", "kind", "agents", "feature", "energy", "share", "active steps", "peak"],
        body,
        [True, False, False, False, True, True, False, False],
    )
    if len(shown) < len(rows):
        rest = sum(s["energy"] or 0.0 for s in rows[len(shown) :])
        L.append(f"... {len(rows) - len(shown)} more terms with {rest:.6g} in total")
    L += ["", "agent costs C_i = own + pair (pair terms count for both agents)"]
    L += _table(
        ["agent", "C_i", "own", "pair"],
        [
            [a["agent"], f"{a['cost']:.6g}", f"{a['own']:.6g}", f"{a['pair']:.6g}"]
            for a in sol["agent_costs"]
        ],
        [False, True, True, True],
    )
    return "\n".join(L)
