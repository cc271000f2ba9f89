"""Solver comparison studies: games x solvers x initial strategies -> one table.

:func:`run_comparison` solves every game (a :class:`~epo_casadi.game.PotentialGame` with its
parameters ``p``) with every solver choice (a name of the solver table
:data:`solvers.registry.SOLVERS`, with options) from every initial strategy, checks each
solution with the equilibrium test of its solver
(:meth:`solvers.registry.SolverEntry.check`), and returns a :class:`Comparison`: one
:class:`Row` per (game, solver, init), written as Markdown (:meth:`Comparison.markdown`)
or CSV (:meth:`Comparison.csv`), and the energy histories for the figures
(:func:`plot_gaps`).

Time, one definition for every solver (columns ``setup_s`` and ``solve_s``)
    * ``setup_s``: building what the solver needs for this game and option structure, on a
      fresh copy of the game (its own symbolic build is not counted; every derived
      function, NLP, backend and QP is), and one first evaluation of it: LM: the
      Gauss-Newton backend and batched functions, one linearization; IPOPT: the NLP
      (``casadi.nlpsol``) and its helper functions; iLQ: the solver's CasADi functions
      (and the generated C with ``compiled=True``); SQP: the QP's CasADi functions, one
      linearization and the OSQP set-up (each solver's ``prepare`` in the table; a
      registered solver without one builds nothing ahead). Measured once per (game,
      solver) and repeated in that pair's rows.
    * ``solve_s``: the solve call afterwards (the solver's own ``wall_time``), which reuses
      what the set-up built. The equilibrium check is timed apart (``check_s``).

Equilibrium check per solver (column ``check``)
    * ``open-loop`` for LM, IPOPT and SQP (solvers registered with that equilibrium): the
      local open-loop Nash certificate (:func:`solvers.nash.nash_certificate`);
      ``player_gain`` is the largest best-response gap. It is the soft-penalty game's
      test: a solution on a hard bound or hard collision constraint (IPOPT/SQP with
      bounds) is expected to fail it.
    * ``feedback`` for iLQ (solvers registered with that equilibrium): the sampled
      feedback Nash check (:func:`solvers.feedback_nash.feedback_nash_check`);
      ``player_gain`` is the largest own-cost decrease a player's policy deviation found.
    * ``none`` when the solve has no usable iterate (``nonfinite``, ``infeasible``,
      ``failed``) or checks are turned off.

    Both are local by default. Column ``verdict``: ``passes``, ``fails`` (an improvement
    found, or violated stationarity) or ``unknown`` (a best response that did not finish
    and showed no gap), with ``check_note`` saying why for the agents that do not pass;
    ``check_ok`` is "every agent passes" (``False`` for ``unknown`` too).

What the point is (column ``equilibrium``)
    The result's :class:`solvers.result.Equilibrium`: ``open-loop Nash``, ``feedback
    Nash``, or ``potential minimum (coupled dynamics: not a Nash equilibrium)`` for LM,
    IPOPT and SQP on a game with coupled dynamics, whose status may still be
    ``converged`` (the potential's first-order tolerance holds).

Energy gap
    ``gap = E - E_best`` with ``E_best`` the lowest finite energy of the game's rows with a
    usable status (``converged`` or ``max_iter``); rows of another status get a gap too
    when their energy is finite. A failed solve is a row with its status and message,
    never an exception.
"""

from __future__ import annotations

import csv
import io
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from epo_casadi.errors import SpecError, short_repr
from epo_casadi.game import PotentialGame

from .registry import SOLVERS
from .result import Status, fmt_number

__all__ = [
    "COLUMNS",
    "SolverChoice",
    "InitChoice",
    "Row",
    "Comparison",
    "parse_solver",
    "parse_init",
    "run_comparison",
    "plot_gaps",
    "setup_solver",
    "solve_with",
    "ScalingRow",
    "scaling_study",
    "fit_slopes",
    "plot_scaling",
]


@dataclass(frozen=True)
class SolverChoice:
    """A registered solver's name and its options (validated: unknown keys and bad values
    raise :class:`SpecError` naming the field). ``label`` names the choice in tables."""

    name: str
    options: dict = field(default_factory=dict, hash=False, compare=False)
    label: str = ""

    def __post_init__(self):
        entry = SOLVERS.entry(self.name, "solver")
        object.__setattr__(self, "_entry", entry)
        object.__setattr__(self, "_opts", entry.make_options(dict(self.options), self.name))
        if not self.label:
            tail = ",".join(f"{k}={v}" for k, v in self.options.items())
            object.__setattr__(self, "label", f"{self.name}:{tail}" if tail else self.name)

    @property
    def options_object(self):
        """The validated options dataclass."""
        return self._opts

    @property
    def entry(self):
        """The solver's :class:`~solvers.registry.SolverEntry`."""
        return self._entry


def _split_top(text: str, sep: str = ",") -> list[str]:
    """``text`` split at ``sep`` outside brackets and braces."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch in "[{(":
            depth += 1
        elif ch in "]})":
            depth -= 1
        if ch == sep and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    out.append(cur)
    return [s for s in (x.strip() for x in out) if s]


def parse_solver(text: str) -> SolverChoice:
    """``"lm"``, ``"ipopt:max_iter=200,tol=1e-6"``, ``"sqp:collision=true"``: the name,
    then ``key=value`` pairs, each value read by :func:`epo_casadi.settings.parse_value`
    (the reader of every ``KEY=VALUE``: numbers, ``true``/``false``/``none``, lists,
    mappings such as ``{a0: [[-1, -1], [1, 1]]}``, else the text)."""
    from epo_casadi.settings import parse_value

    if not isinstance(text, str) or not text.strip():
        raise SpecError("--solver", f"expected NAME or NAME:key=value,..., got {text!r}")
    name, _, rest = text.strip().partition(":")
    SOLVERS.entry(name, "--solver")
    values = {}
    for item in _split_top(rest):
        key, eq, raw = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise SpecError(f"--solver {name}", f"expected key=value, got {short_repr(item)}")
        if key in values:
            raise SpecError(f"--solver {name}.{key}", "given twice")
        values[key] = parse_value(raw, f"--solver {name}.{key}")
    return SolverChoice(name, values, label=text.strip())


@dataclass(frozen=True)
class InitChoice:
    """An initial strategy: ``zero``, ``perturb`` (``scale`` times a seeded standard normal)
    or ``given`` (``controls``, e.g. read from a result file). ``label`` names it."""

    kind: str
    seed: int = 0
    scale: float = 0.1
    controls: np.ndarray | None = field(default=None, compare=False, hash=False)
    label: str = ""

    def __post_init__(self):
        if self.kind not in ("zero", "perturb", "given"):
            raise SpecError(
                "--init", f"expected zero, perturb:SEED[:SCALE] or file:PATH, got {self.kind!r}"
            )
        if not self.label:
            lab = {"zero": "zero", "perturb": f"perturb:{self.seed}:{self.scale:g}"}
            object.__setattr__(self, "label", lab.get(self.kind, "given"))

    def controls_for(self, game: PotentialGame) -> np.ndarray:
        if self.kind == "zero":
            return game.zero_controls()
        if self.kind == "perturb":
            return self.scale * np.random.default_rng(self.seed).standard_normal(game.n_u)
        u = np.asarray(self.controls, float).reshape(-1)
        if u.size != game.n_u:
            raise SpecError(
                f"--init {self.label}", f"expected {game.n_u} controls for this game, got {u.size}"
            )
        return u


def parse_init(text: str) -> InitChoice:
    """``zero`` or ``perturb:SEED[:SCALE]`` (``file:PATH`` is read by the command line)."""
    parts = text.strip().split(":")
    if parts == ["zero"]:
        return InitChoice("zero")
    if parts[0] == "perturb" and len(parts) in (2, 3):
        try:
            seed = int(parts[1])
            scale = float(parts[2]) if len(parts) == 3 else 0.1
        except ValueError:
            raise SpecError("--init", f"expected perturb:SEED[:SCALE], got {text!r}") from None
        if seed < 0 or not math.isfinite(scale) or scale <= 0:
            raise SpecError("--init", f"expected a seed >= 0 and a scale > 0, got {text!r}")
        return InitChoice("perturb", seed=seed, scale=scale, label=text.strip())
    raise SpecError("--init", f"expected zero, perturb:SEED[:SCALE] or file:PATH, got {text!r}")


#: the table's columns, in order (docs/compare.md describes each)
COLUMNS = (
    "game",
    "solver",
    "init",
    "status",
    "equilibrium",
    "energy",
    "gap",
    "iterations",
    "grad_norm",
    "setup_s",
    "solve_s",
    "check",
    "check_ok",
    "verdict",
    "player_gain",
    "check_s",
    "check_note",
    "message",
)


@dataclass
class Row:
    """One (game, solver, init) solve; fields as :data:`COLUMNS`."""

    game: str
    solver: str
    init: str
    status: str
    energy: float
    gap: float
    iterations: int
    grad_norm: float
    setup_s: float
    solve_s: float
    check: str
    check_ok: bool | None
    player_gain: float
    check_s: float
    message: str
    equilibrium: str = ""  #: the result's Equilibrium word ("" when the solver does not say)
    verdict: str = ""  #: passes / fails / unknown ("" without a check)
    check_note: str = ""  #: why agents fail or are unknown ("" when all pass)
    energy_history: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def cells(self) -> dict:
        return {c: getattr(self, c) for c in COLUMNS}


@dataclass
class Comparison:
    """The rows of a study; :meth:`markdown` and :meth:`csv` write the table."""

    rows: list[Row]

    def best_energy(self, game: str) -> float:
        e = [
            r.energy
            for r in self.rows
            if r.game == game and r.status in ("converged", "max_iter") and math.isfinite(r.energy)
        ]
        return min(e) if e else math.nan

    @property
    def games(self) -> list[str]:
        return list(dict.fromkeys(r.game for r in self.rows))

    def _fmt(self, c: str, v) -> str:
        if c == "check_ok":
            return "-" if v is None else ("yes" if v else "no")
        if c == "verdict":
            return {"": "-", "fails": "FAILS"}.get(v, v)
        if c in ("equilibrium", "check_note") and not v:
            return "-"
        if isinstance(v, float):
            if not math.isfinite(v):
                return "nan" if math.isnan(v) else str(v)
            spec = ".3f" if c.endswith("_s") else (".3g" if c != "energy" else ".8g")
            return fmt_number(v, spec)
        return str(v)

    def markdown(self, columns: Sequence[str] = COLUMNS) -> str:
        lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
        for r in self.rows:
            cells = r.cells()
            lines.append(
                "| " + " | ".join(self._fmt(c, cells[c]).replace("|", "/") for c in columns) + " |"
            )
        return "\n".join(lines) + "\n"

    def csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(COLUMNS)
        for r in self.rows:
            cells = r.cells()
            w.writerow(
                [
                    ""
                    if cells[c] is None
                    else (repr(float(cells[c])) if isinstance(cells[c], float) else cells[c])
                    for c in COLUMNS
                ]
            )
        return buf.getvalue()


# --------------------------------------------------------------------------------------
# one solver: set-up, solve, check
# --------------------------------------------------------------------------------------
def setup_solver(choice: SolverChoice, game: PotentialGame, p: np.ndarray, u0: np.ndarray) -> None:
    """Build (on ``game``'s cache) what ``choice`` needs, and evaluate it once: the
    ``setup_s`` of the module docstring (the solver's ``prepare``)."""
    prepare = choice.entry.prepare
    if prepare is not None:
        prepare(game, p, u0, choice.options_object)


def solve_with(choice: SolverChoice, game: PotentialGame, p: np.ndarray, u0: np.ndarray):
    """Solve one problem with ``choice`` (its entry function); the ``SolveResult``."""
    return choice.entry.solve(game, p, u0, choice.options_object)


def _check(choice: SolverChoice, game: PotentialGame, p: np.ndarray, res):
    """(check name, ok, largest player gain, seconds, verdict, note)."""
    c = choice.entry.check(game, p, res)
    detail = c.detail
    verdict = str(getattr(detail, "verdict", "passes" if c.ok else "fails"))
    return c.kind, c.ok, c.gain, c.seconds, verdict, _note(detail)


def _note(detail) -> str:
    """The reasons of the agents that do not pass, one phrase each (``""`` if all pass)."""
    reasons = getattr(detail, "reasons", ()) or ()
    names = getattr(detail, "agents", None) or [f"player {i}" for i in range(len(reasons))]
    verdicts = getattr(detail, "verdicts", ()) or ()
    parts = []
    for i, r in enumerate(reasons):
        if r:
            v = f"{verdicts[i]}: " if i < len(verdicts) else ""
            parts.append(f"{names[i]} {v}{r}")
    return "; ".join(parts)


def run_comparison(
    games: Sequence[tuple[str, PotentialGame, np.ndarray]],
    solvers: Sequence[SolverChoice],
    inits: Sequence[InitChoice] = (InitChoice("zero"),),
    check: bool = True,
    progress: bool | None = None,
) -> Comparison:
    """Solve every ``(name, game, p)`` with every solver choice from every init.

    Each (game, solver) pair gets a fresh copy of the game (so its set-up is measured
    from scratch, see the module docstring). ``progress``: a tqdm bar (``None``: only on
    a terminal). Solver exceptions become rows with status ``failed``.
    """
    from tqdm.auto import tqdm

    if not games or not solvers or not inits:
        raise SpecError("compare", "expected at least one game, one solver and one init")
    rows: list[Row] = []
    total = len(games) * len(solvers) * len(inits)
    bar = tqdm(
        total=total,
        desc="solving",
        unit="solve",
        disable=None if progress is None else not progress,
        leave=False,
    )
    for gname, game0, p in games:
        p = np.asarray(p, float)
        for choice in solvers:
            game = PotentialGame(game0.spec)  # fresh cache: the set-up is built in the timer
            u_first = inits[0].controls_for(game)
            setup_err = None
            t0 = time.perf_counter()
            try:
                setup_solver(choice, game, p, u_first)
            except Exception as e:  # noqa: BLE001 - a failed set-up is a row, not a crash
                setup_err = f"set-up failed: {type(e).__name__}: {e}".splitlines()[0]
            setup_s = time.perf_counter() - t0
            for init in inits:
                bar.set_postfix_str(f"{gname} {choice.label} {init.label}")
                rows.append(_one_row(gname, game, p, choice, init, setup_s, setup_err, check))
                bar.update(1)
    bar.close()
    comp = Comparison(rows)
    for g in comp.games:
        best = comp.best_energy(g)
        for r in comp.rows:
            if r.game == g:
                r.gap = r.energy - best if math.isfinite(r.energy) else math.nan
    return comp


def _failed_row(base: dict, message: str) -> Row:
    """The row of a solver that could not be built or raised: status failed, no numbers."""
    return Row(
        **base,
        status=Status.FAILED.value,
        energy=math.nan,
        gap=math.nan,
        iterations=0,
        grad_norm=math.nan,
        solve_s=0.0,
        check="none",
        check_ok=None,
        player_gain=math.nan,
        check_s=0.0,
        message=message,
    )


def _one_row(gname, game, p, choice, init, setup_s, setup_err, check) -> Row:
    base = dict(game=gname, solver=choice.label, init=init.label, setup_s=setup_s)
    if setup_err is not None:
        return _failed_row(base, setup_err)
    u0 = init.controls_for(game)
    try:
        res = solve_with(choice, game, p, u0)
    except Exception as e:  # noqa: BLE001 - a failed solve is a row, not a crash
        msg = f"{type(e).__name__}: {e}".splitlines()[0]
        return _failed_row(base, msg)
    st = res.status
    name, ok, gain, cs, verdict, note = "none", None, math.nan, 0.0, "", ""
    if check and st in (Status.CONVERGED, Status.MAX_ITER, Status.STALLED):
        try:
            name, ok, gain, cs, verdict, note = _check(choice, game, p, res)
        except Exception as e:  # noqa: BLE001
            name, ok = f"error: {type(e).__name__}", False
            verdict, note = "unknown", f"the check raised {type(e).__name__}: {e}".splitlines()[0]
    return Row(
        **base,
        status=st.value,
        energy=float(res.energy),
        gap=math.nan,
        iterations=int(res.iterations),
        grad_norm=float(res.grad_norm),
        solve_s=float(res.wall_time),
        check=name,
        check_ok=ok,
        player_gain=gain,
        check_s=cs,
        message=_message(res),
        equilibrium=str(getattr(res, "equilibrium", None) or ""),
        verdict=verdict,
        check_note=note,
        energy_history=np.asarray(res.energy_history, float).reshape(-1),
    )


def _message(res) -> str:
    info = res.info
    for key in ("stop", "return_status"):
        if key in info:
            v = info[key]
            return str(v.item() if isinstance(v, np.ndarray) and v.ndim == 0 else v)
    if "stationarity" in info:
        return f"max|a| {fmt_number(info['stationarity'], '.2g')}"
    return ""


# --------------------------------------------------------------------------------------
# figures (matplotlib imported on use)
# --------------------------------------------------------------------------------------
def plot_gaps(comp: Comparison, game: str):
    """Figure of ``E - E_best`` against iterations and against solve time for ``game``.

    Solvers do not time their iterations: iteration ``i`` of ``S`` is drawn at
    ``i / S * solve_s``. Gaps are clipped at 1e-12 for the log scale.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    best = comp.best_energy(game)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    for r in comp.rows:
        if r.game != game or r.energy_history.size == 0 or not math.isfinite(best):
            continue
        gap = np.maximum(r.energy_history - best, 1e-12)
        it = np.arange(gap.size)
        t = it / max(gap.size - 1, 1) * r.solve_s
        lab = f"{r.solver} ({r.init}): {r.status}"
        ax1.semilogy(it, gap, marker=".", label=lab)
        ax2.semilogy(t, gap, marker=".", label=lab)
    ax1.set_xlabel("iteration")
    ax2.set_xlabel("solve time (s)")
    for ax in (ax1, ax2):
        ax.set_ylabel("E - E_best")
        ax.grid(True, which="both", alpha=0.3)
    ax1.legend(fontsize=7)
    fig.suptitle(f"{game}: energy gap (E_best = {fmt_number(best, '.8g')})")
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------------------
# scaling study
# --------------------------------------------------------------------------------------
@dataclass
class ScalingRow:
    """One solve of the scaling study."""

    solver: str
    N: int
    K: int
    n_u: int
    status: str
    iterations: int
    setup_s: float
    solve_s: float

    @staticmethod
    def header() -> list[str]:
        return [f.name for f in fields(ScalingRow)]


def scaling_study(
    make_game: Callable[[int, int], tuple[PotentialGame, np.ndarray]],
    solvers: Sequence[SolverChoice],
    Ns: Sequence[int] = (2, 4, 8),
    Ks: Sequence[int] = (20, 50, 100, 200),
    K_fixed: int = 40,
    N_fixed: int = 2,
    progress: bool | None = None,
) -> list[ScalingRow]:
    """Time per solve against ``N`` (at ``K_fixed``) and against ``K`` (at ``N_fixed``).

    ``make_game(N, K) -> (game, p)``; every solve starts from zero controls. Set-up and
    solve are timed as in :func:`run_comparison`.
    """
    from tqdm.auto import tqdm

    sizes = [(n, K_fixed) for n in Ns] + [
        (N_fixed, k) for k in Ks if (N_fixed, k) not in [(n, K_fixed) for n in Ns]
    ]
    out = []
    bar = tqdm(
        total=len(sizes) * len(solvers),
        desc="scaling",
        disable=None if progress is None else not progress,
        leave=False,
    )
    for N, K in sizes:
        game0, p = make_game(N, K)
        for choice in solvers:
            game = PotentialGame(game0.spec)
            u0 = game.zero_controls()
            t0 = time.perf_counter()
            try:
                setup_solver(choice, game, p, u0)
                setup_s = time.perf_counter() - t0
                res = solve_with(choice, game, p, u0)
                st, it, ts = res.status.value, int(res.iterations), float(res.wall_time)
            except Exception as e:  # noqa: BLE001
                setup_s = time.perf_counter() - t0
                st, it, ts = f"failed: {type(e).__name__}", 0, math.nan
            out.append(ScalingRow(choice.label, N, K, game.n_u, st, it, setup_s, ts))
            bar.update(1)
    bar.close()
    return out


def fit_slopes(rows: Sequence[ScalingRow], axis: str, fixed: int) -> dict[str, float]:
    """Least-squares slope of ``log(solve_s)`` against ``log(N)`` (``axis='N'``, rows with
    ``K == fixed``) or ``log(K)`` (``axis='K'``, ``N == fixed``), per solver (finite times
    of usable solves only; NaN with fewer than two points)."""
    out = {}
    for s in dict.fromkeys(r.solver for r in rows):
        pts = [
            (getattr(r, axis), r.solve_s)
            for r in rows
            if r.solver == s
            and getattr(r, "K" if axis == "N" else "N") == fixed
            and r.status in ("converged", "max_iter")
            and math.isfinite(r.solve_s)
            and r.solve_s > 0
        ]
        if len(pts) < 2:
            out[s] = math.nan
            continue
        x, y = np.log([a for a, _ in pts]), np.log([b for _, b in pts])
        out[s] = float(np.polyfit(x, y, 1)[0])
    return out


def plot_scaling(rows: Sequence[ScalingRow], K_fixed: int, N_fixed: int):
    """Log-log figure: solve time against N and against K, with fitted slopes."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, axis, fixed in ((axes[0], "N", K_fixed), (axes[1], "K", N_fixed)):
        slopes = fit_slopes(rows, axis, fixed)
        other = "K" if axis == "N" else "N"
        for s, slope in slopes.items():
            pts = sorted(
                (getattr(r, axis), r.solve_s, r.status)
                for r in rows
                if r.solver == s and getattr(r, other) == fixed and math.isfinite(r.solve_s)
            )
            if not pts:
                continue
            x = [a for a, _, _ in pts]
            y = [b for _, b, _ in pts]
            (line,) = ax.loglog(x, y, marker="o", label=f"{s} (slope {slope:.2f})")
            bad = [(a, b) for a, b, st in pts if st not in ("converged", "max_iter")]
            if bad:
                ax.loglog(*zip(*bad, strict=True), "x", color=line.get_color(), ms=10)
        ticks = sorted({getattr(r, axis) for r in rows if getattr(r, other) == fixed})
        if ticks:
            ax.set_xticks(ticks)
            ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel(axis)
        ax.set_ylabel("solve time (s)")
        ax.set_title(f"time per solve vs {axis} ({other} = {fixed}); x: not converged")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
