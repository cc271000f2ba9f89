"""Waymo Open Motion reader (scenarios/real/tfrecord.py, waymo_schema.py, waymo.py) and the
``waymo`` training preset: TFRecord framing and CRC-32C against published test vectors and a
bitwise reference, corrupt and truncated files refused naming the record, records that are
not Scenarios, the pair rule and the valid-flag rule, the window, lanes and goal candidates
against hand-computed values on small files the tests write, no future in the choice; on
../shared/realdata/waymo when present: both shipped files read and one scene checked against
the raw states, and generate -> train --preset waymo -> evaluate -> show-predictions."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from scenarios.dataset import DatasetError, load_split, read_manifest
from scenarios.real import tfrecord as tfr
from scenarios.real.waymo import (
    MPH,
    WaymoRecipe,
    WaymoScenario,
    game_from_recipe,
    parse_scenario,
    read_scenarios,
)
from scenarios.real.waymo_schema import message_class, scenario_class
from tests.helpers import cli, one_error_line

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "waymo"
FILES = ("motion_data_one_scenario.tfrecord", "womd_scenario_input.tfrecord")


# --------------------------------------------------------------------------------------
# small scenarios written with the schema
# --------------------------------------------------------------------------------------
def _track(msg, tid, kind, xy, heading, vel, length, width=2.0, invalid=()):
    t = msg.tracks.add(id=tid, object_type=kind)
    for k, (x, y) in enumerate(xy):
        t.states.add(
            center_x=x,
            center_y=y,
            center_z=0.5,
            length=length,
            width=width,
            height=1.5,
            heading=heading[k] if np.ndim(heading) else heading,
            velocity_x=vel[0],
            velocity_y=vel[1],
            valid=k not in invalid,
        )


def _line(points):
    return [message_class("MapPoint")(x=float(x), y=float(y), z=0.0) for x, y in points]


#: lane 100 along y = -2 from x = -45 to 155 (25 mph), lane 101 along x = 52 from y = -60 to
#: 60 (35 mph), both points 0.5 m apart; a road edge, a road line, a crosswalk
LANE100 = np.stack([np.arange(-45.0, 155.01, 0.5), np.full(401, -2.0)], 1)
LANE101 = np.stack([np.full(241, 52.0), np.arange(-60.0, 60.01, 0.5)], 1)
CROSSWALK = np.array([[18.0, -3.0], [22.0, -3.0], [22.0, 3.0], [18.0, 3.0]])

K = np.arange(91)


def tiny_scenario(sid="s-a", interest=(), predict=(1, 0, 2), shift_future=0.0) -> bytes:
    """91 steps at 10 Hz, current index 10. Tracks (index: id, type):
    0: 7 vehicle along +x at 10 m/s from (0, 0), length 4;
    1: 3 vehicle along +y at 5 m/s from (50, -40), length 5;
    2: 11 pedestrian along -y at 1 m/s from (20, 5), length 0.6, invalid at step 30;
    3: 12 cyclist standing at (30, 30), length 1.8.
    ``shift_future`` moves every position after the current step by that many metres in x."""
    m = scenario_class()(scenario_id=sid, current_time_index=10, sdc_track_index=0)
    m.timestamps_seconds.extend((0.1 * K).tolist())
    fut = np.where(K > 10, shift_future, 0.0)
    _track(m, 7, 1, np.stack([1.0 * K + fut, 0 * K], 1), 0.0, (10.0, 0.0), 4.0)
    _track(m, 3, 1, np.stack([50 + fut, -40 + 0.5 * K], 1), math.pi / 2, (0.0, 5.0), 5.0)
    _track(m, 11, 2, np.stack([20 + fut, 5 - 0.1 * K], 1), -math.pi / 2, (0.0, -1.0), 0.6,
           0.5, invalid=(30,))  # fmt: skip
    _track(m, 12, 3, np.stack([30 + 0 * K + fut, 30 + 0 * K], 1), 0.0, (0.0, 0.0), 1.8, 0.6)
    m.objects_of_interest.extend(interest)
    for i in predict:
        m.tracks_to_predict.add(track_index=i, difficulty=1)
    f = m.map_features.add(id=100)
    f.lane.speed_limit_mph = 25.0
    f.lane.polyline.extend(_line(LANE100))
    f.lane.exit_lanes.extend([101])
    f = m.map_features.add(id=101)
    f.lane.speed_limit_mph = 35.0
    f.lane.polyline.extend(_line(LANE101))
    f.lane.entry_lanes.extend([100])
    f = m.map_features.add(id=200)
    f.road_edge.type = 1
    f.road_edge.polyline.extend(_line([[-45, -6], [155, -6]]))
    f = m.map_features.add(id=300)
    f.road_line.type = 1
    f.road_line.polyline.extend(_line([[-45, 0], [155, 0]]))
    f = m.map_features.add(id=400)
    f.crosswalk.polygon.extend(_line(CROSSWALK))
    return m.SerializeToString()


def write_tiny(path: Path, **kw) -> Path:
    """A file of two scenarios: s-a (tracks to predict 1, 0, 2) and s-b (objects of interest
    12 and 7)."""
    return tfr.write_records(
        path, [tiny_scenario(**kw), tiny_scenario("s-b", interest=(12, 7), **kw)]
    )


# --------------------------------------------------------------------------------------
# TFRecord framing and CRC-32C
# --------------------------------------------------------------------------------------
def _crc_bitwise(data: bytes) -> int:
    """CRC-32C one bit at a time (the definition, no table)."""
    c = 0xFFFFFFFF
    for b in data:
        c ^= b
        for _ in range(8):
            c = (c >> 1) ^ (0x82F63B78 if c & 1 else 0)
    return c ^ 0xFFFFFFFF


def test_crc32c_known_vectors_and_the_bitwise_definition():
    assert tfr.crc32c(b"123456789") == 0xE3069283  # the CRC catalogue's check value
    assert tfr.crc32c(b"") == 0
    assert tfr.crc32c(bytes(32)) == 0x8A9136AA  # RFC 3720 B.4: 32 bytes of zeros
    assert tfr.crc32c(b"\xff" * 32) == 0x62A8AB43  # ... 32 bytes of 0xff
    assert tfr.crc32c(bytes(range(32))) == 0x46DD794E  # ... 32 incrementing bytes
    rng = np.random.default_rng(0)
    for n in (1, 3, 2047, 2048, 2053, 9000, 70001):  # both paths, odd tails
        d = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert tfr.crc32c(d) == _crc_bitwise(d), n
        assert tfr.crc32c(d[n // 3 :], tfr.crc32c(d[: n // 3])) == _crc_bitwise(d)
    # the TFRecord mask, written out: rotate right by 15, add 0xa282ead8
    c = 0xE3069283
    assert tfr.masked_crc32c(b"123456789") == (((c >> 15) | (c << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def test_framing_round_trip(tmp_path):
    payloads = [b"", b"abc", bytes(range(256)) * 20]
    p = tfr.write_records(tmp_path / "a.tfrecord", payloads)
    raw = p.read_bytes()
    assert len(raw) == sum(16 + len(x) for x in payloads)
    # the first header by hand: length 0, then masked CRCs of 8 zero bytes and of b""
    assert raw[:8] == bytes(8)
    assert struct.unpack("<I", raw[8:12])[0] == tfr.masked_crc32c(bytes(8))
    assert struct.unpack("<I", raw[12:16])[0] == tfr.masked_crc32c(b"")
    recs = list(tfr.iter_records(p))
    assert [r.payload for r in recs] == payloads
    assert [r.index for r in recs] == [0, 1, 2]
    assert [r.offset for r in recs] == [0, 16, 35]
    assert tfr.read_record(p, 35, 2) == payloads[2]
    assert list(tfr.iter_records(tfr.write_records(tmp_path / "e.tfrecord", []))) == []


def _corrupt(path: Path, at: int) -> Path:
    b = bytearray(path.read_bytes())
    b[at] ^= 0x01
    path.write_bytes(bytes(b))
    return path


def test_a_corrupt_payload_byte_is_refused_naming_the_record(tmp_path):
    p = tfr.write_records(tmp_path / "a.tfrecord", [b"first", b"second record", b"third"])
    _corrupt(p, 21 + 12 + 3)  # inside record 1's payload (record 1 starts at byte 21)
    with pytest.raises(DatasetError) as e:
        list(tfr.iter_records(p))
    assert e.value.where == f"{p}:record 1"
    assert "payload's CRC" in e.value.message and "byte 21" in e.value.message
    # a corrupt length is the length's CRC
    q = tfr.write_records(tmp_path / "b.tfrecord", [b"first", b"second record"])
    _corrupt(q, 21 + 2)
    with pytest.raises(DatasetError, match="length's CRC") as e:
        list(tfr.iter_records(q))
    assert e.value.where.endswith("record 1")
    # a corrupt stored CRC of the payload is a payload CRC failure too
    r = tfr.write_records(tmp_path / "c.tfrecord", [b"first"])
    _corrupt(r, 12 + 5 + 1)
    with pytest.raises(DatasetError, match="record 0.*payload's CRC"):
        list(tfr.iter_records(r))


def test_truncated_files_and_huge_lengths_are_refused(tmp_path):
    good = tfr.write_records(tmp_path / "a.tfrecord", [b"x" * 40, b"y" * 40]).read_bytes()
    for cut, words in ((56 + 30, "payload bytes"), (56 + 5, "header has 5 of 12"), (len(good) - 1, "payload bytes")):  # fmt: skip
        p = tmp_path / f"cut{cut}.tfrecord"
        p.write_bytes(good[:cut])
        with pytest.raises(DatasetError) as e:
            list(tfr.iter_records(p))
        assert e.value.where == f"{p}:record 1" and "truncated" in e.value.message, e.value
        assert words in e.value.message
    head = struct.pack("<Q", 2**40)
    p = tmp_path / "huge.tfrecord"
    p.write_bytes(head + struct.pack("<I", tfr.masked_crc32c(head)) + b"z" * 100)
    with pytest.raises(DatasetError, match=r"record 0.*over the limit"):
        list(tfr.iter_records(p))
    with pytest.raises(DatasetError, match="record 4.*no record at this offset"):
        tfr.read_record(tmp_path / "a.tfrecord", len(good), 4)


def test_crc_numpy_path_agrees_on_a_megabyte():
    """The chunked numpy path against the byte-at-a-time table path on 1 MB."""
    d = np.random.default_rng(1).integers(0, 256, 2**20, dtype=np.uint8).tobytes()
    assert tfr.crc32c(d) == tfr._update_bytes(0xFFFFFFFF, d) ^ 0xFFFFFFFF


# --------------------------------------------------------------------------------------
# records
# --------------------------------------------------------------------------------------
def test_schema_reads_back_what_was_written():
    rec = parse_scenario(tiny_scenario(), "f", 3, 99)
    assert (rec.scenario_id, rec.current, rec.index, rec.offset) == ("s-a", 10, 3, 99)
    assert rec.track_ids.tolist() == [7, 3, 11, 12]
    assert rec.object_type.tolist() == [1, 1, 2, 3]
    assert rec.states.shape == (4, 91, 9) and rec.valid.shape == (4, 91)
    assert rec.valid.sum(axis=1).tolist() == [91, 91, 90, 91] and not rec.valid[2, 30]
    np.testing.assert_allclose(rec.states[1, 10, :2], [50.0, -35.0])
    np.testing.assert_allclose(rec.states[1, 10, [3, 6, 7, 8]], [5.0, math.pi / 2, 0, 5], 1e-6)
    assert rec.predict == ((1, 1), (0, 1), (2, 1)) and rec.interest == ()
    kinds = [(m.id, m.kind) for m in rec.map]
    assert kinds == [(100, "lane"), (101, "lane"), (200, "road_edge"), (300, "road_line"), (400, "crosswalk")]  # fmt: skip
    lane = rec.map[0]
    assert lane.exit == (101,) and lane.speed_limit_mph == 25.0 and lane.points.shape == (401, 3)
    assert rec.map[1].entry == (100,)


def test_records_that_are_not_scenarios_are_refused(tmp_path):
    point = message_class("MapPoint")(x=1.0, y=2.0).SerializeToString()  # valid protobuf
    p = tfr.write_records(tmp_path / "x.tfrecord", [tiny_scenario(), point])
    with pytest.raises(DatasetError, match="record 1: not a Waymo Scenario: no scenario_id"):
        read_scenarios([p])
    q = tfr.write_records(tmp_path / "y.tfrecord", [b"\xff\xff\xff\xff"])
    with pytest.raises(DatasetError, match=r"y.tfrecord:record 0: not a Waymo Scenario protocol"):
        read_scenarios([q])
    empty = tfr.write_records(tmp_path / "z.tfrecord", [])
    with pytest.raises(DatasetError, match="no records"):
        read_scenarios([empty])


def test_bad_fields_name_the_record_and_the_field(tmp_path):
    m = scenario_class().FromString(tiny_scenario())
    m.tracks[1].states[4].center_x = float("nan")
    with pytest.raises(DatasetError, match=r"record 0: tracks\[1\].states\[4\].center_x"):
        parse_scenario(m.SerializeToString(), "f")
    m = scenario_class().FromString(tiny_scenario())
    m.tracks[2].states[30].center_x = float("nan")  # an invalid state: not read
    parse_scenario(m.SerializeToString(), "f")
    m = scenario_class().FromString(tiny_scenario())
    m.tracks_to_predict.add(track_index=9)
    with pytest.raises(DatasetError, match=r"tracks_to_predict\[3\].track_index: expected 0 .. 3"):
        parse_scenario(m.SerializeToString(), "f")
    m = scenario_class().FromString(tiny_scenario())
    m.timestamps_seconds[50] = 5.3
    with pytest.raises(DatasetError, match=r"timestamps_seconds\[50\]: expected steps of 0.1 s"):
        parse_scenario(m.SerializeToString(), "f")
    m = scenario_class().FromString(tiny_scenario())
    del m.tracks[3].states[-1]
    with pytest.raises(DatasetError, match=r"tracks\[3\].states: 90 states, expected 91"):
        parse_scenario(m.SerializeToString(), "f")
    m = scenario_class().FromString(tiny_scenario())
    m.tracks[0].object_type = 9
    with pytest.raises(DatasetError, match=r"tracks\[0\].object_type: expected 0 .. 4"):
        parse_scenario(m.SerializeToString(), "f")
    # a window longer than the record
    p = tfr.write_records(tmp_path / "a.tfrecord", [tiny_scenario()])
    with pytest.raises(DatasetError, match="record 0: current_time_index: the window needs 11"):
        WaymoScenario.from_raw([p], history=11)


# --------------------------------------------------------------------------------------
# pairs, window, lanes, goal candidates
# --------------------------------------------------------------------------------------
def test_pairs_and_the_valid_flag_rule(tmp_path):
    p = write_tiny(tmp_path / "t.tfrecord")
    sc = WaymoScenario.from_raw([p])
    # s-a: tracks to predict 1, 0, 2 -> (1, 0) kept; (1, 2) and (0, 2) have the pedestrian's
    # invalid step 30 in the window. s-b: objects of interest 12 (cyclist), 7 (vehicle): the
    # vehicle (track index 0) first
    assert [(u.scenario, u.tracks) for u in sc.units] == [(0, (1, 0)), (1, (0, 3))]
    assert sc.skipped == {"type": 0, "invalid": 2, "no pair": 0}
    # step 3: the grid 1, 4, ..., 88 misses step 30, so the pedestrian's pairs are kept
    sc3 = WaymoScenario.from_raw([p], step=3)
    assert (sc3.recipe.history, sc3.recipe.horizon, sc3.recipe.dt) == (3, 26, 0.3)
    assert [u.tracks for u in sc3.units] == [(1, 0), (1, 2), (0, 2), (0, 3)]
    assert sc3.skipped["invalid"] == 0
    # the paper's vehicles only: the pedestrian and cyclist pairs are skipped by type
    scv = WaymoScenario.from_raw([p], step=3, types=["vehicle"])
    assert [u.tracks for u in scv.units] == [(1, 0)] and scv.skipped["type"] == 3
    # pairs=predict ignores the objects of interest: s-b's tracks to predict are 1, 0, 2 too
    scp = WaymoScenario.from_raw([p], pairs="predict")
    assert [(u.scenario, u.tracks) for u in scp.units] == [(0, (1, 0)), (1, (1, 0))]
    with pytest.raises(DatasetError, match="no pair to make a sample of"):
        WaymoScenario.from_raw([p], pairs="interest", types=["pedestrian"])


def test_the_scene_against_hand_computed_values(tmp_path):
    p = write_tiny(tmp_path / "t.tfrecord")
    sc = WaymoScenario.from_raw([p])
    s = sc.run_unit(0, None)
    s = {k: v[0] for k, v in s.items()}
    assert set(s) == set(sc.schema())
    for k, fs in sc.schema().items():
        assert s[k].shape == fs.shape and s[k].dtype == np.dtype(fs.dtype), k
    assert s["history"].shape == (11, 2, 4) and s["future"].shape == (6, 2, 80, 4)
    np.testing.assert_array_equal(s["origin"], [50.0, -35.0])  # track 3 at step 10
    k = np.arange(11)
    hist = np.zeros((11, 2, 4))
    hist[:, 0] = np.stack([0 * k, -40 + 0.5 * k + 35, 5 + 0 * k, np.pi / 2 + 0 * k], 1)
    hist[:, 1] = np.stack([k - 50.0, 35 + 0 * k, 10 + 0 * k, 0 * k], 1)
    np.testing.assert_allclose(s["history"], hist, atol=1e-5)
    k = np.arange(11, 91)
    np.testing.assert_allclose(s["future"][0, 0, :, 1], -40 + 0.5 * k + 35, atol=1e-4)
    np.testing.assert_allclose(s["future"][0, 1, :, 0], k - 50.0, atol=1e-4)
    np.testing.assert_array_equal(s["future"][3], s["future"][0])
    assert s["mode_valid"].tolist() == [True] + [False] * 5
    assert s["track_id"].tolist() == [3, 7] and s["agent_kind"].tolist() == [1, 1]
    np.testing.assert_allclose(s["radius"], [2.5, 2.0])  # length / 2
    np.testing.assert_allclose(s["length"], [5.0, 4.0])
    assert s["agents_mask"].all() and int(s["frame"]) == 10 and int(s["scenario"]) == 0
    # closest distance over the window: both at their start x of 0 .. 90 and y 0 vs -40 .. 5
    t = np.arange(91)
    gap = np.hypot(50 - 1.0 * t, -40 + 0.5 * t)
    assert s["min_distance"] == pytest.approx(gap.min(), abs=1e-4)
    assert sc.recipe.dt == 0.1
    # lanes: 10 pieces of lane 100 (200 m), 6 of lane 101 (120 m); the two 2 m away first,
    # lane 100's piece x = -5 .. 15 (track 7 at (10, 0)) before lane 101's y = -40 .. -20
    # (track 3 at (50, -35)) on the tie
    assert s["lanes_mask"].sum() == 16 and not s["lanes_mask"][16:].any()
    assert s["lane_id"][:2].tolist() == [100, 101] and (s["lane_id"][16:] == -1).all()
    x = np.linspace(-5, 15, 10)
    np.testing.assert_allclose(s["lanes"][0], np.stack([x - 50, 0 * x + 33], 1), atol=1e-4)
    y = np.linspace(-40, -20, 10)
    np.testing.assert_allclose(s["lanes"][1], np.stack([0 * y + 2, y + 35], 1), atol=1e-4)
    # the pieces are nearest first (distance to the nearest agent, computed here by sampling)
    agents = np.array([[50.0, -35.0], [10.0, 0.0]]) - [50.0, -35.0]
    dense = [np.concatenate([np.linspace(a, b, 50) for a, b in zip(ln[:-1], ln[1:], strict=True)]) for ln in s["lanes"][:16]]  # fmt: skip
    d = [np.linalg.norm(q[:, None] - agents[None], axis=-1).min() for q in dense]
    assert np.all(np.diff(d) >= -0.01), d
    np.testing.assert_allclose(s["speed_limit"], [35 * MPH, 25 * MPH], rtol=1e-6)
    # goal candidates: track 3 (5 m/s) reaches 40 m in 8 s: range 1.5 * 40 + 10 = 70 m; the
    # first is the pool point nearest (50, 5), lane 101's (52, 4) (tie with (52, 6): first)
    c = s["goal_candidates"] + [50.0, -35.0]
    assert s["goal_candidates_on_map"].all()
    np.testing.assert_allclose(c[0, 0], [52.0, 4.0], atol=1e-4)
    assert (np.linalg.norm(c[0] - [50, -35], axis=1) <= 70 + 1e-3).all()
    assert (np.linalg.norm(c[1] - [10, 0], axis=1) <= 130 + 1e-3).all()
    assert len(np.unique(c[0].round(3), axis=0)) == 64  # farthest-point sampling: distinct
    on_map = [_on_pool(q) for q in c.reshape(-1, 2)]
    assert all(on_map)


def _on_pool(q) -> bool:
    """On lane 100, lane 101 or the crosswalk outline (within 1 mm)."""
    on100 = abs(q[1] + 2) < 1e-3 and -45 - 1e-3 <= q[0] <= 155 + 1e-3
    on101 = abs(q[0] - 52) < 1e-3 and -60 - 1e-3 <= q[1] <= 60 + 1e-3
    x, y = q
    cw = (abs(x - 18) < 1e-3 or abs(x - 22) < 1e-3) and -3 <= y <= 3
    cw = cw or ((abs(y + 3) < 1e-3 or abs(y - 3) < 1e-3) and 18 <= x <= 22)
    return bool(on100 or on101 or cw)


def test_goal_candidates_beyond_the_map_fill_with_a_spiral(tmp_path):
    p = write_tiny(tmp_path / "t.tfrecord")
    sc = WaymoScenario.from_raw([p], goal_points=500)
    s = {k: v[0] for k, v in sc.run_unit(0, None).items()}
    c = s["goal_candidates"][0] + [50.0, -35.0]
    on = s["goal_candidates_on_map"][0]
    # the pool: lanes every 2 m (101 + 61 points), crosswalk outline every 2 m (8 points)
    pool = np.concatenate(
        [
            np.stack([np.arange(-45, 155.01, 2.0), np.full(101, -2.0)], 1),
            np.stack([np.full(61, 52.0), np.arange(-60, 60.01, 2.0)], 1),
        ]
    )
    n_near = int((np.linalg.norm(pool - [50, -35], axis=1) <= 70).sum())
    cw = np.array([[18, -3], [20, -3], [22, -3], [22, -1], [22, 1], [22, 3], [20, 3], [18, 3], [18, 1], [18, -1], [18, -3]], float)  # fmt: skip
    n_near += int((np.linalg.norm(cw - [50, -35], axis=1) <= 70).sum())
    assert on.sum() == n_near and on[:n_near].all()
    assert all(_on_pool(q) for q in c[on])
    assert (np.linalg.norm(c[~on] - [50, -35], axis=1) <= 70 + 1e-3).all()


def test_no_future_enters_lanes_goals_or_the_pair(tmp_path):
    a = WaymoScenario.from_raw([write_tiny(tmp_path / "a.tfrecord")])
    b = WaymoScenario.from_raw([write_tiny(tmp_path / "b.tfrecord", shift_future=25.0)])
    assert [u.tracks for u in a.units] == [u.tracks for u in b.units]
    for i in range(a.n_units):
        sa, sb = a.run_unit(i, None), b.run_unit(i, None)
        for k in ("history", "lanes", "lanes_mask", "lane_id", "goal_candidates", "origin"):
            np.testing.assert_array_equal(sa[k], sb[k], err_msg=k)
        assert not np.array_equal(sa["future"], sb["future"])


def test_more_agents_than_the_pair(tmp_path):
    p = write_tiny(tmp_path / "t.tfrecord")
    sc = WaymoScenario.from_raw([p], agents=3)
    s = {k: v[0] for k, v in sc.run_unit(0, None).items()}
    # the pair (3, 7), then the cyclist 12 (the pedestrian 11 has an invalid step)
    assert s["track_id"].tolist() == [3, 7, 12] and s["agents_mask"].all()
    np.testing.assert_allclose(s["history"][-1, 2, :2], [30 - 50, 30 + 35])
    s1 = {k: v[0] for k, v in sc.run_unit(1, None).items()}  # s-b: (7, 12) and track 3
    assert s1["track_id"].tolist() == [7, 12, 3]
    sc4 = WaymoScenario.from_raw([p], agents=4)
    s = {k: v[0] for k, v in sc4.run_unit(0, None).items()}
    assert s["track_id"].tolist() == [3, 7, 12, -1]
    assert s["agents_mask"].tolist() == [True, True, True, False]
    assert not s["history"][:, 3].any() and s["radius"][3] == 0
    assert not s["goal_candidates"][3].any()


def test_recipe_follows_step_and_builds_the_game():
    r = WaymoRecipe(step=5)
    assert (r.history, r.horizon, r.dt, r.collision_every) == (2, 16, 0.5, 1)
    r1 = WaymoRecipe()
    assert (r1.history, r1.horizon, r1.dt, r1.collision_every, r1.modes, r1.agents) == (10, 80, 0.1, 5, 6, 2)  # fmt: skip
    assert WaymoRecipe.from_dict(json.loads(json.dumps(r.to_dict()))) == r
    g = game_from_recipe(r.to_dict())
    assert (g.N, g.K, g.dt) == (2, 16, 0.5)
    assert "radius.a0" in g.params.names
    from epo_casadi.errors import SpecError

    with pytest.raises(SpecError, match="waymo.dt"):
        WaymoRecipe(step=2, dt=0.1)
    with pytest.raises(SpecError, match="waymo.types"):
        WaymoRecipe(types=["truck"])
    with pytest.raises(SpecError, match="waymo.stride"):
        WaymoRecipe(stride=2)


# --------------------------------------------------------------------------------------
# splits and the command
# --------------------------------------------------------------------------------------
def _scenarios(n, path):
    return tfr.write_records(path, [tiny_scenario(f"s{i}") for i in range(n)])


def test_splits_by_scenario_and_by_file(tmp_path):
    two = WaymoScenario.from_raw([write_tiny(tmp_path / "t.tfrecord")])
    sp = two.split_units(0)
    assert sorted(sp["train"] + sp["test"]) == [0, 1] and sp["val"] == []
    ten = WaymoScenario.from_raw([_scenarios(10, tmp_path / "ten.tfrecord")], step=3)
    sp = ten.split_units(0)
    by = {s: {ten.units[u].scenario for u in us} for s, us in sp.items()}
    assert [len(by[s]) for s in ("train", "val", "test")] == [8, 1, 1]
    assert not (by["train"] & by["test"]) and not (by["train"] & by["val"])
    assert sorted(u for us in sp.values() for u in us) == list(range(ten.n_units))
    assert ten.split_units(0) == sp and ten.split_units(1) != sp
    f = WaymoScenario.from_raw(
        [_scenarios(3, tmp_path / "tr.tfrecord")],
        val=[_scenarios(1, tmp_path / "va.tfrecord")],
        test=[_scenarios(2, tmp_path / "te.tfrecord")],
    )
    sp = f.split_units(0)
    assert [sorted({f.units[u].scenario for u in sp[s]}) for s in ("train", "val", "test")] == [[0, 1, 2], [3], [4, 5]]  # fmt: skip
    assert f.recipe.files == (("tr.tfrecord", "train"), ("va.tfrecord", "val"), ("te.tfrecord", "test"))  # fmt: skip
    one = WaymoScenario.from_raw([_scenarios(1, tmp_path / "one.tfrecord")])
    from epo_casadi.errors import SpecError

    with pytest.raises(SpecError, match="for training and for testing"):
        one.split_units(0)


def test_generate_command_files_and_figures(tmp_path, capsys):
    p = write_tiny(tmp_path / "raw" / "t.tfrecord")
    out, fig = tmp_path / "d", tmp_path / "fig"
    args = ["generate", "waymo", "--raw", p.parent, "--out", out, "--no-progress", "--workers", "1"]
    rc, so, se = cli(capsys, *args, "--set", "step=5", "--draw", fig)
    assert rc == 0, se
    assert "train 1, val 0, test 1 samples" in so
    m = read_manifest(out)
    assert m["scenario"] == "waymo" and m["meta"]["dt"] == 0.5 and m["meta"]["scenarios"] == ["s-a", "s-b"]  # fmt: skip
    assert m["meta"]["skipped"]["invalid"] == 2
    assert m["schema"]["lanes"]["shape"] == [128, 10, 2]
    test = load_split(out, "test")
    train = load_split(out, "train")
    assert len(test["history"]) + len(train["history"]) == 2
    assert sorted(p.name for p in fig.iterdir()) == ["s-a.png", "s-b.png"]
    assert (fig / "s-a.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a corrupted record: one error line naming the file and the record
    bad = tmp_path / "bad" / "t.tfrecord"
    bad.parent.mkdir()
    raw = bytearray(p.read_bytes())
    raw[len(raw) - 100] ^= 0x10  # inside the last record's payload
    bad.write_bytes(bytes(raw))
    rc, _, se = cli(capsys, "generate", "waymo", "--raw", bad, "--out", tmp_path / "d2")
    line = one_error_line(rc, se, f"{bad}:record 1", "payload's CRC")
    assert "Traceback" not in line
    rc, _, se = cli(capsys, "generate", "waymo", "--raw", tmp_path / "nothing", "--out", tmp_path / "d3")  # fmt: skip
    one_error_line(rc, se, "--raw")
    rc, _, se = cli(capsys, "generate", "waymo", "--raw", p, "--out", tmp_path / "d4", "--set", "files=[]")  # fmt: skip
    one_error_line(rc, se, "files")


# --------------------------------------------------------------------------------------
# the training preset
# --------------------------------------------------------------------------------------
def test_preset_values_and_unknown_names(tmp_path, capsys):
    from learning.presets import PRESETS, get_preset

    w = get_preset("waymo")
    assert dict(w.train) == {"batch_size": 32, "lr": 1e-4}
    assert dict(w.loss) == {"imitation": 1.0, "goal": 1.0, "probability": 1.0}
    assert w.model_fields("epo")["goal_decoder"] == "regress"
    assert "goal_decoder" not in w.model_fields("sc")
    assert (w.model["modes"], w.model["lm_steps"], w.model["step_size"], w.model["damping"]) == (6, 2, 0.3, 10.0)  # fmt: skip
    assert sorted(PRESETS) == ["waymo"]
    rc, _, se = cli(
        capsys, "train", "--data", tmp_path, "--out", tmp_path / "r", "--preset", "nope"
    )
    one_error_line(rc, se, "--preset", "'nope'", "waymo")


def test_preset_options_override(tmp_path, capsys):
    """A tiny dataset of the small file; one epoch with the preset, --lr given explicitly."""
    data = tmp_path / "d"
    p = write_tiny(tmp_path / "t.tfrecord")
    rc, _, se = cli(capsys, "generate", "waymo", "--raw", p, "--out", data, "--no-progress",
                    "--workers", "1", "--set", "step=10", "--set", "lane_count=8",
                    "--set", "goal_points=8")  # fmt: skip
    assert rc == 0, se
    run = tmp_path / "run"
    tiny = ["hist_width=8", "hist_layers=1", "lane_width=8", "global_width=16", "heads=2", "dec_width=16"]  # fmt: skip
    sets = [a for t in tiny for a in ("--set", t)]
    rc, _, se = cli(capsys, "train", "--data", data, "--out", run, "--preset", "waymo", "--epochs", "1",
                    "--lr", "3e-4", "--no-progress", *sets)  # fmt: skip
    assert rc == 0, se
    cfg = json.loads((run / "config.json").read_text())["train"]
    assert cfg["lr"] == 3e-4 and cfg["batch_size"] == 32
    assert cfg["loss"] == {"imitation": 1.0, "goal": 1.0, "probability": 1.0}
    assert cfg["model"]["goal_decoder"] == "regress" and cfg["model"]["modes"] == 6
    assert cfg["model"]["hist_width"] == 8


# --------------------------------------------------------------------------------------
# the shipped files
# --------------------------------------------------------------------------------------
def _shared():
    if not all((SHARED / f).is_file() for f in FILES):
        pytest.skip(f"../shared/realdata/waymo not present: {SHARED} (the Waymo test data)")
    return SHARED


def test_shipped_files_read():
    d = _shared()
    a, b = (read_scenarios([d / f]) for f in FILES)
    assert len(a) == len(b) == 1
    a, b = a[0], b[0]
    assert (a.scenario_id, len(a.track_ids), a.states.shape[1]) == ("637f20cafde22ff8", 83, 91)
    assert (b.scenario_id, len(b.track_ids), b.states.shape[1]) == ("ee519cf571686d19", 257, 91)
    assert a.current == b.current == 10
    # tracks to predict: 2 vehicles and 1 pedestrian; objects of interest: none
    assert sorted(a.object_type[[k for k, _ in a.predict]].tolist()) == [1, 1, 2]
    assert a.interest == ()
    # objects of interest: a vehicle and a pedestrian
    idx = [int(np.flatnonzero(b.track_ids == i)[0]) for i in b.interest]
    assert b.interest == (625, 2694) and b.object_type[idx].tolist() == [1, 2]
    assert {m.kind for m in a.map} == {"lane", "road_line", "road_edge", "crosswalk"}


def test_shipped_scene_against_the_raw_states():
    d = _shared()
    sc = WaymoScenario.from_raw([d])
    assert [sc.scenarios[u.scenario].scenario_id for u in sc.units] == ["637f20cafde22ff8", "ee519cf571686d19"]  # fmt: skip
    # the vehicle 1676 has invalid steps in the window: its two pairs are skipped
    assert sc.skipped == {"type": 0, "invalid": 2, "no pair": 0}
    s = {k: v[0] for k, v in sc.run_unit(1, None).items()}
    # decode the record again, straight from the protobuf message
    payload = next(tfr.iter_records(d / FILES[1])).payload
    msg = scenario_class().FromString(payload)
    veh = next(t for t in msg.tracks if t.id == 625)
    ped = next(t for t in msg.tracks if t.id == 2694)
    xy = lambda t, ks: np.array([[t.states[k].center_x, t.states[k].center_y] for k in ks])  # noqa: E731
    origin = xy(veh, [10])[0]
    np.testing.assert_allclose(s["origin"], origin)
    np.testing.assert_allclose(s["history"][:, 0, :2], xy(veh, range(11)) - origin, atol=1e-4)
    np.testing.assert_allclose(s["history"][:, 1, :2], xy(ped, range(11)) - origin, atol=1e-4)
    np.testing.assert_allclose(s["future"][0, 1, :, :2], xy(ped, range(11, 91)) - origin, atol=1e-3)
    v = math.hypot(veh.states[10].velocity_x, veh.states[10].velocity_y)
    assert s["history"][-1, 0, 2] == pytest.approx(v, rel=1e-6)
    assert s["radius"].tolist() == pytest.approx([veh.states[10].length / 2, ped.states[10].length / 2])  # fmt: skip
    assert s["track_id"].tolist() == [625, 2694] and s["lanes_mask"].all()


def test_shipped_end_to_end(tmp_path, capsys):
    """generate -> train --preset waymo (one epoch, tiny widths, dt 0.5 s) -> evaluate ->
    show-predictions, the commands a holder of the full Waymo set runs."""
    d = _shared()
    data, run = tmp_path / "d", tmp_path / "run"
    rc, so, se = cli(capsys, "generate", "waymo", "--raw", d / FILES[0], "--raw", d / FILES[1],
                     "--out", data, "--no-progress", "--workers", "1", "--set", "step=5",
                     "--draw", tmp_path / "fig")  # fmt: skip
    assert rc == 0, se
    assert "train 1, val 0, test 1 samples" in so
    assert len(list((tmp_path / "fig").glob("*.png"))) == 2
    tiny = ["hist_width=8", "hist_layers=1", "lane_width=8", "global_width=16", "heads=2", "dec_width=16"]  # fmt: skip
    sets = [a for t in tiny for a in ("--set", t)]
    rc, so, se = cli(capsys, "train", "--data", data, "--out", run, "--preset", "waymo",
                     "--epochs", "1", "--no-progress", *sets)  # fmt: skip
    assert rc == 0, se
    rc, so, se = cli(capsys, "evaluate", run, "--data", data, "--out", tmp_path / "ev")
    assert rc == 0, se
    assert "minSADE" in (tmp_path / "ev" / "results.md").read_text()
    rc, so, se = cli(capsys, "show-predictions", run, "--data", data, "--out", tmp_path / "p.png")
    assert rc == 0, se
    assert (tmp_path / "p.png").stat().st_size > 1000
