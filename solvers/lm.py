"""Batched Levenberg-Marquardt on the potential ``E(u, p) = 1/2 ||r(u, p)||^2``.

One call solves ``B`` problems (e.g. batch x modes) with their own parameters and
initial strategies. Each step, for every problem (paper Sec. 4.2, Theseus semantics)::

    (J'J + lambda D) du = -J'r,        u <- u + alpha * du

with ``D = I`` (or ``diag(J'J)`` with ``ellipsoidal=True``), damping ``lambda`` and step
size ``alpha``. :meth:`LMOptions.paper` gives the paper's setting (``S = 2`` steps,
``alpha = 0.3``, ``lambda = 10``, no adaptation). With ``adaptive_damping`` a step that
does not lower the energy is rejected and ``lambda`` grows; an accepted one shrinks it.

The linear algebra is a *Gauss-Newton backend*. :class:`DenseGN` (:mod:`solvers.gn`) evaluates
``r`` and ``J`` for the whole batch with mapped CasADi functions (no Python loop per
problem) and solves the damped normal equations numerically (batched Cholesky), never
with a symbolic inverse. The default, :class:`solvers.structured.StructuredGN`, computes
the same step exactly without forming ``J'J``: single shooting's Gauss-Newton system is
an LQ problem over the time stages, solved by a Riccati recursion vectorized over the
batch (about 7x faster for N = 2, K = 40 in a batch of 64; ``bench/bench_lm.py``).
The same backend is reused by the differentiable layer to solve with the same matrix
in its backward pass.

A minimizer of ``E`` is a local open-loop Nash equilibrium only when every agent's
dynamics depend on its own controls only (:mod:`epo_casadi.game`); for a game with coupled
dynamics the result says ``equilibrium = potential minimum (coupled dynamics: not a Nash
equilibrium)`` (:class:`solvers.result.Equilibrium`), whatever its status.

Shapes follow :mod:`epo_casadi.game`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields

import numpy as np

from epo_casadi.errors import SpecError, check_number, short_repr
from epo_casadi.game import PotentialGame

from .batch import BatchFunction
from .gn import DenseGN, Linearization  # the shared backend piece, one level down
from .result import (
    SolveResult,
    Status,
    StopReason,
    demote_nonfinite,
    grad_inf_norm,
    mark_nonfinite_stops,
    potential_equilibrium,
)

__all__ = ["LMOptions", "DenseGN", "Linearization", "solve_lm", "check_options", "MAX_STEPS"]

#: Largest iteration limit an options object accepts (``lm.steps``, ``ipopt.max_iter``):
#: far above any converging solve, small enough that a typo cannot run for days.
MAX_STEPS = 10_000_000


def check_options(cls, values: dict | None, where: str):
    """Build a frozen options dataclass from a dict; unknown keys are an error."""
    if values is None:
        return cls()
    if isinstance(values, cls):
        return values
    if not isinstance(values, dict):
        raise SpecError(where, f"expected a mapping of options, got {type(values).__name__}")
    if not all(isinstance(k, str) for k in values):
        raise SpecError(where, f"expected option names as keys, got {short_repr(list(values))}")
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise SpecError(where, f"unknown option(s) {unknown}; allowed: {sorted(names)}")
    return cls(**values)


def _pos(name, v, allow_zero=False):
    check_number(f"lm.{name}", v, lo=0, lo_open=not allow_zero)


@dataclass(frozen=True)
class LMOptions:
    """Levenberg-Marquardt options (defaults: a converging standalone solve)."""

    steps: int = 500  #: maximum number of steps S (a converging solve stops long before)
    step_size: float = 1.0  #: alpha in u <- u + alpha du, 0 < alpha <= 1
    damping: float = 1e-2  #: initial damping lambda
    adaptive_damping: bool = True  #: reject energy-increasing steps and adapt lambda
    damping_up: float = 10.0  #: factor on lambda after a rejected step
    damping_down: float = 0.3  #: factor on lambda after an accepted step
    min_damping: float = 1e-9  #: lower clamp of lambda
    max_damping: float = 1e9  #: stop when lambda exceeds this (E cannot be lowered further)
    ellipsoidal: bool = False  #: D = diag(J'J) instead of the identity
    gtol: float = 1e-8  #: stop, converged, when |J'r|_inf <= gtol (0 disables)
    ftol: float = 1e-12  #: stop when an accepted step lowers E by <= ftol * (1 + E) (0 disables)
    ctol: float = 1e-4  #: an ftol/max_damping stop is converged iff max_j cos(r, J e_j) <= ctol
    backend: str = (
        "structured"  #: GN backend: "structured" (stage Riccati), "fused" (fast_gn.py) or "dense"
    )
    compiled: bool = (
        False  #: structured/fused backends: evaluate their functions as generated C (needs gcc)
    )
    threads: int | None = None  #: threads for mapped evaluation (None: EPO_THREADS or all cores)
    polish: int = 0  #: Newton steps (exact Hessian) after an ftol/damping stop with |grad| > gtol
    #: when a solve ends in any status but 'converged', solve again along the collision
    #: weight (pair weights scaled up from 0.01, warm-started; solvers.continuation)
    continuation: bool = True

    def __post_init__(self):
        if (
            isinstance(self.steps, bool)
            or not isinstance(self.steps, int)
            or not 0 <= self.steps <= MAX_STEPS
        ):
            raise SpecError(
                "lm.steps",
                f"expected an integer >= 0 and <= {MAX_STEPS} (the iteration limit), "
                f"got {short_repr(self.steps)}",
            )
        _pos("step_size", self.step_size)
        if self.step_size > 1:
            raise SpecError("lm.step_size", f"expected 0 < step_size <= 1, got {self.step_size}")
        _pos("damping", self.damping, allow_zero=True)
        _pos("damping_up", self.damping_up)
        _pos("damping_down", self.damping_down)
        _pos("gtol", self.gtol, allow_zero=True)
        _pos("ctol", self.ctol)
        _pos("min_damping", self.min_damping, allow_zero=True)
        _pos("max_damping", self.max_damping)
        if not self.damping_up > 1 or not self.damping_down < 1:
            raise SpecError(
                "lm.damping_up/damping_down",
                f"expected damping_up > 1 and damping_down < 1, got {self.damping_up}, {self.damping_down}",
            )
        for name in ("adaptive_damping", "ellipsoidal", "compiled", "continuation"):
            if not isinstance(getattr(self, name), bool):
                raise SpecError(
                    f"lm.{name}", f"expected true or false, got {short_repr(getattr(self, name))}"
                )
        if self.threads is not None and (
            isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1
        ):
            raise SpecError(
                "lm.threads", f"expected an integer >= 1 or null, got {short_repr(self.threads)}"
            )
        _pos("ftol", self.ftol, allow_zero=True)
        if (
            isinstance(self.polish, bool)
            or not isinstance(self.polish, int)
            or not 0 <= self.polish <= 1000
        ):
            raise SpecError(
                "lm.polish", f"expected an integer >= 0 and <= 1000, got {short_repr(self.polish)}"
            )
        if self.backend not in ("dense", "structured", "fused"):
            raise SpecError(
                "lm.backend",
                f"expected 'dense', 'structured' or 'fused', got {short_repr(self.backend)}",
            )

    @classmethod
    def paper(cls, **overrides) -> LMOptions:
        """The paper's layer setting: S = 2 fixed steps, alpha = 0.3, lambda = 10."""
        base = dict(
            steps=2, step_size=0.3, damping=10.0, adaptive_damping=False, gtol=0.0, ftol=0.0
        )
        base.update(overrides)
        return cls(**base)


def make_backend(game: PotentialGame, options: LMOptions):
    """The Gauss-Newton backend ``options`` name, built once per game (``game.cached``).

    A game with coupled dynamics (``game.coupled``) always gets :class:`DenseGN`: the
    stage-wise backends assume each agent steps with its own dynamics.
    """
    key = ("lm_backend", options.backend, options.threads, options.compiled)

    def build():
        if getattr(game, "coupled", False):
            return DenseGN(game, threads=options.threads)
        if options.backend == "structured":
            from .structured import StructuredGN

            return StructuredGN(game, threads=options.threads, compiled=options.compiled)
        if options.backend == "fused":
            from .fast_gn import FusedGN

            return FusedGN(game, threads=options.threads, compiled=options.compiled)
        return DenseGN(game, threads=options.threads)

    return game.cached(key, build)


def batch_function(game: PotentialGame, name: str, threads: int | None = None) -> BatchFunction:
    """:class:`BatchFunction` of the game's named function, built once per game and threads."""
    return game.cached(
        ("batch", name, threads), lambda: BatchFunction(game.function(name), threads)
    )


def solve_lm(
    game: PotentialGame,
    p: np.ndarray,
    u0: np.ndarray | None = None,
    options: LMOptions | dict | None = None,
    backend=None,
) -> SolveResult:
    """Minimize the potential of ``game`` for one problem or a batch.

    ``p``: ``(n_p,)`` or ``(B, n_p)``; ``u0``: ``(n_u,)`` or ``(B, n_u)`` (zeros if None).
    A problem whose energy or step turns non-finite is frozen at its last finite iterate
    with status ``NONFINITE``; the other problems continue unaffected.
    """
    opts = check_options(LMOptions, options, "lm")
    # Non-finite values are detected and masked per problem below; numpy's overflow and
    # invalid-value warnings would only duplicate that (and fail under warnings-as-errors).
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return _solve_lm(game, p, u0, opts, backend)


def _solve_lm(game, p, u0, opts, backend) -> SolveResult:
    t0 = time.perf_counter()
    single = np.ndim(p) == 1 and (u0 is None or np.ndim(u0) == 1)
    U, P = game.check_inputs(game.zero_controls() if u0 is None else u0, p)
    be = backend or make_backend(game, opts)
    s = _LMState.start(be, U.copy(), P, opts)
    for _ in range(opts.steps):
        if not s.active.any():
            break
        _lm_step(s, be, opts)
    if opts.polish and opts.gtol > 0 and game.n_u:
        _polish_stops(s, game, be, opts)
    cos = _judge_stalls(s, be, opts)
    res = _lm_result(s, game, opts, cos, time.perf_counter() - t0)
    return res[0] if single else res


@dataclass
class _LMState:
    """The batch's iterate and bookkeeping during :func:`solve_lm`."""

    U: np.ndarray  #: controls ``(B, n_u)``
    P: np.ndarray  #: parameters ``(B, n_p)``
    lin: Linearization  #: the linearization at ``U``
    E: np.ndarray  #: energies ``(B,)``
    lam: np.ndarray  #: damping ``(B,)``
    active: np.ndarray  #: problems still iterating ``(B,)``
    status: np.ndarray  #: :class:`Status` per problem
    stop: np.ndarray  #: why each problem stopped (``info["stop"]``)
    iters: np.ndarray  #: iterations per problem
    hist: list  #: energies after each step taken
    lam_hist: list  #: damping after each step taken

    @classmethod
    def start(cls, be, U, P, opts: LMOptions) -> _LMState:
        """The state at ``U``: problems non-finite or already below ``gtol`` are stopped."""
        B = U.shape[0]
        lam = np.full(B, float(opts.damping))
        active = np.ones(B, dtype=bool)
        status = np.full(B, Status.MAX_ITER, dtype=object)
        stop = np.array([StopReason.MAX_ITER] * B, dtype=object)
        iters = np.zeros(B, dtype=int)
        lin = be.linearize(U, P)
        E = lin.energy.copy()
        # history grows with the steps taken (a loop that ended early stops here, whatever
        # opts.steps is), never with the iteration limit
        s = cls(U, P, lin, E, lam, active, status, stop, iters, [E.copy()], [lam.copy()])
        bad = ~np.isfinite(E) | ~np.all(np.isfinite(lin.gradient), axis=1)
        s.finish(bad, Status.NONFINITE, StopReason.NONFINITE)
        done = _converged_grad(lin, opts.gtol) & active
        s.finish(done, Status.CONVERGED, StopReason.GTOL)
        return s

    def finish(self, mask: np.ndarray, status: Status, stop: StopReason) -> None:
        """Stop the problems ``mask`` with ``status`` and the reason ``stop``."""
        self.status[mask], self.active[mask], self.stop[mask] = status, False, stop


def _converged_grad(lin: Linearization, gtol: float) -> np.ndarray:
    """``(B,)``: the gradient's inf-norm is at most ``gtol`` (all False for ``gtol = 0``)."""
    if gtol > 0:
        return np.max(np.abs(lin.gradient), axis=1) <= gtol
    return np.zeros(lin.gradient.shape[0], bool)


def _lm_step(s: _LMState, be, opts: LMOptions) -> None:
    """One damped Gauss-Newton step of every active problem, then the stopping tests."""
    U, P, active = s.U, s.P, s.active
    du = be.solve(s.lin, s.lam, -s.lin.gradient, opts.ellipsoidal)
    U_try = U + opts.step_size * du
    finite = np.all(np.isfinite(U_try), axis=1)
    U_try[~finite] = U[~finite]
    if opts.adaptive_damping:
        E_try = be.energy(U_try, P)
        accept = active & finite & np.isfinite(E_try) & (E_try < s.E)
    else:
        accept = active & finite
    s.iters[active] += 1
    U_prev = U.copy()
    U[accept] = U_try[accept]
    new_lin = be.linearize(U, P)
    E_new = new_lin.energy
    nonfinite = active & (~finite | ~np.isfinite(E_new))
    if nonfinite.any():  # freeze at the last finite iterate
        U[nonfinite] = U_prev[nonfinite]
        s.status[nonfinite], active[nonfinite] = Status.NONFINITE, False
        s.stop[nonfinite] = StopReason.NONFINITE
    decrease = s.E - E_new
    if opts.adaptive_damping:
        lam = np.where(accept, np.maximum(s.lam * opts.damping_down, opts.min_damping), s.lam)
        s.lam = np.where(active & ~accept, lam * opts.damping_up, lam)
        s.finish(active & (s.lam > opts.max_damping), Status.STALLED, StopReason.MAX_DAMPING)
    keep = ~nonfinite
    s.E = np.where(keep, E_new, s.E)
    s.lin = _merge(s.lin, new_lin, keep)
    s.finish(active & _converged_grad(s.lin, opts.gtol), Status.CONVERGED, StopReason.GTOL)
    if opts.ftol > 0:
        small = active & accept & (np.abs(decrease) <= opts.ftol * (1 + np.abs(s.E)))
        s.finish(small, Status.STALLED, StopReason.FTOL)
    s.hist.append(s.E.copy())
    s.lam_hist.append(s.lam.copy())


def _polish_stops(s: _LMState, game: PotentialGame, be, opts: LMOptions) -> None:
    """A stop without progress above ``gtol`` gets a few exact-Hessian Newton steps."""
    cand = (
        np.isin(s.stop, (StopReason.FTOL, StopReason.MAX_DAMPING))
        & (np.max(np.abs(s.lin.gradient), axis=1) > opts.gtol)
        & (s.status != Status.NONFINITE)
    )
    if cand.any():
        s.U, done = _polish(game, s.U, s.P, cand, opts)
        new_lin = be.linearize(s.U, s.P)
        s.E = np.where(cand, new_lin.energy, s.E)
        s.lin = _merge(s.lin, new_lin, cand)
        s.status[done], s.stop[done] = Status.CONVERGED, StopReason.POLISH


def _judge_stalls(s: _LMState, be, opts: LMOptions) -> np.ndarray:
    """A stop without progress (ftol, damping cap) is converged only where the first-order
    test holds; otherwise the iterate is a stall, not a stationary point. Returns the
    residual cosines ``(B,)`` (zeros when nothing stalled)."""
    cos = np.zeros(s.U.shape[0])
    candidates = (s.status == Status.STALLED) & (s.stop != StopReason.POLISH)
    if candidates.any():
        cos = residual_cosine(s.lin, be)
        s.status[candidates & (cos <= opts.ctol)] = Status.CONVERGED
    return cos


def _lm_result(s: _LMState, game: PotentialGame, opts: LMOptions, cos, wall) -> SolveResult:
    """The batched :class:`SolveResult` of the final state (states and costs rolled out)."""
    U, P, E = s.U, s.P, s.E
    X = _rollout(game, U, P, opts.threads)
    C = batch_function(game, "agent_costs", opts.threads)(U, P)[0]
    status = demote_nonfinite(s.status, E[:, None], X, C)
    mark_nonfinite_stops(status, s.stop)
    return SolveResult(
        solver="lm",
        controls=U,
        states=X,
        energy=E,
        agent_costs=C,
        status=status,
        iterations=s.iters,
        energy_history=np.stack(s.hist),
        grad_norm=grad_inf_norm(s.lin.gradient),
        wall_time=wall,
        info={
            "damping": s.lam,
            "damping_history": np.stack(s.lam_hist),
            "stop": s.stop,
            "residual_cosine": cos,
            "options": opts,
        },
        equilibrium=potential_equilibrium(game.coupled),
    )


def _polish(game: PotentialGame, U, P, cand, opts) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``opts.polish`` Newton steps ``H du = -g`` (exact Hessian of ``E``) for the
    problems in ``cand``, batched over them. A step is taken only where ``H`` is positive
    definite (a minimum's neighbourhood), and kept only if it lowers ``|g|_inf`` without
    raising ``E`` beyond round-off (halved up to 5 times). Returns the controls and the
    problems whose gradient reached ``gtol`` (``(B,)``)."""
    idx = np.nonzero(cand)[0]
    hf = batch_function(game, "hessian", opts.threads)
    gf = batch_function(game, "gradient", opts.threads)
    ef = batch_function(game, "energy", opts.threads)
    Ui, Pi = U[idx].copy(), P[idx]
    g = gf(Ui, Pi)[0]
    e = ef(Ui, Pi)[0][:, 0]
    gn = np.max(np.abs(g), axis=1)
    live = gn > opts.gtol
    for _ in range(opts.polish):
        if not live.any():
            break
        H = hf.dense(0, hf(Ui, Pi)[0])
        du = np.zeros_like(Ui)
        for b in np.nonzero(live)[0]:  # only the few flagged problems, a few steps each
            try:
                L = np.linalg.cholesky(H[b])
            except np.linalg.LinAlgError:
                live[b] = False  # not a minimum's neighbourhood: leave it as it is
                continue
            du[b] = -np.linalg.solve(L.T, np.linalg.solve(L, g[b]))
        alpha = np.ones(len(idx))
        moved = np.zeros(len(idx), bool)
        for _ in range(6):
            todo = live & ~moved
            if not todo.any():
                break
            Ut = Ui + alpha[:, None] * du
            gt = gf(Ut, Pi)[0]
            et = ef(Ut, Pi)[0][:, 0]
            gtn = np.max(np.abs(gt), axis=1)
            ok = todo & np.isfinite(et) & (gtn < gn) & (et <= e + 1e-12 * (1 + np.abs(e)))
            Ui[ok], g[ok], e[ok], gn[ok] = Ut[ok], gt[ok], et[ok], gtn[ok]
            moved |= ok
            alpha = np.where(todo & ~ok, 0.5 * alpha, alpha)
        live &= moved & (gn > opts.gtol)
    U = U.copy()
    U[idx] = Ui
    done = np.zeros(U.shape[0], bool)
    done[idx] = gn <= opts.gtol
    return U, done


def residual_cosine(lin, backend=None) -> np.ndarray:
    """Scale-free first-order measure ``max_j |(J'r)_j| / (||r|| ||J e_j||)``, ``(B,)``.

    The largest cosine between the residual and a column of ``J`` (MINPACK's ``gtol``
    test): 0 at a stationary point whatever the scale of the weights, about 1 where a
    control still pulls straight along the residual. Columns with ``J e_j = 0`` count 0.
    """
    g = np.abs(np.asarray(lin.gradient, dtype=float))
    B, n = g.shape
    if n == 0:
        return np.zeros(B)
    if hasattr(lin, "diag_jtj") and hasattr(lin, "backend"):  # structured: stage layout
        d = np.empty((B, n))
        d[:, lin.backend._u_index] = lin.diag_jtj().reshape(B, -1)
    else:
        d = np.einsum("bii->bi", lin.JtJ)
    rn = np.sqrt(np.einsum("bi,bi->b", lin.r, lin.r))
    scale = np.sqrt(np.maximum(d, 0.0)) * rn[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(g > 0, g / scale, 0.0)
    c = np.where(np.isfinite(c), c, np.inf)  # a zero scale with a non-zero gradient
    return np.max(c, axis=1)


def _merge(old: Linearization, new: Linearization, keep: np.ndarray) -> Linearization:
    if keep.all():
        return new
    if hasattr(new, "select"):  # backends with their own (e.g. stage-wise) storage
        return new.select(old, ~keep)
    out = Linearization(
        new.r.copy(), new.J.copy(), new.energy.copy(), new.gradient.copy(), new.JtJ.copy()
    )
    for name in ("r", "J", "energy", "gradient", "JtJ"):
        getattr(out, name)[~keep] = getattr(old, name)[~keep]
    return out


def _rollout(game: PotentialGame, U, P, threads=None) -> np.ndarray:
    return batch_function(game, "rollout", threads)(U, P)[0]


def prepare_lm(game: PotentialGame, p, u0, o: LMOptions) -> None:
    """Build and evaluate once what a solve reuses (``epo compare``'s ``setup_s``): the
    backend's linearization and energy, the batched rollout and agent costs."""
    be = make_backend(game, o)
    U, P = game.check_inputs(u0, p)
    be.linearize(U, P)
    be.energy(U, P)
    batch_function(game, "rollout", o.threads)(U, P)
    batch_function(game, "agent_costs", o.threads)(U, P)
