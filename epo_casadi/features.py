"""Energy features: residual vectors ``c(.)`` of one agent and ``d(.)`` of a pair.

A feature turns trajectories into a residual vector; the game multiplies it by one
scalar weight parameter and adds ``1/2 ||w * c||^2`` to the energy (paper Eq. (7)).
Shapes and time indices follow the contract in :mod:`epo_casadi.game`: an agent's
trajectory is ``X`` (``nx x (K+1)``, column ``k`` is ``x_k``; ``x_0`` is the
initial state) and ``U`` (``nu x K``, column ``k`` is ``u_k``).

Own features (:data:`OWN_FEATURES`, App. F.3 of the paper):

======================  ===========================================  ===============
kind                    residual                                     time steps
======================  ===========================================  ===============
``goal``                ``p(x_K) - g`` (terminal position to goal)    ``K``
``velocity``            velocity of ``x_k``                          ``1..K``
``acceleration``        acceleration control ``u_k``                 ``0..K-1``
``jerk``                ``(a_{k+1} - a_k) / dt``                     ``0..K-2``
``turn_rate``           turn rate at ``(x_k, u_k)``                  ``0..K-1``
``turn_acceleration``   ``(w_{k+1} - w_k) / dt``                     ``0..K-2``
``reference_velocity``  ``speed(x_k) - v_ref``                       ``1..K``
``path``                distance of ``p(x_k)`` to a polyline         ``1..K``
``velocity_bound``      ``max(0, s - hi) + max(0, lo - s)``          ``1..K``
``acceleration_bound``  same on the acceleration                     ``0..K-1``
``turn_rate_bound``     same on the turn rate                        ``0..K-1``
======================  ===========================================  ===============

Pair feature (:data:`PAIR_FEATURES`): ``collision``,
``max(0, r_i + r_j + margin - dist(p_i(x_k), p_j(x_k)))`` every ``every``-th step
``k = every, 2 every, ..., <= K`` with the smooth distance
``sqrt(dx^2 + dy^2 + eps)`` so derivatives stay finite when two centres coincide.
It is symmetric in ``(i, j)``, the condition under which the potential's
minimizer is an open-loop Nash equilibrium (paper Sec. 3.2, after Kavuncu et al., Theorem 2).

Soft bounds use ``max(0, g)``; the residual has a kink where the bound becomes
active, the energy ``1/2 max(0, g)^2`` is continuously differentiable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import casadi as ca

from .dynamics import Dynamics
from .errors import SpecError, short_repr
from .registry import FEATURES, NAME_RE
from .registry import PAIR_FEATURES as _PAIR_REGISTRY

__all__ = [
    "AgentContext",
    "Feature",
    "ParamSpec",
    "RESERVED_BLOCKS",
    "PairFeature",
    "Goal",
    "Velocity",
    "Acceleration",
    "Jerk",
    "TurnRate",
    "TurnAcceleration",
    "ReferenceVelocity",
    "Path",
    "VelocityBound",
    "AccelerationBound",
    "TurnRateBound",
    "Collision",
    "OWN_FEATURES",
    "PAIR_FEATURES",
    "make_feature",
    "make_pair_feature",
    "smooth_distance",
]

DIST_EPS = 1e-9  # inside the square root of the smooth distance (m^2)


@dataclass
class AgentContext:
    """What a feature sees of one agent: symbolic trajectory and reference parameters."""

    dynamics: Dynamics
    X: Any  # nx x (K+1)
    U: Any  # nu x K
    dt: float
    refs: dict[str, Any]  # reference parameter name -> SX column (goal, vref, path)
    radius: float = 0.0

    @property
    def K(self) -> int:
        return self.U.shape[1]


def smooth_distance(p, q):
    """Smooth Euclidean distance ``sqrt(||p - q||^2 + eps)`` of two CasADi columns.

    ``p``, ``q``: columns of equal length (positions in metres); the result is a scalar
    expression in metres. ``eps`` is :data:`DIST_EPS` (1e-9 m^2), so the distance is at
    least about 3e-5 m and its derivatives stay finite where ``p = q`` (the gradient is
    zero there instead of undefined). Used by ``collision`` and ``path``.
    """
    d = p - q
    return ca.sqrt(ca.sumsqr(d) + DIST_EPS)


def _bound(q, lower: float, upper: float):
    return ca.fmax(0, q - upper) + ca.fmax(0, lower - q)


#: parameter block prefixes of the game itself, not available to a feature's own blocks
RESERVED_BLOCKS = ("x0", "goal", "vref", "path", "w")


@dataclass(frozen=True)
class ParamSpec:
    """A parameter block a feature declares (:meth:`Feature.params`).

    The game adds one block ``<name>.<agent>`` of ``size`` entries per agent whose
    features declare it (group ``"feature"`` of :class:`epo_casadi.game.ParamLayout`),
    with ``default`` as its default value; the feature reads it as ``ctx.refs[name]``
    (an SX column). ``entries`` names the entries (``<name>.<agent>.<entry>``; default:
    ``0, 1, ...``, none for a block of one entry). Like every block it can be set per
    solve through ``p``, predicted by a network and changed with ``--set``.
    """

    name: str
    size: int
    default: tuple[float, ...] | float = 0.0
    entries: tuple[str, ...] | None = None

    def __post_init__(self):
        where = f"params.{self.name}"
        if not isinstance(self.name, str) or not NAME_RE.match(self.name):
            raise SpecError(
                "params.name",
                f"expected a block name of letters, digits and '_', got {short_repr(self.name)}",
            )
        if self.name in RESERVED_BLOCKS:
            raise SpecError(
                where, f"{self.name!r} is a block of the game itself; reserved: {RESERVED_BLOCKS}"
            )
        n = self.size
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise SpecError(f"{where}.size", f"expected an integer >= 1, got {short_repr(n)}")
        d = self.default
        d = (d,) * n if isinstance(d, (int, float)) and not isinstance(d, bool) else d
        try:
            d = tuple(float(v) for v in d)
        except (TypeError, ValueError):
            raise SpecError(
                f"{where}.default", f"expected {n} numbers, got {short_repr(self.default)}"
            ) from None
        if len(d) != n or not all(math.isfinite(v) for v in d):
            raise SpecError(
                f"{where}.default", f"expected {n} finite numbers, got {short_repr(self.default)}"
            )
        object.__setattr__(self, "default", d)
        if self.entries is not None:
            e = tuple(self.entries)
            if len(e) != n or not all(isinstance(x, str) and NAME_RE.match(x) for x in e):
                raise SpecError(
                    f"{where}.entries", f"expected {n} entry names, got {short_repr(self.entries)}"
                )
            object.__setattr__(self, "entries", e)

    def entry_names(self, agent: str) -> list[str]:
        """One readable name per entry of the block of ``agent``."""
        block = f"{self.name}.{agent}"
        if self.entries is not None:
            return [f"{block}.{e}" for e in self.entries]
        return [block] if self.size == 1 else [f"{block}.{j}" for j in range(self.size)]


@dataclass(frozen=True)
class Feature:
    """Base of own features. ``label`` names the weight (defaults to the kind).

    A subclass (built-in or a user's, see :mod:`epo_casadi.registry`) sets ``kind`` and
    defines ``steps(K)`` and ``residual(ctx)``; ``refs()`` names the agent's reference
    blocks it reads (``goal``, ``vref``, ``path``) and ``params()`` declares blocks of
    its own (:class:`ParamSpec`); both arrive in ``ctx.refs``.
    """

    kind: ClassVar[str] = ""
    label: str | None = None
    weight: float = 1.0  # default value of this feature's weight parameter

    @property
    def key(self) -> str:
        return self.label or self.kind

    def refs(self) -> dict[str, int]:
        """Reference parameters of the agent this feature reads (``goal``, ``vref``,
        ``path``): name -> size."""
        return {}

    def params(self) -> tuple[ParamSpec, ...]:
        """Parameter blocks of this feature's own (see :class:`ParamSpec`)."""
        return ()

    def steps(self, K: int) -> list[int]:
        raise NotImplementedError

    def residual(self, ctx: AgentContext):
        raise NotImplementedError

    def formula(self, s) -> Any:
        """The residual at one symbolic step, for ``epo inspect`` (a CasADi expression or str).

        ``s`` (:class:`epo_casadi.inspect.FormulaSymbols`) looks like an
        :class:`AgentContext` whose ``X[:, k]`` / ``U[:, k]`` take a step *label*
        (``"k"``, ``"k+1"``, ``s.K``) and give named symbols (``v_k``); ``s.refs`` holds the
        reference entries by parameter name (``goal.robot.x``). ``None`` (this default):
        inspect shows the residual at the first step of a short horizon instead.
        """
        return None

    def check(self, dynamics: Dynamics) -> None:
        """Raise :class:`SpecError` when the feature does not apply to ``dynamics``."""
        w = self.weight
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w):
            raise SpecError(f"{self.key}.weight", f"expected a finite number, got {short_repr(w)}")
        if w < 0:  # the rule of the game layer (learning.layer), said the same way
            raise SpecError(
                f"{self.key}.weight", f"expected a number >= 0 (weights must be >= 0), got {w:g}"
            )
        x = ca.SX.sym("x", dynamics.nx, 3)
        u = ca.SX.sym("u", dynamics.nu, 2)
        refs = {n: ca.SX.sym(n, s) for n, s in self.refs().items()}
        refs.update({b.name: ca.SX.sym(b.name, b.size) for b in self.params()})
        try:
            r = self.residual(AgentContext(dynamics, x, u, 0.1, refs))
        except SpecError:
            raise
        except Exception as e:  # a user's residual that does not build is a spec error
            msg = (str(e).strip().splitlines() or [""])[-1]
            raise SpecError(
                self.key, f"residual() fails on a symbolic trajectory ({type(e).__name__}: {msg})"
            ) from None
        if not isinstance(r, (ca.SX, ca.MX, ca.DM)) or (r.numel() and r.shape[1] != 1):
            raise SpecError(
                self.key, f"residual() must return a CasADi column vector, got {short_repr(r)}"
            )

    def to_dict(self) -> dict:
        """``{"type": <registered name or module:Class>, <field>: value, ...}``."""
        d = {"type": FEATURES.type_name(type(self))}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "label" and v is None:
                continue
            d[f.name] = _plain(v)
        return d


def _plain(v):
    """Tuples as lists, recursively (YAML and JSON writers take lists)."""
    return [_plain(x) for x in v] if isinstance(v, (tuple, list)) else v


def _cols(fn, ks):
    return ca.vertcat(*[fn(k) for k in ks]) if ks else ca.SX(0, 1)


@dataclass(frozen=True)
class Goal(Feature):
    """Terminal goal: ``p(x_K) - g``, the position of the last state minus the goal (m).

    Two rows at step ``K``; ``g`` is the agent's reference block ``goal.<agent>`` (2
    entries, metres, the world frame), settable per solve or predicted by a network.
    ``c_goal`` of the paper (App. F.3). Fields: ``label``, ``weight`` (:class:`Feature`).
    """

    kind: ClassVar[str] = "goal"

    def refs(self):
        return {"goal": 2}

    def steps(self, K):
        return [K]

    def residual(self, ctx):
        return ctx.dynamics.position(ctx.X[:, ctx.K]) - ctx.refs["goal"]

    def formula(self, s):
        return self.residual(s)


@dataclass(frozen=True)
class Velocity(Feature):
    """Velocity penalty: the velocity of ``x_k`` for ``k = 1..K``, as the dynamics define it.

    One row per step (``v``, m/s) for heading models (unicycle, bicycle), two (``vx``,
    ``vy``) for the double integrator (:meth:`Dynamics.velocity`). Pulls the agent
    towards standing still, so it is weighed against ``goal`` or ``reference_velocity``.
    ``c_vel`` of the paper (App. F.3). Fields: ``label``, ``weight``.
    """

    kind: ClassVar[str] = "velocity"

    def steps(self, K):
        return list(range(1, K + 1))

    def residual(self, ctx):
        return _cols(lambda k: ctx.dynamics.velocity(ctx.X[:, k]), self.steps(ctx.K))

    def formula(self, s):
        return s.dynamics.velocity(s.X[:, "k"])


@dataclass(frozen=True)
class Acceleration(Feature):
    """Control effort: the acceleration control ``u_k`` for ``k = 0..K-1``.

    One row per step (longitudinal ``a``, m/s^2) for heading models, two (``ax``, ``ay``)
    for the double integrator (:meth:`Dynamics.acceleration`). ``c_acc`` of the paper
    (App. F.3). Fields: ``label``, ``weight``.
    """

    kind: ClassVar[str] = "acceleration"

    def steps(self, K):
        return list(range(K))

    def residual(self, ctx):
        return _cols(lambda k: ctx.dynamics.acceleration(ctx.U[:, k]), self.steps(ctx.K))

    def formula(self, s):
        return s.dynamics.acceleration(s.U[:, "k"])


@dataclass(frozen=True)
class Jerk(Feature):
    """Jerk: ``(a_{k+1} - a_k) / dt`` for ``k = 0..K-2``, the finite difference of the
    acceleration control (m/s^3), one row per step and acceleration component.

    ``c_jerk`` of the paper (App. F.3). Needs ``K >= 2`` to have rows. Fields: ``label``,
    ``weight``.
    """

    kind: ClassVar[str] = "jerk"

    def steps(self, K):
        return list(range(K - 1))

    def residual(self, ctx):
        acc = ctx.dynamics.acceleration
        return _cols(
            lambda k: (acc(ctx.U[:, k + 1]) - acc(ctx.U[:, k])) / ctx.dt, self.steps(ctx.K)
        )

    def formula(self, s):
        acc = s.dynamics.acceleration
        return (acc(s.U[:, "k+1"]) - acc(s.U[:, "k"])) / s.dt


@dataclass(frozen=True)
class TurnRate(Feature):
    """Turn rate at ``(x_k, u_k)`` for ``k = 0..K-1`` (rad/s), one row per step.

    The unicycle's ``omega``; the bicycle's ``v tan(delta) / L``
    (:meth:`Dynamics.turn_rate`). The double integrator has no heading, so the feature is
    refused for it (:class:`~epo_casadi.errors.SpecError`). ``c_turnr`` of the paper
    (App. F.3). Fields: ``label``, ``weight``.
    """

    kind: ClassVar[str] = "turn_rate"

    def steps(self, K):
        return list(range(K))

    def residual(self, ctx):
        tr = ctx.dynamics.turn_rate
        return _cols(lambda k: tr(ctx.X[:, k], ctx.U[:, k]), self.steps(ctx.K))

    def formula(self, s):
        return s.dynamics.turn_rate(s.X[:, "k"], s.U[:, "k"])


@dataclass(frozen=True)
class TurnAcceleration(Feature):
    """Turn acceleration: ``(w_{k+1} - w_k) / dt`` for ``k = 0..K-2`` with ``w_k`` the turn
    rate at ``(x_k, u_k)`` (rad/s^2), one row per step.

    Heading models only, as :class:`TurnRate`. ``c_turnacc`` of the paper (App. F.3).
    Fields: ``label``, ``weight``.
    """

    kind: ClassVar[str] = "turn_acceleration"

    def steps(self, K):
        return list(range(K - 1))

    def residual(self, ctx):
        tr = ctx.dynamics.turn_rate
        X, U = ctx.X, ctx.U
        return _cols(
            lambda k: (tr(X[:, k + 1], U[:, k + 1]) - tr(X[:, k], U[:, k])) / ctx.dt,
            self.steps(ctx.K),
        )

    def formula(self, s):
        tr, X, U = s.dynamics.turn_rate, s.X, s.U
        return (tr(X[:, "k+1"], U[:, "k+1"]) - tr(X[:, "k"], U[:, "k"])) / s.dt


@dataclass(frozen=True)
class ReferenceVelocity(Feature):
    """Reference speed: ``speed(x_k) - v_ref`` for ``k = 1..K`` (m/s), one row per step.

    ``v_ref`` is the agent's reference block ``vref.<agent>`` (1 entry, m/s, e.g. a lane's
    speed limit). For the double integrator the speed is ``sqrt(vx^2 + vy^2)`` (with
    ``1e-12`` under the root). ``c_vref`` of the paper (App. F.3). Fields: ``label``,
    ``weight``.
    """

    kind: ClassVar[str] = "reference_velocity"

    def refs(self):
        return {"vref": 1}

    def steps(self, K):
        return list(range(1, K + 1))

    def residual(self, ctx):
        return _cols(
            lambda k: ctx.dynamics.speed(ctx.X[:, k]) - ctx.refs["vref"], self.steps(ctx.K)
        )

    def formula(self, s):
        return s.dynamics.speed(s.X[:, "k"]) - s.refs["vref"]


@dataclass(frozen=True)
class Path(Feature):
    """Distance of the position to a polyline of ``points`` vertices (a parameter).

    The polyline parameter ``path`` holds ``(x_0, y_0, x_1, y_1, ...)``. The
    distance to the nearest segment uses a clamped projection and the smooth
    distance; the minimum over segments is continuous and differentiable almost
    everywhere (where the nearest segment does not switch).
    """

    kind: ClassVar[str] = "path"
    points: int | None = None  # None: the number of vertices of the agent's path

    def __post_init__(self):
        if self.points is not None and not (isinstance(self.points, int) and self.points >= 2):
            raise SpecError(
                "path.points",
                f"a polyline needs an integer >= 2 points, got {short_repr(self.points)}",
            )

    def refs(self):
        return {"path": 2 * self.points}

    def steps(self, K):
        return list(range(1, K + 1))

    def residual(self, ctx):
        P = ca.reshape(ctx.refs["path"], 2, self.points)

        def dist(k):
            q = ctx.dynamics.position(ctx.X[:, k])
            ds = []
            for s in range(self.points - 1):
                a, b = P[:, s], P[:, s + 1]
                ab = b - a
                t = ca.dot(q - a, ab) / (ca.sumsqr(ab) + 1e-12)
                t = ca.fmin(1, ca.fmax(0, t))
                ds.append(smooth_distance(q, a + t * ab))
            out = ds[0]
            for d in ds[1:]:
                out = ca.fmin(out, d)
            return out

        return _cols(dist, self.steps(ctx.K))

    def formula(self, s):
        q = s.dynamics.position(s.X[:, "k"])
        return (
            f"min over segments j = 0..{self.points - 2} of the smooth distance "
            f"sqrt(|{q} - proj_j|^2 + 1e-9), proj_j = {q} clamped onto the segment "
            f"(P_j, P_j+1) of {s.ref_name('path')} = (x0, y0, x1, y1, ...)"
        )


@dataclass(frozen=True)
class _BoundFeature(Feature):
    lower: float = -math.inf
    upper: float = math.inf

    def __post_init__(self):
        lo, hi = float(self.lower), float(self.upper)
        if math.isnan(lo) or math.isnan(hi) or not lo < hi:
            raise SpecError(f"{self.kind}.lower/upper", f"need lower < upper, got {lo} and {hi}")
        if math.isinf(lo) and math.isinf(hi):
            raise SpecError(f"{self.kind}", "give at least one finite bound (lower or upper)")

    def _q(self, ctx, k):
        raise NotImplementedError

    def residual(self, ctx):
        lo, hi = float(self.lower), float(self.upper)
        lo = -1e300 if math.isinf(lo) else lo
        hi = 1e300 if math.isinf(hi) else hi
        return _cols(lambda k: _bound(self._q(ctx, k), lo, hi), self.steps(ctx.K))

    def formula(self, s):
        q, lo, hi = self._q(s, "k"), float(self.lower), float(self.upper)
        parts = ([ca.fmax(0, q - hi)] if math.isfinite(hi) else []) + (
            [ca.fmax(0, lo - q)] if math.isfinite(lo) else []
        )
        return parts[0] if len(parts) == 1 else parts[0] + parts[1]


@dataclass(frozen=True)
class VelocityBound(_BoundFeature):
    """Soft speed bound: ``max(0, s_k - upper) + max(0, lower - s_k)`` with ``s_k`` the
    speed of ``x_k``, for ``k = 1..K`` (m/s), one row per step; zero inside the bounds.

    ``lower``, ``upper`` (m/s; default ``-inf`` and ``inf``): at least one finite,
    ``lower < upper``. The energy ``1/2 (w max(0, g))^2`` is the quadratic penalty of the
    paper's soft constraints, ``c_velb`` (App. F.3). Fields also ``label``, ``weight``.
    """

    kind: ClassVar[str] = "velocity_bound"

    def steps(self, K):
        return list(range(1, K + 1))

    def _q(self, ctx, k):
        return ctx.dynamics.speed(ctx.X[:, k])


@dataclass(frozen=True)
class AccelerationBound(_BoundFeature):
    """Soft bound on the acceleration control: ``max(0, a_k - upper) + max(0, lower - a_k)``
    for ``k = 0..K-1`` (m/s^2), one row per step and acceleration component (two for the
    double integrator, each bounded alone); zero inside the bounds.

    ``lower``, ``upper`` (m/s^2) as in :class:`VelocityBound`. ``c_accb`` of the paper
    (App. F.3). Fields also ``label``, ``weight``.
    """

    kind: ClassVar[str] = "acceleration_bound"

    def steps(self, K):
        return list(range(K))

    def _q(self, ctx, k):
        return ctx.dynamics.acceleration(ctx.U[:, k])


@dataclass(frozen=True)
class TurnRateBound(_BoundFeature):
    """Soft bound on the turn rate ``w_k`` at ``(x_k, u_k)``:
    ``max(0, w_k - upper) + max(0, lower - w_k)`` for ``k = 0..K-1`` (rad/s), one row per
    step; zero inside the bounds.

    ``lower``, ``upper`` (rad/s) as in :class:`VelocityBound`; heading models only, as
    :class:`TurnRate`. ``c_turnrb`` of the paper (App. F.3). Fields also ``label``,
    ``weight``.
    """

    kind: ClassVar[str] = "turn_rate_bound"

    def steps(self, K):
        return list(range(K))

    def _q(self, ctx, k):
        return ctx.dynamics.turn_rate(ctx.X[:, k], ctx.U[:, k])


# --- pairwise -------------------------------------------------------------------------
@dataclass(frozen=True)
class PairFeature:
    """Base of pairwise features ``d(x_i, x_j)``; must be symmetric in ``(i, j)``."""

    kind: ClassVar[str] = ""
    label: str | None = None
    weight: float = 1.0  # default value of the weight parameter of every pair
    pairs: tuple[tuple[str, str], ...] | None = None  # None: every pair of agents

    @property
    def key(self) -> str:
        return self.label or self.kind

    def steps(self, K: int) -> list[int]:
        raise NotImplementedError

    def residual(self, a: AgentContext, b: AgentContext):
        raise NotImplementedError

    def formula(self, a, b) -> Any:
        """The residual of a pair at one symbolic step (see :meth:`Feature.formula`); ``a``
        and ``b`` name their symbols by agent (``robot.x_k``). ``None``: generic display."""
        return None

    def to_dict(self) -> dict:
        """``{"type": <registered name or module:Class>, <field>: value, ...}``."""
        d = {"type": _PAIR_REGISTRY.type_name(type(self))}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            d[f.name] = _plain(v)
        return d


@dataclass(frozen=True)
class Collision(PairFeature):
    """Collision avoidance of a pair of circles:
    ``max(0, r_i + r_j + margin - dist(p_i(x_k), p_j(x_k)))`` (m), one row per step
    ``k = every, 2 every, ..., <= K``.

    ``r_i``, ``r_j`` are the agents' radii (m; a parameter block where the game makes them
    one), ``dist`` is :func:`smooth_distance`; the row is zero while the circles, grown by
    ``margin``, do not overlap. It is symmetric in ``(i, j)``, as a potential game's pair
    terms must be (module docstring). The paper's interaction feature ``d(.)`` (Eq. (7)),
    a point-to-point distance active when the circles overlap, evaluated every step in RPI
    and every fifth in exiD (App. F.3).

    Fields: ``label``, ``weight`` (>= 0, the default value of every pair's weight
    ``w.<a>-<b>.<label>``), ``pairs`` (agent-name pairs; ``None``: every pair), ``every``
    (integer >= 1, the step stride) and ``margin`` (m, >= 0).
    """

    kind: ClassVar[str] = "collision"
    every: int = 1
    margin: float = 0.0  #: safety distance (m) added to r_i + r_j

    def __post_init__(self):
        if not (isinstance(self.every, int) and self.every >= 1):
            raise SpecError(
                "collision.every", f"expected an integer >= 1, got {short_repr(self.every)}"
            )
        w = self.weight
        if isinstance(w, (int, float)) and not isinstance(w, bool) and w < 0:
            raise SpecError(
                "collision.weight", f"expected a number >= 0 (weights must be >= 0), got {w:g}"
            )
        m = self.margin
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m) or m < 0:
            raise SpecError(
                "collision.margin", f"expected a finite distance >= 0 (m), got {short_repr(m)}"
            )

    def steps(self, K):
        return list(range(self.every, K + 1, self.every))

    def residual(self, a, b):
        pa, pb = a.dynamics.position, b.dynamics.position
        reach = a.radius + b.radius + float(self.margin)
        return _cols(
            lambda k: ca.fmax(0, reach - smooth_distance(pa(a.X[:, k]), pb(b.X[:, k]))),
            self.steps(a.K),
        )

    def formula(self, a, b):
        reach = a.radius + b.radius + float(self.margin)
        pa, pb = a.dynamics.position(a.X[:, "k"]), b.dynamics.position(b.X[:, "k"])
        return ca.fmax(0, reach - smooth_distance(pa, pb))


FEATURES.bind(
    Feature,
    (
        Goal,
        Velocity,
        Acceleration,
        Jerk,
        TurnRate,
        TurnAcceleration,
        ReferenceVelocity,
        Path,
        VelocityBound,
        AccelerationBound,
        TurnRateBound,
    ),
)
_PAIR_REGISTRY.bind(PairFeature, (Collision,))
#: own features by name: the built-ins and every registered one (the registry's live table)
OWN_FEATURES: dict[str, type[Feature]] = FEATURES.table
#: pair features by name (the registry's live table)
PAIR_FEATURES: dict[str, type[PairFeature]] = _PAIR_REGISTRY.table


def make_feature(spec: Any, where: str = "feature") -> Feature:
    """Own feature from a name, a mapping ``{"type": ..., options}`` (a registered name or
    ``module:Class``) or an instance of any :class:`Feature` subclass."""
    return FEATURES.construct(spec, where)


def make_pair_feature(spec: Any, where: str = "pair_feature") -> PairFeature:
    """Pair feature from a name, a mapping or an instance (see :func:`make_feature`)."""
    return _PAIR_REGISTRY.construct(spec, where)
