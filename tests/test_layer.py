"""The differentiable game layer (learning/layer.py).

References used here (STYLE.md): float64 finite differences (``torch.autograd.gradcheck``)
for both backward modes, an independent solver (``solve_lm`` on the same options; an exact
Newton refinement for the implicit mode's finite differences) and a known optimum (weights
recovered from demonstrations generated with them).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from epo_casadi import (
    Acceleration,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    Jerk,
    PotentialGame,
    SpecError,
    TurnRate,
    Velocity,
)
from learning.layer import (
    STATUS_CODES,
    GameLayer,
    GameLayerFunction,
    decode_status,
    status_code,
)
from learning.layer_core import layer_functions
from solvers.lm import DenseGN, LMOptions, solve_lm
from solvers.result import Status

from .helpers import crossing_game

MAX_ITER, NONFINITE, CONVERGED = (
    status_code(s) for s in (Status.MAX_ITER, Status.NONFINITE, Status.CONVERGED)
)


def head_on_spec(K: int = 6, collision: float = 5.0, gap: float = 1.2) -> GameSpec:
    """Two unicycles driving at each other; with zero controls they overlap from step 4."""
    feats = [Goal(weight=2.0), Velocity(weight=0.5), Acceleration(weight=1.0), TurnRate(weight=1.0)]
    a0 = AgentSpec(
        "a0", "unicycle", feats, radius=0.25, x0=[-gap / 2, 0.05, 1.0, 0.0], goal=[0.8, 0.1]
    )
    a1 = AgentSpec(
        "a1", "unicycle", feats, radius=0.25, x0=[gap / 2, -0.05, 1.0, np.pi], goal=[-0.8, -0.1]
    )
    return GameSpec([a0, a1], [Collision(weight=collision)], horizon=K, dt=0.1)


@pytest.fixture(scope="module")
def game() -> PotentialGame:
    return PotentialGame(head_on_spec())


def collision_energy(game, u, p) -> np.ndarray:
    """Energy of the collision term of every problem at ``(u, p)``."""
    te = np.array(
        [
            np.array(game.function("term_energies")(ui, pi)).ravel()
            for ui, pi in zip(u, p, strict=True)
        ]
    )
    idx = [t.index for t in game.terms if t.feature == "collision"]
    return te[:, idx].sum(1)


def inputs(layer: GameLayer, seed: int = 0):
    """Leaf tensors (u_init, w_own, w_pair, goal, x0) of a batch of two problems."""
    rng = np.random.default_rng(seed)
    base = layer.default_params()
    u0 = torch.tensor(0.05 * rng.normal(size=(2, layer.game.n_u)), requires_grad=True)
    w_own = base[layer.param_index("w_own")].clone().requires_grad_()
    w_pair = base[layer.param_index("w_pair")].clone().requires_grad_()
    goal = (
        base[layer.param_index("goal")] + torch.tensor(0.1 * rng.normal(size=(2, 4)))
    ).requires_grad_()
    x0 = base[layer.param_index("x0")].clone().requires_grad_()
    return u0, w_own, w_pair, goal, x0


# --------------------------------------------------------------------------------------
# Forward: same numbers as the solver
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "options",
    [
        LMOptions.paper(),
        # early stopping by gtol/ftol: some problems freeze before the last step
        LMOptions(
            steps=40, step_size=1.0, damping=1.0, adaptive_damping=False, gtol=1e-6, ftol=1e-9
        ),
    ],
    ids=["paper", "early_stop"],
)
def test_unrolled_outputs_equal_solve_lm(options):
    game = crossing_game(N=2, K=12, offset=0.3)
    layer = GameLayer(game, options)
    rng = np.random.default_rng(1)
    P = np.tile(game.default_params(), (3, 2, 1))
    P[..., game.params.group("goal")] += 0.3 * rng.normal(size=(3, 2, 4))
    U = 0.1 * rng.normal(size=(3, 2, game.n_u))
    out = layer(torch.tensor(P), torch.tensor(U))
    assert out.controls.shape == (3, 2, game.n_u) and out.states.shape == (3, 2, game.n_x)
    assert out.status.shape == (3, 2) and out.status.dtype == torch.int64
    ref = solve_lm(game, P.reshape(6, -1), U.reshape(6, -1), options)
    assert np.array_equal(out.controls.numpy().reshape(6, -1), ref.controls)
    assert np.array_equal(out.states.numpy().reshape(6, -1), ref.states)
    assert list(decode_status(out.status).ravel()) == list(ref.status)
    if options.gtol > 0:
        # the early-stopping path was taken, at different steps for different problems
        assert (ref.iterations < options.steps).all() and len(set(ref.iterations)) > 1


def test_implicit_forward_is_the_newton_optimum(game):
    """The implicit forward stops at a stationary point: an exact Newton refinement (an
    independent solver using the Hessian) barely moves it, and the gradient is ~0 there."""
    layer = GameLayer(game, backward="implicit")
    P = np.tile(game.default_params(), (2, 1))
    U = 0.05 * np.random.default_rng(2).normal(size=(2, game.n_u))
    out = layer(torch.tensor(P), torch.tensor(U))
    assert (out.status == CONVERGED).all()
    u = out.controls.numpy()
    assert np.abs(u - U).max() > 0.1  # the solve moved far from the start
    # LM stops by ftol here (|grad| ~ 4e-7 > gtol; Gauss-Newton converges linearly with
    # non-zero residuals), ~1e-6 from the optimum; the Hessian is well conditioned (~2.5)
    np.testing.assert_allclose(u, newton_polish(game, u, P), rtol=0, atol=5e-6)
    grad = game.function("gradient")
    for b in range(2):
        assert np.abs(np.array(grad(u[b], P[b])).ravel()).max() <= 5e-6
    roll = game.function("rollout")
    X = np.array([np.array(roll(u[b], P[b])).ravel() for b in range(2)])
    np.testing.assert_allclose(out.states.numpy(), X, rtol=0, atol=1e-12)


class CountingDense(DenseGN):
    """The dense backend, counting its calls."""

    def __init__(self, game):
        super().__init__(game)
        self.calls = {"linearize": 0, "solve": 0}

    def linearize(self, U, P):
        self.calls["linearize"] += 1
        return super().linearize(U, P)

    def solve(self, lin, damping, rhs, ellipsoidal=False):
        self.calls["solve"] += 1
        return DenseGN.solve(lin, damping, rhs, ellipsoidal)


def counting_structured(game):
    """A structured backend (no dense fallback asserted) that counts its own Riccati solves."""
    from solvers.structured import StructuredGN, StructuredLinearization

    class Counting(StructuredGN):
        def linearize(self, U, P):
            lin = super().linearize(U, P)
            assert isinstance(lin, StructuredLinearization)
            self.calls["linearize"] += 1
            return lin

        def solve(self, lin, damping, rhs, ellipsoidal=False):
            assert isinstance(lin, StructuredLinearization)  # never the dense path
            self.calls["solve"] += 1
            return super().solve(lin, damping, rhs, ellipsoidal)

    be = Counting(game)
    be.calls = {"linearize": 0, "solve": 0}
    assert be.fallback is None
    return be


class NaNAtSecondLinearization(DenseGN):
    """The dense backend, with problem 1's energy turned NaN at its second linearization
    (after the first step): the problem must be frozen there and the others go on."""

    def __init__(self, game):
        super().__init__(game)
        self.count = 0

    def linearize(self, U, P):
        lin = super().linearize(U, P)
        self.count += 1
        if self.count == 2:
            lin.energy[1] = np.nan
        return lin


def test_problem_turning_nonfinite_mid_solve_is_frozen(game):
    opts = LMOptions.paper(steps=3)
    layer = GameLayer(game, opts, backend=NaNAtSecondLinearization(game))
    u0, _, _, goal, _ = inputs(layer)
    p = layer.assemble_params(goal=goal)
    out = layer(p, u0)
    assert out.status.tolist() == [MAX_ITER, NONFINITE]
    ref = solve_lm(
        game, p.detach().numpy(), u0.detach().numpy(), opts, backend=NaNAtSecondLinearization(game)
    )
    assert list(ref.status) == [Status.MAX_ITER, Status.NONFINITE]
    assert np.array_equal(out.controls.detach().numpy(), ref.controls)
    torch.testing.assert_close(out.controls[1], u0[1].detach(), rtol=0, atol=0)  # frozen at u0
    # problem 0 is untouched by its neighbour: as solved alone with a clean backend
    alone = GameLayer(game, opts, backend=DenseGN(game))
    out0 = alone(layer.assemble_params(goal=goal[:1]), u0[:1])
    torch.testing.assert_close(out.controls[:1], out0.controls, rtol=0, atol=1e-12)
    g = torch.autograd.grad(out.states[0].square().sum(), goal)[0]
    g0 = torch.autograd.grad(out0.states.square().sum(), goal)[0]
    assert torch.isfinite(g).all() and (g[1] == 0).all() and (g[0] != 0).any()
    torch.testing.assert_close(g[:1], g0[:1], rtol=1e-10, atol=1e-12)


@pytest.fixture(scope="module")
def game8() -> PotentialGame:
    """The head-on game with K = 8: there the structured backend does not fall back."""
    g = PotentialGame(head_on_spec(K=8))
    from solvers.structured import StructuredGN

    assert StructuredGN(g).fallback is None
    return g


def test_default_backend_is_structured_without_fallback(game8, game):
    from solvers.structured import StructuredGN

    for g, falls_back in ((game8, False), (game, True)):
        be = GameLayer(g, LMOptions.paper()).core.backend
        assert isinstance(be, StructuredGN) and (be.fallback is not None) == falls_back


def test_dense_and_structured_backends_agree_in_the_layer(game8):
    opts = LMOptions.paper()
    dense, struct = CountingDense(game8), counting_structured(game8)
    u0, w_own, w_pair, goal, x0 = inputs(GameLayer(game8, opts))
    p = GameLayer(game8, opts).assemble_params(goal=goal).detach().numpy()
    assert (collision_energy(game8, u0.detach().numpy(), p) > 0.1).all()
    outs, grads = {}, {}
    for name, backend in (("dense", dense), ("structured", struct)):
        layer = GameLayer(game8, opts, backend=backend)
        p = layer.assemble_params(goal=goal)
        out = layer(p, u0)
        grads[name] = torch.autograd.grad(out.states.square().sum(), (u0, goal))
        # S linearizations and S solves forward, S solves backward
        assert backend.calls == {"linearize": 2, "solve": 2 + 2}, name
        ref = solve_lm(game8, p.detach().numpy(), u0.detach().numpy(), opts, backend=backend)
        assert np.array_equal(out.controls.detach().numpy(), ref.controls)
        outs[name] = out.controls.detach()
    assert (outs["dense"] - u0.detach()).abs().max() > 1e-2  # the steps moved
    torch.testing.assert_close(outs["dense"], outs["structured"], rtol=0, atol=1e-12)
    for a, b in zip(grads["dense"], grads["structured"], strict=True):
        assert a.abs().max() > 0
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------------------------
# Gradients vs finite differences
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "options",
    [
        LMOptions.paper(),
        LMOptions(steps=8, step_size=1.0, damping=0.1, adaptive_damping=False, gtol=0.0, ftol=0.0),
    ],
    ids=["paper", "8_steps"],
)
def test_gradcheck_unrolled(game, options):
    layer = GameLayer(game, options, "unrolled")
    u0, w_own, w_pair, goal, x0 = inputs(layer)
    p = layer.assemble_params(goal=goal).detach().numpy()
    assert (collision_energy(game, u0.detach().numpy(), p) > 0.1).all()  # the regime we claim

    def f(u0, w_own, w_pair, goal, x0):
        out = layer(layer.assemble_params(w_own=w_own, w_pair=w_pair, goal=goal, x0=x0), u0)
        return out.controls, out.states

    assert torch.autograd.gradcheck(f, (u0, w_own, w_pair, goal, x0))
    out = layer(layer.assemble_params(goal=goal), u0)
    assert (collision_energy(game, out.controls.detach().numpy(), p) > 0).all()  # still active


def newton_polish(game, u, p, iters=4):
    """Refine converged solutions with exact Newton steps (an independent reference)."""
    g, H = game.function("gradient"), game.function("hessian")
    u = np.array(u, dtype=float)
    for b in range(u.shape[0]):
        for _ in range(iters):
            u[b] -= np.linalg.solve(np.array(H(u[b], p[b])), np.array(g(u[b], p[b])).ravel())
    return u


def test_gradcheck_implicit(game):
    layer = GameLayer(game, LMOptions(steps=100), "implicit")
    u0, w_own, w_pair, goal, x0 = inputs(layer)
    p = layer.assemble_params(goal=goal).detach().numpy()
    assert (collision_energy(game, u0.detach().numpy(), p) > 0.1).all()
    roll = game.function("rollout")

    def f(u0, w_own, w_pair, goal, x0):
        # LM stops at |grad| ~ 1e-9 (an energy-decrease test at rounding level); finite
        # differences need the optimum to ~1e-14, so add the (detached) Newton refinement.
        p = layer.assemble_params(w_own=w_own, w_pair=w_pair, goal=goal, x0=x0)
        out = layer(p, u0)
        assert (out.status == CONVERGED).all()
        P = p.detach().numpy()
        U = newton_polish(game, out.controls.detach().numpy(), P)
        X = np.array([np.array(roll(ub, pb)).ravel() for ub, pb in zip(U, P, strict=True)])
        du = torch.tensor(U) - out.controls.detach()
        dx = torch.tensor(X) - out.states.detach()
        assert du.abs().max() < 1e-6
        return out.controls + du, out.states + dx

    assert torch.autograd.gradcheck(f, (u0, w_own, w_pair, goal, x0))
    out = layer(layer.assemble_params(goal=goal), u0)
    assert (collision_energy(game, out.controls.detach().numpy(), p) > 0).all()  # active at u*
    g = torch.autograd.grad(out.controls.sum() + out.states.sum(), u0)[0]
    assert torch.equal(g, torch.zeros_like(g))  # implicit mode: no dependence on u_init


@pytest.mark.parametrize("backward", ["unrolled", "implicit"])
def test_gradcheck_structured_backend(game8, backward):
    """Both backward modes through the structured (Riccati) backend, which really runs here
    (no dense fallback; every solve goes through its stage recursion), against float64
    finite differences."""
    opts = LMOptions.paper() if backward == "unrolled" else LMOptions(steps=100)
    be = counting_structured(game8)
    layer = GameLayer(game8, opts, backward, backend=be)
    u0, w_own, w_pair, goal, x0 = inputs(layer)
    p = layer.assemble_params(goal=goal).detach().numpy()
    assert (collision_energy(game8, u0.detach().numpy(), p) > 0.1).all()
    roll = game8.function("rollout")

    def f(u0, w_own, w_pair, goal, x0):
        p = layer.assemble_params(w_own=w_own, w_pair=w_pair, goal=goal, x0=x0)
        out = layer(p, u0)
        if backward == "unrolled":
            return out.controls, out.states
        assert (out.status == CONVERGED).all()
        P = p.detach().numpy()
        U = newton_polish(game8, out.controls.detach().numpy(), P)
        X = np.array([np.array(roll(ub, pb)).ravel() for ub, pb in zip(U, P, strict=True)])
        du = torch.tensor(U) - out.controls.detach()
        assert du.abs().max() < 1e-6
        return out.controls + du, out.states + (torch.tensor(X) - out.states.detach())

    assert torch.autograd.gradcheck(f, (u0, w_own, w_pair, goal, x0))
    assert be.calls["solve"] > 0 and be.calls["linearize"] > 0


def test_unrolled_approaches_implicit(game):
    u0, w_own, w_pair, goal, x0 = inputs(GameLayer(game))
    target = torch.tensor(np.random.default_rng(3).normal(size=game.n_x))
    grads, sols = {}, {}
    modes = {
        "implicit": GameLayer(game, LMOptions(steps=100), "implicit"),
        "unrolled_5": GameLayer(
            game,
            LMOptions(steps=5, step_size=1.0, damping=1e-2, adaptive_damping=False, gtol=0, ftol=0),
        ),
        "unrolled_60": GameLayer(
            game,
            LMOptions(
                steps=60, step_size=1.0, damping=1e-2, adaptive_damping=False, gtol=0, ftol=0
            ),
        ),
    }
    for name, layer in modes.items():
        out = layer(layer.assemble_params(w_own=w_own, w_pair=w_pair, goal=goal, x0=x0), u0)
        loss = ((out.states - target) ** 2).sum()
        grads[name] = torch.cat(
            [g.reshape(-1) for g in torch.autograd.grad(loss, (w_own, w_pair, goal, x0))]
        )
        sols[name] = out.controls.detach()
    torch.testing.assert_close(sols["unrolled_60"], sols["implicit"], rtol=0, atol=1e-6)

    def rel(a):
        return float((grads[a] - grads["implicit"]).norm() / grads["implicit"].norm())

    assert rel("unrolled_60") < 1e-5 < rel("unrolled_5")


def test_gradients_reach_every_input():
    game = crossing_game(N=2, K=15)
    opts = LMOptions.paper()
    layer = GameLayer(game, opts)
    rng = np.random.default_rng(4)
    base = layer.default_params()
    # problem 0: agents cross head-on (collision active); problem 1: pedestrian moved far away
    x0 = base[layer.param_index("x0")].repeat(2, 1)
    x0[:, 4] = 0.8  # agent a1 starts 2.2 m in front of a0, both at 1 m/s
    x0[1, 5] += 20.0
    goal = base[layer.param_index("goal")].repeat(2, 1)
    goal[1, 3] += 20.0
    x0.requires_grad_()
    goal.requires_grad_()
    w_own = base[layer.param_index("w_own")].repeat(2, 1).requires_grad_()
    w_pair = base[layer.param_index("w_pair")].repeat(2, 1).requires_grad_()
    u0 = torch.tensor(0.1 * rng.normal(size=(2, game.n_u)), requires_grad=True)
    p = layer.assemble_params(x0=x0, goal=goal, w_own=w_own, w_pair=w_pair)
    out = layer(p, u0)
    loss = out.states.square().sum() + out.controls.square().sum()
    g_u0, g_x0, g_goal, g_own, g_pair = torch.autograd.grad(loss, (u0, x0, goal, w_own, w_pair))
    for gr in (g_u0, g_x0, g_goal, g_own, g_pair):
        assert torch.isfinite(gr).all()
    assert (g_u0 != 0).all(dim=1).any() and (g_u0.abs().sum(1) > 0).all()
    assert (g_x0.abs().sum(1) > 0).all() and (g_goal != 0).all()
    # a weight gets a gradient exactly when its term is non-zero at an iterate the steps used
    P = p.detach().numpy()
    u1 = GameLayer(game, LMOptions.paper(steps=1))(p.detach(), u0.detach()).controls.numpy()
    te = game.function("term_energies")
    used = np.zeros((2, len(game.terms)), dtype=bool)
    for U in (u0.detach().numpy(), u1):
        used |= np.array([np.array(te(U[b], P[b])).ravel() > 0 for b in range(2)])
    w_names = [b.name for b in game.params.blocks if b.group in ("w_own", "w_pair")]
    g_w = torch.cat([g_own, g_pair], dim=1).numpy()
    for t in game.terms:
        j = w_names.index(t.weight)
        np.testing.assert_array_equal(g_w[:, j] != 0, used[:, t.index], err_msg=t.weight)
    assert used[0, -1] and not used[1, -1]  # collision active in problem 0 only
    assert not used[:, [t.index for t in game.terms if t.feature_type == "velocity_bound"]].any()


# --------------------------------------------------------------------------------------
# Learning: recover weights from demonstrations
# --------------------------------------------------------------------------------------
def learning_spec(w_goal: float, w_acc: float) -> GameSpec:
    feats = [Goal(weight=w_goal), Acceleration(weight=w_acc), TurnRate(weight=1.0)]
    a0 = AgentSpec("a0", "unicycle", feats, radius=0.25, x0=[-2.0, 0.0, 1.0, 0.0], goal=[2.0, 0.5])
    a1 = AgentSpec(
        "a1", "unicycle", feats, radius=0.25, x0=[2.0, 0.1, 1.0, np.pi], goal=[-2.0, -0.5]
    )
    return GameSpec([a0, a1], [Collision(weight=3.0)], horizon=10, dt=0.2)


@pytest.mark.parametrize(
    "backward, options",
    [
        ("implicit", LMOptions(steps=100)),
        # the paper's mode with enough fixed-damping steps to be nearly converged
        ("unrolled", LMOptions.paper(steps=10, step_size=1.0, damping=0.1)),
    ],
    ids=["implicit", "unrolled_10"],
)
def test_learning_recovers_weight_ratio(backward, options):
    """True goal : acceleration = 3 : 1; learning starts from 1 : 3 (turn-rate weight fixed)."""
    torch.manual_seed(0)
    game = PotentialGame(learning_spec(3.0, 1.0))
    layer = GameLayer(game, options, backward)
    rng = np.random.default_rng(5)
    B = 6
    x0 = layer.default_params()[layer.param_index("x0")].repeat(B, 1)
    x0[:, [0, 1, 4, 5]] += torch.tensor(0.3 * rng.normal(size=(B, 4)))
    goal = layer.default_params()[layer.param_index("goal")] + torch.tensor(
        0.5 * rng.normal(size=(B, 4))
    )
    p_true = layer.assemble_params(x0=x0, goal=goal)
    demo = layer(p_true).states.detach()
    own = [b.name for b in game.params.blocks if b.group == "w_own"]
    goal_idx = [i for i, n in enumerate(own) if n.endswith(".goal")]
    acc_idx = [i for i, n in enumerate(own) if n.endswith(".acceleration")]
    log_w = torch.tensor([np.log(1.0), np.log(3.0)], requires_grad=True)
    opt = torch.optim.Adam([log_w], lr=0.05)
    w_fixed = layer.default_params()[layer.param_index("w_own")]
    for _ in range(250):
        w = w_fixed.clone()
        w = w.index_copy(0, torch.tensor(goal_idx), log_w[0].exp().expand(2))
        w = w.index_copy(0, torch.tensor(acc_idx), log_w[1].exp().expand(2))
        out = layer(layer.assemble_params(x0=x0, goal=goal, w_own=w))
        loss = ((out.states - demo) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    ratio = float((log_w[0] - log_w[1]).exp().detach())
    assert abs(ratio - 3.0) / 3.0 < 0.02, ratio
    assert float(loss.detach()) < 1e-6


# --------------------------------------------------------------------------------------
# Dtypes, shapes, parameters
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("backward", ["unrolled", "implicit"])
def test_float32(game, backward):
    layer = GameLayer(game, backward=backward)
    u0, _, _, goal, _ = inputs(layer)
    outs, grads = {}, {}
    for dt in (torch.float64, torch.float32):
        g32 = goal.detach().to(dt).requires_grad_()
        u32 = u0.detach().to(dt).requires_grad_()
        out = layer(layer.assemble_params(goal=g32), u32)
        assert out.controls.dtype == dt and out.states.dtype == dt
        grads[dt] = torch.autograd.grad(out.states.sum(), (g32, u32))
        assert all(g.dtype == dt for g in grads[dt])
        outs[dt] = out.states
    torch.testing.assert_close(
        outs[torch.float32].double(), outs[torch.float64], rtol=1e-5, atol=1e-5
    )
    for a, b in zip(grads[torch.float32], grads[torch.float64], strict=True):
        torch.testing.assert_close(a.double(), b, rtol=1e-4, atol=1e-5)


def test_broadcasting_and_default_u_init(game):
    layer = GameLayer(game)
    p = layer.default_params().requires_grad_()
    u = torch.zeros(3, 2, game.n_u, dtype=torch.float64)
    out = layer(p, u)
    assert out.controls.shape == (3, 2, game.n_u) and out.status.shape == (3, 2)
    single = layer(p)  # u_init defaults to zeros, no batch dimension
    assert single.controls.shape == (game.n_u,) and single.status.shape == ()
    torch.testing.assert_close(single.controls, out.controls[1, 0], rtol=0, atol=0)
    (gp,) = torch.autograd.grad(out.states.sum(), p)  # summed over the broadcast problems
    (g1,) = torch.autograd.grad(single.states.sum(), p)
    torch.testing.assert_close(gp, 6 * g1)


def test_assemble_params(game):
    layer = GameLayer(game)
    goal = torch.tensor([[1.0, 2.0], [3.0, 4.0]], dtype=torch.float64, requires_grad=True)  # (N, 2)
    w = torch.tensor(7.0, dtype=torch.float64, requires_grad=True)
    p = layer.assemble_params(goal=goal, blocks={"w.a0-a1.collision": w.reshape(1)})
    ref = game.params.pack({"goal.a0": [1, 2], "goal.a1": [3, 4], "w.a0-a1.collision": 7.0})
    np.testing.assert_array_equal(p.detach().numpy(), ref)
    (gg, gw) = torch.autograd.grad((p * torch.arange(game.n_p)).sum(), (goal, w))
    idx = game.params.group("goal")
    np.testing.assert_array_equal(gg.numpy().ravel(), idx)
    assert float(gw) == game.params["w.a0-a1.collision"].start
    batched = layer.assemble_params(x0=torch.zeros(5, 8))
    assert batched.shape == (5, game.n_p) and batched.dtype == torch.float32  # the values' dtype
    # per-agent blocks (..., N, 2) with batch dimensions: the same as flat (..., 2 N)
    goals = torch.arange(3 * 5 * 4, dtype=torch.float64).reshape(3, 5, 2, 2)
    torch.testing.assert_close(
        layer.assemble_params(goal=goals), layer.assemble_params(goal=goals.reshape(3, 5, 4))
    )
    assert layer.assemble_params(goal=goals).shape == (3, 5, game.n_p)
    with pytest.raises(SpecError, match="w_pair"):
        layer.assemble_params(w_pair=torch.ones(3))
    with pytest.raises(SpecError, match="unknown parameter block"):
        layer.assemble_params(blocks={"w.nobody.goal": torch.ones(1)})


def test_status_codes():
    assert STATUS_CODES[status_code(Status.NONFINITE)] is Status.NONFINITE
    assert list(decode_status(torch.tensor([[0, 2]])).ravel()) == [
        Status.CONVERGED,
        Status.NONFINITE,
    ]


# --------------------------------------------------------------------------------------
# Invalid inputs and options
# --------------------------------------------------------------------------------------
def test_invalid_inputs_raise(game):
    layer = GameLayer(game)
    p = layer.default_params().repeat(2, 1)
    bad = p.clone()
    bad[1, game.params["goal.a1"].start] = float("nan")
    with pytest.raises(ValueError, match=r"p: NaN or inf in \['goal.a1.x'\] of problem \(1,\)"):
        layer(bad)
    bad = p.clone()
    bad[0, game.params["w.a0.velocity"].start] = -1.0
    with pytest.raises(ValueError, match=r"negative weight\(s\) \['w.a0.velocity'\]"):
        layer(bad)
    u = torch.zeros(2, game.n_u, dtype=torch.float64)
    u[1, 3] = float("inf")
    with pytest.raises(ValueError, match="u_init: NaN or inf in problem"):
        layer(p, u)
    with pytest.raises(SpecError, match="last dimension"):
        layer(p[:, :-1])
    with pytest.raises(SpecError, match="floating-point"):
        GameLayerFunction.apply(layer.core, p, torch.zeros(2, game.n_u, dtype=torch.long), (2,))


@pytest.mark.parametrize("backward", ["unrolled", "implicit"])
def test_invalid_inputs_masked(game, backward):
    layer = GameLayer(game, backward=backward, on_invalid="mask")
    u0, _, _, goal, _ = inputs(layer)
    goal3 = torch.cat([goal.detach(), goal.detach()[:1]]).requires_grad_()
    u3 = torch.cat([u0.detach(), u0.detach()[:1]]).requires_grad_()
    p = layer.assemble_params(goal=goal3)
    mask = torch.zeros_like(p)
    mask[1, game.params["goal.a0"].start] = float("nan")  # problem 1: NaN goal
    mask[2, game.params["w.a1.goal"].start] = -10.0  # problem 2: negative weight
    out = layer(p + mask, u3)
    assert out.status.tolist()[1:] == [NONFINITE, NONFINITE] and out.status[0] != NONFINITE
    assert torch.isfinite(out.controls).all() and torch.isfinite(out.states).all()
    assert (out.controls[1:] == 0).all()
    ref = layer(layer.assemble_params(goal=goal3[:1]), u3[:1])
    torch.testing.assert_close(out.states[:1], ref.states, rtol=0, atol=0)
    gg, gu = torch.autograd.grad(out.states.sum() + out.controls.sum(), (goal3, u3))
    assert torch.isfinite(gg).all() and torch.isfinite(gu).all()
    assert (gg[1:] == 0).all() and (gu[1:] == 0).all() and (gg[0] != 0).any()
    rg = torch.autograd.grad(ref.states.sum() + ref.controls.sum(), goal3)[0]
    torch.testing.assert_close(gg[:1], rg[:1])


def test_invalid_options(game):
    with pytest.raises(SpecError, match="adaptive_damping"):
        GameLayer(game, LMOptions(), "unrolled")
    with pytest.raises(SpecError, match="ellipsoidal"):
        GameLayer(game, LMOptions.paper(ellipsoidal=True), "unrolled")
    with pytest.raises(SpecError, match="converged solve"):
        GameLayer(game, LMOptions.paper(), "implicit")
    with pytest.raises(SpecError, match="backward"):
        GameLayer(game, backward="adjoint")
    with pytest.raises(SpecError, match="on_invalid"):
        GameLayer(game, on_invalid="ignore")
    with pytest.raises(SpecError, match="unknown option"):
        GameLayer(game, {"stepz": 2})


def test_step_vjp_is_built_once(game):
    assert layer_functions(game, "lm_step_vjp") is layer_functions(game, "lm_step_vjp")
    f = layer_functions(game, "lm_step_vjp")
    assert f.name_in() == ["u", "p", "du", "z"] and f.name_out() == ["gu", "gp"]


def test_documented_defaults(game):
    """The defaults the docstring promises: paper options for the unrolled mode, a
    converging LMOptions() for the implicit one, errors on invalid input, CasADi's
    interpreter (no C compiler needed)."""
    layer = GameLayer(game)
    assert layer.backward == "unrolled" and layer.options == LMOptions.paper()
    assert layer.on_invalid == "raise" and layer.compiled is False
    assert GameLayer(game, backward="implicit").options == LMOptions()


def test_compiled_layer_leaves_large_functions_interpreted(game8, monkeypatch):
    """With ``compiled=True`` the functions above MAX_COMPILED_INSTRUCTIONS stay
    interpreted (named in ``layer.interpreted``); outputs and gradients equal the fully
    interpreted layer's bit for bit, and those of the fully compiled one to rounding."""
    pytest.importorskip("solvers.codegen").find_compiler()
    import learning.layer_core as L

    rng = np.random.default_rng(3)
    p0 = torch.as_tensor(game8.params.defaults())
    u0 = torch.as_tensor(rng.normal(scale=0.1, size=(2, game8.n_u)))

    def run(layer):
        p = p0.expand(2, -1).clone().requires_grad_(True)
        u = u0.clone().requires_grad_(True)
        out = layer(p, u)
        (out.states.square().mean() + out.controls.square().mean()).backward()
        return [t.detach().numpy() for t in (out.controls, out.states, p.grad, u.grad)]

    plain = run(GameLayer(game8))
    full = GameLayer(game8, compiled=True, vjp="monolithic")
    assert full.interpreted == []
    sizes = {n: layer_functions(game8, n).n_instructions() for n in ("lm_step_vjp", "rollout_vjp")}
    monkeypatch.setattr(
        L, "MAX_COMPILED_INSTRUCTIONS", (sizes["rollout_vjp"] + sizes["lm_step_vjp"]) // 2
    )
    assert sizes["rollout_vjp"] < sizes["lm_step_vjp"]
    part = GameLayer(game8, compiled=True, vjp="monolithic")
    assert part.interpreted == ["lm_step_vjp"]
    monkeypatch.setattr(L, "MAX_COMPILED_INSTRUCTIONS", 0)
    none = GameLayer(game8, compiled=True, vjp="monolithic")
    assert none.interpreted == ["lm_step_vjp", "rollout_vjp"]
    for a, b in zip(run(none), plain, strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(run(part), run(full), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------------------
# Stage-wise VJP of the unrolled steps (solvers/fast_vjp.py)
# --------------------------------------------------------------------------------------
def lag_game(K: int = 8) -> PotentialGame:
    """Two unicycles with jerk (rows coupling u_k and u_{k+1}), colliding head-on."""
    spec = head_on_spec(K=K)
    agents = [
        AgentSpec(
            a.name,
            "unicycle",
            [*a.features, Jerk(weight=0.2)],
            radius=a.radius,
            x0=a.x0,
            goal=a.goal,
        )
        for a in spec.agents
    ]
    return PotentialGame(GameSpec(agents, spec.pair_features, horizon=K, dt=spec.dt))


def layer_grads(layer: GameLayer, seed: int = 0):
    """Outputs and gradients w.r.t. (u_init, w_own, w_pair, goal, x0) of a loss on both
    the controls and the states."""
    u0, w_own, w_pair, goal, x0 = inputs(layer, seed)
    p = layer.assemble_params(w_own=w_own, w_pair=w_pair, goal=goal, x0=x0)
    out = layer(p, u0)
    (out.controls.square().sum() + out.states.sin().sum()).backward()
    leaves = (u0, w_own, w_pair, goal, x0)
    return [out.controls.detach(), out.states.detach()] + [t.grad for t in leaves]


@pytest.mark.parametrize(
    "make", [lambda: PotentialGame(head_on_spec(K=8)), lag_game], ids=["head_on", "jerk"]
)
def test_staged_vjp_layer_gradients_equal_monolithic(make):
    """The layer's torch gradients with the stage-wise VJP equal those of the monolithic
    one to rounding (S = 3 steps, collisions active, several backends)."""
    game = make()
    opts = LMOptions.paper(steps=3)
    for backend in ("structured", "fused"):
        o = LMOptions.paper(steps=3, backend=backend)
        mono = GameLayer(game, o, vjp="monolithic")
        staged = GameLayer(game, o, vjp="staged")
        assert (mono.vjp, staged.vjp) == ("monolithic", "staged")
        u0 = inputs(mono)[0].detach().numpy()
        P0 = np.tile(game.params.defaults(), (2, 1))
        assert collision_energy(game, u0, P0).max() > 0
        a, b = layer_grads(staged), layer_grads(mono)
        for x, y in zip(a, b, strict=True):
            torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12 * float(y.abs().max()))
    assert GameLayer(game, opts).vjp == "monolithic"  # interpreted: the reference


def test_compiled_layer_uses_the_staged_vjp_for_large_graphs(game8, tmp_path, monkeypatch):
    """``vjp="auto"`` with ``compiled=True``: monolithic for a small graph, staged above
    STAGED_VJP_MIN_INSTRUCTIONS; the compiled staged layer equals the interpreted
    monolithic one to rounding."""
    pytest.importorskip("solvers.codegen").find_compiler()
    import learning.layer_core as L

    opts = LMOptions.paper(steps=2, backend="fused", compiled=True)
    assert GameLayer(game8, opts, compiled=True, cache_dir=tmp_path).vjp == "monolithic"
    monkeypatch.setattr(L, "STAGED_VJP_MIN_INSTRUCTIONS", 0)
    layer = GameLayer(game8, opts, compiled=True, cache_dir=tmp_path)
    assert layer.vjp == "staged" and layer.interpreted == []
    ref = GameLayer(game8, opts, vjp="monolithic")
    for x, y in zip(layer_grads(layer), layer_grads(ref), strict=True):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12 * float(y.abs().max()))


def test_vjp_option_errors(game8):
    with pytest.raises(SpecError, match="vjp"):
        GameLayer(game8, vjp="fast")
    from .test_extending import _coupled_game

    coupled = _coupled_game()[0]
    with pytest.raises(SpecError, match="coupled"):
        GameLayer(coupled, vjp="staged")
    assert GameLayer(coupled, vjp="auto", compiled=False).vjp == "monolithic"
    assert GameLayer(game8, backward="implicit").vjp is None
