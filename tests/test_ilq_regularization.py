"""The iLQ solver's shift of indefinite own blocks (solvers.ilq, "Regularization").

References computed another way: ``LDL'`` pivots as ratios of leading principal minors
(numpy determinants) and ``scipy.linalg.ldl``; Gershgorin bounds and shifts written out by
hand; positive definiteness by numpy eigenvalues; feed-forward terms by a numpy solve of
the shifted block. The game has exact Hessians with hand-made indefinite stage blocks, and
is solved by both the numpy and the compiled Riccati recursion.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import pytest
import scipy.linalg

from epo_casadi import Acceleration, AgentSpec, GameSpec, PotentialGame
from epo_casadi.dynamics import Dynamics
from solvers.ilq import ILQSolver
from solvers.ilq.riccati import _gershgorin, _ldl_pivots

DELTA = 1e-8  # ILQOptions().min_curvature, the documented default

# Own 2x2 control Hessians, each chosen so that one slip in the shift logic shows:
# A: row 0 has the smaller Gershgorin bound (-1.5 < 1.5) and h00 < 0; g = -1.5.
M_A = np.array([[-1.0, 0.5], [0.5, 2.0]])
# B: positive diagonal, negative Schur complement 1 - 1.5^2 / 2 = -0.125 (only the second
# pivot fails); row 1 has the smaller bound (2 - 1.5 = 0.5 > 1 - 1.5 = -0.5); g = -0.5.
M_B = np.array([[2.0, 1.5], [1.5, 1.0]])
# positive definite (pivots 2, 0.875): no shift
M_PD = np.array([[2.0, 0.5], [0.5, 1.0]])


def documented_shift(g: float, delta: float = DELTA) -> float:
    """``max(delta - g, delta) + max(-g, 0)`` (the module docstring)."""
    return max(delta - g, delta) + max(-g, 0.0)


# shifts by hand: A: 1.5 + delta + 1.5; B: 0.5 + delta + 0.5
MU_A, MU_B = 3.0 + DELTA, 1.0 + DELTA


def test_hand_shifts_are_the_documented_ones_and_make_the_blocks_positive_definite():
    """The hand values above, checked against numpy eigenvalues (not against the solver)."""
    assert documented_shift(-1.5) == pytest.approx(MU_A, rel=1e-15)
    assert documented_shift(-0.5) == pytest.approx(MU_B, rel=1e-15)
    for M, mu in ((M_A, MU_A), (M_B, MU_B)):
        lam = np.linalg.eigvalsh(M)
        assert lam[0] < 0 < lam[1]  # indefinite
        assert np.linalg.eigvalsh(M + mu * np.eye(2))[0] >= DELTA
        # Gershgorin's theorem: the bound lies below the smallest eigenvalue
        g = min(M[i, i] - abs(M[i, 1 - i]) for i in range(2))
        assert g <= lam[0]


# --------------------------------------------------------------------------------------
# the compiled recursion's symbolic pieces, evaluated on numbers
# --------------------------------------------------------------------------------------
def _eval(fn, M: np.ndarray) -> np.ndarray:
    H = ca.SX.sym("H", *M.shape)
    out = fn(H)
    out = ca.vertcat(*out) if isinstance(out, list) else out
    return np.asarray(ca.Function("f", [H], [out])(M), float).ravel()


def _minor_ratios(M: np.ndarray) -> np.ndarray:
    """Pivots of ``LDL'`` without pivoting: ``det(M[:j+1, :j+1]) / det(M[:j, :j])``."""
    dets = [1.0] + [np.linalg.det(M[: j + 1, : j + 1]) for j in range(M.shape[0])]
    return np.array([dets[j + 1] / dets[j] for j in range(M.shape[0])])


@pytest.mark.parametrize(
    "M",
    [
        M_A,
        M_B,
        np.array([[4.0, 1.0, -2.0], [1.0, 3.0, 0.5], [-2.0, 0.5, -1.0]]),  # indefinite
        np.array([[2.0, -1.0, 0.3], [-1.0, 2.0, -1.0], [0.3, -1.0, 2.0]]),  # positive definite
    ],
)
def test_ldl_pivots_are_the_ratios_of_leading_minors(M):
    np.testing.assert_allclose(_eval(_ldl_pivots, M), _minor_ratios(M), rtol=1e-12)


def test_ldl_pivots_match_scipy_on_a_positive_definite_matrix():
    """scipy's Bunch-Kaufman factorization does not pivot here (perm is the identity)."""
    M = np.array([[2.0, -1.0, 0.3], [-1.0, 2.0, -1.0], [0.3, -1.0, 2.0]])
    _, D, perm = scipy.linalg.ldl(M)
    assert list(perm) == [0, 1, 2] and np.count_nonzero(D - np.diag(np.diag(D))) == 0
    np.testing.assert_allclose(_eval(_ldl_pivots, M), np.diag(D), rtol=1e-12)


@pytest.mark.parametrize(
    ("M", "g"),
    [
        (M_A, -1.5),  # row 0 is the smallest
        (M_B, -0.5),  # row 1 is the smallest
        (np.array([[-3.0, 1.0, 0.5], [1.0, 2.0, -0.5], [0.5, -0.5, 1.0]]), -4.5),  # row 0
        (np.array([[5.0, 1.0, 0.5], [1.0, 2.0, -0.5], [0.5, -0.5, -1.0]]), -2.0),  # row 2
    ],
)
def test_gershgorin_bound_by_hand(M, g):
    assert _eval(_gershgorin, M)[0] == pytest.approx(g, abs=1e-15)
    assert g <= np.linalg.eigvalsh(M)[0]


# --------------------------------------------------------------------------------------
# an exact-Hessian game whose own stage blocks are the matrices above
# --------------------------------------------------------------------------------------
K = 3
# own Hessian of player i at stage k; player a is convex at stage 0 (no shift there)
BLOCKS = [[M_PD, M_A, M_A], [M_B, M_B, M_B]]
GRADS = [np.array([0.3, -0.7]), np.array([-0.4, 0.9])]  # own gradients at u = 0
# the shifts by hand, (K, N)
MU_REF = np.array([[0.0, MU_B], [MU_A, MU_B], [MU_A, MU_B]])


@dataclass(frozen=True)
class Thruster(Dynamics):
    """A planar double integrator with a second ``y`` thruster: three controls."""

    name = "thruster3"
    state_names: tuple[str, ...] = ("x", "y", "vx", "vy")
    control_names: tuple[str, ...] = ("ax", "ay", "b")

    def step(self, x, u, dt):
        return ca.vertcat(
            x[0] + dt * x[2], x[1] + dt * x[3], x[2] + dt * u[0], x[3] + dt * (u[1] + u[2])
        )

    def acceleration(self, u):
        return u[0:2]


def own_cost_game(blocks, grads, dynamics_a="double_integrator"):
    """Two agents; ``C_i = sum_k 1/2 u_ik' M_ik u_ik + g_i' u_ik`` (``blocks[i][k] = M_ik``).

    The costs depend on the own controls only, so at every stage player ``i``'s own block
    of the Riccati recursion is ``M_ik`` exactly (gains ``P = 0``, the value functions
    carry no state curvature), and its feed-forward term at ``u = 0`` is
    ``(M_ik + mu_ik I)^-1 g_i``.
    """
    agents = [
        AgentSpec("a", dynamics_a, [Acceleration()], x0=[0.0, 0.0, 1.0, 0.0]),
        AgentSpec("b", "double_integrator", [Acceleration()], x0=[4.0, 1.0, -1.0, 0.5]),
    ]
    game = PotentialGame(GameSpec(agents, [], horizon=K, dt=0.2))
    x, u, p = ca.SX.sym("x", game.n_x), ca.SX.sym("u", game.n_u), ca.SX.sym("p", game.n_p)
    C = []
    for i in range(2):
        Ui = ca.reshape(u[game.uoff[i] : game.uoff[i + 1]], game.nu[i], K)
        C.append(
            sum(
                0.5 * ca.bilin(ca.DM(blocks[i][k]), Ui[:, k], Ui[:, k])
                + ca.dot(ca.DM(grads[i]), Ui[:, k])
                for k in range(K)
            )
        )
    costs = ca.Function("own_costs", [x, u, p], [ca.vertcat(*C)], ["x", "u", "p"], ["C"])
    return game, costs


@pytest.fixture(scope="module")
def game_and_costs():
    return own_cost_game(BLOCKS, GRADS)


def _first_pass(game, costs, backend, monkeypatch, tmp_path, delta=DELTA):
    """The result of ``max_iter = 0``: the shifts and ``P``, ``a`` of the first backward pass."""
    s = ILQSolver(game, costs)
    opts = {"hessian": "exact", "max_iter": 0, "min_curvature": delta}
    if backend == "compiled":
        from solvers.codegen import CompilerError, find_compiler

        try:
            find_compiler()
        except CompilerError:
            pytest.skip("no C compiler")
        monkeypatch.setenv("EPO_CACHE_DIR", str(tmp_path))

        def no_fallback(*args):
            raise AssertionError("the compiled stage fell back to numpy")

        monkeypatch.setattr(s, "_numpy_backward", no_fallback)
        opts["compiled"] = True
    res = s.solve(game.default_params(), options=opts)
    assert res.info["backend"] == backend and res.info["hessian"] == "exact"
    return res


def _check_first_pass(res, game, blocks, grads, mu_ref, delta=DELTA):
    """Shifts and feed-forward terms of the first backward pass against the hand values."""
    np.testing.assert_allclose(res.info["regularization"], mu_ref, rtol=1e-14, atol=0)
    assert res.info["max_regularization"] == pytest.approx(np.max(mu_ref), rel=1e-14)
    a = res.info["feedforward"]
    for k in range(K):
        for i in range(2):
            H = blocks[i][k] + mu_ref[k, i] * np.eye(game.nu[i])
            lam = np.linalg.eigvalsh(H)[0]
            assert lam > 0 and (mu_ref[k, i] == 0 or lam >= delta)  # convex, lifted if shifted
            own = slice(game.uoff[i] // K, game.uoff[i + 1] // K)
            np.testing.assert_allclose(
                a[k, own], np.linalg.solve(H, grads[i]), rtol=1e-12, atol=1e-14
            )
    np.testing.assert_array_equal(res.info["gains"], 0.0)


@pytest.mark.parametrize("backend", ["numpy", "compiled"])
def test_indefinite_blocks_are_shifted_by_the_documented_amount(
    game_and_costs, backend, monkeypatch, tmp_path
):
    game, costs = game_and_costs
    res = _first_pass(game, costs, backend, monkeypatch, tmp_path)
    _check_first_pass(res, game, BLOCKS, GRADS, MU_REF)


# pivots exactly at min_curvature = 1 (exact in floating point): a: h00 = 1;
# b: h11 - h01 h10 / h00 = 1.75 - 2.25 / 3 = 1 (LDL': 1.75 - (1.5 / 3) 1.5)
EDGE = [[np.diag([1.0, 3.0])] * K, [np.array([[3.0, 1.5], [1.5, 1.75]])] * K]
EDGE_GRADS = [np.array([1.0, -2.0]), np.array([0.5, 0.25])]


@pytest.mark.parametrize("backend", ["numpy", "compiled"])
def test_pivots_exactly_at_min_curvature_are_accepted(backend, monkeypatch, tmp_path):
    """``>= min_curvature`` passes (no shift); a hair above, both blocks are shifted by
    ``max(delta - g, delta) + max(-g, 0) = delta`` (``g = 1`` for a, ``0.25`` for b)."""
    game, costs = own_cost_game(EDGE, EDGE_GRADS)
    res = _first_pass(game, costs, backend, monkeypatch, tmp_path, delta=1.0)
    _check_first_pass(res, game, EDGE, EDGE_GRADS, np.zeros((K, 2)), delta=1.0)
    d = 1.0 + 2.0**-20
    res = _first_pass(game, costs, backend, monkeypatch, tmp_path, delta=d)
    mu = np.full((K, 2), d)
    _check_first_pass(res, game, EDGE, EDGE_GRADS, mu, delta=d)


# three controls for agent a: the general path (Cholesky test, Gershgorin of every row)
M3 = np.array([[-3.0, 1.0, 0.5], [1.0, 2.0, -0.5], [0.5, -0.5, 1.0]])  # g = -4.5 (row 0)
M3_PD = np.array([[2.0, -1.0, 0.3], [-1.0, 2.0, -1.0], [0.3, -1.0, 2.0]])
BLOCKS3 = [[M3_PD, M3, M3], [M_B, M_PD, M_B]]
GRADS3 = [np.array([0.3, -0.7, 0.2]), np.array([-0.4, 0.9])]
MU3 = np.array([[0.0, MU_B], [9.0 + DELTA, 0.0], [9.0 + DELTA, MU_B]])


@pytest.mark.parametrize("backend", ["numpy", "compiled"])
def test_three_control_agent_is_shifted_by_the_documented_amount(backend, monkeypatch, tmp_path):
    assert documented_shift(-4.5) == pytest.approx(MU3[1, 0], rel=1e-15)
    game, costs = own_cost_game(BLOCKS3, GRADS3, Thruster())
    assert game.nu == [3, 2]
    res = _first_pass(game, costs, backend, monkeypatch, tmp_path)
    _check_first_pass(res, game, BLOCKS3, GRADS3, MU3)


def _stage_matrix(s, blocks):
    T = np.zeros((s.N, s.n, s.n))
    for i, M in enumerate(blocks):
        T[i, s.uo[i] : s.uo[i + 1], s.uo[i] : s.uo[i + 1]] = M
    return T


def test_numpy_own_shift_of_hand_made_blocks(game_and_costs):
    """``_own_shift`` (2x2 closed form) on stage matrices holding the blocks."""
    game, costs = game_and_costs
    s = ILQSolver(game, costs)
    for blocks, want in (((M_A, M_B), [MU_A, MU_B]), ((M_B, M_PD), [MU_B, 0.0])):
        got = s._own_shift(_stage_matrix(s, blocks), DELTA)
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=0)
    assert s._own_shift(_stage_matrix(s, (M_PD, M_PD)), DELTA) is None


def test_numpy_own_shift_general_path_at_the_threshold():
    """Three controls: the Cholesky test. Pivots (0.25, 4, 1): accepted at delta = 0.25
    (``L_00^2 = 0.25`` exactly), shifted at delta = 0.5 by ``max(delta - g, delta) = delta``
    (``g = 0.25``)."""
    game, costs = own_cost_game(BLOCKS3, GRADS3, Thruster())
    s = ILQSolver(game, costs)
    T = _stage_matrix(s, (np.diag([0.25, 4.0, 1.0]), M_PD))
    assert s._own_shift(T, 0.25) is None
    np.testing.assert_allclose(s._own_shift(T, 0.5), [0.5, 0.0], rtol=1e-14, atol=0)
