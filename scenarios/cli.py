"""The ``epo`` command line.

Subcommands live in their own modules and are imported only when used, so ``epo
--help`` stays fast and ``epo solve`` never imports torch. Toolkit errors
(:class:`epo_casadi.errors.EpoError`, file and option errors) print one line naming
the field and exit with status 2, without a traceback.
"""

from __future__ import annotations

import importlib
import math
import os
import sys
import warnings

# Small dense solves (a few hundred unknowns) are slower with threaded BLAS on a busy
# machine; our batching parallelizes over problems instead. Set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import click  # noqa: E402

from epo_casadi.errors import EpoError  # noqa: E402

# name -> "module:attribute" of a click command or group
COMMANDS: dict[str, tuple[str, str]] = {
    "solve": ("scenarios.commands.solve:solve", "Solve a game file with LM or IPOPT."),
    "inspect": (
        "scenarios.commands.inspect:inspect_cmd",
        "Show term formulas, dynamics, parameters, sparsity (--json).",
    ),
    "export": (
        "scenarios.commands.export:export_cmd",
        "Export a game's functions as CasADi files or C source.",
    ),
    "demo": ("scenarios.commands.demo:demo", "Run the main job on built-in defaults."),
    "compare": (
        "scenarios.commands.compare:compare",
        "Compare solvers on games and starts: table, figures, scaling.",
    ),
    "generate": ("scenarios.commands.generate:generate", "Generate a dataset (e.g. rpi)."),
    "data": ("scenarios.commands.data:data", "Verify or show a generated dataset."),
    "simulate": (
        "scenarios.commands.simulate:simulate",
        "Closed-loop episodes: plan, track, drive.",
    ),
    "train": (
        "learning.commands:train_cmd",
        "Train ours (epo), V-LSTM + SC (sc) or V-LSTM (vlstm).",
    ),
    "evaluate": (
        "learning.commands:evaluate_cmd",
        "Score runs and CV on a split: the paper's table.",
    ),
    "show-predictions": (
        "learning.commands:show_cmd",
        "Draw one sample's predicted modes and weights.",
    ),
    "show-weights": (
        "learning.commands:show_weights_cmd",
        "Spider plots of ours' weights per mode and agent.",
    ),
    "pipeline": (
        "learning.commands:pipeline_cmd",
        "Small end to end: data, train, evaluate, figures.",
    ),
}


#: the largest integer any option takes (what a seed, a count or an index can be stored as)
MAX_INT = 2**63 - 1


class _Checked:
    """Mixed into every number type of every command (:func:`harden`): a float option
    refuses ``nan`` / ``inf`` (a range check lets NaN through) and an integer option
    refuses values beyond :data:`MAX_INT`, at parse time, as one usage error line."""

    def convert(self, value, param, ctx):
        v = super().convert(value, param, ctx)
        if isinstance(v, float) and not math.isfinite(v):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        if isinstance(v, int) and not isinstance(v, bool) and abs(v) > MAX_INT:
            self.fail(f"{value!r} is too large (at most {MAX_INT}).", param, ctx)
        return v


_CHECKED: dict[type, type] = {}


def harden(cmd: click.Command) -> click.Command:
    """Give every int / float option and argument of ``cmd`` (and its subcommands) the
    checks of :class:`_Checked`, so no command can forget them. Returns ``cmd``."""
    if getattr(cmd, "_epo_hardened", False):
        return cmd
    for p in cmd.params:
        t = p.type
        if isinstance(t, (click.types.IntParamType, click.types.FloatParamType)) and not (
            isinstance(t, _Checked)
        ):
            cls = type(t)
            if cls not in _CHECKED:
                _CHECKED[cls] = type(f"Checked{cls.__name__}", (_Checked, cls), {})
            new = object.__new__(_CHECKED[cls])
            new.__dict__.update(t.__dict__)
            p.type = new
    if isinstance(cmd, click.Group):
        for sub in cmd.commands.values():
            harden(sub)
    cmd._epo_hardened = True
    return cmd


class LazyGroup(click.Group):
    """The ``epo`` group: lists the subcommands of :data:`COMMANDS` and imports a
    subcommand's module only when it is run or its help is shown, so ``epo --help`` stays
    fast and ``epo solve`` never imports torch.

    A command whose module cannot be imported (a broken install, a missing optional
    dependency) becomes one that prints what is missing and exits with status 1.
    """

    def list_commands(self, ctx):
        return sorted(COMMANDS)

    def get_command(self, ctx, name):
        if name not in COMMANDS:
            return None
        target, _ = COMMANDS[name]
        mod, attr = target.split(":")
        try:
            return harden(getattr(importlib.import_module(mod), attr))
        except (ImportError, AttributeError) as e:  # pragma: no cover - a broken install
            msg = f"'{name}' is not available in this install: {e}"

            @click.command(name=name, help=COMMANDS[name][1])
            def unavailable():
                raise click.ClickException(msg)

            return unavailable

    def format_commands(self, ctx, formatter):
        rows = [(n, COMMANDS[n][1]) for n in self.list_commands(ctx)]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup)
@click.version_option(package_name="epo")
def cli():
    """epo: energy-based potential games for joint motion forecasting and control."""


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings at the command line: one line naming what happened, no source location."""
    click.echo(f"warning: {message}", err=True)


def _command(argv: list[str] | None) -> str:
    """The subcommand named on the command line (``"solve "``), or ``""``."""
    args = sys.argv[1:] if argv is None else [str(a) for a in argv]
    return f"{args[0]} " if args and args[0] in COMMANDS else ""


def _os_error(e: OSError) -> str:
    """One line for an operating-system error: the path, then the system's reason."""
    import errno

    reason = e.strerror or str(e) or type(e).__name__
    if e.errno == errno.ENOTDIR and e.filename:
        from pathlib import Path

        for parent in Path(e.filename).parents:
            if parent.exists() and not parent.is_dir():
                reason = f"{parent} is a file, not a folder"
                break
    where = f"{e.filename}: " if e.filename else ""
    return f"{where}{reason}"


def main(argv: list[str] | None = None) -> int:
    """Console entry point: runs the CLI, turns toolkit errors into one-line messages."""
    shown = warnings.showwarning
    warnings.showwarning = _one_line_warning
    try:
        rc = cli.main(args=argv, prog_name="epo", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("Aborted.", err=True)
        return 130
    except click.UsageError as e:  # a bad option or argument: one line, like every input error
        path = e.ctx.command_path if e.ctx is not None else f"epo {_command(argv)}".strip()
        click.echo(f"error: {e.format_message()} (see '{path} --help')", err=True)
        return 2
    except click.ClickException as e:
        e.show()
        return e.exit_code
    except EpoError as e:
        click.echo(f"error: {e}", err=True)
        return 2
    except OSError as e:  # a file the command could not read or write: one line, like the rest
        click.echo(f"error: {_os_error(e)}", err=True)
        return 2
    except KeyboardInterrupt:
        click.echo("Interrupted.", err=True)
        return 130
    finally:
        warnings.showwarning = shown
    return rc if isinstance(rc, int) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
