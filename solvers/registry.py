"""Solvers by name: the one table that ``epo solve``, game files, ``epo compare`` and the
multi-modal solver read.

Every solver is one :class:`SolverEntry` in :data:`SOLVERS`, registered once: its name,
its entry function, its frozen options class, the kind of equilibrium it finds (which
decides the check that certifies a result), a one-line description and, for
``epo compare``'s ``setup_s``, how to build what it needs before the timed solve. The
built-ins:

* ``lm``: :func:`solvers.lm.solve_lm`, ``LMOptions``, open-loop;
* ``ipopt``: :func:`solvers.ipopt.solve_ipopt`, ``IpoptOptions``, open-loop;
* ``ilq``: :func:`solvers.ilq.solve_ilq`, ``ILQOptions``, feedback;
* ``sqp``: :func:`solvers.sqp.solve_sqp`, ``SQPOptions``, open-loop;
* ``olne``: :func:`solvers.olne.solve_olne`, ``OLNEOptions``, open-loop (the game's own
  first-order conditions, coupled games included).

The contract of an entry function (every built-in keeps it)::

    solve(game, p, u0=None, options=None) -> SolveResult

``p``: ``(n_p,)`` or ``(B, n_p)``; ``u0``: ``(n_u,)`` or ``(B, n_u)`` (zeros if None);
``options``: the solver's options object, a mapping of its fields or None (defaults).

A user's own solver is one registration, after which it is found by name everywhere
(:func:`solve_game`, ``epo compare``, ``epo solve --solver``, the ``solver:`` section of
a game file, :func:`solvers.multimodal.solve_multimodal`)::

    from solvers.registry import register_solver
    register_solver("mine", my_package.solve_mine, MyOptions, description="...")

A name already in the table is refused unless ``replace=True`` (registering the same
function and options class again is a no-op), as for features and dynamics
(:class:`epo_casadi.registry.Registry`). That class is a name -> *model class* table whose
entries are built from ``{"type": ..., options}`` mappings and checked against a base
class; a solver is a record of several objects (function, options, check), so it has a
table of its own that keeps the same rules and messages and reuses the same pieces
(:data:`~epo_casadi.registry.NAME_RE`, :func:`~epo_casadi.registry.load_class` for
``"module:function"`` strings).

Every entry function is stored wrapped in the continuation fallback
(:class:`solvers.continuation.ContinuedSolve`; :attr:`SolverEntry.function` is the function
itself): a solve of one problem that ends in any status but ``converged`` is solved again
with the game's pair weights scaled up from 0.01 to the full weight, each stage
warm-started at the last, its solves listed in ``info["attempts"]``. An options class with
a ``continuation`` field switches it (every built-in has one, default ``True``); one
without the field never gets it.

Options from a mapping (a game file's ``solver.<name>`` section, ``--solver
name:key=value``) are built by one function, :meth:`SolverEntry.make_options`: unknown
keys and bad values raise :class:`~epo_casadi.errors.SpecError` naming the field.
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, fields, is_dataclass
from typing import Any

import numpy as np

from epo_casadi.errors import SpecError, short_repr
from epo_casadi.game import PotentialGame
from epo_casadi.registry import NAME_RE, load_class

from .continuation import ContinuedSolve
from .ilq import ILQOptions, solve_ilq
from .ipopt import IpoptOptions, solve_ipopt
from .lm import LMOptions, prepare_lm, solve_lm
from .olne import OLNEOptions, prepare_olne, solve_olne
from .result import SolveResult
from .sqp import SQPOptions, solve_sqp

__all__ = [
    "EQUILIBRIA",
    "SOLVERS",
    "EquilibriumCheck",
    "SolverEntry",
    "SolverTable",
    "check_bounds",
    "register_solver",
    "unregister_solver",
    "solver_entry",
    "solve_game",
]

#: the kinds of equilibrium a solver may find, each with its check (:meth:`SolverEntry.check`)
EQUILIBRIA = ("open-loop", "feedback")


@dataclass(frozen=True)
class EquilibriumCheck:
    """The check of one result: which test, whether it passes, the largest player gain."""

    kind: str  #: "open-loop" (Nash certificate) or "feedback" (sampled feedback Nash check)
    ok: bool  #: the test passes
    gain: float  #: largest best-response gap / own-cost decrease a deviation found
    seconds: float  #: time of the check
    detail: Any = None  #: the NashCertificate or FeedbackNashCheck behind it


def _open_loop(game: PotentialGame, p: np.ndarray, res: SolveResult) -> EquilibriumCheck:
    from .nash import nash_certificate

    t0 = time.perf_counter()
    c = nash_certificate(game, p=p, u=res.controls)
    gap = float(np.max(c.best_response_gap)) if len(c.best_response_gap) else 0.0
    return EquilibriumCheck("open-loop", bool(c.ok), gap, time.perf_counter() - t0, c)


def _feedback(game: PotentialGame, p: np.ndarray, res: SolveResult) -> EquilibriumCheck:
    from .feedback_nash import check_ilq_result

    t0 = time.perf_counter()
    c = check_ilq_result(game, p, res)
    return EquilibriumCheck("feedback", c.ok, float(np.max(c.gain)), time.perf_counter() - t0, c)


_CHECKS = {"open-loop": _open_loop, "feedback": _feedback}


@dataclass(frozen=True)
class SolverEntry:
    """One registered solver (see the module docstring for the entry function's contract)."""

    name: str  #: the name in every table (letters, digits, '_')
    #: entry function solve(game, p, u0, options); :func:`register_solver` stores it
    #: wrapped in the continuation fallback (:class:`solvers.continuation.ContinuedSolve`)
    solve: Callable[..., SolveResult]
    options: type  #: its frozen options dataclass
    equilibrium: str = "open-loop"  #: "open-loop" or "feedback": which check certifies it
    description: str = ""  #: one line, for listings
    #: prepare(game, p, u0, options): build and evaluate once what a solve reuses
    #: (``epo compare``'s ``setup_s``); None: nothing is built ahead of the solve
    prepare: Callable[..., None] | None = None
    #: the multi-modal solver (and ``epo solve --modes``) may use it
    multimodal: bool = True
    #: the options field of the iteration limit (``epo solve --steps``); None: it has none
    iteration_limit: str | None = None
    #: check_game(options, spec, where): options that name parts of a game fit it
    check_game: Callable[..., None] | None = None

    @property
    def function(self) -> Callable[..., SolveResult]:
        """The registered entry function itself, without the continuation fallback."""
        return getattr(self.solve, "function", self.solve)

    def option_names(self) -> list[str]:
        """The fields of its options class."""
        return [f.name for f in fields(self.options) if f.init]

    def make_options(self, values: Any = None, where: str | None = None) -> Any:
        """The options object from ``None`` (defaults), an options object or a mapping.

        ``where`` (default: the solver's name) prefixes the field of every error: an
        unknown key ``where.key: unknown option; allowed: [...]``, a value the options
        class refuses ``where.<its field>``.
        """
        cls = self.options
        where = self.name if where is None else where
        if values is None:
            return cls()
        if isinstance(values, cls):
            return values
        if not isinstance(values, Mapping):
            raise SpecError(where, f"expected a mapping of options, got {short_repr(values)}")
        names = self.option_names()
        unknown = sorted((k for k in values if k not in names), key=str)
        if unknown:
            k = unknown[0]
            key = k if isinstance(k, str) and len(k) <= 60 else short_repr(k, 60)
            raise SpecError(f"{where}.{key}", f"unknown option; allowed: {sorted(names)}")
        try:
            return cls(**values)
        except SpecError as e:  # "lm.steps" -> "<where>.steps"
            head, dot, tail = e.field.partition(".")
            if head in names:  # the class named its own field without a prefix
                tail, dot = e.field, "."
            raise SpecError(f"{where}.{tail}" if dot else where, e.message) from None
        except (TypeError, ValueError) as e:
            raise SpecError(where, str(e)) from None

    def check(self, game: PotentialGame, p: np.ndarray, result: SolveResult) -> EquilibriumCheck:
        """The equilibrium test of this solver's kind on ``result`` (see :data:`EQUILIBRIA`)."""
        return _CHECKS[self.equilibrium](game, np.asarray(p, float), result)

    def takes(self, argument: str) -> bool:
        """Whether the entry function has a parameter ``argument`` (e.g. iLQ's ``costs``)."""
        try:
            return argument in inspect.signature(self.solve).parameters
        except (TypeError, ValueError):
            return False


class SolverTable(Mapping):
    """Name -> :class:`SolverEntry`, in registration order (the built-ins first)."""

    def __init__(self) -> None:
        self._table: dict[str, SolverEntry] = {}
        self._originals: dict[str, SolverEntry] = {}

    def __getitem__(self, name: str) -> SolverEntry:
        return self._table[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._table)

    def __len__(self) -> int:
        return len(self._table)

    def names(self) -> list[str]:
        """The registered names, in registration order."""
        return list(self._table)

    def entry(self, name: Any, where: str = "solver") -> SolverEntry:
        """The entry of ``name``; else one :class:`SpecError` at ``where`` listing the table."""
        if isinstance(name, str) and name in self._table:
            return self._table[name]
        raise SpecError(where, self.unknown(name))

    def unknown(self, name: Any) -> str:
        """The message for a name that is not in the table (it lists the table)."""
        return (
            f"expected one of the registered solvers {self.names()}, got {short_repr(name)} "
            f"(unknown solver: {short_repr(name)} is not one of them)"
        )

    def register(self, entry: SolverEntry, *, replace: bool = False) -> SolverEntry:
        """Add ``entry`` (see :func:`register_solver`, which builds and checks it)."""
        where = "register_solver"
        old = self._table.get(entry.name)
        if old is not None and old != entry and not replace:
            which = "built-in" if entry.name in self._originals else "registered"
            raise SpecError(
                f"{where}.name",
                f"{entry.name!r} is already the {which} solver {_qualname(old.function)}; pick "
                f"another name or pass replace=True",
            )
        self._table[entry.name] = entry
        return entry

    def unregister(self, name: str) -> None:
        """Remove a user's solver; a replaced built-in gets its original entry back."""
        if name in self._originals:
            if self._table.get(name) is self._originals[name]:
                raise SpecError("unregister_solver", f"{name!r} is a built-in solver")
            self._table[name] = self._originals[name]
            return
        if name not in self._table:
            raise SpecError("unregister_solver", f"no solver registered as {name!r}")
        del self._table[name]

    def _bind_builtins(self) -> None:
        self._originals = dict(self._table)


def _qualname(obj: Any) -> str:
    return f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', repr(obj))}"


#: every solver, by name (built-ins: lm, ipopt, ilq, sqp, olne)
SOLVERS = SolverTable()


def register_solver(
    name: str,
    entry: Callable[..., SolveResult] | str,
    options: type | str,
    *,
    equilibrium: str = "open-loop",
    description: str = "",
    prepare: Callable[..., None] | None = None,
    multimodal: bool = True,
    iteration_limit: str | None = None,
    check_game: Callable[..., None] | None = None,
    replace: bool = False,
) -> SolverEntry:
    """Register a solver under ``name``; return its :class:`SolverEntry`.

    ``entry``: the entry function (or ``"module:function"``), see the module docstring;
    ``options``: its frozen options dataclass (or ``"module:Class"``); ``equilibrium``:
    ``"open-loop"`` (certified by :func:`solvers.nash.nash_certificate`) or
    ``"feedback"`` (by :func:`solvers.feedback_nash.check_ilq_result`, which reads the
    policy an iLQ result holds). ``iteration_limit``: the options field ``epo solve
    --steps`` sets (default: ``max_iter`` or ``steps`` when the options have one). The
    other arguments are the fields of :class:`SolverEntry`. A name in the table is
    refused unless ``replace=True``.
    """
    where = "register_solver"
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise SpecError(
            f"{where}.name", f"expected letters, digits and '_', got {short_repr(name)}"
        )
    if isinstance(entry, str):
        entry = load_class(entry, f"{where}.entry")
    if isinstance(entry, ContinuedSolve):  # a registered entry's solve: wrap its function once
        entry = entry.function
    if not callable(entry):
        raise SpecError(f"{where}.entry", f"expected a function, got {short_repr(entry)}")
    if isinstance(options, str):
        options = load_class(options, f"{where}.options")
    if not (isinstance(options, type) and is_dataclass(options)):
        raise SpecError(
            f"{where}.options", f"expected a frozen dataclass of options, got {short_repr(options)}"
        )
    if not options.__dataclass_params__.frozen:
        raise SpecError(f"{where}.options", f"{options.__name__} must be a frozen dataclass")
    if equilibrium not in EQUILIBRIA:
        raise SpecError(
            f"{where}.equilibrium",
            f"expected one of {list(EQUILIBRIA)}, got {short_repr(equilibrium)}",
        )
    names = [f.name for f in fields(options)]
    if iteration_limit is None:
        iteration_limit = next((n for n in ("max_iter", "steps") if n in names), None)
    elif iteration_limit not in names:
        raise SpecError(
            f"{where}.iteration_limit",
            f"expected a field of {options.__name__} ({names}), got {short_repr(iteration_limit)}",
        )
    for key, fn in (("prepare", prepare), ("check_game", check_game)):
        if fn is not None and not callable(fn):
            raise SpecError(f"{where}.{key}", f"expected a function or None, got {short_repr(fn)}")
    return SOLVERS.register(
        SolverEntry(
            name=name,
            solve=ContinuedSolve(entry, options, iteration_limit),
            options=options,
            equilibrium=equilibrium,
            description=str(description),
            prepare=prepare,
            multimodal=bool(multimodal),
            iteration_limit=iteration_limit,
            check_game=check_game,
        ),
        replace=replace,
    )


def unregister_solver(name: str) -> None:
    """Remove a user's solver (a replaced built-in gets its original entry back)."""
    SOLVERS.unregister(name)


def solver_entry(name: str, where: str = "solver") -> SolverEntry:
    """The entry of ``name``; an unknown name is one :class:`SpecError` listing the table."""
    return SOLVERS.entry(name, where)


def solve_game(
    game: PotentialGame,
    p: np.ndarray,
    u0: np.ndarray | None = None,
    solver: str = "lm",
    options: Any = None,
) -> SolveResult:
    """Solve ``game`` at ``p`` from ``u0`` with the registered solver ``solver``;
    ``options``: its options object, a mapping of its fields or None. With the
    continuation fallback (:mod:`solvers.continuation`) unless the options switch it off."""
    entry = SOLVERS.entry(solver)
    return entry.solve(game, p, u0, entry.make_options(options))


# --------------------------------------------------------------------------------------
# the built-ins
# --------------------------------------------------------------------------------------
def _prepare_ipopt(game: PotentialGame, p, u0, o: IpoptOptions) -> None:
    from .ipopt import _solver_for

    _solver_for(game, o)


def _prepare_ilq(game: PotentialGame, p, u0, o: ILQOptions) -> None:
    from .ilq import get_solver

    s = get_solver(game, None, o.hessian)
    if o.compiled:
        s.compile()


def _prepare_sqp(game: PotentialGame, p, u0, o: SQPOptions) -> None:
    from .sqp.solver import _solver_for

    _solver_for(game, o).prepare(p, u0)


def check_bounds(opts: Any, spec: Any, where: str) -> None:
    """Per-agent bounds (IPOPT's and SQP's ``control_bounds`` / ``state_bounds``) name
    agents of the game ``spec``, with one entry per component."""
    agents = {a.name: a for a in spec.agents}
    for key, size, what in (("control_bounds", "nu", "control"), ("state_bounds", "nx", "state")):
        for name, lo, _hi in getattr(opts, key) or ():
            w = f"{where}.{key}.{name}"
            if name not in agents:
                raise SpecError(w, f"unknown agent; expected one of {list(agents)}")
            dyn = agents[name].dynamics
            n = getattr(dyn, size)
            if len(lo) != n:
                names = dyn.control_names if what == "control" else dyn.state_names
                raise SpecError(
                    w,
                    f"expected [lower, upper] lists of {n} {what} entries ({', '.join(names)}), "
                    f"got {len(lo)}",
                )


register_solver(
    "lm",
    solve_lm,
    LMOptions,
    description="Levenberg-Marquardt on the potential (local open-loop Nash)",
    prepare=prepare_lm,
)
register_solver(
    "ipopt",
    solve_ipopt,
    IpoptOptions,
    description="IPOPT on the potential, optional hard bounds (local open-loop Nash)",
    prepare=_prepare_ipopt,
    multimodal=False,
    check_game=check_bounds,
)
register_solver(
    "ilq",
    solve_ilq,
    ILQOptions,
    equilibrium="feedback",
    description="iLQ game solver (local feedback Nash)",
    prepare=_prepare_ilq,
)
register_solver(
    "sqp",
    solve_sqp,
    SQPOptions,
    description="Gauss-Newton SQP on OSQP, hard bounds and collision constraints",
    prepare=_prepare_sqp,
    multimodal=False,
    check_game=check_bounds,
)
register_solver(
    "olne",
    solve_olne,
    OLNEOptions,
    description="Newton on every player's first-order conditions (open-loop Nash, coupled games too)",
    prepare=prepare_olne,
    multimodal=False,
)
SOLVERS._bind_builtins()
