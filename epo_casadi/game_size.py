"""How large the symbolic game of a spec will be, from the spec alone (:mod:`epo_casadi.game`).

:func:`estimate_size` counts a :class:`SizeEstimate` (weighted residual entries and an upper
bound on the Jacobian's nonzeros) in time linear in the agents and features, nothing
symbolic built; the weights :data:`PAIR_WEIGHT` and :data:`PATH_SEGMENT_WEIGHT` and the
memory per entry :data:`BYTES_PER_ENTRY` and :data:`BYTES_PER_JACOBIAN_NNZ` are measured.
The limits a game is refused at, and :func:`~epo_casadi.game.check_size_estimate`, are in
:mod:`epo_casadi.game`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .features import Path

if TYPE_CHECKING:
    from .game_spec import GameSpec

#: Weights of :attr:`SizeEstimate.entries`: an agent's rolled-out step and an own
#: feature's step count 1, a pair feature's step of one pair :data:`PAIR_WEIGHT`, a ``path``
#: feature's step :data:`PATH_SEGMENT_WEIGHT` per polyline segment: their measured memory
#: relative to an own feature's step (below).
PAIR_WEIGHT = 3
PATH_SEGMENT_WEIGHT = 6
#: Memory (bytes) per entry of :attr:`SizeEstimate.entries` that the symbolic build and a
#: Levenberg-Marquardt solve (structured backend) take at their peak. Measured with the
#: peak resident memory (``ru_maxrss``) of fresh processes that build a game and run three
#: LM steps, less the memory before the build: unicycle crossings (tests/helpers.py
#: ``crossing_spec``, every pair colliding) with N = 2 at K = 1000 and 2000, N = 10 at
#: K = 200, N = 20 at K = 100, N = 30 at K = 40, and one agent following a 20-vertex path at
#: K = 1000 (90 to 373 MB). A least-squares fit gives 40 MB fixed, 2.9 kB per own step,
#: 9.5 kB per pair step and 17 kB per path segment step (hence the weights), and the rounded
#: weights with this constant (and the 40 MB) within 5 % of each run; the build alone is
#: 0.4 of it.
BYTES_PER_ENTRY = 3_000
#: Memory (bytes) per entry of :attr:`SizeEstimate.jacobian_nnz` that ``epo export`` of its
#: default functions (rollout, residual, jacobian, energy, gradient, agent_costs, as C)
#: takes at its peak, measured like :data:`BYTES_PER_ENTRY`: crossings with N = 2 at K =
#: 100, 200 and 300 gave 0.43 to 0.50 kB, N = 6 at K = 60 (pair rows weigh more) 0.79 kB.
#: The estimate is an upper bound, 1.9 (N = 6) to 3.5 (N = 2) times the true count, and
#: the true count costs 1.5 kB per nonzero in every run; the larger constant is kept.
BYTES_PER_JACOBIAN_NNZ = 800


@dataclass(frozen=True)
class SizeEstimate:
    """How large the symbolic game of a :class:`GameSpec` will be, found from the spec alone.

    ``entries``: one per agent and rolled-out step and per own feature and step it covers,
    :data:`PAIR_WEIGHT` per pair and step of each pair feature, :data:`PATH_SEGMENT_WEIGHT`
    per segment and step of a ``path`` feature: what the build and the solvers' memory
    grow with (:data:`BYTES_PER_ENTRY` each). ``jacobian_nnz``: an upper bound on the nonzeros of
    ``J = dr/du`` (a row at step ``k`` may depend on the controls of its agents at steps
    ``0..k``; single shooting makes this grow with ``K^2``).
    """

    entries: int
    jacobian_nnz: int

    @property
    def bytes(self) -> int:
        """Estimated peak memory of the build and an LM solve."""
        return self.entries * BYTES_PER_ENTRY

    @property
    def jacobian_bytes(self) -> int:
        """Estimated peak memory of building and exporting the Jacobian."""
        return self.jacobian_nnz * BYTES_PER_JACOBIAN_NNZ


def _gb(n: float) -> str:
    return f"{n / 1e9:,.1f} GB" if n >= 1e8 else f"{n / 1e6:.0f} MB"


def estimate_size(spec: GameSpec) -> SizeEstimate:
    """The :class:`SizeEstimate` of ``spec``, in time linear in its agents and features
    (pairs are counted, never listed; nothing symbolic is built)."""
    K, N = spec.horizon, len(spec.agents)
    group_nu = [a.dynamics.nu for a in spec.agents]  # controls a row of the agent may see
    idx = {a.name: n for n, a in enumerate(spec.agents)}
    for c in spec.couplings:
        ids = [idx[a] for a in c.agents]
        total = sum(spec.agents[i].dynamics.nu for i in ids)
        for i in ids:
            group_nu[i] = total

    def steps(feature) -> tuple[int, int]:
        """(steps, sum over steps of the controls' time steps a row there may see)."""
        ks = np.clip(np.asarray(list(feature.steps(K)), dtype=np.int64), 0, K - 1)
        return int(ks.size), int((ks + 1).sum())

    entries = N * K
    jac = 0
    for i, a in enumerate(spec.agents):
        for f in a.features:
            n, seen = steps(f)
            if isinstance(f, Path):
                entries += n * PATH_SEGMENT_WEIGHT * max(1, int(f.points or 2) - 1)
            else:
                entries += n
            jac += seen * group_nu[i]
    for pf in spec.pair_features:
        n, seen = steps(pf)
        if pf.pairs is None:
            pairs = N * (N - 1) // 2
            nu_pairs = (N - 1) * sum(group_nu)  # sum over pairs a < b of nu_a + nu_b
        else:
            keys = {tuple(sorted((idx[x], idx[y]))) for x, y in pf.pairs}
            pairs = len(keys)
            nu_pairs = sum(group_nu[x] + group_nu[y] for x, y in keys)
        entries += n * pairs * PAIR_WEIGHT
        jac += seen * nu_pairs
    return SizeEstimate(int(entries), int(jac))
