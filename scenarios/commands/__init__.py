"""The ``epo`` subcommands below the learning layer, one module each (click commands).

:data:`scenarios.cli.COMMANDS` names each command's ``module:attribute``; the module is
imported only when its command runs or shows its help. ``solve``, ``inspect``, ``export``,
``demo``, ``compare``, ``generate``, ``data`` and ``simulate`` live here;
:mod:`scenarios.commands.options` holds the options they share for reading game files.
The commands that need torch (``train``, ``evaluate``, ``show-predictions``,
``show-weights``, ``pipeline``) live in ``learning.commands``.
"""
