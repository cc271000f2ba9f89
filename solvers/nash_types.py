"""The options and the result of the open-loop Nash certificate of :mod:`solvers.nash`:
:class:`NashOptions` (tolerances, best-response methods and their sizes, global starts),
:class:`NashCertificate` (the verdict, the gaps and residuals per agent, the table) and
``_Attempt`` (one best-response solve), with the IPOPT statuses that count as converged
(:data:`CONVERGED`) and the names of the methods (:data:`METHOD_NAMES`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import ClassVar

import numpy as np

from epo_casadi.errors import check_bool, check_number

from .result import Verdict

#: IPOPT statuses after which a best response counts as evidence of the gap
CONVERGED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
#: what each best-response method is called in the table and in ``decided_by``
METHOD_NAMES = {
    "exact": "ipopt (exact Hessian)",
    "l-bfgs": "ipopt (L-BFGS)",
    "lm": "lm (agent residuals)",
    "curvature": "negative curvature of the exact own Hessian",
}


@dataclass(frozen=True)
class NashOptions:
    """Tolerances of the certificate and options of the best-response solves."""

    stat_tol: float = 1e-5  #: stationarity tolerance: s_i <= stat_tol * S_i (see the module doc)
    gap_tol: float = 1e-6  #: best-response gap tolerance: gap_i <= gap_tol * S_i
    scale_cap: float = 1e6  #: S_i = 1 + min(|C_i|, scale_cap): the scale of both tolerances
    best_response: bool = True  #: solve the best responses (False: stationarity only, gaps 0)
    exact_hessian_max: int = 200  #: exact Hessian up to this many controls per agent, then L-BFGS
    best_response_max: int = 600  #: agents with more controls get the stationarity test only
    max_iter: int = 300  #: iterations per best-response solve (IPOPT, and the fallback's LM)
    tol: float = 1e-10  #: IPOPT tolerance of the best responses; the fallback's: tol * S_i
    fallback: bool = True  #: LM on the agent's residuals when IPOPT stops early without a gap
    global_starts: int = 0  #: more starts per agent: zero controls, then seeded draws (0: local)
    global_scale: float = 1.0  #: standard deviation of the drawn starts (control units)
    global_seed: int = 0  #: seed of the drawn starts

    def __post_init__(self):
        for name in ("stat_tol", "gap_tol", "tol", "scale_cap", "global_scale"):
            check_number(f"nash.{name}", getattr(self, name), lo=0, lo_open=True)
        for name in (
            "max_iter",
            "exact_hessian_max",
            "best_response_max",
            "global_starts",
            "global_seed",
        ):
            check_number(f"nash.{name}", getattr(self, name), lo=0, integer=True)
        check_bool("nash.best_response", self.best_response)
        check_bool("nash.fallback", self.fallback)


@dataclass(frozen=True, eq=False)
class NashCertificate:
    """Per-agent evidence for (or against) an open-loop Nash equilibrium (local unless
    ``options.global_starts > 0``).

    Arrays have one entry per agent, in the order of :attr:`agents`.
    """

    kind: ClassVar[str] = "open-loop"

    agents: tuple[str, ...]  #: agent names
    costs: np.ndarray  #: C_i(u, p), (N,)
    stationarity: np.ndarray  #: |dC_i/du_i|_inf, (N,)
    best_response_costs: np.ndarray  #: lowest C_i any best response found (C_i if none lower), (N,)
    best_response_gap: np.ndarray  #: C_i(u) - best_response_costs >= 0, (N,)
    relative_gap: np.ndarray  #: best_response_gap / S_i, (N,)
    best_response_status: tuple[
        str, ...
    ]  #: IPOPT's return status from the candidate, per agent ("skipped" if not solved)
    best_response_method: tuple[
        str, ...
    ]  #: "exact" / "l-bfgs" Hessian, or "off" / "too large" (stationarity only), per agent
    stat_ok: np.ndarray  #: stationarity finite and within tolerance, (N,) bool
    gap_ok: np.ndarray  #: no gap found, and a best response that finished (or none run), (N,) bool
    reasons: tuple[str, ...]  #: why each agent fails or is unknown ("" where it passes)
    ok: bool  #: every agent passes (verdict "passes")
    time_s: float  #: wall time of the certificate (on first use, with building its functions)
    options: NashOptions
    verdicts: tuple[Verdict, ...] = ()  #: per agent: passes / fails / unknown
    verdict: Verdict = Verdict.PASSES  #: fails if one fails, else unknown if one is, else passes
    decided_by: tuple[str, ...] = ()  #: per agent, the test or method that decided its verdict
    global_best_costs: np.ndarray | None = None  #: lowest C_i from the global starts (NaN: none)

    def to_dict(self) -> dict:
        """JSON-ready dictionary (non-finite numbers as None)."""
        d = {"kind": self.kind}
        for f in fields(self):
            k, v = f.name, getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v = [x if not isinstance(x, float) or np.isfinite(x) else None for x in v.tolist()]
            elif isinstance(v, tuple):
                v = [str(x) for x in v] if k == "verdicts" else list(v)
            elif isinstance(v, NashOptions):
                v = asdict(v)
            elif isinstance(v, Verdict):
                v = v.value
            elif isinstance(v, (np.bool_, np.floating)):
                v = v.item()
            d[k] = v
        return d

    def scope(self) -> str:
        """What the certificate searched: ``local`` or ``local + K global starts``."""
        k = self.options.global_starts
        return "local" if not k else f"local + {k} global start{'s' if k > 1 else ''} per agent"

    def summary(self) -> str:
        """A text table, one row per agent, the verdict, what decided it and the reasons."""
        o = self.options
        if o.global_starts:
            title = (
                f"open-loop Nash certificate, {self.scope()} (zero controls and seeded draws "
                "against the others' fixed controls): a sampled search beyond the local one"
            )
        else:
            title = (
                "local open-loop Nash certificate: certifies a LOCAL equilibrium (best "
                "responses from the candidate; global_starts > 0 searches other basins)"
            )
        head = (
            f"{'agent':>10s} {'C_i':>12s} {'|dC_i/du_i|':>12s} {'gap':>12s} {'rel. gap':>10s}"
            f" {'best resp.':>10s}  {'verdict':<8s} decided by"
        )
        lines = [title, head]
        for i, a in enumerate(self.agents):
            v = self.verdicts[i] if self.verdicts else ("passes" if self.ok else "fails")
            word = {"passes": "passes", "fails": "FAILS", "unknown": "unknown"}[str(v)]
            by = self.decided_by[i] if self.decided_by else ""
            lines.append(
                f"{a:>10s} {self.costs[i]:12.6g} {self.stationarity[i]:12.3g} "
                f"{self.best_response_gap[i]:12.3g} {self.relative_gap[i]:10.3g}"
                f" {self.best_response_method[i]:>10s}  {word:<8s} {by}"
            )
        verdict = {"passes": "passes", "fails": "FAILS", "unknown": "UNKNOWN"}[str(self.verdict)]
        lines.append(
            f"{verdict} ({self.scope()}; stat_tol {o.stat_tol:g}, gap_tol {o.gap_tol:g}, "
            f"relative to 1 + min(|C_i|, {o.scale_cap:g})) in {self.time_s:.3g} s"
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


@dataclass
class _Attempt:
    """One best-response solve: method, its stop, whether it finished, the cost reached."""

    method: str  #: "exact", "l-bfgs" or "lm"
    status: str  #: IPOPT's return status, or LM's stop ("gtol", "max_iter", ...)
    converged: bool
    cost: float  #: C_i at the point reached (NaN if not finite)
    controls: np.ndarray  #: u_i at the point reached

    @property
    def label(self) -> str:
        return f"{METHOD_NAMES[self.method]}: {self.status}"
