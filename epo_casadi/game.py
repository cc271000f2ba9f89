"""The single-shooting potential game: the problem contract of the whole toolkit.

Every other module refers to this docstring for notation, shapes and index order.

Agents and time
    ``N`` agents, indexed ``i = 0..N-1`` in the order of :attr:`GameSpec.agents`.
    Agent ``i`` has ``nx_i`` states and ``nu_i`` controls (:mod:`epo_casadi.dynamics`).
    Horizon ``K`` steps of length ``dt``: controls ``u_{i,k}`` for ``k = 0..K-1``, states
    ``x_{i,k}`` for ``k = 0..K``, ``x_{i,k+1} = f_i(x_{i,k}, u_{i,k}, dt)``, ``x_{i,0}`` given.

Decision variable ``u`` (the joint open-loop strategy), length ``n_u = K * sum_i nu_i``
    agent-major, then time, then control component::

        u[uoff_i + k * nu_i + c]    (uoff_i = K * sum_{j<i} nu_j)

    :meth:`PotentialGame.split_controls` turns it into per-agent ``(K, nu_i)`` arrays.

Rolled-out states ``x``, length ``n_x = (K+1) * sum_i nx_i``, same order::

        x[xoff_i + k * nx_i + c]    (k = 0..K; the k = 0 block is the initial state)

Parameters ``p``, length ``n_p``: one flat vector, described by :class:`ParamLayout`
    (:attr:`PotentialGame.params`), made of named blocks in this order:
    ``x0.<agent>`` (initial state, ``nx_i``), ``goal.<agent>`` (2), ``vref.<agent>`` (1),
    ``path.<agent>`` (``2 P``, polyline vertices ``x0, y0, x1, y1, ...``), the blocks
    features declare themselves ``<name>.<agent>`` (:class:`epo_casadi.features.ParamSpec`;
    agent order, then the order the agent's features declare them), then the own
    weights ``w.<agent>.<feature>`` (1 each) and the pair weights
    ``w.<agent_a>-<agent_b>.<feature>`` (1 each, ``a`` before ``b`` in agent order).
    Reference and feature blocks exist only for agents with a feature that reads them.

Residual ``r(u, p)`` and energy (paper Eq. (6)-(7))
    ``r`` stacks weighted feature residuals: for each agent, each own feature in the
    order given, ``w * c(.)``; then for each pair feature, each pair ``a < b``,
    ``w * d(.)``. :attr:`PotentialGame.terms` lists every block (agent, feature, weight
    parameter, time steps, rows). The energy is ``E(u, p) = 1/2 ||r(u, p)||^2``.

Agent costs (the game)
    ``C_i(u, p) = own_i + sum_{j != i} pair_ij`` with ``own_i`` the energy of agent
    ``i``'s own blocks and ``pair_ij`` the energy of the pair blocks of ``{i, j}``. Pair
    terms are shared by both agents, so, **when each agent's dynamics depend on its own
    controls only** (no :class:`Coupling`), ``C_i - E`` (the other agents' own blocks and
    their pairs without ``i``) does not depend on ``u_i``: every stationary point of ``E``
    is stationary for each ``C_i`` in ``u_i``, and a minimizer of ``E`` is an open-loop
    Nash equilibrium (paper Theorem C.1, App. C). With coupled dynamics
    (``GameSpec(couplings=...)``, :attr:`PotentialGame.coupled`) an agent's controls move
    another agent's state, ``C_i - E`` depends on ``u_i``, and a minimizer of ``E`` is in
    general not a Nash equilibrium: the potential solvers say so in their result
    (``SolveResult.equilibrium``, :class:`solvers.result.Equilibrium`), and the open-loop
    Nash certificate (:mod:`solvers.nash`) tests the agents' own conditions.

Batches
    Numeric arrays may carry leading batch dimensions: ``u`` as ``(B, n_u)``, ``p`` as
    ``(B, n_p)``. CasADi functions take one problem (column vectors).

Named CasADi functions (:meth:`PotentialGame.function`), all with inputs ``(u, p)``
unless noted: ``rollout -> x``, ``residual -> r``, ``energy -> E``,
``gradient -> g``, ``jacobian -> J`` (of ``r``), ``hessian -> H`` (exact, of ``E``),
``gn_hessian -> H`` (``J'J``), ``agent_costs -> C`` (``N``),
``pseudo_gradient -> g`` (stacked ``dC_i/du_i``), ``term_energies -> e`` (one per
term), ``lm_terms -> (r, J)`` (dense ``J``, for batched solvers),
``traj_residual(x, u, p) -> r`` and ``traj_agent_costs(x, u, p) -> C`` (states as free
inputs, for solvers that do not roll out, e.g. iLQ games).

Modules. This module holds :class:`PotentialGame` and the size limits
(:func:`check_size_estimate`); the pieces live beside it and every name stays importable
from here: :mod:`epo_casadi.game_spec` (:class:`AgentSpec`, :class:`Coupling`,
:class:`GameSpec`), :mod:`epo_casadi.game_params` (:class:`ParamLayout`, :class:`Term`) and
:mod:`epo_casadi.game_size` (:func:`estimate_size`, :class:`SizeEstimate`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import casadi as ca
import numpy as np

from .errors import SpecError, check_size
from .features import AgentContext, PairFeature
from .game_params import ParamBlock, ParamLayout, Term
from .game_size import BYTES_PER_ENTRY as BYTES_PER_ENTRY
from .game_size import BYTES_PER_JACOBIAN_NNZ as BYTES_PER_JACOBIAN_NNZ
from .game_size import PAIR_WEIGHT as PAIR_WEIGHT
from .game_size import PATH_SEGMENT_WEIGHT as PATH_SEGMENT_WEIGHT
from .game_size import SizeEstimate, estimate_size
from .game_size import _gb as _gb
from .game_spec import MAX_HORIZON as MAX_HORIZON
from .game_spec import REFERENCES as REFERENCES
from .game_spec import AgentSpec, Coupling, GameSpec, agent_radius
from .game_spec import _finite_vector as _finite_vector

__all__ = [
    "AgentSpec",
    "Coupling",
    "GameSpec",
    "ParamBlock",
    "ParamLayout",
    "Term",
    "PotentialGame",
    "SizeEstimate",
    "estimate_size",
]

#: Largest :attr:`SizeEstimate.entries` a game may have: about 6 GB at
#: :data:`BYTES_PER_ENTRY` (50 agents with every pair colliding: K <= 490; 2 agents: any
#: K up to :data:`MAX_HORIZON`). Solves of games near the limit take many minutes.
MAX_ENTRIES = 2_000_000
#: Largest :attr:`SizeEstimate.jacobian_nnz` for the functions that hold the Jacobian
#: ``J = dr/du`` or a Hessian symbolically (:data:`DERIVATIVE_FUNCTIONS`): about 4 GB at
#: :data:`BYTES_PER_JACOBIAN_NNZ` (a 2-unicycle crossing up to about K = 600).
MAX_JACOBIAN_NNZ = 5_000_000
#: named functions whose build holds the Jacobian (or a Hessian) symbolically: their size
#: grows with the horizon squared in single shooting
DERIVATIVE_FUNCTIONS = ("jacobian", "hessian", "gn_hessian", "lm_terms")


def check_size_estimate(spec: GameSpec, functions: Sequence[str] = ()) -> SizeEstimate:
    """Refuse a game too large to build (:data:`MAX_ENTRIES`) and, when ``functions``
    name one of :data:`DERIVATIVE_FUNCTIONS`, one whose Jacobian is too large to build
    (:data:`MAX_JACOBIAN_NNZ`); one :class:`SpecError` naming the limit. Returns the
    estimate."""
    est = estimate_size(spec)
    hint = "fewer agents or pairs, a shorter horizon or a collision 'every' > 1 make it smaller"
    check_size(
        "game",
        est.entries,
        MAX_ENTRIES,
        f"weighted residual entries: agents and features x steps, pairs x steps; about "
        f"{_gb(est.bytes)} to build and solve; {hint}",
    )
    wanted = [n for n in functions if n in DERIVATIVE_FUNCTIONS]
    if wanted:
        check_size(
            f"function {wanted[0]}",
            est.jacobian_nnz,
            MAX_JACOBIAN_NNZ,
            f"estimated Jacobian nonzeros, growing with the horizon squared; about "
            f"{_gb(est.jacobian_bytes)} to build; {hint}, or leave out "
            f"{', '.join(DERIVATIVE_FUNCTIONS)}",
        )
    return est


# --------------------------------------------------------------------------------------
# The game
# --------------------------------------------------------------------------------------
class PotentialGame:
    """Symbolic single-shooting potential game built from a :class:`GameSpec`.

    See the module docstring for the contract. Functions are built on first use and
    cached; :meth:`function` returns one by name, :attr:`FUNCTIONS` lists them.
    """

    FUNCTIONS = (
        "rollout",
        "residual",
        "energy",
        "gradient",
        "jacobian",
        "hessian",
        "gn_hessian",
        "agent_costs",
        "pseudo_gradient",
        "term_energies",
        "lm_terms",
        "traj_residual",
        "traj_agent_costs",
    )
    #: pair count from which a pair feature is built as one function per group of pairs
    PAIR_FUNCTION_MIN = 16
    #: pair count from which the build shows a progress bar (on a terminal only)
    PAIR_PROGRESS_MIN = 300

    def __init__(self, spec: GameSpec):
        if not isinstance(spec, GameSpec):
            raise SpecError("spec", f"expected a GameSpec, got {type(spec).__name__}")
        #: the size of the build, from the spec (a game over MAX_ENTRIES is refused here)
        self.size_estimate = check_size_estimate(spec)
        self.spec = spec
        self.K = spec.horizon
        self.dt = spec.dt
        self.agents = spec.agents
        self.N = len(spec.agents)
        self.agent_names = [a.name for a in spec.agents]
        self.nx = [a.dynamics.nx for a in spec.agents]
        self.nu = [a.dynamics.nu for a in spec.agents]
        self.uoff = np.concatenate([[0], np.cumsum([self.K * n for n in self.nu])]).astype(int)
        self.xoff = np.concatenate([[0], np.cumsum([(self.K + 1) * n for n in self.nx])]).astype(
            int
        )
        self.n_u = int(self.uoff[-1])
        self.n_x = int(self.xoff[-1])
        self.params = self._layout()
        self.n_p = self.params.size
        #: True when joint models step several agents together (GameSpec.couplings)
        self.coupled = bool(spec.couplings)
        idx = {n: i for i, n in enumerate(self.agent_names)}
        self._couplings = [(tuple(idx[a] for a in c.agents), c.model) for c in spec.couplings]
        coupled = {i for ids, _ in self._couplings for i in ids}
        self._single = [i for i in range(self.N) if i not in coupled]
        self._build()
        self._cache: dict[str, ca.Function] = {}
        self._derived: dict = {}

    # ---- layout ----------------------------------------------------------------------
    def _layout(self) -> ParamLayout:
        blocks: list[ParamBlock] = []
        start = 0

        def add(name, group, default, entries):
            nonlocal start
            default = tuple(float(v) for v in default)
            blocks.append(ParamBlock(name, group, start, len(default), default, tuple(entries)))
            start += len(default)

        for a in self.agents:
            x0 = a.x0 if a.x0 is not None else (0.0,) * a.dynamics.nx
            add(f"x0.{a.name}", "x0", x0, [f"x0.{a.name}.{s}" for s in a.dynamics.state_names])
        refs = [a.refs() for a in self.agents]
        for a, r in zip(self.agents, refs, strict=True):
            if "goal" in r:
                g = a.goal if a.goal is not None else (0.0, 0.0)
                add(f"goal.{a.name}", "goal", g, [f"goal.{a.name}.x", f"goal.{a.name}.y"])
        for a, r in zip(self.agents, refs, strict=True):
            if "vref" in r:
                add(f"vref.{a.name}", "vref", [a.vref or 0.0], [f"vref.{a.name}"])
        for a, r in zip(self.agents, refs, strict=True):
            if "path" in r:
                n = r["path"] // 2
                pts = (
                    np.asarray(a.path, float).reshape(-1) if a.path is not None else np.zeros(2 * n)
                )
                add(
                    f"path.{a.name}",
                    "path",
                    pts,
                    [f"path.{a.name}.{c}{j}" for j in range(n) for c in "xy"],
                )
        for a in self.agents:
            if a.radius_param:
                add(f"radius.{a.name}", "radius", [a.radius], [f"radius.{a.name}"])
        for a in self.agents:
            for s in a.param_specs().values():
                add(f"{s.name}.{a.name}", "feature", s.default, s.entry_names(a.name))
        for a in self.agents:
            for f in a.features:
                add(f"w.{a.name}.{f.key}", "w_own", [f.weight], [f"w.{a.name}.{f.key}"])
        for pf in self.spec.pair_features:
            for i, j in self.spec.pairs_of(pf):
                nm = f"w.{self.agent_names[i]}-{self.agent_names[j]}.{pf.key}"
                add(nm, "w_pair", [pf.weight], [nm])
        return ParamLayout(blocks)

    # ---- symbolic build -----------------------------------------------------------------
    def _contexts(self, x, u, p) -> list[AgentContext]:
        ctxs = []
        for i, a in enumerate(self.agents):
            X = ca.reshape(x[int(self.xoff[i]) : int(self.xoff[i + 1])], self.nx[i], self.K + 1)
            U = ca.reshape(u[int(self.uoff[i]) : int(self.uoff[i + 1])], self.nu[i], self.K)
            refs = {}
            for r in a.refs():
                b = self.params[f"{r}.{a.name}"]
                refs[r] = p[b.start : b.start + b.size]
            ctxs.append(AgentContext(a.dynamics, X, U, self.dt, refs, agent_radius(a, refs)))
        return ctxs

    def agent_steps(self, xs: Sequence, us: Sequence) -> list:
        """Next states of every agent, ``[x_{i,k+1}]``, from stage ``k``'s per-agent states
        ``xs`` and controls ``us`` (CasADi columns, agent order): each agent's own
        dynamics, or the joint model of its coupling."""
        out: list = [None] * self.N
        for i in self._single:
            out[i] = self.agents[i].dynamics.step(xs[i], us[i], self.dt)
        for ids, model in self._couplings:
            nxt = model.step([xs[i] for i in ids], [us[i] for i in ids], self.dt)
            for i, x in zip(ids, nxt, strict=True):
                out[i] = x
        return out

    def stage_step(self, x, u):
        """The joint step of one stage: ``x`` (``sum nx_i``) and ``u`` (``sum nu_i``),
        agents stacked in order -> next ``x``. Solvers that work per stage (iLQ) use it, so
        coupled dynamics reach them."""
        xo = np.concatenate([[0], np.cumsum(self.nx)]).astype(int)
        uo = np.concatenate([[0], np.cumsum(self.nu)]).astype(int)
        xs = [x[int(xo[i]) : int(xo[i + 1])] for i in range(self.N)]
        us = [u[int(uo[i]) : int(uo[i + 1])] for i in range(self.N)]
        return ca.vertcat(*self.agent_steps(xs, us))

    def _rollout_expr(self, u, p):
        xs = []
        for a in self.agents:
            b = self.params[f"x0.{a.name}"]
            xs.append(p[b.start : b.start + b.size])
        Us = [
            ca.reshape(u[int(self.uoff[i]) : int(self.uoff[i + 1])], self.nu[i], self.K)
            for i in range(self.N)
        ]
        trajs = [[x] for x in xs]
        for k in range(self.K):
            xs = self.agent_steps(xs, [U[:, k] for U in Us])
            for traj, x in zip(trajs, xs, strict=True):
                traj.append(x)
        return ca.vertcat(*[ca.vertcat(*t) for t in trajs])

    def _pair_residuals(self, pf: PairFeature, pairs, ctxs: list[AgentContext]) -> list:
        """Unweighted residuals ``d`` of ``pf`` for every pair, in the order of ``pairs``.

        Below :attr:`PAIR_FUNCTION_MIN` pairs each pair's expression is built by the
        feature itself. From there on, pairs are grouped by what the feature can see
        besides the trajectories (dynamics, radii, reference sizes); the feature builds
        its expression once per group, as a function of symbolic trajectories, and that
        function is evaluated on each pair's trajectories. CasADi replays the same
        operations, so the expressions are the same either way; only the Python work per
        pair shrinks (1,225 pairs of 50 agents: ~20x less). Long builds show a progress
        bar on a terminal (tqdm).
        """
        if len(pairs) < self.PAIR_FUNCTION_MIN:
            return [pf.residual(ctxs[i], ctxs[j]) for i, j in pairs]
        fns: dict = {}

        def signature(c: AgentContext):
            r = "param" if "radius" in c.refs else float(c.radius)
            return (c.dynamics, r, tuple((n, v.shape) for n, v in c.refs.items()))

        def pair_function(ca_: AgentContext, cb: AgentContext) -> ca.Function:
            key = (signature(ca_), signature(cb))
            if key not in fns:
                syms, ins = [], []
                for tag, c in (("a", ca_), ("b", cb)):
                    X = ca.SX.sym(f"X_{tag}", *c.X.shape)
                    U = ca.SX.sym(f"U_{tag}", *c.U.shape)
                    refs = {n: ca.SX.sym(f"{n}_{tag}", *v.shape) for n, v in c.refs.items()}
                    r = refs["radius"] if "radius" in c.refs else c.radius
                    syms.append(AgentContext(c.dynamics, X, U, c.dt, refs, r))
                    ins += [X, U, *refs.values()]
                fns[key] = ca.Function(f"pair_{pf.key}", ins, [pf.residual(*syms)])
            return fns[key]

        from tqdm.auto import tqdm

        out = []
        bar = tqdm(
            pairs,
            desc=f"building {pf.key} pair terms",
            unit="pair",
            disable=None if len(pairs) >= self.PAIR_PROGRESS_MIN else True,
            leave=False,
        )
        for i, j in bar:
            a, b = ctxs[i], ctxs[j]
            out.append(pair_function(a, b)(a.X, a.U, *a.refs.values(), b.X, b.U, *b.refs.values()))
        return out

    def _build(self):
        u = ca.SX.sym("u", self.n_u)
        p = ca.SX.sym("p", self.n_p)
        x = ca.SX.sym("x", self.n_x)
        ctxs = self._contexts(x, u, p)
        blocks, terms, row = [], [], 0
        for i, a in enumerate(self.agents):
            for f in a.features:
                w = p[self.params[f"w.{a.name}.{f.key}"].start]
                r = w * f.residual(ctxs[i])
                terms.append(
                    Term(
                        len(terms),
                        "own",
                        (a.name,),
                        f.key,
                        f.kind,
                        f"w.{a.name}.{f.key}",
                        tuple(f.steps(self.K)),
                        slice(row, row + r.shape[0]),
                    )
                )
                blocks.append(r)
                row += r.shape[0]
        for pf in self.spec.pair_features:
            pairs = self.spec.pairs_of(pf)
            for (i, j), d in zip(pairs, self._pair_residuals(pf, pairs, ctxs), strict=True):
                nm = f"w.{self.agent_names[i]}-{self.agent_names[j]}.{pf.key}"
                r = p[self.params[nm].start] * d
                terms.append(
                    Term(
                        len(terms),
                        "pair",
                        (self.agent_names[i], self.agent_names[j]),
                        pf.key,
                        pf.kind,
                        nm,
                        tuple(pf.steps(self.K)),
                        slice(row, row + r.shape[0]),
                    )
                )
                blocks.append(r)
                row += r.shape[0]
        self.terms: tuple[Term, ...] = tuple(terms)
        self.n_r = row
        r_traj = ca.vertcat(*blocks) if blocks else ca.SX(0, 1)
        # per-term energies and agent costs, in trajectory form
        e_terms = ca.vertcat(*[0.5 * ca.sumsqr(b) for b in blocks]) if blocks else ca.SX(0, 1)
        C = []
        for a in self.agent_names:
            idx = [t.index for t in self.terms if a in t.agents]
            C.append(ca.sum1(e_terms[idx]) if idx else ca.SX(0))
        C = ca.vertcat(*C)
        self._traj = {
            "traj_residual": ca.Function(
                "traj_residual", [x, u, p], [r_traj], ["x", "u", "p"], ["r"]
            ),
            "traj_term_energies": ca.Function(
                "traj_term_energies", [x, u, p], [e_terms], ["x", "u", "p"], ["e"]
            ),
            "traj_agent_costs": ca.Function(
                "traj_agent_costs", [x, u, p], [C], ["x", "u", "p"], ["C"]
            ),
        }
        self._u, self._p = u, p
        self._x_roll = self._rollout_expr(u, p)
        self._r = self._traj["traj_residual"](self._x_roll, u, p)
        self._e_terms = self._traj["traj_term_energies"](self._x_roll, u, p)
        self._C = self._traj["traj_agent_costs"](self._x_roll, u, p)
        self._E = 0.5 * ca.sumsqr(self._r)

    # ---- functions ----------------------------------------------------------------------
    def function(self, name: str) -> ca.Function:
        """The named CasADi function (see :attr:`FUNCTIONS` and the module docstring)."""
        if name in self._cache:
            return self._cache[name]
        if name in self._traj and name != "traj_term_energies":
            f = self._traj[name]
        elif name in self.FUNCTIONS:
            f = getattr(self, f"_make_{name}")()
        else:
            raise SpecError(
                "function", f"unknown function {name!r}; expected one of {list(self.FUNCTIONS)}"
            )
        self._cache[name] = f
        return f

    def cached(self, key, factory):
        """The object stored under ``key``, made by ``factory()`` on first use.

        The one cache for what solvers derive from a game (backends, NLPs, mapped or
        generated functions): it lives exactly as long as the game. ``key`` must be
        hashable and name everything the object depends on (e.g. its options).
        """
        try:
            return self._derived[key]
        except KeyError:
            value = self._derived[key] = factory()
            return value

    def jacobian_sparsity(self) -> ca.Sparsity:
        """Structural sparsity of ``J = dr/du`` (``n_r x n_u``), without building ``J``.

        The same pattern as the output of :meth:`function` ``("jacobian")``, found by
        sparsity propagation (``n_u / 64`` sweeps) instead of a symbolic Jacobian, whose
        build grows with ``n_u`` times the graph (minutes for 50 agents).
        """
        if "jacobian" in self._cache:
            return self._cache["jacobian"].sparsity_out(0)
        return self.cached(("jacobian_sparsity",), lambda: ca.jacobian_sparsity(self._r, self._u))

    def functions(self) -> dict[str, ca.Function]:
        return {n: self.function(n) for n in self.FUNCTIONS}

    def _fn(self, name, outs, onames):
        return ca.Function(name, [self._u, self._p], outs, ["u", "p"], onames)

    def _make_rollout(self):
        return self._fn("rollout", [self._x_roll], ["x"])

    def _make_residual(self):
        return self._fn("residual", [self._r], ["r"])

    def _make_energy(self):
        return self._fn("energy", [self._E], ["E"])

    def _make_gradient(self):
        return self._fn("gradient", [ca.gradient(self._E, self._u)], ["g"])

    def _make_jacobian(self):
        return self._fn("jacobian", [ca.jacobian(self._r, self._u)], ["J"])

    def _make_hessian(self):
        H, _ = ca.hessian(self._E, self._u)
        return self._fn("hessian", [H], ["H"])

    def _make_gn_hessian(self):
        J = ca.jacobian(self._r, self._u)
        return self._fn("gn_hessian", [ca.mtimes(J.T, J)], ["H"])

    def _make_agent_costs(self):
        return self._fn("agent_costs", [self._C], ["C"])

    def _make_pseudo_gradient(self):
        parts = []
        for i in range(self.N):
            ui = self._u[int(self.uoff[i]) : int(self.uoff[i + 1])]
            parts.append(ca.gradient(self._C[i], ui))
        return self._fn("pseudo_gradient", [ca.vertcat(*parts)], ["g"])

    def _make_term_energies(self):
        return self._fn("term_energies", [self._e_terms], ["e"])

    def _make_lm_terms(self):
        return self._fn(
            "lm_terms", [self._r, ca.densify(ca.jacobian(self._r, self._u))], ["r", "J"]
        )

    def generate_c(
        self,
        directory: str,
        names: Sequence[str] = ("residual", "jacobian"),
        name: str = "epo_game",
    ) -> str:
        """Write C source of the named functions to ``directory/name.c``; return its path.

        Plain CasADi code generation (no compiler needed here). To compile and load it as
        an opt-in speed path use :func:`solvers.codegen.compile_functions`. Avoid Hessians
        of large games: their C is large and slow to compile.
        """
        import os

        if not name.isidentifier():
            raise SpecError("name", f"expected a C identifier, got {name!r}")
        check_size_estimate(self.spec, names)  # a Jacobian too large to build is refused
        cg = ca.CodeGenerator(f"{name}.c", {"with_header": True})
        for n in names:
            cg.add(self.function(n))
        os.makedirs(directory, exist_ok=True)
        cg.generate(os.path.join(directory, ""))
        return os.path.join(directory, f"{name}.c")

    # ---- symbolic access for other builders -----------------------------------------------
    @property
    def symbols(self) -> dict[str, Any]:
        """The SX symbols and expressions: ``u``, ``p``, ``x`` (rollout), ``r``, ``E``, ``C``."""
        return {
            "u": self._u,
            "p": self._p,
            "x": self._x_roll,
            "r": self._r,
            "E": self._E,
            "C": self._C,
        }

    # ---- numeric helpers ------------------------------------------------------------------
    def default_params(self, **values) -> np.ndarray:
        """The parameter vector of the spec's defaults, with named blocks replaced.

        Keywords name blocks with ``__`` for ``.`` (``goal__robot=[1, 2]``); for names
        that are not identifiers use ``game.params.pack({...})``.
        """
        return self.params.pack({k.replace("__", "."): v for k, v in values.items()})

    def split_controls(self, u: np.ndarray) -> list[np.ndarray]:
        """Per-agent controls ``(..., K, nu_i)`` from ``u`` of shape ``(..., n_u)``."""
        u = np.asarray(u)
        return [
            u[..., self.uoff[i] : self.uoff[i + 1]].reshape(*u.shape[:-1], self.K, self.nu[i])
            for i in range(self.N)
        ]

    def join_controls(self, parts: Sequence[np.ndarray]) -> np.ndarray:
        """Inverse of :meth:`split_controls`."""
        if len(parts) != self.N:
            raise SpecError("controls", f"expected {self.N} per-agent arrays, got {len(parts)}")
        flat = []
        for i, a in enumerate(parts):
            a = np.asarray(a, dtype=float)
            if a.shape[-2:] != (self.K, self.nu[i]):
                raise SpecError(
                    f"controls[{i}]", f"expected shape (..., {self.K}, {self.nu[i]}), got {a.shape}"
                )
            flat.append(a.reshape(*a.shape[:-2], -1))
        return np.concatenate(flat, axis=-1)

    def split_states(self, x: np.ndarray) -> list[np.ndarray]:
        """Per-agent states ``(..., K+1, nx_i)`` from ``x`` of shape ``(..., n_x)``."""
        x = np.asarray(x)
        return [
            x[..., self.xoff[i] : self.xoff[i + 1]].reshape(*x.shape[:-1], self.K + 1, self.nx[i])
            for i in range(self.N)
        ]

    def radii(self, p: np.ndarray | None = None) -> np.ndarray:
        """Every agent's collision radius ``(..., N)``: the spec's, or for agents with
        ``radius_param`` the entry ``radius.<name>`` of ``p`` ``(..., n_p)`` (its default
        when ``p`` is None)."""
        fixed = np.array([float(a.radius) for a in self.agents])
        if p is None:
            return fixed
        p = np.asarray(p, dtype=float)
        out = np.broadcast_to(fixed, p.shape[:-1] + (self.N,)).copy()
        for i, a in enumerate(self.agents):
            if a.radius_param:
                out[..., i] = p[..., self.params[f"radius.{a.name}"].start]
        return out

    def positions(self, x: np.ndarray) -> np.ndarray:
        """Positions ``(..., N, K+1, 2)`` of every agent (first two state entries)."""
        return np.stack([s[..., :2] for s in self.split_states(x)], axis=-3)

    def zero_controls(self) -> np.ndarray:
        return np.zeros(self.n_u)

    def check_inputs(self, u, p) -> tuple[np.ndarray, np.ndarray]:
        """Validate shapes and finiteness; return float arrays ``(B, n_u)``, ``(B, n_p)``."""
        u = np.asarray(u, dtype=float)
        p = np.asarray(p, dtype=float)
        if u.shape[-1:] != (self.n_u,):
            raise SpecError("u", f"expected last dimension n_u = {self.n_u}, got shape {u.shape}")
        if p.shape[-1:] != (self.n_p,):
            raise SpecError("p", f"expected last dimension n_p = {self.n_p}, got shape {p.shape}")
        u2, p2 = np.atleast_2d(u), np.atleast_2d(p)
        if u2.ndim != 2 or p2.ndim != 2:
            raise SpecError(
                "u/p", f"expected 1-D or 2-D (batch, n) arrays, got {u.shape} and {p.shape}"
            )
        B = max(u2.shape[0], p2.shape[0])
        if u2.shape[0] not in (1, B) or p2.shape[0] not in (1, B):
            raise SpecError("u/p", f"batch sizes differ: {u2.shape[0]} and {p2.shape[0]}")
        u2 = np.broadcast_to(u2, (B, self.n_u))
        p2 = np.broadcast_to(p2, (B, self.n_p))
        if not np.all(np.isfinite(u2)):
            raise SpecError("u", "contains NaN or inf")
        if not np.all(np.isfinite(p2)):
            bad = sorted({self.params.names[j] for j in np.where(~np.isfinite(p2))[1]})
            raise SpecError("p", f"contains NaN or inf in {bad}")
        return np.ascontiguousarray(u2), np.ascontiguousarray(p2)

    def __repr__(self) -> str:
        return (
            f"PotentialGame(N={self.N}, K={self.K}, dt={self.dt}, n_u={self.n_u}, "
            f"n_p={self.n_p}, n_r={self.n_r}, terms={len(self.terms)})"
        )
