"""The closed-loop rollout of one iteration (:mod:`solvers.ilq`, step 3).

:func:`build_rollout` builds, once per solver, the CasADi function ``ilq_rollout``
``(x0, Xr, Ur, PA, eps) -> (X, U)``: the nonlinear dynamics stepped with the feedback
policy ``U_k = Ur_k - P_k (X_k - Xr_k) - Q_k (Y_k - Yr_k) - eps a_k`` (``PA`` holds
``[P_k | Q_k | a_k]`` of every stage, row-major). ``s`` is the
:class:`solvers.ilq.ILQSolver` being built (after :func:`solvers.ilq.quadratize.
build_quadratize`, which sets the carried variables ``aug``).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..codegen import BufferCall as _Call

__all__ = ["build_rollout"]


def build_rollout(s) -> None:
    """Set ``s.roll`` (the interpreted ``ilq_rollout``) and ``s._x0_idx`` (the initial states
    in ``p``)."""
    K, nx, nu, nxs = s.K, s.nx, s.nu, s.nxs
    x0 = ca.SX.sym("x0", nx)
    Xr = ca.SX.sym("Xr", nx, K + 1)
    Ur = ca.SX.sym("Ur", nu, K)
    PA = ca.SX.sym("PA", (nxs + 1) * nu, K)
    eps = ca.SX.sym("eps")
    x = x0
    X, U = [x0], []
    dy = ca.SX.zeros(s.na)  # deviation of the carried variables Y_k (none at k = 0)
    aug = s.aug.tolist()
    for k in range(K):
        pa = ca.reshape(PA[:, k], nxs + 1, nu).T  # row-major (nu, nxs+1) block of stage k
        dx = ca.vertcat(x - Xr[:, k], dy)
        u = Ur[:, k] - ca.mtimes(pa[:, :nxs], dx) - eps * pa[:, nxs]
        if s.na:
            dy = ca.vertcat(u - Ur[:, k], x - Xr[:, k])[aug]
        x = s._joint_step(x, u)
        X.append(x)
        U.append(u)
    s.roll = _Call(
        ca.Function(
            "ilq_rollout",
            [x0, Xr, Ur, PA, eps],
            [ca.horzcat(*X), ca.horzcat(*U)],
            ["x0", "Xr", "Ur", "PA", "eps"],
            ["X", "U"],
        )
    )
    blocks = [s.game.params[f"x0.{a}"] for a in s.game.agent_names]
    s._x0_idx = np.concatenate([np.arange(b.start, b.start + b.size) for b in blocks]).astype(
        np.intp
    )
