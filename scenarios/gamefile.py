"""Game files: a potential game written down in YAML or JSON.

A game file holds one :class:`epo_casadi.GameSpec` (agents, features, horizon, step)
plus optional solver options. The schema, with every field, is documented in
``docs/gamefiles.md``; in short::

    horizon: 40                 # K, number of steps (integer >= 1)
    dt: 0.1                     # step length in seconds (> 0)
    agents:                     # at least one
      - name: robot             # letters, digits, '_' ; unique
        dynamics: unicycle      # or {type: bicycle, wheelbase: 2.7}
        radius: 0.25            # metres, >= 0 (default 0.25)
        radius_param: false     # true: radius is the default of a parameter radius.<name>
        x0: [0, -3, 1, 1.57]    # initial state, nx numbers (required)
        goal: [0, 3]            # required by the 'goal' feature
        vref: 1.0               # required by 'reference_velocity'
        path: [[0, 0], [1, 0]]  # polyline, required by 'path'
        features:
          - {type: goal, weight: 3}
          - {type: velocity_bound, weight: 5, lower: 0, upper: 2}
    pair_features:
      - {type: collision, weight: 10, every: 1}
    solver:                     # options per registered solver (solvers.registry)
      lm: {steps: 200}          # solvers.lm.LMOptions fields
      ipopt: {max_iter: 500}    # solvers.ipopt.IpoptOptions fields
      ilq: {max_iter: 200}      # solvers.ilq.ILQOptions fields
      sqp: {collision: true}    # solvers.sqp.SQPOptions fields

Every problem in a file raises :class:`epo_casadi.SpecError` whose ``field`` is the
path of the offending entry (``agents[1].radius``, ``agents[0].features[2].upper``,
``solver.lm.steps``) and whose message says what was expected. Unknown keys are
errors, never ignored. Numbers must be finite (YAML ``.nan``/``.inf`` are rejected;
leave a bound out instead of writing an infinite one). YAML anchors, aliases and merge
keys (``<<: *base``; the mapping's own keys override the merged ones) are read; data
nested deeper than :data:`MAX_DEPTH` or expanding to more than :data:`MAX_VALUES` values
is refused.

Public API: :func:`load_game` (path), :func:`parse_game` (an already parsed mapping),
:class:`GameFile`, :func:`dump_game` / :func:`save_game` (the inverse) and
:func:`apply_settings` (the CLI's ``--set NAME=VALUE``).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from epo_casadi.dynamics import make_dynamics
from epo_casadi.errors import SpecError, short_repr
from epo_casadi.features import OWN_FEATURES, PAIR_FEATURES, Feature, PairFeature
from epo_casadi.features import Path as PathFeature
from epo_casadi.game import MAX_HORIZON, AgentSpec, GameSpec, PotentialGame
from epo_casadi.registry import DYNAMICS, FEATURES, freeze
from epo_casadi.registry import PAIR_FEATURES as _PAIR_REGISTRY
from epo_casadi.registry import allow_imports as _allow_imports
from scenarios.files import check_input_file

__all__ = [
    "GameFile",
    "load_game",
    "parse_game",
    "dump_game",
    "save_game",
    "apply_settings",
    "example_path",
    "EXAMPLES",
]

EXAMPLES_DIR = Path(__file__).resolve().parent / "examples"
#: names of the example files shipped in ``scenarios/examples`` (without ``.yaml``)
EXAMPLES = ("crossing2", "robot_pedestrian", "intersection4", "highway_merge")

_NAME_RE = re.compile(r"^[A-Za-z0-9_]+$")
#: Largest number of values (numbers, strings, lists, mappings) a game file may expand to,
#: counting every repetition of a YAML alias: a few aliases can otherwise stand for
#: billions of values and hang the loader.
MAX_VALUES = 1_000_000
#: Deepest nesting of lists and mappings a game file may have (a game file needs about 7:
#: ``solver.ipopt.control_bounds.<agent>[0][1]``); deeper data is refused in one line, never
#: by a RecursionError of a reader.
MAX_DEPTH = 64
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
#: the rule on weights that the game layer (learning.layer.GameLayer) enforces, said the
#: same way wherever a weight enters: game files, --set, the feature objects
WEIGHT_RULE = " (weights must be >= 0)"
#: dynamics by name: built-ins and registered ones (epo_casadi.registry; 'module:Class' too)
_DYNAMICS = DYNAMICS.table


def example_path(name: str) -> Path:
    """Path of a shipped example file, by name (``"crossing2"``) or file name."""
    stem = name[:-5] if name.endswith(".yaml") else name
    if stem not in EXAMPLES:
        raise SpecError(
            "example", f"unknown example {short_repr(name)}; expected one of {list(EXAMPLES)}"
        )
    return EXAMPLES_DIR / f"{stem}.yaml"


# --------------------------------------------------------------------------------------
# The result of loading
# --------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------
def load_game(path: str | Path, allow_imports: Sequence[str] = ()) -> GameFile:
    """Read a game file (``.yaml``/``.yml`` or ``.json``); see the module docstring.

    ``allow_imports``: modules whose ``module:Class`` names the file may import (with
    their submodules), besides those of ``$EPO_ALLOW_IMPORT`` and open
    :func:`epo_casadi.registry.allow_imports` blocks; any other is refused before it is
    imported. Raises :class:`SpecError` for every problem in the file (syntax included)
    and ``FileNotFoundError`` when there is no such file.
    """
    path = Path(path)
    where = path.name
    if path.exists():  # a pipe or a device would block or be read forever
        check_input_file(path, where)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise SpecError(
            where, f"not a UTF-8 text file (byte {e.start}); expected YAML or JSON"
        ) from None
    if not text.strip():
        raise SpecError(
            where, "the file is empty; expected a mapping with 'horizon', 'dt' and 'agents'"
        )
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text, object_pairs_hook=lambda pairs: _json_unique(pairs, where))
        except json.JSONDecodeError as e:
            raise SpecError(
                where, f"invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}"
            ) from None
        except RecursionError:  # the decoder recurses once per level of nesting
            raise SpecError(
                where, f"invalid JSON: nested more than {MAX_DEPTH} levels deep"
            ) from None
    else:
        data = _load_yaml(text, where)
    if data is None:
        raise SpecError(
            where, "the file holds no data; expected a mapping with 'horizon', 'dt' and 'agents'"
        )
    return parse_game(data, source=path, allow_imports=allow_imports)


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


# --------------------------------------------------------------------------------------
# Field checks
# --------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------
# YAML / JSON details
# --------------------------------------------------------------------------------------
def _load_yaml(text: str, where: str):
    import yaml

    class _Loader(yaml.SafeLoader):
        pass

    def _mapping(loader, node, deep=False):
        out, merged = {}, {}
        for knode, vnode in node.value:
            mark = knode.start_mark
            if knode.tag == "tag:yaml.org,2002:merge":  # '<<: *base' or '<<: [*a, *b]'
                for src in reversed(_merge_sources(loader, vnode, deep, mark)):
                    merged.update(src)  # the first mapping listed wins
                continue
            key = loader.construct_object(knode, deep=deep)
            try:
                hash(key)
            except TypeError:
                raise SpecError(
                    where,
                    f"a key at line {mark.line + 1}, column {mark.column + 1} is a "
                    f"{_tname(key)}; expected a name",
                ) from None
            if key in out:
                raise SpecError(
                    where,
                    f"duplicate key {short_repr(key)} at line {mark.line + 1}, column {mark.column + 1}",
                )
            out[key] = loader.construct_object(vnode, deep=deep)
        # YAML merge keys: the mapping's own keys override the merged ones, wherever written
        return {**{k: v for k, v in merged.items() if k not in out}, **out} if merged else out

    def _merge_sources(loader, vnode, deep, mark) -> list:
        """The mappings a merge key ``<<`` names (a mapping, or a list of mappings)."""
        nodes = vnode.value if isinstance(vnode, yaml.SequenceNode) else [vnode]
        out = []
        for n in nodes:
            if not isinstance(n, yaml.MappingNode):
                raise SpecError(
                    where,
                    f"the merge key '<<' at line {mark.line + 1}, column {mark.column + 1} "
                    "expects a mapping (an alias like *base) or a list of mappings",
                )
            out.append(loader.construct_object(n, deep=deep))
        return out

    _Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping)
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
    except RecursionError:
        raise SpecError(where, "invalid YAML: nested too deeply") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise SpecError(where, f"invalid YAML{at}: {problem}") from None


def _json_unique(pairs, where: str):
    out = {}
    for k, v in pairs:
        if k in out:
            raise SpecError(where, f"duplicate key {short_repr(k)}")
        out[k] = v
    return out


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------
def _feature_dict(f: Feature | PairFeature) -> dict:
    d: dict[str, Any] = {}
    for k, v in f.to_dict().items():
        if v is None or (isinstance(v, float) and math.isinf(v)):
            continue  # defaults: no label, no pair list, no bound on that side
        d[k] = float(v) if k == "weight" else v
    return d


def dump_game(spec: GameSpec | GameFile, solver_options: Mapping | None = None) -> dict:
    """The game-file mapping of ``spec`` (inverse of :func:`parse_game`).

    Plain lists, numbers and strings only, so ``yaml.safe_dump`` and ``json.dump`` both
    write it; ``parse_game(dump_game(spec)).spec`` is equal to ``spec``.
    """
    if isinstance(spec, GameFile):
        solver_options = spec.solver_options if solver_options is None else solver_options
        spec = spec.spec
    if not isinstance(spec, GameSpec):
        raise SpecError("spec", f"expected a GameSpec, got {type(spec).__name__}")
    if spec.couplings:
        raise SpecError("couplings", "game files cannot hold coupled dynamics yet (Python API)")
    agents = []
    for a in spec.agents:
        dyn = a.dynamics.to_dict()
        d: dict[str, Any] = {
            "name": a.name,
            "dynamics": dyn["type"] if len(dyn) == 1 else dyn,
            "radius": float(a.radius),
            "x0": [float(v) for v in (a.x0 if a.x0 is not None else (0.0,) * a.dynamics.nx)],
        }
        if a.radius_param:
            d["radius_param"] = True
        if a.goal is not None:
            d["goal"] = [float(v) for v in a.goal]
        if a.vref is not None:
            d["vref"] = float(a.vref)
        if a.path is not None:
            d["path"] = [[float(x), float(y)] for x, y in a.path]
        d["features"] = [_feature_dict(f) for f in a.features]
        agents.append(d)
    out: dict[str, Any] = {"horizon": int(spec.horizon), "dt": float(spec.dt), "agents": agents}
    if spec.pair_features:
        out["pair_features"] = [_feature_dict(pf) for pf in spec.pair_features]
    if solver_options:
        out["solver"] = {k: dict(v) for k, v in solver_options.items() if v is not None}
    return out


def save_game(
    spec: GameSpec | GameFile, path: str | Path, solver_options: Mapping | None = None
) -> Path:
    """Write ``spec`` as a game file (YAML, or JSON for a ``.json`` suffix)."""
    path = Path(path)
    data = dump_game(spec, solver_options)
    if path.suffix.lower() == ".json":
        path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    else:
        import yaml

        path.write_text(
            yaml.safe_dump(data, sort_keys=False, default_flow_style=None), encoding="utf-8"
        )
    return path


# --------------------------------------------------------------------------------------
# --set NAME=VALUE
# --------------------------------------------------------------------------------------
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
