"""The numeric core of the game layer (:class:`learning.layer.GameLayer`): numpy in, numpy out.

The CasADi functions of the backward pass (:func:`layer_functions`, built once per game),
the choice of the step VJP (one graph or stage-wise, :data:`STAGED_VJP_MIN_INSTRUCTIONS`),
which functions are compiled (:data:`MAX_COMPILED_INSTRUCTIONS`), and ``_Core``: the
options, Gauss-Newton backend and batched functions of one layer, with the input
validation, the forward solve (:func:`solvers.lm.solve_lm` or the unrolled steps) and the
vector-Jacobian products of both backward modes in float64. The mathematics is in the
docstring of :mod:`learning.layer`; this module imports no torch.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame
from solvers.batch import BatchFunction
from solvers.codegen import AUTO_O1_LIMIT
from solvers.fast_vjp import staged_step_vjp, staged_vjp_info
from solvers.lm import make_backend, solve_lm
from solvers.result import Status

__all__ = [
    "MAX_COMPILED_INSTRUCTIONS",
    "STAGED_VJP_MIN_INSTRUCTIONS",
    "STATUS_CODES",
    "layer_functions",
    "status_code",
]

#: Status of code ``c`` is ``STATUS_CODES[c]`` (0 converged, 1 max_iter, 2 nonfinite, ...).
STATUS_CODES: tuple[Status, ...] = tuple(Status)
_CODE = {s: i for i, s in enumerate(STATUS_CODES)}
_NONFINITE = _CODE[Status.NONFINITE]


def status_code(status: Status) -> int:
    """Integer code of a :class:`~solvers.result.Status` (index in :data:`STATUS_CODES`)."""
    return _CODE[status]


# --------------------------------------------------------------------------------------
# CasADi functions of the backward pass, built once per game
# --------------------------------------------------------------------------------------


def _build(game: PotentialGame, name: str) -> ca.Function:
    sym = game.symbols
    u, p, r, x, E = sym["u"], sym["p"], sym["r"], sym["x"], sym["E"]
    up = ca.vertcat(u, p)

    def split(g):
        g = ca.densify(g)
        return g[: game.n_u], g[game.n_u :]

    if name == "lm_step_vjp":
        du = ca.SX.sym("du", game.n_u)
        z = ca.SX.sym("z", game.n_u)
        a = ca.SX.sym("a", game.n_r)
        b = ca.SX.sym("b", game.n_r)
        Jz = ca.jtimes(r, u, z)
        Jdu = ca.jtimes(r, u, du)
        phi = ca.dot(a, Jz) + ca.dot(b, Jdu + r)
        g = ca.gradient(phi, up)
        g = ca.substitute(g, ca.vertcat(a, b), ca.vertcat(Jdu + r, Jz))
        gu, gp = split(g)
        return ca.Function(name, [u, p, du, z], [gu, gp], ["u", "p", "du", "z"], ["gu", "gp"])
    if name == "rollout_vjp":
        xbar = ca.SX.sym("xbar", game.n_x)
        gu, gp = split(ca.gradient(ca.dot(xbar, x), up))
        return ca.Function(name, [u, p, xbar], [gu, gp], ["u", "p", "xbar"], ["gu", "gp"])
    if name == "gradient_p_vjp":
        w = ca.SX.sym("w", game.n_u)
        gp = ca.densify(ca.gradient(ca.dot(w, ca.gradient(E, u)), p))
        return ca.Function(name, [u, p, w], [gp], ["u", "p", "w"], ["gp"])
    raise SpecError("function", f"unknown layer function {name!r}")


def layer_functions(game: PotentialGame, name: str) -> ca.Function:
    """The named CasADi function of the layer's backward pass (built once per game).

    ``lm_step_vjp(u, p, du, z) -> (gu, gp)``: gradient w.r.t. ``(u, p)`` of
    ``phi = a'J(u,p)z + b'(J(u,p)du + r(u,p))`` with ``a = J du + r`` and ``b = J z``
    held fixed (see the module docstring). ``rollout_vjp(u, p, xbar) -> (gu, gp)``:
    gradient of ``xbar'x(u, p)``. ``gradient_p_vjp(u, p, w) -> gp``: gradient w.r.t.
    ``p`` of ``w' grad_u E(u, p)`` (the cross term of the implicit mode).
    """
    return game.cached(("layer", name), lambda: _build(game, name))


# --------------------------------------------------------------------------------------
# The numeric core (numpy, float64)
# --------------------------------------------------------------------------------------
#: with ``compiled=True`` the layer's functions above this many CasADi instructions stay
#: interpreted (:attr:`GameLayer.interpreted` names them): ``bench/bench_layer.py --part
#: vjp`` compiles each game's step VJP and times it against the interpreter (the exiD
#: game's, 342k instructions at N = 4, K = 20, ran 1.6x faster compiled at -O0: 0.678
#: against 1.103 ms per problem and step), so a larger graph gains little for a compile
#: that grows with its size. Games with a stage structure use the stage-wise VJP instead (small functions)
MAX_COMPILED_INSTRUCTIONS = 150_000
#: with ``compiled=True`` and ``vjp="auto"`` the step VJP is staged when the one graph
#: (``lm_step_vjp``) has more SX instructions than this: the size from which
#: :func:`solvers.codegen.compile_functions` compiles it at ``-O0``, about as slow as the
#: interpreter (measured, ``bench/bench_layer.py --part vjp``: RPI N = 2, 28k: the one
#: graph 2.4x faster than staged; N = 4, 72k: staged 2.2x faster)
STAGED_VJP_MIN_INSTRUCTIONS = AUTO_O1_LIMIT


def _choose_vjp(game: PotentialGame, vjp: str, compiled: bool) -> str:
    """``"staged"`` or ``"monolithic"``: what ``vjp`` (:data:`VJP_MODES`) resolves to."""
    if vjp == "monolithic" or (vjp == "auto" and not compiled):
        return "monolithic"
    if staged_step_vjp(game) is not None:
        if vjp == "staged":
            return "staged"
        # auto: staged where the one graph would be compiled at -O0 or not at all; below,
        # the one graph at -O1 is faster (RPI, N = 2, K = 40: 0.010 against 0.024 ms per
        # problem and step; N = 4, 72k instructions at -O0: 0.136 against 0.061); stage
        # functions too large to compile stay monolithic
        big = layer_functions(game, "lm_step_vjp").n_instructions()
        fits = staged_vjp_info(game)["distinct_instructions"] <= MAX_COMPILED_INSTRUCTIONS
        return "staged" if big > STAGED_VJP_MIN_INSTRUCTIONS and fits else "monolithic"
    if vjp == "staged":
        raise SpecError(
            "vjp",
            f"no stage-wise VJP for this game ({staged_vjp_info(game)['reason']}); "
            "use vjp='monolithic' or 'auto'",
        )
    return "monolithic"


class _Core:
    """Options, backend and batched functions of one layer; numpy in, numpy out."""

    def __init__(
        self,
        game,
        options,
        backward,
        on_invalid,
        backend,
        compiled=False,
        cache_dir=None,
        vjp="auto",
    ):
        self.game = game
        self.options = options
        self.backward = backward
        self.on_invalid = on_invalid
        self.backend = backend if backend is not None else make_backend(game, options)
        self.interpreted: list[str] = []
        t = options.threads
        # the forward rollout stays interpreted so that outputs equal solve_lm's bit for bit
        self.rollout = BatchFunction(game.function("rollout"), t)
        self.vjp_mode = _choose_vjp(game, vjp, compiled) if backward == "unrolled" else None
        step = "lm_step_vjp_staged" if self.vjp_mode == "staged" else "lm_step_vjp"
        names = ["rollout_vjp"] + ([step] if backward == "unrolled" else ["gradient_p_vjp"])
        fns = {
            n: staged_step_vjp(game) if n == "lm_step_vjp_staged" else layer_functions(game, n)
            for n in names
        }
        if backward == "implicit":
            fns["hessian"] = game.function("hessian")
        if compiled:
            from solvers.codegen import compile_libraries

            # a monolithic VJP of a large game (e.g. 666k instructions for the left-turn
            # game, K = 60 with path terms) takes the compiler minutes and gigabytes: such
            # functions stay interpreted, the others are compiled. The staged VJP is a small
            # MX graph of stage functions (each compiled once): always compiled, in its own
            # library, in parallel with the others
            small = {
                n: f for n, f in fns.items() if f.n_instructions() <= MAX_COMPILED_INSTRUCTIONS
            }
            self.interpreted = sorted(set(fns) - set(small))
            tag = f"n{game.N}_k{game.K}"
            libs = []
            if set(small) - {"lm_step_vjp_staged"}:
                libs.append(
                    (
                        [f for n, f in small.items() if n != "lm_step_vjp_staged"],
                        f"epo_layer_{backward}_{tag}",
                    )
                )
            if "lm_step_vjp_staged" in small:
                libs.append(([small["lm_step_vjp_staged"]], f"epo_layer_vjp_staged_{tag}"))
            for lib in compile_libraries(libs, cache_dir) if libs else []:
                fns.update(lib)
        self.rollout_vjp = BatchFunction(fns["rollout_vjp"], t)
        if backward == "unrolled":
            self.step_vjp = BatchFunction(fns[step], t)
        else:
            self.hessian = BatchFunction(fns["hessian"], t)
            self.cross_vjp = BatchFunction(fns["gradient_p_vjp"], t)
        self.weight_idx = np.concatenate([game.params.group("w_own"), game.params.group("w_pair")])
        self.defaults = game.params.defaults()

    # ---- validation -------------------------------------------------------------------
    def validate(self, U: np.ndarray, P: np.ndarray, batch_shape: tuple) -> np.ndarray:
        """Valid-problem mask; raises :class:`SpecError` unless ``on_invalid == 'mask'``."""
        bad_p = ~np.isfinite(P)
        bad_u = ~np.isfinite(U)
        with np.errstate(invalid="ignore"):
            neg = np.zeros_like(bad_p)
            neg[:, self.weight_idx] = P[:, self.weight_idx] < 0
        invalid = bad_p.any(1) | bad_u.any(1) | neg.any(1)
        if self.on_invalid == "raise" and invalid.any():
            names = self.game.params.names

            def where(mask):
                b = int(np.flatnonzero(mask.any(1))[0])
                idx = np.unravel_index(b, batch_shape) if batch_shape else ()
                return tuple(int(i) for i in idx), sorted(
                    {names[j] for j in np.flatnonzero(mask[b])}
                )

            if bad_p.any():
                i, ent = where(bad_p)
                raise SpecError(
                    "p",
                    f"NaN or inf in {ent} of problem {i} (pass on_invalid='mask' to mask such problems)",
                )
            if neg.any():
                i, ent = where(neg)
                raise SpecError(
                    "p", f"negative weight(s) {ent} in problem {i}; weights must be >= 0"
                )
            b = int(np.flatnonzero(bad_u.any(1))[0])
            i = tuple(int(v) for v in np.unravel_index(b, batch_shape)) if batch_shape else ()
            raise SpecError(
                "u_init",
                f"NaN or inf in problem {i} (entries {np.flatnonzero(bad_u[b])[:8].tolist()})",
            )
        return ~invalid

    # ---- forward ------------------------------------------------------------------------
    def forward(self, U0: np.ndarray, P: np.ndarray):
        if self.backward == "implicit":
            res = solve_lm(self.game, P, U0, self.options, backend=self.backend)
            status = np.array([_CODE[s] for s in np.ravel(res.status)], dtype=np.int64)
            return res.controls, res.states, status, {"U": res.controls}
        return self._unrolled(U0, P)

    def _unrolled(self, U0: np.ndarray, P: np.ndarray):
        """``solve_lm`` with fixed damping, recording what the backward pass needs."""
        opts, be = self.options, self.backend
        B = U0.shape[0]
        U = np.array(U0, dtype=float)
        lam = np.full(B, float(opts.damping))
        active = np.ones(B, dtype=bool)
        status = np.full(B, _CODE[Status.MAX_ITER], dtype=np.int64)
        lin = be.linearize(U, P)
        E = lin.energy.copy()
        bad = ~np.isfinite(E) | ~np.all(np.isfinite(lin.gradient), axis=1)
        status[bad], active[bad] = _NONFINITE, False

        def grad_small(lin_):
            if opts.gtol <= 0:
                return np.zeros(B, bool)
            return np.max(np.abs(lin_.gradient), axis=1) <= opts.gtol

        done = grad_small(lin) & active
        status[done], active[done] = _CODE[Status.CONVERGED], False
        tape = []
        for s in range(opts.steps):
            if not active.any():
                break
            du = be.solve(lin, lam, -lin.gradient, False)
            U_try = U + opts.step_size * du
            finite = np.all(np.isfinite(U_try), axis=1)
            U_try[~finite] = U[~finite]
            accept = active & finite
            U_prev = U.copy()
            U[accept] = U_try[accept]
            last = s == opts.steps - 1
            if last and opts.gtol <= 0:  # no later step needs J: the energy is enough
                new_lin, E_new = None, be.energy(U, P)
            else:
                new_lin = be.linearize(U, P)
                E_new = new_lin.energy
            nonfinite = active & (~finite | ~np.isfinite(E_new))
            if nonfinite.any():
                U[nonfinite] = U_prev[nonfinite]
                status[nonfinite], active[nonfinite] = _NONFINITE, False
            tape.append((U_prev, du, lin, accept & ~nonfinite))
            decrease = E - E_new
            keep = ~nonfinite
            E = np.where(keep, E_new, E)
            if new_lin is not None:
                lin = _merge(lin, new_lin, keep)
            small = np.zeros(B, bool)
            if opts.ftol > 0:
                small = accept & (np.abs(decrease) <= opts.ftol * (1 + np.abs(E)))
            conv = active & (grad_small(lin) | small) if new_lin is not None else active & small
            status[conv], active[conv] = _CODE[Status.CONVERGED], False
        X = self.rollout(U, P)[0]
        return U, X, status, {"U": U, "tape": tape, "lam": lam}

    # ---- backward -----------------------------------------------------------------------
    def vjp(self, saved: dict, P: np.ndarray, gU: np.ndarray, gX: np.ndarray | None):
        """Cotangents of ``(p, u_init)`` from those of ``(controls, states)``."""
        U = saved["U"]
        ubar = gU.copy()
        pbar = np.zeros_like(P)
        if gX is not None:
            gu, gp = self.rollout_vjp(U, P, gX)
            ubar += gu
            pbar += gp
        if self.backward == "implicit":
            H = self.hessian.dense(0, self.hessian(U, P)[0])
            w = _sym_solve(H, ubar)
            pbar -= self.cross_vjp(U, P, w)[0]
            return pbar, np.zeros_like(U)
        alpha = self.options.step_size
        for U_s, du, lin, moved in reversed(saved["tape"]):
            if not moved.any():
                continue
            v = np.where(moved[:, None], alpha * ubar, 0.0)
            z = self.backend.solve(lin, saved["lam"], v, False)
            gu, gp = self.step_vjp(U_s, P, du, z)
            ubar = ubar - np.where(moved[:, None], gu, 0.0)
            pbar = pbar - np.where(moved[:, None], gp, 0.0)
        return pbar, ubar


def _merge(old, new, keep):
    """``new`` where ``keep``, else ``old`` (as ``solvers.lm._merge``), for any backend."""
    if keep.all():
        return new
    if hasattr(old, "select"):  # backends with their own linearization type
        return old.select(new, keep)
    out = type(new)(**{k: np.array(v, copy=True) for k, v in vars(new).items()})
    for name in ("r", "J", "energy", "gradient", "JtJ"):
        getattr(out, name)[~keep] = getattr(old, name)[~keep]
    return out


def _sym_solve(H: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Batched ``H^{-1} rhs``; the pseudo-inverse where ``H`` is singular.

    A control whose row of ``H`` is exactly zero (no residual depends on it: a padded
    agent's, whose weights are all zero) is decoupled from the others: the solve puts a
    unit diagonal there and a zero right-hand side, so its component is 0 and the rest is
    ``H_rest^{-1} rhs_rest``, the pseudo-inverse's answer, without making the whole system
    singular."""
    free = ~np.any(H != 0, axis=-1)  # (B, n): an exactly zero row (and column: H = H')
    if free.any():
        H = H.copy()
        b, i = np.nonzero(free)
        H[b, i, i] = 1.0
        rhs = np.where(free, 0.0, rhs)
    try:
        w = np.linalg.solve(H, rhs[..., None])[..., 0]
        if np.all(np.isfinite(w)):
            return w
    except np.linalg.LinAlgError:
        pass
    return np.einsum("bij,bj->bi", np.linalg.pinv(H, hermitian=True), rhs)
