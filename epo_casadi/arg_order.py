"""One argument order for functions of a game, its parameters and a strategy: ``(game, p, u)``.

The solvers take ``(game, p, u0=None, ...)``; the Nash certificate and the inspection
helpers follow the same order, ``(game, p, u, ...)``. They used to take ``(game, u, p)``;
:func:`p_u_order` keeps such calls working for a deprecation period:

* keyword calls (``f(game, p=p, u=u)``) are always safe and never warn;
* a positional call in the old order is recognised by sizes (the first array's last
  dimension is ``game.n_u``, the second's ``game.n_p``), swapped, and a
  :class:`DeprecationWarning` says so; ``f(game, u, p=p)`` (the old order with ``p`` as
  a keyword) is handled the same way;
* when ``game.n_u == game.n_p`` sizes cannot tell the orders apart, so a positional call
  whose two arrays both have that size raises :class:`~epo_casadi.errors.SpecError`
  asking for keywords (rather than guess and silently swap a strategy and parameters).

Arrays whose sizes fit neither order are passed on unchanged in the new order; the
function's own validation (:meth:`PotentialGame.check_inputs`) names the bad one.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from .errors import SpecError

__all__ = ["p_u_order", "resolve_p_u"]

F = TypeVar("F", bound=Callable[..., Any])


def _last_dim(x) -> int | None:
    try:
        shape = np.shape(x)
    except Exception:  # ragged lists and the like: let the function's validation report it
        return None
    return int(shape[-1]) if len(shape) >= 1 else None


def resolve_p_u(
    game, args: tuple, kwargs: dict, where: str, lead: str = "game, "
) -> tuple[tuple, dict]:
    """Return ``(args, kwargs)`` of a call ``f(game, *args, **kwargs)`` rewritten so that
    ``args`` starts with ``p, u`` (the order of :mod:`epo_casadi.arg_order`).

    ``where`` names the function in messages, ``lead`` the arguments before ``p``. Raises :class:`SpecError` for an ambiguous
    positional call (``n_u == n_p``); warns with :class:`DeprecationWarning` for the old
    order.
    """
    if not (hasattr(game, "n_u") and hasattr(game, "n_p")):
        return args, kwargs  # not a game: the function's own check says so
    n_u, n_p = int(game.n_u), int(game.n_p)
    old = (
        f"{where}({lead}u, p) is deprecated; the order is {where}({lead}p, u) like the "
        f"solvers (or pass p= and u= as keywords)"
    )
    if len(args) >= 2 and "p" not in kwargs and "u" not in kwargs:
        a, b = _last_dim(args[0]), _last_dim(args[1])
        if n_u == n_p and a == b == n_u:
            raise SpecError(
                f"{where}(p, u)",
                f"ambiguous positional arguments: this game has n_u = n_p = {n_u}, so the "
                f"order (p, u) cannot be told from the deprecated (u, p) by size; pass them "
                f"as keywords: {where}({lead}p=..., u=...)",
            )
        if n_u != n_p and a == n_u and b == n_p:
            warnings.warn(old, DeprecationWarning, stacklevel=3)
            return (args[1], args[0], *args[2:]), kwargs
        return args, kwargs
    if len(args) >= 1 and "p" in kwargs and "u" not in kwargs:
        # f(game, u, p=p): only the old signature reads the first positional as u
        warnings.warn(old, DeprecationWarning, stacklevel=3)
        kwargs = dict(kwargs)
        return (kwargs.pop("p"), args[0], *args[1:]), kwargs
    return args, kwargs


def p_u_order(func: F | None = None, *, method: bool = False) -> F:
    """Decorator for ``func(game, p, u, ...)`` (or, with ``method=True``, a method
    ``func(self, p, u, ...)`` of an object with a ``game`` attribute) that accepts the
    deprecated ``(game, u, p)`` order as described in :mod:`epo_casadi.arg_order`."""

    def wrap(f: F) -> F:
        where = f.__name__

        @functools.wraps(f)
        def call(first, *args, **kwargs):
            game = first.game if method else first
            args, kwargs = resolve_p_u(game, args, kwargs, where, "" if method else "game, ")
            return f(first, *args, **kwargs)

        return call  # type: ignore[return-value]

    return wrap if func is None else wrap(func)
