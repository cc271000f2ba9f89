"""The one reader of ``KEY=VALUE`` settings (``--set``, ``--solver NAME:key=value,...``).

Every command line option that takes ``KEY=VALUE`` reads the value with :func:`parse_value`,
so ``1e-6`` is a number, ``none`` is ``None`` and ``lm`` is a string everywhere:

- a JSON value: ``1``, ``1e-6``, ``-0.5``, ``[1, 2]``, ``{"a": 1}``, ``"quoted text"``;
- ``true`` / ``false`` / ``none`` / ``null`` in any case (Python's ``True``, ``None`` too);
- a flow list or mapping that is not JSON (``[a, b]``, ``{w: 1.5}``), read as YAML with
  numbers in the JSON form (``1e-6`` is a float, not YAML 1.1's string);
- anything else is the text itself (``lm``, ``left-turn``), stripped of outer spaces.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable
from typing import Any

from .errors import SpecError, short_repr

__all__ = ["parse_value", "parse_settings"]

_WORDS = {"true": True, "false": False, "none": None, "null": None}
_KEY_RE = re.compile(r"^[A-Za-z_][\w.\-]*$")
#: the longest value text read (a value is a number, a word or a short list)
MAX_VALUE = 10_000


def _yaml_flow(text: str) -> Any:
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    # YAML 1.1 reads 1e-6 (no dot) as a string; read every JSON number as a float
    Loader.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile(r"^[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)$"),
        list("-+0123456789."),
    )
    return yaml.load(text, Loader=Loader)  # noqa: S506 - a SafeLoader subclass


def parse_value(text: str, field: str = "value") -> Any:
    """The value a ``KEY=VALUE`` text stands for (module docstring); :class:`SpecError`
    naming ``field`` for a malformed list or mapping or a value over ``MAX_VALUE`` chars."""
    if not isinstance(text, str):
        raise SpecError(field, f"expected text, got {short_repr(text)}")
    if len(text) > MAX_VALUE:
        raise SpecError(field, f"expected at most {MAX_VALUE} characters, got {len(text)}")
    s = text.strip()
    if s.lower() in _WORDS:
        return _WORDS[s.lower()]
    try:
        return json.loads(s)
    except (ValueError, RecursionError):
        pass
    if s[:1] in "[{":
        import yaml

        try:
            return _yaml_flow(s)
        except (yaml.YAMLError, RecursionError):
            raise SpecError(field, f"cannot read the value {short_repr(s)}") from None
    return s


def parse_settings(items: Iterable[str], option: str = "--set") -> dict[str, Any]:
    """``{"key": value}`` from ``KEY=VALUE`` texts (:func:`parse_value` reads each value).

    A text without ``=``, an empty or malformed key, or a key given twice is a
    :class:`SpecError` naming ``option``.
    """
    out: dict[str, Any] = {}
    for item in items:
        key, eq, raw = str(item).partition("=")
        key = key.strip()
        if not eq:
            raise SpecError(option, f"expected KEY=VALUE, got {short_repr(item)}")
        if not _KEY_RE.match(key):
            raise SpecError(
                option, f"expected a key of letters, digits, '_', '.', '-', got {short_repr(key)}"
            )
        if key in out:
            raise SpecError(f"{option} {key}", "given twice")
        out[key] = parse_value(raw, f"{option} {key}")
    return out
