"""scenarios.maps: lanes, road maps, resampling, routes, tasks, conflict zones, and the
left-turn intersection geometries built on highway-env."""

import math

import numpy as np
import pytest

from epo_casadi.errors import SpecError
from scenarios.maps import Lane, RoadMap, arc_length, project_to_polyline, resample_polyline


def L_shape():
    # 10 m east, then 5 m north: length 15
    return np.array([[0.0, 0.0], [4.0, 0.0], [10.0, 0.0], [10.0, 5.0]])


def test_resample_is_equally_spaced_in_arc_length():
    line = L_shape()
    pts = resample_polyline(line, 16)
    s, d = project_to_polyline(pts, line)
    np.testing.assert_allclose(d, 0.0, atol=1e-12)
    np.testing.assert_allclose(s, np.arange(16.0), atol=1e-12)  # 15 m in 15 intervals
    assert arc_length(line)[-1] == 15.0


def test_projection_matches_dense_brute_force():
    rng = np.random.default_rng(0)
    line = np.cumsum(rng.normal(size=(7, 2)), axis=0)
    q = rng.normal(size=(20, 2)) * 2
    s, d = project_to_polyline(q, line)
    dense = resample_polyline(line, 20001)
    dd = np.linalg.norm(q[:, None] - dense[None], axis=2)
    k = dd.argmin(axis=1)
    step = arc_length(line)[-1] / 20000
    np.testing.assert_allclose(d, dd.min(axis=1), atol=1e-6 + step)
    np.testing.assert_allclose(s, k * step, atol=2 * step + 1e-3)


def test_lane_validation_names_the_field():
    with pytest.raises(SpecError, match=r"lanes\[a\]\.centre"):
        Lane("a", np.zeros((1, 2)))
    with pytest.raises(SpecError, match=r"lanes\[a\]\.centre.*coincide"):
        Lane("a", [[0, 0], [0, 0], [1, 0]])
    with pytest.raises(SpecError, match=r"lanes\[a\]\.width"):
        Lane("a", [[0, 0], [1, 0]], width=0.0)
    with pytest.raises(SpecError, match=r"lanes\[a\]\.speed_limit"):
        Lane("a", [[0, 0], [1, 0]], speed_limit=float("nan"))
    with pytest.raises(SpecError, match=r"lanes\[a\]\.successors"):
        Lane("a", [[0, 0], [1, 0]], successors="b")
    a = Lane("a", [[0, 0], [1, 0]], successors=("zz",))
    with pytest.raises(SpecError, match=r"lanes\[a\]\.successors: unknown lane ids \['zz'\]"):
        RoadMap((a,))
    with pytest.raises(SpecError, match="duplicate"):
        RoadMap((Lane("a", [[0, 0], [1, 0]]), Lane("a", [[0, 1], [1, 1]])))
    with pytest.raises(SpecError, match="unknown lane id 'q'; valid: a"):
        RoadMap((Lane("a", [[0, 0], [1, 0]]),)).lane("q")


def small_map():
    return RoadMap(
        (
            Lane("in", [[0, 0], [10, 0]], width=3.0, speed_limit=10.0, successors=("out",)),
            Lane("out", [[10, 0], [10, 5], [10, 20]], width=3.0, speed_limit=6.0),
            Lane("far", [[50, 50], [60, 50]], successors=()),
        )
    )


def test_route_task_and_errors():
    m = small_map()
    r = m.route(("in", "out"))
    assert r.shape == (4, 2)
    assert arc_length(r)[-1] == 30.0
    t = m.task(("in", "out"), n_points=31, radius=1.5)
    assert t.path.shape == (31, 2) and t.speed == 6.0 and t.radius == 1.5
    np.testing.assert_allclose(t.goal, [10.0, 20.0])
    np.testing.assert_allclose(np.linalg.norm(np.diff(t.path, axis=0), axis=1)[:10], 1.0)
    with pytest.raises(SpecError, match="not a successor"):
        m.route(("out", "in"))
    with pytest.raises(SpecError, match="route"):
        m.route(())
    with pytest.raises(SpecError, match="n_points"):
        m.task(("in",), n_points=1, radius=1.0)


def test_conflict_zone_of_perpendicular_lanes():
    m = RoadMap(
        (
            Lane("ew", [[-10, 0], [10, 0]]),
            Lane("sn", [[0, -10], [0, 10]]),
            Lane("p", [[-10, 9], [10, 9]]),
        )
    )
    z = m.conflict_zone("ew", "sn", clearance=2.0, step=0.1)
    # centre lines within 2 m of each other: |x| < 2 on "ew", |y| < 2 on "sn"
    assert z.a[0] == pytest.approx(8.1, abs=1e-9) and z.a[1] == pytest.approx(11.9, abs=1e-9)
    assert z.b[0] == pytest.approx(8.1, abs=1e-9) and z.b[1] == pytest.approx(11.9, abs=1e-9)
    np.testing.assert_allclose(z.point, [0.0, 0.0], atol=1e-9)
    assert m.conflict_zone("ew", "p", clearance=2.0) is None
    # distance to the road: inside a lane <= 0, 5 m off "ew" and "sn" -> 5 - 1.75
    np.testing.assert_allclose(m.distance_to_road([[3.0, 0.5], [5.0, -5.0]]), [-1.25, 3.25])


def test_from_highway_samples_lane_positions():
    from scenarios.sim._highway import hw

    H = hw()
    net = H.RoadNetwork()
    net.add_lane("a", "b", H.StraightLane([0, 0], [20, 0], width=3.0, speed_limit=8.0))
    net.add_lane("b", "c", H.CircularLane([20, 10], 10.0, -math.pi / 2, 0.0, width=3.0))
    m = RoadMap.from_highway(net, step=0.5)
    assert m.ids == ("a>b:0", "b>c:0")
    assert m.lane("a>b:0").successors == ("b>c:0",)
    arc = m.lane("b>c:0")
    hl = net.get_lane(("b", "c", 0))
    assert arc.length == pytest.approx(hl.length, rel=1e-3)  # chords of a 10 m circle
    s = np.linspace(0, hl.length, len(arc.centre))
    np.testing.assert_allclose(arc.centre, [hl.position(x, 0) for x in s], atol=1e-12)
    np.testing.assert_allclose(arc.centre[0], m.lane("a>b:0").centre[-1], atol=1e-12)
    assert m.lane("a>b:0").speed_limit == 8.0 and arc.width == 3.0


@pytest.fixture(scope="module")
def geometries():
    from scenarios.sim.left_turn import GEOMETRIES, LeftTurnWorld

    return {g: LeftTurnWorld(geometry=g) for g in GEOMETRIES}


def test_four_geometries_differ(geometries):
    assert len(geometries) >= 4
    sig = set()
    for w in geometries.values():
        g = w.geometry
        sig.add((g.lane_width, g.lanes, g.angle))
        # the exit leaves at the geometry's angle
        exit_ = w.road_map.lane("ego_exit").centre
        h = math.atan2(*(exit_[-1] - exit_[0])[::-1])
        assert math.isclose((h - math.pi / 2) % (2 * math.pi), math.radians(g.angle), abs_tol=1e-9)
        # lane count: ego direction + oncoming + crossing lanes
        n_onc = sum(i.startswith("oncoming") and i.endswith("approach") for i in w.road_map.ids)
        assert n_onc == g.lanes
        assert {ln.width for ln in w.road_map.lanes} == {g.lane_width}
    assert len(sig) == len(geometries)
    widths = {w.geometry.lane_width for w in geometries.values()}
    angles = {w.geometry.angle for w in geometries.values()}
    counts = {w.geometry.lanes for w in geometries.values()}
    assert len(widths) >= 3 and len(angles) >= 3 and len(counts) >= 2


def test_geometry_lanes_are_continuous(geometries):
    for w in geometries.values():
        for ln in w.road_map.lanes:
            seg = np.linalg.norm(np.diff(ln.centre, axis=0), axis=1)
            # sampled every 0.5 m along highway-env's lane (chords of arcs a bit shorter)
            assert seg.max() <= 0.5 + 1e-9 and seg.min() > 0.2
        rm = w.road_map
        a, t, e = (rm.lane(i) for i in ("ego_approach", "ego_turn", "ego_exit"))
        np.testing.assert_allclose(a.centre[-1], t.centre[0], atol=1e-9)
        np.testing.assert_allclose(t.centre[-1], e.centre[0], atol=1e-9)
        # tangent-continuous: the turn starts along the approach and ends along the exit
        assert abs(a.heading(a.length) - t.heading(0.0)) < 0.05
        dh = (t.heading(t.length) - e.heading(0.0) + math.pi) % (2 * math.pi) - math.pi
        assert abs(dh) < 0.05
        # the turn path has constant curvature 1 / turn_radius about one centre
        c = t.centre
        mid = c[len(c) // 2]
        chord = c[-1] - c[0]
        R = w.geometry.turn_radius
        half = np.linalg.norm(chord) / 2
        sag = R - math.sqrt(R * R - half * half)
        rel = mid - c[0]
        line_d = abs(chord[0] * rel[1] - chord[1] * rel[0]) / np.linalg.norm(chord)
        assert line_d == pytest.approx(sag, rel=1e-3)
        # the turn crosses every oncoming lane: a conflict zone on each
        for i in range(w.geometry.lanes):
            route = rm.route((f"oncoming{i}_approach", f"oncoming{i}_through"))
            assert rm.conflict_zone(w.ego_route, route, clearance=2.5) is not None
