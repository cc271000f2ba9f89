"""The exiD release layout: a reader for its recordings and lanelet2 maps, and the paper's
sample extraction (App. E "exiD", App. F.3) into the toolkit's dataset format.

Release layout (exiD v2, the levelXdata family shared with inD / rounD / uniD)
    ``DIR/data/NN_tracks.csv``, ``NN_tracksMeta.csv``, ``NN_recordingMeta.csv`` per
    recording ``NN`` (the three CSVs may also lie directly in ``DIR``), and one lanelet2
    map per location, ``DIR/maps/lanelet2/<locationId>_<name>.osm`` (or ``<locationId>.osm``;
    also looked for in ``DIR/maps`` and ``DIR``). The column names are those of the
    format documentation of the levelXdata datasets (ika, RWTH Aachen: "inD/rounD/uniD
    format 1.1", shared by exiD) and of ika's ``drone-dataset-tools`` reader
    (``src/tracks_import.py``: ``read_tracks`` / ``read_tracks_meta`` /
    ``read_recording_meta``); exiD adds the lane columns (``laneletId``,
    ``latLaneCenterOffset``, ``laneWidth``, ``lonLaneletPos``, ... , where a vehicle on
    two lanelets has ``"id1;id2"``). Columns read:

    ``NN_tracks.csv`` (one row per track and frame): ``recordingId, trackId, frame,
    xCenter, yCenter`` (m, local frame = UTM minus the recording's ``xUtmOrigin,
    yUtmOrigin``), ``heading`` (deg, counter-clockwise from +x), ``width, length`` (m),
    ``xVelocity, yVelocity`` (m/s), ``xAcceleration, yAcceleration`` (m/s^2),
    ``lonVelocity, latVelocity, lonAcceleration, latAcceleration``; optional
    ``laneletId`` (first id of a ``;`` list; empty or ``-1``: none; without the column
    the lanelet is found on the map).
    ``NN_tracksMeta.csv`` (one row per track): ``recordingId, trackId, initialFrame,
    finalFrame, numFrames, width, length, class``.
    ``NN_recordingMeta.csv`` (one row): ``recordingId, locationId, frameRate,
    xUtmOrigin, yUtmOrigin``; optional ``speedLimit`` (m/s; ``-1`` or missing: none),
    ``latLocation, lonLocation, duration, numTracks, ...``.

    Every problem is a :class:`~scenarios.dataset.DatasetError` whose ``where`` is
    ``<file>:<column>`` (a missing file or column, a cell with its line, a track whose row
    count differs from its ``numFrames``, a frame rate that does not divide the sampling
    step). Every table goes through one check, :func:`read_table` with the
    :class:`Column` s of :data:`TRACKS_TABLE`, :data:`TRACKS_META_TABLE`,
    :data:`RECORDING_META_TABLE`: each cell read must be a finite number (not ``nan``,
    ``inf``, text or empty) within its bounds, a whole number where an integer is meant.
    The columns not listed are not read. Then: recordingMeta has one row, the
    ``recordingId`` of every row is the file name's ``NN``, a track has one tracksMeta
    row and one tracks row per frame, its frames run from ``initialFrame`` to
    ``finalFrame`` without gaps, and ``laneletId`` holds ids (``id`` or ``id1;id2``, empty
    or ``-1``: none).

Bounds (inclusive; each a module constant)
    ``recordingId``, ``locationId``: integers 0 .. 32767 (:data:`MAX_ID`, stored as int16;
    also the ``NN`` of the file names); ``trackId``: 0 .. 2^31 - 1; frames (``frame``,
    ``initialFrame``, ``finalFrame``): 0 .. 10^7 (:data:`MAX_FRAME`), ``numFrames`` >= 1;
    ``xCenter``, ``yCenter``: within 10^6 m of the local origin (:data:`MAX_POSITION`);
    ``xUtmOrigin``, ``yUtmOrigin``: within 10^7 m (:data:`MAX_UTM`, the extent of UTM
    coordinates); ``heading``: -360 .. 360 deg; ``width``: (0, 10] m, ``length``: (0, 50]
    m (tracks and tracksMeta); every velocity component within 100 m/s
    (:data:`MAX_SPEED`), every acceleration component within 100 m/s^2
    (:data:`MAX_ACCELERATION`); ``frameRate``: 1 .. 1000 Hz; ``speedLimit``: -1 .. 100 m/s
    (<= 0: none); ``latLocation``: -90 .. 90, ``lonLocation``: -180 .. 180 deg. A
    recording of which the resampled arrays would exceed :data:`MAX_GRID_CELLS` tracks x
    samples is refused before they are built, and one of which no sample can be made
    (fewer than ``agents`` tracks span a scene's ``history + 1 + horizon`` samples: all
    tracks too short, a ``frameRate`` too high) is refused naming the recording.

Maps: a light OSM parse, not the ``lanelet2`` package
    ``lanelet2`` has wheels on PyPI (1.2.3, Linux x86-64 manylinux_2_31 only; none for
    macOS or Windows) and brings a compiled Boost stack; what the extraction needs of a
    map is small: every lanelet's left and right bound (``way`` s of ``node`` s), its
    centre line (the mean of the bounds resampled to the same arc fractions), width,
    speed limit, successors and left / right neighbours. That is ~150 lines of
    ``xml.etree`` here, runs everywhere the toolkit runs, and writes back trivially for the
    generator (:mod:`scenarios.highway`). Conventions of lanelet2's OSM format: a
    ``relation`` with ``type=lanelet`` and members ``left`` / ``right`` (ways); node
    positions from ``local_x`` / ``local_y`` tags when every node has them, else from
    ``lat`` / ``lon`` projected to UTM (WGS84, the zone of the recording's
    ``lonLocation`` or of the nodes, :func:`utm_from_latlon`) minus the recording's
    ``xUtmOrigin`` / ``yUtmOrigin``; left neighbour = the lanelet whose right bound is
    this one's left bound (the same way), successors = lanelets whose centre starts
    within 0.5 m of this one's end in a similar heading; the speed limit from the
    lanelet's ``speed_limit`` tag (km/h unless ``mph``), else a ``speed_limit``
    regulatory element it references (``sign_type`` ``de274-<kmh>`` or ``speed_limit``),
    else the recording's ``speedLimit``, else 130 km/h (the German advisory speed).
    Lanelets of subtype ``walkway``, ``crosswalk``, ``bicycle_lane``, ``stairs`` are left
    out. The result is a :class:`LaneletMap`: a :class:`scenarios.maps.RoadMap` (lane ids
    are the lanelet ids as strings) plus the neighbour relations.
    Checks: node ``lat`` within 90 deg, ``lon`` within 180 deg, ``local_x`` / ``local_y``
    within 10^7 m (all finite) and a finite UTM position; ids and references integers;
    a speed limit in (0, 500] km/h; a lanelet's bounds at most :data:`MAX_LANE_WIDTH`
    (30 m) apart on average. A map is used for a recording only if every track's first,
    middle and last position lies within :data:`MAP_DISTANCE` (200 m) of one of its
    lanelets (:func:`check_map_near`; the map of another location, lat/lon swapped or a
    wrong UTM origin put the lanes km away), and each lane of a sample (the agent's
    current lanelet and its neighbours, continued) passes within 200 m of its agent;
    otherwise the error names the map file and the distance.

Extraction (App. E, one work unit per recording)
    1. Resampling: every ``step = dt * frameRate`` frames (``dt = 0.2`` s, 5 frames at
       exiD's 25 Hz), on the global frame grid (``frame % step == 0``); a ``frameRate``
       that does not give an integer step is an error.
    2. Lane changes: a vehicle changes lane between two samples when its lanelet changes
       to one that is neither a successor nor a predecessor of the previous one (across
       lanes: a neighbour, or a jump over several). Where ``laneletId`` is missing, the
       lanelet is the one whose centre line is nearest within its half width.
    3. Scenes (``N = 4``): for every vehicle with a lane change at sample ``c``, every
       current sample ``t`` on the grid of ``stride`` samples such that the change lies in
       ``(t - H, t + T]`` and the vehicle exists from ``t - H`` to ``t + T``; its agents are
       that vehicle (agent 0) and the ``N - 1`` vehicles nearest to it at ``t`` (within
       ``neighbour_range``) that exist over the same window. A scene with fewer is
       skipped; the same set of agents at the same ``t`` is kept once. With
       ``max_scenes_per_recording`` > 0, that many scenes, evenly spread, are kept.
    4. Sample: history ``H + 1 = 10`` states (1.8 s), the future ``T = 20`` states (4 s),
       state ``(x, y, v, theta)``: ``xCenter, yCenter``, ``v = |(xVelocity, yVelocity)|``,
       ``theta = heading`` (rad, continuous per agent, the current one in ``(-pi, pi]``).
       Fixed global orientation (paper App. F: the origin is fixed), translated so that
       the scene's origin (the mean current position of its agents, in ``frame``) is 0.
    5. Modes: real data has one future: ``future`` ``(M = 5, N, T, 4)`` holds it in slot
       ``gt_mode = 0`` and copies it in the other slots with ``mode_valid`` False (the
       RPI / left-turn convention for unavailable modes).
    6. Map input: per agent, its current lane and its left and right neighbours (where one
       is missing, the current lane's boundary on that side, as the paper's goal decoder
       does), each a *corridor* (the lanelet continued through its straightest
       predecessors and successors) windowed from ``lane_behind`` m behind to
       ``lane_ahead`` m ahead of the agent (clamped to the corridor's ends, so every point
       lies on the map), resampled to ``P = lane_points``:
       ``lanes`` ``(3 N, P, 2)`` (agent-major: left, current, right). ``paths``
       ``(N, P, 2)``: the current lane (the game's lane feature), ``vref`` ``(N,)``: its
       speed limit. ``goal_candidates`` ``(N, G = 60, 2)``: ``G / 3`` points on each of
       the three from ``goal_near * v T dt`` to ``goal_far * v T dt + goal_margin`` m ahead
       of the agent (``goal_candidate_lane``: 0 left, 1 current, 2 right;
       ``goal_candidate_on_lane`` False on a boundary).
    7. Kept per agent: ``length``, ``width``, ``vehicle_class`` (index in
       :data:`CLASSES`), ``radius = length / 2`` (the paper's ``r = L / 2``),
       ``track_id``, ``lane_change`` (in the window); per sample ``recording``,
       ``location``, ``frame`` (current frame).

Splits (paper: the test set is a different map)
    Recordings of ``test_locations`` (default ``(0,)``, the paper's "map 0") are the test
    split; of the others, a seeded ``val_fraction`` of the recordings (at least one) is
    val, the rest train. No location is in test and in train / val.

Game (App. F.3, exiD): ``N = 4`` unicycles, ``K = T = 20``, ``dt = 0.2``; per agent the
terminal goal (the goal decoder's), ``lane`` (:class:`~epo_casadi.features.Path` on
``paths``), ``vref`` (:class:`~epo_casadi.features.ReferenceVelocity` on ``vref``),
velocity, acceleration, jerk, turn rate, turn acceleration; collision every 5th step.
Each agent's collision radius is a parameter of the game (``AgentSpec.radius_param``,
block ``radius.v<i>``, default ``radius`` = 2.5 m, ``L / 2`` of a 5 m car), and ours fills
it with the sample's ``L / 2`` (field ``radius``), the paper's ``r = L / 2``
(``radius_per_agent``; False: every agent has ``radius``, a number of the game. Datasets
written before this field existed keep that game: :func:`learning.data.dataset_game`).
"""

from __future__ import annotations

from .lanelet import (
    DEFAULT_SPEED_LIMIT,
    SKIP_SUBTYPES,
    LaneletMap,
    check_map_near,
    find_map,
    lane_changes,
    map_distance,
    read_lanelet_map,
)
from .recipe import ExidRecipe, raw_digest
from .recording import Recording, find_recordings, read_recording
from .scenario import CLASSES, ExidScenario
from .tables import (
    FRAME_RATE,
    MAP_DISTANCE,
    MAX_ACCELERATION,
    MAX_FRAME,
    MAX_GRID_CELLS,
    MAX_ID,
    MAX_LANE_WIDTH,
    MAX_LENGTH,
    MAX_POSITION,
    MAX_SPEED,
    MAX_SPEED_LIMIT,
    MAX_TRACK_ID,
    MAX_UTM,
    MAX_WIDTH,
    RECORDING_META_COLUMNS,
    RECORDING_META_TABLE,
    TRACK_COLUMNS,
    TRACKS_META_COLUMNS,
    TRACKS_META_TABLE,
    TRACKS_TABLE,
    Column,
    read_table,
)
from .utm import latlon_from_utm, utm_from_latlon, utm_zone

__all__ = [
    "CLASSES",
    "TRACK_COLUMNS",
    "TRACKS_META_COLUMNS",
    "RECORDING_META_COLUMNS",
    "Recording",
    "LaneletMap",
    "ExidRecipe",
    "ExidScenario",
    "find_recordings",
    "read_recording",
    "read_lanelet_map",
    "read_table",
    "Column",
    "TRACKS_TABLE",
    "TRACKS_META_TABLE",
    "RECORDING_META_TABLE",
    "check_map_near",
    "map_distance",
    "find_map",
    "raw_digest",
    "utm_zone",
    "utm_from_latlon",
    "latlon_from_utm",
    "lane_changes",
    "DEFAULT_SPEED_LIMIT",
    "SKIP_SUBTYPES",
    "MAX_ID",
    "MAX_TRACK_ID",
    "MAX_FRAME",
    "MAX_POSITION",
    "MAX_UTM",
    "MAX_SPEED",
    "MAX_ACCELERATION",
    "MAX_LENGTH",
    "MAX_WIDTH",
    "FRAME_RATE",
    "MAX_SPEED_LIMIT",
    "MAP_DISTANCE",
    "MAX_LANE_WIDTH",
    "MAX_GRID_CELLS",
]
