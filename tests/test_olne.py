"""The open-loop Nash solver (solvers.olne) on coupled and uncoupled games.

References computed another way:

* LQ games (double integrators, linear joint models, goal / velocity / acceleration
  features and a linear pair "spring"): the open-loop Nash equilibrium from the stacked
  first-order conditions as one linear system in numpy, with the rollout matrices and
  every player's residual rows built by hand from the LQ data (A, B, x0, weights, goals);
  the potential minimizer from the joint least-squares problem of the same matrices.
* Nonlinear games: LM's potential minimizer (uncoupled: the same equilibrium) and the
  local open-loop Nash certificate (best responses by IPOPT).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from typing import ClassVar

import casadi as ca
import numpy as np
import pytest

from epo_casadi import (
    Acceleration,
    AgentSpec,
    Collision,
    Coupling,
    GameSpec,
    Goal,
    JointDynamics,
    PotentialGame,
    SpecError,
    Velocity,
)
from epo_casadi.features import Feature, PairFeature
from scenarios.gamefile import example_path, load_game
from solvers import nash_certificate, solve_lm
from solvers.olne import OLNEOptions, game_jacobian, solve_olne
from solvers.registry import SOLVERS, solve_game
from solvers.result import Status, StopReason

from .helpers import LinearJoint, cli, crossing_game

DT = 0.2


# --------------------------------------------------------------------------------------
# LQ games and their numpy references
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Spring(PairFeature):
    """Linear pair term ``p_a(x_k) - p_b(x_k)`` for ``k = 1..K`` (keep together)."""

    kind: ClassVar[str] = "spring"

    def steps(self, K):
        return list(range(1, K + 1))

    def residual(self, a, b):
        return ca.vertcat(*[a.X[0:2, k] - b.X[0:2, k] for k in self.steps(a.K)])


def _di():
    """One double integrator (explicit Euler, step DT): A (4x4), B (4x2)."""
    a = np.eye(4)
    a[0, 2] = a[1, 3] = DT
    b = np.zeros((4, 2))
    b[2, 0] = b[3, 1] = DT
    return a, b


def _tuple(M):
    return tuple(map(tuple, np.asarray(M, float)))


def shared_mass():
    """Both players push one point mass (each holds a copy of its state, equal from the
    start): next = A x + B (u_a + u_b) for both copies."""
    a, b = _di()
    A = np.kron(np.eye(2), a)
    B = np.vstack([np.hstack([b, b]), np.hstack([b, b])])
    return A, B


def tow():
    """A truck and a trailer whose velocity is pulled towards the truck's."""
    a, b = _di()
    A = np.kron(np.eye(2), a)
    A[6, 6] = A[7, 7] = 1 - 0.8 * DT
    A[6, 2] = A[7, 3] = 0.8 * DT
    B = np.kron(np.eye(2), b)
    return A, B


@dataclass
class LQ:
    """An LQ game as data: per agent x0, goal and weights (goal, velocity, acceleration),
    the joint couplings (member indices, A, B), spring pairs and their weight."""

    x0: list
    goals: list
    weights: list  # (w_goal, w_vel, w_acc) per agent
    couplings: list  # (member indices, A, B)
    springs: list  # index pairs
    w_spring: float = 1.0
    K: int = 6

    @property
    def N(self):
        return len(self.x0)

    def spec(self) -> GameSpec:
        names = [f"p{i}" for i in range(self.N)]
        agents = [
            AgentSpec(
                names[i],
                "double_integrator",
                [Goal(weight=wg), Velocity(weight=wv), Acceleration(weight=wa)],
                x0=self.x0[i],
                goal=self.goals[i],
            )
            for i, (wg, wv, wa) in enumerate(self.weights)
        ]
        cpl = [
            Coupling(tuple(names[i] for i in ids), LinearJoint(_tuple(A), _tuple(B)))
            for ids, A, B in self.couplings
        ]
        pairs = tuple((names[i], names[j]) for i, j in self.springs)
        pf = [Spring(weight=self.w_spring, pairs=pairs)] if pairs else []
        return GameSpec(agents, pf, horizon=self.K, dt=DT, couplings=cpl)

    def joint(self):
        """The joint A (4N x 4N) and B (4N x 2N) over all agents, in agent order."""
        N = self.N
        A, B = np.zeros((4 * N, 4 * N)), np.zeros((4 * N, 2 * N))
        a, b = _di()
        coupled = set()
        for ids, Aj, Bj in self.couplings:
            xs = np.concatenate([np.arange(4 * i, 4 * i + 4) for i in ids])
            us = np.concatenate([np.arange(2 * i, 2 * i + 2) for i in ids])
            A[np.ix_(xs, xs)] = Aj
            B[np.ix_(xs, us)] = Bj
            coupled |= set(ids)
        for i in set(range(N)) - coupled:
            A[4 * i : 4 * i + 4, 4 * i : 4 * i + 4] = a
            B[4 * i : 4 * i + 4, 2 * i : 2 * i + 2] = b
        return A, B

    def residual_maps(self):
        """Each player's residual rows as ``r_i(u) = G_i u + h_i`` (u in the game's
        agent-major order), built from the joint rollout x_k = Phi_k x0 + Gamma_k u."""
        N, K = self.N, self.K
        A, B = self.joint()
        x0 = np.concatenate([np.asarray(x, float) for x in self.x0])
        # column of u for (agent i, step k, component c): i * 2K + 2k + c
        col = lambda i, k, c: i * 2 * K + 2 * k + c  # noqa: E731
        Phi, Gam = [np.eye(4 * N)], [np.zeros((4 * N, 2 * N * K))]
        for k in range(K):
            Gk = A @ Gam[-1]
            for i in range(N):
                for c in range(2):
                    Gk[:, col(i, k, c)] += B[:, 2 * i + c]
            Phi.append(A @ Phi[-1])
            Gam.append(Gk)
        xs = [(Gam[k], Phi[k] @ x0) for k in range(K + 1)]  # state of step k: G u + h

        def rows(i, entries, k):
            """Rows of agent i's state entries ``entries`` (a slice of 0..3) at step k."""
            G, h = xs[k]
            idx = 4 * i + np.arange(4)[entries]
            return G[idx], h[idx]

        own = []
        for i, (wg, wv, wa) in enumerate(self.weights):
            Gs, hs = [], []
            G, h = rows(i, slice(0, 2), K)
            Gs.append(wg * G)
            hs.append(wg * (h - np.asarray(self.goals[i], float)))
            for k in range(1, K + 1):
                G, h = rows(i, slice(2, 4), k)
                Gs.append(wv * G)
                hs.append(wv * h)
            for k in range(K):
                G = np.zeros((2, 2 * N * K))
                G[0, col(i, k, 0)] = G[1, col(i, k, 1)] = wa
                Gs.append(G)
                hs.append(np.zeros(2))
            own.append((np.vstack(Gs), np.concatenate(hs)))
        pair = {}
        for i, j in self.springs:
            Gs, hs = [], []
            for k in range(1, K + 1):
                Ga, ha = rows(i, slice(0, 2), k)
                Gb, hb = rows(j, slice(0, 2), k)
                Gs.append(self.w_spring * (Ga - Gb))
                hs.append(self.w_spring * (ha - hb))
            pair[(i, j)] = (np.vstack(Gs), np.concatenate(hs))
        maps = []
        for i in range(N):
            parts = [own[i]] + [v for (a, b), v in pair.items() if i in (a, b)]
            maps.append((np.vstack([g for g, _ in parts]), np.concatenate([h for _, h in parts])))
        return maps, own, pair

    def nash(self) -> np.ndarray:
        """The open-loop Nash equilibrium: player i's condition G_i[:, u_i]' (G_i u + h_i)
        = 0, stacked over the players, one linear system."""
        maps, _, _ = self.residual_maps()
        K = self.K
        rows, rhs = [], []
        for i, (G, h) in enumerate(maps):
            Gi = G[:, 2 * K * i : 2 * K * (i + 1)]
            rows.append(Gi.T @ G)
            rhs.append(-Gi.T @ h)
        return np.linalg.solve(np.vstack(rows), np.concatenate(rhs))

    def potential_min(self) -> np.ndarray:
        """The minimizer of the potential: every own and pair row once, least squares."""
        _, own, pair = self.residual_maps()
        parts = own + list(pair.values())
        G = np.vstack([g for g, _ in parts])
        h = np.concatenate([h for _, h in parts])
        return np.linalg.lstsq(G, -h, rcond=None)[0]


def _di_start(x, y, vx=0.0, vy=0.0):
    return [x, y, vx, vy]


LQ_GAMES = {
    "two_uncoupled_spring": LQ(
        x0=[_di_start(0, 0, 1, 0), _di_start(0, 2, 0, -0.5)],
        goals=[[3, 1], [2, -1]],
        weights=[(2.0, 0.5, 1.0), (1.5, 0.3, 0.8)],
        couplings=[],
        springs=[(0, 1)],
        w_spring=0.7,
    ),
    "three_uncoupled_spring": LQ(
        x0=[_di_start(0, 0), _di_start(1, 1, 0.5, 0), _di_start(-1, 0.5, 0, 0.3)],
        goals=[[2, 2], [-1, 2], [0, -2]],
        weights=[(2.0, 0.5, 1.0), (1.0, 0.2, 0.6), (1.5, 0.4, 1.2)],
        couplings=[],
        springs=[(0, 1), (0, 2), (1, 2)],
        w_spring=0.5,
    ),
    "two_shared_mass": LQ(
        x0=[_di_start(0, 0), _di_start(0, 0)],
        goals=[[2, 1], [-1, 2]],
        weights=[(3.0, 0.0, 1.0), (3.0, 0.0, 1.0)],
        couplings=[((0, 1), *shared_mass())],
        springs=[],
    ),
    "three_tow_and_free": LQ(
        x0=[_di_start(1, -1, 0.5, 0.2), _di_start(-1, 0.5, 0, -0.3), _di_start(0, 2, 0.3, 0)],
        goals=[[0, 0], [0, 0.5], [2, 1]],
        weights=[(2.0, 0.5, 1.0), (2.0, 0.5, 1.0), (1.0, 0.3, 0.7)],
        couplings=[((0, 1), *tow())],
        springs=[(0, 2), (1, 2)],
        w_spring=0.6,
    ),
}


@pytest.fixture(scope="module")
def lq_games():
    return {k: (lq, PotentialGame(lq.spec())) for k, lq in LQ_GAMES.items()}


@pytest.mark.parametrize("name", list(LQ_GAMES))
@pytest.mark.parametrize("jacobian", ["exact", "gn"])
def test_lq_equilibrium_equals_the_stacked_conditions(lq_games, name, jacobian):
    lq, game = lq_games[name]
    assert game.coupled == bool(lq.couplings)
    p = game.default_params()
    # the hand-built rollout matrices are the game's (else the reference means nothing)
    u = np.random.default_rng(0).standard_normal(game.n_u)
    maps, _, _ = lq.residual_maps()
    costs = [0.5 * float(np.sum((G @ u + h) ** 2)) for G, h in maps]
    C = np.asarray(game.function("agent_costs")(u, p), dtype=float).ravel()
    np.testing.assert_allclose(C, costs, rtol=1e-12)
    ref = lq.nash()
    res = solve_olne(game, p, options={"jacobian": jacobian, "tol": 1e-11, "start": "given"})
    assert res.status is Status.CONVERGED and res.info["stop"] is StopReason.GTOL
    assert res.iterations == 1  # F is affine: one Newton step (the GN matrix is exact here)
    np.testing.assert_allclose(res.controls, ref, atol=1e-10, rtol=0)
    assert res.info["stationarity"] <= 1e-11
    # every player's own cost is a strictly convex quadratic in its controls
    assert res.info["second_order_ok"] and np.all(res.info["own_hessian_min_eig"] > 0)
    # from the default start (the potential minimizer) Newton reaches the same point
    res = solve_olne(game, p, options={"jacobian": jacobian, "tol": 1e-11})
    assert res.status is Status.CONVERGED
    np.testing.assert_allclose(res.controls, ref, atol=1e-10, rtol=0)


def test_lq_game_jacobian_is_the_stacked_system(lq_games):
    """The game Jacobian M = dF/du of an LQ game is the stacked matrix of the reference."""
    lq, game = lq_games["three_tow_and_free"]
    maps, _, _ = lq.residual_maps()
    K = lq.K
    want = np.vstack([G[:, 2 * K * i : 2 * K * (i + 1)].T @ G for i, (G, _) in enumerate(maps)])
    p = game.default_params()
    u = np.random.default_rng(1).standard_normal(game.n_u)
    for kind in ("exact", "gn"):
        _, M = game_jacobian(game, kind)(u, p)
        np.testing.assert_allclose(np.asarray(ca.densify(M)), want, atol=1e-12)
    assert not np.allclose(want, want.T)  # coupled: not a Hessian


def test_coupled_equilibrium_is_not_the_potential_minimizer(lq_games):
    """The shared point mass: LM's potential minimum is far from the equilibrium and fails
    the certificate; the solver's point is the equilibrium and passes it."""
    lq, game = lq_games["two_shared_mass"]
    p = game.default_params()
    ref, pot = lq.nash(), lq.potential_min()
    lm = solve_lm(game, p)
    assert lm.status is Status.CONVERGED
    np.testing.assert_allclose(lm.controls, pot, atol=1e-7)
    gap = float(np.max(np.abs(ref - pot)))
    assert gap > 0.5  # the two are different points, not round-off apart
    res = solve_olne(game, p)
    assert res.status is Status.CONVERGED
    np.testing.assert_allclose(res.controls, ref, atol=1e-9)
    assert float(np.max(np.abs(res.controls - lm.controls))) > 0.5
    assert res.grad_norm > 1e-2  # dE/du is not zero at the equilibrium of a coupled game
    assert nash_certificate(game, p, res.controls).ok
    bad = nash_certificate(game, p, lm.controls)
    assert not bad.ok and np.all(bad.best_response_gap > 1e-3)


# --------------------------------------------------------------------------------------
# nonlinear games
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def crossing():
    """The shipped two-unicycle crossing (collision term active at the solution)."""
    gf = load_game(example_path("crossing2"))
    return gf.game, gf.params


def _collision_energy(game, u, p) -> float:
    coll = next(t.index for t in game.terms if t.feature_type == "collision")
    return float(game.function("term_energies")(u, p)[coll])


def test_uncoupled_game_agrees_with_the_potential_minimizer(crossing):
    game, p = crossing
    lm = solve_lm(game, p, options={"gtol": 1e-10})
    assert lm.status is Status.CONVERGED
    assert _collision_energy(game, lm.controls, p) > 1e-3  # the players interact
    for opts in ({}, {"jacobian": "gn", "start": "given"}):
        res = solve_olne(game, p, options=opts)
        assert res.status is Status.CONVERGED, (opts, res.info["stop"])
        assert res.info["stationarity"] <= 1e-8
        np.testing.assert_allclose(res.controls, lm.controls, atol=1e-6)
        np.testing.assert_allclose(res.energy, lm.energy, rtol=1e-10)
        assert res.info["second_order_ok"]


def test_nonlinear_result_passes_the_certificate(crossing):
    """From zero controls (no potential start) the Gauss-Newton variant reaches LM's
    equilibrium of the shipped crossing; the result passes the certificate."""
    game, p = crossing
    res = solve_olne(game, p, options={"jacobian": "gn", "start": "given"})
    assert res.status is Status.CONVERGED, res.info["stop"]
    assert res.info["second_order_ok"]
    cert = nash_certificate(game, p, res.controls)
    assert cert.ok, cert.summary()


def test_a_saddle_is_reported_and_escaped():
    """Exact Newton from zero controls on a shorter crossing converges to a point where
    both players' first-order conditions hold but each sits on a saddle of its own cost:
    the solver reports the negative own curvature, and a unilateral deviation along it
    (evaluated here with the agent costs alone) lowers that player's cost. With escapes
    (the default) it ends at an equilibrium that passes the certificate."""
    g = crossing_game(N=2, K=20, offset=0.3)
    q = g.default_params()
    costs = g.function("agent_costs")
    pg = g.function("pseudo_gradient")

    def C(u):
        return np.asarray(costs(u, q), dtype=float).ravel()

    def F(u):
        return np.asarray(pg(u, q), dtype=float).ravel()

    res = solve_olne(g, q, options={"start": "given", "saddle_escapes": 0})
    assert res.status is Status.CONVERGED and res.info["saddle_escapes"] == 0
    assert not res.info["second_order_ok"]
    low = res.info["own_hessian_min_eig"]
    i = int(np.argmin(low))
    assert low[i] < -1.0
    a, b = g.uoff[i], g.uoff[i + 1]
    H = np.empty((b - a, b - a))  # player i's own Hessian by central differences of F_i
    for j in range(b - a):
        e = np.zeros(g.n_u)
        e[a + j] = 1e-5
        H[:, j] = (F(res.controls + e)[a:b] - F(res.controls - e)[a:b]) / 2e-5
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    assert w[0] == pytest.approx(low[i], rel=1e-4)
    u = res.controls.copy()
    u[a:b] += 0.1 * V[:, 0]
    assert C(u)[i] < C(res.controls)[i] - 1e-2  # not an equilibrium
    esc = solve_olne(g, q, options={"start": "given"})
    assert esc.status is Status.CONVERGED and esc.info["saddle_escapes"] >= 1
    assert esc.info["second_order_ok"] and np.all(esc.info["own_hessian_min_eig"] > 0)
    assert _collision_energy(g, esc.controls, q) > 1e-3
    assert nash_certificate(g, q, esc.controls).ok


def test_nonlinear_coupled_game_passes_the_certificate():
    """Two unicycles avoiding each other, and a tow truck with its trailer."""
    from epo_casadi.dynamics import Unicycle

    @dataclass(frozen=True)
    class Tow(JointDynamics):
        """The truck is a unicycle; the trailer's velocity follows the truck's."""

        name = "tow_nl"

        def step(self, xs, us, dt):
            t, r = xs
            nt = Unicycle().step(t, us[0], dt)
            vx, vy = t[2] * ca.cos(t[3]), t[2] * ca.sin(t[3])
            nr = ca.vertcat(
                r[0] + r[2] * dt,
                r[1] + r[3] * dt,
                r[2] + dt * (us[1][0] + 0.8 * (vx - r[2])),
                r[3] + dt * (us[1][1] + 0.8 * (vy - r[3])),
            )
            return [nt, nr]

    feats = [Goal(weight=2.0), Velocity(weight=0.5), Acceleration(weight=1.0)]
    agents = [
        AgentSpec("truck", "unicycle", feats, x0=[0, 0, 1.0, 0.3], goal=[2.5, 1.0], radius=0.3),
        AgentSpec(
            "trailer", "double_integrator", feats, x0=[-0.8, 0, 0, 0], goal=[1.0, -0.5], radius=0.3
        ),
        AgentSpec("car", "unicycle", feats, x0=[2, 2, 1.0, -1.2], goal=[1.0, -1.5], radius=0.3),
    ]
    spec = GameSpec(
        agents,
        [Collision(weight=10.0)],
        horizon=12,
        dt=0.2,
        couplings=[Coupling(("truck", "trailer"), Tow())],
    )
    game = PotentialGame(spec)
    p = game.default_params()
    res = solve_olne(game, p)
    assert res.status is Status.CONVERGED, res.info["stop"]
    assert res.info["second_order_ok"]
    assert nash_certificate(game, p, res.controls).ok
    lm = solve_lm(game, p)
    assert float(np.max(np.abs(res.controls - lm.controls))) > 1e-3
    bad = nash_certificate(game, p, lm.controls)
    assert not bad.ok and np.max(bad.best_response_gap) > 1e-3  # an improvement was found


# --------------------------------------------------------------------------------------
# stops, options, inputs
# --------------------------------------------------------------------------------------
def test_stop_reasons(crossing):
    game, p = crossing
    res = solve_olne(game, p, options={"max_iter": 1, "start": "given"})
    assert res.status is Status.MAX_ITER and res.info["stop"] is StopReason.MAX_ITER
    assert res.iterations == 1 and res.info["stationarity"] > 1e-8
    # a tolerance below what round-off lets F reach: stalled, not converged
    res = solve_olne(game, p, options={"tol": 1e-300, "max_iter": 50})
    assert res.status is Status.STALLED and res.info["stop"] is StopReason.LINE_SEARCH
    assert res.info["stationarity"] < 1e-8  # it did get there; only the test cannot hold
    # zero iterations: the start is reported as it is
    res = solve_olne(game, p, options={"max_iter": 0, "start": "given"})
    assert res.status is Status.MAX_ITER and res.iterations == 0
    np.testing.assert_array_equal(res.controls, game.zero_controls())


def test_non_finite_inputs_are_one_spec_error(crossing):
    game, p = crossing
    u = game.zero_controls()
    u[3] = np.nan
    with pytest.raises(SpecError) as e:
        solve_olne(game, p, u)
    assert e.value.field == "u" and "NaN" in e.value.message
    q = p.copy()
    q[0] = np.inf
    with pytest.raises(SpecError) as e:
        solve_olne(game, q)
    assert e.value.field == "p"


@dataclass(frozen=True)
class Root(Feature):
    """``sqrt(a_0)``: finite at zero controls, with an infinite derivative there."""

    kind: ClassVar[str] = "root_test"

    def steps(self, K):
        return [0]

    def residual(self, ctx):
        return ca.sqrt(ctx.U[0, 0])


def test_a_game_that_is_not_finite_at_the_start_is_nonfinite():
    agents = [
        AgentSpec("a", "double_integrator", [Goal(), Acceleration(), Root()], x0=[0, 0, 0, 0]),
        AgentSpec("b", "double_integrator", [Goal(), Acceleration()], x0=[1, 0, 0, 0]),
    ]
    game = PotentialGame(GameSpec(agents, horizon=3, dt=DT))
    p = game.default_params()
    res = solve_olne(game, p, options={"start": "given"})
    assert res.status is Status.NONFINITE and res.info["stop"] is StopReason.NONFINITE
    assert res.iterations == 0 and np.all(np.isfinite(res.controls))


def test_options_are_checked():
    assert OLNEOptions.from_mapping({"max_iter": 5}).max_iter == 5
    with pytest.raises(dataclasses.FrozenInstanceError):
        OLNEOptions().tol = 1.0  # type: ignore[misc]
    for bad, field in [
        ({"max_iter": -1}, "olne.max_iter"),
        ({"tol": 0.0}, "olne.tol"),
        ({"tol": float("nan")}, "olne.tol"),
        ({"jacobian": "bfgs"}, "olne.jacobian"),
        ({"start": "lm"}, "olne.start"),
        ({"armijo": 0.7}, "olne.armijo"),
        ({"backtrack": 1.0}, "olne.backtrack"),
        ({"damping_down": 1.0}, "olne.damping_down"),
        ({"second_order": 1}, "olne.second_order"),
    ]:
        with pytest.raises(SpecError) as e:
            OLNEOptions.from_mapping(bad)
        assert e.value.field == field, bad
    with pytest.raises(SpecError, match="unknown option"):
        OLNEOptions.from_mapping({"steps": 3})
    with pytest.raises(SpecError) as e:
        SOLVERS["olne"].make_options({"tol": -1.0})
    assert e.value.field == "olne.tol"


def test_batch_and_registry(crossing):
    game, p = crossing
    rng = np.random.default_rng(2)
    U0 = 0.05 * rng.standard_normal((2, game.n_u))
    batch = solve_game(game, np.stack([p, p]), U0, solver="olne")
    assert batch.batched and batch.controls.shape == (2, game.n_u)
    for b in range(2):
        one = solve_olne(game, p, U0[b])
        np.testing.assert_array_equal(batch[b].controls, one.controls)
        assert batch[b].status is one.status
        assert batch[b].info["own_hessian_min_eig"].shape == (game.N,)
    e = SOLVERS["olne"]
    assert e.equilibrium == "open-loop" and e.iteration_limit == "max_iter"
    json.dumps(batch[0].to_dict())  # strict JSON: every info entry converts


# --------------------------------------------------------------------------------------
# the command line
# --------------------------------------------------------------------------------------
def test_cli_solve_and_compare(capsys, tmp_path):
    out = tmp_path / "olne.json"
    rc, stdout, err = cli(
        capsys, "solve", example_path("crossing2"), "--solver", "olne", "--out", out
    )
    assert rc == 0, err
    assert "olne: converged" in stdout and "Nash certificate: passes" in stdout
    data = json.loads(out.read_text())
    assert data["solver"] == "olne" and data["status"] == "converged" and data["stop"] == "gtol"
    rc, stdout, err = cli(
        capsys,
        "compare",
        example_path("crossing2"),
        "--solver",
        "lm",
        "--solver",
        "olne",
        "--no-figures",
        "--out",
        tmp_path / "cmp",
    )
    assert rc == 0, err
    import csv

    rows = list(csv.DictReader((tmp_path / "cmp" / "compare.csv").read_text().splitlines()))
    by = {r["solver"]: r for r in rows}
    assert set(by) == {"lm", "olne"}
    assert by["olne"]["status"] == "converged" and by["olne"]["check_ok"] == "True"
    assert abs(float(by["olne"]["energy"]) - data["energy"]) <= 1e-9 * (1 + data["energy"])
    assert abs(float(by["olne"]["energy"]) - float(by["lm"]["energy"])) <= 1e-6


def test_game_file_options():
    import yaml

    from scenarios.gamefile import parse_game

    d = yaml.safe_load(example_path("crossing2").read_text())
    d["solver"] = {"olne": {"jacobian": "gn", "max_iter": 40}}
    o = parse_game(d).options("olne")
    assert isinstance(o, OLNEOptions) and (o.jacobian, o.max_iter) == ("gn", 40)
    d["solver"] = {"olne": {"max_itr": 40}}
    with pytest.raises(SpecError) as e:
        parse_game(d)
    assert e.value.field.startswith("solver.olne") and "unknown option" in e.value.message
