"""What an import does not pull in: ``import learning`` and ``epo --help`` stay light.

Each check runs in a fresh interpreter and reads ``sys.modules``; no timings are asserted.
"""

from __future__ import annotations

import json
import subprocess
import sys

#: never imported by ``import learning`` nor by the layer and model modules
HEAVY = (
    "filterpy",
    "scipy.stats",
    "learning.tgl",
    "learning.control",
    "learning.planner",
    "scenarios.closed_loop",
)


def _modules(code: str, names) -> dict[str, bool]:
    """Run ``code`` in a fresh interpreter; which of ``names`` are in ``sys.modules`` then."""
    probe = (
        f"\nimport json, sys\nprint(json.dumps({{n: n in sys.modules for n in {list(names)!r}}}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code + probe], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_learning_imports_nothing_heavy():
    seen = _modules("import learning", (*HEAVY, "torch", "learning.layer", "learning.models"))
    assert not any(seen.values()), seen


def test_layer_and_models_without_the_closed_loop_or_tgl():
    code = (
        "from learning import GameLayer, ModelConfig, build_model\n"
        "import learning.data, learning.metrics, learning.baselines, learning.backbones\n"
        "assert GameLayer.__module__ == 'learning.layer'"
    )
    seen = _modules(code, (*HEAVY, "torch"))
    assert seen.pop("torch")  # the layer is torch
    assert not any(seen.values()), seen


def test_tgl_is_imported_on_first_use():
    code = (
        "import sys\n"
        "from learning.models import MODEL_KINDS, model_class\n"
        "assert 'learning.tgl' not in sys.modules\n"
        "from learning.tgl import TGLModel\n"
        "assert model_class('tgl') is TGLModel and MODEL_KINDS['tgl'] is TGLModel\n"
        "import learning\n"
        "assert learning.TGLModel is TGLModel"
    )
    assert _modules(code, ("learning.tgl",)) == {"learning.tgl": True}


def _cli(args: list[str]) -> str:
    return (
        "import contextlib, io, sys\n"
        f"sys.argv = ['epo', *{args!r}]\n"
        "from scenarios.cli import main\n"
        "buf = io.StringIO()\n"
        "with contextlib.redirect_stdout(buf):\n"
        "    try:\n"
        "        main()\n"
        "    except SystemExit as e:\n"
        "        assert e.code in (0, None), e.code\n"
        "assert 'Usage:' in buf.getvalue(), buf.getvalue()"
    )


def test_epo_help_imports_no_torch_nor_solvers():
    seen = _modules(
        _cli(["--help"]), (*HEAVY, "torch", "learning", "solvers", "osqp", "matplotlib")
    )
    assert not any(seen.values()), seen


def test_epo_train_help_imports_no_torch():
    """The learning commands' options are read without torch (only ``learning.commands``)."""
    names = (*HEAVY, "torch", "learning.layer", "learning.models", "solvers", "matplotlib")
    seen = _modules(_cli(["train", "--help"]), (*names, "learning.commands"))
    assert seen.pop("learning.commands")
    assert not any(seen.values()), seen
