"""Every ```python block of README.md runs as written (cvxpylayers-style README tests), and
prints what the README promises: the solver's status, the layer's status codes."""

import pathlib
import re

import pytest

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def _check_solver_block(out: str) -> None:
    # result.summary() of an LM solve: "lm: <status> (<message>); energy ..., N iterations"
    m = re.search(r"^lm: (\w+) \(.*\); energy ([-+.\deE]+), (\d+) iterations", out, re.M)
    assert m, out
    assert m.group(1) == "converged", out
    assert float(m.group(2)) > 0 and int(m.group(3)) >= 1


def _check_layer_block(out: str) -> None:
    from learning.layer import decode_status
    from solvers.result import Status

    # print(out.controls.shape, out.status, w_own.grad.abs().sum() > 0)
    m = re.search(r"torch\.Size\(\[(\d+), (\d+)\]\) tensor\(\[([\d, ]+)\]\) tensor\((\w+)\)", out)
    assert m, out
    codes = [int(c) for c in m.group(3).split(",")]
    assert int(m.group(1)) == len(codes) == 8
    # the paper setting runs exactly S = 2 steps without a tolerance: max_iter everywhere
    assert list(decode_status(codes)) == [Status.MAX_ITER] * 8
    assert m.group(4) == "True"  # gradients reached the weights


CHECKS = {"solve_lm(": _check_solver_block, "GameLayer(": _check_layer_block}


def test_readme_has_examples():
    assert BLOCKS, "README.md has no python examples"
    for key in CHECKS:  # every kind of block we check is still there
        assert any(key in b for b in BLOCKS), key


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_example_runs(index, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    exec(
        compile(BLOCKS[index], f"README.md[python block {index}]", "exec"),
        {"__name__": "__readme__"},
    )
    out = capsys.readouterr().out
    checks = [fn for key, fn in CHECKS.items() if key in BLOCKS[index]]
    assert checks, f"README python block {index} has no check of what it prints"
    for check in checks:
        check(out)
