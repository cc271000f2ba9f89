"""The flat parameter vector and the residual blocks of a game (:mod:`epo_casadi.game`).

:class:`ParamBlock` is one named block of ``p``, :class:`ParamLayout` the ordered blocks
(looked up by name, grouped, packed from and unpacked to named values, defaults), and
:class:`Term` one block of the residual vector ``r`` (agent, feature, weight parameter,
time steps, rows); the order of both is the contract in :mod:`epo_casadi.game`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import SpecError
from .game_spec import _finite_vector


@dataclass(frozen=True)
class ParamBlock:
    """One named block of the flat parameter vector ``p`` (:class:`ParamLayout`).

    ``name``: the block's name (``x0.robot``, ``w.robot.goal``, ``w.robot-ped.collision``;
    the naming of the module docstring); ``group``: its kind, one of
    :attr:`ParamLayout.GROUPS`; ``start``, ``size``: its entries are
    ``p[start : start + size]`` (:attr:`slice`); ``default``: ``size`` default values (in
    their entries' units: m, m/s, rad, weights); ``entries``: one readable name per entry
    (``x0.robot.v``).
    """

    name: str  # e.g. "x0.robot", "w.robot.goal", "w.robot-ped.collision"
    group: str  # "x0" | "goal" | "vref" | "path" | "radius" | "feature" | "w_own" | "w_pair"
    start: int
    size: int
    default: tuple[float, ...]
    entries: tuple[str, ...]  # one readable name per entry

    @property
    def slice(self) -> slice:
        return slice(self.start, self.start + self.size)


class ParamLayout:
    """Names, offsets and defaults of the flat parameter vector ``p``."""

    GROUPS = ("x0", "goal", "vref", "path", "radius", "feature", "w_own", "w_pair")

    def __init__(self, blocks: Sequence[ParamBlock]):
        self.blocks: tuple[ParamBlock, ...] = tuple(blocks)
        self._by_name = {b.name: b for b in self.blocks}

    @property
    def size(self) -> int:
        return sum(b.size for b in self.blocks)

    @property
    def names(self) -> list[str]:
        """One name per entry of ``p`` (e.g. ``x0.robot.v``)."""
        return [e for b in self.blocks for e in b.entries]

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    def __getitem__(self, name: str) -> ParamBlock:
        try:
            return self._by_name[name]
        except KeyError:
            raise SpecError(
                "params", f"unknown parameter block {name!r}; known: {list(self._by_name)}"
            ) from None

    def group(self, group: str) -> np.ndarray:
        """Indices into ``p`` of all entries of ``group`` (see :attr:`GROUPS`)."""
        if group not in self.GROUPS:
            raise SpecError("group", f"expected one of {self.GROUPS}, got {group!r}")
        idx = [np.arange(b.start, b.start + b.size) for b in self.blocks if b.group == group]
        return np.concatenate(idx) if idx else np.zeros(0, dtype=int)

    def defaults(self) -> np.ndarray:
        return np.array([v for b in self.blocks for v in b.default], dtype=float)

    def pack(
        self, values: Mapping[str, Any] | None = None, base: np.ndarray | None = None
    ) -> np.ndarray:
        """A parameter vector: ``base`` (default: :meth:`defaults`) with named blocks replaced.

        ``values`` maps block names to numbers or arrays of the block's size; an unknown
        name, a wrong size or a non-finite value raises :class:`SpecError`.
        """
        p = self.defaults() if base is None else np.array(base, dtype=float).reshape(-1).copy()
        if p.size != self.size:
            raise SpecError("params", f"expected a vector of {self.size} entries, got {p.size}")
        for name, v in (values or {}).items():
            b = self[name]
            p[b.slice] = _finite_vector(v, b.size, f"params[{name!r}]")
        return p

    def unpack(self, p: np.ndarray) -> dict[str, np.ndarray]:
        """Block name -> values; ``p`` may carry leading batch dimensions."""
        p = np.asarray(p)
        if p.shape[-1] != self.size:
            raise SpecError("params", f"expected a last dimension of {self.size}, got {p.shape}")
        return {b.name: p[..., b.slice] for b in self.blocks}

    def __repr__(self) -> str:
        lines = [f"ParamLayout({self.size} entries)"]
        for b in self.blocks:
            lines.append(f"  [{b.start:4d}:{b.start + b.size:4d}] {b.name:32s} {b.group}")
        return "\n".join(lines)


@dataclass(frozen=True)
class Term:
    """One block of the residual vector (see the module docstring)."""

    index: int
    kind: str  # "own" | "pair"
    agents: tuple[str, ...]
    feature: str  # feature key (label or kind)
    feature_type: str
    weight: str  # name of the weight parameter block
    steps: tuple[int, ...]
    rows: slice  # rows of r

    @property
    def size(self) -> int:
        return self.rows.stop - self.rows.start


# --------------------------------------------------------------------------------------
# The game
