"""Scenes of recorded tracks (scenarios.real.scenes) against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from epo_casadi import PotentialGame
from epo_casadi.errors import SpecError
from scenarios.real.recipe import SceneRecipe
from scenarios.real.scenes import (
    Track,
    closest_approach,
    contiguous_pieces,
    crowd_game_spec,
    scene_schema,
    select_agents,
    stack_scenes,
    unicycle_states,
    window_scenes,
)


def test_pieces_split_at_gaps_and_keep_ids():
    f = np.array([0, 10, 20, 40, 50, 60, 70])
    xy = np.arange(14.0).reshape(7, 2)
    parts = contiguous_pieces(Track(7, f, xy), 10)
    assert [p.frames.tolist() for p in parts] == [[0, 10, 20], [40, 50, 60, 70]]
    assert all(p.id == 7 for p in parts)
    assert parts[1].xy.tolist() == xy[3:].tolist()
    with pytest.raises(SpecError, match="increasing"):
        contiguous_pieces(Track(1, np.array([0, 10, 10]), np.zeros((3, 2))), 10)


def test_states_by_backward_differences():
    xy = np.array([[0.0, 0.0], [0.4, 0.0], [0.4, 0.0], [0.4, 0.8]])
    s = unicycle_states(xy, 0.4)
    # v_k = |p_k - p_{k-1}| / dt, v_0 = v_1; heading held while standing
    assert np.allclose(s[:, 2], [1.0, 1.0, 0.0, 2.0])
    assert np.allclose(s[:, 3], [0.0, 0.0, 0.0, math.pi / 2])
    assert np.array_equal(s[:, :2], xy)
    # a later position never changes an earlier state
    xy2 = xy.copy()
    xy2[3] = [9.0, -9.0]
    assert np.array_equal(unicycle_states(xy2, 0.4)[:3], s[:3])
    # standing first, then moving: the first move's heading is used before it
    s = unicycle_states(np.array([[0.0, 0.0], [0.0, 0.0], [0.0, -1.0]]), 1.0)
    assert np.allclose(s[:, 3], -math.pi / 2)


def test_closest_approach_uses_observed_velocity_only():
    focal = np.array([[0.0, 0.0], [1.0, 0.0]])  # moving +x at 1 per step
    # a: 3 m ahead now, walking towards the focal: meets it;  b: 2 m beside, walking away
    a = np.array([[5.0, 0.0], [4.0, 0.0]])
    b = np.array([[1.0, 1.0], [1.0, 2.0]])
    d = closest_approach(focal, np.stack([a, b]), horizon=3)
    # a: at step k, a = 4 - k, focal = 1 + k -> gap |3 - 2k|: min over k = 0..3 is 1
    # b: (1, 2 + k) against (1 + k, 0): gap sqrt(k^2 + (2 + k)^2), min at k = 0: 2
    assert np.allclose(d, [1.0, 2.0])
    order = select_agents(d, np.array([5, 3]), 1)
    assert order.tolist() == [0]
    # ties: the lower id first; max_distance leaves the far ones out
    assert select_agents(np.array([1.0, 1.0, 5.0]), np.array([9, 2, 1]), 3, 2.0).tolist() == [1, 0]


def _line(i, start, n, y, speed=1.0):
    f = np.arange(start, start + n)
    return Track(i, f, np.c_[speed * np.arange(n, dtype=float), np.full(n, y)])


def test_window_scenes_pad_order_and_origin():
    tracks = [_line(0, 0, 6, 0.0), _line(1, 0, 6, 3.0), _line(2, 0, 6, 1.0), _line(3, 2, 3, 0.5)]
    sc = window_scenes(tracks, step=1, history=1, horizon=2, agents=3, dt=0.5)
    # focal pieces of >= 4 frames (0, 1, 2) with current frames 1..3; track 3 covers no window
    assert len(sc) == 9
    s = sc[0]  # focal 0 at frame 1: others 2 (1 m) before 1 (3 m)
    assert s["track_id"].tolist() == [0, 2, 1] and s["agents_mask"].all()
    assert s["frame"] == 1 and np.allclose(s["origin"], [1.0, 0.0])
    assert np.allclose(s["history"][:, 1, :2], [[-1.0, 1.0], [0.0, 1.0]])
    assert np.allclose(s["gt"][0, :, 0], [1.0, 2.0]) and np.allclose(s["gt"][0, :, 2], 2.0)
    assert s["min_distance"] == pytest.approx(1.0)
    one = window_scenes(tracks[:1], step=1, history=1, horizon=2, agents=3, dt=0.5)[0]
    assert one["agents_mask"].tolist() == [True, False, False]
    assert one["track_id"].tolist() == [0, -1, -1]
    assert not one["history"][:, 1:].any() and not one["gt"][1:].any()
    assert one["min_distance"] == math.inf
    schema = scene_schema(3, 1, 2, 4)
    out = stack_scenes([one, s], schema, np.array([0.3, 1.5]))
    assert out["radius"].tolist() == [[pytest.approx(0.3), 0, 0], [pytest.approx(0.3)] * 3]
    assert out["future"].shape == (2, 4, 3, 2, 4)
    assert np.array_equal(out["future"][:, 0], out["future"][:, 3])
    assert out["mode_valid"].tolist() == [[True, False, False, False]] * 2
    assert {k: v.dtype.name for k, v in out.items()} == {k: f.dtype for k, f in schema.items()}


def test_crowd_game_has_the_waymo_features_and_a_radius_per_agent():
    g = PotentialGame(crowd_game_spec(SceneRecipe(agents=3, horizon=4, dt=0.4)))
    own = ["goal", "velocity", "acceleration", "jerk", "turn_rate", "turn_acceleration"]
    for i in range(3):
        assert [n for n in g.params.names if n.startswith(f"w.a{i}.")] == [
            f"w.a{i}.{f}" for f in own
        ]
    pairs = [n for n in g.params.names if "-" in n]
    assert pairs == ["w.a0-a1.collision", "w.a0-a2.collision", "w.a1-a2.collision"]
    assert [b.name for b in g.params.blocks if b.name.startswith("radius")] == [
        "radius.a0",
        "radius.a1",
        "radius.a2",
    ]
    assert g.N == 3 and g.K == 4 and g.dt == pytest.approx(0.4)
