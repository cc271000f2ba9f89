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

import json
from pathlib import Path

import click

from epo_casadi.game import PotentialGame

#: functions exported when no --function is given (cheap to build and to compile)
DEFAULT_FUNCTIONS = ("rollout", "residual", "jacobian", "energy", "gradient", "agent_costs")
EXPORT_FORMAT = "epo-export/1"


def export_game(
    game, p, out: Path, fmt: str, functions: tuple[str, ...], name: str = "epo_game"
) -> dict:
    """Write the export of ``game`` to ``out``; return the manifest (also written)."""
    from epo_casadi.errors import SpecError
    from epo_casadi.inspect import ENERGY_CONVENTION, param_summary

    if fmt not in ("casadi", "c"):
        raise SpecError("--format", f"expected 'casadi' or 'c', got {fmt!r}")
    out.mkdir(parents=True, exist_ok=True)
    funcs = [game.function(n) for n in functions]
    files = []
    if fmt == "casadi":
        for f in funcs:
            path = out / f"{f.name()}.casadi"
            f.save(str(path))
            files.append(path.name)
        build = None
    else:
        src = Path(game.generate_c(str(out), list(functions), name=name))
        files += [src.name, f"{name}.h"]
        build = f"cc -O2 -fPIC -shared {src.name} -o lib{name}.so -lm"
        (out / "BUILD.txt").write_text(
            "Build a shared library (load it with casadi.external(NAME, PATH) or link it):\n"
            f"  {build}\n"
            "Every function follows CasADi's generated-C calling convention "
            "(NAME, NAME_work, NAME_sparsity_in/out; see the header).\n"
        )
        files.append("BUILD.txt")
    manifest = {
        "format": EXPORT_FORMAT,
        "export": fmt,
        "files": files,
        "build": build,
        "energy_convention": ENERGY_CONVENTION,
        "sizes": {
            "N": game.N,
            "K": game.K,
            "dt": game.dt,
            "n_u": game.n_u,
            "n_x": game.n_x,
            "n_p": game.n_p,
            "n_r": game.n_r,
        },
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
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1, allow_nan=False) + "\n")
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
def export_cmd(game_file: Path, fmt: str, out: Path, functions: tuple[str, ...], settings):
    """Export the named functions of GAME_FILE as CasADi files or as C source."""
    from scenarios.gamefile import apply_settings, load_game

    gf = load_game(game_file)
    p = apply_settings(gf.game, gf.params, settings)
    m = export_game(gf.game, p, out, fmt, tuple(dict.fromkeys(functions or DEFAULT_FUNCTIONS)))
    click.echo(f"wrote {', '.join(m['files'])} and manifest.json to {out}")
    if m["build"]:
        click.echo(f"build: (cd {out} && {m['build']})")
