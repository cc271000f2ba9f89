"""Overlap rate with oriented vehicle boxes (learning.metrics): the separating-axis test by
hand on constructed pairs, against an independent linear-programming intersection test on
random pairs, the motion headings, and the choice between boxes and circles."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import linprog

from learning.metrics import (
    all_metrics,
    box_overlap,
    motion_headings,
    overlap_rate,
    overlap_rate_boxes,
)
from learning.scoring import boxes


def _ov(c1, h1, l1, w1, c2, h2, l2, w2) -> bool:
    t = torch.tensor
    out = box_overlap(t(c1, dtype=torch.float64), t(h1), t(l1), t(w1), t(c2), t(h2), t(l2), t(w2))
    return bool(out)


def test_constructed_pairs_by_hand():
    # two 4 x 2 boxes end to end: touching at a gap of exactly 4 is not an overlap
    assert not _ov([0, 0], 0.0, 4.0, 2.0, [4.0, 0], 0.0, 4.0, 2.0)
    assert _ov([0, 0], 0.0, 4.0, 2.0, [3.99, 0], 0.0, 4.0, 2.0)
    # a 2 x 2 square turned 45 deg reaches sqrt(2) towards the 4 x 2 box's end at x = 2
    s = 2 + math.sqrt(2)
    assert _ov([0, 0], 0.0, 4.0, 2.0, [s - 0.01, 0], math.pi / 4, 2.0, 2.0)
    assert not _ov([0, 0], 0.0, 4.0, 2.0, [s + 0.01, 0], math.pi / 4, 2.0, 2.0)
    # only the turned square's own (diagonal) axis separates: A's axes overlap (2 - sqrt2 < 1),
    # the diagonal does not (2 sqrt2 > sqrt2 + 1); the edge x + y = 4 - sqrt2 passes (1, 1)
    assert not _ov([0, 0], 0.0, 2.0, 2.0, [2.0, 2.0], math.pi / 4, 2.0, 2.0)
    assert _ov([0, 0], 0.0, 2.0, 2.0, [1.6, 1.6], math.pi / 4, 2.0, 2.0)
    # one inside the other (no edge crosses), either order
    assert _ov([0, 0], 0.3, 10.0, 4.0, [1.0, 0.5], 1.0, 2.0, 1.0)
    assert _ov([1.0, 0.5], 1.0, 2.0, 1.0, [0, 0], 0.3, 10.0, 4.0)
    # two 5 x 2 cars side by side 3.5 m apart (adjacent lanes): circles r = L / 2 overlap,
    # boxes do not; heading pi is the same box as heading 0
    assert not _ov([0, 0], 0.0, 5.0, 2.0, [1.0, 3.5], math.pi, 5.0, 2.0)
    assert _ov([0, 0], 0.0, 5.0, 2.0, [1.0, 1.9], math.pi, 5.0, 2.0)


def _halfspaces(c, h, length, width):
    """A x <= b of a rectangle (outward normals)."""
    u = np.array([math.cos(h), math.sin(h)])
    v = np.array([-math.sin(h), math.cos(h)])
    A = np.stack([u, -u, v, -v])
    b = A @ np.asarray(c) + np.array([length, length, width, width]) / 2
    return A, b


def _lp_margin(box1, box2) -> float:
    """Largest t with a point at distance >= t inside both rectangles (LP; > 0: they overlap)."""
    A = np.concatenate([_halfspaces(*box1)[0], _halfspaces(*box2)[0]])
    b = np.concatenate([_halfspaces(*box1)[1], _halfspaces(*box2)[1]])
    res = linprog(
        [0, 0, -1], A_ub=np.c_[A, np.ones(len(A))], b_ub=b, bounds=[(None, None)] * 2 + [(None, 10)]
    )
    assert res.status == 0
    return -res.fun


def test_random_pairs_against_linear_programming():
    rng = np.random.default_rng(0)
    n = 400
    c1, c2 = rng.uniform(-1, 1, (n, 2)), rng.uniform(-6, 6, (n, 2))
    h1, h2 = rng.uniform(-math.pi, math.pi, (2, n))
    l1, l2 = rng.uniform(1, 8, (2, n))
    w1, w2 = rng.uniform(0.5, 3, (2, n))
    ours = box_overlap(*(torch.tensor(a) for a in (c1, h1, l1, w1, c2, h2, l2, w2))).numpy()
    margin = np.array(
        [_lp_margin((c1[i], h1[i], l1[i], w1[i]), (c2[i], h2[i], l2[i], w2[i])) for i in range(n)]
    )
    clear = np.abs(margin) > 1e-6  # leave out exact touching
    assert clear.sum() > 390 and 0.2 < ours.mean() < 0.8  # both outcomes well represented
    assert np.array_equal(ours[clear], margin[clear] > 0)


def test_motion_headings_hold_when_stopped():
    # moves +x, then +y, then stops, then -x; the first heading comes from start
    pos = torch.tensor([[1.0, 0.0], [1.0, 1.0], [1.0, 1.0], [1.0, 1.01], [0.0, 1.0]])
    h = motion_headings(pos, start=torch.tensor([0.0, 0.0]), heading0=torch.tensor(2.0))
    want = torch.tensor([0.0, math.pi / 2, math.pi / 2, math.pi / 2, math.atan2(-0.01, -1.0)])
    torch.testing.assert_close(h, want)
    # standing still from the start: the current heading throughout
    still = torch.zeros(2, 3, 4, 2)
    h0 = torch.tensor([[0.1, 0.2, 0.3]]).expand(2, 3)
    torch.testing.assert_close(
        motion_headings(still, torch.zeros(2, 3, 2), h0), h0[..., None].expand(2, 3, 4)
    )
    # without start, step 0 takes step 1's direction
    torch.testing.assert_close(
        motion_headings(torch.tensor([[0.0, 0.0], [0.0, -1.0]])), torch.full((2,), -math.pi / 2)
    )


def _scene(direction):
    """Two 5 x 2 cars 3 m apart laterally (x), both moving along ``direction`` for 3 steps."""
    d = torch.tensor(direction, dtype=torch.float32)
    steps = torch.arange(1, 4, dtype=torch.float32)[:, None] * d
    start = torch.tensor([[0.0, 0.0], [3.0, 0.0]])
    pred = (start[:, None] + steps[None])[None, None]  # (1, 1, 2, 3, 2)
    return pred, start[None]


def test_box_heading_follows_the_motion():
    L, W, p = torch.full((2,), 5.0), torch.full((2,), 2.0), torch.ones(1, 1)
    pred, start = _scene([0.0, 1.0])  # driving side by side along y: lengths along y
    assert overlap_rate_boxes(pred, p, L, W, start=start).item() == 0.0
    pred, start = _scene([1.0, 0.0])  # one behind the other along x, 3 m apart: 5 m cars overlap
    assert overlap_rate_boxes(pred, p, L, W, start=start).item() == 1.0
    # the heading is not read from heading0 once the cars move
    assert overlap_rate_boxes(pred, p, L, W, start=start, heading0=torch.full((1, 2), 1.57)) == 1.0


def test_boxes_use_the_most_likely_mode_and_the_mask():
    side, start = _scene([0.0, 1.0])
    behind, _ = _scene([1.0, 0.0])
    pred = torch.cat([side, behind], dim=1)  # (1, 2, 2, 3, 2)
    L, W = torch.full((1, 2), 5.0), torch.full((1, 2), 2.0)
    assert overlap_rate_boxes(pred, torch.tensor([[0.6, 0.4]]), L, W, start).item() == 0.0
    assert overlap_rate_boxes(pred, torch.tensor([[0.4, 0.6]]), L, W, start).item() == 1.0
    mask = torch.tensor([[True, False]])
    assert overlap_rate_boxes(pred, torch.tensor([[0.4, 0.6]]), L, W, start, mask=mask) == 0.0
    # short cars (2.5 m) 3 m apart do not overlap end to end
    assert overlap_rate_boxes(pred, torch.tensor([[0.4, 0.6]]), L / 2, W, start).item() == 0.0
    with pytest.raises(ValueError, match="length"):
        overlap_rate_boxes(pred, torch.tensor([[0.4, 0.6]]), torch.ones(3), W, start)


def test_all_metrics_switches_to_boxes_with_vehicle_sizes():
    side, start = _scene([0.0, 1.0])  # 3 m apart side by side: circles of 2.5 m overlap
    gt, probs, radii = side[:, 0], torch.ones(1, 1), torch.full((2,), 2.5)
    circles = all_metrics(side, gt, probs, radii)
    assert circles["OR"].item() == 1.0 and "OR_circle" not in circles
    hist = torch.zeros(1, 3, 2, 4)
    hist[:, -1, :, :2], hist[:, -1, :, 3] = start, math.pi / 2
    batch = {"history": hist, "length": torch.full((1, 2), 5.0), "width": torch.full((1, 2), 2.0)}
    b = boxes(batch)
    torch.testing.assert_close(b["start"], start)
    m = all_metrics(side, gt, probs, radii, boxes=b)
    assert m["OR"].item() == 0.0 and torch.equal(m["OR_circle"], overlap_rate(side, probs, radii))
    assert boxes({"history": hist}) is None


def test_box_hits_grow_by_hand():
    """Two 4 x 2 m cars in a row, 1 m bumper to bumper, driving along x: growing both boxes by
    g in length closes the gap by g (half of g at each facing bumper), so they touch at g = 1."""
    from learning.metrics import box_hits

    t = torch.arange(3, dtype=torch.float64)
    pos = torch.stack([torch.stack([t, 0 * t], -1), torch.stack([t + 5.0, 0 * t], -1)])[None]
    L, W = (
        torch.full((1, 2), 4.0, dtype=torch.float64),
        torch.full((1, 2), 2.0, dtype=torch.float64),
    )
    for g, want in ((0.0, False), (0.9, False), (1.1, True)):
        hit, h = box_hits(pos, L, W, start=pos[:, :, 0] - torch.tensor([1.0, 0.0]), grow=g)
        assert torch.equal(hit[0, 0, 1], torch.full((3,), want)) and hit[0, 0, 0].all()
        assert torch.allclose(h, torch.zeros_like(h))  # heading along the motion
