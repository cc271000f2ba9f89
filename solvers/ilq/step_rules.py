"""The step rules of the iLQ iteration (:mod:`solvers.ilq.iteration`): limits and the secant.

The limits of the adaptive regularization (``_MAX_MU``, ``_MIN_MU``, ``_MAX_RESETS``), the
smallest first trial step ``_MIN_STEP`` and the sufficient decrease ``_ARMIJO`` of the
line search, shared by :class:`~solvers.ilq.iteration.SolveOnce` and
:class:`~solvers.ilq.iteration.BatchSolve`; ``_secant_step`` predicts the first trial step
of the next iteration from the last accepted one, ``_max`` is ``max |a|`` (``inf`` when
not finite).
"""

from __future__ import annotations

import math

import numpy as np

_MAX_MU = 1e8  # largest global regularization the adaptive retries reach
_MIN_MU = 1e-4  # first raised regularization; below it, a lowered one returns to mu0
_MAX_RESETS = 2  # returns to the requested regularization before a solve is called stalled
_MIN_STEP = 1e-2  # smallest first trial step the secant predicts (relative to step_size)
_ARMIJO = 0.1  # sufficient decrease of the merit per unit step: (1 - c eps) x reference


def _secant_step(a_old, a_new, eps, cap):
    """First trial step of the next iteration from the last accepted one (a secant).

    Along the last direction the feed-forward went from ``a_old`` to ``a_new`` with step
    ``eps``; with ``rho = <a_new, a_old> / |a_old|^2`` the linear model
    ``a(e) = (1 - e (1 - rho) / eps) a_old`` vanishes at ``e = eps / (1 - rho)`` (at most
    ``cap``). An iteration that overshoots (``a`` flips sign: ``rho = -0.97`` gives about
    half a step) is damped; after a damped step the model is refitted (``rho ~ 0``: it
    fitted, keep the step; ``rho = 1/2``: twice the step). After a full step only a clear
    overshoot (``rho < -1/4``) damps, so an iteration that converges with full steps keeps
    them.
    """
    den = float(np.vdot(a_old, a_old))
    if not den > 0:
        return cap
    rho = float(np.vdot(a_new, a_old)) / den
    if not (math.isfinite(rho) and rho < 1.0) or (eps >= cap and rho >= -0.25):
        return cap
    return min(cap, max(_MIN_STEP * cap, eps / (1.0 - rho)))


def _max(a):
    a = np.asarray(a, float)
    m = float(a.max()) if a.size else 0.0
    if math.isfinite(m):  # the common case, without the masked copy
        return m
    a = a[np.isfinite(a)]
    return float(a.max()) if a.size else 0.0
