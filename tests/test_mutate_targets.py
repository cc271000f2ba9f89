"""The mutation run's map of modules to tests names files that exist.

A module split in two leaves its moved code outside the run unless the new module is
mapped too; these checks fail on a renamed or removed file and when one of the splits
listed below loses a part from the map (a new split must be added to that list).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _targets() -> dict[str, list[str]]:
    spec = importlib.util.spec_from_file_location("epo_bench_mutate", ROOT / "bench" / "mutate.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # the module's dataclasses look themselves up there
    try:
        spec.loader.exec_module(mod)
    finally:
        del sys.modules[spec.name]
    return mod.TARGETS


def test_every_target_and_its_tests_exist():
    targets = _targets()
    missing = [p for p in targets if not (ROOT / p).is_file()]
    missing += [t for tests in targets.values() for t in tests if not (ROOT / t).is_file()]
    assert missing == []


def test_split_modules_are_mutated_with_their_parent():
    targets = _targets()
    parts = {
        "solvers/nash.py": ["solvers/nash_types.py"],
        "solvers/ilq/iteration.py": ["solvers/ilq/step_rules.py", "solvers/ilq/batch_trial.py"],
        "epo_casadi/game.py": [
            "epo_casadi/game_spec.py",
            "epo_casadi/game_params.py",
            "epo_casadi/game_size.py",
        ],
    }
    for parent, children in parts.items():
        assert parent in targets
        for child in children:
            assert targets.get(child) == targets[parent], child
    safety = [
        f"solvers/control/{m}.py"
        for m in ("safety", "safety_options", "safety_geometry", "safety_filter")
    ]
    assert all(targets.get(m) == ["tests/test_safety_filter.py"] for m in safety)
