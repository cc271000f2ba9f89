"""The kinks of the residual (``max``/``min``: collision, bounds) and equilibria on them.

The safeguards of :mod:`solvers.ilq` that switch on after the first failed line search:
the kinks' curvature blended over a width (:func:`_smooth_kinks`, :func:`build_kink_quad`;
the kink continuation of :class:`solvers.ilq.iteration.SolveOnce`), the report of a solve
that stops on a kink (:func:`blend_report`), and the search for a feedback equilibrium
*on* the kinks (:func:`kink_equilibrium`: curvatures ``theta_j^2``, ``theta_j in [0, 1]``,
the hinge's generalized Hessian, found by Newton steps on ``theta`` with pinned solves,
then the feedback-Nash check; docs/ilq.md, "Equilibria on a kink"). ``s`` is the
:class:`solvers.ilq.ILQSolver`.
"""

from __future__ import annotations

import dataclasses
import time

import casadi as ca
import numpy as np

from ..codegen import BufferCall as _Call
from ..result import Status
from ..stages import from_stages, to_stages

__all__ = ["blend_report", "build_kink_quad", "kink_equilibrium", "kink_summary"]

_PIN_ITER = 120  # iterations of one pinned solve (kinks at fixed curvature; linear rate)
_KINK_NEWTON = 8  # Newton steps on the kinks' blend fractions theta (z(theta) ~ linear)
_THETA_FD = 1e-3  # step of theta in the finite-difference Jacobian of z(theta)
_PIN_BUDGET = 1500  # pinned iterations of one search for an equilibrium on a kink
_KINK_HALVINGS = 4  # halvings of a Newton step on theta before the search gives up


def build_kink_quad(s, pinned: bool = False):
    """``(quadratize(X, U, p, w), kinks(X, U, p))`` with the kinks' curvature blended over
    ``w`` (:func:`_smooth_kinks`), or ``None``. Same outputs as ``ilq_quadratize``: the
    gradients, costs, energy and dynamics are exact, only the Hessian blocks change (on
    the exact blocks' sparsity). ``pinned``: ``quadratize(X, U, p, w, s)``, kink ``j``
    with ``s_j >= 0`` at Gauss-Newton curvature ``s_j^2`` (equilibria on a kink)."""
    if s.hessian != "gauss_newton":
        return None
    smooth = _smooth_kinks(s.game.function("traj_residual"), pinned=pinned)
    if smooth is None:
        return None
    Xs, Us, p, x_flat, u_flat, z, C, E, grads, player_rows, hess_sel, phi_out = s._blend_sym
    w = ca.SX.sym("w")
    s_in = [ca.SX.sym("s", smooth.size1_in(smooth.n_in() - 1))] if pinned else []
    rb, zk = smooth(x_flat, u_flat, p, w, *s_in)
    outs = []
    for grad, rows_i, (sp, sel) in zip(grads, player_rows, hess_sel, strict=True):
        outs.append(ca.densify(grad))
        if rows_i:
            J = ca.jacobian(rb[rows_i], z)
            H = ca.project(ca.mtimes(J.T, J), sp)
        else:
            H = ca.SX(sp)
        outs.append(H.nz[sel.tolist()] if sel.size else ca.SX(0, 1))
    quad = ca.Function(
        "ilq_quadratize_kinks", [Xs, Us, p, w, *s_in], [C, E, ca.vertcat(*outs), phi_out]
    )
    kinks = ca.Function("ilq_kinks", [Xs, Us, p], [zk])
    return _Call(quad), _Call(kinks)


def blend_report(s, X1, U1, p, w: float, res_w: float, failed_width: float):
    """``info["kink_equilibrium"]`` of a solve that stopped on a kink: the blended solution
    ``(X1, U1)`` (width ``w``, ``max |a| = res_w``), its kink arguments inside the band and
    the message; with ``sel``, the indices of those kinks. The caller adds the policies."""
    (zk,) = s._kink_quad[1](X1, U1, p)
    z = np.array(zk, float).ravel()
    sel = np.flatnonzero(np.abs(z) < 0.5 * w)
    kink_info = {
        "width": w,
        "stationarity": res_w,
        "kinks": [(int(i), float(z[i]), float(z[i] / w + 0.5)) for i in sel],
    }
    at = "the exact kinks" if failed_width == 0 else f"w = {failed_width:g}"
    kink_info["message"] = (
        f"no feedback equilibrium at the exact kinks: max |a| <= tol only with the kinks' "
        f"curvature blended over w = {w:g} ({len(sel)} kink argument(s) inside the band, "
        f"|z| <= {float(np.max(np.abs(z[sel]))):.1e}), and at {at} no step passes the "
        f"line search: the blended solution keeps kink arguments inside the band, so the "
        f"equilibrium likely sits on a kink, where the one-sided curvatures give "
        f"different gains"
    )
    kink_info["failed_width"] = failed_width
    return kink_info, sel


def kink_equilibrium(s, p, U1, sel, theta, opts, backward) -> dict:
    """An equilibrium on the kinks ``sel`` near the blended solution ``U1`` (stages).

    Pinned solves (:attr:`solvers.ilq.ILQSolver.kink_pins`: kink ``j`` of ``sel`` at
    Gauss-Newton curvature ``theta_j^2``, the other kinks exact, to ``tol / 100``) and
    Newton steps on ``theta`` (:func:`_kink_newton`) until every ``|z_j| <= 1e-2
    min(kink_widths)`` (at most ``_PIN_BUDGET`` pinned iterations); then ``max |a|`` with
    those curvatures at the requested regularization and the feedback-Nash check of the
    policy (:mod:`solvers.feedback_nash`). A dict: ``ok`` and the figures, or ``ok = False``
    and a ``reason`` when no such point was found (docs/ilq.md, "Equilibria on a kink")."""
    g = s.game
    if s._pin_quad is None:
        s._pin_quad = build_kink_quad(s, pinned=True)[0]
    zfun = s._kink_quad[1]
    m = int(zfun.f.size1_out(0))
    ztol = 1e-2 * min(opts.kink_widths)
    sub = dataclasses.replace(
        opts, kink_widths=(), restart=False, tol=1e-2 * opts.tol, max_iter=_PIN_ITER
    )
    pinned = _PinnedSolves(s, p, sub, backward, zfun, m)
    sel = np.asarray(sel, int).copy()
    try:
        found = _kink_newton(pinned, sel, theta, from_stages(g, None, U1)[1], ztol)
    except _KinkBudget:
        found = f"the pinned solves used up {_PIN_BUDGET} iterations"
    if not isinstance(found, tuple):
        why = found or (
            "a pinned solve failed, or the Newton steps on theta did not bring the kink "
            f"arguments to |z| <= {ztol:g}"
        )
        return {"ok": False, "iterations": pinned.total, "reason": why}
    r, sel, th, z = found
    return _check_on_kinks(s, p, r, sel, th, z, m, opts, backward, pinned.total)


class _PinnedSolves:
    """``pinned(sel, theta, u) -> (result, z_sel, converged)``: a solve from ``u`` with kink
    ``j`` of ``sel`` at curvature ``theta_j^2`` (options ``sub``); ``total`` counts the
    iterations and :class:`_KinkBudget` is raised once they reach ``_PIN_BUDGET``."""

    def __init__(self, s, p, sub, backward, zfun, m: int):
        self.s, self.p, self.sub, self.backward, self.zfun, self.m = s, p, sub, backward, zfun, m
        self.total = 0

    def __call__(self, sel, th, u):
        s, p, sub = self.s, self.p, self.sub
        if self.total >= _PIN_BUDGET:
            raise _KinkBudget
        pins = np.full(self.m, -1.0)
        pins[sel] = th
        s.kink_pins = pins
        try:
            r = s._solve_once(p, u, sub, self.backward, sub.max_iter, time.perf_counter())
        finally:
            s.kink_pins = None
        self.total += int(r.iterations)
        X, U = to_stages(s.game, r.states, r.controls)
        (zk,) = self.zfun(X, U, p)
        ok = r.status is Status.CONVERGED
        return r, np.asarray(zk, float).ravel()[sel], ok


def _check_on_kinks(s, p, r, sel, th, z, m: int, opts, backward, total: int) -> dict:
    """The result ``r`` of the pinned solve with kinks ``sel`` at curvatures ``th^2``:
    ``max |a|`` with those curvatures at the requested regularization (a fresh pass) and
    the feedback-Nash check of its policy, as :func:`kink_equilibrium` returns them."""
    from ..feedback_nash import feedback_nash_check

    g = s.game
    X, U = to_stages(g, r.states, r.controls)
    s.kink_pins = np.full(m, -1.0)
    s.kink_pins[sel] = th
    try:
        C, E = s.quadratize(X, U, p, opts.compiled)
        PA, mu, fin = backward(float(opts.regularization), float(opts.min_curvature))
    finally:
        s.kink_pins = None
    res = float(np.max(np.abs(PA[:, :, -1]))) if s.K else 0.0
    check = feedback_nash_check(
        g,
        p,
        r.states,
        r.controls,
        PA[:, :, : s.nx],
        PA[:, :, s.nxs],
        gains_prev=PA[:, :, s.nx : s.nxs],
        prev_variables=s.aug,
    )
    return {
        "ok": bool(fin and res <= opts.tol and check.ok),
        "result": r,
        "X": X,
        "U": U,
        "C": C,
        "E": E,
        "PA": PA,
        "mu": mu,
        "stationarity": res,
        "kinks": sel,
        "theta": th,
        "z": z,
        "iterations": total,
        "check": check,
    }


def _smooth_kinks(f: ca.Function, pinned: bool = False) -> ca.Function | None:
    """``f`` (an SX function) with the curvature of its kinks blended over a width ``w``.

    Returns ``(f's inputs, w) -> (r, z)``: ``r`` is ``f`` with every ``fmax(a, b) = a +
    relu(b - a)`` replaced by ``a + g(b - a)`` (``fmin(a, b) = a - relu(a - b)`` likewise),
    ``g' = clip(z / w + 1/2, 0, 1)``: equal to ``relu`` (values and derivatives) outside
    ``|z| < w/2``, a quadratic blend inside, ``relu`` itself at ``w = 0``; ``z`` are the
    kink arguments ``b - a`` (``a - b`` for ``fmin``). ``None`` when ``f`` has no kink, is
    not an SX function or holds operations not replayed here (calls).

    ``pinned``: one more input ``s`` (one entry per kink): kink ``j`` with ``s_j >= 0``
    has the slope ``s_j`` in ``r``'s Jacobian whatever its argument (``r`` itself is then
    not ``f``'s: only the Jacobian is used, for Gauss-Newton curvature ``s_j^2``), the
    others are blended over ``w`` as above (``w = 0``: exact).
    """
    if not f.is_a("SXFunction"):
        return None
    ops = [f.instruction_id(k) for k in range(f.n_instructions())]
    if ca.OP_FMAX not in ops and ca.OP_FMIN not in ops:
        return None
    zs, ws = ca.SX.sym("z"), ca.SX.sym("w")
    h = 0.5 * ws
    inner = (zs + h) ** 2 / (2 * ca.fmax(ws, 1e-300))
    blend = ca.if_else(zs <= -h, 0, ca.if_else(zs >= h, zs, inner))
    # one call per kink (evaluated symbolically in C++ and inlined into the new graph)
    relu = ca.Function("smooth_relu", [zs, ws], [blend])
    ins = [ca.SX.sym(f"i{i}", f.sparsity_in(i)) for i in range(f.n_in())]
    w_in = ca.SX.sym("w")
    out_nz = [[ca.SX(0)] * f.nnz_out(i) for i in range(f.n_out())]
    kinks, pins = [], []
    work: dict = {}
    for k, op in enumerate(ops):
        a, o = f.instruction_input(k), f.instruction_output(k)
        if op == ca.OP_CONST:
            work[o[0]] = ca.SX(f.instruction_constant(k))
        elif op == ca.OP_INPUT:
            work[o[0]] = ins[a[0]].nz[a[1]]
        elif op == ca.OP_OUTPUT:
            out_nz[o[0]][o[1]] = work[a[0]]
        elif op in (ca.OP_FMAX, ca.OP_FMIN):
            x, y = work[a[0]], work[a[1]]
            z = y - x if op == ca.OP_FMAX else x - y
            kinks.append(z)
            g = relu(z, w_in)
            if pinned:
                pins.append(ca.SX.sym(f"s{len(pins)}"))
                g = ca.if_else(pins[-1] >= 0, pins[-1] * z, g)
            work[o[0]] = x + g if op == ca.OP_FMAX else x - g
        elif len(a) == 2 and len(o) == 1:
            work[o[0]] = ca.SX.binary(op, work[a[0]], work[a[1]])
        elif len(a) == 1 and len(o) == 1:
            work[o[0]] = ca.SX.unary(op, work[a[0]])
        else:  # calls or other multi-argument operations
            return None
    outs = [
        ca.SX(f.sparsity_out(i), ca.vertcat(*nz)) if nz else ca.SX(f.sparsity_out(i))
        for i, nz in enumerate(out_nz)
    ]
    if len(outs) != 1:
        return None
    if pinned:
        s_in = ca.vertcat(*pins)
        return ca.Function(f.name() + "_pinned", [*ins, w_in, s_in], [outs[0], ca.vertcat(*kinks)])
    return ca.Function(f.name() + "_kinks", [*ins, w_in], [outs[0], ca.vertcat(*kinks)])


def _kink_newton(pinned, sel, theta, u0, ztol):
    """Newton steps on the blend fractions ``theta`` of the kinks ``sel`` until every kink
    argument ``|z_j| <= ztol``: ``pinned(sel, theta, u) -> (result, z, ok)`` solves with
    those kinks at fixed curvature ``theta^2`` from ``u``. The Jacobian of ``z(theta)`` by
    finite differences, then Broyden updates; steps halved until the pinned solve
    converges and ``max |z|`` drops; a kink whose ``theta`` would leave ``[0, 1]`` is
    released (exact curvature). ``(result, sel, theta, z)`` or ``None``."""
    th = np.asarray(theta, float).copy()
    r, z, ok = pinned(sel, th, u0)
    if not ok:
        return None
    J = None
    for _ in range(_KINK_NEWTON):
        if _max_abs(z) <= ztol:
            break
        if J is None:  # finite differences of z(theta), one pinned solve per kink
            J = np.empty((th.size, th.size))
            for j in range(th.size):
                h = -_THETA_FD if th[j] > 0.5 else _THETA_FD
                t2 = th.copy()
                t2[j] += h
                _, z2, ok2 = pinned(sel, t2, r.controls)
                if not ok2:
                    return None
                J[:, j] = (z2 - z) / h
        try:
            step = np.linalg.solve(J, z)
        except np.linalg.LinAlgError:
            return None
        if not np.isfinite(step).all():
            return None
        keep = (th - step >= 0) & (th - step <= 1)
        if not keep.all():  # theta leaves [0, 1]: that kink is released (exact
            sel, th, J = sel[keep], th[keep], None  # curvature), the others stay
            r, z, ok = pinned(sel, th, r.controls)
            if not ok:
                return None
            continue
        for _half in range(_KINK_HALVINGS):  # damped: the pinned solve converges, |z| drops
            r2, z2, ok2 = pinned(sel, th - step, r.controls)
            if ok2 and _max_abs(z2) < _max_abs(z):
                break
            step = 0.5 * step
        else:
            return None
        J += np.outer(z2 - z + J @ step, -step) / float(step @ step)  # Broyden update
        th, r, z = th - step, r2, z2
    if _max_abs(z) > ztol:
        return None
    return r, sel, th, z


class _KinkBudget(Exception):
    """The pinned solves of one search used up ``_PIN_BUDGET`` iterations."""


def _max_abs(v) -> float:
    return float(np.max(np.abs(v))) if np.size(v) else 0.0


def kink_summary(eq: dict, tol: float) -> dict:
    """``info["kink_equilibrium"]["equilibrium"]``: what the search for an equilibrium on
    the kinks found (:func:`kink_equilibrium`)."""
    if "reason" in eq:
        return {
            "ok": False,
            "iterations": eq["iterations"],
            "message": f"no equilibrium on the kinks: {eq['reason']}",
        }
    c = eq["check"]
    kinks = [
        (int(i), float(t), float(z))
        for i, t, z in zip(eq["kinks"], eq["theta"], eq["z"], strict=True)
    ]
    out = {
        "ok": eq["ok"],
        "kinks": kinks,  # (index, theta, z): curvature theta^2 of kink argument z
        "stationarity": eq["stationarity"],
        "feedback_nash": bool(c.ok),
        "feedback_nash_gain": float(c.max_relative_gain),
        "iterations": eq["iterations"],
    }
    th = ", ".join(f"{t:.4f}" for _, t, _ in kinks)
    zmax = max((abs(z) for _, _, z in kinks), default=0.0)
    if eq["ok"]:
        out["message"] = (
            f"feedback equilibrium on {len(kinks)} kink(s): max |a| {eq['stationarity']:.1e} <= "
            f"tol with the kinks' Gauss-Newton curvature theta^2 (theta {th}, an element of "
            f"the hinge's generalized Hessian) at |z| <= {zmax:.1e}; the feedback-Nash check "
            f"passes (largest relative gain {c.max_relative_gain:.1e})"
        )
    else:
        why = []
        if not eq["stationarity"] <= tol:
            why.append(f"max |a| {eq['stationarity']:.1e} > tol {tol:g}")
        if not c.ok:
            why.append(f"the feedback-Nash check fails ({c.max_relative_gain:.1e})")
        if not why:
            why.append("the pass with those curvatures is not finite")
        out["message"] = f"no equilibrium on the kinks (theta {th}): " + "; ".join(why)
    return out
