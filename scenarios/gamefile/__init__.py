"""Game files: a potential game written down in YAML or JSON.

A game file holds one :class:`epo_casadi.GameSpec` (agents, features, horizon, step)
plus optional solver options. The schema, with every field, is documented in
``docs/gamefiles.md``; in short::

    horizon: 40                 # K, number of steps (integer >= 1)
    dt: 0.1                     # step length in seconds (> 0)
    agents:                     # at least one
      - name: robot             # letters, digits, '_' ; unique
        dynamics: unicycle      # or {type: bicycle, wheelbase: 2.7}
        radius: 0.25            # metres, >= 0 (default 0.25)
        radius_param: false     # true: radius is the default of a parameter radius.<name>
        x0: [0, -3, 1, 1.57]    # initial state, nx numbers (required)
        goal: [0, 3]            # required by the 'goal' feature
        vref: 1.0               # required by 'reference_velocity'
        path: [[0, 0], [1, 0]]  # polyline, required by 'path'
        features:
          - {type: goal, weight: 3}
          - {type: velocity_bound, weight: 5, lower: 0, upper: 2}
    pair_features:
      - {type: collision, weight: 10, every: 1}
    solver:                     # options per registered solver (solvers.registry)
      lm: {steps: 200}          # solvers.lm.LMOptions fields
      ipopt: {max_iter: 500}    # solvers.ipopt.IpoptOptions fields
      ilq: {max_iter: 200}      # solvers.ilq.ILQOptions fields
      sqp: {collision: true}    # solvers.sqp.SQPOptions fields

Every problem in a file raises :class:`epo_casadi.SpecError` whose ``field`` is the
path of the offending entry (``agents[1].radius``, ``agents[0].features[2].upper``,
``solver.lm.steps``) and whose message says what was expected. Unknown keys are
errors, never ignored. Numbers must be finite (YAML ``.nan``/``.inf`` are rejected;
leave a bound out instead of writing an infinite one). YAML anchors, aliases and merge
keys (``<<: *base``; the mapping's own keys override the merged ones) are read; data
nested deeper than :data:`MAX_DEPTH` or expanding to more than :data:`MAX_VALUES` values
is refused.

Public API: :func:`load_game` (path), :func:`parse_game` (an already parsed mapping),
:class:`GameFile`, :func:`dump_game` / :func:`save_game` (the inverse) and
:func:`apply_settings` (the CLI's ``--set NAME=VALUE``).
"""

from __future__ import annotations

from epo_casadi.game import MAX_HORIZON as MAX_HORIZON

from .checks import MAX_DEPTH as MAX_DEPTH
from .checks import MAX_VALUES as MAX_VALUES
from .checks import WEIGHT_RULE as WEIGHT_RULE
from .parameters import apply_settings
from .parsing import GameFile, parse_game
from .reading import EXAMPLES, example_path, load_game
from .reading import EXAMPLES_DIR as EXAMPLES_DIR
from .writing import dump_game, save_game

__all__ = [
    "GameFile",
    "load_game",
    "parse_game",
    "dump_game",
    "save_game",
    "apply_settings",
    "example_path",
    "EXAMPLES",
]
