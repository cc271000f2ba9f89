"""Named parameters set on a parameter vector: :func:`apply_settings`, the CLI's
``--set NAME=VALUE`` on a game's blocks (``goal.robot``) and their entries
(``x0.robot.v``), weights kept >= 0."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from epo_casadi.errors import SpecError, short_repr
from epo_casadi.game import PotentialGame

from .checks import WEIGHT_RULE


def apply_settings(
    game: PotentialGame, p: np.ndarray, settings: Sequence[str] | Mapping[str, Any]
) -> np.ndarray:
    """A copy of ``p`` with named parameters replaced.

    ``settings`` holds ``"NAME=VALUE"`` strings (or a mapping ``NAME -> VALUE``). ``NAME``
    is a parameter block (``goal.robot``, ``w.robot.goal``, ``w.robot-ped.collision``,
    ``x0.robot``) or one entry of a block (``x0.robot.v``, ``goal.robot.x``); ``VALUE`` is
    one number or comma-separated numbers (optionally in brackets) of the block's size.
    """
    layout = game.params
    p = np.array(p, dtype=float).reshape(-1).copy()
    entries = {n: k for k, n in enumerate(layout.names)}
    items = (
        settings.items() if isinstance(settings, Mapping) else [_split_setting(s) for s in settings]
    )
    weights = np.zeros(p.size, dtype=bool)  # the layer's rule: weights must be >= 0
    weights[layout.group("w_own")] = weights[layout.group("w_pair")] = True
    for name, value in items:
        where = f"--set {name}"
        vals = _parse_values(value, where)
        if name in layout:
            b = layout[name]
            if vals.size != b.size:
                raise SpecError(
                    where,
                    f"expected {b.size} comma-separated numbers for block {name!r}, got {vals.size}",
                )
            idx = np.arange(b.start, b.start + b.size)
        elif name in entries:
            if vals.size != 1:
                raise SpecError(where, f"expected one number for entry {name!r}, got {vals.size}")
            idx = np.array([entries[name]])
        else:
            import difflib

            blocks = [b.name for b in layout.blocks]
            known = list(dict.fromkeys(blocks + list(entries)))
            close = difflib.get_close_matches(name, known, n=3, cutoff=0.6)
            hint = f"did you mean {' or '.join(map(repr, close))}? " if close else ""
            raise SpecError(
                where,
                f"unknown parameter; {hint}expected a block {blocks} or one of its entries (e.g. {layout.names[0]!r})",
            )
        neg = weights[idx] & (vals < 0)
        if neg.any():
            raise SpecError(where, f"expected a number >= 0{WEIGHT_RULE}, got {vals[neg][0]:g}")
        p[idx] = vals
    return p


def _split_setting(s: str) -> tuple[str, str]:
    if not isinstance(s, str) or "=" not in s:
        raise SpecError("--set", f"expected NAME=VALUE, got {short_repr(s)}")
    name, value = s.split("=", 1)
    name = name.strip()
    if not name:
        raise SpecError("--set", f"expected NAME=VALUE with a parameter name, got {short_repr(s)}")
    return name, value


def _parse_values(value: Any, where: str) -> np.ndarray:
    if isinstance(value, str):
        text = value.strip().removeprefix("[").removesuffix("]")
        parts = [t for t in text.replace(" ", ",").split(",") if t]
        try:
            vals = np.array([float(t) for t in parts], dtype=float)
        except ValueError:
            raise SpecError(where, f"expected numbers, got {short_repr(value)}") from None
    else:
        try:
            vals = np.asarray(value, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise SpecError(where, f"expected numbers, got {short_repr(value)}") from None
    if vals.size == 0:
        raise SpecError(where, "expected at least one number")
    if not np.all(np.isfinite(vals)):
        raise SpecError(where, f"expected finite numbers, got {short_repr(value)}")
    return vals
