"""Generated highway interaction data in the exiD release layout, from highway-env.

The real exiD recordings cannot be downloaded here, so this package records traffic of
highway-env (1.12.1; reactive IDM / MOBIL vehicles) on highway entries and exits and writes
it **in the exiD file format** (``data/NN_tracks.csv``, ``NN_tracksMeta.csv``,
``NN_recordingMeta.csv`` and one lanelet2 map per location,
``maps/lanelet2/<id>_<name>.osm``), so that the very reader and extraction of
:mod:`scenarios.exid` run on it unchanged.

Locations (:data:`LOCATIONS`; "maps", one can be held out as the test map)
    ``0 onramp-2``: two lanes, an on-ramp with a 180 m acceleration lane, 100 km/h.
    ``1 offramp-3``: three lanes, an off-ramp with a 150 m deceleration lane, 120 km/h.
    ``2 onramp-3``: three lanes, an on-ramp with a 250 m acceleration lane, no limit.
    ``3 offramp-2``: two lanes, an off-ramp with a 120 m deceleration lane, no limit.
    Main lanes run along +x at ``y = -i w`` (lane 0 the left-most); the ramp is on the
    right: a straight ramp and a sine-shaped converging (diverging) lane join the
    auxiliary (acceleration / deceleration) lane, the extra right-most lane of the middle
    section. Each location has its own UTM origin (zone 32, around Cologne).

Traffic (per recording, seeded)
    highway-env ``IDMVehicle`` s (IDM longitudinal, MOBIL lane changes, highway-env's
    lane-following steering and kinematic bicycle) with one change (:func:`driver_class`):
    *mandatory* lane changes for the ramp traffic. On-ramp vehicles leave the acceleration
    lane towards the main road as soon as the gap is safe for them and their new follower
    (MOBIL's safety criterion with a braking limit that grows towards the lane's end) and
    brake for its end if they cannot; exiting vehicles move right lane by lane before the
    exit and take the deceleration lane (one not on it 40 m before its end misses the exit
    and drives on); a lane change that became unsafe while the vehicle is still on its own
    lane is called off. Through traffic may not enter the auxiliary lane;
    otherwise it changes lanes by MOBIL (discretionary). Randomized per vehicle: class
    (car 85 %, truck 15 %; trucks only in the two right-most lanes and on ramps), length
    and width (cars 4.2-5.2 x 1.75-2.0 m, trucks 10-16.5 x 2.5 m), desired speed (cars
    0.85-1.15 x the limit, capped at 45 m/s; trucks 22-25 m/s), IDM time headway
    (1.0-2.0 s), comfortable acceleration, jam distance (2-4 m; the IDM runs on bumper-to-bumper
    gaps, where highway-env's measures between centres), MOBIL politeness (0-0.5) and threshold
    (0.1-0.4 m/s^2). Vehicles enter at the upstream ends (Poisson arrivals, 900-1600
    veh/h/lane, ramps 500-1000 veh/h, 30 % of the main-road vehicles at an exit take it)
    with a free entry gap, and leave at the downstream ends. The road fills during
    ``warmup`` s before frame 0. Speeds never go below zero (braking ends at standstill).
    Crashes are detected with each vehicle's own length and width (highway-env's crash
    pre-check radius is set from them); a vehicle in a crash (rare) is removed at once (its
    track ends), as real data has none.

Recording (exiD layout, :mod:`scenarios.exid` docstring)
    ``frame_rate`` Hz (25, as exiD) = the simulation step. Positions and headings are the
    simulated ones; velocities and accelerations are the central differences of the
    recorded positions (as a tracker's would be), ``lon``/``lat`` components in the
    vehicle's frame; ``laneletId`` is highway-env's current lane (the nearest), also
    ``latLaneCenterOffset``, ``laneWidth``, ``lonLaneletPos``, ``laneletLength``,
    ``traveledDistance``, ``trackLifetime``. Maps: every highway-env lane is a lanelet
    whose left and right bounds are ways of nodes with ``lat`` / ``lon`` only (WGS84,
    inverse UTM of the local coordinates plus the origin); adjacent lanes share their
    boundary way; ``speed_limit`` tag in km/h where the location has a limit.

Limits (what real exiD has and this does not): no sensor noise or tracking errors (real
tracks are smoothed detections), no motorcycles, vans or buses, no curved main roads or
cloverleaf loops, no weaving sections with on- and off-ramp together, IDM/MOBIL drivers
(no cooperative yielding beyond MOBIL politeness, no forced merges at standstill beyond
waiting at the lane end), and highway-env's kinematic model for trucks as for cars.
On-ramp vehicles that find no gap wait at the end of the acceleration lane and queue behind
each other, bumper gaps of 2-4 m (docs/exid.md: the test map's scenes).

Deterministic for a seed: recording ``i`` uses ``SeedSequence(seed, spawn_key=(i,))``;
existing complete recordings are kept (a stopped run resumes).

Output folder (:func:`generate_raw`)
    One run at a time writes to a folder (its ``.lock``; a second run is refused at once),
    and the folder records its recipe in ``recipe.json`` (kind ``highway-raw``: the seed
    and every :class:`HighwayOptions` field but ``recordings``) before anything else is
    written. A rerun with the same recipe resumes; one with another seed, duration or
    option is refused naming the differing fields, so recordings of two recipes never mix.
    Recording ``i`` depends only on the recipe and ``i``, so a rerun with *more*
    ``recordings`` extends the set (the finished recordings are kept); one with fewer than
    the folder already holds is refused. A non-empty folder without ``recipe.json`` (files
    of something else, or of a version of epo that recorded no recipe) is refused.
    Every file is written atomically; a recording whose files cannot all be written
    (a full disk) leaves none of them.

Limits (checked before any work; :data:`MAX_RECORDINGS`, :data:`MAX_DURATION`,
:data:`MAX_WARMUP`, :data:`MAX_FRAMES`)
    at most 10,000 recordings, 3,600 s recorded per recording and 600 s of warm-up, and
    100,000 recorded frames per recording (``duration x frame_rate``: one recording is
    held in memory until it is written).
"""

from __future__ import annotations

from .drivers import driver_class, size_vehicle
from .options import MAX_DURATION, MAX_FRAMES, MAX_RECORDINGS, MAX_WARMUP, HighwayOptions
from .raw_set import _FILES as _FILES
from .raw_set import _record_files as _record_files
from .raw_set import generate_raw, raw_recipe
from .recording import record
from .road import LOCATIONS, Location, build_network, write_map

__all__ = [
    "Location",
    "LOCATIONS",
    "HighwayOptions",
    "build_network",
    "driver_class",
    "size_vehicle",
    "write_map",
    "record",
    "generate_raw",
    "raw_recipe",
    "MAX_RECORDINGS",
    "MAX_DURATION",
    "MAX_WARMUP",
    "MAX_FRAMES",
]
