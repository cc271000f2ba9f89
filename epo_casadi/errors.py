"""Typed errors: every input error names the field and what was expected."""

from __future__ import annotations

import math
import reprlib

__all__ = [
    "EpoError",
    "SpecError",
    "OutputError",
    "check_number",
    "check_bool",
    "check_size",
    "from_mapping",
    "short_repr",
]

#: Longest message a :class:`SpecError` carries; longer ones are cut (a whole YAML structure
#: in a message would cost minutes to build and print).
MAX_MESSAGE = 2000

_repr = reprlib.Repr()
_repr.maxlevel, _repr.maxlist, _repr.maxdict, _repr.maxtuple = 3, 8, 6, 8
_repr.maxstring, _repr.maxother, _repr.maxlong = 60, 60, 40


def short_repr(value, limit: int = 80) -> str:
    """``repr(value)`` with bounded cost and length: nested containers are elided
    (``reprlib``), never walked in full, and the text is cut at ``limit`` characters."""
    s = _repr.repr(value)
    return s if len(s) <= limit else s[: limit - 3] + "..."


class EpoError(Exception):
    """Base class of the toolkit's own errors (the CLI prints these without a traceback)."""


class SpecError(EpoError, ValueError):
    """An invalid game, option or parameter value.

    ``field`` is the dotted path of the offending entry (``agents[1].radius``), ``message``
    says what was expected and what was found.
    """

    def __init__(self, field: str, message: str):
        field, message = str(field)[:200], str(message)
        if len(message) > MAX_MESSAGE:
            message = message[: MAX_MESSAGE - 3] + "..."
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")


class OutputError(EpoError, OSError):
    """An output file or folder could not be written (a path through a file, a full disk).

    ``path`` is the file that was to be written; nothing is left at ``path`` or beside it
    (writers write a temporary file and rename it into place).
    """

    def __init__(self, path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{path}: cannot write: {reason}")

    def __str__(self) -> str:
        return f"{self.path}: cannot write: {self.reason}"


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
        raise SpecError(field, f"expected {kind}{rng}, got {short_repr(value)}")
    return value


def check_bool(field: str, value) -> bool:
    """Return ``value`` if it is ``True`` or ``False``, else raise :class:`SpecError`."""
    if not isinstance(value, bool):
        raise SpecError(field, f"expected True or False, got {short_repr(value)}")
    return value


def check_size(field: str, value, limit: int | float, what: str = "", *, lo: int = 1):
    """Return ``value`` if it is an integer in ``[lo, limit]``; else :class:`SpecError`.

    The one check of sizes that must be bounded before any work starts (episode and sample
    counts, horizons, widths, estimated bytes): the message names ``field``, the value and the
    limit, and ``what`` says what the limit protects (e.g. ``"memory"``), so a user knows
    that a larger value is refused on purpose, not misread. Booleans and floats with a
    fraction are refused; ``5.0`` is read as ``5``.
    """
    v = value
    if isinstance(v, float) and math.isfinite(v) and v.is_integer():
        v = int(v)
    if isinstance(v, bool) or not isinstance(v, int):
        raise SpecError(field, f"expected an integer, got {short_repr(value)}")
    if v < lo:
        raise SpecError(field, f"expected an integer >= {lo}, got {v}")
    if v > limit:
        why = f" ({what})" if what else ""
        lim = f"{limit:,}" if isinstance(limit, int) else f"{limit:g}"
        raise SpecError(field, f"{v:,} is over the limit of {lim}{why}")
    return v


def from_mapping(cls, values, where: str, what: str = "field"):
    """``cls(**values)`` for a dataclass ``cls`` after checking that ``values`` is a mapping
    whose keys are all fields of ``cls``; otherwise :class:`SpecError` at ``where`` naming the
    unknown keys and the allowed ones (``what`` is how the message calls a key, e.g.
    ``"recipe field"``). The fields' own checks (``__post_init__``) run as usual."""
    from collections.abc import Mapping
    from dataclasses import fields

    if not isinstance(values, Mapping):
        raise SpecError(where, f"expected a mapping of {what}s, got {type(values).__name__}")
    names = {f.name for f in fields(cls) if f.init}
    unknown = sorted(set(values) - names, key=str)
    if unknown:
        raise SpecError(where, f"unknown {what}(s) {unknown}; allowed: {sorted(names)}")
    return cls(**values)
