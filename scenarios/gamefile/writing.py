"""Writing a game back as a game file: :func:`dump_game` (the plain mapping, the inverse
of :func:`parse_game`) and :func:`save_game` (YAML or JSON on disk)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from epo_casadi.errors import SpecError
from epo_casadi.features import Feature, PairFeature
from epo_casadi.game import GameSpec

from .parsing import GameFile


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
