"""The paper's driving features (epo_casadi.presets), shared by the driving scenarios."""

from __future__ import annotations

from types import SimpleNamespace

from epo_casadi.presets import DRIVING_WEIGHTS, driving_features
from scenarios.exid import ExidScenario
from scenarios.left_turn import LeftTurnScenario


def test_driving_features_in_the_papers_order_with_the_recipes_weights():
    w = SimpleNamespace(**{k: float(i + 1) for i, k in enumerate(DRIVING_WEIGHTS)})
    full = driving_features(w, lane_points=7)
    assert [type(f).__name__ for f in full] == [
        "Goal",
        "Path",
        "ReferenceVelocity",
        "Velocity",
        "Acceleration",
        "Jerk",
        "TurnRate",
        "TurnAcceleration",
    ]
    assert [f.weight for f in full] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    assert full[1].points == 7 and full[1].label == "lane" and full[2].label == "vref"
    waymo = driving_features(w)
    assert [type(f).__name__ for f in waymo] == [type(f).__name__ for f in full[:1] + full[3:]]


def test_left_turn_and_exid_agents_use_them():
    for sc in (LeftTurnScenario(), ExidScenario()):
        r = sc.recipe
        for agent in sc.agent_specs():
            mine = driving_features(r, lane_points=r.lane_points)
            key = lambda f: (type(f), f.weight, f.label, getattr(f, "points", None))  # noqa: E731
            assert [key(f) for f in agent.features] == [key(f) for f in mine]
            assert any(getattr(f, "points", None) == r.lane_points for f in agent.features)
