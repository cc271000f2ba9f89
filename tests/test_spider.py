"""Spider plot weights (learning.spider): per-agent own and pairwise weights, normalized per mode."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from learning.spider import spider_weights


def test_spider_weights_by_hand():
    names = ["w.a.goal", "w.a.lane", "w.b.goal", "w.b.lane", "w.a-b.collision", "radius.a"]
    groups = {"w_own": [0, 1, 2, 3], "w_pair": [4]}
    game = SimpleNamespace(
        params=SimpleNamespace(names=names, group=groups.__getitem__), agent_names=["a", "b"]
    )
    p = np.array([[1.0, 10.0, 100.0, 1.0, 10.0, 7.0], [2.0, 20.0, 200.0, 2.0, 20.0, 7.0]])
    w, axes = spider_weights(p, game)
    assert axes == ["goal", "lane", "collision"]
    # geometric mean of (1, 10, 100, 1, 10) is 10^(4/5); mode 1 is mode 0 scaled by 2: same plot
    want = np.log10(np.array([[1.0, 10.0, 10.0], [100.0, 1.0, 10.0]])) - 0.8
    np.testing.assert_allclose(w[0], want)
    np.testing.assert_allclose(w[1], want)
