"""The iLQ solver object (:class:`ILQSolver`) and the entry function (:func:`solve_ilq`).

The method is described in :mod:`solvers.ilq`. The solver builds the game's CasADi
functions once (:mod:`solvers.ilq.quadratize`, :mod:`solvers.ilq.rollout`), holds the work
arrays of the LQ game (:mod:`solvers.ilq.riccati`) and runs solves
(:class:`solvers.ilq.iteration.SolveOnce`), with one restart from the open-loop
equilibrium after a stall.
"""

from __future__ import annotations

import dataclasses
import time

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame

from ..lm import check_options
from ..result import Equilibrium, SolveResult, Status, StopReason
from ..stages import _stage_index
from . import riccati
from .iteration import SolveOnce, solve_starts
from .kinks import build_kink_quad
from .options import HESSIANS, ILQOptions
from .quadratize import build_quadratize
from .rollout import build_rollout

__all__ = ["ILQSolver", "get_solver", "solve_ilq"]

# stalled solves that restart
_RESTART_STOPS = (StopReason.LINE_SEARCH, StopReason.REGULARIZED_ONLY)


class ILQSolver:
    """iLQ game solver for one game and one set of player costs (functions built once).

    ``costs``: ``None`` (the game's ``traj_agent_costs``) or a ``casadi.Function``
    ``(x, u, p) -> C`` with ``C`` of ``N`` entries, in the layout of :mod:`epo_casadi.game`.
    ``hessian``: ``"gauss_newton"`` (game costs only: ``J_i'J_i`` of player ``i``'s
    residual rows, positive semi-definite), ``"exact"`` or ``"auto"`` (Gauss-Newton for the
    game's costs, exact for custom ones). The object holds work arrays and CasADi buffers:
    one solve at a time (not thread-safe; use one solver per thread).
    """

    def __init__(
        self, game: PotentialGame, costs: ca.Function | None = None, hessian: str = "auto"
    ):
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        if hessian not in HESSIANS:
            raise SpecError("ilq.hessian", f"expected one of {HESSIANS}, got {hessian!r}")
        self.game = game
        self.custom_costs = costs is not None
        if hessian == "auto":
            hessian = "exact" if self.custom_costs else "gauss_newton"
        if hessian == "gauss_newton" and self.custom_costs:
            raise SpecError(
                "ilq.hessian",
                "'gauss_newton' needs the game's own (sum-of-squares) costs; use 'exact' with custom costs",
            )
        self.hessian = hessian
        self.costs = self._check_costs(game, costs)
        K, N = game.K, game.N
        self.K, self.N = K, N
        self.nx = int(sum(game.nx))
        self.nu = int(sum(game.nu))
        self.n = self.nu + self.nx + 1
        self.xidx, self.uidx = _stage_index(game)
        self.uo = np.concatenate([[0], np.cumsum(game.nu)]).astype(int)
        self.xo = np.concatenate([[0], np.cumsum(game.nx)]).astype(int)
        build_quadratize(self)
        build_rollout(self)
        riccati.build_indices(self)
        self._compiled: riccati.CompiledRiccati | None = None
        self._cquad = None  # solvers.fast_ilq.CompiledQuadratize after compile(), if it applies
        self._croll = None  # solvers.fast_ilq.CompiledRollout after compile()
        self._ftrial = None  # solvers.fast_ilq.CompiledTrial after compile(), game costs only
        self._grad = None  # the potential's gradient (result's grad_norm), on first use
        self.quad_backend = "interpreted"  #: quadratization used with compiled=True
        self.kink_width = 0.0  #: blend width of the kinks' curvature in the current solve
        self._kink_quad = None  # (quadratize, kinks) with blended kinks; False: no kinks
        self.kink_pins = None  #: per-kink slopes (>= 0: pinned, < 0: blended) or None
        self._pin_quad = None  # quadratize(X, U, p, w, s), built on first need

    @property
    def has_kinks(self) -> bool:
        """Whether the game's residual has kinks (``max``/``min``) whose curvature the
        solver can blend (Gauss-Newton only; built on first call)."""
        if self._kink_quad is None:
            self._kink_quad = build_kink_quad(self) or False
        return bool(self._kink_quad)

    def kinks_within(self, X, U, p, width: float) -> int:
        """Number of kink arguments (``b - a`` of the residual's ``max(a, b)``, ``a - b`` of
        ``min(a, b)``) within ``width / 2`` of their kink at ``(X, U)``."""
        if width <= 0 or not self.has_kinks:
            return 0
        (zk,) = self._kink_quad[1](X, U, p)
        return int(np.count_nonzero(np.abs(zk) < 0.5 * width))

    # ---- checks ---------------------------------------------------------------------------
    @staticmethod
    def _check_costs(game, costs):
        if costs is None:
            return game.function("traj_agent_costs")
        if not isinstance(costs, ca.Function):
            raise SpecError(
                "costs", f"expected a casadi.Function (x, u, p) -> C, got {type(costs).__name__}"
            )
        want = [(game.n_x, 1), (game.n_u, 1), (game.n_p, 1)]
        got = [(costs.size1_in(i), costs.size2_in(i)) for i in range(costs.n_in())]
        if costs.n_in() != 3 or got != want:
            raise SpecError("costs", f"expected inputs (x, u, p) of sizes {want}, got {got}")
        if costs.n_out() < 1 or costs.numel_out(0) != game.N:
            raise SpecError(
                "costs",
                f"expected a first output with N = {game.N} entries, got shape {costs.size_out(0)}",
            )
        if costs.is_a("MXFunction"):
            try:
                costs = costs.expand()
            except RuntimeError as e:
                raise SpecError("costs", f"the MX function cannot be expanded to SX: {e}") from None
        return costs

    # ---- symbolic builders ------------------------------------------------------------------
    def _joint_step(self, X, U):
        # the game's own stage map: each agent's dynamics, or its coupling's joint model
        return self.game.stage_step(X, U)

    # ---- numeric pieces ---------------------------------------------------------------------
    def rollout(self, p, Xr, Ur, PA, eps, compiled: bool = False):
        """Closed-loop rollout ``U_k = Ur_k - P_k (X_k - Xr_k) - eps a_k``: ``(X, U)``.

        ``compiled``: the generated-C stage fold when :meth:`compile` built it.
        """
        if compiled and self._croll is not None:
            X, U = self._croll(p[self._x0_idx], Xr, Ur, PA, eps)
        else:
            X, U = self.roll(p[self._x0_idx], Xr, Ur, PA, eps)
        return X.reshape(self.K + 1, self.nx).copy(), U.reshape(self.K, self.nu).copy()

    def quadratize(self, X, U, p, compiled: bool = False):
        """Costs ``C`` and energy ``E`` at ``(X, U)``; fills ``self.Lam`` and ``self.Phi``.

        ``compiled``: with the generated-C stage functions when :meth:`compile` built them
        (:mod:`solvers.fast_ilq`), else the interpreted trajectory function.
        """
        if self.kink_pins is not None:  # kinks at given slopes (an equilibrium on a kink)
            C, E, lam, phi = self._pin_quad(X, U, p, self.kink_width, self.kink_pins)
        elif self.kink_width > 0:  # blended kinks (interpreted; only after a failed search)
            C, E, lam, phi = self._kink_quad[0](X, U, p, self.kink_width)
        elif compiled and self._cquad is not None:
            return self._cquad(X, U, p)
        else:
            C, E, lam, phi = self.quad(X, U, p)
        self.Lam[self._lam_tgt] = lam[self._lam_src]
        self.Phi.reshape(-1)[self._phi_tgt] = phi
        return C.copy(), float(E[0])

    def _trial_fn(self, compiled: bool):
        """The one-call trial (rollout, quadratization, Riccati: :class:`solvers.fast_ilq.
        CompiledTrial`) where :meth:`quadratize` would use the compiled stage functions with
        the game's costs, else ``None``."""
        if compiled and self.kink_pins is None and self.kink_width <= 0:
            return self._ftrial
        return None

    def _own_shift(self, T, delta):
        """Shift per player so that its own block ``T_i[u_i, u_i]`` has pivots >= delta
        (:func:`solvers.ilq.riccati.own_shift`; ``None`` when no block needs one)."""
        return riccati.own_shift(self, T, delta)

    def backward(self, mu0: float, delta: float):
        """Coupled Riccati recursion on ``self.Lam``/``self.Phi``.

        Returns ``(PA, mu, ok)``: ``PA (K, nu, nx+1)`` holds ``[P_k | a_k]``, ``mu (K, N)``
        the shift added to each player's own block (``mu0`` included), ``ok`` False when
        a stage could not be solved (non-finite numbers). The compiled fold after
        :meth:`compile`, else numpy (:func:`solvers.ilq.riccati.backward`).
        """
        if self._compiled is not None:
            return self._compiled.backward(mu0, delta)
        return riccati.backward(self, mu0, delta)

    def _numpy_backward(self, mu0, delta):
        """:meth:`backward` in numpy, also after :meth:`compile` (the compiled fold's
        fallback for a singular stage)."""
        return riccati.backward(self, mu0, delta)

    def compile(self) -> ILQSolver:
        """Build the generated-C paths used with ``compiled=True``.

        The Riccati recursion (:class:`solvers.ilq.riccati.CompiledRiccati`), the rollout (a stage folded over
        the horizon) and, where the costs split into stage functions, the quadratization
        (:mod:`solvers.fast_ilq`; :attr:`quad_backend` is then ``"compiled"``). All are
        cached on disk per structure.
        """
        if self._compiled is None:
            from .. import fast_ilq

            fast_ilq.compile_solver(self)  # one library; also the one-call trial (_ftrial)
        return self

    def riccati_fold(self) -> riccati.CompiledRiccati:
        """The generated Riccati recursion of this solver, built but not compiled
        (:func:`solvers.fast_ilq.compile_solver` compiles it into the solver's library)."""
        return riccati.CompiledRiccati(self, compile_now=False)

    # ---- the solve ------------------------------------------------------------------------
    def solve(
        self, p: np.ndarray, u0: np.ndarray | None = None, options: ILQOptions | dict | None = None
    ) -> SolveResult:
        """Solve one problem: ``p (n_p,)``, ``u0 (n_u,)`` (zeros if None)."""
        opts = check_options(ILQOptions, options, "ilq")
        if opts.hessian not in ("auto", self.hessian):
            raise SpecError(
                "ilq.hessian",
                f"this solver was built with hessian={self.hessian!r}, options ask for {opts.hessian!r}",
            )
        if opts.compiled:
            self.compile()
        backward = (
            self.backward if opts.compiled or self._compiled is None else self._numpy_backward
        )
        t0 = time.perf_counter()
        g = self.game
        U0, P = g.check_inputs(g.zero_controls() if u0 is None else u0, p)
        if U0.shape[0] != 1:
            raise SpecError("u0/p", "ILQSolver.solve takes one problem; solve_ilq takes a batch")
        res = self._solve_once(P[0], U0[0], opts, backward, opts.max_iter, t0)
        return self._restart(res, P[0], U0[0], opts, backward, t0)

    def _restart(self, res, p, u0, opts, backward, t0) -> SolveResult:
        """``res`` of the solve of ``p`` from ``u0``, or the restart from the open-loop
        equilibrium where it stalled (``ILQOptions.restart``)."""
        g = self.game
        if not (
            opts.restart
            and not self.custom_costs
            and res.status is Status.STALLED
            and res.info["stop"] in _RESTART_STOPS
            and res.iterations < opts.max_iter
        ):
            return res
        # iLQ's own safeguards failed (typically far from an equilibrium, in collision):
        # start once more from the open-loop equilibrium, the potential's minimizer
        from ..lm import solve_lm

        lm = solve_lm(g, p, u0)
        again = self._solve_once(
            p, np.asarray(lm.controls), opts, backward, opts.max_iter - int(res.iterations), t0
        )
        info = {"at": int(res.iterations), "stop": res.info["stop"], "lm_status": lm.status.value}
        # the restart's result when it converged or found a kink equilibrium, else the first
        keep = again if again.status is Status.CONVERGED or again.info["stop"] == "kink" else res
        return dataclasses.replace(
            keep,
            iterations=np.int64(int(res.iterations) + int(again.iterations)),
            wall_time=time.perf_counter() - t0,
            info={**keep.info, "restart": {**info, "result": again.info["stop"]}},
        )

    def _solve_once(self, p, u0, opts, backward, max_iter, t0, once=None) -> SolveResult:
        """One iLQ solve of problem ``p (n_p,)`` from ``u0 (n_u,)``, at most ``max_iter``
        iterations (the iteration of :mod:`solvers.ilq`; :class:`solvers.ilq.iteration.
        SolveOnce`); ``once``: the run of that solve already made with other starts
        (:func:`solvers.ilq.iteration.solve_starts`)."""
        res = (once or SolveOnce(self, p, u0, opts, backward, max_iter, t0).run)()
        # a feedback Nash equilibrium of the players' own costs: coupled dynamics included
        return dataclasses.replace(res, equilibrium=Equilibrium.FEEDBACK)


# --------------------------------------------------------------------------------------
# entry function
# --------------------------------------------------------------------------------------
def get_solver(
    game: PotentialGame, costs: ca.Function | None = None, hessian: str = "auto"
) -> ILQSolver:
    """The cached :class:`ILQSolver` of ``game``, ``costs`` and ``hessian``, built on first use."""
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    # The entry keeps ``costs`` alive, so its id is not reused while cached.
    key = ("ilq", None if costs is None else id(costs), hessian)
    costs_, solver = game.cached(key, lambda: (costs, ILQSolver(game, costs, hessian)))
    if costs_ is not costs:  # pragma: no cover - guarded by keeping costs alive
        raise RuntimeError("iLQ solver cache returned another cost function")
    return solver


def solve_ilq(
    game: PotentialGame,
    p: np.ndarray,
    u0: np.ndarray | None = None,
    options: ILQOptions | dict | None = None,
    costs: ca.Function | None = None,
) -> SolveResult:
    """Local feedback Nash equilibrium of ``game`` by iLQ (see the module docstring).

    ``p``: ``(n_p,)`` or ``(B, n_p)``; ``u0``: ``(n_u,)`` or ``(B, n_u)`` (zeros if None);
    ``costs``: ``None`` (the game's agent costs) or a ``casadi.Function (x, u, p) -> C``.
    A batch is returned as one batched result, each problem's entry the solve of that
    problem alone; with ``compiled=True`` all problems iterate together
    (:func:`solvers.ilq.iteration.solve_starts`), else one after the other. The result's
    ``equilibrium`` is ``feedback Nash`` (:class:`solvers.result.Equilibrium`): a feedback
    Nash equilibrium of the players' own costs, also for games with coupled dynamics (no
    potential is involved).
    """
    opts = check_options(ILQOptions, options, "ilq")
    solver = get_solver(game, costs, opts.hessian)
    single = np.ndim(p) == 1 and (u0 is None or np.ndim(u0) == 1)
    if single:
        return solver.solve(p, u0, opts)
    U, P = game.check_inputs(game.zero_controls() if u0 is None else u0, p)
    t0 = time.perf_counter()
    rs = solve_starts(solver, P, U, opts)
    return _stack(rs, time.perf_counter() - t0)


def _stack(rs: list[SolveResult], wall: float) -> SolveResult:
    S = max(r.energy_history.shape[0] for r in rs)
    hist = np.stack(
        [np.pad(r.energy_history, (0, S - r.energy_history.shape[0]), mode="edge") for r in rs],
        axis=1,
    )
    status = np.empty(len(rs), dtype=object)
    status[:] = [r.status for r in rs]
    info: dict = {}
    for key in ("gains", "gains_prev", "feedforward", "regularization"):
        info[key] = np.stack([r.info[key] for r in rs])
    for key in ("stationarity", "max_regularization"):
        info[key] = np.array([r.info[key] for r in rs])
    info["residual_history"] = [r.info["residual_history"] for r in rs]
    info["step_sizes"] = [r.info["step_sizes"] for r in rs]
    info["custom_costs"] = rs[0].info["custom_costs"]
    info["options"] = rs[0].info["options"]
    return SolveResult(
        solver="ilq",
        controls=np.stack([r.controls for r in rs]),
        states=np.stack([r.states for r in rs]),
        energy=np.array([r.energy for r in rs], float),
        agent_costs=np.stack([r.agent_costs for r in rs]),
        status=status,
        iterations=np.array([r.iterations for r in rs]),
        energy_history=hist,
        grad_norm=np.array([r.grad_norm for r in rs], float),
        wall_time=wall,
        info=info,
        equilibrium=Equilibrium.FEEDBACK,
    )
