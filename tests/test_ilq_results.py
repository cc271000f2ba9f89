"""What solve_ilq reports, checked against independent computations: the gradient norm of
the potential at its solution, and a batch of problems that need different iteration
counts stacked as the documented per-problem results."""

from __future__ import annotations

import numpy as np

from solvers.ilq import solve_ilq

from .helpers import crossing_game


def test_grad_norm_is_the_potential_gradient_at_the_solution():
    g = crossing_game(N=2, K=10, offset=0.3)
    p = g.default_params()
    res = solve_ilq(g, p)
    ref = np.abs(np.asarray(g.function("gradient")(res.controls, p))).max()
    assert np.isfinite(res.grad_norm) and res.grad_norm == ref


def test_batch_of_different_lengths_equals_one_by_one():
    g = crossing_game(N=2, K=20, offset=0.5)
    P = np.stack([g.default_params(), g.default_params(goal__a0=[-2.0, 1.5])])
    U0 = np.stack([np.zeros(g.n_u), 0.3 * np.random.default_rng(0).normal(size=g.n_u)])
    batch = solve_ilq(g, P, U0)
    ones = [solve_ilq(g, P[b], U0[b]) for b in range(2)]
    lengths = [r.energy_history.shape[0] for r in ones]
    assert (
        all(r.status.ok for r in ones) and lengths[0] != lengths[1]
    )  # the regime: one history is padded
    assert batch.energy_history.shape == (max(lengths), 2)
    for b, one in enumerate(ones):
        assert batch.status[b] is one.status and batch.iterations[b] == one.iterations
        np.testing.assert_array_equal(batch.controls[b], one.controls)
        h = batch.energy_history[:, b]
        np.testing.assert_array_equal(h[: lengths[b]], one.energy_history)
        assert np.all(h[lengths[b] :] == one.energy_history[-1])  # padded with the last value
