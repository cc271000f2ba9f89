"""Every ```python block of README.md runs as written (cvxpylayers-style README tests), and
prints what the README promises: the solver's status, the layer's status codes, a verified
dataset, the solvers' agreement and the Nash certificate."""

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


def _check_data_block(out: str) -> None:
    # print(report.counts); print(verify(...).summary()); print({name: shape})
    m = re.search(r"\{'train': (\d+), 'val': (\d+), 'test': (\d+)\}", out)
    assert m, out
    counts = [int(c) for c in m.groups()]
    assert all(c > 0 for c in counts), out  # every split got main games
    v = re.search(r"^ok: data/rpi-tiny: (\d+) shards, (\d+) samples", out, re.M)
    assert v, out  # verify() found no problem
    assert int(v.group(2)) == sum(counts), out
    # future: (samples, M = 2 modes, N = 2 agents, T = 40 steps, 4 states)
    assert f"'future': ({counts[0]}, 2, 2, 40, 4)" in out, out


def _check_compare_block(out: str) -> None:
    rows = re.findall(r"^(\w+): (\w+) \(.*\); energy ([-+.\deE]+),", out, re.M)
    energy = {name: float(e) for name, _, e in rows}
    assert sorted(energy) == ["ilq", "ipopt", "lm", "sqp"], out
    assert all(status == "converged" for _, status, _ in rows), out
    # LM, IPOPT and SQP reach the same minimizer (printed to 4 decimals); iLQ's feedback
    # equilibrium is another point with a higher potential
    assert abs(energy["ipopt"] - energy["lm"]) < 2e-4 and abs(energy["sqp"] - energy["lm"]) < 2e-4
    assert energy["ilq"] > energy["lm"] + 1e-3, out
    assert re.search(r"^passes \(", out, re.M), out  # the LM solution is a local Nash eq.


CHECKS = {
    "solve_lm(": _check_solver_block,
    "GameLayer(": _check_layer_block,
    "load_split(": _check_data_block,
    "nash_certificate(": _check_compare_block,
}


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
