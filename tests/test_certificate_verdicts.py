"""Three-valued equilibrium checks: passes / fails / unknown, local and global.

References computed another way: independent best responses by scipy (BFGS on ``C_i``
with finite-difference gradients, several starts), and a numpy closed loop (unicycle
steps written out here, the other player's affine policy applied by hand) minimized by
scipy for the feedback check. The command line: ``epo solve --solver ilq`` prints the
feedback verdict, and every solver ``epo compare`` runs is accepted by ``epo solve``.
"""

from __future__ import annotations

import csv
import io
import json

import numpy as np
import pytest
from scipy.optimize import minimize

from epo_casadi import (
    Acceleration,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    PotentialGame,
    TurnRate,
    Velocity,
)
from scenarios.gamefile import example_path
from solvers.compare import COLUMNS, parse_solver
from solvers.feedback_nash import check_ilq_result
from solvers.ilq import solve_ilq, to_stages
from solvers.lm import solve_lm
from solvers.nash import NashOptions, nash_certificate
from solvers.registry import SOLVERS
from solvers.result import Status, Verdict

from .helpers import cli, crossing_game, solved_crossing


def own_cost(g, p, u, i):
    """``u_i -> C_i(u_i, u_{-i})``: agent ``i``'s cost, the others' controls of ``u`` fixed."""
    a, b = int(g.uoff[i]), int(g.uoff[i + 1])
    f = g.function("agent_costs")

    def c(ui):
        return float(f(np.concatenate([u[:a], ui, u[b:]]), p)[i])

    return c


def scipy_best_response(g, p, u, i, starts) -> float:
    """The lowest ``C_i`` that BFGS (central-difference gradients) reaches from ``starts``."""
    c = own_cost(g, p, u, i)
    return min(minimize(c, x0, method="BFGS", jac="3-point").fun for x0 in starts)


@pytest.fixture(scope="module")
def crossing():
    """A 2-agent crossing (collision active) and its potential minimizer: an equilibrium."""
    g, p, _, sol = solved_crossing()
    return g, p, sol.controls


def _nudged(g, u, eps=1e-6, seed=0):
    """``u`` moved by ``eps`` (max-norm) along a seeded direction: still an equilibrium to
    every tolerance (gap ~ eps^2), but not stationary to a best response's own tolerance."""
    d = np.random.default_rng(seed).standard_normal(u.size)
    return u + eps * d / np.abs(d).max()


def test_exact_equilibrium_passes_against_independent_best_responses(crossing):
    g, p, u = crossing
    cert = nash_certificate(g, p, u)
    assert cert.verdict is Verdict.PASSES and cert.ok
    assert cert.verdicts == (Verdict.PASSES, Verdict.PASSES)
    assert all(by.startswith("ipopt (exact Hessian)") for by in cert.decided_by)
    rng = np.random.default_rng(1)
    for i in range(g.N):
        a, b = int(g.uoff[i]), int(g.uoff[i + 1])
        starts = [u[a:b], u[a:b] + 0.3 * rng.standard_normal(b - a), np.zeros(b - a)]
        best = scipy_best_response(g, p, u, i, starts)
        tol = NashOptions().gap_tol * (1 + abs(cert.costs[i]))
        assert best >= cert.costs[i] - tol  # no start finds a better response
    assert "LOCAL" in cert.summary()
    d = json.loads(json.dumps(cert.to_dict()))
    assert d["verdict"] == "passes" and d["verdicts"] == ["passes", "passes"]
    assert d["kind"] == "open-loop" and len(d["decided_by"]) == 2


def test_a_best_response_cut_short_is_unknown_not_fails(crossing):
    g, p, u = crossing
    v = _nudged(g, u)
    full = nash_certificate(g, p, v)
    assert full.verdict is Verdict.PASSES  # the nudged point is an equilibrium
    assert np.all(full.best_response_gap < 1e-9)
    # no IPOPT iteration allowed, no second method: the gap is unknown, not a failure
    short = nash_certificate(g, p, v, {"max_iter": 0, "fallback": False})
    assert short.best_response_status == ("Maximum_Iterations_Exceeded",) * 2
    assert short.verdict is Verdict.UNKNOWN and not short.ok
    assert short.verdicts == (Verdict.UNKNOWN, Verdict.UNKNOWN)
    assert short.stat_ok.all() and not short.gap_ok.any()
    for r in short.reasons:
        assert "did not converge" in r and "Maximum_Iterations_Exceeded" in r
        assert "the gap is unknown" in r
    text = short.summary()
    assert "UNKNOWN" in text and "FAILS" not in text and "unknown" in text
    # L-BFGS stopped after 2 iterations: unknown alone ...
    lbfgs = {"exact_hessian_max": 0, "max_iter": 2}
    alone = nash_certificate(g, p, v, {**lbfgs, "fallback": False})
    assert alone.verdict is Verdict.UNKNOWN
    assert alone.best_response_status == ("Maximum_Iterations_Exceeded",) * 2
    # ... and the second method decides: LM on the agent's residuals (2 iterations, its
    # energy decrease below round-off), then the Newton model at its point: passes
    for o in (lbfgs, {"max_iter": 0}):
        rescued = nash_certificate(g, p, v, o)
        assert rescued.verdict is Verdict.PASSES, rescued.summary()
        assert all(by.startswith("lm (agent residuals)") for by in rescued.decided_by)
        assert all("Newton test passes" in by for by in rescued.decided_by)
    # a second method cut short as well stays unknown: the LM at a perturbed agent
    w = u.copy()
    a, b = int(g.uoff[1]), int(g.uoff[2])
    w[a:b] += 0.2 * np.random.default_rng(3).standard_normal(b - a)
    none = nash_certificate(g, p, w, {"max_iter": 0, "stat_tol": 1.0})
    assert none.verdicts[1] is Verdict.UNKNOWN and "Newton test" in none.reasons[1]


def test_a_found_improvement_fails_even_when_the_solve_is_cut_short(crossing):
    g, p, u = crossing
    v = u.copy()
    a, b = int(g.uoff[1]), int(g.uoff[2])
    v[a:b] += 0.2 * np.random.default_rng(3).standard_normal(b - a)
    loose = {"stat_tol": 1.0, "max_iter": 1}  # isolate the gap; one IPOPT iteration only
    cert = nash_certificate(g, p, v, loose)
    assert cert.best_response_status[1] == "Maximum_Iterations_Exceeded"
    assert cert.verdicts[1] is Verdict.FAILS and cert.verdict is Verdict.FAILS
    assert cert.best_response_gap[1] > 0.1
    assert "lowers C_i" in cert.reasons[1] and "Maximum_Iterations_Exceeded" in cert.decided_by[1]
    # the full best response against an independent one from the same start
    full = nash_certificate(g, p, v)
    ref = scipy_best_response(g, p, v, 1, [v[a:b]])
    assert full.best_response_costs[1] == pytest.approx(ref, rel=1e-6)
    assert full.verdicts[1] is Verdict.FAILS


# ------------------------------------------------------------------------------ local vs global
K_BARRIER = 30


@pytest.fixture(scope="module")
def barrier():
    """A car passing a pedestrian who (heavily damped) barely moves; the car's goal is
    0.3 m to the left, so passing on the left is cheaper. The potential minimizer
    reached from a right-swerving start passes on the right: a local equilibrium, with a
    better response for the car behind the pedestrian."""
    K = K_BARRIER
    agents = [
        AgentSpec(
            "car",
            "unicycle",
            [Goal(weight=3.0), Velocity(weight=0.3), Acceleration(), TurnRate()],
            radius=0.3,
            x0=[-2.0, 0.0, 1.0, 0.0],
            goal=[2.0, 0.3],
        ),
        AgentSpec(
            "ped",
            "unicycle",
            [Goal(weight=3.0), Velocity(weight=20.0), Acceleration(weight=10.0), TurnRate()],
            radius=0.3,
            x0=[0.0, 0.0, 0.0, np.pi / 2],
            goal=[0.0, 0.0],
        ),
    ]
    g = PotentialGame(GameSpec(agents, [Collision(weight=30.0)], horizon=K, dt=0.1))
    p = g.default_params()

    def swerve(turn):
        k = K // 6
        car = np.vstack(
            [
                np.tile([0.0, turn], (k, 1)),
                np.tile([0.0, -turn], (2 * k, 1)),
                np.tile([0.0, turn], (k, 1)),
                np.zeros((K - 4 * k, 2)),
            ]
        )
        return g.join_controls([car, np.zeros((K, 2))])

    right = solve_lm(g, p, swerve(1.0))
    left = solve_lm(g, p, swerve(-1.0))
    y_right = g.split_states(right.states)[0][:, 1]
    y_left = g.split_states(left.states)[0][:, 1]
    assert right.status is Status.CONVERGED and left.status is Status.CONVERGED
    assert y_right.min() < -0.4 and y_left.max() > 0.4  # the two sides
    assert left.agent_costs[0] < right.agent_costs[0] - 1.0  # the left is cheaper for the car
    return g, p, right, left


def test_local_certificate_passes_and_global_starts_find_the_other_side(barrier):
    g, p, right, left = barrier
    local = nash_certificate(g, p, right.controls)
    assert local.verdict is Verdict.PASSES  # no descent method sees past the pedestrian
    glob = nash_certificate(g, p, right.controls, {"global_starts": 4})
    assert glob.verdict is Verdict.FAILS and glob.verdicts == (Verdict.FAILS, Verdict.PASSES)
    assert glob.decided_by[0].startswith("global start")
    gap = glob.best_response_gap[0]
    assert gap > 1.0
    # independent: BFGS from the left-swerving controls reaches the same better response
    a, b = int(g.uoff[0]), int(g.uoff[1])
    ref = scipy_best_response(g, p, right.controls, 0, [left.controls[a:b]])
    assert glob.best_response_costs[0] == pytest.approx(ref, rel=1e-5)
    assert "local + 4 global starts per agent" in glob.summary()
    assert (
        np.isfinite(glob.global_best_costs[0]) and glob.global_best_costs[0] < right.agent_costs[0]
    )


def _closed_loop_car_cost(g, p, res, w):
    """The car's cost when it plays the sequence ``w`` (K, 2) and the pedestrian its iLQ
    policy ``u = U* - P (X - X*) - a`` (numpy, unicycle steps written out)."""
    K, dt = g.K, g.dt
    X, U = to_stages(g, res.states, res.controls)
    P, a = res.info["gains"], res.info["feedforward"]
    x = X[0].copy()
    xs, us = [x], []
    for k in range(K):
        u = U[k] - P[k] @ (x - X[k]) - a[k]
        u[0:2] = w[k]
        nxt = np.empty(8)
        for j in range(2):
            s = x[4 * j : 4 * j + 4]
            nxt[4 * j : 4 * j + 4] = [
                s[0] + s[2] * np.cos(s[3]) * dt,
                s[1] + s[2] * np.sin(s[3]) * dt,
                s[2] + u[2 * j] * dt,
                s[3] + u[2 * j + 1] * dt,
            ]
        x = nxt
        xs.append(x)
        us.append(u)
    xs, us = np.array(xs), np.array(us)
    xf = np.concatenate([xs[:, 0:4].ravel(), xs[:, 4:8].ravel()])
    uf = np.concatenate([us[:, 0:2].ravel(), us[:, 2:4].ravel()])
    return float(g.function("traj_agent_costs")(xf, uf, p)[0])


def test_feedback_check_is_local_and_its_global_starts_find_the_other_side(barrier):
    g, p, right, left = barrier
    res = solve_ilq(g, p, right.controls)
    assert res.status is Status.CONVERGED
    assert g.split_states(res.states)[0][:, 1].min() < -0.4  # still on the right
    assert not res.info["prev_variables"].size  # no lagged terms: the policy is P, a
    local = check_ilq_result(g, p, res)
    assert local.verdict is Verdict.PASSES and local.ok and local.global_gain is None
    assert "LOCAL" in local.summary()
    glob = check_ilq_result(g, p, res, {"global_starts": 6})
    assert glob.verdict is Verdict.FAILS and not glob.ok_agent[0] and glob.ok_agent[1]
    assert glob.decided_by[0].startswith("global start")
    # independent: the car's closed-loop cost, minimized by BFGS from the left pass
    base = _closed_loop_car_cost(g, p, res, g.split_controls(res.controls)[0])
    assert base == pytest.approx(glob.costs[0], rel=1e-10)
    ref = minimize(
        lambda w: _closed_loop_car_cost(g, p, res, w.reshape(-1, 2)),
        g.split_controls(left.controls)[0].ravel(),
        method="BFGS",
        jac="3-point",
    ).fun
    assert base - ref > 1.0
    assert glob.global_gain[0] == pytest.approx(base - ref, rel=1e-4)
    d = json.loads(json.dumps(glob.to_dict()))
    assert d["verdict"] == "fails" and d["verdicts"] == ["fails", "passes"]
    assert d["global_starts"] == 6 and d["kind"] == "feedback"


def test_feedback_check_without_evidence_is_unknown(crossing):
    g, p, u = crossing
    res = solve_ilq(g, p, u)
    chk = check_ilq_result(g, p, res, {"n_random": 0, "n_coordinate": 0})
    assert chk.trials == 0 and chk.verdict is Verdict.UNKNOWN and not chk.ok
    assert all("no deviation" in r for r in chk.reasons)


# ------------------------------------------------------------------------------ command line
def test_epo_solve_ilq_prints_the_feedback_verdict(capsys, tmp_path):
    out = tmp_path / "r.json"
    rc, stdout, err = cli(
        capsys, "solve", example_path("crossing2"), "--solver", "ilq", "--out", out
    )
    assert rc == 0, err
    assert "ilq: converged" in stdout and "equilibrium: feedback Nash" in stdout
    assert "feedback Nash check: passes (local, sampled policy deviations" in stdout
    data = json.loads(out.read_text())
    assert data["certificate"] is None and data["equilibrium"] == "feedback Nash"
    fb = data["feedback_check"]
    assert fb["kind"] == "feedback" and fb["verdict"] == "passes" and fb["ok"] is True
    assert len(fb["gain"]) == 2 and fb["global_starts"] == 0
    rc, stdout, err = cli(
        capsys, "solve", example_path("crossing2"), "--solver", "ilq", "--no-certificate"
    )
    assert rc == 0, err
    assert "ilq: converged" in stdout and "feedback Nash check" not in stdout


@pytest.mark.parametrize("name", list(SOLVERS))
def test_every_compare_solver_is_an_epo_solve_solver(name, capsys):
    """``epo compare`` runs every solver of the table (its default); ``epo solve`` takes
    each of them by name."""
    assert parse_solver(name).name == name
    rc, stdout, err = cli(
        capsys, "solve", example_path("crossing2"), "--solver", name, "--no-certificate"
    )
    assert rc != 2, err  # accepted (not a usage error)
    assert f"\n{name}: " in "\n" + stdout, stdout


def test_every_writer_handles_every_verdict(crossing, tmp_path):
    """Summary text, JSON, the ``epo solve`` lines, ``epo compare``'s table and CSV and
    ``epo demo``'s row carry passes, fails and unknown (and no check) as such."""
    from scenarios.commands.demo import _row
    from scenarios.commands.solve import result_dict, summary_lines, write_result
    from solvers.compare import Comparison, Row

    g, p, u = crossing
    res = solve_lm(g, p, u)
    v = u.copy()
    a, b = int(g.uoff[1]), int(g.uoff[2])
    v[a:b] += 0.2 * np.random.default_rng(3).standard_normal(b - a)
    certs = {
        "passes": nash_certificate(g, p, u),
        "fails": nash_certificate(g, p, v),
        "unknown": nash_certificate(g, p, _nudged(g, u), {"max_iter": 0, "fallback": False}),
    }
    word = {"passes": "passes", "fails": "FAILS", "unknown": "unknown"}
    demo_word = {"passes": "yes", "fails": "NO", "unknown": "unknown"}
    rows = []
    for verdict, cert in certs.items():
        assert str(cert.verdict) == verdict
        data = result_dict(g, p, res, cert, source="crossing.yaml")
        back = json.loads(write_result(data, tmp_path / f"{verdict}.json").read_text())
        assert back["certificate"]["verdict"] == verdict
        text = "\n".join(summary_lines(g, back))
        assert f"Nash certificate: {word[verdict]} (local;" in text
        if verdict != "passes":  # the reason of each agent that does not pass
            assert f"    a1: {verdict}: " in text, text
        assert _row("crossing", back)[7] == demo_word[verdict]
        rows.append(
            Row(
                "crossing", "lm", "zero", "converged", 1.0, 0.0, 3, 1e-9, 0.1, 0.2,
                "open-loop", verdict == "passes", 0.0, 0.1, "gtol",
                equilibrium="open-loop Nash", verdict=verdict,
                check_note="" if verdict == "passes" else f"a1 {verdict}: why",
            )
        )  # fmt: skip
    rows.append(
        Row("crossing", "lm", "zero", "nonfinite", float("nan"), float("nan"), 0, float("nan"),
            0.1, 0.0, "none", None, float("nan"), 0.0, "nonfinite")
    )  # fmt: skip
    comp = Comparison(rows)
    md = comp.markdown().splitlines()[2:]
    cells = [[c.strip() for c in line.strip("|").split("|")] for line in md]
    col = list(COLUMNS).index
    assert [r[col("verdict")] for r in cells] == ["passes", "FAILS", "unknown", "-"]
    assert [r[col("check_ok")] for r in cells] == ["yes", "no", "no", "-"]
    assert [r[col("equilibrium")] for r in cells] == ["open-loop Nash"] * 3 + ["-"]
    table = list(csv.DictReader(io.StringIO(comp.csv())))
    assert [r["verdict"] for r in table] == ["passes", "fails", "unknown", ""]
    assert table[2]["check_note"] == "a1 unknown: why"
    # a feedback check's verdict in the epo solve lines, and no check at all
    ilq = solve_ilq(g, p, u)
    fb = check_ilq_result(g, p, ilq, {"n_random": 0, "n_coordinate": 0})
    back = json.loads(json.dumps(result_dict(g, p, ilq, fb)))
    text = "\n".join(summary_lines(g, back))
    assert "feedback Nash check: unknown (local, sampled" in text and "no deviation" in text
    none = "\n".join(summary_lines(g, json.loads(json.dumps(result_dict(g, p, res)))))
    assert "Nash certificate" not in none and "equilibrium: open-loop Nash" in none


def test_feedback_options_are_checked():
    from epo_casadi import SpecError
    from solvers.feedback_nash import FeedbackNashOptions

    for key, value in (("global_starts", -1), ("global_scale", 0.0), ("max_iter", 1.5)):
        with pytest.raises(SpecError) as e:
            FeedbackNashOptions(**{key: value})
        assert e.value.field == f"feedback_nash.{key}"


def test_a_saddle_of_an_agents_cost_fails_on_its_negative_curvature():
    """Newton on the stacked conditions from zero controls (no saddle escapes) stops on a
    point where both players' own Hessians have a negative eigenvalue: stationary, and
    IPOPT warm-started there stops at once. The second-order test finds the improvement
    along the eigenvector; LM's equilibrium of the same game passes."""
    from solvers.lm import solve_lm
    from solvers.olne import solve_olne

    g = crossing_game(N=2, K=20, offset=0.3)
    p = g.default_params()
    r = solve_olne(g, p, None, {"start": "given", "saddle_escapes": 0})
    assert r.status.value == "converged" and not r.info["second_order_ok"]
    c = nash_certificate(g, p, r.controls)
    assert c.verdicts == (Verdict.FAILS, Verdict.FAILS)
    assert all("negative curvature" in d for d in c.decided_by)
    assert np.all(c.best_response_gap > 1e-4)
    # the found improvement is real, by references the certificate did not use: each
    # player's own Hessian by central differences of its gradient has a negative
    # eigenvalue, and BFGS started a little along that direction reaches a cost at least as
    # low as the certificate's best response
    C = np.asarray(g.function("agent_costs")(r.controls, p)).ravel()
    np.testing.assert_allclose(c.costs, C, rtol=1e-12)
    pg = g.function("pseudo_gradient")
    for i in range(g.N):
        a, b = int(g.uoff[i]), int(g.uoff[i + 1])
        H = np.empty((b - a, b - a))
        for j in range(b - a):
            e = np.zeros(g.n_u)
            e[a + j] = 1e-5
            dF = np.asarray(pg(r.controls + e, p) - pg(r.controls - e, p)).ravel()
            H[:, j] = dF[a:b] / 2e-5
        w, V = np.linalg.eigh(0.5 * (H + H.T))
        assert w[0] < -1.0  # measured -32.6
        ui = r.controls[a:b]
        best = scipy_best_response(g, p, r.controls, i, [ui + 1e-2 * V[:, 0], ui - 1e-2 * V[:, 0]])
        assert best <= c.best_response_costs[i] + 1e-6 * (1 + abs(C[i]))
    lm = solve_lm(g, p)
    assert nash_certificate(g, p, lm.controls).verdict is Verdict.PASSES
