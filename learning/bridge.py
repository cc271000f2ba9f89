"""Torch bridge to a game's own CasADi rollout: one set of dynamics for the whole toolkit.

:class:`GameRollout` evaluates the game's ``rollout`` function ``x(u, p)`` (the problem
contract in :mod:`epo_casadi.game`: ``u`` ``(..., n_u)``, ``p`` ``(..., n_p)`` ->
``x`` ``(..., n_x)``, the ``k = 0`` block being the initial state) as a torch op. The
forward pass is one mapped CasADi call over the flattened batch (no Python loop per
problem or time step); the backward pass is the vector-Jacobian product of the same graph
(:func:`learning.layer_core.layer_functions` ``"rollout_vjp"``, one reverse sweep), so the
gradient is exact for any dynamics, built-in or a user's (``docs/extending.md``). It
computes in float64 and returns the promoted input dtype, on the input's device (CPU
inside). Double backward is not supported.

:meth:`GameRollout.states` is the form the networks use: initial states ``(..., N, nx)``
and per-agent controls ``(..., N, K, nu)`` -> states ``(..., N, K+1, nx)``.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import torch
from torch.autograd.function import once_differentiable

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame
from solvers.batch import BatchFunction

from .layer_core import layer_functions

__all__ = ["GameRollout"]


def _dense_rollout(game: PotentialGame) -> ca.Function:
    """``rollout(u, p) -> x`` with a dense output (a model may leave states structurally 0)."""
    sym = game.symbols
    return ca.Function(
        "rollout_dense", [sym["u"], sym["p"]], [ca.densify(sym["x"])], ["u", "p"], ["x"]
    )


class _Core:
    def __init__(self, game: PotentialGame, threads: int | None):
        self.game = game
        self.forward = BatchFunction(
            game.cached(("bridge", "rollout_dense"), lambda: _dense_rollout(game)), threads
        )
        self.vjp = BatchFunction(layer_functions(game, "rollout_vjp"), threads)


def _to_numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to(device="cpu", dtype=torch.float64).contiguous().numpy()


class _RolloutFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, core: _Core, p: torch.Tensor, u: torch.Tensor):
        dtype = torch.promote_types(p.dtype, u.dtype)
        P, U = _to_numpy(p), _to_numpy(u)
        ctx.core, ctx.P, ctx.U = core, P, U
        ctx.meta = (p.dtype, p.device, u.dtype, u.device)
        if P.shape[0] == 0:
            return torch.zeros(0, core.game.n_x, dtype=dtype, device=p.device)
        X = core.forward(U, P)[0]
        return torch.from_numpy(X).to(device=p.device, dtype=dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_x):
        core, P, U = ctx.core, ctx.P, ctx.U
        p_dtype, p_device, u_dtype, u_device = ctx.meta
        if P.shape[0] == 0:
            gu, gp = np.zeros_like(U), np.zeros_like(P)
        else:
            gu, gp = core.vjp(U, P, _to_numpy(g_x))
        out_p = torch.from_numpy(gp).to(device=p_device, dtype=p_dtype)
        out_u = torch.from_numpy(gu).to(device=u_device, dtype=u_dtype)
        return (
            None,
            out_p if ctx.needs_input_grad[1] else None,
            out_u if ctx.needs_input_grad[2] else None,
        )


class GameRollout:
    """The rollout ``x(u, p)`` of ``game`` as a differentiable torch op.

    ``rollout(p, u)``: ``p`` ``(..., n_p)``, ``u`` ``(..., n_u)`` (leading dimensions
    broadcast) -> ``x`` ``(..., n_x)``. Only the ``x0`` blocks of ``p`` (and any block a
    user's dynamics reads) matter. ``threads``: as :class:`solvers.batch.BatchFunction`.
    """

    def __init__(self, game: PotentialGame, threads: int | None = None):
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        self.game = game
        self.core = game.cached(("bridge", "core", threads), lambda: _Core(game, threads))
        # entries of p that are initial states: agent order, nx_i each (the contract)
        self.x0_index = torch.as_tensor(game.params.group("x0"), dtype=torch.long)

    def __call__(self, p: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        g = self.game
        for name, t, n in (("p", p, g.n_p), ("u", u, g.n_u)):
            if not isinstance(t, torch.Tensor) or not t.is_floating_point():
                raise SpecError(name, f"expected a floating-point tensor, got {type(t).__name__}")
            if t.shape[-1:] != (n,):
                raise SpecError(name, f"expected last dimension {n}, got {tuple(t.shape)}")
        lead = torch.broadcast_shapes(p.shape[:-1], u.shape[:-1])
        P = p.expand(*lead, g.n_p).reshape(-1, g.n_p)
        U = u.expand(*lead, g.n_u).reshape(-1, g.n_u)
        x = _RolloutFunction.apply(self.core, P, U)
        return x.reshape(*lead, g.n_x)

    def states(
        self, x0: torch.Tensor, controls: torch.Tensor, p: torch.Tensor | None = None
    ) -> torch.Tensor:
        """States ``(..., N, K+1, nx)`` from initial states ``x0`` ``(..., N, nx)`` and
        controls ``(..., N, K, nu)`` (every agent with the same ``nx`` and ``nu``).

        ``x0`` fills the ``x0`` blocks of ``p`` (default: the game's defaults); the
        result is differentiable w.r.t. ``x0``, ``controls`` and ``p``.
        """
        g = self.game
        if len(set(g.nx)) != 1 or len(set(g.nu)) != 1:
            raise SpecError(
                "game", "states() needs every agent with the same nx and nu; call the rollout"
            )
        N, K, nx, nu = g.N, g.K, g.nx[0], g.nu[0]
        if x0.shape[-2:] != (N, nx):
            raise SpecError("x0", f"expected shape (..., {N}, {nx}), got {tuple(x0.shape)}")
        if controls.shape[-3:] != (N, K, nu):
            raise SpecError(
                "controls", f"expected shape (..., {N}, {K}, {nu}), got {tuple(controls.shape)}"
            )
        dtype = torch.promote_types(x0.dtype, controls.dtype)
        lead = torch.broadcast_shapes(x0.shape[:-2], controls.shape[:-3])
        base = (
            torch.as_tensor(g.params.defaults(), dtype=dtype, device=x0.device)
            if p is None
            else p.to(dtype)
        )
        base = base.expand(*lead, g.n_p)
        idx = self.x0_index.to(x0.device)
        P = base.index_copy(-1, idx, x0.to(dtype).expand(*lead, N, nx).reshape(*lead, N * nx))
        u = controls.to(dtype).expand(*lead, N, K, nu).reshape(*lead, N * K * nu)
        return self(P, u).reshape(*lead, N, K + 1, nx)
