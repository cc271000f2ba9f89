"""scenarios.sim: the simulated worlds (left turn, crossing, merge) and their registry."""

import math

import casadi as ca
import numpy as np
import pytest

from epo_casadi.dynamics import Unicycle
from epo_casadi.errors import SpecError
from scenarios.maps import project_to_polyline
from scenarios.sim import make_world
from scenarios.sim.common import Character, Sensor
from solvers.control.types import Observation, World
from solvers.control.vehicle import VehicleModel


def run(world, seed, commands):
    """Truth and observations of an episode under fixed commands."""
    obs = [world.reset(seed)]
    truth = [world.truth()]
    for u in commands:
        obs.append(world.step(u))
        truth.append(world.truth())
    return np.array(truth), np.array([np.concatenate([o.ego, o.others.ravel()]) for o in obs])


CASES = {
    "left-turn": dict(geometry="g1", dropout_prob=0.1),
    "crossing": dict(dropout_prob=0.1),
    "merge": dict(traffic=3, dropout_prob=0.1),
}


@pytest.mark.parametrize("name", list(CASES))
def test_episode_is_bit_identical_for_a_seed(name):
    w = make_world(name, **CASES[name])
    assert isinstance(w, World)
    u = np.array([[0.5, 0.02]] * 25)
    t1, o1 = run(w, 3, u)
    t2, o2 = run(w, 3, u)
    assert np.array_equal(t1, t2) and np.array_equal(o1, o2, equal_nan=True)
    # a fresh world gives the same episode too
    t3, o3 = run(make_world(name, **CASES[name]), 3, u)
    assert np.array_equal(t1, t3) and np.array_equal(o1, o3, equal_nan=True)
    t4, o4 = run(w, 4, u)
    assert not np.array_equal(t1, t4)
    assert not np.array_equal(o1, o4, equal_nan=True)
    n = w.n_agents
    assert t1.shape == (26, n, 4) and w.radii.shape == (n,)
    assert len(w.tasks()) == n and w.tasks()[0] is w.ego_task
    assert w.ego_task.path.shape[1] == 2 and w.road_map.lanes


def test_ego_step_is_the_vehicle_model_step():
    w = make_world("left-turn", geometry="g2", ego_distance=(25.0, 25.0))
    assert w.vehicle == VehicleModel.highway()
    w.reset(0)
    rng = np.random.default_rng(1)
    for _ in range(20):
        u = np.array([rng.uniform(-3, 3), rng.uniform(-0.5, 0.5)])
        x0 = w.truth()[0]
        w.step(u)
        np.testing.assert_allclose(w.truth()[0], w.vehicle.step(x0, u, w.dt), rtol=0, atol=1e-12)
    assert w.outcome() == "running"


def test_crossing_robot_is_the_unicycle_euler_step():
    w = make_world("crossing")
    w.reset(0)
    f = Unicycle()
    for u in ([0.5, 0.3], [-1.0, -0.2], [0.0, 1.0]):
        x0 = w.truth()[0]
        w.step(u)
        ref = np.array(ca.DM(f.step(ca.DM(x0), ca.DM(u), w.dt))).ravel()
        np.testing.assert_allclose(w.truth()[0], ref, rtol=0, atol=1e-12)


def _follow(world, obs, v_ref, look=6.0):
    """A plain pure-pursuit driver along the ego route (bicycle commands)."""
    from scenarios.sim.left_turn import _pose

    x = obs.ego
    p, _ = _pose(world.ego_route, world.progress() + look)
    ang = (math.atan2(p[1] - x[1], p[0] - x[0]) - x[3] + math.pi) % (2 * math.pi) - math.pi
    delta = float(np.clip(math.atan(5.0 * math.sin(ang) / look), -0.7, 0.7))
    return [float(np.clip(v_ref - x[2], -5, 3)), delta]


@pytest.mark.parametrize("geometry", ["g0", "g3"])
def test_oncoming_yields_to_an_early_ego_and_goes_when_the_gap_is_large(geometry):
    cautious = Character(aggressiveness=0.0, desired_speed=10.0, reaction=0.2)
    # early ego: 3 m before the conflict zone at 6 m/s, the oncoming vehicle 25 m away
    w = make_world(
        "left-turn",
        geometry=geometry,
        ego_distance=(3.0, 3.0),
        ego_speed=(6.0, 6.0),
        other_distance=(25.0, 25.0),
        character=cautious,
    )
    obs = w.reset(0)
    ego_in = other_in = None
    v_before = []
    while w.outcome() == "running":
        obs = w.step(_follow(w, obs, 6.0))
        x = w.truth()
        s_o = project_to_polyline(x[1:2, :2], w.other_route)[0][0]
        if ego_in is None and w.progress() >= w.conflict.a[0]:
            ego_in = w.k
        if other_in is None and s_o >= w.conflict.b[0]:
            other_in = w.k
        if other_in is None:
            v_before.append(x[1, 2])
    assert w.outcome() == "success"
    assert "yield" in w.decisions
    assert min(v_before) < 0.5 * cautious.desired_speed  # it braked ...
    assert ego_in < other_in  # ... and the ego went first
    # large gap: the ego stands 20 m before the zone; the oncoming vehicle goes at speed
    w = make_world(
        "left-turn",
        geometry=geometry,
        ego_distance=(20.0, 20.0),
        ego_speed=(0.0, 0.0),
        other_distance=(25.0, 25.0),
        character=cautious,
    )
    w.reset(0)
    for _ in range(60):
        w.step([0.0, 0.0])
    x = w.truth()
    assert set(w.decisions) == {"go"}
    assert project_to_polyline(x[1:2, :2], w.other_route)[0][0] > w.conflict.b[1]
    assert x[1, 2] > 0.9 * cautious.desired_speed
    assert w.outcome() == "timeout" or w.outcome() == "running"


@pytest.mark.parametrize("geometry", ["g0", "g1", "g2", "g3"])
def test_yielding_car_stops_clear_of_the_ego_path_without_reversing(geometry):
    from scenarios.sim.left_turn import WAIT_CLEARANCE

    w = make_world("left-turn", geometry=geometry, noise_std=0.0)
    for seed in (0, 2):  # seed 2: aggressiveness 0.93, the hardest stop
        w.forced_decision = "yield"
        w.reset(seed)
        v = []
        for _ in range(120):  # the ego brakes and stands far away
            w.step([-5.0, 0.0])
            v.append(w.truth()[1, 2])
        x = w.truth()[1]
        d = project_to_polyline(x[None, :2], w.ego_route)[1][0]
        assert min(v) >= 0.0 and abs(v[-1]) < 1e-9  # it stopped, it never reversed
        # its centre is clear of the ego's route by half its length, half the ego's width
        # and a margin, and by the planners' circles (r + r + 1 m), up to 0.3 m of overshoot
        assert d >= WAIT_CLEARANCE - 0.3 and d >= 2 * w.radii[1] + 1.0, (seed, d)


def test_oncoming_goes_when_the_ego_stands_and_waits_clear_of_its_lane():
    # the ego stands with its centre half a length before the conflict zone, its body
    # 0.7 m from the oncoming car's side: a waiting ego, after ``patience`` s the car goes
    kw = dict(geometry="g0", noise_std=0.0, ego_distance=(0.0, 0.0), ego_speed=(0.0, 0.0))
    kw.update(other_distance=(25.0, 25.0), character=Character(0.0, 10.0, 0.2))
    outcome = {}
    for patience in (1.0, 100.0):
        w = make_world("left-turn", patience=patience, **kw)
        w.reset(0)
        for _ in range(60):
            w.step([0.0, 0.0])
        s_o = project_to_polyline(w.truth()[1:, :2], w.other_route)[0][0]
        outcome[patience] = (w.decisions[0], w.decisions[-1], s_o > w.conflict.b[1], w.outcome())
        if patience == 1.0:  # yields at first, goes once the ego has stood still for 1 s
            assert w.decisions.index("go") == round(patience / w.dt) - 1  # 10th decision
    assert outcome[1.0] == ("yield", "go", True, "running")
    assert outcome[100.0] == ("yield", "yield", False, "running")  # without it: a deadlock


def test_slow_oncoming_start_accelerates_to_its_desired_speed():
    w = make_world("left-turn", noise_std=0.0, other_speed=(1.0, 1.0), ego_speed=(0.0, 0.0))
    w.reset(0)
    assert w.truth()[1, 2] == 1.0
    for _ in range(40):
        w.step([0.0, 0.0])
    assert w.truth()[1, 2] > 3.0 and w.tasks()[1].speed == w.character.desired_speed


def test_bold_driver_forces_its_way_where_a_cautious_one_yields():
    # the ego reaches the zone in 20 / 6 = 3.3 s; the oncoming vehicle clears it in ~2.6 s
    kw = dict(geometry="g0", ego_distance=(20.0, 20.0), ego_speed=(6.0, 6.0))
    kw["other_distance"] = (15.0, 15.0)
    seen = {}
    for g in (0.0, 1.0):
        w = make_world("left-turn", character=Character(g, 10.0, 0.2), **kw)
        obs = w.reset(0)
        while w.outcome() == "running" and w.k < 40:
            obs = w.step(_follow(w, obs, 6.0))
        seen[g] = w.decisions[0]
    assert seen == {0.0: "yield", 1.0: "go"}


def test_crossing_pedestrian_yields_or_goes():
    w = make_world("crossing", robot_speed=0.0, character=Character(0.0, 1.2, 0.2))
    yielded = 0
    walked = 0
    for seed in range(6):
        w.reset(seed)
        if w.conflict.a[0] <= w.options.radius:
            continue  # the robot stands inside the zone (the goal is next to it): waited for
        for _ in range(80):
            w.step([0.0, 0.0])  # the robot stands at its start: every gap is large
        assert set(w.decisions) == {"go"}
        assert np.linalg.norm(w.truth()[1, :2] - w.goals[1]) < 0.2  # it walked to its goal
        walked += 1
    assert walked >= 4
    fast = make_world("crossing", robot_speed=1.8, character=Character(0.0, 1.2, 0.2))
    for seed in range(6):
        fast.reset(seed)
        v_min = np.inf
        while fast.outcome() == "running":
            x = fast.truth()[0]
            g = fast.goals[0]
            err = (math.atan2(g[1] - x[1], g[0] - x[0]) - x[3] + math.pi) % (2 * math.pi) - math.pi
            fast.step([0.0, float(np.clip(2 * err, -1.5, 1.5))])
            v_min = min(v_min, fast.truth()[1, 2])
        if "yield" in fast.decisions:
            yielded += 1
            assert v_min < 0.3 and fast.outcome() == "success"
    assert yielded >= 2


def test_collision_against_a_hand_placed_overlap():
    for mode in ("rectangles", "circles"):
        w = make_world("left-turn", collision=mode)
        w.reset(0)
        w.step([0.0, 0.0])
        assert w.outcome() == "running"
        other = w.truth()[1]
        # ego 1 m behind the oncoming vehicle's centre, same heading: the bodies overlap
        back = other[:2] - np.array([math.cos(other[3]), math.sin(other[3])])
        w.set_state(0, [back[0], back[1], 0.0, other[3]])
        w.step([0.0, 0.0])
        assert w.outcome() == "collision", mode
        w.step([0.0, 0.0])
        assert w.outcome() == "collision"  # the first terminal outcome sticks
    # circles: 2 r = 3.5 m (default r = 1.75 m); 3.4 m apart collides, 3.6 m does not
    # (rectangles side by side do not)
    for gap, expect in ((3.4, "collision"), (3.6, "running")):
        w = make_world("left-turn", collision="circles", ego_distance=(30.0, 30.0))
        assert w.radii.tolist() == [1.75, 1.75]
        w.reset(0)
        e = w.truth()[0]
        w.set_state(1, [e[0] - gap, e[1], 0.0, e[3]])
        w.step([0.0, 0.0])
        assert w.outcome() == expect
    c = make_world("crossing")
    c.reset(0)
    c.set_state(1, c.truth()[0] + [0.45, 0.0, 0.0, 0.0])  # 0.45 < 2 x 0.25
    c.step([0.0, 0.0])
    assert c.outcome() == "collision"


def test_off_road_and_timeout():
    w = make_world("left-turn", ego_distance=(30.0, 30.0), max_steps=5)
    w.reset(0)
    e = w.truth()[0]
    w.set_state(0, [e[0] + 20.0, e[1], 0.0, e[3]])  # 20 m to the right of the road
    w.step([0.0, 0.0])
    assert w.outcome() == "off_road"
    w.reset(0)
    for _ in range(5):
        w.step([0.0, 0.0])
    assert w.outcome() == "timeout"


def test_measurement_noise_and_dropouts():
    s = Sensor(3, 0.4, 0.0, 2)
    s.reset(np.random.default_rng(0))
    truth = np.arange(6.0).reshape(3, 2)
    z = np.array([s.measure(truth) for _ in range(4000)]) - truth
    assert abs(z.std() / 0.4 - 1) < 0.03 and abs(z.mean()) < 0.02
    # dropouts: NaN rows in bursts of at least dropout_burst steps; dropout_prob is the
    # fraction of the measurements lost
    p, L = 0.05, 4
    s = Sensor(2, 0.1, p, L)
    s.reset(np.random.default_rng(1))
    nan = np.array([np.isnan(s.measure(truth[:2])) for _ in range(20000)])
    assert np.array_equal(nan[..., 0], nan[..., 1])
    assert abs(nan[..., 0].mean() - p) < 0.01
    for a in range(2):
        runs = np.diff(np.flatnonzero(np.diff(np.r_[0, nan[:, a, 0], 0])))[::2]
        assert runs.min() >= L
    # through a world: the residuals of the oncoming vehicle's position have the set std
    w = make_world("left-turn", noise_std=0.5, dropout_prob=0.0, max_steps=400)
    res = []
    obs = w.reset(0)
    for _ in range(200):
        res.append(obs.others[0] - w.truth()[1, :2])
        obs = w.step([0.0, 0.0])
    assert abs(np.std(res) / 0.5 - 1) < 0.1
    w = make_world("left-turn", dropout_prob=1.0)
    obs = w.reset(0)
    assert isinstance(obs, Observation) and np.isnan(obs.others).all()
    assert np.isfinite(obs.ego).all()


def test_merge_traffic_reacts_to_the_ego():
    w = make_world("merge", traffic=2, spread=0.0, ego_start=(60.0, 60.0), ego_speed=(20.0, 20.0))
    w.reset(0)
    # put the ego right in front of the first vehicle in its lane: IDM brakes for it
    x = w.truth()
    w.set_state(0, [x[1, 0] + 12.0, x[1, 1], x[1, 2] - 5.0, 0.0])
    w.step([0.0, 0.0])
    assert w.truth()[1, 2] < x[1, 2] - 0.2


def test_bad_names_and_options_name_the_field():
    with pytest.raises(
        SpecError, match=r"scenario: unknown scenario 'nope'; valid: left-turn, merge, crossing"
    ):
        make_world("nope")
    cases = [
        ("left-turn", dict(foo=1), r"left-turn\.foo: unknown option"),
        (
            "left-turn",
            dict(geometry="g9"),
            r"left-turn\.geometry: unknown geometry 'g9'; valid: g0",
        ),
        ("left-turn", dict(noise_std=-1.0), r"left-turn\.noise_std"),
        ("left-turn", dict(dropout_prob=2.0), r"left-turn\.dropout_prob"),
        ("left-turn", dict(ego_speed=(5.0, 1.0)), r"left-turn\.ego_speed: expected low <= high"),
        ("left-turn", dict(collision="boxes"), r"left-turn\.collision"),
        ("crossing", dict(dropout_burst=0), r"crossing\.dropout_burst"),
        ("crossing", dict(character="bold"), r"crossing\.character"),
        ("merge", dict(lanes=0), r"merge\.lanes"),
        ("merge", dict(traffic=1.5), r"merge\.traffic"),
    ]
    for name, opts, pattern in cases:
        with pytest.raises(SpecError, match=pattern):
            make_world(name, **opts)
    with pytest.raises(SpecError, match=r"character\.aggressiveness"):
        Character(aggressiveness=1.5)
    w = make_world("crossing")
    with pytest.raises(SpecError, match="reset"):
        w.step([0.0, 0.0])
    w.reset(0)
    with pytest.raises(SpecError, match="command"):
        w.step([0.0, np.nan])
    with pytest.raises(SpecError, match="seed"):
        w.reset(-1)
