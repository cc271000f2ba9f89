"""IPOPT on the potential ``E(u, p) = 1/2 ||r(u, p)||^2`` (reference solver).

A second, independent way to minimize the potential of a :class:`~epo_casadi.game.PotentialGame`
(the other is :func:`solvers.lm.solve_lm`): an interior-point method on the NLP ::

    min_u  E(u, p)
    s.t.   lower_i <= u_{i,k}   <= upper_i        (control_bounds, hard, every k = 0..K-1)
           lower_i <= x_{i,k}   <= upper_i        (state_bounds, hard, every k = 1..K)

with the exact Hessian of the Lagrangian (``hessian="exact"``) or the Gauss-Newton
matrix ``J'J`` of the objective plus the exact curvature of the state constraints
(``hessian="gn"``). The NLP is built once per game and :class:`IpoptOptions` by
:class:`IpoptSolver`; :func:`solve_ipopt` is the entry function and keeps one solver
per ``(game, options)``, cached on the game. The parameters ``p`` are the NLP parameter
``'p'``, so changing ``p`` never rebuilds anything. The expensive part of the set-up, the
symbolic Hessian of the Lagrangian (the Jacobian of the gradient), can also be kept on disk
for large games (``cache=True``), keyed by the game's structure (not its parameter values)
and checked on reading (docs/solvers.md, "Set-up"); ``info["setup_s"]`` reports the set-up
time. Shapes and index order follow
:mod:`epo_casadi.game`; IPOPT solves one problem at a time, a batch ``(B, n)`` is a
loop over its problems.

Without bounds the solution is a local minimizer of ``E`` and hence (paper Theorem C.1) a local
open-loop Nash equilibrium when each agent's dynamics depend on its own controls only; check
it with :func:`solvers.nash.nash_certificate`. With coupled dynamics (``game.coupled``) the
result's ``equilibrium`` says ``potential minimum (coupled dynamics: not a Nash
equilibrium)`` (:class:`solvers.result.Equilibrium`).
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import sys
import tempfile
import time
import warnings
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from epo_casadi.errors import SpecError, check_number, short_repr
from epo_casadi.game import PotentialGame

from .batch import BatchFunction
from .codegen import cache_dir
from .lm import MAX_STEPS, check_options
from .result import (
    SolveResult,
    Status,
    demote_nonfinite,
    grad_inf_norm,
    padded_histories,
    potential_equilibrium,
)

__all__ = ["IpoptOptions", "IpoptSolver", "solve_ipopt", "ipopt_status"]

Bounds = tuple[tuple[str, tuple[float, ...], tuple[float, ...]], ...]

# Only IPOPT's own first-order stops are CONVERGED: "Solved_To_Acceptable_Level" means the
# (looser) acceptable_tol held for acceptable_iter iterations in a row. A search direction
# too small to move the iterate is a stall, like LM's damping cap; everything else
# (restoration failure, diverging iterates, errors) is FAILED.
_STATUS = {
    "Solve_Succeeded": Status.CONVERGED,
    "Solved_To_Acceptable_Level": Status.CONVERGED,
    "Maximum_Iterations_Exceeded": Status.MAX_ITER,
    "Infeasible_Problem_Detected": Status.INFEASIBLE,
    "Invalid_Number_Detected": Status.NONFINITE,
    "Search_Direction_Becomes_Too_Small": Status.STALLED,
}


def ipopt_status(return_status: str) -> Status:
    """:class:`Status` of an IPOPT ``return_status`` string (unknown strings: ``FAILED``)."""
    return _STATUS.get(return_status, Status.FAILED)


def _bound_value(v, where: str, default: float) -> float:
    if v is None:
        return default
    if (
        isinstance(v, bool)
        or not isinstance(v, (int, float, np.floating, np.integer))
        or math.isnan(v)
    ):
        raise SpecError(where, f"expected a number, inf or None, got {short_repr(v)}")
    return float(v)


def agent_bounds(game: PotentialGame, bounds: Bounds | None, sizes, where: str):
    """``(agent index, lower, upper)`` of each entry of ``bounds`` (normalized by
    :func:`_normalize_bounds`), checked against the game: a known agent name and
    ``sizes[i]`` entries per list (``game.nu`` or ``game.nx``); ``where`` names the field
    in the errors."""
    names = game.agent_names
    for name, lo, hi in bounds or ():
        at = f"{where}[{name!r}]"
        if name not in names:
            raise SpecError(at, f"unknown agent; expected one of {names}")
        i = names.index(name)
        if len(lo) != sizes[i]:
            raise SpecError(
                at, f"expected {sizes[i]} entries per list for agent {name!r}, got {len(lo)}"
            )
        yield i, np.asarray(lo, float), np.asarray(hi, float)


def _normalize_bounds(value, where: str) -> Bounds | None:
    """``{agent: (lower, upper)}`` -> ``((agent, lower, upper), ...)`` sorted by name."""
    if value is None:
        return None
    if isinstance(value, tuple) and all(isinstance(e, tuple) and len(e) == 3 for e in value):
        value = {name: (lo, hi) for name, lo, hi in value}  # already normalized
    if not isinstance(value, Mapping):
        raise SpecError(
            where,
            f"expected a mapping agent name -> (lower list, upper list), got {type(value).__name__}",
        )
    out = []
    for name, pair in value.items():
        w = f"{where}[{name!r}]"
        if not isinstance(name, str):
            raise SpecError(where, f"expected agent names as keys, got {short_repr(name)}")
        if not isinstance(pair, Sequence) or isinstance(pair, str) or len(pair) != 2:
            raise SpecError(w, f"expected a pair (lower list, upper list), got {short_repr(pair)}")
        lo_in, hi_in = pair
        if (
            not isinstance(lo_in, Sequence)
            or not isinstance(hi_in, Sequence)
            or isinstance(lo_in, str)
            or isinstance(hi_in, str)
        ):
            raise SpecError(
                w,
                f"expected two lists of numbers (None or inf for no bound), got {short_repr(pair)}",
            )
        if len(lo_in) != len(hi_in):
            raise SpecError(
                w, f"lower and upper lists differ in length: {len(lo_in)} and {len(hi_in)}"
            )
        lo = tuple(_bound_value(v, f"{w}.lower[{c}]", -math.inf) for c, v in enumerate(lo_in))
        hi = tuple(_bound_value(v, f"{w}.upper[{c}]", math.inf) for c, v in enumerate(hi_in))
        for c, (a, b) in enumerate(zip(lo, hi, strict=True)):
            if not a <= b:
                raise SpecError(w, f"entry {c}: expected lower <= upper, got {a} > {b}")
        out.append((name, lo, hi))
    return tuple(sorted(out))


@dataclass(frozen=True)
class IpoptOptions:
    """IPOPT options (defaults: a tight unconstrained solve of the potential).

    ``control_bounds`` and ``state_bounds`` map an agent name to ``(lower, upper)``, two
    lists with one entry per control (``nu_i``) or state (``nx_i``) component in the order
    of :mod:`epo_casadi.dynamics`; ``None`` or ``inf`` means unbounded. They are stored
    normalized as a sorted tuple of ``(name, lower, upper)``. IPOPT keeps bounds up to its
    ``bound_relax_factor`` (about ``1e-8``).
    """

    max_iter: int = 500  #: maximum number of IPOPT iterations
    tol: float = 1e-8  #: IPOPT's (scaled) overall convergence tolerance
    acceptable_tol: float = 1e-6  #: tolerance of the "acceptable" stop
    acceptable_iter: int = 15  #: acceptable iterations in a row before stopping there (0 disables)
    print_level: int = 0  #: IPOPT output verbosity, 0 (silent) to 12
    hessian: str = (
        "exact"  #: "exact" (Hessian of the Lagrangian) or "gn" (J'J + constraint curvature)
    )
    control_bounds: Bounds | Mapping | None = None  #: hard bounds on u_{i,k}, per agent
    state_bounds: Bounds | Mapping | None = None  #: hard bounds on x_{i,k}, k = 1..K, per agent
    linear_solver: str = "mumps"  #: IPOPT linear solver (the CasADi wheel ships "mumps")
    #: keep large Hessians of the Lagrangian on disk (docs/solvers.md, "Set-up"); off by
    #: default: loading one takes as long as building it
    cache: bool = False
    #: when a solve ends in any status but 'converged', solve again along the collision
    #: weight (pair weights scaled up from 0.01, warm-started; solvers.continuation)
    continuation: bool = True

    def __post_init__(self):
        for name in ("max_iter", "acceptable_iter"):
            check_number(f"ipopt.{name}", getattr(self, name), lo=0, hi=MAX_STEPS, integer=True)
        for name in ("tol", "acceptable_tol"):
            check_number(f"ipopt.{name}", getattr(self, name), lo=0, lo_open=True)
        check_number("ipopt.print_level", self.print_level, lo=0, hi=12, integer=True)
        if self.hessian not in ("exact", "gn"):
            raise SpecError(
                "ipopt.hessian", f"expected 'exact' or 'gn', got {short_repr(self.hessian)}"
            )
        if not isinstance(self.continuation, bool):
            raise SpecError(
                "ipopt.continuation", f"expected true or false, got {short_repr(self.continuation)}"
            )
        if not isinstance(self.cache, bool):
            raise SpecError("ipopt.cache", f"expected true or false, got {short_repr(self.cache)}")
        if not isinstance(self.linear_solver, str) or not self.linear_solver:
            raise SpecError(
                "ipopt.linear_solver",
                f"expected a solver name, got {short_repr(self.linear_solver)}",
            )
        object.__setattr__(
            self, "control_bounds", _normalize_bounds(self.control_bounds, "ipopt.control_bounds")
        )
        object.__setattr__(
            self, "state_bounds", _normalize_bounds(self.state_bounds, "ipopt.state_bounds")
        )


class IpoptSolver:
    """The potential's NLP for one game and one :class:`IpoptOptions`, built once.

    ``solver.solve(p, u0)`` solves one problem or a batch (a loop); the NLP itself is the
    ``nlpsol`` attribute (a :class:`casadi.Function`), with parameter ``p`` = the game's
    parameter vector.
    """

    def __init__(self, game: PotentialGame, options: IpoptOptions | dict | None = None):
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        self.game = game
        t0, c0 = time.perf_counter(), time.process_time()
        self.options = opts = check_options(IpoptOptions, options, "ipopt")
        sym = game.symbols
        u, p, x, E = sym["u"], sym["p"], sym["x"], sym["E"]

        # control bounds -> lbx / ubx (K copies of the per-agent bounds)
        self.lbx = np.full(game.n_u, -np.inf)
        self.ubx = np.full(game.n_u, np.inf)
        for i, lo, hi in agent_bounds(game, opts.control_bounds, game.nu, "ipopt.control_bounds"):
            sl = slice(int(game.uoff[i]), int(game.uoff[i + 1]))
            self.lbx[sl] = np.tile(lo, game.K)
            self.ubx[sl] = np.tile(hi, game.K)

        # state bounds -> g = the bounded entries of the rolled-out states, k = 1..K
        rows, lbg, ubg = [], [], []
        for i, lo, hi in agent_bounds(game, opts.state_bounds, game.nx, "ipopt.state_bounds"):
            for k in range(1, game.K + 1):
                for c in range(game.nx[i]):
                    if np.isfinite(lo[c]) or np.isfinite(hi[c]):
                        rows.append(int(game.xoff[i]) + k * game.nx[i] + c)
                        lbg.append(lo[c])
                        ubg.append(hi[c])
        self.state_rows = np.asarray(rows, dtype=int)
        self.lbg = np.asarray(lbg, dtype=float)
        self.ubg = np.asarray(ubg, dtype=float)
        g = x[rows] if rows else ca.SX(0, 1)

        nlp_opts = {
            "print_time": False,
            "error_on_fail": False,
            "show_eval_warnings": opts.print_level > 0,
            "ipopt.print_level": opts.print_level,
            "ipopt.sb": "yes",
            "ipopt.max_iter": opts.max_iter,
            "ipopt.tol": opts.tol,
            "ipopt.acceptable_tol": opts.acceptable_tol,
            "ipopt.acceptable_iter": opts.acceptable_iter,
            "ipopt.linear_solver": opts.linear_solver,
        }
        self._g = g
        #: the Hessian of the Lagrangian handed to IPOPT (``triu``), built or loaded
        self.hess_lag, self.setup_source = _hessian_of_lagrangian(game, g, opts)
        nlp_opts["hess_lag"] = self.hess_lag
        self.nlpsol = ca.nlpsol("epo_ipopt", "ipopt", {"x": u, "p": p, "f": E, "g": g}, nlp_opts)
        self._rollout = BatchFunction(game.function("rollout"))
        self._costs = BatchFunction(game.function("agent_costs"))
        self._grad = BatchFunction(game.function("gradient"))
        self._energy = BatchFunction(game.function("energy"))
        #: set-up of this solver (Hessian of the Lagrangian, built or loaded, and the
        #: ``nlpsol``): wall and CPU seconds; ``setup_source`` says "built", "disk" or
        #: "rebuilt" (a cache file was unreadable or corrupted and was replaced)
        self.setup_s = time.perf_counter() - t0
        self.setup_cpu_s = time.process_time() - c0

    def _solve_one(self, u0: np.ndarray, p: np.ndarray) -> dict:
        try:
            sol = self.nlpsol(x0=u0, p=p, lbx=self.lbx, ubx=self.ubx, lbg=self.lbg, ubg=self.ubg)
            st = self.nlpsol.stats()
        except RuntimeError as e:  # evaluation error at the initial point etc.
            return {
                "u": u0.copy(),
                "return_status": f"Error: {e}".splitlines()[0],
                "iter": 0,
                "history": [],
                "lam_x": np.zeros_like(u0),
                "lam_g": np.zeros(self.lbg.size),
            }
        u = np.asarray(sol["x"], dtype=float).reshape(-1)
        hist = list(st.get("iterations", {}).get("obj", []))
        return {
            "u": u,
            "return_status": str(st.get("return_status", "unknown")),
            "iter": int(st.get("iter_count", 0)),
            "history": hist,
            "lam_x": np.asarray(sol["lam_x"], dtype=float).reshape(-1),
            "lam_g": np.asarray(sol["lam_g"], dtype=float).reshape(-1),
        }

    def solve(self, p: np.ndarray, u0: np.ndarray | None = None) -> SolveResult:
        """Solve for ``p`` (``(n_p,)`` or ``(B, n_p)``) from ``u0`` (zeros if None).

        ``energy_history`` holds IPOPT's objective at every iterate (the first entry is
        the start after IPOPT moved it inside the bounds); a shorter run repeats its
        final value. ``info``: ``return_status`` (IPOPT's string), ``lam_x`` and
        ``lam_g`` (bound and constraint multipliers), ``max_violation`` (largest bound
        or state-constraint violation at the solution), ``options``, ``setup_s`` (wall
        seconds this solver's construction took, paid once per game and options) and
        ``setup_source`` (``"built"``, ``"disk"`` or ``"rebuilt"``: the Hessian's origin).
        """
        game = self.game
        t0 = time.perf_counter()
        single = np.ndim(p) == 1 and (u0 is None or np.ndim(u0) == 1)
        U0, P = game.check_inputs(game.zero_controls() if u0 is None else u0, p)
        runs = [self._solve_one(U0[b], P[b]) for b in range(U0.shape[0])]
        U = np.stack([r["u"] for r in runs])
        X = self._rollout(U, P)[0]
        C = self._costs(U, P)[0]
        G = self._grad(U, P)[0]
        E = self._energy(U, P)[0][:, 0]
        status = np.empty(len(runs), dtype=object)
        for b, r in enumerate(runs):
            status[b] = ipopt_status(r["return_status"])
        status = demote_nonfinite(status, E[:, None], X, C, U)
        viol = (
            np.maximum(np.maximum(self.lbx - U, U - self.ubx), 0.0).max(axis=1)
            if game.n_u
            else np.zeros(len(runs))
        )
        if self.state_rows.size:
            xs = X[:, self.state_rows]
            viol = np.maximum(
                viol, np.maximum(np.maximum(self.lbg - xs, xs - self.ubg), 0.0).max(axis=1)
            )
        res = SolveResult(
            solver="ipopt",
            controls=U,
            states=X,
            energy=E,
            agent_costs=C,
            status=status,
            iterations=np.array([r["iter"] for r in runs], dtype=int),
            energy_history=padded_histories([r["history"] for r in runs], E),
            grad_norm=grad_inf_norm(G),
            wall_time=time.perf_counter() - t0,
            info={
                "return_status": np.array([r["return_status"] for r in runs], dtype=object),
                "lam_x": np.stack([r["lam_x"] for r in runs]),
                "lam_g": np.stack([r["lam_g"] for r in runs]),
                "max_violation": viol,
                "options": self.options,
                "setup_s": self.setup_s,
                "setup_source": self.setup_source,
            },
            equilibrium=potential_equilibrium(game.coupled),
        )
        return res[0] if single else res


# --------------------------------------------------------------------------------------
# the Hessian of the Lagrangian: built once per game structure, cached on disk
# --------------------------------------------------------------------------------------
#: a game's Hessian goes to the disk cache when ``n_u`` times the instruction count of its
#: energy function reaches this (about 0.3 s of symbolic build; smaller ones are rebuilt)
DISK_CACHE_MIN_WORK = 1_000_000
#: progress lines on a terminal (stderr) for builds at least this large (same measure)
PROGRESS_MIN_WORK = 1_000_000
_MAGIC = b"EPO-IPOPT-HESS 1\n"
#: how often this process built a Hessian of the Lagrangian, loaded one from the disk cache,
#: or replaced an unreadable cache file (for tests and diagnostics)
CACHE_STATS = {"built": 0, "disk": 0, "rebuilt": 0}


def _progress(message: str) -> None:
    if sys.stderr is not None and sys.stderr.isatty():
        print(message, file=sys.stderr, flush=True)


def _build_hessian(game: PotentialGame, g, hessian: str) -> ca.Function:
    """``triu`` of the Hessian of ``lam_f E + lam_g' g`` (``"exact"``), or of the
    Gauss-Newton ``lam_f J'J`` plus the constraints' exact curvature (``"gn"``)."""
    sym = game.symbols
    u, p = sym["u"], sym["p"]
    lam_f = ca.SX.sym("lam_f")
    lam_g = ca.SX.sym("lam_g", g.shape[0])
    if hessian == "gn":
        J = ca.jacobian(sym["r"], u)
        H = lam_f * ca.mtimes(J.T, J)
        if g.shape[0]:
            H = H + ca.hessian(ca.dot(lam_g, g), u)[0]
    else:
        # the Jacobian of the gradient (forward over reverse), not ca.hessian: the same
        # matrix to rounding, built 3.6x (N = 4) to 6x (N = 6) faster (docs/solvers.md)
        H = ca.jacobian(ca.gradient(lam_f * sym["E"] + ca.dot(lam_g, g), u), u)
    return ca.Function(
        f"epo_{hessian}_hess_lag",
        [u, p, lam_f, lam_g],
        [ca.triu(H)],
        ["x", "p", "lam_f", "lam_g"],
        ["triu_hess_gamma_x_x"],
    )


def _structure_key(game: PotentialGame, g, hessian: str) -> str:
    """Hash of everything the Hessian depends on: the game's symbolic graphs of ``r``,
    ``E`` and ``g`` in ``(u, p)`` (agents, dynamics, features, pairs, horizon, dt; not
    the parameter values, which are the symbol ``p``), the Hessian kind and CasADi."""
    sym = game.symbols
    f = ca.Function("epo_ipopt_nlp", [sym["u"], sym["p"]], [sym["r"], sym["E"], g])
    h = hashlib.sha256()
    for part in (_MAGIC.decode(), ca.__version__, hessian, f.serialize()):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()[:24]


def _load(path: Path, game: PotentialGame, n_g: int) -> ca.Function:
    """The Hessian stored at ``path``; ``ValueError`` if the file is not intact."""
    data = path.read_bytes()
    head, sep, rest = data.partition(b"\n")
    digest, sep2, payload = rest.partition(b"\n")
    if head + sep != _MAGIC or not sep2:
        raise ValueError("not an epo IPOPT cache file")
    if hashlib.sha256(payload).hexdigest().encode() != digest:
        raise ValueError("checksum mismatch")
    f = ca.Function.deserialize(zlib.decompress(payload).decode())
    shapes = [(game.n_u, 1), (game.n_p, 1), (1, 1), (n_g, 1)]
    if f.n_in() != 4 or [f.size_in(k) for k in range(4)] != shapes or f.n_out() != 1:
        raise ValueError("the stored function has another signature")
    if f.size_out(0) != (game.n_u, game.n_u):
        raise ValueError("the stored Hessian has another size")
    return f


def _save(path: Path, f: ca.Function) -> None:
    payload = zlib.compress(f.serialize().encode(), 1)
    digest = hashlib.sha256(payload).hexdigest().encode()
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}_")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(_MAGIC + digest + b"\n" + payload)
        os.replace(tmp, path)  # atomic: readers see no file or the whole file
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _hessian_of_lagrangian(game: PotentialGame, g, opts: IpoptOptions) -> tuple[ca.Function, str]:
    """The ``hess_lag`` function for ``nlpsol`` and where it came from ("built", "disk",
    "rebuilt"). Large ones are read from and written to the cache folder of
    :func:`solvers.codegen.cache_dir` as ``ipopt_hess_<kind>_n<N>_k<K>_<hash>.bin``."""
    work = game.n_u * game.function("energy").n_instructions()
    path = None
    source = "built"
    if opts.cache and work >= DISK_CACHE_MIN_WORK:
        key = _structure_key(game, g, opts.hessian)
        try:
            folder = cache_dir()
        except OSError as e:  # no usable cache folder: build, as with cache=False
            warnings.warn(f"no IPOPT cache folder ({e}); building the Hessian", stacklevel=4)
        else:
            path = folder / f"ipopt_hess_{opts.hessian}_n{game.N}_k{game.K}_{key}.bin"
        if path is not None and path.exists():
            try:
                f = _load(path, game, g.shape[0])
            except (ValueError, RuntimeError, OSError, zlib.error, UnicodeDecodeError) as e:
                warnings.warn(
                    f"IPOPT cache file {path} is unusable ({e}); rebuilding it", stacklevel=4
                )
                source = "rebuilt"
            else:
                CACHE_STATS["disk"] += 1
                return f, "disk"
    big = work >= PROGRESS_MIN_WORK
    if big:
        _progress(
            f"epo: building the IPOPT Hessian ({opts.hessian}) for {game.N} agents, "
            f"{game.n_u} controls ..."
        )
    t0 = time.perf_counter()
    f = _build_hessian(game, g, opts.hessian)
    CACHE_STATS[source] += 1
    if path is not None:
        try:
            _save(path, f)
        except OSError as e:  # a read-only cache folder costs a rebuild next time, no more
            warnings.warn(f"could not write the IPOPT cache file {path}: {e}", stacklevel=4)
            path = None
    if big:
        _progress(
            f"epo: IPOPT Hessian built in {time.perf_counter() - t0:.1f} s"
            + (f" (cached in {path.parent})" if path is not None else "")
        )
    return f, source


def _solver_for(game: PotentialGame, opts: IpoptOptions) -> IpoptSolver:
    return game.cached(("ipopt", opts), lambda: IpoptSolver(game, opts))


def solve_ipopt(
    game: PotentialGame,
    p: np.ndarray,
    u0: np.ndarray | None = None,
    options: IpoptOptions | dict | None = None,
) -> SolveResult:
    """Minimize the potential of ``game`` with IPOPT, for one problem or a batch.

    ``p``: ``(n_p,)`` or ``(B, n_p)``; ``u0``: ``(n_u,)`` or ``(B, n_u)`` (zeros if None),
    the warm start. ``options``: :class:`IpoptOptions` or a dict of its fields (unknown
    keys raise :class:`~epo_casadi.errors.SpecError`). The NLP is built on the first call
    for a ``(game, options)`` pair and reused afterwards. Status: ``Solve_Succeeded`` and
    ``Solved_To_Acceptable_Level`` -> ``CONVERGED``, ``Maximum_Iterations_Exceeded`` ->
    ``MAX_ITER``, ``Infeasible_Problem_Detected`` -> ``INFEASIBLE``,
    ``Invalid_Number_Detected`` -> ``NONFINITE``, ``Search_Direction_Becomes_Too_Small`` ->
    ``STALLED``, anything else -> ``FAILED``; a usable-looking status with NaN or inf in
    the energy, costs, states or controls becomes ``NONFINITE``. IPOPT's string is
    ``result.info["return_status"]``.
    """
    if not isinstance(game, PotentialGame):
        raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
    opts = check_options(IpoptOptions, options, "ipopt")
    return _solver_for(game, opts).solve(p, u0)
