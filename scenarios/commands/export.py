"""``epo export GAME --format {casadi,c} --out DIR``: take a game to another program.

``casadi``: every chosen named function of the game (:meth:`PotentialGame.function`) as
``DIR/<name>.casadi`` (``casadi.Function.save``; load with ``casadi.Function.load``).
``c``: one C file with a header (``DIR/epo_game.c``, ``DIR/epo_game.h``,
:meth:`PotentialGame.generate_c`) and the line that builds a shared library from it.
Both write ``DIR/manifest.json``: the functions with their inputs and outputs (names and
sizes), the parameter vector's blocks with the file's values (``--set`` applied), sizes
and the energy convention, so a caller knows what to pass as ``p``.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from pathlib import Path

import click

from epo_casadi.errors import OutputError
from epo_casadi.game import PotentialGame
from scenarios.commands.options import allow_import_option

#: functions exported when no --function is given (cheap to build and to compile)
DEFAULT_FUNCTIONS = ("rollout", "residual", "jacobian", "energy", "gradient", "agent_costs")
EXPORT_FORMAT = "epo-export/1"


def export_game(
    game, p, out: Path, fmt: str, functions: tuple[str, ...], name: str = "epo_game"
) -> dict:
    """Write the export of ``game`` to ``out``; return the manifest (also written).

    Everything is refused before any build that cannot be written or would not fit: an
    unknown format, a game whose Jacobian or Hessian is too large to build
    (:func:`epo_casadi.game.check_size_estimate`), an ``out`` that is a file, a dangling
    link or inside a file. The files are written into a hidden folder inside ``out``,
    flushed to disk and checked complete (CasADi writes its files itself and does not
    report a full disk), then renamed into place, manifest last; any failure is one
    :class:`epo_casadi.errors.OutputError` and leaves no file of this export behind.
    """
    from epo_casadi.errors import SpecError
    from epo_casadi.game import check_size_estimate
    from scenarios.files import check_output_dir, ensure_dir

    if fmt not in ("casadi", "c"):
        raise SpecError("--format", f"expected 'casadi' or 'c', got {fmt!r}")
    if not name.isidentifier():
        raise SpecError("name", f"expected a C identifier, got {name!r}")
    check_size_estimate(game.spec, functions)
    out = Path(out)
    created = not out.exists()
    ensure_dir(check_output_dir(out))
    try:
        stage = Path(tempfile.mkdtemp(dir=out, prefix=".export-"))
    except OSError as e:
        _cleanup(None, out, created)
        raise OutputError(out, e.strerror or type(e).__name__) from None
    try:
        manifest = _write_export(game, p, stage, fmt, functions, name)
        for f in [*manifest["files"], "manifest.json"]:
            os.replace(stage / f, out / f)
    except OSError as e:
        _cleanup(stage, out, created)
        if isinstance(e, OutputError):
            raise OutputError(out / Path(e.path).name, e.reason) from None
        raise OutputError(out, _reason(e)) from None
    except BaseException:
        _cleanup(stage, out, created)
        raise
    _cleanup(stage, None, False)
    return manifest


def _reason(e: OSError) -> str:
    return "no space left on the device" if e.errno == errno.ENOSPC else (e.strerror or str(e))


def _cleanup(stage: Path | None, out: Path | None, created: bool) -> None:
    """Remove the staging folder, and ``out`` when this export created it (left empty)."""
    if stage is not None:
        shutil.rmtree(stage, ignore_errors=True)
    if out is not None and created:
        try:
            out.rmdir()
        except OSError:
            pass


def _complete(path: Path, c_source: bool) -> None:
    """Flush a file CasADi wrote to disk; :class:`OutputError` if it is incomplete.

    CasADi's writers do not report a failed write (a full disk leaves a truncated file):
    the file is synced (a late write error shows there), a C file or header must end with
    its closing ``#endif`` and a ``.casadi`` file must load back.
    """
    import casadi as ca

    try:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
            size = os.fstat(fd).st_size
            tail = b""
            if c_source and size:
                os.lseek(fd, max(0, size - 64), os.SEEK_SET)
                tail = os.read(fd, 64)
        finally:
            os.close(fd)
    except OSError as e:
        raise OutputError(path, _reason(e)) from None
    if c_source:
        ok = tail.rstrip().endswith(b"#endif")
    else:
        try:
            ca.Function.load(str(path))
            ok = True
        except RuntimeError:
            ok = False
    if not ok:
        try:
            full = os.statvfs(path.parent).f_bavail == 0
        except OSError:
            full = False
        raise OutputError(path, "no space left on the device" if full else "written incompletely")


def _write_export(game, p, stage: Path, fmt: str, functions, name: str) -> dict:
    from epo_casadi.inspect import ENERGY_CONVENTION, param_summary
    from epo_casadi.inspect.report import game_sizes
    from scenarios.files import write_atomic

    funcs = [game.function(n) for n in functions]
    files = []
    if fmt == "casadi":
        for f in funcs:
            path = stage / f"{f.name()}.casadi"
            f.save(str(path))
            _complete(path, c_source=False)
            files.append(path.name)
        build = None
    else:
        src = Path(game.generate_c(str(stage), list(functions), name=name))
        for f in (src, stage / f"{name}.h"):
            _complete(f, c_source=True)
        files += [src.name, f"{name}.h"]
        build = f"cc -O2 -fPIC -shared {src.name} -o lib{name}.so -lm"
        write_atomic(
            stage / "BUILD.txt",
            "Build a shared library (load it with casadi.external(NAME, PATH) or link it):\n"
            f"  {build}\n"
            "Every function follows CasADi's generated-C calling convention "
            "(NAME, NAME_work, NAME_sparsity_in/out; see the header).\n",
        )
        files.append("BUILD.txt")
    manifest = {
        "format": EXPORT_FORMAT,
        "export": fmt,
        "files": files,
        "build": build,
        "energy_convention": ENERGY_CONVENTION,
        "sizes": game_sizes(game),
        "agents": list(game.agent_names),
        "functions": [
            {
                "name": f.name(),
                "inputs": [
                    {"name": f.name_in(i), "shape": list(f.size_in(i))} for i in range(f.n_in())
                ],
                "outputs": [
                    {"name": f.name_out(i), "shape": list(f.size_out(i)), "nnz": f.nnz_out(i)}
                    for i in range(f.n_out())
                ],
            }
            for f in funcs
        ],
        "params": [
            {k: b[k] for k in ("name", "start", "size", "entries", "values")}
            for b in param_summary(game, p)
        ],
        "p": [float(v) for v in p],
    }
    write_atomic(stage / "manifest.json", json.dumps(manifest, indent=1, allow_nan=False) + "\n")
    return manifest


@click.command("export")
@click.argument("game_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["casadi", "c"]),
    required=True,
    help="casadi: casadi.Function.save files; c: C source with a header and a build line.",
)
@click.option(
    "--out", required=True, type=click.Path(file_okay=False, path_type=Path), help="Directory."
)
@click.option(
    "--function",
    "functions",
    multiple=True,
    type=click.Choice(PotentialGame.FUNCTIONS),
    help=f"A named function to export (repeatable; default: {', '.join(DEFAULT_FUNCTIONS)}).",
)
@click.option(
    "--set",
    "settings",
    multiple=True,
    metavar="NAME=VALUE",
    help="Replace a parameter in the manifest's p (repeatable).",
)
@allow_import_option
def export_cmd(game_file: Path, fmt: str, out: Path, functions: tuple[str, ...], settings):
    """Export the named functions of GAME_FILE as CasADi files or as C source."""
    from scenarios.gamefile import apply_settings, load_game

    gf = load_game(game_file)
    p = apply_settings(gf.game, gf.params, settings)
    m = export_game(gf.game, p, out, fmt, tuple(dict.fromkeys(functions or DEFAULT_FUNCTIONS)))
    click.echo(f"wrote {', '.join(m['files'])} and manifest.json to {out}")
    if m["build"]:
        click.echo(f"build: (cd {out} && {m['build']})")
