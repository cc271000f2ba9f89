"""Open-loop Nash equilibria of general games: Newton on every player's first-order conditions.

The potential solvers (:mod:`solvers.lm`, :mod:`solvers.ipopt`, :mod:`solvers.sqp`)
minimize ``E``; that is an open-loop Nash equilibrium (OLNE) only when each agent's
dynamics depend on its own controls alone (the theorem in :mod:`epo_casadi.game`). With
coupled dynamics (``GameSpec(couplings=...)``) ``C_i - E`` depends on ``u_i`` and a
minimizer of ``E`` is in general not an equilibrium. This solver works on the players'
own costs ``C_i``, coupled or not. Shapes and index order follow the contract in
:mod:`epo_casadi.game`.

The system
    The stacked first-order conditions of all players (the game's ``pseudo_gradient``)::

        F(u, p) = [dC_0/du_0; dC_1/du_1; ...; dC_{N-1}/du_{N-1}] = 0          (n_u rows)

    and the *game Jacobian* ``M = dF/du`` (``n_u x n_u``): block row ``i`` is the
    derivative of player ``i``'s gradient with respect to every player's controls, and its
    diagonal block ``M_ii`` is player ``i``'s own Hessian ``d^2 C_i / du_i^2``. For an
    uncoupled game ``F = dE/du`` and ``M`` is the Hessian of ``E``; with coupled dynamics
    ``M`` is in general not symmetric.

    ``jacobian="exact"`` builds ``M`` symbolically (CasADi, the Jacobian of ``F``).
    ``jacobian="gn"`` uses each player's Gauss-Newton matrix instead: with ``r_i`` the
    residual rows of the terms player ``i`` takes part in (``C_i = 1/2 |r_i|^2``) and
    ``J_i = dr_i/du``, block row ``i`` is ``J_i[:, u_i]' J_i``. It is exact where the
    residuals are affine in ``u`` (linear dynamics, quadratic costs), its diagonal blocks
    are positive semidefinite, and Newton with it converges linearly instead of
    quadratically. ``F`` itself is exact in both modes: a converged point of either is a
    zero of the same ``F``.

Start
    ``start="potential"`` (the default): Newton starts where :func:`solvers.lm.solve_lm`
    (default options) ends from ``u0``. For an uncoupled game that point (when LM
    converges) is already an equilibrium and Newton confirms it to ``tol`` (one or two
    steps on the shipped examples); for a coupled game it is a nearby start.
    ``start="given"``: Newton starts at ``u0`` itself.

One iteration (every problem of a batch on its own)
    With the merit ``phi(u) = 1/2 |F(u)|^2`` and a damping ``mu >= 0`` relative to
    ``s = max diag(M'M)``::

        mu = 0:   M d = -F                            (Newton)
        mu > 0:   (M'M + mu s I) d = -M'F             (Levenberg-Marquardt on F)

    then a backtracking line search ``u + a d``, ``a = 1, backtrack, backtrack^2, ...``
    (``max_backtracks`` reductions) that accepts the first ``a`` with
    ``phi(u + a d) <= phi(u) + armijo a F'M d``. A full step lowers the damping
    (``damping_down``; below ``min_damping`` it is 0 again: Newton), a shortened one
    raises it (``damping_up``); when no trial passes, the damping is raised and the
    direction solved again, up to ``max_damping``. With the exact ``M`` every direction
    with ``mu > 0`` descends on ``phi``; near a solution with ``M`` invertible the full
    Newton step is taken and converges quadratically (an LQ game, ``F`` affine, is solved
    in one step). With ``jacobian="gn"`` the test uses the Gauss-Newton slope.

Second order and escapes
    ``F = 0`` is each player's first-order condition, not its second-order one: a player
    may sit at a saddle of its own cost there (Newton is drawn to every zero of ``F``).
    With ``second_order=True`` (the default) each player's exact own Hessian is examined
    at every converged point: a block is positive semidefinite when its smallest
    eigenvalue is ``>= -SECOND_ORDER_TOL (1 + max |eigenvalue|)``. Where some are not, every
    such player moves along the eigenvector of its smallest eigenvalue to the best of
    ``+-1, +-1/2, ..., +-2^-19`` times it for its own cost (the others held), and Newton
    continues from there (at most ``saddle_escapes`` times; an escape counts as an
    iteration). ``info["own_hessian_min_eig"]`` ``(..., N)`` holds each player's smallest
    eigenvalue at the end and ``info["second_order_ok"]`` whether every block is positive
    semidefinite (then no player gains by a small unilateral deviation, to second order).

Statuses (``result.status`` / ``info["stop"]``, a :class:`~solvers.result.StopReason`)
    * ``converged`` / ``gtol``: ``|F|_inf <= tol``: the first-order conditions of
      **every** player hold, which is what an open-loop Nash equilibrium needs;
      ``info["second_order_ok"]`` says whether the second-order ones hold too.
    * ``max_iter`` / ``max_iter``: ``max_iter`` iterations without meeting ``tol``.
    * ``stalled`` / ``line_search``: no trial step lowers the merit, up to
      ``max_damping``: a stationary point of ``phi`` that is not a solution
      (``M'F = 0``, ``F != 0``), or a ``tol`` below what round-off lets ``F`` reach.
    * ``nonfinite`` / ``nonfinite``: ``F`` or ``M`` is NaN or inf at a point the
      iteration reached (a finite start where the game is not), or the final energy, costs
      or states are not. Trial points with NaN or inf are rejected by the line search. A
      start ``u0`` or parameters ``p`` with NaN or inf are refused with one
      :class:`~epo_casadi.errors.SpecError`.

    Like every local method it finds an equilibrium near its start;
    :func:`solvers.nash.nash_certificate` checks a result with best responses. The
    solver is for the unconstrained game of the paper (soft penalties): it takes no hard
    bounds (they would make ``F = 0`` a mixed complementarity problem; IPOPT and SQP take
    bounds on the potential).

Result fields
    ``energy`` is the potential ``E`` at the point and ``grad_norm`` the inf-norm of
    ``dE/du``, as for every solver (for a coupled game it is *not* zero at an
    equilibrium); ``info["stationarity"]`` is ``|F|_inf``, the quantity ``tol`` tests.
    ``iterations`` counts Newton steps and escapes (``info["start_iterations"]``: LM's,
    with ``info["start_status"]``); ``energy_history`` holds ``E`` before each iteration
    and at the end; ``info["stationarity_history"]``, ``info["step_sizes"]`` (NaN for an
    escape) and ``info["damping_history"]``: per problem (object arrays of ``B`` arrays);
    ``info["saddle_escapes"]``: escapes taken, ``(...)``.

Cost
    The CasADi functions (``F`` with ``M``, and ``F`` alone for the line search) are built
    once per game and ``jacobian`` kind and cached on the game (``game.cached``). Building
    the exact ``M`` costs about as much as an exact Hessian of ``E``; in single shooting it
    is a dense ``n_u x n_u`` matrix that every iteration factors (``O(n_u^3)``). A batch is
    solved problem by problem. The solver is meant for games with up to a few thousand
    controls.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError, check_bool, check_number, from_mapping, short_repr
from epo_casadi.game import PotentialGame

from .lm import MAX_STEPS, LMOptions, prepare_lm
from .result import (
    Equilibrium,
    SolveResult,
    Status,
    StopReason,
    demote_nonfinite,
    grad_inf_norm,
    mark_nonfinite_stops,
    padded_histories,
    per_problem,
)

__all__ = ["OLNEOptions", "OLNESolver", "solve_olne", "game_jacobian"]

#: relative tolerance of the second-order test: an own-Hessian block is positive
#: semidefinite when its smallest eigenvalue is >= -SECOND_ORDER_TOL (1 + max |eigenvalue|)
SECOND_ORDER_TOL = 1e-8


@dataclass(frozen=True)
class OLNEOptions:
    """Options of :func:`solve_olne` (defaults: a tight solve of the unconstrained game)."""

    max_iter: int = 100  #: Newton iterations (each with one Jacobian)
    #: "potential": Newton starts where LM's minimization of E from u0 ends; "given": at u0
    start: str = "potential"
    tol: float = 1e-8  #: converged when |F|_inf <= tol (every player's first-order condition)
    jacobian: str = "exact"  #: game Jacobian: "exact" (dF/du) or "gn" (per-player Gauss-Newton)
    damping: float = 0.0  #: initial damping mu (relative to max diag(M'M)); 0: Newton first
    min_damping: float = 1e-12  #: damping after the first rejection; below it, back to 0
    max_damping: float = 1e8  #: stop (stalled) when no step passes at this damping
    damping_up: float = 10.0  #: factor on the damping after a rejected or shortened step
    damping_down: float = 0.1  #: factor on the damping after a full step
    armijo: float = 1e-4  #: sufficient-decrease factor of the line search on 1/2 |F|^2
    backtrack: float = 0.5  #: factor on the step size after a rejected trial
    max_backtracks: int = 10  #: step-size halvings before the damping is raised instead
    second_order: bool = True  #: report each player's smallest own-Hessian eigenvalue
    #: escapes from a converged point where a player's own Hessian has a negative
    #: eigenvalue (a step along it that lowers that player's cost, then Newton again)
    saddle_escapes: int = 5
    #: when a solve ends in any status but 'converged', solve again along the collision
    #: weight (pair weights scaled up from 0.01, warm-started; solvers.continuation)
    continuation: bool = True

    def __post_init__(self):
        check_number("olne.max_iter", self.max_iter, lo=0, hi=MAX_STEPS, integer=True)
        check_number("olne.max_backtracks", self.max_backtracks, lo=0, hi=100, integer=True)
        check_number("olne.saddle_escapes", self.saddle_escapes, lo=0, hi=1000, integer=True)
        check_number("olne.tol", self.tol, lo=0, lo_open=True)
        for name in ("damping", "min_damping"):
            check_number(f"olne.{name}", getattr(self, name), lo=0)
        check_number("olne.max_damping", self.max_damping, lo=0, lo_open=True)
        check_number("olne.damping_up", self.damping_up, lo=1, lo_open=True)
        check_number("olne.damping_down", self.damping_down, lo=0, hi=1, lo_open=True)
        if self.damping_down >= 1:
            raise SpecError(
                "olne.damping_down", f"expected 0 < damping_down < 1, got {self.damping_down}"
            )
        check_number("olne.armijo", self.armijo, lo=0, hi=0.5, lo_open=True)
        if self.armijo >= 0.5:
            raise SpecError("olne.armijo", f"expected 0 < armijo < 0.5, got {self.armijo}")
        check_number("olne.backtrack", self.backtrack, lo=0, hi=1, lo_open=True)
        if self.backtrack >= 1:
            raise SpecError("olne.backtrack", f"expected 0 < backtrack < 1, got {self.backtrack}")
        if self.jacobian not in ("exact", "gn"):
            raise SpecError(
                "olne.jacobian", f"expected 'exact' or 'gn', got {short_repr(self.jacobian)}"
            )
        check_bool("olne.second_order", self.second_order)
        check_bool("olne.continuation", self.continuation)
        if self.start not in ("potential", "given"):
            raise SpecError(
                "olne.start", f"expected 'potential' or 'given', got {short_repr(self.start)}"
            )
        if self.min_damping > self.max_damping:
            raise SpecError(
                "olne.min_damping",
                f"expected min_damping <= max_damping ({self.max_damping:g}), "
                f"got {self.min_damping:g}",
            )

    @classmethod
    def from_mapping(cls, values, where: str = "olne") -> OLNEOptions:
        """The options from a mapping of their fields (unknown keys: one :class:`SpecError`)."""
        return from_mapping(cls, values, where, "option")


def game_jacobian(game: PotentialGame, kind: str = "exact") -> ca.Function:
    """``(u, p) -> (F, M)``: the stacked first-order conditions ``F`` (the game's
    ``pseudo_gradient``) and the game Jacobian ``M`` (``"exact"``: ``dF/du``; ``"gn"``:
    per-player Gauss-Newton block rows, see the module docstring). Built once per game and
    kind (``game.cached``)."""
    if kind not in ("exact", "gn"):
        raise SpecError("kind", f"expected 'exact' or 'gn', got {short_repr(kind)}")
    return game.cached(("olne_jacobian", kind), lambda: _build_jacobian(game, kind))


def _build_jacobian(game: PotentialGame, kind: str) -> ca.Function:
    sym = game.symbols
    u, p = sym["u"], sym["p"]
    F = game.function("pseudo_gradient")(u, p)
    if kind == "exact":
        M = ca.jacobian(F, u)
    else:
        r = sym["r"]
        J = ca.jacobian(r, u)
        blocks = []
        for i, name in enumerate(game.agent_names):
            rows = [
                j for t in game.terms if name in t.agents for j in range(t.rows.start, t.rows.stop)
            ]
            a, b = int(game.uoff[i]), int(game.uoff[i + 1])
            if not rows or b == a:
                blocks.append(ca.SX(b - a, game.n_u))
                continue
            Ji = J[rows, :]
            blocks.append(ca.mtimes(Ji[:, a:b].T, Ji))
        M = ca.vertcat(*blocks) if blocks else ca.SX(0, game.n_u)
    return ca.Function(f"olne_{kind}_jacobian", [u, p], [F, M], ["u", "p"], ["F", "M"])


def _own_hessians(game: PotentialGame) -> ca.Function:
    """``(u, p) -> (H_0, ..., H_{N-1})``: each player's exact own Hessian ``d^2C_i/du_i^2``
    (for the second-order report of ``jacobian="gn"``). Built once per game."""

    def build():
        sym = game.symbols
        u, p, C = sym["u"], sym["p"], sym["C"]
        outs = []
        for i in range(game.N):
            ui = u[int(game.uoff[i]) : int(game.uoff[i + 1])]
            outs.append(ca.hessian(C[i], ui)[0] if ui.shape[0] else ca.SX(0, 0))
        return ca.Function("olne_own_hessians", [u, p], outs)

    return game.cached(("olne_own_hessians",), build)


class OLNESolver:
    """The functions of one game and one Jacobian kind, built once; ``solve`` runs
    :func:`solve_olne`'s iteration on one problem or a batch (a loop over its problems)."""

    def __init__(self, game: PotentialGame, jacobian: str = "exact"):
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        t0 = time.perf_counter()
        self.game = game
        self.kind = jacobian
        #: (u, p) -> (F, M)
        self.newton = game_jacobian(game, jacobian)
        #: (u, p) -> F, for the line search
        self.residual = game.function("pseudo_gradient")
        self._energy = game.function("energy")
        self._gradient = game.function("gradient")
        self._costs = game.function("agent_costs")
        self._rollout = game.function("rollout")
        #: wall seconds of building the functions (once per game and kind)
        self.setup_s = time.perf_counter() - t0

    # ---- numbers at one point ------------------------------------------------------------
    def _F(self, u, p) -> np.ndarray:
        return np.asarray(self.residual(u, p), dtype=float).reshape(-1)

    def _FM(self, u, p) -> tuple[np.ndarray, np.ndarray]:
        F, M = self.newton(u, p)
        return np.asarray(F, dtype=float).reshape(-1), np.asarray(ca.densify(M), dtype=float)

    def own_hessian_eigen(self, u, p, M: np.ndarray | None = None) -> tuple:
        """Each player's own Hessian block ``d^2 C_i / du_i^2`` at ``u``: its smallest
        eigenvalue, its largest eigenvalue modulus (two ``(N,)`` arrays; NaN where the
        block is not finite, ``inf`` and 0 for a player without controls) and the
        eigenvector of the smallest (a list of ``N`` arrays). ``M``: the exact game
        Jacobian there, if at hand (its diagonal blocks are these)."""
        g = self.game
        if M is None or self.kind != "exact":
            hs = _own_hessians(g).call([ca.DM(u), ca.DM(p)])
            blocks = [np.asarray(ca.densify(h), dtype=float) for h in hs]
        else:
            blocks = [M[g.uoff[i] : g.uoff[i + 1], g.uoff[i] : g.uoff[i + 1]] for i in range(g.N)]
        low, big = np.full(g.N, np.inf), np.zeros(g.N)
        vecs = [np.zeros(H.shape[0]) for H in blocks]
        for i, H in enumerate(blocks):
            if H.size == 0:
                continue
            if not np.all(np.isfinite(H)):
                low[i] = big[i] = np.nan
                continue
            ev, V = np.linalg.eigh(0.5 * (H + H.T))
            low[i], big[i], vecs[i] = float(ev[0]), float(np.max(np.abs(ev))), V[:, 0]
        return low, big, vecs

    # ---- the solve ---------------------------------------------------------------------
    def prepare(self, p: np.ndarray, u0: np.ndarray | None = None) -> OLNESolver:
        """Evaluate the functions once at ``(u0, p)``: the whole first-call cost."""
        g = self.game
        U0, P = g.check_inputs(g.zero_controls() if u0 is None else u0, p)
        with np.errstate(all="ignore"):
            self._FM(U0[0], P[0])
            self._F(U0[0], P[0])
        return self

    def solve(self, p: np.ndarray, u0: np.ndarray | None = None, options=None) -> SolveResult:
        """Solve for ``p`` (``(n_p,)`` or ``(B, n_p)``) from ``u0`` (zeros if None)."""
        opts = _options(options)
        if opts.jacobian != self.kind:
            raise SpecError(
                "olne.jacobian",
                f"this solver was built for jacobian={self.kind!r}; use solve_olne",
            )
        g = self.game
        t0 = time.perf_counter()
        single = np.ndim(p) == 1 and (u0 is None or np.ndim(u0) == 1)
        U0, P = g.check_inputs(g.zero_controls() if u0 is None else u0, p)
        B = U0.shape[0]
        U0, P = U0.copy(), P.copy()
        start = None
        if opts.start == "potential":
            from .lm import solve_lm

            start = solve_lm(g, P, U0)
            U0 = np.where(np.isfinite(start.controls), start.controls, U0)
        with np.errstate(all="ignore"):
            runs = [self._run(U0[b].copy(), P[b], opts) for b in range(B)]
            res = self._stack(runs, P, opts, time.perf_counter() - t0)
        if start is not None:
            res.info["start_status"] = np.asarray(start.status, dtype=object).reshape(B)
            res.info["start_iterations"] = np.asarray(start.iterations).reshape(B)
        return res[0] if single else res

    def _run(self, u: np.ndarray, p: np.ndarray, o: OLNEOptions) -> dict:
        """One problem: Newton iterations, and after a converged point where a player's own
        Hessian has a negative eigenvalue, an escape along it and Newton again (at most
        ``saddle_escapes`` times; see the module docstring)."""
        h = {"energy": [float(self._energy(u, p))], "steps": [], "damping": []}
        F, M = self._FM(u, p)
        h["stationarity"] = [float(np.max(np.abs(F), initial=0.0))]
        it, escapes = 0, 0
        while True:
            u, F, M, status, stop, it = self._newton(u, p, F, M, o, it, h)
            eig = None
            if status is Status.CONVERGED and o.second_order:
                eig = self.own_hessian_eigen(u, p, M if self.kind == "exact" else None)
                if escapes < o.saddle_escapes and it < o.max_iter:
                    esc = self._escape(u, p, *eig, o)
                    if esc is not None:
                        escapes += 1
                        it += 1  # an escape counts as an iteration (one entry of every history)
                        u = esc
                        F, M = self._FM(u, p)
                        h["energy"].append(float(self._energy(u, p)))
                        h["stationarity"].append(float(np.max(np.abs(F), initial=0.0)))
                        h["steps"].append(np.nan)  # an escape, not a Newton step
                        h["damping"].append(np.nan)
                        continue
            break
        if eig is None and o.second_order and np.all(np.isfinite(u)):
            eig = self.own_hessian_eigen(u, p, M if self.kind == "exact" else None)
        if eig is None:
            eig = (np.full(self.game.N, np.nan),) * 2
        return {
            "u": u,
            "status": status,
            "stop": stop,
            "iter": it,
            "escapes": escapes,
            "eig": eig[0],
            "eig_scale": eig[1],
            **h,
        }

    def _newton(self, u, p, F, M, o: OLNEOptions, it: int, h: dict):
        """Damped Newton iterations from ``u`` until a stop; ``it``: iterations so far (of
        ``max_iter``). Appends to the histories ``h``."""
        n = u.size
        mu = float(o.damping)
        if not (np.all(np.isfinite(F)) and np.all(np.isfinite(M))):
            return u, F, M, Status.NONFINITE, StopReason.NONFINITE, it
        if h["stationarity"][-1] <= o.tol:
            return u, F, M, Status.CONVERGED, StopReason.GTOL, it
        while it < o.max_iter:
            phi = 0.5 * float(F @ F)
            scale = max(float(np.max(np.sum(M * M, axis=0), initial=0.0)), 1e-300)
            accepted = None
            while accepted is None:
                d = _direction(M, F, mu * scale, n)
                if d is not None:
                    slope = float(F @ (M @ d))
                    if slope < 0:
                        accepted = self._line_search(u, p, d, phi, slope, o)
                if accepted is None:
                    mu = o.min_damping if mu < o.min_damping else mu * o.damping_up
                    if mu > o.max_damping:
                        break
            it += 1
            if accepted is None:
                for key, v in (("steps", 0.0), ("damping", mu)):
                    h[key].append(v)
                for key in ("energy", "stationarity"):
                    h[key].append(h[key][-1])
                return u, F, M, Status.STALLED, StopReason.LINE_SEARCH, it
            alpha, u = accepted
            if alpha == 1.0:
                mu = mu * o.damping_down
                if mu < o.min_damping:
                    mu = 0.0
            else:
                mu = max(mu * o.damping_up, o.min_damping)
            h["steps"].append(alpha)
            h["damping"].append(mu)
            F, M = self._FM(u, p)
            h["energy"].append(float(self._energy(u, p)))
            h["stationarity"].append(float(np.max(np.abs(F), initial=0.0)))
            if not (np.all(np.isfinite(F)) and np.all(np.isfinite(M))):
                return u, F, M, Status.NONFINITE, StopReason.NONFINITE, it
            if h["stationarity"][-1] <= o.tol:
                return u, F, M, Status.CONVERGED, StopReason.GTOL, it
        return u, F, M, Status.MAX_ITER, StopReason.MAX_ITER, it

    def _escape(self, u, p, low, big, vecs, o: OLNEOptions) -> np.ndarray | None:
        """A point away from a converged point where players have negative own curvature
        (relative to their block's scale, below ``-SECOND_ORDER_TOL``): each such player
        ``i`` moves along its eigenvector ``v_i`` to ``u_i + t v_i``, ``t`` the best of
        ``+-1, +-1/2, ..., +-2^-19`` for its own cost ``C_i`` with the others held (it must
        lower ``C_i`` by a quarter of the quadratic model's ``|lambda| t^2 / 2``). None:
        every block is positive semidefinite, or no player found such a point."""
        g = self.game
        with np.errstate(invalid="ignore"):
            rel = np.where(np.isfinite(low) & np.isfinite(big), low / (1.0 + big), 0.0)
        bad = np.nonzero(rel < -SECOND_ORDER_TOL)[0]
        if bad.size == 0:
            return None
        C0 = np.asarray(self._costs(u, p), dtype=float).reshape(-1)
        out, moved = u.copy(), False
        for i in bad:
            a, b = int(g.uoff[i]), int(g.uoff[i + 1])
            best = None
            for j in range(20):
                t = 0.5**j
                for sign in (1.0, -1.0):
                    ut = u.copy()
                    ut[a:b] += sign * t * vecs[i]
                    ci = float(np.asarray(self._costs(ut, p), dtype=float).reshape(-1)[i])
                    if np.isfinite(ci) and ci <= C0[i] - 0.125 * abs(low[i]) * t * t:
                        if best is None or ci < best[0]:
                            best = (ci, ut[a:b])
            if best is not None:
                out[a:b] = best[1]
                moved = True
        return out if moved else None

    def _line_search(self, u, p, d, phi, slope, o: OLNEOptions):
        """The first step size that passes the Armijo test on ``phi``, with its point;
        None when none of the ``max_backtracks + 1`` trials does."""
        alpha = 1.0
        for _ in range(o.max_backtracks + 1):
            ut = u + alpha * d
            if np.all(np.isfinite(ut)):
                Ft = self._F(ut, p)
                if np.all(np.isfinite(Ft)):
                    if 0.5 * float(Ft @ Ft) <= phi + o.armijo * alpha * slope:
                        return alpha, ut
            alpha *= o.backtrack
        return None

    def _stack(self, runs: list[dict], P: np.ndarray, o: OLNEOptions, wall: float) -> SolveResult:
        g = self.game
        B = len(runs)
        U = np.stack([r["u"] for r in runs])
        X = np.empty((B, g.n_x))
        E = np.empty(B)
        C = np.empty((B, g.N))
        G = np.empty((B, g.n_u))
        for b in range(B):
            X[b] = np.asarray(self._rollout(U[b], P[b]), dtype=float).reshape(-1)
            E[b] = float(self._energy(U[b], P[b]))
            C[b] = np.asarray(self._costs(U[b], P[b]), dtype=float).reshape(-1)
            G[b] = np.asarray(self._gradient(U[b], P[b]), dtype=float).reshape(-1)
        status = np.empty(B, dtype=object)
        status[:] = [r["status"] for r in runs]
        status = demote_nonfinite(status, E[:, None], X, C, U)
        stop = mark_nonfinite_stops(status, np.array([r["stop"] for r in runs], dtype=object))
        eig = np.stack([r["eig"] for r in runs])
        second = np.array([_psd(r["eig"], r["eig_scale"]) for r in runs], dtype=bool)
        res = SolveResult(
            solver="olne",
            controls=U,
            states=X,
            energy=E,
            agent_costs=C,
            status=status,
            iterations=np.array([r["iter"] for r in runs], dtype=int),
            energy_history=padded_histories([r["energy"] for r in runs], E),
            grad_norm=grad_inf_norm(G),
            wall_time=wall,
            info={
                "stop": stop,
                "stationarity": np.array([r["stationarity"][-1] for r in runs]),
                "stationarity_history": per_problem(runs, "stationarity"),
                "step_sizes": per_problem(runs, "steps"),
                "damping_history": per_problem(runs, "damping"),
                "saddle_escapes": np.array([r["escapes"] for r in runs], dtype=int),
                "jacobian": o.jacobian,
                "options": o,
                "setup_s": self.setup_s,
            },
            equilibrium=Equilibrium.OPEN_LOOP,  # coupled or not: the players' own conditions
        )
        if o.second_order:
            res.info["own_hessian_min_eig"] = eig
            res.info["second_order_ok"] = second
        return res


def _direction(M: np.ndarray, F: np.ndarray, mu: float, n: int) -> np.ndarray | None:
    """The Newton (``mu = 0``) or damped least-squares direction; None where it has no
    finite solution (a singular ``M`` at ``mu = 0``)."""
    if n == 0:
        return None
    try:
        if mu == 0.0:
            d = np.linalg.solve(M, -F)
        else:
            A = M.T @ M
            A[np.diag_indices(n)] += mu
            L = np.linalg.cholesky(A)
            d = -np.linalg.solve(L.T, np.linalg.solve(L, M.T @ F))
    except np.linalg.LinAlgError:
        return None
    return d if np.all(np.isfinite(d)) else None


def _psd(low: np.ndarray, big: np.ndarray) -> bool:
    """Every own-Hessian block positive semidefinite within :data:`SECOND_ORDER_TOL`."""
    with np.errstate(invalid="ignore"):
        return bool(np.all(np.isfinite(big) & (low >= -SECOND_ORDER_TOL * (1.0 + big))))


def _options(options) -> OLNEOptions:
    if options is None:
        return OLNEOptions()
    if isinstance(options, OLNEOptions):
        return options
    return OLNEOptions.from_mapping(options, "olne")


def _solver_for(game: PotentialGame, kind: str) -> OLNESolver:
    return game.cached(("olne_solver", kind), lambda: OLNESolver(game, kind))


def solve_olne(
    game: PotentialGame,
    p: np.ndarray,
    u0: np.ndarray | None = None,
    options: OLNEOptions | dict | None = None,
) -> SolveResult:
    """An open-loop Nash equilibrium of ``game`` (coupled or not) for one problem or a batch.

    ``p``: ``(n_p,)`` or ``(B, n_p)``; ``u0``: ``(n_u,)`` or ``(B, n_u)`` (zeros if None).
    ``options``: :class:`OLNEOptions` or a mapping of its fields. Solves every player's
    first-order conditions ``F(u) = 0`` by damped Newton with a line search on
    ``1/2 |F|^2``; ``converged`` means ``|F|_inf <= tol`` for every player, and
    ``info["own_hessian_min_eig"]`` / ``info["second_order_ok"]`` report the players'
    second-order conditions (see the module docstring). The unconstrained (soft-penalty)
    game only: no hard bounds.
    """
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    opts = _options(options)
    return _solver_for(game, opts.jacobian).solve(p, u0, opts)


def prepare_olne(game: PotentialGame, p, u0, options: OLNEOptions) -> None:
    """Build and evaluate once what a solve reuses (``epo compare``'s ``setup_s``): the
    game Jacobian and line-search functions and, for ``start="potential"``, LM's backend."""
    opts = _options(options)
    if opts.start == "potential":
        prepare_lm(game, p, u0, LMOptions())
    _solver_for(game, opts.jacobian).prepare(p, u0)
