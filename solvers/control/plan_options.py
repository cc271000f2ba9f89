"""Options of the planners without a network (:mod:`solvers.control.plan`).

:class:`PlannerOptions` holds the horizon, the energy weights of the driving game, the
commit-logic margins of the game oracle and the LM / IPOPT settings of both planners, checked
when the options are made (:class:`~epo_casadi.errors.SpecError`); :data:`MAX_HORIZON`,
:data:`MAX_PATH_POINTS` and :data:`MAX_STEPS` bound the sizes. The planners, the game and
the commit logic they configure are described in :mod:`solvers.control.plan`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from epo_casadi.errors import SpecError, check_number, check_size

from ..lm import LMOptions

#: most planning steps (a game of N agents has 2 N K unknowns and is rebuilt per K)
MAX_HORIZON = 1000
#: most lane-window vertices per agent (parameters of the game)
MAX_PATH_POINTS = 1000
#: most LM steps per period / of a cold start, and IPOPT iterations per plan
MAX_STEPS = 100_000


@dataclass(frozen=True)
class PlannerOptions:
    """Horizon, energy weights and solver settings of the game oracle and the CV planner.

    The defaults give a 3 s horizon at the world's ``dt`` and a plan within a period
    (``epo simulate`` measures it: the real-time factor in the summary).
    """

    horizon: int = 30  #: planning steps K (of the world's dt), 2 to MAX_HORIZON (1000)
    path_points: int = 10  #: vertices of each agent's lane window (a fixed parameter size),
    #: 2 to 1000
    path_behind: float = 3.0  #: metres of lane kept behind an agent's projection
    path_ahead: float = 10.0  #: metres of lane beyond max(v, speed) * horizon
    w_path: float = 5.0  #: weight of the distance to the lane centre line
    w_vref: float = 0.6  #: weight of speed - lane speed
    w_velocity: float = 0.05  #: weight of the speed itself
    w_acceleration: float = 0.5  #: weight of the acceleration
    w_jerk: float = 0.05  #: weight of the jerk
    w_turn_rate: float = 1.0  #: weight of the turn rate
    w_turn_acceleration: float = 0.1  #: weight of the turn acceleration
    w_reverse: float = 5.0  #: weight of max(0, -v) (soft; the plans never reverse anyway)
    w_collision: float = 50.0  #: weight of the collision penetration
    collision_margin: float = 1.0  #: metres added to r_i + r_j in the collision feature
    steps: int = 10  #: LM steps per period (warm-started), at most 100,000
    start_acceleration: float = 2.0  #: oracle: |a| of the "ego first" / "others first" starts
    switch_margin: float = 0.3  #: oracle: switch from letting another agent go first to going
    #: first only for an equilibrium this fraction of (1 + |E|) lower
    yield_margin: float = 0.02  #: oracle: the same for switching to letting it go first (the
    #: safe direction), and to leave the warm-started equilibrium without a conflict zone
    commit_time: float = 1.0  #: oracle: least time (s) after a switch before going first
    stop_gap: float = 0.5  #: oracle: m from the ego's front at its stop line to the zone
    stop_deceleration: float = 4.0  #: oracle: m/s^2; the ego is committed to going first
    #: once it cannot stop before its stop line with it
    stopped_speed: float = 1.0  #: oracle: m/s; a converged agent slower than this gets its
    #: estimated speed as speed reference (it waits), not its lane's desired speed
    unconverged_inflation: float = 1.0  #: m added to the radius of an unconverged track
    hold_weight: float = 100.0  #: oracle: factor on the acceleration and turn-rate weights
    #: of an agent predicted to keep its velocity (an unconverged track, a stopped agent)
    temperature: float = 1.0  #: oracle: mode weights exp(-(E - E_min) / temperature)
    first_steps: int = 100  #: LM steps of a cold start (first period, after a failure), at
    #: most 100,000
    gtol: float = 1e-6  #: LM gradient tolerance (stops early once met)
    backend: str = "fused"  #: LM Gauss-Newton backend: "fused" (one problem at a time is its
    #: strength; equal to "structured" to 1e-12), "structured" or "dense"
    compiled: bool | None = None  #: the backend as generated C; None: when a C compiler is
    #: found (solvers.codegen.find_compiler), else interpreted
    ipopt_max_iter: int = 100  #: IPOPT iterations of the CV planner's best response (at most
    #: 100,000)
    ipopt_tol: float = 1e-8  #: IPOPT tolerance of the CV planner

    def __post_init__(self):
        sizes = (
            ("horizon", MAX_HORIZON, "game size", 2),
            ("path_points", MAX_PATH_POINTS, "game size", 2),
            ("steps", MAX_STEPS, "planning time", 1),
            ("first_steps", MAX_STEPS, "planning time", 1),
            ("ipopt_max_iter", MAX_STEPS, "planning time", 1),
        )
        for name, limit, what, lo in sizes:
            v = check_size(f"planner.{name}", getattr(self, name), limit, what, lo=lo)
            object.__setattr__(self, name, v)
        for f in fields(self):
            if f.name.startswith("w_") or f.name in ("path_behind", "path_ahead"):
                check_number(f"planner.{f.name}", getattr(self, f.name), lo=0)
        for name in (
            "collision_margin",
            "gtol",
            "start_acceleration",
            "switch_margin",
            "yield_margin",
            "commit_time",
            "stop_gap",
            "stopped_speed",
            "unconverged_inflation",
        ):
            check_number(f"planner.{name}", getattr(self, name), lo=0)
        check_number("planner.stop_deceleration", self.stop_deceleration, lo=0, lo_open=True)
        check_number("planner.hold_weight", self.hold_weight, lo=1)
        check_number("planner.temperature", self.temperature, lo=0, lo_open=True)
        check_number("planner.ipopt_tol", self.ipopt_tol, lo=0, lo_open=True)
        if self.backend not in ("fused", "structured", "dense"):
            raise SpecError(
                "planner.backend",
                f"expected 'fused', 'structured' or 'dense', got {self.backend!r}",
            )
        if self.compiled is not None and not isinstance(self.compiled, bool):
            raise SpecError(
                "planner.compiled", f"expected true, false or null, got {self.compiled!r}"
            )

    @classmethod
    def from_dict(cls, values: dict | None) -> PlannerOptions:
        """Options from a mapping; an unknown key is an error naming the allowed ones."""
        from ..lm import check_options

        return check_options(cls, values, "planner")

    def lm(self, steps: int) -> LMOptions:
        return LMOptions(
            steps=steps,
            gtol=self.gtol,
            ftol=0.0,
            backend=self.backend,
            compiled=_have_compiler() if self.compiled is None else self.compiled,
            threads=1,
        )


def _have_compiler() -> bool:
    from ..codegen import CompilerError, find_compiler

    try:
        find_compiler()
    except CompilerError:
        return False
    return True
