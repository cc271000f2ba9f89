"""The continuation fallback of every registered solver (solvers.continuation).

References computed another way: the potential's gradient from the game's own ``gradient``
function at the game's own parameters (not the stages' scaled ones), the energy from the
game's ``energy`` function, the Nash certificate's best responses, and the solver's own
entry function called without the wrapper (``SolverEntry.function``) for the results that
must not change. The stage logic (which weights, which warm starts, which result is kept,
when no continuation runs) is checked exactly on a recording solver.
"""

from __future__ import annotations

import inspect
import json
from dataclasses import dataclass, field

import numpy as np
import pytest
import yaml

from epo_casadi import PotentialGame
from epo_casadi.errors import SpecError
from scenarios.gamefile import example_path, load_game, parse_game
from solvers import ILQOptions, IpoptOptions, LMOptions, OLNEOptions, SQPOptions
from solvers.compare import parse_solver
from solvers.continuation import KINK_WIDTHS, WEIGHT_SCALES, ContinuedSolve
from solvers.feedback_nash import check_ilq_result
from solvers.nash import nash_certificate
from solvers.registry import SOLVERS, register_solver, solve_game, unregister_solver
from solvers.result import SolveResult, Status

from .helpers import family_spec

#: the 6-vehicle bicycle intersection at collision weight 300 (K = 20): LM's default first
#: attempt ends at its iteration limit, far from stationary
HARD = ("intersection", 6, "bicycle", 300.0, 0, 20)
_games: dict = {}


def game_of(args) -> tuple[PotentialGame, np.ndarray]:
    if args not in _games:
        g = PotentialGame(family_spec(*args))
        _games[args] = (g, g.default_params())
    return _games[args]


def _grad(g, p, u) -> float:
    return float(np.abs(np.asarray(g.function("gradient")(u, p))).max())


# ----------------------------------------------------------------------------- a real game
def test_lm_first_attempt_stalls_and_the_continuation_converges():
    g, p = game_of(HARD)
    coll = [t.index for t in g.terms if t.feature_type == "collision"]
    te = np.asarray(g.function("term_energies")(g.zero_controls(), p)).ravel()
    assert sum(te[i] for i in coll) > 1.0  # the regime: in collision at the start
    first = SOLVERS["lm"].function(g, p, None, LMOptions())
    assert first.status is Status.MAX_ITER and _grad(g, p, first.controls) > 1.0

    res = solve_game(g, p, solver="lm")
    assert res.status is Status.CONVERGED
    # the point is judged at the game's own weights, by references the solver did not use
    E = float(np.asarray(g.function("energy")(res.controls, p)).ravel()[0])
    assert E == pytest.approx(float(res.energy), rel=1e-12)
    assert _grad(g, p, res.controls) <= 1e-4 * (1 + abs(E))
    assert E < 0.5 * float(first.energy)
    cert = nash_certificate(g, p=p, u=res.controls)
    assert cert.verdict == "passes", cert.reasons
    assert float(np.max(cert.best_response_gap)) <= 1e-6

    att = res.info["attempts"]
    assert [a["stage"] for a in att] == ["first"] + ["weight"] * (len(WEIGHT_SCALES) + 1)
    assert [a["weight_scale"] for a in att] == [1.0, *WEIGHT_SCALES, 1.0]
    assert (att[0]["status"], att[0]["iterations"]) == ("max_iter", int(first.iterations))
    assert att[0]["energy"] == float(first.energy)
    assert att[-1]["kept"] and att[-1]["status"] == "converged"
    assert sum(a.get("kept", False) for a in att) == 1
    assert int(res.iterations) == sum(a["iterations"] for a in att)
    assert res.wall_time >= sum(a["seconds"] for a in att)


def test_epo_solve_writes_and_prints_the_attempts(capsys, tmp_path):
    from scenarios.gamefile import dump_game

    from .helpers import cli

    path, out = tmp_path / "hard.yaml", tmp_path / "r.json"
    path.write_text(yaml.safe_dump(dump_game(family_spec(*HARD))))
    rc, stdout, err = cli(capsys, "solve", path, "--out", out, "--no-certificate")
    assert rc == 0, err
    data = json.loads(out.read_text())
    assert data["status"] == "converged" and data["attempts"][0]["status"] == "max_iter"
    assert [a["weight_scale"] for a in data["attempts"]] == pytest.approx(
        [1.0, *WEIGHT_SCALES, 1.0]
    )
    assert data["iterations"] == sum(a["iterations"] for a in data["attempts"])
    line = next(ln for ln in stdout.splitlines() if "continuation:" in ln)
    assert "first attempt max_iter after 500 iterations; 5 more solves" in line
    assert "kept: weight at weight scale 1 (converged)" in line
    # the switch in the game file: the first attempt, no attempts in the file
    d = yaml.safe_load(path.read_text())
    d["solver"] = {"lm": {"continuation": False}}
    path.write_text(yaml.safe_dump(d))
    rc, stdout, err = cli(capsys, "solve", path, "--out", out, "--no-certificate")
    data = json.loads(out.read_text())
    assert rc == 0 and data["status"] == "max_iter" and data["attempts"] is None
    assert data["iterations"] == 500 and "continuation:" not in stdout


def test_switch_off_gives_the_first_attempt_on_every_front_door():
    g, p = game_of(HARD)
    ref = SOLVERS["lm"].function(g, p, None, LMOptions())
    for options in ({"continuation": False}, LMOptions(continuation=False)):
        off = solve_game(g, p, solver="lm", options=options)
        assert "attempts" not in off.info
        assert off.status is ref.status is Status.MAX_ITER
        assert np.array_equal(off.controls, ref.controls) and off.iterations == ref.iterations
    # epo compare's and a game file's way of saying it
    assert parse_solver("lm:continuation=false").options_object == LMOptions(continuation=False)
    d = yaml.safe_load(example_path("crossing2").read_text())
    d["solver"] = {"ilq": {"continuation": False}}
    assert parse_game(d).options("ilq") == ILQOptions(continuation=False)
    d["solver"] = {"sqp": {"continuation": "no"}}
    with pytest.raises(SpecError) as e:
        parse_game(d)
    assert e.value.field == "solver.sqp.continuation"


@pytest.mark.parametrize("name", ["lm", "ipopt", "ilq", "sqp", "olne"])
def test_a_first_attempt_that_converges_is_returned_as_it_is(name):
    # each on a game of its own: a solver's caches (SQP's OSQP object and its warm start)
    # make a second solve on the same game differ in the last bits
    g, p = load_game(example_path("crossing2")).game, load_game(example_path("crossing2")).params
    entry = SOLVERS[name]
    ref = entry.function(g, p, None, entry.make_options(None))
    g = load_game(example_path("crossing2")).game
    res = solve_game(g, p, solver=name)
    assert ref.status is res.status is Status.CONVERGED
    assert np.array_equal(res.controls, ref.controls) and res.iterations == ref.iterations
    assert float(res.energy) == float(ref.energy)
    assert set(res.info) == set(ref.info) and "attempts" not in res.info


def test_every_builtin_options_class_has_the_switch_on_by_default():
    for cls in (LMOptions, IpoptOptions, ILQOptions, SQPOptions, OLNEOptions):
        assert cls().continuation is True
        with pytest.raises(SpecError) as e:
            cls(continuation=1)
        assert e.value.field.endswith(".continuation")
    for name in ("lm", "ipopt", "ilq", "sqp", "olne"):
        e = SOLVERS[name]
        assert isinstance(e.solve, ContinuedSolve) and e.solve.function is e.function
        assert inspect.signature(e.solve) == inspect.signature(e.function)
    assert SOLVERS["ilq"].takes("costs")


# ----------------------------------------------------------------------------- the stage logic
@dataclass(frozen=True)
class ToyOptions:
    max_iter: int = 10
    #: the toy converges when the largest pair weight is below reach * (its start's u[0]),
    #: or at most `easy` from any start; its u[0] is then that weight
    reach: float = 4.0
    easy: float = 5.0
    stop: str = "line_search"  #: the stop word of a failed solve
    continuation: bool = True


@dataclass(frozen=True)
class ToyKinkOptions(ToyOptions):
    kink_widths: tuple = (1e-2, 1e-3)
    continuation: bool = True


@dataclass
class Recorder:
    calls: list = field(default_factory=list)

    def __call__(self, game, p, u0=None, options=None):
        o = options if options is not None else ToyOptions()
        if isinstance(o, dict):
            o = (ToyKinkOptions if "kink_widths" in o else ToyOptions)(**o)
        p = np.asarray(p, float)
        u = np.zeros(game.n_u) if u0 is None else np.array(u0, float)
        self.calls.append((p.copy(), None if u0 is None else u.copy(), options))
        if p.ndim == 2:  # a batch: every problem converged, as a batched result
            B = p.shape[0]
            return SolveResult(
                "toy", np.zeros((B, game.n_u)), np.zeros((B, game.n_x)), np.zeros(B),
                np.zeros((B, game.N)), np.array([Status.STALLED] * B, dtype=object),
                np.ones(B, int), np.zeros((2, B)), np.zeros(B), 0.0, {"stop": o.stop},
            )  # fmt: skip
        w = float(np.max(p[game.params.group("w_pair")]))
        wide = getattr(o, "kink_widths", (0,))[:1] == (KINK_WIDTHS[0],)
        ok = w <= o.easy or w < o.reach * u[0] or wide
        if ok:
            u[0] = w
        status = Status.CONVERGED if ok else Status.STALLED
        if not ok and o.stop == "max_iter":
            status = Status.MAX_ITER
        energy = w if ok else 1000.0 + w + len(self.calls)
        return SolveResult(
            "toy", u, np.zeros(game.n_x), np.asarray(energy), np.zeros(game.N), status,
            np.asarray(3 if ok else o.max_iter), np.full(2, energy), np.asarray(0.0), 0.01,
            {"stop": "tol" if ok else o.stop},
        )  # fmt: skip


@pytest.fixture
def toy():
    rec = Recorder()
    register_solver("toy_cont", rec, ToyOptions)
    register_solver("toy_kink", rec, ToyKinkOptions)
    try:
        yield rec
    finally:
        unregister_solver("toy_cont")
        unregister_solver("toy_kink")


def _pair_weights(game, calls):
    idx = game.params.group("w_pair")
    return [float(np.max(c[0][idx])) for c in calls]


def test_stages_scale_only_the_pair_weights_and_warm_start_from_the_last(toy):
    g, p = game_of(HARD)
    idx = g.params.group("w_pair")
    others = np.setdiff1d(np.arange(g.n_p), idx)
    u0 = np.zeros(g.n_u)
    res = solve_game(g, p, u0, solver="toy_cont")
    scales = [1.0, *WEIGHT_SCALES, 1.0]
    assert _pair_weights(g, toy.calls) == pytest.approx([300.0 * s for s in scales], rel=1e-14)
    for q, _, _ in toy.calls:
        assert np.array_equal(q[others], p[others])
        assert np.allclose(q[idx] / p[idx], q[idx][0] / p[idx][0])  # one factor on every pair
    assert np.array_equal(toy.calls[1][1], u0)  # the first stage starts at the solve's u0
    for (_, start, _), (q, _, _) in zip(toy.calls[2:], toy.calls[1:-1], strict=True):
        assert start[0] == pytest.approx(float(np.max(q[idx])))  # the last stage's controls
    assert res.status is Status.CONVERGED and float(res.energy) == pytest.approx(300.0)
    att = res.info["attempts"]
    assert [a["status"] for a in att] == ["stalled"] + ["converged"] * 5
    assert int(res.iterations) == 10 + 5 * 3 and att[-1]["kept"]


def test_a_continuation_that_does_not_reach_the_full_weight_says_so(toy):
    g, p = game_of(HARD)
    res = solve_game(g, p, solver="toy_cont", options={"reach": 2.0})  # 3.16x steps: too far
    att = res.info["attempts"]
    assert [a["status"] for a in att] == ["stalled", "converged"] + ["stalled"] * 4
    assert res.status is Status.STALLED
    # kept: the full-weight attempt with the lower energy (first 1301, last stage 1306)
    assert [a["energy"] for a in att if a["weight_scale"] == 1.0] == [1301.0, 1306.0]
    assert att[0]["kept"] and sum(a.get("kept", False) for a in att) == 1
    assert float(res.energy) == 1301.0 and np.array_equal(res.controls, np.zeros(g.n_u))


def test_when_no_continuation_runs(toy):
    g, p = game_of(HARD)
    idx = g.params.group("w_pair")
    no_pairs = np.where(np.isin(np.arange(g.n_p), idx), 0.0, p)
    cases = [
        # off; the options reach the solver with the switch at its default, so caches
        # keyed on the options (IPOPT's NLP) are shared with a solve that has it on
        (dict(options={"continuation": False, "reach": 3.0}), ToyOptions(reach=3.0)),
        (dict(options=ToyOptions(continuation=False)), ToyOptions()),
        (dict(options={"stop": "max_iter", "max_iter": 5}), None),  # a short budget, used up
        (dict(u0=np.full(g.n_u, np.nan)), None),  # refused input
        (dict(p=no_pairs, options={"easy": -1.0}), None),  # no pair weight to scale
        (dict(p=np.stack([p, p])), None),  # a batch
    ]
    for case, passed in cases:
        toy.calls.clear()
        res = solve_game(g, case.get("p", p), case.get("u0"), "toy_cont", case.get("options"))
        assert len(toy.calls) == 1 and "attempts" not in res.info, case
        if not res.batched:
            assert res.status is not Status.CONVERGED
        if passed is not None:
            assert toy.calls[0][2] == passed
    toy.calls.clear()  # a mapping handed to the entry itself (as the multi-modal solver does)
    SOLVERS["toy_cont"].solve(g, p, None, {"continuation": False, "reach": 3.0})
    assert len(toy.calls) == 1 and toy.calls[0][2] == {"reach": 3.0}
    with pytest.raises(SpecError) as e:  # a bad value reaches the solver's own check
        SOLVERS["lm"].solve(*game_of(HARD), None, {"continuation": "no"})
    assert e.value.field == "lm.continuation"
    # the iteration limit at its default: a max_iter stop is continued
    toy.calls.clear()
    res = solve_game(g, p, solver="toy_cont", options={"stop": "max_iter"})
    assert len(toy.calls) == 6 and res.status is Status.CONVERGED


def test_a_kink_stage_after_a_failed_line_search(toy):
    g, p = game_of(HARD)
    res = solve_game(g, p, solver="toy_kink", options={"reach": 2.0})
    att = res.info["attempts"]
    assert [a["stage"] for a in att][-2:] == ["weight", "kink"]
    assert att[-1]["kink_widths"] == list(KINK_WIDTHS) and att[-1]["kept"]
    assert toy.calls[-1][2] == ToyKinkOptions(reach=2.0, kink_widths=KINK_WIDTHS)
    # from the last weight stage's end (stalled: its start, u[0] = 3 from the first stage)
    assert np.array_equal(toy.calls[-1][1], toy.calls[-2][1]) and toy.calls[-1][1][0] == 3.0
    assert res.status is Status.CONVERGED
    # after another stop (here the iteration limit) no kink stage runs
    toy.calls.clear()
    res = solve_game(g, p, solver="toy_kink", options={"reach": 2.0, "stop": "max_iter"})
    assert [a["stage"] for a in res.info["attempts"]][-1] == "weight"


def test_registering_the_same_solver_again_is_a_no_op(toy):
    e = SOLVERS["toy_cont"]
    assert e.function is toy and e.solve == ContinuedSolve(toy, ToyOptions, "max_iter")
    assert register_solver("toy_cont", toy, ToyOptions) == e
    assert register_solver("toy_cont", e.solve, ToyOptions) == e  # its wrapper: wrapped once


# ----------------------------------------------------------------------------- iLQ
def test_ilq_stalls_and_the_continuation_converges_to_a_checked_feedback_equilibrium():
    """Three bicycles crossing at collision weight 1000: iLQ's first attempt (its restart
    from the open-loop equilibrium included) ends stalled; the continuation converges, by
    iLQ's own test recomputed and by the sampled feedback-Nash check."""
    g, p = game_of(("crossing", 3, "bicycle", 1000.0, 2, 20))
    res = solve_game(g, p, solver="ilq")
    att = res.info["attempts"]
    assert att[0]["status"] == "stalled" and att[0]["weight_scale"] == 1.0
    assert res.status is Status.CONVERGED and att[-1]["kept"] and att[-1]["weight_scale"] == 1.0
    # iLQ's first-order test, recomputed: a fresh solve from the result stops at once
    again = SOLVERS["ilq"].function(g, p, res.controls, ILQOptions(kink_widths=(), restart=False))
    assert again.status is Status.CONVERGED and again.iterations == 0
    check = check_ilq_result(g, p, res)
    assert check.ok, check.gain
