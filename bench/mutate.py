"""Mutation testing of the core modules: does the test suite notice one-line bugs?

Not a test and not part of ``make test``. Run from the repository root::

    .venv/bin/python bench/mutate.py --sample 150 --seed 16     # the run in docs/mutation.md
    .venv/bin/python bench/mutate.py --list | head               # every mutant, no test run
    .venv/bin/python bench/mutate.py --ids 17,342 --seed 16      # re-run chosen mutants

What it does
    1. Parses every target module (``TARGETS``) with :mod:`ast` and lists every *mutant*:
       one small change at one place (operators below). Mutant ids are positions in this
       deterministic list (files in ``TARGETS`` order, nodes in source order).
    2. Draws a seeded sample (``random.Random(seed).sample``) of ``--sample`` ids, sorted.
    3. Copies the repository (without ``.venv``, ``.git``, caches, data and results) to a
       fresh folder under ``/tmp``; the working tree is never written to.
    4. Runs the mapped test modules once unmutated (they must pass), then for each mutant
       writes the mutated file into the copy, runs ``pytest -x -q`` on the mapped test
       modules with a timeout, and restores the file. A mutant is *killed* when the tests
       fail (or time out), *survived* when they pass.
    5. Prints one line per mutant and the survival rate; ``--json`` writes every record.

Operators (each applied at one node)
    ``cmp``: ``<``/``<=``, ``>``/``>=``, ``==``/``!=``, ``is``/``is not``, ``in``/``not in``
    swapped; ``arith``: ``+``/``-``, ``*``/``/``, ``**`` -> ``*``, ``&``/``|`` (mask
    combination) swapped, also in augmented assignments; ``const``: a float ``c`` -> ``1000 c``
    (``0.0`` -> ``1.0``; a 1000x looser or larger tolerance), an int ``n`` -> ``n + 1``, a
    negative index literal ``-n`` -> ``0`` (the last step read as the first), ``True``/``False``
    swapped; ``unary``: ``-x`` -> ``x``, ``~mask`` -> ``mask``, ``not x`` -> ``x``;
    ``bool``: ``and``/``or`` swapped; ``return``: ``return v`` -> ``return 0.5 * (v)`` for
    numeric-looking values (calls, arithmetic, subscripts, names); ``mask``: a call of
    ``where``/``masked_fill`` replaced by its value argument (the mask is not applied);
    ``minmax``: ``argmin``/``argmax``, ``min``/``max``, ``amin``/``amax`` swapped (e.g. the
    worst mode chosen instead of the best).

Docstrings, strings, annotations, f-strings and ``__all__`` are never mutated.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: module -> the test modules that claim to cover it
TARGETS: dict[str, list[str]] = {
    "learning/metrics.py": ["tests/test_metrics.py", "tests/test_losses.py"],
    "learning/losses.py": ["tests/test_losses.py", "tests/test_options.py"],
    "learning/layer.py": ["tests/test_layer.py"],
    "solvers/lm.py": ["tests/test_lm.py", "tests/test_structured.py"],
    "solvers/gn.py": ["tests/test_lm.py", "tests/test_structured.py"],
    "solvers/structured.py": ["tests/test_structured.py"],
    "solvers/nash.py": ["tests/test_nash.py"],
    "solvers/nash_types.py": ["tests/test_nash.py"],
    "solvers/multimodal.py": ["tests/test_multimodal.py"],
    "solvers/result.py": ["tests/test_result.py"],
    "solvers/ipopt.py": ["tests/test_ipopt.py"],
    **{
        f"solvers/ilq/{m}.py": [
            "tests/test_ilq.py",
            "tests/test_ilq_results.py",
            "tests/test_ilq_regularization.py",
            "tests/test_options.py",
        ]
        for m in (
            "options",
            "quadratize",
            "riccati",
            "rollout",
            "iteration",
            "step_rules",
            "batch_trial",
            "kinks",
            "solver",
        )
    },
    **{
        f"solvers/control/{m}.py": ["tests/test_safety_filter.py"]
        for m in ("safety", "safety_options", "safety_geometry", "safety_filter")
    },
    "solvers/batch.py": ["tests/test_lm.py"],
    **{
        f"epo_casadi/{m}.py": ["tests/test_game.py", "tests/test_gamefile.py"]
        for m in ("game", "game_spec", "game_params", "game_size")
    },
    "epo_casadi/features.py": ["tests/test_game.py", "tests/test_goals.py"],
    "epo_casadi/dynamics.py": ["tests/test_game.py"],
    "epo_casadi/errors.py": ["tests/test_game.py", "tests/test_gamefile.py"],
}

IGNORE = {".venv", ".git", "__pycache__", ".pytest_cache", ".ruff_cache", "results", "data"}

CMP_SWAP = {
    ast.Lt: ast.LtE,
    ast.LtE: ast.Lt,
    ast.Gt: ast.GtE,
    ast.GtE: ast.Gt,
    ast.Eq: ast.NotEq,
    ast.NotEq: ast.Eq,
    ast.Is: ast.IsNot,
    ast.IsNot: ast.Is,
    ast.In: ast.NotIn,
    ast.NotIn: ast.In,
}
BIN_SWAP = {
    ast.Add: ast.Sub,
    ast.Sub: ast.Add,
    ast.Mult: ast.Div,
    ast.Div: ast.Mult,
    ast.Pow: ast.Mult,
    ast.BitAnd: ast.BitOr,
    ast.BitOr: ast.BitAnd,
}
AUG_TEXT = {ast.Add: "+=", ast.Sub: "-=", ast.Mult: "*=", ast.Div: "/=", ast.BitAnd: "&=",
            ast.BitOr: "|="}  # fmt: skip


MINMAX = {"argmin": "argmax", "argmax": "argmin", "min": "max", "max": "min",
          "amin": "amax", "amax": "amin"}  # fmt: skip


@dataclass(frozen=True)
class Mutant:
    id: int
    file: str
    line: int
    op: str
    before: str
    after: str
    start: int  # character offsets in the file's text
    end: int


def _offsets(text: str) -> list[int]:
    out, pos = [0], 0
    for line in text.splitlines(keepends=True):
        pos += len(line)
        out.append(pos)
    return out


def _skip_nodes(tree: ast.AST) -> set[int]:
    """ids of nodes never mutated: docstrings, annotations, f-strings, ``__all__``."""
    skip: set[int] = set()

    def mark(node):
        for n in ast.walk(node):
            skip.add(id(n))

    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                mark(body[0])
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if node.returns is not None:
                mark(node.returns)
            for a in node.args.args + node.args.kwonlyargs + node.args.posonlyargs:
                if a.annotation is not None:
                    mark(a.annotation)
        if isinstance(node, ast.AnnAssign):
            mark(node.annotation)
        if isinstance(node, ast.JoinedStr):
            mark(node)
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            mark(node)
    return skip


def _numeric_return(v: ast.AST) -> bool:
    if isinstance(v, ast.Call):
        f = v.func
        name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
        return not name[:1].isupper() and name not in {"dict", "list", "tuple", "str", "set"}
    return isinstance(v, (ast.BinOp, ast.Subscript, ast.Name)) and not (
        isinstance(v, ast.Name) and v.id in {"None", "self", "cls"}
    )


def mutants_of(rel: str, start_id: int = 0) -> list[Mutant]:
    text = (ROOT / rel).read_text()
    tree = ast.parse(text)
    skip = _skip_nodes(tree)
    offs = _offsets(text)
    out: list[Mutant] = []

    def span(node):
        return offs[node.lineno - 1] + node.col_offset, offs[
            node.end_lineno - 1
        ] + node.end_col_offset

    def add(node, op, new_src, start=None, end=None):
        s, e = span(node) if start is None else (start, end)
        before = text[s:e]
        if new_src == before:
            return
        out.append(Mutant(start_id + len(out), rel, node.lineno, op, before, new_src, s, e))

    def unparse_with(node, **changes):
        clone = ast.parse(ast.unparse(node), mode="eval").body
        for k, v in changes.items():
            setattr(clone, k, v)
        return "(" + ast.unparse(clone) + ")"

    negative_literals: set[int] = set()
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.UnaryOp)
            and isinstance(node.op, ast.USub)
            and isinstance(node.operand, ast.Constant)
            and type(node.operand.value) in (int, float)
        ):
            negative_literals.add(id(node.operand))

    for node in ast.walk(tree):
        if id(node) in skip or not hasattr(node, "lineno"):
            continue
        if isinstance(node, ast.Compare):
            for i, op in enumerate(node.ops):
                if type(op) in CMP_SWAP:
                    ops = list(node.ops)
                    ops[i] = CMP_SWAP[type(op)]()
                    add(node, "cmp", unparse_with(node, ops=ops))
        elif isinstance(node, ast.BinOp) and type(node.op) in BIN_SWAP:
            add(node, "arith", unparse_with(node, op=BIN_SWAP[type(node.op)]()))
        elif isinstance(node, ast.AugAssign) and type(node.op) in AUG_TEXT:
            t_end = offs[node.target.end_lineno - 1] + node.target.end_col_offset
            v_start = offs[node.value.lineno - 1] + node.value.col_offset
            seg = text[t_end:v_start]
            old = AUG_TEXT[type(node.op)]
            new = AUG_TEXT.get(BIN_SWAP.get(type(node.op)))
            if new and old in seg:
                add(node, "arith", seg.replace(old, new, 1), t_end, v_start)
        elif isinstance(node, ast.UnaryOp):
            if isinstance(node.op, (ast.USub, ast.Invert, ast.Not)):
                if isinstance(node.operand, ast.Constant):
                    if type(node.operand.value) is int:
                        add(node, "const", "0")
                    continue
                add(node, "unary", "(" + ast.unparse(node.operand) + ")")
        elif isinstance(node, ast.BoolOp):
            new = ast.Or() if isinstance(node.op, ast.And) else ast.And()
            add(node, "bool", unparse_with(node, op=new))
        elif isinstance(node, ast.Constant) and id(node) not in negative_literals:
            v = node.value
            if isinstance(v, bool):
                add(node, "const", repr(not v))
            elif isinstance(v, float):
                add(node, "const", repr(v * 1000.0) if v != 0 else "1.0")
            elif isinstance(v, int):
                add(node, "const", repr(v + 1))
        elif isinstance(node, ast.Return) and node.value is not None:
            if _numeric_return(node.value):
                s, e = span(node.value)
                add(node.value, "return", f"0.5 * ({text[s:e]})", s, e)
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            if name in MINMAX:  # the other extreme: the worst mode instead of the best
                s, e = span(f)
                add(f, "minmax", MINMAX[name], e - len(name), e)
            if name == "where" and len(node.args) == 3:
                add(node, "mask", "(" + ast.unparse(node.args[1]) + ")")
            elif name == "masked_fill" and isinstance(f, ast.Attribute):
                add(node, "mask", "(" + ast.unparse(f.value) + ")")
    out.sort(key=lambda m: (m.start, m.end, m.op, m.after))
    return [Mutant(start_id + i, *tuple(asdict(m).values())[1:]) for i, m in enumerate(out)]


def all_mutants() -> list[Mutant]:
    out: list[Mutant] = []
    for rel in TARGETS:
        out += mutants_of(rel, len(out))
    return out


def copy_repo(dest: Path) -> None:
    def ignore(d, names):
        return [n for n in names if n in IGNORE or n.endswith((".pyc", ".egg-info"))]

    shutil.copytree(ROOT, dest, ignore=ignore, symlinks=True)


def run_tests(repo: Path, tests: list[str], timeout: float) -> tuple[str, float, str]:
    env = dict(os.environ, PYTHONPATH=str(repo), PYTHONDONTWRITEBYTECODE="1")
    env.setdefault("EPO_THREADS", "1")
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "timeout", time.perf_counter() - t0, ""
    tail = (p.stdout + p.stderr).strip().splitlines()
    return (
        ("passed" if p.returncode == 0 else "failed"),
        time.perf_counter() - t0,
        (tail[-1] if tail else ""),
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sample", type=int, default=150, help="mutants drawn (0: all)")
    ap.add_argument("--seed", type=int, default=16)
    ap.add_argument("--ids", default="", help="comma-separated mutant ids instead of a sample")
    ap.add_argument("--timeout", type=float, default=180.0, help="seconds per mutant")
    ap.add_argument(
        "--rerun",
        default="",
        help="a --json file of an earlier run: re-run its survivors (matched by file, operator "
        "and text, nearest line, so that edits elsewhere in the source do not matter)",
    )
    ap.add_argument("--only", default="", help="comma-separated target modules (default: all)")
    ap.add_argument("--list", action="store_true", help="list the mutants and exit")
    ap.add_argument("--json", default="", help="write every record to this file")
    args = ap.parse_args(argv)

    muts = all_mutants()
    if args.only:
        keep = set(args.only.split(","))
        unknown = keep - set(TARGETS)
        if unknown:
            ap.error(f"--only: unknown module(s) {sorted(unknown)}; known: {list(TARGETS)}")
        muts = [m for m in muts if m.file in keep]  # ids stay those of the full list
    if args.list:
        for m in muts:
            print(f"{m.id:5d} {m.file}:{m.line} {m.op}: {m.before!r} -> {m.after!r}")
        return 0
    if args.rerun:
        chosen = []
        for r in json.loads(Path(args.rerun).read_text()):
            if r["verdict"] != "passed":
                continue
            same = [
                m
                for m in muts
                if (m.file, m.op, m.before, m.after)
                == (r["file"], r["op"], r["before"], r["after"])
            ]
            if not same:
                print(f"#{r['id']} {r['file']}:{r['line']}: no longer in the source", flush=True)
                continue
            chosen.append(min(same, key=lambda m: abs(m.line - r["line"])))
    elif args.ids:
        by_id = {m.id: m for m in muts}
        chosen = [by_id[int(i)] for i in args.ids.split(",")]
    elif args.sample and args.sample < len(muts):
        chosen = sorted(random.Random(args.seed).sample(muts, args.sample), key=lambda m: m.id)
    else:
        chosen = muts
    print(f"{len(muts)} mutants in {len(TARGETS)} modules; running {len(chosen)} "
          f"(seed {args.seed})", flush=True)  # fmt: skip

    work = Path(tempfile.mkdtemp(prefix="epo-mutate-"))
    repo = work / "repo"
    copy_repo(repo)
    records = []
    try:
        broken = set()
        for rel in sorted({m.file for m in chosen}):  # baseline: the mapped tests pass
            verdict, secs, tail = run_tests(repo, TARGETS[rel], args.timeout)
            print(f"baseline {rel}: {verdict} in {secs:.0f} s", flush=True)
            if verdict != "passed":
                print(f"  unmutated tests fail ({tail}): its mutants are skipped", flush=True)
                broken.add(rel)
        for m in chosen:
            if m.file in broken:
                records.append({**asdict(m), "verdict": "skipped", "seconds": 0.0})
                continue
            path = repo / m.file
            original = path.read_text()
            mutated = original[: m.start] + m.after + original[m.end :]
            try:
                ast.parse(mutated)
            except SyntaxError:
                verdict, secs, tail = "invalid", 0.0, "syntax error"
            else:
                path.write_text(mutated)
                try:
                    verdict, secs, tail = run_tests(repo, TARGETS[m.file], args.timeout)
                finally:
                    path.write_text(original)
            killed = verdict in ("failed", "timeout")
            records.append({**asdict(m), "verdict": verdict, "seconds": round(secs, 1)})
            mark = "killed " if killed else verdict.upper()
            print(f"{mark:8s} #{m.id} {m.file}:{m.line} {m.op}: {m.before!r} -> {m.after!r}"
                  f" ({secs:.0f} s)", flush=True)  # fmt: skip
    finally:
        shutil.rmtree(work, ignore_errors=True)
    valid = [r for r in records if r["verdict"] not in ("invalid", "skipped")]
    skipped = len(records) - len(valid)
    if skipped:
        print(f"{skipped} mutants skipped (invalid, or their unmutated tests failed)")
    survived = [r for r in valid if r["verdict"] == "passed"]
    rate = len(survived) / max(len(valid), 1)
    print(f"\n{len(valid)} mutants run, {len(valid) - len(survived)} killed, "
          f"{len(survived)} survived: survival rate {rate:.1%}")  # fmt: skip
    for r in survived:
        print(f"  survived #{r['id']} {r['file']}:{r['line']} {r['op']}: "
              f"{r['before']!r} -> {r['after']!r}")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(records, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
