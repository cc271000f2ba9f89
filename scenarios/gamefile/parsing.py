"""A game file's mapping made into a game (:func:`parse_game`): the schema of its keys,
the agents, their dynamics and features, the pair features and the ``solver`` section,
each validated, and the result, :class:`GameFile`."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from epo_casadi.dynamics import make_dynamics
from epo_casadi.errors import SpecError, short_repr
from epo_casadi.features import OWN_FEATURES, PAIR_FEATURES
from epo_casadi.features import Path as PathFeature
from epo_casadi.game import MAX_HORIZON, AgentSpec, GameSpec, PotentialGame
from epo_casadi.registry import DYNAMICS, FEATURES, freeze
from epo_casadi.registry import PAIR_FEATURES as _PAIR_REGISTRY
from epo_casadi.registry import allow_imports as _allow_imports

from .checks import (
    WEIGHT_RULE,
    _check_finite,
    _check_size,
    _integer,
    _keys,
    _number,
    _polyline,
    _short,
    _tname,
    _vector,
    _wrap,
)

_NAME_RE = re.compile(r"^[A-Za-z0-9_]+$")
_TOP_KEYS = ("horizon", "dt", "agents", "pair_features", "solver")
_AGENT_KEYS = (
    "name",
    "dynamics",
    "radius",
    "radius_param",
    "x0",
    "goal",
    "vref",
    "path",
    "features",
)
#: dynamics by name: built-ins and registered ones (epo_casadi.registry; 'module:Class' too)
_DYNAMICS = DYNAMICS.table


@dataclass(frozen=True, eq=False)
class GameFile:
    """A loaded game file.

    ``spec``: the game; ``params``: its default parameter vector ``p`` (layout in
    :class:`epo_casadi.ParamLayout`); ``solver_options``: ``{"lm": {...}, "ilq": {...}}``,
    one entry per solver of :data:`solvers.registry.SOLVERS` the file gives options for,
    as validated plain dictionaries (pass one as ``options=`` to the solver);
    ``path``: the file it came from (``None`` for :func:`parse_game` without a source).
    """

    spec: GameSpec
    params: np.ndarray
    solver_options: dict = field(default_factory=dict)
    path: Path | None = None

    @cached_property
    def game(self) -> PotentialGame:
        """The symbolic game (built on first use, then cached)."""
        return PotentialGame(self.spec)

    def options(self, solver: str, **overrides) -> Any:
        """Options object of the registered solver ``solver`` (``"lm"``, ``"ipopt"``,
        ``"ilq"``, ``"sqp"`` or a user's): file values, then ``overrides``."""
        from solvers.registry import SOLVERS

        entry = SOLVERS.entry(solver, "solver")
        values = {**self.solver_options.get(solver, {}), **overrides}
        return entry.make_options(values, f"solver.{solver}")

    @property
    def name(self) -> str:
        return self.path.stem if self.path is not None else "game"


def parse_game(
    data: Any, source: str | Path | None = None, allow_imports: Sequence[str] = ()
) -> GameFile:
    """Validate an already parsed game mapping (the schema of :func:`load_game`;
    ``allow_imports`` as there)."""
    if isinstance(allow_imports, str):
        allow_imports = (allow_imports,)
    with _allow_imports(*allow_imports, where="allow_imports"):
        return _parse_game(data, source)


def _parse_game(data: Any, source: str | Path | None) -> GameFile:
    if not isinstance(data, Mapping):
        where = Path(source).name if source is not None else "game"
        raise SpecError(
            where, f"expected a mapping with 'horizon', 'dt' and 'agents', got {_tname(data)}"
        )
    _check_size(data, Path(source).name if source is not None else "game")
    _keys(data, "", _TOP_KEYS, required=("horizon", "dt", "agents"))
    horizon = _integer(
        data["horizon"],
        "horizon",
        minimum=1,
        maximum=MAX_HORIZON,
        note=" (the symbolic build and the solvers' memory grow with the horizon)",
    )
    dt = _number(data["dt"], "dt", positive=True)
    agents_raw = data["agents"]
    if not isinstance(agents_raw, list) or not agents_raw:
        raise SpecError("agents", f"expected a non-empty list of agents, got {_short(agents_raw)}")
    agents, names = [], []
    for i, a in enumerate(agents_raw):
        spec = _agent(a, f"agents[{i}]")
        if spec.name in names:
            raise SpecError(
                f"agents[{i}].name", f"duplicate agent name {spec.name!r}; names must be unique"
            )
        names.append(spec.name)
        agents.append(spec)
    pfs_raw = data.get("pair_features", [])
    if pfs_raw is None:
        pfs_raw = []
    if not isinstance(pfs_raw, list):
        raise SpecError("pair_features", f"expected a list of pair features, got {_short(pfs_raw)}")
    pair_features, keys = [], set()
    for n, pf in enumerate(pfs_raw):
        obj = _feature(pf, f"pair_features[{n}]", PAIR_FEATURES, names=names)
        every = getattr(obj, "every", None)
        if every is not None and every > horizon:
            raise SpecError(
                f"pair_features[{n}].every",
                f"expected an integer <= horizon ({horizon}): every {every} checks no step at all",
            )
        if obj.key in keys:
            raise SpecError(
                f"pair_features[{n}]", f"duplicate pair feature {obj.key!r}; give one a 'label'"
            )
        keys.add(obj.key)
        pair_features.append(obj)
    spec = _wrap(lambda: GameSpec(agents, pair_features, horizon=horizon, dt=dt), "")
    solver_options = _solver(data.get("solver"), spec)
    game = PotentialGame(spec)
    gf = GameFile(
        spec, game.params.defaults(), solver_options, Path(source) if source is not None else None
    )
    gf.__dict__["game"] = game  # prime the cached property: the game is built once
    return gf


def _agent(a: Any, where: str) -> AgentSpec:
    if not isinstance(a, Mapping):
        raise SpecError(
            where,
            f"expected a mapping with 'name', 'dynamics', 'x0' and 'features', got {_short(a)}",
        )
    _keys(a, where, _AGENT_KEYS, required=("name", "dynamics", "x0", "features"))
    name = a["name"]
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise SpecError(
            f"{where}.name", f"expected a name of letters, digits and '_', got {short_repr(name)}"
        )
    dyn = _dynamics(a["dynamics"], f"{where}.dynamics")
    radius = _number(a.get("radius", 0.25), f"{where}.radius", minimum=0.0, unit=" (metres)")
    radius_param = a.get("radius_param", False)
    if not isinstance(radius_param, bool):
        raise SpecError(
            f"{where}.radius_param", f"expected true or false, got {short_repr(radius_param)}"
        )
    names = dyn.state_names
    x0 = _vector(a["x0"], len(names), f"{where}.x0", f"({', '.join(names)}) of '{dyn.name}'")
    goal = _vector(a["goal"], 2, f"{where}.goal", "(x, y)") if a.get("goal") is not None else None
    vref = _number(a["vref"], f"{where}.vref") if a.get("vref") is not None else None
    path = _polyline(a["path"], f"{where}.path") if a.get("path") is not None else None
    feats_raw = a["features"]
    if not isinstance(feats_raw, list):
        raise SpecError(
            f"{where}.features", f"expected a list of features, got {_short(feats_raw)}"
        )
    feats, keys = [], set()
    for n, f in enumerate(feats_raw):
        fw = f"{where}.features[{n}]"
        obj = _feature(f, fw, OWN_FEATURES, path_points=None if path is None else len(path))
        if obj.key in keys:
            raise SpecError(fw, f"duplicate feature {obj.key!r}; give one a 'label'")
        keys.add(obj.key)
        needs = {"path"} if isinstance(obj, PathFeature) else obj.refs()
        if "goal" in needs and goal is None:
            raise SpecError(
                f"{where}.goal",
                f"missing: the '{obj.kind}' feature ({fw}) needs the agent's goal [x, y]",
            )
        if "vref" in needs and vref is None:
            raise SpecError(
                f"{where}.vref",
                f"missing: the '{obj.kind}' feature ({fw}) needs the agent's vref (m/s)",
            )
        if "path" in needs and path is None:
            raise SpecError(
                f"{where}.path",
                f"missing: the '{obj.kind}' feature ({fw}) needs the agent's path [[x, y], ...]",
            )
        feats.append(obj)
    return _wrap(
        lambda: AgentSpec(
            name,
            dyn,
            feats,
            radius=radius,
            x0=x0,
            goal=goal,
            vref=vref,
            path=path,
            radius_param=radius_param,
        ),
        where,
    )


def _dynamics(d: Any, where: str):
    if isinstance(d, str):
        d = {"type": d}
    if not isinstance(d, Mapping):
        raise SpecError(
            where,
            f"expected a model name {sorted(_DYNAMICS)} or a mapping with 'type', got {_short(d)}",
        )
    if "type" not in d:
        raise SpecError(f"{where}.type", f"missing; expected one of {sorted(_DYNAMICS)}")
    kind = d["type"]
    cls = DYNAMICS.resolve(kind, f"{where}.type")  # a name or an allowed 'module:Class'
    options = DYNAMICS.options(cls)
    _keys(d, where, ("type", *options))
    if cls.__module__.startswith("epo_casadi."):  # built-in options are positive lengths
        values = {k: _number(d[k], f"{where}.{k}", positive=True) for k in options if k in d}
    else:  # a user's model checks its own options (make_dynamics reports them)
        values = {k: d[k] for k in options if k in d}
    return _wrap(lambda: make_dynamics({"type": kind, **values}), where)


def _feature(
    f: Any, where: str, registry: dict, names: Sequence[str] = (), path_points: int | None = None
):
    if isinstance(f, str):
        f = {"type": f}
    if not isinstance(f, Mapping):
        raise SpecError(where, f"expected a feature name or a mapping with 'type', got {_short(f)}")
    if "type" not in f:
        raise SpecError(f"{where}.type", f"missing; expected one of {sorted(registry)}")
    kind = f["type"]
    # a registered name or an allowed 'module:Class'; a wrong kind of class is refused
    cls = (FEATURES if registry is OWN_FEATURES else _PAIR_REGISTRY).resolve(kind, f"{where}.type")
    allowed = ("type", *[fl.name for fl in fields(cls)])
    _keys(f, where, allowed)
    opts: dict[str, Any] = {}
    for key, v in f.items():
        fw = f"{where}.{key}"
        if key == "type":
            continue
        if key == "weight":
            opts[key] = _number(v, fw, minimum=0.0, unit=WEIGHT_RULE)
        elif key == "label":
            if v is not None and (not isinstance(v, str) or not _NAME_RE.match(v)):
                raise SpecError(
                    fw, f"expected a label of letters, digits and '_', got {short_repr(v)}"
                )
            opts[key] = v
        elif key in ("lower", "upper"):
            if v is not None:
                opts[key] = _number(v, fw)
        elif key == "points":
            if v is not None:
                opts[key] = _integer(v, fw, minimum=2)
        elif key == "every":
            opts[key] = _integer(v, fw, minimum=1)
        elif key == "pairs":
            opts[key] = _pairs(v, fw, names)
        else:  # a field of a user's feature: its class checks it (lists become tuples)
            opts[key] = freeze(v)
    if kind == "path":
        pts = opts.get("points")
        if pts is not None and path_points is not None and pts != path_points:
            raise SpecError(
                f"{where}.points",
                f"expected {path_points} (the number of points of the agent's path), got {pts}",
            )
    if "lower" in cls.__dataclass_fields__:
        lo, hi = opts.get("lower"), opts.get("upper")
        if lo is None and hi is None:
            raise SpecError(
                where, f"the '{kind}' feature needs 'lower', 'upper' or both (finite numbers)"
            )
        if lo is not None and hi is not None and not lo < hi:
            raise SpecError(f"{where}.upper", f"expected upper > lower = {lo}, got {hi}")
    return _wrap(lambda: cls(**opts), where)


def _pairs(v: Any, where: str, names: Sequence[str]):
    if v is None:
        return None
    if not isinstance(v, list) or not v:
        raise SpecError(
            where, f"expected a non-empty list of [agent, agent] pairs, got {_short(v)}"
        )
    out = []
    for n, pr in enumerate(v):
        if (
            not isinstance(pr, list)
            or len(pr) != 2
            or pr[0] == pr[1]
            or any(not isinstance(a, str) or a not in names for a in pr)
        ):
            raise SpecError(
                f"{where}[{n}]",
                f"expected two different agent names from {list(names)}, got {_short(pr)}",
            )
        out.append(tuple(pr))
    return tuple(out)


def _solver(s: Any, spec: GameSpec) -> dict:
    """The ``solver`` section: options per registered solver, each validated now (and
    against the game where the solver checks that, e.g. bounds naming agents)."""
    if s is None:
        return {}
    from solvers.registry import SOLVERS

    if not isinstance(s, Mapping):
        raise SpecError(
            "solver",
            f"expected a mapping solver name -> options (solvers: {SOLVERS.names()}), "
            f"got {_short(s)}",
        )
    _keys(s, "solver", tuple(SOLVERS))
    out = {}
    for name, values in s.items():
        where = f"solver.{name}"
        if values is None:
            values = {}
        if not isinstance(values, Mapping):
            raise SpecError(where, f"expected a mapping of options, got {_short(values)}")
        values = dict(values)
        _check_finite(values, where)
        entry = SOLVERS[name]
        opts = entry.make_options(values, where)  # validate now, keep the plain mapping
        if entry.check_game is not None:
            entry.check_game(opts, spec, where)
        out[name] = values
    return out
