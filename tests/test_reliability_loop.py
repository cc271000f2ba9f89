"""Reliability of the closed loop: ``epo simulate``, its worlds, estimator, planners, trackers.

One regression test per defect; each docstring names the class of defects it closes. The
episodes are tiny (the crossing world, a few steps, short horizons); the one trained model is
a one-epoch SC network on the synthetic RPI set of ``tests/test_models.py``.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import scenarios.closed_loop as closed_loop
from epo_casadi.errors import OutputError, SpecError
from scenarios.closed_loop import EpisodeResult, SimConfig, run_episodes
from scenarios.closed_loop import loop as episode_loop
from scenarios.sim import make_world
from scenarios.sim.common import Character, Sensor
from solvers.control.estimate import UKFEstimator, UKFOptions
from solvers.control.plan import ConstantVelocityPlanner, GameOracle, PlannerOptions
from solvers.control.track import MPCOptions, MPCTracker, PIDTracker
from solvers.control.types import Observation, Plan
from solvers.control.vehicle import VehicleModel
from tests.helpers import cli, one_error_line, proc_children, process_family, survivors
from tests.test_plan import TwoCarScene

ROOT = Path(__file__).resolve().parents[1]
DT = 0.1
#: a cheap closed loop: the RPI crossing, 3 steps, a short CV horizon, the PID tracker
QUICK = ["crossing", "--planner", "cv", "--tracker", "pid", "--no-progress", "--no-figures",
         "--set", "world.max_steps=3", "--set", "planner.horizon=5"]  # fmt: skip


def simulate(capsys, *args):
    return cli(capsys, "simulate", *args)


# ------------------------------------------------------------------------ model identity
@pytest.fixture(scope="module")
def sc_run(tmp_path_factory):
    """A one-epoch tiny SC run on the synthetic RPI set (plays the crossing world)."""
    from learning.models import ModelConfig
    from learning.train import TrainConfig, train
    from tests.test_models import TINY, synthetic_dataset

    cfg = TrainConfig(
        model=ModelConfig(kind="sc", **TINY), epochs=1, batch_size=8, lr=1e-3, val_split=None
    )
    run = tmp_path_factory.mktemp("sc") / "run"
    train(synthetic_dataset(), run, cfg, progress=False)
    return SimpleNamespace(dir=run, cfg=cfg)


def test_resume_after_further_training_is_refused_naming_the_checkpoint(sc_run, tmp_path, capsys):
    """Class closed: a resumed ``simulate --planner sc/model`` mixes episodes of two models
    when the run was trained further in between (config.json named the run's path only).
    The checkpoint's SHA-256, epoch and step are recorded; a resume against another
    checkpoint is one line naming the field."""
    import shutil

    from learning.train import train
    from tests.test_models import synthetic_dataset

    run = tmp_path / "run"
    shutil.copytree(sc_run.dir, run)
    out = tmp_path / "sim"
    args = ["crossing", "--planner", "sc", "--model", run, "--tracker", "pid", "--workers", 1,
            "--no-progress", "--no-figures", "--set", "world.max_steps=2", "--out", out]  # fmt: skip
    rc, _, err = simulate(capsys, *args, "--episodes", 1)
    assert rc == 0, err
    header = json.loads((out / "config.json").read_text())
    ident = header["config"]["model_checkpoint"]
    assert ident["checkpoint"] == "best.pt" and ident["epoch"] == 1 and ident["step"] > 0
    from scenarios.dataset import sha256_file

    assert ident["sha256"] == sha256_file(run / "best.pt")
    rc, stdout, err = simulate(capsys, *args, "--episodes", 2)  # the same model: resumed
    assert rc == 0 and "(1 run, 1 kept)" in stdout, (stdout, err)
    train(synthetic_dataset(), run, replace(sc_run.cfg, epochs=2), progress=False)  # further
    before = sorted(p.name for p in (out / "episodes").iterdir())
    rc, _, err = simulate(capsys, *args, "--episodes", 3)
    line = one_error_line(rc, err, "config.json", "config.model_checkpoint.sha256", "there")
    assert "config.model_checkpoint.epoch (1 there, 2 asked)" in line, line
    assert sorted(p.name for p in (out / "episodes").iterdir()) == before  # nothing mixed in


def test_workers_refuse_a_checkpoint_that_changed_during_the_run(sc_run):
    """Class closed: within one run, workers load the run directory again; a checkpoint
    replaced meanwhile would give episodes of another model. A pinned configuration
    (``model_checkpoint``, set from the first build) refuses any other checkpoint."""
    cfg = SimConfig("crossing", planner="sc", model=str(sc_run.dir), tracker="pid")
    world, _, planner, _ = cfg.build()
    pinned = cfg.pinned(planner)
    assert pinned.model_checkpoint == planner.identity and pinned.pinned(planner) is pinned
    pinned.build()  # the same checkpoint: fine
    stale = replace(cfg, model_checkpoint={**planner.identity, "sha256": "0" * 64})
    with pytest.raises(SpecError) as e:
        stale.build()
    assert e.value.field == "model_checkpoint.sha256" and "changed" in e.value.message
    # an oracle configuration has no model to pin
    oracle = SimConfig("crossing")
    assert oracle.pinned(GameOracle()) is oracle and "model_checkpoint" not in oracle.to_dict()


def test_network_planner_never_raises_on_a_missing_observation(sc_run):
    """Class closed: the planners' documented promise (never raise) broken by a missing
    observation or estimate."""
    from learning.planner import load_planner

    world = make_world("crossing")
    planner = load_planner(sc_run.dir, world)
    for obs, est in ((None, None), (Observation(0.0, np.zeros(4), np.zeros((1, 2))), None)):
        plan = planner.plan(obs, est)
        assert isinstance(plan, Plan) and not plan.ok and np.isnan(plan.states).all()


# ------------------------------------------------------------------------ trackers
def _straight_plan(t0=0.0, K=30):
    S = np.stack(
        [8.0 * DT * np.arange(1, K + 1), np.zeros(K), np.full(K, 8.0), np.zeros(K)], axis=1
    )
    return Plan(t0, DT, S, np.zeros((K, 2)))


WORLD = SimpleNamespace(vehicle=VehicleModel.highway(), dt=DT)
EGO = np.array([0.0, 0.3, 7.5, 0.02])


@pytest.mark.parametrize("bad_t", [float("nan"), float("inf"), None, "0.1"])
@pytest.mark.parametrize("cls", [PIDTracker, MPCTracker])
def test_a_non_finite_time_brakes_once_and_does_not_poison_the_tracker(cls, bad_t):
    """Class closed: ``PIDTracker.control`` with a NaN time returned NaN commands (no
    fallback) and NaN for every later valid call (NaN integrators); the MPC's QP kept the
    NaN numbers and fell back on every later call too. A bad time brakes, leaves the
    tracker's loops as they were, and the next valid call tracks."""
    ref, tracker = cls(), cls()
    ref.reset(WORLD)
    tracker.reset(WORLD)
    for k in range(3):
        ref.control(EGO, _straight_plan(k * DT), k * DT)
        tracker.control(EGO, _straight_plan(k * DT), k * DT)
    state = {k: v for k, v in vars(tracker).items() if k.startswith("_i") or k.endswith("prev")}
    cmd = tracker.control(EGO, _straight_plan(0.3), bad_t)
    assert cmd.fallback and "time t" in cmd.info["reason"] and np.isfinite(cmd.value).all()
    assert tracker.fallbacks == 1
    if cls is PIDTracker:  # integrators and previous errors untouched
        for k, v in state.items():
            if k != "u_prev":
                assert getattr(tracker, k) == v, k
    for k in range(3, 8):
        cmd = tracker.control(EGO, _straight_plan(k * DT), k * DT)
        assert not cmd.fallback and np.isfinite(cmd.value).all(), (k, cmd)
    assert tracker.fallbacks == 1


def test_mpc_recovers_after_numbers_osqp_cannot_take():
    """Class closed: one call with a plan far out of range (finite, 1e200) broke OSQP's
    KKT update and every later call fell back. Such numbers never reach OSQP, and after a
    QP that OSQP did not solve the next call starts from a fresh set-up."""
    mpc = MPCTracker()
    mpc.reset(WORLD)
    far = _straight_plan()
    far = Plan(0.0, DT, far.states * 1e200, far.controls)
    assert mpc.control(EGO, far, 0.0).fallback
    assert not mpc.control(EGO, _straight_plan(), 0.0).fallback and mpc.setups == 1

    # an unsolved QP (faked once): the next call sets the QP up again and solves
    def unsolved(**kw):
        return SimpleNamespace(info=SimpleNamespace(status="faked", status_val=-99), x=None)

    mpc.solver.solve = unsolved
    assert mpc.control(EGO, _straight_plan(0.1), 0.1).fallback
    cmd = mpc.control(EGO, _straight_plan(0.2), 0.2)
    assert not cmd.fallback and mpc.setups == 2 and cmd.info["status"] == "solved"


@pytest.mark.parametrize("cls", [PIDTracker, MPCTracker])
def test_control_before_reset_is_a_spec_error(cls):
    """Class closed: ``PIDTracker.control`` before ``reset`` was an AttributeError traceback."""
    with pytest.raises(SpecError) as e:
        cls().control(EGO, _straight_plan(), 0.0)
    assert e.value.field == "tracker" and "before reset" in e.value.message


# ------------------------------------------------------------------------ estimator
@pytest.mark.parametrize("bad", [1e200, -1e200, 2e6, np.inf])
def test_ukf_rejects_absurd_measurements_and_never_goes_nan(bad):
    """Class closed: a UKF measurement of 1e200 gave NaN states and then a ValueError
    traceback in the next predict. Such a measurement (infinite, or farther than
    ``max_position`` from the origin) is rejected as an outlier: the filter only predicts,
    the step is marked not valid, ``rejected`` counts it, and tracking goes on."""
    est = UKFEstimator()
    e = est.reset(Observation(0.0, np.zeros(4), np.zeros((1, 2))), DT)
    for k in range(1, 5):
        e = est.update(Observation(k * DT, np.zeros(4), np.array([[0.8 * k, 0.0]])))
    before = e.states.copy()
    e = est.update(Observation(0.5, np.zeros(4), np.array([[bad, 0.0]])))
    assert est.rejected == 1 and not e.valid[0, -1]
    assert np.isfinite(e.states).all() and np.isfinite(e.covariances).all()
    assert abs(e.states[0, 0] - before[0, 0] - 0.8) < 0.2  # predicted on at ~8 m/s
    for k in range(6, 10):
        e = est.update(Observation(k * DT, np.zeros(4), np.array([[0.8 * k, 0.0]])))
        assert e.valid[0, -1]
    assert np.isfinite(e.history).all() and abs(e.states[0, 0] - 7.2) < 0.3
    assert est.rejected == 1
    # a NaN row stays a dropout, not an outlier
    est.update(Observation(1.0, np.zeros(4), np.array([[np.nan, 0.0]])))
    assert est.rejected == 1
    with pytest.raises(SpecError, match="ukf.max_position"):
        UKFOptions(max_position=0.0)


# ------------------------------------------------------------------------ planners
@pytest.mark.parametrize("cls", [GameOracle, ConstantVelocityPlanner])
def test_game_planners_never_raise_on_a_missing_estimate(cls):
    """Class closed: ``GameOracle.plan(obs, None)`` and the CV planner's raised an
    AttributeError although the docs promise a failed plan; the code now keeps the promise
    (a missing or malformed observation or estimate is ``Plan(ok=False)``)."""
    scene = TwoCarScene()
    planner = cls({"horizon": 5})
    planner.reset(scene)
    obs, est = scene.observe()
    for o, e, words in (
        (obs, None, "expected an Estimate, got NoneType"),
        (None, est, "finite time t"),
        (None, None, "finite time t"),
        (obs, "states", "expected an Estimate, got str"),
        (Observation(float("nan"), obs.ego, obs.others), est, "finite time t"),
    ):
        plan = planner.plan(o, e)
        assert isinstance(plan, Plan) and not plan.ok and words in plan.message, plan.message
        assert plan.states.shape == (5, 4) and np.isnan(plan.states).all()
    assert planner.plan(obs, est).ok  # and it plans again


# ------------------------------------------------------------------------ size bounds
@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: PlannerOptions(horizon=100_000_000), "planner.horizon"),
        (lambda: PlannerOptions(path_points=10**9), "planner.path_points"),
        (lambda: PlannerOptions(first_steps=10**9), "planner.first_steps"),
        (lambda: UKFOptions(history=1_000_000_000), "ukf.history"),
        (lambda: UKFOptions(init_points=10**6), "ukf.init_points"),
        (lambda: MPCOptions(horizon=100_000), "mpc.horizon"),
        (lambda: MPCOptions(max_iter=10**12), "mpc.max_iter"),
        (lambda: make_world("crossing", max_steps=10**9), "crossing.max_steps"),
        (lambda: make_world("crossing", n_path=10**9), "crossing.n_path"),
        (lambda: make_world("left-turn", dropout_burst=10**9), "left-turn.dropout_burst"),
        (lambda: make_world("merge", traffic=10**6), "merge.traffic"),
    ],
)
def test_every_size_option_is_bounded(make, field):
    """Class closed: sizes of the world, planner, tracker and estimator passed validation
    however large (every episode then failed allocating). One mechanism,
    ``check_size``: the message names the field and the limit."""
    with pytest.raises(SpecError) as e:
        make()
    assert e.value.field == field and "over the limit of" in e.value.message, e.value


def test_oversized_options_and_episodes_are_refused_before_any_work(tmp_path, capsys):
    """Class closed: ``--set planner.horizon=1e8`` / ``estimator.history=1e9`` passed, every
    episode errored and the command exited 0; ``--episodes 1e9`` built a list of every
    episode number (20 GB). All are refused in one line before anything is written."""
    out = tmp_path / "o"
    for extra, words in (
        (["--set", "planner.horizon=100000000"], ("planner.horizon", "100,000,000", "1,000")),
        (["--set", "estimator.history=1000000000"], ("ukf.history", "1,000")),
        (["--set", "tracker.horizon=100000"], ()),
        (["--episodes", "1000000000"], ("--episodes", "100,000")),
    ):
        tracker = ["--tracker", "mpc"] if "tracker.horizon" in str(extra) else []
        base = QUICK[:-2] if "planner.horizon" in str(extra) else QUICK
        rc, _, err = simulate(capsys, *base, *extra, *tracker, "--out", out)
        one_error_line(rc, err, "over the limit", *words)
        assert not out.exists()
    with pytest.raises(SpecError, match="episodes"):
        run_episodes(SimConfig("crossing"), 10**9, out=out, progress=False)
    assert not out.exists()


# ------------------------------------------------------------------------ exit status
def _fake_episode(fail):
    def run_episode(world, estimator, planner, tracker, seed, index=0, keep_log=True, **kw):
        if fail(seed):
            raise RuntimeError(f"world broke at seed {seed}")
        return EpisodeResult(index, seed, "success", {"fallbacks": 0}, [], [1.0, 2.0])

    return run_episode


def test_a_run_where_every_episode_errored_exits_1(tmp_path, capsys, monkeypatch):
    """Class closed: every episode errored and ``epo simulate`` exited 0. Status 1 and one
    line with the count and the first error; summary.md says it too."""
    monkeypatch.setattr(episode_loop, "run_episode", _fake_episode(lambda s: True))
    out = tmp_path / "o"
    rc, stdout, err = simulate(capsys, *QUICK, "--episodes", 2, "--workers", 1, "--out", out)
    assert rc == 1, err
    msg = "2 of 2 episodes ended in an error; the first, episode 0 (seed 0): RuntimeError: world broke at seed 0"
    assert err.strip().splitlines() == [f"error: {msg}"]
    assert msg in (out / "summary.md").read_text()
    # some errored: exit 0, one warning line, and summary.md names them
    monkeypatch.setattr(episode_loop, "run_episode", _fake_episode(lambda s: s == 1))
    out = tmp_path / "p"
    rc, _, err = simulate(capsys, *QUICK, "--episodes", 3, "--workers", 1, "--out", out)
    msg = "1 of 3 episodes ended in an error; the first, episode 1 (seed 1): RuntimeError"
    assert rc == 0 and len(err.strip().splitlines()) == 1 and err.startswith(f"warning: {msg}")
    assert msg in (out / "summary.md").read_text()


# ------------------------------------------------------------------------ workers
def test_workers_are_capped_to_the_usable_cores(tmp_path, capsys, monkeypatch):
    """Class closed: ``--workers 8`` on 2 cores started 8 processes (latencies inflated
    threefold). It is lowered to the usable cores with one warning line."""
    import scenarios.commands.dataset_options as generate

    seen = {}

    def fake_run(config, episodes, **kw):
        seen.update(kw)
        raise SpecError("stop", "here")

    monkeypatch.setattr(generate, "cores", lambda: 2)
    monkeypatch.setattr(closed_loop, "run_episodes", fake_run)
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # the test suite turns warnings into errors
        rc, _, err = simulate(capsys, *QUICK, "--episodes", 10, "--workers", 8, "--out", tmp_path)
    lines = err.strip().splitlines()
    assert lines[0] == "warning: --workers 8 is more than the 2 usable core(s); using 2"
    assert seen["workers"] == 2 and rc == 2 and lines[1] == "error: stop: here"
    rc, _, err = simulate(capsys, *QUICK, "--episodes", 10, "--workers", 2, "--out", tmp_path)
    assert "warning" not in err and seen["workers"] == 2


# ------------------------------------------------------------------------ outputs
def test_full_disk_is_one_line_and_leaves_no_temporary(tmp_path, capsys, monkeypatch):
    """Class closed: a full disk under ``simulate --out`` was an OSError traceback and left
    temporary files. Every output is written by ``scenarios.files.write_atomic``."""
    out = tmp_path / "o"

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    rc, _, err = simulate(capsys, *QUICK, "--episodes", 1, "--workers", 1, "--out", out)
    one_error_line(rc, err, "config.json: cannot write: no space left on the device")
    assert [p.name for p in out.iterdir()] == [".lock"]
    # the figures too
    monkeypatch.undo()
    from scenarios.commands.simulate import write_figures
    from tests.test_closed_loop import StandInConfig

    rep = run_episodes(StandInConfig(), 1, out=tmp_path / "f", progress=False)
    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OutputError, match="episode-00000.png: cannot write: no space left"):
        write_figures(tmp_path / "f", rep)
    assert not [p for p in (tmp_path / "f" / "figures").iterdir()]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_out_is_one_line(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        rc, _, err = simulate(capsys, *QUICK, "--episodes", 1, "--out", ro / "o")
        one_error_line(rc, err, "cannot write")
    finally:
        ro.chmod(0o700)


def test_out_through_a_file_and_a_changed_configuration_are_one_line(tmp_path, capsys):
    """An --out inside a file is refused before any work; a rerun with another world
    option names the differing field."""
    f = tmp_path / "notes.txt"
    f.write_text("mine")
    rc, _, err = simulate(capsys, *QUICK, "--episodes", 1, "--out", f / "run")
    one_error_line(rc, err, "is a file")
    assert f.read_text() == "mine"
    out = tmp_path / "o"
    rc, _, err = simulate(capsys, *QUICK, "--episodes", 1, "--workers", 1, "--out", out)
    assert rc == 0, err
    args = [a if a != "world.max_steps=3" else "world.max_steps=4" for a in QUICK]
    rc, _, err = simulate(capsys, *args, "--episodes", 1, "--out", out)
    one_error_line(rc, err, "config.world_options.max_steps (3 there, 4 asked)")


# ------------------------------------------------------------------------ options
def test_desired_speeds_the_world_cannot_honour_are_refused():
    """Class closed: ``world.desired_speed`` above 1 (a fraction of the speed limit) did
    nothing (IDM clips to the lane's limit) while the oracle was told the higher speed."""
    with pytest.raises(SpecError) as e:
        make_world("left-turn", desired_speed=(0.8, 1.5))
    assert e.value.field == "left-turn.desired_speed" and "[0.05, 1.0]" in e.value.message
    make_world("left-turn", desired_speed=(1.0, 1.0))  # the limit itself is fine
    fast = Character(aggressiveness=0.5, desired_speed=13.0, reaction=0.5)
    with pytest.raises(SpecError) as e:
        make_world("left-turn", geometry="g0", character=fast)
    assert e.value.field == "left-turn.character.desired_speed" and "12 m/s" in e.value.message
    make_world("left-turn", geometry="g2", character=fast)  # g2's limit is 14 m/s
    with pytest.raises(SpecError, match=r"merge\.desired_speed"):
        make_world("merge", desired_speed=(0.9, 1.2))


@pytest.mark.parametrize("p, burst", [(0.1, 3), (0.3, 3), (0.5, 5), (0.2, 1), (1.0, 3)])
def test_dropout_probability_is_the_lost_fraction(p, burst):
    """Class closed: ``--dropout p`` lost about 2p of the measurements (3-step bursts, each
    started with probability p). The lost fraction is p on average, bursts kept."""
    s = Sensor(3, 0.0, p, burst)
    s.reset(np.random.default_rng(7))
    lost = np.array([np.isnan(s.measure(np.zeros((3, 2))))[:, 0] for _ in range(20000)])
    assert abs(lost.mean() - p) < 0.015, lost.mean()
    # through a world, as --dropout sets it
    w = make_world("crossing", dropout_prob=p, dropout_burst=burst, max_steps=10**4)
    obs = [w.reset(0).others]
    for _ in range(3000):
        obs.append(w.step([0.0, 0.0]).others)
    assert abs(np.isnan(np.array(obs)[..., 0]).mean() - p) < 0.05


def test_noise_with_set_noise_std_is_an_error_naming_both(tmp_path, capsys):
    """Class closed: ``--noise`` silently overrode ``--set world.noise_std``."""
    for opt, key in (("--noise", "noise_std"), ("--dropout", "dropout_prob"),
                     ("--geometry", "geometry")):  # fmt: skip
        value = "g1" if opt == "--geometry" else "0.1"
        rc, _, err = simulate(
            capsys,
            "left-turn",
            opt,
            value,
            "--set",
            f"world.{key}={value}",
            "--out",
            tmp_path / "o",
        )
        one_error_line(rc, err, opt, f"--set world.{key}")
    assert not (tmp_path / "o").exists()


def test_scheduler_timeout_is_an_option_of_simulate(tmp_path, capsys):
    """Class closed: the dask timeout message recommended ``--scheduler-timeout``, which
    ``simulate`` did not have."""
    pytest.importorskip("distributed")
    rc, _, err = simulate(
        capsys, *QUICK, "--episodes", 1, "--engine", "dask", "--scheduler", "tcp://127.0.0.1:9",
        "--scheduler-timeout", "0.5", "--out", tmp_path / "o",
    )  # fmt: skip
    one_error_line(rc, err, "scheduler", "tcp://127.0.0.1:9", "0.5 s", "--scheduler-timeout")


# ------------------------------------------------------------------------ SIGTERM
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux)")
def test_sigterm_stops_simulate_like_ctrl_c(tmp_path):
    """Class closed: SIGTERM killed ``epo simulate`` with status 143 and a leaked-semaphore
    warning from its worker pool. It now stops as Ctrl-C does: 130, the pool shut down,
    no traceback, no process left, the finished episodes kept."""
    out = tmp_path / "o"
    need = 2 if len(os.sched_getaffinity(0)) >= 2 else 0  # one core: no pool to wait for
    args = [sys.executable, "-m", "scenarios.cli", "simulate", *QUICK, "--episodes", "2000",
            "--workers", "2", "--out", str(out)]  # fmt: skip
    with open(tmp_path / "log.txt", "w+") as log:
        p = subprocess.Popen(args, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 240
            while time.monotonic() < deadline and p.poll() is None:
                done = list((out / "episodes").glob("episode-*.json")) if out.exists() else []
                if done and len(proc_children(p.pid)) >= need:
                    break
                time.sleep(0.05)
            assert p.poll() is None, "the run ended before it could be stopped"
            family = process_family(p.pid)
            p.send_signal(signal.SIGTERM)
            p.wait(60)
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
        log.seek(0)
        text = log.read()
    alive = survivors(family)
    assert not alive, f"processes outlived the stopped run: {alive}"
    assert p.returncode == 130, (p.returncode, text)
    assert "Traceback" not in text and "leaked" not in text, text
    assert text.strip().splitlines()[-1] in ("Aborted.", "Interrupted.")
    assert list((out / "episodes").glob("episode-*.json"))  # finished episodes kept
