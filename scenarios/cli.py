"""The ``epo`` command line.

Subcommands live in their own modules and are imported only when used, so ``epo
--help`` stays fast and ``epo solve`` never imports torch. Toolkit errors
(:class:`epo_casadi.errors.EpoError`, file and option errors) print one line naming
the field and exit with status 2, without a traceback.
"""

from __future__ import annotations

import importlib
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


class LazyGroup(click.Group):
    def list_commands(self, ctx):
        return sorted(COMMANDS)

    def get_command(self, ctx, name):
        if name not in COMMANDS:
            return None
        target, _ = COMMANDS[name]
        mod, attr = target.split(":")
        try:
            return getattr(importlib.import_module(mod), attr)
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
        click.echo(f"error: {e.format_message()} (see 'epo {_command(argv)}--help')", err=True)
        return 2
    except click.ClickException as e:
        e.show()
        return e.exit_code
    except EpoError as e:
        click.echo(f"error: {e}", err=True)
        return 2
    except (FileNotFoundError, IsADirectoryError, PermissionError) as e:
        click.echo(f"error: {e.filename}: {e.strerror}", err=True)
        return 2
    except KeyboardInterrupt:
        click.echo("Interrupted.", err=True)
        return 130
    finally:
        warnings.showwarning = shown
    return rc if isinstance(rc, int) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
