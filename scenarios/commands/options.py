"""Options shared by the commands that read game files (``solve``, ``inspect``, ``export``,
``compare``).

:func:`allow_import_option` adds ``--allow-import MODULE`` (repeatable; commas allowed):
the modules whose ``module:Class`` names the game files may import, with their
submodules, besides those of ``$EPO_ALLOW_IMPORT``. Every other ``module:Class`` in a file
is refused before it is imported (:func:`epo_casadi.registry.allow_imports`).
"""

from __future__ import annotations

import functools

import click

__all__ = ["allow_import_option"]


def allow_import_option(command):
    """Decorator of a click command's function: adds ``--allow-import`` and runs the
    command inside :func:`epo_casadi.registry.allow_imports` of the given modules (the
    function itself takes no new argument)."""

    @functools.wraps(command)
    def run(*args, allow_import: tuple[str, ...] = (), **kwargs):
        from epo_casadi.registry import allow_imports

        with allow_imports(*allow_import, where="--allow-import"):
            return command(*args, **kwargs)

    return click.option(
        "--allow-import",
        "allow_import",
        multiple=True,
        metavar="MODULE",
        help="Let the game file import MODULE (and its submodules) for a 'module:Class' type "
        "(repeatable; also $EPO_ALLOW_IMPORT). Other imports are refused.",
    )(run)
