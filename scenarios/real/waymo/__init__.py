"""Waymo Open Motion scenarios (TFRecord files of ``Scenario`` records) as a dataset.

Reading
    :func:`read_scenarios` reads TFRecord files (:mod:`scenarios.real.tfrecord`: the
    framing and its CRC-32C checks, no TensorFlow) and parses every payload with the
    ``protobuf`` package against the schema of :mod:`scenarios.real.waymo_schema` (the
    fields listed there; others are skipped). Each record is checked: it must have a
    ``scenario_id``, timestamps 0.1 s apart (10 Hz, within 0.02 s), tracks whose state count
    equals the timestamps', a ``current_time_index`` and ``sdc_track_index`` inside them,
    ``tracks_to_predict`` indices and ``objects_of_interest`` ids of its tracks, object
    types 0..4, and at every *valid* state finite values within bounds (positions within
    10^7 m, sizes within [0, 100] m, velocities within 200 m/s). Any problem is one
    :class:`~scenarios.dataset.DatasetError` naming ``<file>:record <i>`` and the field.

Agents: interacting pairs (the paper's Waymo setting, App. F)
    ``pairs="auto"`` (default): the ``objects_of_interest`` when the record lists at least
    two (the interactive split labels exactly two), else the ``tracks_to_predict``;
    ``"interest"`` / ``"predict"`` use only that list. Every pair of the listed tracks is a
    candidate (in list order), kept when both are of the recipe's ``types`` (default all of
    vehicle, pedestrian, cyclist; the paper keeps vehicles only: ``--set types=[vehicle]``)
    and both have ``valid`` states at every step of the window. A pair with an invalid step
    on the window's grid is skipped (never interpolated), and every skip is counted in the
    manifest's ``meta.skipped``. The choice reads the lists and the flags only, no
    positions. Slot 0 is the pair's vehicle when it has one vehicle, else the first in list
    order. With ``agents`` N > 2 the other N - 2 slots are the tracks of the kept types
    valid over the whole window chosen by :func:`scenarios.real.scenes.closest_approach`
    (observed positions only; padded and masked when there are fewer).

Window and units
    One scene per pair at the record's ``current_time_index`` c: ``history`` H past steps
    and the current one, ``horizon`` T future steps, ``step`` s grid steps (0.1 s) apart:
    states ``c - H s .. c + T s``. The defaults are the paper's: s = 1 (dt 0.1 s), H = 10
    (1 s of history plus the current step), T = 80 (8 s), M = 6 modes, collisions every 5th
    step. The game's horizon is T, so s = 5 (``--set step=5``: dt 0.5 s, H = 2, T = 16,
    collisions every step, the same 0.5 s apart) is a five times shorter game for quick
    runs. States: ``(x, y, v, theta)`` with the recorded centre, the speed
    ``|(velocity_x, velocity_y)|`` and the recorded heading, unwrapped over the window
    (the current one in [-pi, pi)). ``radius`` = length / 2 at the current step (the
    paper's r = L / 2), ``length`` and ``width`` the current box.

Scene frame
    ``origin`` is the slot-0 agent's current position in the record's frame; positions,
    lanes and goal candidates are relative to it. The axes stay the record's (no rotation).

Lanes (the map input)
    Every lane centre polyline (``MapFeature.lane``) is cut into pieces of equal arc length
    at most ``lane_piece`` metres (20 m), each resampled to ``lane_points`` P points (10);
    the ``lane_count`` L (128) pieces nearest to any recorded agent's current position
    within ``lane_range`` (150 m), nearest first, are ``lanes`` ``(L, P, 2)``; fewer fill
    the first slots and ``lanes_mask`` ``(L,)`` marks them, ``lane_id`` gives each piece's
    map feature id (-1: empty). ``speed_limit`` is the limit of the lane of each agent's
    nearest piece (m/s; 0 without lanes).

Goal candidates (no future)
    A pool of map points: every lane centre and crosswalk outline resampled every
    ``goal_spacing`` metres (2 m). For agent i at position p, speed v and heading theta,
    the pool points within R = ``goal_scale`` v T dt + ``goal_margin`` (1.5 v T dt + 10 m)
    of p, thinned to ``goal_points`` G (64) by farthest-point sampling that starts at the
    pool point nearest the constant-velocity end point p + v T dt (cos theta, sin theta).
    With fewer than G points in range all are taken and the rest are points of a Vogel
    spiral of radius R around p (``goal_candidates_on_map`` False). Only the current state
    enters. Padded slots are zeros.

Splits (by scenario: a scenario's pairs stay in one split)
    The scenarios of ``--raw`` files train; of ``--val`` files validate; of ``--test``
    files test (the paper: train on the official training split, test on the validation
    split). Without ``--test`` files, a seeded share ``test_fraction`` (0.1, at least one
    scenario) of the ``--raw`` scenarios tests; without ``--val`` files a seeded share
    ``val_fraction`` (0.1, at least one when three or more remain) of the rest validates.
    So the two scenarios of the Waymo test data run end to end (one trains, one tests, no
    validation). Fewer than one training and one test scenario is refused.
"""

from ..waymo_schema import OBJECT_TYPES
from .figures import draw_record, draw_scenarios
from .maps import goal_candidates, goal_pool, lane_pieces
from .recipe import PAIR_RULES, WaymoRecipe, game_from_recipe
from .records import (
    GRID_DT,
    MPH,
    MapLine,
    ScenarioRecord,
    find_files,
    parse_scenario,
    read_scenarios,
)
from .scenario import WaymoScenario

__all__ = [
    "GRID_DT",
    "MPH",
    "OBJECT_TYPES",
    "PAIR_RULES",
    "MapLine",
    "ScenarioRecord",
    "WaymoRecipe",
    "WaymoScenario",
    "draw_record",
    "draw_scenarios",
    "find_files",
    "game_from_recipe",
    "goal_candidates",
    "goal_pool",
    "lane_pieces",
    "parse_scenario",
    "read_scenarios",
]
