"""The specs of a game (:mod:`epo_casadi.game`): agents, coupled dynamics, the whole game.

:class:`AgentSpec` (an agent's dynamics, features, initial state, references and radius),
:class:`Coupling` (agents whose dynamics are one joint model) and :class:`GameSpec` (the
agents, pair features, horizon and step), each checked when made (a :class:`SpecError`
naming the field) and written back as a dict by ``to_dict``; :data:`REFERENCES` are the
reference blocks features may read, :data:`MAX_HORIZON` the longest horizon, and
:func:`agent_radius` what pair features see as an agent's radius.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import casadi as ca
import numpy as np

from .dynamics import Dynamics, JointDynamics, make_dynamics
from .errors import SpecError
from .features import (
    Feature,
    PairFeature,
    ParamSpec,
    Path,
    make_feature,
    make_pair_feature,
)

#: reference blocks of an agent that features may read through ``Feature.refs()``
REFERENCES = ("goal", "vref", "path")

#: Largest horizon a game may have: the symbolic build and every solver's memory grow
#: linearly with K (K = 2000: 4 s and 0.1 GB to build crossing2); 10^12 would end in an
#: allocation failure deep inside CasADi instead of a message.
MAX_HORIZON = 10_000


def _finite_vector(value, size: int | None, where: str) -> tuple[float, ...]:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise SpecError(where, f"expected a list of numbers, got {value!r}") from None
    if size is not None and arr.size != size:
        raise SpecError(where, f"expected {size} numbers, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise SpecError(where, f"expected finite numbers, got {arr.tolist()}")
    return tuple(float(v) for v in arr)


# --------------------------------------------------------------------------------------
# Specs
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AgentSpec:
    """One agent: dynamics, geometry, own features and default reference values.

    ``x0``, ``goal``, ``vref`` and ``path`` are the *default* values of the agent's
    parameter blocks; every one of them can be changed per solve through ``p``.
    ``radius`` is a number of the game unless ``radius_param`` is true: then it is the
    default of a parameter block ``radius.<name>`` (group ``"radius"``), so one game can
    carry each problem's own radius (e.g. half of each vehicle's length); pair features
    see it as the symbolic ``AgentContext.radius``.
    """

    name: str
    dynamics: Dynamics | str | dict = "unicycle"
    features: Sequence[Feature | str | dict] = ()
    radius: float = 0.25
    x0: Sequence[float] | None = None
    goal: Sequence[float] | None = None
    vref: float | None = None
    path: Sequence[Sequence[float]] | None = None
    radius_param: bool = False

    def __post_init__(self):
        where = f"agents[{self.name!r}]"
        if not isinstance(self.name, str) or not self.name or "." in self.name or "-" in self.name:
            raise SpecError(
                "agents.name", f"expected a non-empty name without '.' or '-', got {self.name!r}"
            )
        dyn = make_dynamics(self.dynamics)
        if dyn.nx < 1:
            raise SpecError(
                f"{where}.dynamics", f"{type(dyn).__name__} declares no state_names (nx = 0)"
            )
        object.__setattr__(self, "dynamics", dyn)
        r = self.radius
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r) or r < 0:
            raise SpecError(f"{where}.radius", f"expected a finite number >= 0 (metres), got {r!r}")
        if not isinstance(self.radius_param, bool):
            raise SpecError(
                f"{where}.radius_param", f"expected true or false, got {self.radius_param!r}"
            )
        if self.x0 is not None:
            object.__setattr__(self, "x0", _finite_vector(self.x0, dyn.nx, f"{where}.x0"))
        if self.goal is not None:
            object.__setattr__(self, "goal", _finite_vector(self.goal, 2, f"{where}.goal"))
        if self.vref is not None:
            object.__setattr__(self, "vref", _finite_vector(self.vref, 1, f"{where}.vref")[0])
        if self.path is not None:
            pts = np.asarray(_finite_vector(self.path, None, f"{where}.path"))
            if pts.size < 4 or pts.size % 2:
                raise SpecError(f"{where}.path", "expected a list of at least two [x, y] points")
            object.__setattr__(self, "path", tuple(map(tuple, pts.reshape(-1, 2).tolist())))
        feats, keys = [], set()
        for n, f in enumerate(self.features):
            f = make_feature(f, f"{where}.features[{n}]")
            if isinstance(f, Path):
                npts = len(self.path) if self.path is not None else None
                if f.points is None:
                    if npts is None:
                        raise SpecError(
                            f"{where}.path",
                            "the 'path' feature needs the agent's path (or 'points')",
                        )
                    f = replace(f, points=npts)
                elif npts is not None and npts != f.points:
                    raise SpecError(
                        f"{where}.path", f"feature expects {f.points} points, path has {npts}"
                    )
            if f.key in keys:
                raise SpecError(
                    f"{where}.features[{n}]", f"duplicate feature {f.key!r}; give one a 'label'"
                )
            keys.add(f.key)
            unknown = sorted(set(f.refs()) - set(REFERENCES))
            if unknown:
                raise SpecError(
                    f"{where}.features[{n}]",
                    f"feature {f.key!r} reads unknown reference(s) {unknown}; the agent has "
                    f"{list(REFERENCES)}; declare blocks of its own with params() (ParamSpec)",
                )
            try:
                f.check(dyn)
            except SpecError as e:
                raise SpecError(f"{where}.features[{n}]", e.message) from None
            feats.append(f)
        object.__setattr__(self, "features", tuple(feats))
        self.param_specs()  # conflicting declarations are an error now, not at build

    def param_specs(self) -> dict[str, ParamSpec]:
        """The parameter blocks the agent's features declare (name -> spec, in order).

        Two features may share a block by declaring it identically (same size, default
        and entries); anything else under one name is a :class:`SpecError`.
        """
        out: dict[str, ParamSpec] = {}
        for n, f in enumerate(self.features):
            specs = f.params()
            if not isinstance(specs, (tuple, list)) or not all(
                isinstance(s, ParamSpec) for s in specs
            ):
                raise SpecError(
                    f"agents[{self.name!r}].features[{n}].params",
                    f"params() must return a tuple of ParamSpec, got {specs!r:.80}",
                )
            for s in specs:
                if s.name in out and out[s.name] != s:
                    raise SpecError(
                        f"agents[{self.name!r}].features[{n}].params.{s.name}",
                        f"declared twice with different size, default or entries: "
                        f"{out[s.name]} and {s}",
                    )
                out[s.name] = s
        return out

    def refs(self) -> dict[str, int]:
        """Every parameter block of this agent its features read (name -> size): the
        references (``goal``, ``vref``, ``path``) and the features' own blocks
        (:meth:`param_specs`); each arrives in ``AgentContext.refs`` under its name."""
        out: dict[str, int] = {}
        for f in self.features:
            out.update(f.refs())
        out.update({n: s.size for n, s in self.param_specs().items()})
        if self.radius_param:
            out["radius"] = 1
        return out

    def to_dict(self) -> dict:
        d: dict[str, Any] = {
            "name": self.name,
            "dynamics": self.dynamics.to_dict(),
            "radius": self.radius,
            "features": [f.to_dict() for f in self.features],
        }
        for k in ("x0", "goal", "vref"):
            if getattr(self, k) is not None:
                d[k] = list(getattr(self, k)) if k != "vref" else self.vref
        if self.path is not None:
            d["path"] = [list(p) for p in self.path]
        if self.radius_param:
            d["radius_param"] = True
        return d


@dataclass(frozen=True)
class Coupling:
    """Coupled dynamics: ``model`` (a :class:`~epo_casadi.dynamics.JointDynamics`) steps
    the states of ``agents`` (two or more names) together; see :class:`GameSpec`."""

    agents: tuple[str, ...]
    model: JointDynamics

    def __post_init__(self):
        names = tuple(self.agents) if isinstance(self.agents, (list, tuple)) else None
        if not names or len(names) < 2 or not all(isinstance(a, str) for a in names):
            raise SpecError(
                "couplings.agents", f"expected two or more agent names, got {self.agents!r:.80}"
            )
        if len(set(names)) != len(names):
            raise SpecError("couplings.agents", f"an agent appears twice in {list(names)}")
        if not isinstance(self.model, JointDynamics):
            raise SpecError(
                "couplings.model",
                f"expected a JointDynamics instance, got {type(self.model).__name__}",
            )
        object.__setattr__(self, "agents", names)


@dataclass(frozen=True)
class GameSpec:
    """A game: agents, pairwise features, horizon ``K`` and step ``dt`` (seconds).

    ``couplings`` (optional, Python API only): :class:`Coupling` objects whose joint
    models step several agents' states together (every agent in at most one); the
    other agents step with their own dynamics. LM (its dense backend; the structured
    ones hand coupled games to it), IPOPT, the iLQ game solver, the Nash certificate and
    the layer accept coupled games.
    """

    agents: Sequence[AgentSpec]
    pair_features: Sequence[PairFeature | str | dict] = ()
    horizon: int = 40
    dt: float = 0.1
    couplings: Sequence[Coupling] = ()

    def __post_init__(self):
        agents = tuple(self.agents)
        if not agents:
            raise SpecError("agents", "a game needs at least one agent")
        for n, a in enumerate(agents):
            if not isinstance(a, AgentSpec):
                raise SpecError(f"agents[{n}]", f"expected an AgentSpec, got {type(a).__name__}")
        names = [a.name for a in agents]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise SpecError("agents.name", f"agent names must be unique, repeated: {sorted(dup)}")
        K = self.horizon
        if isinstance(K, bool) or not isinstance(K, int) or K < 1:
            raise SpecError("horizon", f"expected an integer number of steps >= 1, got {K!r}")
        if K > MAX_HORIZON:
            raise SpecError(
                "horizon",
                f"expected at most {MAX_HORIZON} steps (the symbolic build and every solver's "
                f"memory grow linearly with it), got {K}",
            )
        dt = self.dt
        if (
            isinstance(dt, bool)
            or not isinstance(dt, (int, float))
            or not math.isfinite(dt)
            or dt <= 0
        ):
            raise SpecError("dt", f"expected a step length > 0 in seconds, got {dt!r}")
        pfs, keys = [], set()
        for n, pf in enumerate(self.pair_features):
            pf = make_pair_feature(pf, f"pair_features[{n}]")
            if pf.key in keys:
                raise SpecError(
                    f"pair_features[{n}]", f"duplicate pair feature {pf.key!r}; give one a 'label'"
                )
            keys.add(pf.key)
            w = pf.weight
            if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w):
                raise SpecError(
                    f"pair_features[{n}].weight", f"expected a finite number, got {w!r}"
                )
            for pr in pf.pairs or ():
                if len(pr) != 2 or pr[0] == pr[1] or any(a not in names for a in pr):
                    raise SpecError(
                        f"pair_features[{n}].pairs",
                        f"expected two different agent names from {names}, got {list(pr)}",
                    )
            every = getattr(pf, "every", None)
            if every is not None and every > K:
                raise SpecError(
                    f"pair_features[{n}].every",
                    f"expected an integer <= horizon ({K}): every {every} checks no step at all",
                )
            pfs.append(pf)
        object.__setattr__(self, "agents", agents)
        object.__setattr__(self, "pair_features", tuple(pfs))
        object.__setattr__(self, "dt", float(dt))
        object.__setattr__(self, "couplings", self._check_couplings(agents))

    def _check_couplings(self, agents) -> tuple[Coupling, ...]:
        by_name = {a.name: a for a in agents}
        seen: set[str] = set()
        out = []
        for n, c in enumerate(self.couplings):
            where = f"couplings[{n}]"
            if not isinstance(c, Coupling):
                raise SpecError(where, f"expected a Coupling, got {type(c).__name__}")
            for a in c.agents:
                if a not in by_name:
                    raise SpecError(
                        f"{where}.agents", f"unknown agent {a!r}; expected one of {list(by_name)}"
                    )
                if a in seen:
                    raise SpecError(f"{where}.agents", f"agent {a!r} is in two couplings")
                seen.add(a)
            dyn = [by_name[a].dynamics for a in c.agents]
            xs = [ca.SX.sym(f"x_{a}", d.nx) for a, d in zip(c.agents, dyn, strict=True)]
            us = [ca.SX.sym(f"u_{a}", d.nu) for a, d in zip(c.agents, dyn, strict=True)]
            try:
                nxt = list(c.model.step(xs, us, ca.SX.sym("dt")))
            except SpecError:
                raise
            except Exception as e:
                msg = (str(e).strip().splitlines() or [""])[-1]
                raise SpecError(
                    f"{where}.model", f"step() fails on symbolic states ({type(e).__name__}: {msg})"
                ) from None
            shapes = [tuple(x.shape) for x in nxt]
            want = [(d.nx, 1) for d in dyn]
            if shapes != want:
                raise SpecError(
                    f"{where}.model",
                    f"step() must return one next-state column per agent, shapes {want}, "
                    f"got {shapes}",
                )
            out.append(c)
        return tuple(out)

    def pairs_of(self, pf: PairFeature) -> list[tuple[int, int]]:
        """Index pairs ``(a, b)``, ``a < b``, that ``pf`` couples, in agent order."""
        idx = {a.name: n for n, a in enumerate(self.agents)}
        if pf.pairs is None:
            N = len(self.agents)
            return [(a, b) for a in range(N) for b in range(a + 1, N)]
        out = sorted({tuple(sorted((idx[x], idx[y]))) for x, y in pf.pairs})
        return [(int(a), int(b)) for a, b in out]

    def to_dict(self) -> dict:
        return {
            "horizon": self.horizon,
            "dt": self.dt,
            "agents": [a.to_dict() for a in self.agents],
            "pair_features": [pf.to_dict() for pf in self.pair_features],
        }


def agent_radius(agent: AgentSpec, refs: dict):
    """What pair features see as an agent's radius: the symbolic ``radius`` block of
    ``refs`` for an agent with ``radius_param``, else the spec's number."""
    if agent.radius_param:
        return refs["radius"][0]
    return float(agent.radius)


# --------------------------------------------------------------------------------------
