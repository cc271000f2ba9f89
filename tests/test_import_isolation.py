"""The symbolic, solver and scenario layers never import torch (see STYLE.md)."""

import subprocess
import sys

import pytest


@pytest.mark.parametrize("module", ["epo_casadi", "solvers", "scenarios", "scenarios.cli"])
def test_no_torch_import(module):
    code = f"import sys, {module}; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_no_matplotlib_at_import():
    code = "import sys, epo_casadi, solvers, scenarios; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
