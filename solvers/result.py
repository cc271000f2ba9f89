"""One result type for every solver (LM, IPOPT, iLQ game).

Arrays carry the batch dimensions of the solve's input: a single problem (``u0`` of
shape ``(n_u,)``) gives ``controls`` of shape ``(n_u,)`` and a scalar ``status``; a batch
``(B, n_u)`` gives ``(B, n_u)`` and an array of ``B`` statuses. ``result[b]`` picks one
problem of a batch. Shapes follow the contract in :mod:`epo_casadi.game`.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

__all__ = [
    "Status",
    "StopReason",
    "stop_reason",
    "Equilibrium",
    "potential_equilibrium",
    "Verdict",
    "combine_verdicts",
    "SolveResult",
    "fmt_number",
    "demote_nonfinite",
    "mark_nonfinite_stops",
    "padded_histories",
    "grad_inf_norm",
    "per_problem",
]


class Status(enum.Enum):
    """Outcome of one solve; ``message`` is a readable sentence."""

    CONVERGED = "converged"
    MAX_ITER = "max_iter"
    NONFINITE = "nonfinite"
    INFEASIBLE = "infeasible"
    FAILED = "failed"
    STALLED = "stalled"  # appended last: integer codes (learning.layer.STATUS_CODES) stay stable

    @property
    def message(self) -> str:
        return _MESSAGES[self]

    @property
    def ok(self) -> bool:
        """A usable iterate: ``CONVERGED`` or ``MAX_ITER`` (a ``STALLED`` point is not one)."""
        return self in (Status.CONVERGED, Status.MAX_ITER)


class _Word(str, enum.Enum):
    """A ``str`` enum whose members equal, hash, print and format as their value."""

    __hash__ = str.__hash__
    __str__ = str.__str__
    __format__ = str.__format__


class StopReason(_Word):
    """Why a solver stopped (``info["stop"]``), beside its :class:`Status`.

    A ``str``: a member equals, hashes, prints and is written to JSON as its value
    (``StopReason.FTOL == "ftol"``), so result files hold the plain word. SQP's QP failures
    are not members: they are the string ``"qp <OSQP status>"``. :func:`stop_reason` turns
    a word read back from a file into its member.
    """

    #: LM: the gradient's inf-norm reached ``gtol``.
    GTOL = "gtol"
    #: LM: an accepted step lowered the energy by at most ``ftol (1 + E)``.
    FTOL = "ftol"
    #: LM: the damping passed ``max_damping`` (no step lowers the energy).
    MAX_DAMPING = "max_damping"
    #: LM: exact-Hessian Newton steps after an ``ftol`` / ``max_damping`` stop reached ``gtol``.
    POLISH = "polish"
    #: the iteration limit was reached.
    MAX_ITER = "max_iter"
    #: NaN or inf in the energy, the residual or the step.
    NONFINITE = "nonfinite"
    #: iLQ: ``max |a| <= tol`` at the requested regularization.
    TOL = "tol"
    #: iLQ: the linearization at the requested regularization is singular.
    SINGULAR = "singular"
    #: iLQ: the tolerance holds only with raised regularization.
    REGULARIZED_ONLY = "regularized_only"
    #: iLQ: converged with the kinks blended, and no step passes at the exact kinks.
    KINK = "kink"
    #: iLQ, SQP: no step passes the line search (up to iLQ's regularization cap).
    LINE_SEARCH = "line_search"
    #: iLQ: on a kink, a policy certified as a feedback Nash equilibrium.
    KINK_EQUILIBRIUM = "kink_equilibrium"
    #: SQP: the KKT conditions hold within ``tol`` and ``feas_tol``.
    KKT = "kkt"
    #: SQP: the regularization passed its cap without a step that lowers the KKT error.
    NO_DESCENT = "no_descent"
    #: SQP: the QP's step is negligible (``step_tol``).
    STEP_TOL = "step_tol"


class Equilibrium(_Word):
    """The kind of point a solve looks for (``SolveResult.equilibrium``), beside its
    :class:`Status`.

    The status says whether the solver's own first-order tolerance holds; this says what
    a point that meets it is. A ``str`` (the word is what JSON files and tables hold).
    """

    #: a local open-loop Nash equilibrium; for LM, IPOPT and SQP: a minimizer of the
    #: potential of a game whose agents' dynamics depend on their own controls only
    #: (paper Theorem C.1, :mod:`epo_casadi.game`)
    OPEN_LOOP = "open-loop Nash"
    #: LM, IPOPT, SQP on a game with coupled dynamics (``GameSpec(couplings=...)``): an
    #: agent's controls move another agent's state, ``C_i - E`` depends on ``u_i``, and a
    #: minimizer of the potential is in general no Nash equilibrium
    POTENTIAL_MINIMUM = "potential minimum (coupled dynamics: not a Nash equilibrium)"
    #: iLQ: a local feedback Nash equilibrium of the players' own costs (coupled or not)
    FEEDBACK = "feedback Nash"

    @property
    def message(self) -> str:
        return _EQUILIBRIUM_MESSAGES[self]


_EQUILIBRIUM_MESSAGES = {
    Equilibrium.OPEN_LOOP: "a local open-loop Nash equilibrium",
    Equilibrium.POTENTIAL_MINIMUM: (
        "a minimum of the potential, not a Nash equilibrium: with coupled dynamics an "
        "agent's controls move another agent's state, so C_i - E depends on u_i (the Nash "
        "certificate tests the open-loop conditions)"
    ),
    Equilibrium.FEEDBACK: "a local feedback Nash equilibrium of the players' own costs",
}


def potential_equilibrium(coupled: bool) -> Equilibrium:
    """What a minimizer of the potential is: :attr:`Equilibrium.OPEN_LOOP`, or
    :attr:`Equilibrium.POTENTIAL_MINIMUM` for a game with coupled dynamics
    (``PotentialGame.coupled``)."""
    return Equilibrium.POTENTIAL_MINIMUM if coupled else Equilibrium.OPEN_LOOP


class Verdict(_Word):
    """An equilibrium check's answer, per agent and overall (a ``str``, written as its word).

    ``fails`` only on evidence (an improvement that a best response or a deviation found,
    violated stationarity, a non-finite cost); ``unknown`` when the evidence is missing (a
    best response that stopped early without showing a gap); ``passes`` otherwise.
    """

    PASSES = "passes"
    FAILS = "fails"
    UNKNOWN = "unknown"


def combine_verdicts(verdicts) -> Verdict:
    """The overall verdict: ``fails`` if one agent fails, else ``unknown`` if one is
    unknown, else ``passes`` (also for no agents)."""
    vs = [Verdict(v) for v in verdicts]
    if Verdict.FAILS in vs:
        return Verdict.FAILS
    if Verdict.UNKNOWN in vs:
        return Verdict.UNKNOWN
    return Verdict.PASSES


def stop_reason(value: Any) -> Any:
    """``value`` (a stop word, e.g. read from a result file) as its :class:`StopReason`;
    anything else (``None``, an SQP ``"qp ..."`` string, a word this version does not
    know) is returned unchanged."""
    if isinstance(value, str) and not isinstance(value, StopReason):
        try:
            return StopReason(value)
        except ValueError:
            return value
    return value


def fmt_number(value: Any, spec: str = ".6g") -> str:
    """``value`` formatted with ``spec``; ``None`` (a non-finite value in a result file) and
    anything that is not a number are written as words, NaN and inf as ``nan`` / ``inf``."""
    if value is None:
        return "none (non-finite)"
    try:
        return format(float(value), spec)
    except (TypeError, ValueError):
        return str(value)


_MESSAGES = {
    Status.CONVERGED: "converged: a first-order (stationarity) tolerance was met",
    Status.MAX_ITER: "stopped after the configured number of iterations without meeting a tolerance",
    Status.NONFINITE: "stopped: NaN or inf in the energy or the step (problem masked, controls kept finite)",
    Status.INFEASIBLE: "stopped: the constraints could not be satisfied",
    Status.FAILED: "failed: the solver reported an error",
    Status.STALLED: (
        "stalled: the solver could make no further progress (damping or regularization at "
        "its cap, or a negligible decrease of its merit: the energy for LM, the feedback "
        "residual for iLQ) but the first-order test fails; not a stationary point"
    ),
}


def demote_nonfinite(status: np.ndarray, *arrays: np.ndarray) -> np.ndarray:
    """``status`` (``(B,)`` objects) with ``NONFINITE`` wherever a usable-looking status
    (converged, max_iter, stalled) goes with NaN or inf in one of ``arrays`` (``(B, ...)``):
    a result whose energy, costs or states are not finite is never reported as usable."""
    bad = np.zeros(len(status), dtype=bool)
    for a in arrays:
        a = np.asarray(a, dtype=float)
        bad |= ~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
    soft = np.array([s in (Status.CONVERGED, Status.MAX_ITER, Status.STALLED) for s in status])
    out = np.array(status, dtype=object)
    out[bad & soft] = Status.NONFINITE
    return out


def mark_nonfinite_stops(status: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """``stop`` (``(B,)`` objects, changed in place and returned) with
    :attr:`StopReason.NONFINITE` wherever ``status`` is ``NONFINITE`` (after
    :func:`demote_nonfinite`)."""
    stop[(status == Status.NONFINITE) & (stop != StopReason.NONFINITE)] = StopReason.NONFINITE
    return stop


def padded_histories(histories, last: np.ndarray) -> np.ndarray:
    """``(S, B)``: the per-problem histories (``B`` sequences) as columns, each padded to
    the longest with its final value; an empty one is ``[last[b]]``; ``S >= 1``."""
    cols = [list(h) or [last[b]] for b, h in enumerate(histories)]
    S = max((len(h) for h in cols), default=1)
    hist = np.empty((S, len(cols)))
    for b, h in enumerate(cols):
        hist[:, b] = h + [h[-1]] * (S - len(h))
    return hist


def grad_inf_norm(G: np.ndarray) -> np.ndarray:
    """``(B,)`` infinity norms of the rows of ``G`` ``(B, n_u)`` (zeros when ``n_u = 0``)."""
    return np.max(np.abs(G), axis=1) if G.shape[1] else np.zeros(G.shape[0])


def per_problem(runs: list[dict], key: str) -> np.ndarray:
    """``(B,)`` object array of the float arrays ``run[key]`` (``result[b]`` picks one)."""
    out = np.empty(len(runs), dtype=object)
    for b, r in enumerate(runs):
        out[b] = np.asarray(r[key], dtype=float)
    return out


@dataclass(frozen=True)
class SolveResult:
    """Solution of one problem or a batch of problems.

    Attributes
    ----------
    solver: name of the solver (``"lm"``, ``"ipopt"``, ``"ilq"``).
    controls: optimized joint strategy ``u``, ``(..., n_u)``.
    states: rolled-out joint states ``x``, ``(..., n_x)``.
    energy: potential ``E(u, p)`` at the solution, ``(...)``.
    agent_costs: each agent's own game cost ``C_i``, ``(..., N)``.
    status: :class:`Status` (one problem) or an object array of them.
    iterations: iterations taken, ``(...)``.
    energy_history: energy before each iteration and at the end, ``(S+1, ...)`` where ``S``
        is the largest number of iterations taken in the batch (not the iteration limit);
        entries after a problem stopped repeat its final value.
    grad_norm: infinity norm of the gradient of ``E`` at the solution, ``(...)``.
    wall_time: seconds for the whole call.
    info: solver-specific extras (damping history, IPOPT return string, gains, ...).
    equilibrium: the kind of point the solver looks for (:class:`Equilibrium`, one for the
        whole batch; the status says whether it got there): LM, IPOPT and SQP set
        ``open-loop Nash``, or ``potential minimum (coupled dynamics: not a Nash
        equilibrium)`` for a game with coupled dynamics; iLQ ``feedback Nash``. ``None``:
        the solver does not say.
    """

    solver: str
    controls: np.ndarray
    states: np.ndarray
    energy: np.ndarray
    agent_costs: np.ndarray
    status: Any
    iterations: np.ndarray
    energy_history: np.ndarray
    grad_norm: np.ndarray
    wall_time: float
    info: dict = field(default_factory=dict)
    equilibrium: Equilibrium | None = None

    @property
    def potential_only(self) -> bool:
        """The point is a minimum of the potential only, not a Nash equilibrium (coupled
        dynamics: :attr:`Equilibrium.POTENTIAL_MINIMUM`)."""
        return self.equilibrium is Equilibrium.POTENTIAL_MINIMUM

    @property
    def batched(self) -> bool:
        return np.ndim(self.energy) > 0

    @property
    def ok(self):
        """Whether each problem ended with a usable solution (converged or max_iter)."""
        if not self.batched:
            return self.status.ok
        return np.vectorize(lambda s: s.ok, otypes=[bool])(self.status)

    @property
    def message(self) -> str:
        if not self.batched:
            return self.status.message
        counts: dict[Status, int] = {}
        for s in np.ravel(self.status):
            counts[s] = counts.get(s, 0) + 1
        return ", ".join(f"{n} {s.value}" for s, n in counts.items())

    def __getitem__(self, index) -> SolveResult:
        if not self.batched:
            raise IndexError("this result holds a single problem")
        kw = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "energy_history":
                v = v[
                    (slice(None), index) if not isinstance(index, tuple) else (slice(None), *index)
                ]
            elif f.name in ("solver", "wall_time", "equilibrium"):
                pass
            elif f.name == "info":
                v = {
                    k: (
                        a[index]
                        if isinstance(a, np.ndarray) and a.shape[:1] == np.shape(self.energy)[:1]
                        else a
                    )
                    for k, a in v.items()
                }
            else:
                v = v[index]
            kw[f.name] = v
        return SolveResult(**kw)

    def summary(self) -> str:
        """One line; total over every status (NaN, inf and missing values are printed as
        such); the kind of point (:attr:`equilibrium`) when the solver says."""
        eq = f"; equilibrium: {self.equilibrium.value}" if self.equilibrium is not None else ""
        if self.batched:
            e = np.asarray(self.energy, dtype=float).reshape(-1)
            fin = np.isfinite(e)
            mean = f"{e[fin].mean():.6g}" if fin.any() else "n/a"
            nonfin = f" ({e.size - int(fin.sum())} non-finite)" if not fin.all() else ""
            return (
                f"{self.solver}: {e.size} problems, {self.message}; energy mean {mean}{nonfin}, "
                f"iterations mean {np.mean(self.iterations):.1f}, {self.wall_time * 1e3:.1f} ms{eq}"
            )
        return (
            f"{self.solver}: {self.status.value} ({self.status.message}); "
            f"energy {fmt_number(self.energy, '.6g')}, {int(self.iterations)} iterations, "
            f"|grad|_inf {fmt_number(self.grad_norm, '.3g')}, {self.wall_time * 1e3:.1f} ms{eq}"
        )

    def to_dict(self) -> dict:
        """JSON-ready dictionary (single problem or batch); NaN and inf become ``None``."""

        def conv(v):
            if isinstance(v, enum.Enum):
                return v.value
            if dataclasses.is_dataclass(v) and not isinstance(v, type):
                return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
            if isinstance(v, np.ndarray):
                if v.dtype == object or v.dtype.kind in "fc":
                    return [conv(x) for x in v.tolist()] if v.ndim else conv(v.item())
                return v.tolist()
            if isinstance(v, (np.floating, np.integer, np.bool_)):
                return conv(v.item())
            if isinstance(v, float) and not math.isfinite(v):
                return None  # strict JSON has no NaN / inf
            if isinstance(v, dict):
                return {k: conv(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [conv(x) for x in v]
            return v

        d = {f.name: conv(getattr(self, f.name)) for f in fields(self)}
        d["message"] = self.message
        return d
