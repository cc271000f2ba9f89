"""The long hostile-input walk of every ``epo`` subcommand, each case in a fresh process.

``tests/test_hostile.py`` runs the short version in-process inside ``make test``. This one
uses the same command table and files, adds more values per class, and runs every case as
``python -m scenarios.cli ...`` in its own process with a timeout, so a crash of the
interpreter (a segfault, a bus error, an out-of-memory kill) or a hang counts as a failure
too. Run from the repository root (about 15-25 minutes on 2 cores)::

    .venv/bin/python bench/hostile.py --json /tmp/hostile.json
    .venv/bin/python bench/hostile.py --only "solve,data show" --timeout 60

Every case must exit with status 2 and print one ``error:`` line on stderr and no
traceback. The report prints one line per failing case and the totals.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests import test_hostile as T  # noqa: E402

#: beyond the short suite's values: more spellings of the same classes
MORE_FLOATS = ("NaN", "+inf", "Infinity", "-Infinity", "1e400", "-1e400", "", " ", "0x10", "1,5")
MORE_INTS = ("9223372036854775808", "-9223372036854775809", "1e3", "", " ", "0x10", "2**63")
MORE_SETS = ("=1", "a==", "x={a: [1,", "x=" + "[" * 5000, "world.x=1")


def cases(world: dict) -> list[tuple[str, list[str], str]]:
    """``(label, argv, what the error line must contain)`` for every case."""
    out = []
    for words, cmd in T.LEAVES:
        import click

        for p in cmd.params:
            if not isinstance(p, click.Option) or p.is_flag:
                continue
            if isinstance(p.type, click.types.FloatParamType):
                values = T.BAD_FLOATS + MORE_FLOATS
            elif isinstance(p.type, click.types.IntParamType):
                values = T.BAD_INTS + MORE_INTS
            else:
                continue
            for v in values:
                out.append((f"{' '.join(words)} {p.opts[0]}={v!r}", [*words, p.opts[0], v], ""))
    tmp = Path(tempfile.mkdtemp(prefix="epo-hostile-out-"))
    for i, (cmd, base) in enumerate(T.BASES.items()):
        for case in T.IN_CASES.get(base.get("in"), ()):
            args = T._fill(base, world, tmp / f"in{i}{case}", IN=world[case])
            out.append((f"{cmd} <- {case}", [*cmd.split(), *args], ""))
        if "out" in base:
            for case in ("through_file", "file", "dangling"):
                args = T._fill(base, world, tmp, OUT=world[case])
                out.append((f"{cmd} -> {case}", [*cmd.split(), *args], ""))
        words = tuple(cmd.split())
        leaf = dict(T.LEAVES)[words]
        if any(isinstance(p, click.Option) and "--set" in p.opts for p in leaf.params):
            for text in ("noequals", "x=[1, 2", "no_such_key_at_all=1", *MORE_SETS):
                args = T._fill(base, world, tmp / f"set{i}")
                out.append((f"{cmd} --set {text[:30]!r}", [*words, "--set", text, *args], ""))
    return out


def run_case(argv: list[str], timeout: float) -> tuple[bool, str]:
    env = {**os.environ, "MPLBACKEND": "Agg", "EPO_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    try:
        r = subprocess.run(
            [sys.executable, "-m", "scenarios.cli", *map(str, argv)],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return False, f"ran past {timeout:g} s (a hang, or real work started)"
    lines = r.stderr.strip().splitlines()
    ok = r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: ")
    ok = ok and "Traceback" not in r.stderr
    took = time.perf_counter() - t0
    what = lines[-1] if lines else "(no output)"
    return ok, f"rc {r.returncode}, {len(lines)} lines, {took:.1f} s: {what[:160]}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds per case")
    ap.add_argument("--only", default="", help="comma-separated commands, e.g. 'solve,train'")
    ap.add_argument("--json", default=None, help="write every case's record here")
    a = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="epo-hostile-"))
    world = T.make_world(root)
    only = [c.strip() for c in a.only.split(",") if c.strip()]
    todo = [c for c in cases(world) if not only or any(c[0].startswith(o) for o in only)]
    print(f"{len(todo)} cases; files in {root}", flush=True)
    from tqdm import tqdm

    records, failed = [], 0
    bar = tqdm(todo, unit="case", disable=not sys.stderr.isatty())
    for label, argv, _ in bar:
        ok, what = run_case(argv, a.timeout)
        records.append({"case": label, "argv": list(map(str, argv)), "ok": ok, "result": what})
        if not ok:
            failed += 1
            bar.write(f"FAIL {label}: {what}")
        bar.set_postfix(failed=failed)
    print(f"{len(todo) - failed} of {len(todo)} cases refused in one line; {failed} failed")
    if a.json:
        Path(a.json).write_text(json.dumps(records, indent=1))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
