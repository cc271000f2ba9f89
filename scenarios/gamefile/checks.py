"""The checks every entry of a game file goes through: the size of the whole file
(:data:`MAX_VALUES` values after YAML aliases, :data:`MAX_DEPTH` levels of nesting),
finite numbers, known keys, numbers, integers, vectors and polylines, each raising a
:class:`~epo_casadi.errors.SpecError` named by the entry's path."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from epo_casadi.errors import SpecError, short_repr

#: Largest number of values (numbers, strings, lists, mappings) a game file may expand to,
#: counting every repetition of a YAML alias: a few aliases can otherwise stand for
#: billions of values and hang the loader.
MAX_VALUES = 1_000_000
#: Deepest nesting of lists and mappings a game file may have (a game file needs about 7:
#: ``solver.ipopt.control_bounds.<agent>[0][1]``); deeper data is refused in one line, never
#: by a RecursionError of a reader.
MAX_DEPTH = 64
#: the rule on weights that the game layer (learning.layer.GameLayer) enforces, said the
#: same way wherever a weight enters: game files, --set, the feature objects
WEIGHT_RULE = " (weights must be >= 0)"


def _check_size(data: Any, where: str, limit: int | None = None) -> None:
    """Refuse data that expands to more than ``limit`` values (default :data:`MAX_VALUES`)
    or that is nested more than :data:`MAX_DEPTH` levels deep.

    YAML aliases make one list stand for many: the count is the expanded one, computed in
    time linear in the *distinct* nodes (each shared node is counted once and remembered,
    with its height), so a bomb is measured without being walked. A structure that
    contains itself is refused too. The error names the smallest entry that is too large.
    """
    limit = MAX_VALUES if limit is None else limit
    memo: dict[int, tuple[int, int]] = {}  # id -> (expanded size, height)
    open_: set[int] = set()

    def too_deep(at: str):
        return SpecError(
            at or where, f"nested more than {MAX_DEPTH} levels deep; a game file needs about 7"
        )

    def measure(x, at: str, depth: int) -> tuple[int, int]:
        if not isinstance(x, (Mapping, list)):
            return 1, 0
        i = id(x)
        if i in memo:
            n, h = memo[i]
            if depth + h > MAX_DEPTH:
                raise too_deep(at)
            return n, h
        if depth >= MAX_DEPTH:
            raise too_deep(at)
        if i in open_:
            raise SpecError(at or where, "a YAML alias refers to a structure that contains it")
        open_.add(i)
        n, h = 1, 0
        items = x.items() if isinstance(x, Mapping) else enumerate(x)
        for k, c in items:
            cn, ch = measure(c, _child(at, k), depth + 1)
            n, h = n + cn, max(h, ch + 1)
            if n > limit:
                break  # no need to count further
        open_.discard(i)
        memo[i] = (n, h)
        return n, h

    def size(x, at: str) -> int:
        return measure(x, at, 0)[0]

    def _child(at: str, k) -> str:
        return f"{at}[{k}]" if isinstance(k, int) else (f"{at}.{k}" if at else str(k))

    try:
        total = size(data, "")
    except RecursionError:
        raise SpecError(where, "nested too deeply; expected a game file") from None
    if total <= limit:
        return
    at, x = "", data  # descend to the smallest entry that is still too large
    while isinstance(x, (Mapping, list)):
        items = x.items() if isinstance(x, Mapping) else enumerate(x)
        big = [(k, c) for k, c in items if size(c, "") > limit]
        if not big:
            break
        k, x = big[0]
        at = _child(at, k)
    raise SpecError(
        at or where,
        f"expands to more than {limit} values (YAML aliases repeating a structure?); "
        "a game file holds far fewer",
    )


def _check_finite(v: Any, where: str) -> None:
    if isinstance(v, float) and not math.isfinite(v):
        raise SpecError(where, f"expected a finite number, got {v}")
    if isinstance(v, Mapping):
        for k, x in v.items():
            _check_finite(x, f"{where}.{k}")
    elif isinstance(v, list):
        for n, x in enumerate(v):
            _check_finite(x, f"{where}[{n}]")


def _tname(v: Any) -> str:
    return {
        dict: "a mapping",
        list: "a list",
        str: "a string",
        bool: "a boolean",
        type(None): "nothing (null)",
    }.get(type(v), type(v).__name__)


def _short(v: Any) -> str:
    return short_repr(v, 60)  # bounded cost: never the repr of a whole (alias-bombed) structure


def _keyname(k: Any) -> str:
    """A key as a field name: short text as it is, anything else as a bounded repr."""
    return k if isinstance(k, str) and len(k) <= 60 else _short(k)


def _keys(d: Mapping, where: str, allowed: Sequence[str], required: Sequence[str] = ()) -> None:
    prefix = f"{where}." if where else ""
    for k in d:
        if not isinstance(k, str) or k not in allowed:
            raise SpecError(f"{prefix}{_keyname(k)}", f"unknown key; allowed here: {list(allowed)}")
    for k in required:
        if k not in d:
            raise SpecError(f"{prefix}{k}", "missing required field")
        if d[k] is None:
            raise SpecError(f"{prefix}{k}", "expected a value, got nothing (null)")


def _number(
    v: Any, where: str, *, minimum: float | None = None, positive: bool = False, unit: str = ""
) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        hint = ""
        if isinstance(v, str):
            try:
                float(v)
                hint = " (YAML reads numbers like 1e-3 as text: write 1.0e-3)"
            except ValueError:
                pass
        raise SpecError(where, f"expected a number, got {_tname(v)} {_short(v)}{hint}")
    v = float(v)
    if not math.isfinite(v):
        raise SpecError(where, f"expected a finite number, got {v}")
    if positive and v <= 0:
        raise SpecError(where, f"expected a number > 0, got {v:g}")
    if minimum is not None and v < minimum:
        raise SpecError(where, f"expected a number >= {minimum:g}{unit}, got {v:g}")
    return v


def _integer(
    v: Any, where: str, *, minimum: int, maximum: int | None = None, note: str = ""
) -> int:
    if isinstance(v, float) and v.is_integer():
        v = int(v)
    want = f">= {minimum}" if maximum is None else f">= {minimum} and <= {maximum}"
    if isinstance(v, bool) or not isinstance(v, int):
        raise SpecError(where, f"expected an integer {want}, got {_tname(v)} {_short(v)}")
    if v < minimum or (maximum is not None and v > maximum):
        raise SpecError(where, f"expected an integer {want}{note}, got {_short(v)}")
    return v


def _vector(v: Any, n: int, where: str, what: str) -> list[float]:
    if not isinstance(v, list):
        raise SpecError(
            where, f"expected a list of {n} numbers {what}, got {_tname(v)} {_short(v)}"
        )
    if len(v) != n:
        raise SpecError(where, f"expected {n} numbers {what}, got {len(v)}")
    return [_number(x, f"{where}[{k}]") for k, x in enumerate(v)]


def _polyline(v: Any, where: str) -> list[list[float]]:
    if not isinstance(v, list) or len(v) < 2:
        raise SpecError(where, f"expected a list of at least two [x, y] points, got {_short(v)}")
    return [_vector(pt, 2, f"{where}[{k}]", "[x, y]") for k, pt in enumerate(v)]


def _wrap(make, where: str):
    """Construct a spec object; re-raise its SpecError with this file's field path."""
    try:
        return make()
    except SpecError as e:
        f = e.field
        if where and not f.startswith(where):
            # "agents['robot'].x" or "velocity_bound.lower/upper" -> under `where`
            tail = f.split("]", 1)[1].lstrip(".") if f.startswith("agents[") else ""
            f = f"{where}.{tail}" if tail else where
        raise SpecError(f or "game", e.message) from None
    except (TypeError, ValueError) as e:
        raise SpecError(where or "game", str(e)) from None
