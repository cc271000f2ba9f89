"""Stage-wise vector-Jacobian product of one unrolled LM step (the game layer's backward pass).

Shapes and index order follow the contract in :mod:`epo_casadi.game`. The game layer
(:mod:`learning.layer`, backward mode ``"unrolled"``) needs, per problem and LM step, the
gradient w.r.t. ``(u, p)`` of::

    phi(u, p) = a' J(u, p) z + b' (J(u, p) du + r(u, p)),   a = J du + r,  b = J z  (held fixed)

``learning.layer_core.layer_functions(game, "lm_step_vjp")`` builds it as one CasADi graph over
the whole trajectory (the reference). Its size grows with the horizon times the residual
graph (the left-turn game, K = 60 with path terms: 666k instructions, too large to
compile), so :func:`staged_step_vjp` builds the same function from small stage functions:

Forward (tangent rollout)
    In single shooting ``x_{k+1} = f(x_k, u_k)`` (the joint step
    :meth:`~epo_casadi.game.PotentialGame.stage_step`, ``x_0`` from ``p``), and
    ``J v = R_x dx + R_u v`` with ``dx_{k+1} = f_x dx_k + f_u v_k``, ``dx_0 = 0``
    (``R = traj_residual``). One stage function propagates ``s_k = (x_k, tz_k, td_k)``
    (the state and its tangents along ``z`` and ``du``), run as a ``mapaccum`` over the
    ``K`` stages.
Stage terms
    Every residual row is assigned to the last stage it touches; the rows of stage ``h``
    depend on the window of stages ``[a_h, h]`` they touch (``a_h < h`` for rows that couple
    stages: jerk, turn acceleration), so ``phi = sum_h phi_h(w_h, tz_h, td_h, p)`` with
    ``w_h`` the states and controls of the window. One SX function per stage returns the
    gradient of ``phi_h`` w.r.t. the window's ``(x, u)``, the window's tangent states and
    ``p`` (``a_h``, ``b_h`` substituted after differentiation, as in the reference). Stages
    whose functions serialize identically form one group (first, middle, terminal, and
    one per pattern of sparse terms such as collision every 5th step), mapped over its
    stages; the window gradients are scatter-added by one constant sparse matrix.
Adjoint sweep
    ``lam_K = sbar_K``; ``lam_k = sbar_k + Phi_s' lam_{k+1}``, ``gu_k += Phi_u' lam_{k+1}``
    with ``Phi`` the augmented step above (one stage function, a ``mapaccum`` over the
    stages in reverse); ``x_0``'s part of ``lam_0`` goes to its entries of ``p``.

The result ``lm_step_vjp_staged(u, p, du, z) -> (gu, gp)`` has the reference's signature and
equals it to rounding (tested to 1e-12 relative). It is an MX graph of a few mapped SX
functions. As generated C (:func:`solvers.codegen.compile_functions`, cached by structure)
its compile time does not grow with the horizon, since each distinct stage function is
compiled once (at ``-O1``; wall time on the loaded 2-core machine: left-turn game 10 s,
where the one graph (666k instructions) got the compiler killed for memory; exiD 29 s), and
where the reference is large it is 2 to 9x faster (``bench/bench_layer.py --part vjp``,
CPU per problem and step: left-turn game 0.25 against 2.24 ms, the reference interpreted,
too large to compile; exiD 0.14 against 0.68 and RPI with N = 4 0.061 against 0.136, the
reference compiled at ``-O0``). A small reference compiles at ``-O1`` and is faster (RPI,
N = 2, K = 40: 0.010 against 0.024 ms: the staged form recomputes the dynamics'
derivatives in the adjoint sweep and moves data between the stage functions);
interpreted, the staged form costs 1.06 to 1.9x the reference. Python runs once
per batch and step (:class:`solvers.batch.BatchFunction`), never per stage.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame

from .structured import check_stage_game

__all__ = ["MAX_VJP_GROUPS", "staged_step_vjp", "staged_vjp_info"]

#: Largest number of distinct stage functions (compile time grows with it); a game with
#: more stage patterns gets no staged VJP (:func:`staged_step_vjp` returns ``None``).
MAX_VJP_GROUPS = 24


def staged_step_vjp(game: PotentialGame) -> ca.Function | None:
    """``lm_step_vjp_staged(u, p, du, z) -> (gu, gp)`` (see the module docstring), built
    once per game (:meth:`PotentialGame.cached`), or ``None`` when the game has no stage
    structure the construction can use (coupled dynamics, a residual row that depends on
    a stage outside its window, more than :data:`MAX_VJP_GROUPS` stage patterns); the
    reason is in :func:`staged_vjp_info`."""
    return game.cached(("layer", "lm_step_vjp_staged"), lambda: _build(game))[0]


def staged_vjp_info(game: PotentialGame) -> dict:
    """``{"groups": distinct stage functions, "instructions": SX instructions summed over
    the stages, "distinct_instructions": those of the distinct stage functions (what a
    compiler sees), "reason": why there is no staged VJP (or None)}``."""
    return game.cached(("layer", "lm_step_vjp_staged"), lambda: _build(game))[1]


def _indices(game: PotentialGame):
    """Game index of joint state ``(k, j)`` (``(K+1, n)``) and control ``(k, j)`` (``(K, m)``)."""
    K = game.K
    xg = np.zeros((K + 1, int(sum(game.nx))), dtype=int)
    ug = np.zeros((K, int(sum(game.nu))), dtype=int)
    xc = np.concatenate([[0], np.cumsum(game.nx)]).astype(int)
    uc = np.concatenate([[0], np.cumsum(game.nu)]).astype(int)
    for i in range(game.N):
        nx, nu = int(game.nx[i]), int(game.nu[i])
        xg[:, xc[i] : xc[i + 1]] = (
            int(game.xoff[i]) + np.arange(K + 1)[:, None] * nx + np.arange(nx)[None, :]
        )
        ug[:, uc[i] : uc[i + 1]] = (
            int(game.uoff[i]) + np.arange(K)[:, None] * nu + np.arange(nu)[None, :]
        )
    return xg, ug


def _refused(reason: str):
    return None, {"groups": 0, "instructions": 0, "distinct_instructions": 0, "reason": reason}


def _build(game: PotentialGame):
    try:
        check_stage_game(game)
    except SpecError as e:
        return _refused(str(e))
    K, n_x, n_u, n_p = game.K, game.n_x, game.n_u, game.n_p
    n, m = int(sum(game.nx)), int(sum(game.nu))
    nzv = n_x + n_u
    xg, ug = _indices(game)
    # stage of every entry of v = [x; u] (game order)
    vst = np.empty(nzv, dtype=int)
    vst[xg.reshape(-1)] = np.repeat(np.arange(K + 1), n)
    vst[n_x + ug.reshape(-1)] = np.repeat(np.arange(K), m)
    isx = np.arange(nzv) < n_x
    # residual rows per stage, and the window of stages each stage's rows touch
    x = ca.SX.sym("x", n_x)
    u = ca.SX.sym("u", n_u)
    p = ca.SX.sym("p", n_p)
    v = ca.vertcat(x, u)
    r = game.function("traj_residual")(x, u, p)
    rows, cols = (np.asarray(a, dtype=int) for a in ca.jacobian_sparsity(r, v).get_triplet())
    hi = np.zeros(game.n_r, dtype=int)  # rows touching nothing go to stage 0
    np.maximum.at(hi, rows, vst[cols])
    lo = hi.copy()
    np.minimum.at(lo, rows, vst[cols])
    groups: dict = {}
    for h in range(K + 1):
        rk = np.flatnonzero(hi == h)
        if rk.size == 0:
            continue
        a = int(lo[rk].min())
        win = np.flatnonzero((vst >= a) & (vst <= h))
        win = win[np.lexsort((win, vst[win]))]
        w_s, p_s = ca.SX.sym("w", win.size), ca.SX.sym("p", n_p)
        try:
            f = ca.Function("s", [v[win.tolist()], p], [r[rk.tolist()]])
        except RuntimeError:  # depends on an entry outside its window (not by derivative)
            return _refused(f"the rows of stage {h} depend on entries outside their window")
        e_s = ca.cse(f.call([w_s, p_s])[0])
        key = (ca.Function("s", [w_s, p_s], [e_s]).serialize(), isx[win].tobytes())
        grp = groups.get(key)
        if grp is None:
            if len(groups) >= MAX_VJP_GROUPS:
                return _refused(f"more than {MAX_VJP_GROUPS} distinct stage functions")
            grp = groups[key] = {"w": w_s, "p": p_s, "r": e_s, "xmask": isx[win], "wins": []}
        grp["wins"].append(win)
    # MX graph: tangent rollout, mapped stage groups, scatter-add, adjoint sweep. Data
    # stay in the stage-major layout of the sweeps, S = [x_k; tz_k; td_k] per column, and
    # every window is gathered from there (one gather per group and input), every
    # gradient scattered back into it (one constant sparse matrix), so that little but
    # the stage functions' arithmetic is left
    U, P = ca.MX.sym("u", n_u), ca.MX.sym("p", n_p)
    DU, Z = ca.MX.sym("du", n_u), ca.MX.sym("z", n_u)
    f_fwd, f_adj = _dynamics_functions(game, n, m)
    x0_game = np.concatenate(
        [
            game.params[f"x0.{a.name}"].start + np.arange(game.params[f"x0.{a.name}"].size)
            for a in game.agents
        ]
    )
    UZD = ca.vertcat(U, Z, DU)
    # [u_k; z_k; du_k] per column (3m, K)
    vcol = np.concatenate([ug, n_u + ug, 2 * n_u + ug], axis=1).reshape(-1)
    Vj = ca.reshape(UZD[vcol.tolist()], 3 * m, K)
    s0 = ca.vertcat(P[x0_game.tolist()], ca.MX.zeros(2 * n, 1))
    S = ca.horzcat(s0, f_fwd.mapaccum("vjp_tangent_rollout", K)(s0, Vj))  # (3n, K + 1)
    nS = 3 * n * (K + 1)
    Src = ca.vertcat(ca.vec(S), UZD)
    posx = np.empty(n_x, dtype=int)  # game x index -> its position in vec(S)
    posx[xg.reshape(-1)] = (np.arange(K + 1)[:, None] * 3 * n + np.arange(n)[None, :]).reshape(-1)

    def src(e, t):
        """Position in Src of window entries ``e`` (v index) for input t (0: value, 1: tangent
        along z, 2: along du)."""
        xe = e < n_x
        out = np.empty_like(e)
        out[xe] = posx[e[xe]] + t * n
        out[~xe] = nS + t * n_u + (e[~xe] - n_x)
        return out

    n_acc = nS + n_u + n_p  # [vec(Sbar); ubar (game order); pbar]
    blocks, dests = [], []
    n_instr = n_distinct = 0
    for gi, grp in enumerate(groups.values()):
        f = _stage_vjp_function(grp, n_p, f"vjp_stage{gi}")
        wins = np.stack(grp["wins"])
        mg, nw = wins.shape
        n_instr += f.n_instructions() * mg
        n_distinct += f.n_instructions()
        args = [
            ca.reshape(Src[src(wins.T, t).reshape(-1, order="F").tolist()], nw, mg)
            for t in range(3)
        ]
        G = f.map(f"vjp_stage{gi}_map", "serial", mg, [3], [])(*args, P)
        blocks.append(ca.vec(G))
        # destination of every entry of G (column-major: members one after the other)
        xw = wins[:, grp["xmask"]]
        wdest = np.where(wins < n_x, posx[np.minimum(wins, n_x - 1)], nS + wins - n_x)
        dest = np.concatenate(
            [
                wdest,
                posx[xw] + n,
                posx[xw] + 2 * n,
                np.broadcast_to(nS + n_u + np.arange(n_p), (mg, n_p)),
            ],
            axis=1,
        )
        assert dest.shape[1] == int(G.shape[0])
        dests.append(dest.reshape(-1))
    dest = np.concatenate(dests)
    T = ca.DM.triplet(dest.tolist(), list(range(dest.size)), [1.0] * dest.size, n_acc, dest.size)
    acc = ca.densify(ca.mtimes(T, ca.vertcat(*blocks)))
    Sbar = ca.reshape(acc[:nS], 3 * n, K + 1)
    # adjoint sweep over k = K-1, ..., 0 (a mapaccum over the stages in reverse)
    rev = list(range(K - 1, -1, -1))
    lam, gu_rev = f_adj.mapaccum("vjp_adjoint_sweep", K)(
        Sbar[:, K], S[:, rev], Vj[:, rev], Sbar[:, rev]
    )
    # column c of gu_rev is stage K-1-c: game index ug[k, j] sits at (K-1-k) m + j
    gpos = np.empty(n_u, dtype=int)
    gpos[ug.reshape(-1)] = ((K - 1 - np.arange(K))[:, None] * m + np.arange(m)[None, :]).reshape(-1)
    gu = acc[nS : nS + n_u] + ca.vec(gu_rev)[gpos.tolist()]
    sel = ca.DM.triplet(x0_game.tolist(), list(range(n)), [1.0] * n, n_p, n)
    gp = acc[nS + n_u :] + ca.mtimes(sel, lam[:n, K - 1])
    fn = ca.Function(
        "lm_step_vjp_staged", [U, P, DU, Z], [gu, gp], ["u", "p", "du", "z"], ["gu", "gp"]
    )
    info = {
        "groups": len(groups),
        "instructions": n_instr,
        "distinct_instructions": n_distinct,
        "reason": None,
    }
    return fn, info


def _dynamics_functions(game: PotentialGame, n: int, m: int):
    """The augmented step ``s_{k+1} = Phi(s_k, v_k)`` (``s = (x, tz, td)``, ``v = (u, z, du)``)
    and its adjoint ``(lam_{k+1}, s_k, v_k, sbar_k) -> (sbar_k + Phi_s' lam, Phi_u' lam)``."""
    xs, tz, td = ca.SX.sym("x", n), ca.SX.sym("tz", n), ca.SX.sym("td", n)
    us, zs, ds = ca.SX.sym("u", m), ca.SX.sym("z", m), ca.SX.sym("du", m)
    f = game.stage_step(xs, us)
    xu = ca.vertcat(xs, us)
    phi = ca.vertcat(f, ca.jtimes(f, xu, ca.vertcat(tz, zs)), ca.jtimes(f, xu, ca.vertcat(td, ds)))
    s, vv = ca.vertcat(xs, tz, td), ca.vertcat(us, zs, ds)
    f_fwd = ca.Function("vjp_tangent_step", [s, vv], [ca.densify(phi)])
    lam, sb = ca.SX.sym("lam", 3 * n), ca.SX.sym("sbar", 3 * n)
    g = ca.gradient(ca.dot(lam, phi), ca.vertcat(s, us))
    f_adj = ca.Function(
        "vjp_adjoint_step",
        [lam, s, vv, sb],
        [ca.densify(sb + g[: 3 * n]), ca.densify(g[3 * n :])],
    )
    return f_fwd, f_adj


def _stage_vjp_function(grp: dict, n_p: int, name: str) -> ca.Function:
    """``(w, vz, vd, p) -> [d phi_h/dw; d phi_h/d tz_w; d phi_h/d td_w; d phi_h/dp]`` for the
    rows ``r_h(w, p)`` of one stage group (``vz``, ``vd``: tangents of the window along
    ``z`` and ``du``; their control entries are ``z`` and ``du`` themselves)."""
    w, p, r = grp["w"], grp["p"], grp["r"]
    nw = int(w.shape[0])
    xm = grp["xmask"]
    vz, vd = ca.SX.sym("vz", nw), ca.SX.sym("vd", nw)
    a = ca.SX.sym("a", r.shape[0])
    b = ca.SX.sym("b", r.shape[0])
    Jz = ca.jtimes(r, w, vz)
    Jdu = ca.jtimes(r, w, vd)
    phi = ca.dot(a, Jz) + ca.dot(b, Jdu + r)
    xi = np.flatnonzero(xm).tolist()
    g = ca.gradient(phi, ca.vertcat(w, vz[xi], vd[xi], p))
    g = ca.substitute(g, ca.vertcat(a, b), ca.vertcat(Jdu + r, Jz))
    return ca.Function(name, [w, vz, vd, p], [ca.cse(ca.densify(g))])
