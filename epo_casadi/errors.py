"""Typed errors: every input error names the field and what was expected."""

from __future__ import annotations

import math

__all__ = ["EpoError", "SpecError", "check_number", "check_bool"]


class EpoError(Exception):
    """Base class of the toolkit's own errors (the CLI prints these without a traceback)."""


class SpecError(EpoError, ValueError):
    """An invalid game, option or parameter value.

    ``field`` is the dotted path of the offending entry (``agents[1].radius``), ``message``
    says what was expected and what was found.
    """

    def __init__(self, field: str, message: str):
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")


def check_number(
    field: str, value, *, lo=None, hi=None, lo_open: bool = False, integer: bool = False
):
    """Return ``value`` if it is a finite number (an int with ``integer``) within the bounds.

    ``lo`` is inclusive unless ``lo_open``; ``hi`` is inclusive. Otherwise raise
    :class:`SpecError` naming ``field`` and the expected range. Booleans are not numbers.
    """
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if integer:
        ok = ok and isinstance(value, int)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value <= hi
    if not ok:
        kind = "an integer" if integer else "a finite number"
        if lo is not None and hi is not None:
            rng = f" in {'(' if lo_open else '['}{lo}, {hi}]"
        elif lo is not None:
            rng = f" {'>' if lo_open else '>='} {lo}"
        elif hi is not None:
            rng = f" <= {hi}"
        else:
            rng = ""
        raise SpecError(field, f"expected {kind}{rng}, got {value!r}")
    return value


def check_bool(field: str, value) -> bool:
    """Return ``value`` if it is ``True`` or ``False``, else raise :class:`SpecError`."""
    if not isinstance(value, bool):
        raise SpecError(field, f"expected True or False, got {value!r}")
    return value
