"""The safety filter between the tracker and the actuators: hard constraints on OSQP and a
certified fallback.

Every period the closed loop hands the filter the tracker's command ``u_nom`` together with
the observation, the estimate and the plan (:meth:`SafetyFilter.filter`); what it returns
is what the actuators get. The filter works on the world's vehicle model
(:class:`~solvers.control.vehicle.VehicleModel`, ``world.vehicle`` and ``world.dt``, read
at :meth:`SafetyFilter.reset`) over ``horizon`` steps ``k = 1..N`` at ``t + dt k``.

Constraints (the same set in the QP, in the filter's own check and in the tests'
independent check)
    * speed: ``v_k >= 0`` for every ``k`` (the ego never reverses);
    * collision: the ego's body keeps ``margin`` from every other agent's body grown by
      its uncertainty, in every *constrained mode*, at every ``k``. For a unit vector
      ``n`` the clearance along ``n`` is::

          min_i n' (P_i(x_k) - q) - r_0 - [a |n' h| + b |n' h_perp| + r
                                           + min(z sqrt(n' S_{j,k} n), max_inflation)]
                                           - margin

      with ``P_i`` the ego's points and ``r_0`` their radius (below), ``q``, ``h`` the
      position and heading of agent ``j`` in mode ``m`` and ``(a, b, r)`` its body (a
      rectangle of half-length ``a`` and half-width ``b`` grown by ``r``). Any ``n`` that
      makes this ``>= 0`` separates the two bodies; the constraint is that one does. The
      inflation: ``S_{j,k} = J_k P_j J_k'``, the estimate's covariance ``P_j`` of
      ``(x, y, v)`` carried ``t_k = dt k`` ahead at constant velocity (``J_k = [[1, 0, t_k
      cos theta_j], [0, 1, t_k sin theta_j]]``: the position and the speed uncertainty;
      the heading's does not move the predictions sideways, they follow their lanes);
      ``z`` the standard normal ``quantile`` (a chance-constraint reading: at most ``1 -
      quantile`` probability per constraint for Gaussian errors). The heading's std
      ``sigma_theta`` decides the body: from ``z sigma_theta >= 0.5`` rad on
      (:data:`TURN_DISC`: a standing car, whose heading nothing measures, and whose
      estimated heading drifts by a right angle) it is the disc of radius ``rho + r``,
      ``rho = sqrt(a^2 + b^2)``, that holds every heading.

Bodies (:func:`body_shapes`, :func:`covering_circles`): from the world's ``footprint``
``(length, width)`` (the highway-env worlds' 5 m x 2 m cars). ``shape="box"`` (default):
the ego is its four corners (``r_0 = 0``) and every other car its rectangle; ``"circles"``:
two circles per car, at ``+-length / 4`` along the heading with radius ``sqrt((length /
4)^2 + (width / 2)^2)`` (the smallest two equal circles that cover the rectangle: offset
1.25 m, radius 1.60 m), the ego's two circles against the convex hull of the other's. Two
cars side by side need 2.0 m between centre lines as boxes and 3.2 m as circles (one
covering circle: 5.39 m): on the left turn's 3.5 m lanes the circles leave 0.3 m for the
estimate's error and the inflation, and a passing oncoming car makes the constraint
infeasible. A world without a footprint (the crossing's robot and pedestrian) is one
circle per agent of its ``radii``.

Constrained modes: the plan's joint predictions ``(M, N, K, 4)`` (agent 0, the ego, left
out) whose probability (normalized) is at least ``threshold``, the most likely always, at
most ``max_modes`` (highest first); the estimate's constant-velocity prediction when the
plan has none, or with ``constant_velocity`` (an agent whose speed or heading std is above
2 m/s or 0.5 rad, a track that has not converged, is predicted standing). Predictions are
sampled at the filter's times by linear interpolation (heading unwrapped) and continued at
constant velocity beyond their end; a plan without usable predictions reuses the last
plan's, so a braking command after a failed plan is filtered too. With ``ignore_behind`` an
agent behind the ego, within its width band and heading the same way (within 30 degrees) is
not constrained against: keeping its distance is its driver's task, and a hard constraint
would make the ego flee from every car that follows it.

What happens in a period
    1. *Nominal sequence*: ``u_nom`` then the tracker's own continuation (the MPC's QP
       solution, ``command.info["sequence"]``) and then the plan's controls (its unicycle
       controls sampled like the trackers' reference, :func:`~solvers.control.track.reference`,
       converted to the vehicle's commands and clipped to the box), rolled out on the
       vehicle model from the current state; without a usable plan: braking to a stop,
       steering held. If this rollout meets every constraint, ``u_nom`` passes unchanged
       (no QP is solved).
    2. *QP* (the MPC formulation with the command as its reference), in the commands
       ``U`` alone (the linearized states ``x_{k+1} = F_k + G_k U`` eliminated)::

           min  1/2 w_first |u_0 - u_nom|^2_W + 1/2 sum_{k>=1} |u_k - ubar_k|^2_W
           s.t. u_min <= u_k <= u_max,  |u_k - u_{k-1}| <= rate dt  (u_{-1}: the command
                applied last),  v_k >= min(0, vtop_k),
                n' P_i(x_k) >= s(n) + r_0 + margin + buffer   (the two points nearest)

       with ``W = diag(1 / box width^2)``, ``ubar`` the nominal sequence,
       ``vtop_k`` the highest speed the box and the rates allow
       (:func:`~solvers.control.track.speed_floor`: below zero only right after hard
       braking at a standstill), the model and the points linearized along a safe
       sequence (the last period's, shifted, where it still meets the constraints, else
       the fallback's candidate: never the nominal rollout, which may have driven through
       an obstacle and would put the half-planes on its far side), the normal ``n`` and
       the other body's reach ``s(n)`` along it chosen there, and ``buffer`` (m) absorbing
       the linearization error. The solution is rolled out on the nonlinear model
       (accelerations raised where needed so the speed stops at zero) and checked against
       the constraints themselves; a violation re-linearizes along it and solves again, at
       most ``iterations`` times; a first command within ``tolerance`` of ``u_nom`` is
       replaced by ``u_nom`` where that still checks. OSQP is set up once per structure
       (again when more modes must be constrained than before) and warm-started at the
       linearization sequence with the last solution's duals.
    3. *Fallback* when the QP is infeasible, unsolved or its solution fails the check:
       candidates in this order (:attr:`SafetyFilter.FALLBACKS`), each rolled out and
       checked on the same constraints: braking at ``a_min``, at ``a_min / 2``, holding the
       speed, accelerating at ``a_max`` up to the ego task's speed (the last two: the way
       out of a conflict zone where stopping is not safe), each keeping its lane (pure
       pursuit on the ego task's path), and braking at ``a_min`` with the steering
       returned to straight (a lane that turns into the conflict); steering within its box
       and rate, the jerk limit waived, braking ends at standstill. The first that passes
       the check is taken (``certified``); if none does, the one with the largest smallest
       clearance, flagged ``certified = False``.

The returned :class:`~solvers.control.types.Command` keeps the tracker's ``info`` and adds
``info["safety"]``: ``intervened`` (the command differs from ``u_nom`` by more than
``tolerance`` times the box width in a component, or a fallback was taken), ``fallback``,
``certified`` (the sequence below passes the check), ``reason``, ``nominal``, ``sequence``
``(N, 2)`` (the commands whose rollout was checked, the returned one first), ``states``
(that rollout), ``clearance`` (its smallest, m; ``inf`` without constraints), ``modes`` (the
constrained plan modes' indices; ``"cv"``), ``qp`` (QP solves this period), ``status`` and
``seconds``. A fallback's command has ``fallback=True``. Counters: ``steps``,
``interventions``, ``fallbacks``, ``uncertified``, ``setups``, ``qp_iterations``.
``SafetyFilter.last`` holds the constraint data of the last period (``times``,
``obstacles`` ``(Mc, N-1, H, 4)``, ``ego_points``, ``ego_radius``, ``shapes``, ``cov``
``(N-1, H, 2, 2)``, ``z``, ``modes``).

Modules. This module documents the filter and keeps every name importable from here; the pieces
live beside it: :mod:`solvers.control.safety_options` (:class:`SafetyOptions` and its bounds),
:mod:`solvers.control.safety_geometry` (footprints, body shapes, the constant-velocity
prediction, the rollout function, the lane path) and :mod:`solvers.control.safety_filter`
(:class:`SafetyFilter`).
"""

from __future__ import annotations

from .safety_filter import SafetyFilter as SafetyFilter
from .safety_filter import _log as _log
from .safety_geometry import _MATH as _MATH
from .safety_geometry import _cv as _cv
from .safety_geometry import _heading as _heading
from .safety_geometry import _Path as _Path
from .safety_geometry import _rollout_function as _rollout_function
from .safety_geometry import _sample as _sample
from .safety_geometry import _steer_scalar as _steer_scalar
from .safety_geometry import _wrap as _wrap
from .safety_geometry import body_shapes as body_shapes
from .safety_geometry import covering_circles as covering_circles
from .safety_geometry import world_footprints as world_footprints
from .safety_options import _CV_HEADING_STD as _CV_HEADING_STD
from .safety_options import _CV_SPEED_STD as _CV_SPEED_STD
from .safety_options import _SAME_WAY as _SAME_WAY
from .safety_options import MAX_HORIZON as MAX_HORIZON
from .safety_options import MAX_ITER as MAX_ITER
from .safety_options import MAX_MODES as MAX_MODES
from .safety_options import SHAPES as SHAPES
from .safety_options import SPEED_TOL as SPEED_TOL
from .safety_options import TURN_DISC as TURN_DISC
from .safety_options import SafetyOptions as SafetyOptions

__all__ = [
    "SafetyOptions",
    "SafetyFilter",
    "covering_circles",
    "world_footprints",
    "body_shapes",
    "SHAPES",
    "MAX_HORIZON",
    "MAX_MODES",
]
