"""The fallback of every registered solver: a continuation in the collision weight.

A solve that ends in any status other than ``converged`` is solved again along a path of
easier games: the game's pair weights (the parameters of group ``"w_pair"``, every pair
feature's weight, collisions among them; :class:`epo_casadi.game.ParamLayout`) are scaled
in ``p`` by :data:`WEIGHT_SCALES` in turn (0.01 to 0.316, a factor of ``sqrt(10)`` apart)
and then by 1, each stage warm-started at the controls of the last (the first stage at the
solve's own ``u0``). No new game is built: only ``p`` changes, so every solver reuses what
it built for the game (IPOPT's NLP, iLQ's functions). For a solver whose options have ``kink_widths``
(iLQ: the widths over which the curvature of the residual's kinks is blended), a last stage
at the full weight that stopped because no step passed the line search (``info["stop"]``
``"kink"`` or ``"line_search"``) is solved once more from its own end with
:data:`KINK_WIDTHS`, a kink continuation that starts ten times wider than iLQ's default.

The registry wraps every entry function in :class:`ContinuedSolve`
(:func:`solvers.registry.register_solver`), so :func:`solvers.registry.solve_game`,
``epo solve``, ``epo compare`` and game files get it. It runs when all of these hold:

* the options object has a field ``continuation`` that is true (every built-in solver's
  options have it, default ``True``; ``continuation: false`` in a game file's
  ``solver.<name>`` section, ``--solver name:continuation=false`` or
  ``options={"continuation": False}`` switches it off for that solve; a user's solver gets
  it by giving its options the same field);
* the first attempt's status is not ``converged``;
* one problem, not a batch (``p`` of shape ``(n_p,)``; a batch is returned as solved);
* ``p`` and ``u0`` are finite (a non-finite input is refused by the solver's status, not
  repaired);
* the first attempt did not stop at an iteration limit
  (:attr:`solvers.registry.SolverEntry.iteration_limit`) set below the options class's
  default (a deliberately short solve, such as ``epo solve --steps 2``, is not a stall);
* the game has a pair weight that is not zero at ``p``, or the kink stage applies.

The result is then the last stage's when that stage converged at the full weight, and
otherwise the full-weight attempt (the first, or the continuation's last stage) with the
lower finite energy; its status is that solve's own, so ``converged`` means that a solve
at the game's own ``p`` met its first-order tolerance. ``info["attempts"]`` lists every
solve in order (see :func:`solve_with_continuation`), ``iterations`` and ``wall_time`` are
totals over them, and ``energy_history`` is the kept solve's. A first attempt that
converges is returned as it is, without ``info["attempts"]``: the result is the one the
solver alone gives.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import MISSING, fields, is_dataclass, replace
from typing import Any

import numpy as np

from .result import SolveResult, Status

__all__ = [
    "WEIGHT_SCALES",
    "KINK_WIDTHS",
    "ContinuedSolve",
    "continuation_enabled",
    "solve_with_continuation",
]

#: the scales of the pair weights solved before the full weight (a geometric path)
WEIGHT_SCALES = (0.01, 0.01 * 10**0.5, 0.1, 0.1 * 10**0.5)
#: the kink widths of the last stage's second solve (solvers with ``kink_widths``)
KINK_WIDTHS = (1e-1, 1e-2, 1e-3, 1e-4)

#: the stops after which the kink stage runs (the line search failed at or near a kink)
KINK_STOPS = ("kink", "line_search")

FIELD = "continuation"  #: the options field that switches the continuation on or off


def _default(cls: type, name: str) -> Any:
    for f in fields(cls):
        if f.name == name:
            if f.default is not MISSING:
                return f.default
            if f.default_factory is not MISSING:
                return f.default_factory()
    return None


def continuation_enabled(options_cls: type, options: Any) -> bool:
    """Whether ``options`` (an object of ``options_cls``, a mapping of its fields or
    ``None``) asks for the continuation: its ``continuation`` field, or that field's
    default; ``False`` for an options class without the field."""
    if not (is_dataclass(options_cls) and any(f.name == FIELD for f in fields(options_cls))):
        return False
    if options is None:
        value = _default(options_cls, FIELD)
    elif isinstance(options, Mapping):
        value = options.get(FIELD, _default(options_cls, FIELD))
    else:
        value = getattr(options, FIELD, False)
    return value is True


def _inner(options_cls: type, options: Any) -> Any:
    """``options`` with the ``continuation`` field at its default (or absent): the solver
    never reads it, and caches keyed on the options (IPOPT's NLP) are shared."""
    if options is None or not any(f.name == FIELD for f in fields(options_cls)):
        return options
    if isinstance(options, Mapping):
        if not isinstance(options.get(FIELD), bool):
            return options  # absent, or a bad value for the solver's own check to name
        return {k: v for k, v in options.items() if k != FIELD}
    if isinstance(options, options_cls):
        default = _default(options_cls, FIELD)
        return (
            options if getattr(options, FIELD) == default else replace(options, **{FIELD: default})
        )
    return options


def _short_budget(options_cls: type, options: Any, limit: str | None) -> bool:
    """The options set the iteration limit below the class's default."""
    if limit is None or options is None:
        return False
    default = _default(options_cls, limit)
    value = (
        options.get(limit, default)
        if isinstance(options, Mapping)
        else getattr(options, limit, default)
    )
    try:
        return value is not None and default is not None and value < default
    except TypeError:
        return False


def _timed(fn: Callable[..., SolveResult], *args, **kwargs) -> tuple[SolveResult, float, float]:
    """``fn(*args, **kwargs)``, its wall and its CPU seconds (of this process)."""
    t, c = time.perf_counter(), time.process_time()
    res = fn(*args, **kwargs)
    return res, time.perf_counter() - t, time.process_time() - c


def _attempt(stage: str, scale: float, res: SolveResult, wall: float, cpu: float, **extra) -> dict:
    return {
        "stage": stage,
        "weight_scale": float(scale),
        **extra,
        "status": res.status.value,
        "stop": None if res.info.get("stop") is None else str(res.info["stop"]),
        "iterations": int(res.iterations),
        "energy": float(res.energy),
        "seconds": float(wall),
        "cpu_seconds": float(cpu),
    }


def _with_kink_widths(options_cls: type, options: Any, widths: tuple) -> Any:
    if options is None:
        return options_cls(kink_widths=widths)
    if isinstance(options, Mapping):
        return {**options, "kink_widths": widths}
    return replace(options, kink_widths=widths)


def _has_kinks(options_cls: type) -> bool:
    return is_dataclass(options_cls) and any(f.name == "kink_widths" for f in fields(options_cls))


def solve_with_continuation(
    solve: Callable[..., SolveResult],
    game,
    p: np.ndarray,
    u0: np.ndarray | None = None,
    options: Any = None,
    *,
    options_cls: type | None = None,
    first: SolveResult | None = None,
    first_times: tuple[float, float] | None = None,
    scales: tuple = WEIGHT_SCALES,
    kink_widths: tuple | None = KINK_WIDTHS,
    **extra,
) -> SolveResult:
    """The continuation of the module docstring for one problem, whatever its first status.

    ``solve``: an entry function ``solve(game, p, u0, options, **extra)``; ``options``:
    passed to every solve as given; ``options_cls``: its class (for the kink stage; default
    ``type(options)``). ``first``: the first attempt's result if it was solved already, with
    its wall and CPU seconds ``first_times`` (default: its ``wall_time``, CPU unknown: NaN);
    else it is solved here. ``scales``: the pair-weight scales before the full weight
    (increasing, each in ``(0, 1)``); ``kink_widths``: the widths of the kink stage
    (``None``: no kink stage).

    ``info["attempts"]`` of the result: one mapping per solve, in order: ``stage``
    (``"first"``, ``"weight"`` or ``"kink"``), ``weight_scale`` (the factor on every pair
    weight), ``kink_widths`` (kink stage only), ``status`` and ``stop`` (the solve's own),
    ``iterations``, ``energy`` (the potential at that stage's weights), ``seconds`` (wall)
    and ``cpu_seconds`` (of this process); the kept one has ``kept: True``.
    """
    t_start = time.perf_counter()
    p = np.asarray(p, dtype=float)
    if first is None:
        first, wall, cpu = _timed(solve, game, p, u0, options, **extra)
        before = 0.0  # inside this call's own time
    else:
        wall, cpu = first_times if first_times is not None else (first.wall_time, math.nan)
        before = wall
    attempts = [_attempt("first", 1.0, first, wall, cpu)]
    results = [first]
    idx = np.asarray(game.params.group("w_pair"), dtype=int)
    last = first
    if idx.size and np.any(p[idx] != 0):
        u = u0
        for scale in (*scales, 1.0):
            q = p.copy()
            q[idx] = p[idx] * scale
            last, wall, cpu = _timed(solve, game, q, u, options, **extra)
            attempts.append(_attempt("weight", scale, last, wall, cpu))
            results.append(last)
            u = last.controls
    cls = options_cls if options_cls is not None else type(options)
    if (
        last.status is not Status.CONVERGED
        and kink_widths
        and _has_kinks(cls)
        and str(last.info.get("stop")) in KINK_STOPS
    ):
        start = last.controls if last is not first else u0
        widths = tuple(kink_widths)
        last, wall, cpu = _timed(
            solve, game, p, start, _with_kink_widths(cls, options, widths), **extra
        )
        attempts.append(_attempt("kink", 1.0, last, wall, cpu, kink_widths=list(widths)))
        results.append(last)
    # the kept solve: the last one if it converged at the full weight, else the full-weight
    # attempt with the lowest finite energy (the last one on a tie)
    full = [i for i, a in enumerate(attempts) if a["weight_scale"] == 1.0]
    if results[-1].status is Status.CONVERGED:
        keep = len(results) - 1
    else:
        finite = [i for i in full if np.isfinite(attempts[i]["energy"])]
        keep = min(finite[::-1], key=lambda i: attempts[i]["energy"]) if finite else full[-1]
    attempts[keep]["kept"] = True
    kept = results[keep]
    return replace(
        kept,
        iterations=np.asarray(sum(int(r.iterations) for r in results)),
        wall_time=before + time.perf_counter() - t_start,
        info={**kept.info, "attempts": attempts},
    )


class ContinuedSolve:
    """An entry function with the continuation as its fallback (module docstring).

    Called as the function it wraps (``solve(game, p, u0=None, options=None, **extra)``);
    ``function`` is that function, ``options`` its options class and ``iteration_limit``
    the options field of its iteration limit. Two wrappers of the same function, class and
    limit are equal. ``inspect.signature`` gives the wrapped function's.
    """

    def __init__(self, function: Callable[..., SolveResult], options: type, iteration_limit=None):
        self.function = function
        self.options = options
        self.iteration_limit = iteration_limit
        functools.update_wrapper(self, function)

    def __call__(self, game, p, u0=None, options=None, **extra) -> SolveResult:
        on = continuation_enabled(self.options, options)
        inner = _inner(self.options, options)
        res, wall, cpu = _timed(self.function, game, p, u0, inner, **extra)
        if not on or res.status is Status.CONVERGED or res.batched:
            return res
        if res.status is Status.MAX_ITER and _short_budget(
            self.options, options, self.iteration_limit
        ):
            return res
        pa = np.asarray(p, dtype=float)
        if pa.ndim != 1 or not np.all(np.isfinite(pa)):
            return res
        if u0 is not None:
            ua = np.asarray(u0, dtype=float)
            if ua.ndim != 1 or not np.all(np.isfinite(ua)):
                return res
        idx = game.params.group("w_pair")
        kink = _has_kinks(self.options) and str(res.info.get("stop")) in KINK_STOPS
        if not (len(idx) and np.any(pa[idx] != 0)) and not kink:
            return res  # nothing to continue in
        return solve_with_continuation(
            self.function,
            game,
            pa,
            u0,
            inner,
            options_cls=self.options,
            first=res,
            first_times=(wall, cpu),
            **extra,
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ContinuedSolve):
            return NotImplemented
        return (self.function, self.options, self.iteration_limit) == (
            other.function,
            other.options,
            other.iteration_limit,
        )

    def __hash__(self) -> int:
        return hash((self.function, self.options, self.iteration_limit))

    def __repr__(self) -> str:
        name = getattr(self.function, "__qualname__", repr(self.function))
        return f"ContinuedSolve({name})"
