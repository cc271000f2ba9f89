"""Typed errors: every input error names the field and what was expected."""

from __future__ import annotations

__all__ = ["EpoError", "SpecError"]


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
