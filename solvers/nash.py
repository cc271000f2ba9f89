"""A *local* certificate that a joint strategy is an open-loop Nash equilibrium.

An open-loop Nash equilibrium (OLNE, paper Def. 3.1) is a joint strategy ``u*`` with
``C_i(u*) <= C_i(u_i, u*_{-i})`` for every agent ``i`` and every ``u_i``. The agent costs
``C_i`` are those of :mod:`epo_casadi.game` (own terms of ``i`` plus the pair terms that
involve ``i``). For each agent, :func:`nash_certificate` measures

* **stationarity** ``s_i = |dC_i/du_i (u, p)|_inf``, from the game's ``pseudo_gradient``
  function: first-order optimality of agent ``i``'s problem with the others fixed;
* **best-response gap** ``gap_i = C_i(u) - min_{u_i} C_i(u_i, u_{-i})``, where the minimum
  is a *local* IPOPT solve of agent ``i``'s own problem (the others' controls fixed),
  warm-started at the given ``u_i``. The gap is ``>= 0`` by construction: when IPOPT
  ends above ``C_i(u)`` the given ``u_i`` is its own best known response.

``ok`` holds when every ``s_i <= stat_tol (1 + |C_i|)`` and every
``gap_i <= gap_tol (1 + |C_i|)``. This is a **local** certificate: a small gap says that
no agent can improve by a unilateral deviation that IPOPT finds from the current
point; it does not exclude a better response in another basin of the non-convex
``C_i`` (e.g. passing a pedestrian on the other side). Bounds are not taken into account:
the certificate is for the unconstrained (soft-penalty) game of the paper.

For a potential game every local minimizer of ``E`` passes (Theorem 1); a strategy
perturbed for one agent fails on that agent. Each agent's best-response NLP is built
once per game and options (parameters: ``p`` and the others' controls) and cached.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError, check_bool, check_number
from epo_casadi.game import PotentialGame

from .lm import check_options

__all__ = ["NashOptions", "NashCertificate", "NashChecker", "nash_certificate"]


@dataclass(frozen=True)
class NashOptions:
    """Tolerances of the certificate and options of the best-response solves."""

    stat_tol: float = 1e-5  #: stationarity tolerance, relative: s_i <= stat_tol * (1 + |C_i|)
    gap_tol: float = 1e-6  #: best-response gap tolerance, relative: gap_i <= gap_tol * (1 + |C_i|)
    best_response: bool = True  #: solve the best responses (False: stationarity only, gaps 0)
    max_iter: int = 300  #: IPOPT iterations per best response
    tol: float = 1e-10  #: IPOPT tolerance of the best responses

    def __post_init__(self):
        for name in ("stat_tol", "gap_tol", "tol"):
            check_number(f"nash.{name}", getattr(self, name), lo=0, lo_open=True)
        check_number("nash.max_iter", self.max_iter, lo=0, integer=True)
        check_bool("nash.best_response", self.best_response)


@dataclass(frozen=True, eq=False)
class NashCertificate:
    """Per-agent evidence for (or against) a local open-loop Nash equilibrium.

    Arrays have one entry per agent, in the order of :attr:`agents`.
    """

    agents: tuple[str, ...]  #: agent names
    costs: np.ndarray  #: C_i(u, p), (N,)
    stationarity: np.ndarray  #: |dC_i/du_i|_inf, (N,)
    best_response_costs: np.ndarray  #: min over u_i found by IPOPT (C_i where not improved), (N,)
    best_response_gap: np.ndarray  #: C_i(u) - best_response_costs >= 0, (N,)
    relative_gap: np.ndarray  #: best_response_gap / (1 + |C_i|), (N,)
    best_response_status: tuple[
        str, ...
    ]  #: IPOPT return status per agent ("skipped" if not solved)
    stat_ok: np.ndarray  #: stationarity within tolerance, (N,) bool
    gap_ok: np.ndarray  #: gap within tolerance, (N,) bool
    ok: bool  #: every agent passes both tests
    options: NashOptions

    def to_dict(self) -> dict:
        """JSON-ready dictionary."""
        d = {}
        for f in fields(self):
            k, v = f.name, getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v = v.tolist()
            elif isinstance(v, tuple):
                v = list(v)
            elif isinstance(v, NashOptions):
                v = asdict(v)
            elif isinstance(v, (np.bool_, np.floating)):
                v = v.item()
            d[k] = v
        return d

    def summary(self) -> str:
        """A text table, one row per agent, and the verdict."""
        head = (
            f"{'agent':>10s} {'C_i':>12s} {'|dC_i/du_i|':>12s} {'gap':>12s} {'rel. gap':>10s}  ok"
        )
        lines = ["local open-loop Nash certificate", head]
        for i, a in enumerate(self.agents):
            ok = "yes" if (self.stat_ok[i] and self.gap_ok[i]) else "NO"
            lines.append(
                f"{a:>10s} {self.costs[i]:12.6g} {self.stationarity[i]:12.3g} "
                f"{self.best_response_gap[i]:12.3g} {self.relative_gap[i]:10.3g}  {ok}"
            )
        o = self.options
        verdict = "passes" if self.ok else "FAILS"
        lines.append(
            f"{verdict} (stat_tol {o.stat_tol:g}, gap_tol {o.gap_tol:g}, relative to 1 + |C_i|)"
        )
        return "\n".join(lines)


class NashChecker:
    """Best-response NLPs of every agent of one game, built once (see the module doc)."""

    def __init__(self, game: PotentialGame, options: NashOptions | dict | None = None):
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        self.game = game
        self.options = check_options(NashOptions, options, "nash")
        self._costs = game.function("agent_costs")
        self._pg = game.function("pseudo_gradient")
        self._br: dict[int, ca.Function] = {}

    def best_response_nlp(self, i: int) -> ca.Function:
        """IPOPT solver of agent ``i``: ``x = u_i``, ``p = [p; u_{-i}]``, ``f = C_i``."""
        if i not in self._br:
            g = self.game
            a, b = int(g.uoff[i]), int(g.uoff[i + 1])
            ui = ca.SX.sym("u_i", b - a)
            uo = ca.SX.sym("u_others", g.n_u - (b - a))
            p = ca.SX.sym("p", g.n_p)
            u = ca.vertcat(uo[:a], ui, uo[a:])
            Ci = self._costs(u, p)[i]
            opts = {
                "print_time": False,
                "error_on_fail": False,
                "show_eval_warnings": False,
                "ipopt.print_level": 0,
                "ipopt.sb": "yes",
                "ipopt.max_iter": self.options.max_iter,
                "ipopt.tol": self.options.tol,
            }
            self._br[i] = ca.nlpsol(
                f"best_response_{i}", "ipopt", {"x": ui, "p": ca.vertcat(p, uo), "f": Ci}, opts
            )
        return self._br[i]

    def certify(self, u: np.ndarray, p: np.ndarray) -> NashCertificate:
        """Certificate for one problem: ``u`` ``(n_u,)``, ``p`` ``(n_p,)``."""
        g = self.game
        U, P = g.check_inputs(u, p)
        if U.shape[0] != 1:
            raise SpecError(
                "u/p", f"expected one problem, got a batch of {U.shape[0]}; certify each"
            )
        u, p = U[0], P[0]
        C = np.asarray(self._costs(u, p), dtype=float).reshape(-1)
        pg = np.asarray(self._pg(u, p), dtype=float).reshape(-1)
        stat = np.array(
            [np.max(np.abs(pg[g.uoff[i] : g.uoff[i + 1]]), initial=0.0) for i in range(g.N)]
        )
        br = C.copy()
        statuses = []
        for i in range(g.N):
            a, b = int(g.uoff[i]), int(g.uoff[i + 1])
            if not self.options.best_response or a == b:
                statuses.append("skipped")
                continue
            solver = self.best_response_nlp(i)
            others = np.concatenate([u[:a], u[b:]])
            sol = solver(x0=u[a:b], p=np.concatenate([p, others]))
            st = solver.stats()
            statuses.append(str(st.get("return_status", "unknown")))
            ui = np.asarray(sol["x"], dtype=float).reshape(-1)
            cand = float(self._costs(np.concatenate([u[:a], ui, u[b:]]), p)[i])
            if np.isfinite(cand):
                br[i] = min(C[i], cand)
        gap = C - br
        scale = 1.0 + np.abs(C)
        o = self.options
        stat_ok = stat <= o.stat_tol * scale
        gap_ok = gap <= o.gap_tol * scale
        return NashCertificate(
            agents=tuple(g.agent_names),
            costs=C,
            stationarity=stat,
            best_response_costs=br,
            best_response_gap=gap,
            relative_gap=gap / scale,
            best_response_status=tuple(statuses),
            stat_ok=stat_ok,
            gap_ok=gap_ok,
            ok=bool(np.all(stat_ok) and np.all(gap_ok)),
            options=o,
        )


def nash_certificate(
    game: PotentialGame,
    u: np.ndarray,
    p: np.ndarray,
    options: NashOptions | dict | None = None,
) -> NashCertificate:
    """Local open-loop Nash certificate of the joint strategy ``u`` (``(n_u,)``) for ``p``.

    See the module docstring for what is measured and what "local" means. ``options``:
    :class:`NashOptions` or a dict of its fields (unknown keys raise
    :class:`~epo_casadi.errors.SpecError`).
    """
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    opts = check_options(NashOptions, options, "nash")
    return game.cached(("nash", opts), lambda: NashChecker(game, opts)).certify(u, p)
