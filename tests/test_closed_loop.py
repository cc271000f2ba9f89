"""The closed loop (scenarios.closed_loop), its CLI (epo simulate) and its outputs."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from epo_casadi.errors import SpecError
from scenarios.cli import main
from scenarios.closed_loop import (
    OUTCOMES,
    EpisodeResult,
    SimConfig,
    run_episode,
    run_episodes,
    summarize,
    write_summary,
)
from scenarios.maps import project_to_polyline
from scenarios.sim.left_turn import LeftTurnWorld
from solvers.control.plan import ConstantVelocityPlanner, GameOracle
from solvers.control.types import AgentTask, Command, Estimate, Observation, Plan
from solvers.control.vehicle import VehicleModel

from .helpers import LATE_ACCELERATOR


# --------------------------------------------------------------------------------------
# stand-ins: a unicycle world, a perfect estimator, an open-loop tracker
# --------------------------------------------------------------------------------------
class UnicycleWorld:
    """Ego on a straight northbound lane; one car crossing far ahead (never near)."""

    dt = 0.1
    n_agents = 2
    radii = np.array([1.0, 1.0])
    vehicle = VehicleModel()

    def __init__(self, max_steps: int = 30):
        self.max_steps = max_steps
        path = np.array([[0.0, -50.0], [0.0, 200.0]])
        self.ego_task = AgentTask(path, 8.0, path[-1], 1.0)
        cross = np.array([[-100.0, 80.0], [100.0, 80.0]])
        self._tasks = [self.ego_task, AgentTask(cross, 5.0, cross[-1], 1.0)]

    def reset(self, seed):
        rng = np.random.default_rng(seed)
        self.k = 0
        self.x = np.array([[0.0, 0.0, 6.0 + rng.random(), np.pi / 2], [-60.0, 80.0, 5.0, 0.0]])
        return self._obs()

    def _obs(self):
        return Observation(self.k * self.dt, self.x[0].copy(), self.x[1:, :2].copy())

    def step(self, u):
        x = self.x.copy()
        u = np.stack([np.asarray(u, dtype=float), np.zeros(2)])
        c, s = np.cos(x[:, 3]), np.sin(x[:, 3])
        self.x = x + self.dt * np.stack([x[:, 2] * c, x[:, 2] * s, u[:, 0], u[:, 1]], axis=1)
        self.k += 1
        return self._obs()

    def truth(self):
        return self.x.copy()

    def tasks(self):
        return self._tasks

    def outcome(self):
        return "timeout" if self.k >= self.max_steps else "running"


class PerfectEstimator:
    """The true states of the others (an estimator that cannot be wrong)."""

    def __init__(self, world):
        self.world = world

    def reset(self, obs, dt):
        return self.update(obs)

    def update(self, obs):
        x = self.world.truth()[1:]
        n = len(x)
        return Estimate(x.copy(), np.zeros((n, 4, 4)), x[:, None].copy(), np.ones((n, 1), bool))


class FirstControl:
    """Applies the plan's first unicycle control in the world's vehicle model."""

    def reset(self, world):
        self.vehicle = world.vehicle

    def control(self, ego, plan, t):
        return Command(self.vehicle.clip(self.vehicle.from_unicycle(ego, plan.controls[0])))


class NaNPlanner:
    def reset(self, world):
        pass

    def plan(self, obs, est):
        return Plan(obs.t, 0.1, np.full((5, 4), np.nan), np.full((5, 2), np.nan))


class RaisingPlanner(NaNPlanner):
    def plan(self, obs, est):
        raise RuntimeError("boom")


class StandInConfig:
    """A picklable configuration for run_episodes built from the stand-ins."""

    label = "stand-in cv"

    def to_dict(self):
        return {"stand-in": "cv"}

    def build(self):
        w = UnicycleWorld(max_steps=8)
        return w, PerfectEstimator(w), ConstantVelocityPlanner({"horizon": 10}), FirstControl()


# --------------------------------------------------------------------------------------
# the loop
# --------------------------------------------------------------------------------------
def test_episode_is_bit_identical_for_a_seed():
    cfg = SimConfig("left-turn", planner="cv", tracker="mpc", world_options={"max_steps": 20})
    runs = [run_episode(*cfg.build(), seed=3) for _ in range(2)]
    a, b = (r.log.arrays() for r in runs)
    assert a.keys() == b.keys()
    for k in a:
        if k == "latency":  # wall-clock times, the only thing allowed to differ
            continue
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert runs[0].outcome == runs[1].outcome and runs[0].events == runs[1].events
    assert len(runs[0].log.t) == 20 and np.all(runs[0].log.plan_ok)
    other = run_episode(*cfg.build(), seed=4)
    assert not np.array_equal(other.log.truth, runs[0].log.truth)


@pytest.mark.parametrize("planner", [NaNPlanner(), RaisingPlanner()])
def test_failed_plan_brakes_instead_of_crashing(planner):
    w = UnicycleWorld(max_steps=30)
    r = run_episode(w, PerfectEstimator(w), planner, FirstControl(), seed=0)
    T = len(r.log.t)
    assert r.outcome == "timeout" and T == 30
    assert r.metrics["fallbacks"] == T and np.all(r.log.fallback) and not np.any(r.log.plan_ok)
    assert [e["kind"] for e in r.events] == ["plan_failed"] * T
    if isinstance(planner, RaisingPlanner):
        assert "RuntimeError: boom" in r.events[0]["message"]
    v = r.log.truth[:, 0, 2]
    # the strongest deceleration down to standstill, never reversing
    a = np.maximum(w.vehicle.a_min, -v[:-1] / w.dt)
    np.testing.assert_allclose(r.log.command[:, 0], a)
    np.testing.assert_allclose(r.log.command[:, 1], 0.0)
    assert v[-1] == pytest.approx(0.0, abs=1e-12) and np.all(v >= -1e-12)


def _bold_slow_start(**kw) -> LeftTurnWorld:
    """Unprotected left turns where constant velocity is the wrong prediction: a bold
    oncoming driver (aggressiveness 0.8..1, time margin down to -2 s: it takes its right of
    way) that is slow (0.5..1.5 m/s) 8..12 m before the zone when the ego, 7..9 m before it
    at about 5 m/s, observes it, and then accelerates (IDM) to its desired speed."""
    return LeftTurnWorld(noise_std=0.0, max_steps=40, goal_distance=3.0, **LATE_ACCELERATOR, **kw)


def test_game_oracle_avoids_collisions_where_constant_velocity_collides():
    """The game must matter: on these seeded left turns the CV planner, predicting the slow
    car at its current speed, turns into it (seeds 7 and 14); the oracle, which knows its
    desired speed, lets it pass. Perfect estimates, the plan's first control applied, 2 s
    horizon. Neither planner ever reverses the ego (checked on every episode)."""
    outcomes = {"oracle": [], "cv": []}
    for seed in (0, 1, 7, 14):
        for name, cls in (("oracle", GameOracle), ("cv", ConstantVelocityPlanner)):
            w = _bold_slow_start()
            r = run_episode(w, PerfectEstimator(w), cls({"horizon": 20}), FirstControl(), seed)
            assert w.character.aggressiveness >= 0.8 and r.log.truth[:, 1, 2].max() > 3.0
            outcomes[name].append(r.outcome)
            assert r.log.truth[:, 0, 2].min() >= 0.0, (name, seed)  # the ego never reverses
            if name == "oracle":  # a conflict that was resolved: the car passed the zone
                s = project_to_polyline(w.truth()[1:, :2], w.other_route)[0][0]
                assert s > w.conflict.b[1], (seed, s, w.conflict.b)
    assert "collision" not in outcomes["oracle"], outcomes
    assert outcomes["cv"].count("collision") >= 2, outcomes


# --------------------------------------------------------------------------------------
# runs, outputs, CLI
# --------------------------------------------------------------------------------------
def test_run_episodes_writes_and_resumes(tmp_path):
    out = tmp_path / "run"
    rep = run_episodes(StandInConfig(), 3, seed=5, out=out, progress=False)
    assert rep.ran == 3 and rep.kept == 0
    assert [r.seed for r in rep.results] == [5, 6, 7]
    assert 0 in rep.logs and (out / "episodes" / "episode-00000.npz").is_file()
    (out / "episodes" / "episode-00001.json").unlink()
    again = run_episodes(StandInConfig(), 3, seed=5, out=out, progress=False)
    assert again.ran == 1 and again.kept == 2
    for a, b in zip(rep.results, again.results, strict=True):
        assert a.outcome == b.outcome
        assert {k: v for k, v in a.metrics.items() if "ms" not in k and k != "rtf"} == {
            k: v for k, v in b.metrics.items() if "ms" not in k and k != "rtf"
        }
    with pytest.raises(SpecError, match="another configuration or seed"):
        run_episodes(StandInConfig(), 3, seed=6, out=out, progress=False)
    rows = _csv_rows(out / "episodes.csv")
    assert [int(r["seed"]) for r in rows] == [5, 6, 7]
    assert not list((out / "episodes").glob(".*.tmp"))


def _csv_rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def _result(i, outcome, **metrics):
    return EpisodeResult(i, i, outcome, metrics, [], [10.0 + i, 20.0], message="")


def test_summary_handles_every_outcome(tmp_path):
    results = [
        _result(
            0,
            "success",
            min_distance=1.0,
            time_to_clear=4.0,
            progress=50.0,
            rms_jerk=1.0,
            rtf=0.3,
            fallbacks=0,
        ),
        _result(
            1,
            "collision",
            min_distance=-0.5,
            time_to_clear=math.nan,
            progress=20.0,
            rms_jerk=2.0,
            rtf=0.5,
            fallbacks=2,
        ),
        _result(
            2,
            "timeout",
            min_distance=3.0,
            time_to_clear=math.nan,
            progress=5.0,
            rms_jerk=math.nan,
            rtf=0.4,
            fallbacks=1,
        ),
        _result(
            3,
            "off_road",
            min_distance=2.0,
            time_to_clear=math.nan,
            progress=10.0,
            rms_jerk=0.5,
            rtf=0.2,
            fallbacks=0,
        ),
        EpisodeResult(4, 4, "error", {}, [], [], message="RuntimeError: world broke"),
    ]
    assert {r.outcome for r in results} == set(OUTCOMES)
    s = summarize(results, "x")
    for o in OUTCOMES:
        assert s[f"{o}_rate"] == pytest.approx(0.2)
    assert s["min_distance"] == pytest.approx(1.375)  # error episode has no metrics
    assert s["time_to_clear"] == pytest.approx(4.0)  # only the episode that cleared
    assert s["fallbacks"] == 3
    assert s["plan_p50_ms"] == pytest.approx(np.percentile([10, 20, 11, 20, 12, 20, 13, 20], 50))
    write_summary(tmp_path, results, s)
    md = (tmp_path / "summary.md").read_text()
    table, note = md.split("\n\n")
    assert table.count("\n") == 2 and "| x | 5 | 0.20 | 0.20 |" in table
    # the episodes that ended in an error are said in words below the table
    assert note == "1 of 5 episodes ended in an error; the first, episode 4 (seed 4): " + (
        "RuntimeError: world broke\n"
    )
    rows = _csv_rows(tmp_path / "episodes.csv")
    assert [r["outcome"] for r in rows] == list(OUTCOMES)
    assert rows[4]["message"] == "RuntimeError: world broke" and rows[4]["min_distance"] == ""
    assert rows[1]["time_to_clear"] == ""
    # nothing at all defined: n/a, not a crash
    empty = summarize([results[4]], "e")
    write_summary(tmp_path / "e", [results[4]], empty)
    assert "n/a" in (tmp_path / "e" / "summary.md").read_text()
    json.dumps(results[1].to_dict(), allow_nan=False)  # NaN metrics become null


@pytest.mark.parametrize(
    "args, message",
    [
        (["highway-9"], "unknown scenario 'highway-9'"),
        (["left-turn", "--planner", "mpc"], "Invalid value for '--planner'"),
        (["left-turn", "--tracker", "lqr"], "Invalid value for '--tracker'"),
        (["left-turn", "--planner", "model"], "--planner model needs a trained run"),
        (["left-turn", "--planner", "oracle", "--model", "."], "only used by --planner model"),
        (["left-turn", "--planner", "sc", "--model", "/no/such/run"], "no run directory"),
        (["left-turn", "--episodes", "0"], "Invalid value for '--episodes'"),
        (["left-turn", "--noise", "-1"], "expected a number >= 0"),
        (["left-turn", "--dropout", "2"], "expected a number in [0, 1]"),
        (["left-turn", "--set", "wrld.x=1"], "expected world.KEY"),
        (["left-turn", "--set", "world.lanes=3"], "left-turn.lanes: unknown option"),
        (["left-turn", "--geometry", "g9"], "unknown geometry 'g9'"),
        (["left-turn", "--set", "planner.horizn=3"], "unknown option(s) ['horizn']"),
    ],
)
def test_cli_errors_are_one_line_exit_2(args, message, tmp_path, capsys):
    rc = main(["simulate", *args, "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert message in err, err
    assert "Traceback" not in err


def test_figures_of_a_run(tmp_path):
    from PIL import Image

    from scenarios.commands.simulate import write_figures

    rep = run_episodes(StandInConfig(), 2, seed=0, out=tmp_path, progress=False)
    paths = write_figures(tmp_path, rep)
    assert [p.name for p in paths] == ["episode-00000.png", "episode-00000.gif", "latency.png"]
    with Image.open(paths[1]) as gif:
        assert gif.n_frames == len(rep.logs[0].truth)  # one frame per period (8 steps + end)
    for p in paths:
        assert p.stat().st_size > 1000
