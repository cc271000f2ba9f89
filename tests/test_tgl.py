"""TGL: the batched QP against qpOASES, hard constraints, IFT gradients vs finite differences,
the linearized dynamics against the Euler rollout, the model and ``epo train --model tgl``."""

from __future__ import annotations

import json

import casadi as ca
import numpy as np
import pytest
import torch

from learning.data import SceneDataset
from learning.models import ModelConfig, build_model
from learning.tgl import QPStatus, TGLProblem, linear_dynamics, qp_layer, solve_qp
from learning.train import load_model
from tests.test_models import TINY, synthetic_dataset

#: two agents head-on, 1 m apart sideways: the collision half-spaces and the control
#: boxes (far goal, narrow boxes) are active at the solution
PROBLEM = TGLProblem(
    N=2,
    K=6,
    dt=0.2,
    accel=(-1.0, 1.0),
    turn=(-0.5, 0.5),
    speed=((0.0, 2.0), (0.0, 2.0)),
    radii=(0.5, 0.5),
    pairs=((0, 1),),
    steps=(2, 4, 6),
    margin=0.0,
)


def _inputs(B: int = 1):
    f = torch.float64
    x0 = torch.tensor([[-2.0, 0.05, 1.5, 0.0], [2.0, -0.05, 1.5, np.pi]], dtype=f)
    x0 = x0.expand(B, 2, 4).clone()
    x0[:, 0, 1] += 0.1 * torch.arange(B, dtype=f)  # other problems: other lateral offsets
    w_own = torch.tensor([[2.0, 0.5, 0.3, 0.2, 0.01], [1.0, 0.4, 0.2, 0.3, 0.02]], dtype=f)
    w_pair = torch.tensor([5.0], dtype=f)
    goals = torch.tensor([[6.0, 1.0], [-6.0, -0.5]], dtype=f)
    vref = torch.tensor([2.5, 1.0], dtype=f)
    rep = lambda t: t.expand(B, *t.shape).clone()  # noqa: E731
    return x0, rep(w_own), rep(w_pair), rep(goals), rep(vref)


def _solve(B: int = 1):
    x0, *rest = _inputs(B)
    qp = PROBLEM.build(x0, *rest)
    z, status = qp_layer(qp["P"], qp["q"], qp["A"], qp["lo"], qp["hi"])
    return qp, z, status


def _qpoases(P, q, A, lo, hi) -> np.ndarray:
    """Independent reference: casadi's qpOASES (an active-set QP solver) on the same QP."""
    x = ca.SX.sym("x", len(q))
    f = 0.5 * ca.mtimes([x.T, ca.DM(P), x]) + ca.dot(ca.DM(q), x)
    s = ca.qpsol("s", "qpoases", {"x": x, "f": f, "g": ca.mtimes(ca.DM(A), x)},
                 {"printLevel": "none", "print_time": False})  # fmt: skip
    lbg = np.where(lo > -1e19, lo, -np.inf)
    ubg = np.where(hi < 1e19, hi, np.inf)
    res = s(lbg=lbg, ubg=ubg)
    assert s.stats()["success"]
    return np.asarray(res["x"]).ravel()


def test_qp_matches_an_independent_solver_with_active_hard_constraints():
    qp, z, status = _solve(B=3)
    assert status.tolist() == [QPStatus.SOLVED] * 3
    nu = PROBLEM.n_controls
    for b in range(3):
        P, q, A, lo, hi = (qp[k][b].numpy() for k in ("P", "q", "A", "lo", "hi"))
        ref = _qpoases(P, q, A, lo, hi)
        np.testing.assert_allclose(z[b].numpy(), ref, atol=1e-9)
        Az = A @ z[b].numpy()
        # hard constraints hold (to rounding)
        assert np.all(Az >= lo - 1e-10) and np.all(Az <= hi + 1e-10)
        # the regime: a control box and a collision half-space are active
        act = (np.abs(Az - lo) < 1e-9) | (np.abs(Az - hi) < 1e-9)
        assert act[:nu].any(), "no active control bound"
        C = PROBLEM.n_slack
        col = slice(A.shape[0] - 2 * C, A.shape[0] - C)
        assert act[col].any(), "no active collision half-space"
    u = z[:, :nu].reshape(3, 2, PROBLEM.K, 2)
    assert float(u[..., 0].abs().max()) <= 1.0 + 1e-10  # acceleration box
    assert float(u[..., 1].abs().max()) <= 0.5 + 1e-10  # turn-rate box


def test_a_rough_osqp_start_still_ends_certified_at_the_optimum():
    """OSQP stopped after 5 iterations: the active-set iteration and OSQP's tight re-solve of
    the problems it cannot certify end at the exact solution; without the re-solve the
    rough start is not certified (the regime this test claims)."""
    x0, *rest = _inputs(3)
    qp = PROBLEM.build(x0, *rest)
    args = (qp["P"], qp["q"], qp["A"], qp["lo"], qp["hi"])
    exact = solve_qp(*args)
    assert exact["status"].tolist() == [QPStatus.SOLVED] * 3
    rough = solve_qp(*args, eps=1e-1, max_iter=5)
    assert rough["status"].tolist() == [QPStatus.SOLVED] * 3
    torch.testing.assert_close(rough["z"], exact["z"], rtol=0, atol=1e-10)
    alone = solve_qp(*args, eps=1e-1, max_iter=5, active_set_steps=1, fallback=False)
    assert alone["status"].tolist() != [QPStatus.SOLVED] * 3


def test_gradient_matches_finite_differences_with_active_constraints():
    x0, *args = _inputs(1)
    args = [a.requires_grad_() for a in args]

    proj = torch.tensor(np.random.default_rng(1).normal(size=(3, 2 * PROBLEM.K * 4)))

    def f(w_own, w_pair, goals, vref):  # three random projections of all states
        qp = PROBLEM.build(x0, w_own, w_pair, goals, vref)
        z, _ = qp_layer(qp["P"], qp["q"], qp["A"], qp["lo"], qp["hi"])
        return proj @ PROBLEM.trajectory(x0, z, qp["lin"])["states"].reshape(-1)

    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradient_of_the_bounds_is_the_multiplier():
    """dL/dhi of an active bound equals the finite difference of the solution value."""
    qp, z, _ = _solve(1)
    hi = qp["hi"].clone().requires_grad_()
    z2, _ = qp_layer(qp["P"], qp["q"], qp["A"], qp["lo"], hi)
    (z2 * torch.linspace(0, 1, z2.shape[1], dtype=z2.dtype)).sum().backward()
    g = hi.grad[0]
    Az = qp["A"][0] @ z[0]
    j = int(torch.nonzero((Az - qp["hi"][0]).abs() < 1e-9)[0])  # an active upper bound
    h = 1e-6
    val = []
    for s in (h, -h):
        hh = qp["hi"].clone()
        hh[0, j] += s
        zz, _ = qp_layer(qp["P"], qp["q"], qp["A"], qp["lo"], hh)
        val.append(float((zz * torch.linspace(0, 1, zz.shape[1], dtype=zz.dtype)).sum()))
    assert abs(g[j].item() - (val[0] - val[1]) / (2 * h)) < 1e-6
    assert g[j].item() != 0.0


def test_linear_dynamics_is_the_first_order_euler_rollout():
    rng = np.random.default_rng(0)
    x0 = torch.tensor(rng.normal(size=(1, 3, 4)))
    x0[..., 2] = x0[..., 2].abs() + 0.5
    K, dt = 7, 0.1
    lin = linear_dynamics(x0, K, dt)

    def euler(U):  # the game's explicit Euler unicycle, U (3, K, 2)
        x, out = x0[0].numpy().copy(), []
        for k in range(K):
            x = x + dt * np.stack(
                [x[:, 2] * np.cos(x[:, 3]), x[:, 2] * np.sin(x[:, 3]), U[:, k, 0], U[:, k, 1]], 1
            )
            out.append(x.copy())
        return np.stack(out, 1)  # (3, K, 4)

    dU = rng.normal(size=(3, K, 2))
    for eps in (1e-3, 1e-4):
        lin_pos = lin["pos_c"][0].numpy() + np.einsum("nkdc,nc->nkd", lin["J_pos"][0].numpy(),
                                                      (eps * dU).reshape(3, 2 * K))  # fmt: skip
        err = np.abs(euler(eps * dU)[..., :2] - lin_pos).max()
        assert err < 50 * eps**2  # second order: exact to first order
    np.testing.assert_allclose(euler(0 * dU)[..., :2], lin["pos_c"][0].numpy(), atol=1e-12)


def test_tgl_problem_reads_the_game():
    with SceneDataset(synthetic_dataset(), "train") as ds:
        game = ds.game
    pr = TGLProblem.from_game(game)
    assert (pr.N, pr.K) == (game.N, game.K)
    assert pr.accel == (-2.0, 2.0) and pr.turn == (-1.5, 1.5)  # the RPI bound features
    assert pr.pairs == ((0, 1),) and pr.steps == tuple(range(1, game.K + 1))
    assert pr.margin == pytest.approx(0.15)


def test_tgl_model_forward_backward_and_train_cli(tmp_path):
    data = synthetic_dataset()
    with SceneDataset(data, "train") as ds:
        batch, game = ds.batch(np.arange(4)), ds.game
    torch.manual_seed(0)
    model = build_model(ModelConfig(kind="tgl", **TINY), game)
    out = model(batch)
    B, M, N, K = 4, 2, game.N, game.K
    assert out["pos"].shape == (B, M, N, K, 2) and out["logits"].shape == (B, M)
    assert out["weights"].shape == (B, M, N, 5) and bool((out["weights"] >= 0).all())
    assert out["status"].tolist() == [QPStatus.SOLVED] * (B * M)
    out["pos"].sum().backward()
    g = [p.grad for p in model.encoder.parameters() if p.grad is not None]
    assert g and all(torch.isfinite(t).all() for t in g) and any(t.abs().sum() > 0 for t in g)

    from scenarios.cli import main

    run = tmp_path / "run"
    args = ["train", "--model", "tgl", "--data", str(data), "--out", str(run), "--epochs", "1"]
    assert main([*args, "--batch-size", "4", "--no-progress", "--set", "backbone=hivt"]) == 0
    cfg = json.loads((run / "config.json").read_text())["train"]["model"]
    assert (cfg["kind"], cfg["backbone"]) == ("tgl", "hivt")
    loaded, tcfg, _ = load_model(run, game)
    assert (tcfg.model.kind, tcfg.model.backbone) == ("tgl", "hivt")
    with torch.no_grad():
        a, b = loaded(batch)["pos"], loaded(batch)["pos"]
    assert torch.equal(a, b) and torch.isfinite(a).all()
