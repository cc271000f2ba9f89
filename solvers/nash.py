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

Tolerances. Both tests are relative to a *bounded* scale
``S_i = 1 + min(|C_i|, scale_cap)``: ``s_i <= stat_tol S_i`` and ``gap_i <= gap_tol S_i``.
The cap keeps a huge cost from excusing a huge gradient (a failed solve with
``C_i = 2e204`` and ``s_i = 3e103`` passes a plain relative test). An agent also fails
when its cost or stationarity is not finite, and when its best-response solve stopped
without converging (IPOPT status other than ``Solve_Succeeded`` /
``Solved_To_Acceptable_Level``) unless the point it reached already shows a gap above
the tolerance: a failed best response is no evidence of a small gap.
:attr:`NashCertificate.reasons` says, per agent, why it fails.

This is a **local** certificate: a small gap says that no agent can improve by a
unilateral deviation that IPOPT finds from the current point; it does not exclude a
better response in another basin of the non-convex ``C_i`` (e.g. passing a pedestrian on
the other side). Bounds are not taken into account: the certificate is for the
unconstrained (soft-penalty) game of the paper.

Cost. Each agent's best-response NLP is built once per game and options (parameters:
``p`` and the others' controls) and cached. Its Hessian decides the cost: an exact Hessian
of a single-shooting problem is dense and its symbolic build grows quickly with the
agent's control count ``n_i = K nu_i`` (1 s at ``n_i = 200``, 8 s at 400, minutes at
1,000). So agents with ``n_i <= exact_hessian_max`` get the exact Hessian, larger ones a
limited-memory (L-BFGS) Hessian that needs only the gradient, and agents with
``n_i > best_response_max`` get the stationarity test only; the table says which.
:attr:`NashCertificate.time_s` is the certificate's own wall time, and long checks show a
progress bar on a terminal (tqdm).

For a potential game every local minimizer of ``E`` passes (Theorem 1); a strategy
perturbed for one agent fails on that agent.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields, replace

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError, check_bool, check_number
from epo_casadi.game import PotentialGame

from .lm import check_options

__all__ = ["NashOptions", "NashCertificate", "NashChecker", "nash_certificate"]

#: IPOPT statuses after which a best response counts as evidence of the gap
CONVERGED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


@dataclass(frozen=True)
class NashOptions:
    """Tolerances of the certificate and options of the best-response solves."""

    stat_tol: float = 1e-5  #: stationarity tolerance: s_i <= stat_tol * S_i (see the module doc)
    gap_tol: float = 1e-6  #: best-response gap tolerance: gap_i <= gap_tol * S_i
    scale_cap: float = 1e6  #: S_i = 1 + min(|C_i|, scale_cap): the scale of both tolerances
    best_response: bool = True  #: solve the best responses (False: stationarity only, gaps 0)
    exact_hessian_max: int = 200  #: exact Hessian up to this many controls per agent, then L-BFGS
    best_response_max: int = 600  #: agents with more controls get the stationarity test only
    max_iter: int = 300  #: IPOPT iterations per best response
    tol: float = 1e-10  #: IPOPT tolerance of the best responses

    def __post_init__(self):
        for name in ("stat_tol", "gap_tol", "tol", "scale_cap"):
            check_number(f"nash.{name}", getattr(self, name), lo=0, lo_open=True)
        for name in ("max_iter", "exact_hessian_max", "best_response_max"):
            check_number(f"nash.{name}", getattr(self, name), lo=0, integer=True)
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
    relative_gap: np.ndarray  #: best_response_gap / S_i, (N,)
    best_response_status: tuple[
        str, ...
    ]  #: IPOPT return status per agent ("skipped" if not solved)
    best_response_method: tuple[
        str, ...
    ]  #: "exact" / "l-bfgs" Hessian, or "off" / "too large" (stationarity only), per agent
    stat_ok: np.ndarray  #: stationarity finite and within tolerance, (N,) bool
    gap_ok: np.ndarray  #: gap within tolerance and backed by a converged solve, (N,) bool
    reasons: tuple[str, ...]  #: why each agent fails ("" where it passes)
    ok: bool  #: every agent passes both tests
    time_s: float  #: wall time of the certificate (on first use, with building its functions)
    options: NashOptions

    def to_dict(self) -> dict:
        """JSON-ready dictionary (non-finite numbers as None)."""
        d = {}
        for f in fields(self):
            k, v = f.name, getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v = [x if not isinstance(x, float) or np.isfinite(x) else None for x in v.tolist()]
            elif isinstance(v, tuple):
                v = list(v)
            elif isinstance(v, NashOptions):
                v = asdict(v)
            elif isinstance(v, (np.bool_, np.floating)):
                v = v.item()
            d[k] = v
        return d

    def summary(self) -> str:
        """A text table, one row per agent, the verdict and the reasons of failures."""
        head = (
            f"{'agent':>10s} {'C_i':>12s} {'|dC_i/du_i|':>12s} {'gap':>12s} {'rel. gap':>10s}"
            f" {'best resp.':>10s}  ok"
        )
        lines = ["local open-loop Nash certificate", head]
        for i, a in enumerate(self.agents):
            ok = "yes" if (self.stat_ok[i] and self.gap_ok[i]) else "NO"
            lines.append(
                f"{a:>10s} {self.costs[i]:12.6g} {self.stationarity[i]:12.3g} "
                f"{self.best_response_gap[i]:12.3g} {self.relative_gap[i]:10.3g}"
                f" {self.best_response_method[i]:>10s}  {ok}"
            )
        o = self.options
        verdict = "passes" if self.ok else "FAILS"
        lines.append(
            f"{verdict} (stat_tol {o.stat_tol:g}, gap_tol {o.gap_tol:g}, relative to "
            f"1 + min(|C_i|, {o.scale_cap:g})) in {self.time_s:.3g} s"
        )
        skipped = [
            a
            for a, m in zip(self.agents, self.best_response_method, strict=True)
            if m in ("off", "too large")
        ]
        if skipped:
            lines.append(
                f"stationarity only (best response not solved) for {', '.join(skipped)}: "
                + (
                    "best_response is off"
                    if not o.best_response
                    else f"more than best_response_max = {o.best_response_max} controls"
                )
            )
        for a, r in zip(self.agents, self.reasons, strict=True):
            if r:
                lines.append(f"  {a}: {r}")
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

    def method(self, i: int) -> str:
        """How agent ``i``'s best response is found: ``exact``, ``l-bfgs``, ``off``, ``too large``."""
        n = int(self.game.uoff[i + 1] - self.game.uoff[i])
        o = self.options
        if not o.best_response or n == 0:
            return "off"
        if n > o.best_response_max:
            return "too large"
        return "exact" if n <= o.exact_hessian_max else "l-bfgs"

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
            if self.method(i) == "l-bfgs":
                opts["ipopt.hessian_approximation"] = "limited-memory"
            self._br[i] = ca.nlpsol(
                f"best_response_{i}", "ipopt", {"x": ui, "p": ca.vertcat(p, uo), "f": Ci}, opts
            )
        return self._br[i]

    def certify(self, p: np.ndarray, u: np.ndarray) -> NashCertificate:
        """Certificate for one problem: ``p`` ``(n_p,)``, ``u`` ``(n_u,)`` (the order of
        :func:`nash_certificate`).

        Non-finite ``u`` or ``p`` give a failing certificate (not an exception): every
        solver status, including ``nonfinite``, has one.
        """
        t0 = time.perf_counter()
        g = self.game
        u = np.asarray(u, dtype=float)
        p = np.asarray(p, dtype=float)
        finite_in = bool(np.all(np.isfinite(u)) and np.all(np.isfinite(p)))
        U, P = g.check_inputs(np.nan_to_num(u), np.nan_to_num(p))  # shapes only
        if U.shape[0] != 1:
            raise SpecError(
                "u/p", f"expected one problem, got a batch of {U.shape[0]}; certify each"
            )
        u, p = u.reshape(-1), p.reshape(-1)
        o = self.options
        methods = tuple(self.method(i) for i in range(g.N))
        C, stat = self._stationarity(u, p, finite_in)
        finite = np.isfinite(C) & np.isfinite(stat)
        scale = 1.0 + np.minimum(np.abs(np.nan_to_num(C, nan=np.inf)), o.scale_cap)
        stat_ok = finite & (stat <= o.stat_tol * scale)
        br = C.copy()
        gap_ok = finite.copy()
        statuses, reasons = [], []
        todo = [i for i in range(g.N) if finite[i] and methods[i] in ("exact", "l-bfgs")]
        bar = self._progress(todo)
        for i in range(g.N):
            why = self._first_order_reasons(i, finite_in, finite, stat_ok, stat, scale)
            if i not in todo:
                statuses.append("skipped")
                reasons.append("; ".join(why))
                continue
            st, cand = self._best_response(i, u, p)
            statuses.append(st)
            if np.isfinite(cand):
                br[i] = min(C[i], cand)
            gap_i = C[i] - br[i]
            if gap_i > o.gap_tol * scale[i]:
                gap_ok[i] = False
                why.append(
                    f"best response lowers C_i by {gap_i:.3g} > gap_tol x (1 + min(|C_i|, "
                    f"scale_cap)) = {o.gap_tol * scale[i]:.3g}"
                )
            elif st not in CONVERGED:
                gap_ok[i] = False
                why.append(f"best-response solve did not converge ({st}): the gap is unknown")
            reasons.append("; ".join(why))
            bar.update(1)
        bar.close()
        with np.errstate(invalid="ignore"):
            gap = C - br  # NaN where C_i is not finite
        return NashCertificate(
            agents=tuple(g.agent_names),
            costs=C,
            stationarity=stat,
            best_response_costs=br,
            best_response_gap=gap,
            relative_gap=gap / scale,
            best_response_status=tuple(statuses),
            best_response_method=methods,
            stat_ok=stat_ok,
            gap_ok=gap_ok,
            reasons=tuple(reasons),
            ok=bool(np.all(stat_ok) and np.all(gap_ok)),
            time_s=time.perf_counter() - t0,
            options=o,
        )

    def _stationarity(self, u, p, finite_in: bool) -> tuple[np.ndarray, np.ndarray]:
        """Each agent's cost ``C_i`` and stationarity ``max |dC_i/du_i|`` (``(N,)`` each;
        NaN where not finite or where the inputs are not)."""
        g = self.game
        if not finite_in:
            return np.full(g.N, np.nan), np.full(g.N, np.nan)
        with np.errstate(all="ignore"):
            C = np.asarray(self._costs(u, p), dtype=float).reshape(-1)
            pg = np.asarray(self._pg(u, p), dtype=float).reshape(-1)
        stat = np.array(
            [np.max(np.abs(pg[g.uoff[i] : g.uoff[i + 1]]), initial=0.0) for i in range(g.N)]
        )
        stat[[not np.all(np.isfinite(pg[g.uoff[i] : g.uoff[i + 1]])) for i in range(g.N)]] = np.nan
        return C, stat

    def _progress(self, todo: list[int]):
        """A progress bar over the best-response solves, shown for large problems only."""
        g = self.game
        work = sum(int(g.uoff[i + 1] - g.uoff[i]) for i in todo)
        from tqdm.auto import tqdm

        return tqdm(
            total=len(todo),
            desc="Nash certificate: best responses",
            unit="agent",
            disable=None if work >= 400 else True,
            leave=False,
        )

    def _first_order_reasons(self, i, finite_in, finite, stat_ok, stat, scale) -> list[str]:
        """Why agent ``i`` fails the first-order test (empty where it passes)."""
        why = []
        if not finite_in:
            why.append("the controls or parameters are not finite")
        elif not finite[i]:
            why.append("the cost or its gradient is not finite")
        elif not stat_ok[i]:
            why.append(
                f"stationarity {stat[i]:.3g} > stat_tol x (1 + min(|C_i|, scale_cap)) "
                f"= {self.options.stat_tol * scale[i]:.3g}"
            )
        return why

    def _best_response(self, i: int, u, p) -> tuple[str, float]:
        """Agent ``i``'s best response to the others' ``u_{-i}`` from its own ``u_i``:
        IPOPT's return status and the cost ``C_i`` at the response."""
        g = self.game
        a, b = int(g.uoff[i]), int(g.uoff[i + 1])
        solver = self.best_response_nlp(i)
        others = np.concatenate([u[:a], u[b:]])
        sol = solver(x0=u[a:b], p=np.concatenate([p, others]))
        st = str(solver.stats().get("return_status", "unknown"))
        ui = np.asarray(sol["x"], dtype=float).reshape(-1)
        with np.errstate(all="ignore"):
            cand = float(self._costs(np.concatenate([u[:a], ui, u[b:]]), p)[i])
        return st, cand


def nash_certificate(
    game: PotentialGame,
    p: np.ndarray,
    u: np.ndarray,
    options: NashOptions | dict | None = None,
) -> NashCertificate:
    """Local open-loop Nash certificate of the joint strategy ``u`` (``(n_u,)``) for ``p``
    (``(n_p,)``).

    Arguments in the solvers' order ``(game, p, u)`` (or as keywords ``p=``, ``u=``). See the module docstring for what is measured, the
    tolerances and what "local" means. ``options``: :class:`NashOptions` or a dict of its
    fields (unknown keys raise :class:`~epo_casadi.errors.SpecError`).
    """
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    t0 = time.perf_counter()
    opts = check_options(NashOptions, options, "nash")
    cert = game.cached(("nash", opts), lambda: NashChecker(game, opts)).certify(p=p, u=u)
    return replace(cert, time_s=time.perf_counter() - t0)  # with the first use's build
