"""``epo solve GAME.yaml``: solve a game file with a registered solver, certify, write JSON.

The result file (``--out``) is one JSON object, documented in
``docs/gamefiles.md``: per-agent ``states`` (``(K+1, nx_i)``) and ``controls``
(``(K, nu_i)``), ``energy``, ``agent_costs``, what the point is (``equilibrium``), the
local Nash ``certificate`` or the ``feedback_check``, ``status``, ``message``,
``iterations``, ``time_s``, the ``params`` used (by block) and the solver ``options``.
:func:`read_result` reads one back for a game (``epo inspect --at``).

``--solver`` names any solver of :data:`solvers.registry.SOLVERS` (``lm``, ``ipopt``,
``ilq``, ``sqp`` or a registered one: every solver ``epo compare`` runs). Each solve runs
the equilibrium check of its solver (:meth:`solvers.registry.SolverEntry.check`) unless
``--no-certificate``: the local open-loop Nash certificate (:mod:`solvers.nash`) for the
solvers that find an open-loop equilibrium, the sampled feedback Nash check
(:mod:`solvers.feedback_nash`) of the policy for ``--solver ilq`` (a feedback Nash
equilibrium, :mod:`solvers.ilq`; its first-order condition ``max |a| <= tol`` is
``feedback_residual`` in the file). Both are local checks; the verdict is ``passes``,
``fails`` or ``unknown`` (a best response that did not finish without showing a gap).
A potential solve of a game with coupled dynamics is a potential minimum, not a Nash
equilibrium: the summary and the file's ``equilibrium`` say so. ``--modes N`` runs the multi-modal solver
(:func:`solvers.multimodal.solve_multimodal`, a solver the table marks ``multimodal``:
``ilq``, ``lm`` or a registered one) from ``N`` seeded starts: the file describes the most
likely mode's solve and lists every mode (``modes``: share, energy, costs, passing sides,
member solves, states and controls); with no mode left (every solve dropped) the file
holds the first sample's solve and an empty list, and the exit status is 1.

Exit status of ``epo solve`` (also in ``docs/solvers.md``): 0 converged or stopped at the
iteration limit (``max_iter``), 3 stalled (the solver could make no further progress but the
iterate is not stationary), 1 no usable solution (``nonfinite``, ``infeasible``,
``failed``), 2 bad input or an output that cannot be written. The result file and the
figure are written (atomically) before a non-zero exit, whatever the status.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame
from scenarios.commands.options import allow_import_option
from scenarios.files import check_output_file, write_atomic
from solvers.lm import MAX_STEPS
from solvers.result import Status, fmt_number

RESULT_FORMAT = "epo-result/1"

__all__ = [
    "solve",
    "run_solve",
    "result_dict",
    "energy_history",
    "write_result",
    "read_result",
    "RESULT_FORMAT",
    "EXIT_FAILED",
    "EXIT_STALLED",
    "exit_code",
]

#: exit status of a solve without a usable solution (nonfinite, infeasible, failed)
EXIT_FAILED = 1
#: exit status of a stalled solve (no progress, first-order test fails)
EXIT_STALLED = 3


def exit_code(status: Status) -> int:
    """Exit status of ``epo solve`` for a solver status (0 converged or max_iter)."""
    if status is Status.STALLED:
        return EXIT_STALLED
    return 0 if status.ok else EXIT_FAILED


class SolveExit(click.ClickException):
    """A finished solve whose status is not usable: message on stderr, its own exit code."""

    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.exit_code = code


def _jsonable(v: Any) -> Any:
    """Plain JSON values; non-finite floats become ``None`` (strict JSON has no inf/NaN)."""
    if is_dataclass(v) and not isinstance(v, type):
        return _jsonable(asdict(v))
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, (np.bool_, bool)):
        return bool(v)
    if isinstance(v, (np.integer, int)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return v if math.isfinite(v) else None
    if hasattr(v, "value") and hasattr(v, "message"):  # solvers.result.Status
        return v.value
    return v


def run_solve(game: PotentialGame, p: np.ndarray, solver: str, options: Any, certify: bool = True):
    """Solve one problem with the registered ``solver`` (``"lm"``, ``"ipopt"``, ``"ilq"``,
    ``"sqp"``, ...); return ``(result, check)``: the equilibrium check of the solver's kind
    (a :class:`solvers.nash.NashCertificate` for open-loop solvers, a
    :class:`solvers.feedback_nash.FeedbackNashCheck` of the policy for feedback ones such as
    iLQ), or ``None`` with ``certify=False`` or NaN/inf in the solution."""
    from solvers.registry import SOLVERS

    entry = SOLVERS.entry(solver, "--solver")
    res = entry.solve(game, p, options=options)
    cert = None
    if certify and res.status is not Status.NONFINITE:  # no check of NaN/inf values
        if entry.equilibrium == "open-loop":
            from solvers.nash import nash_certificate

            cert = nash_certificate(game, p=p, u=res.controls)
        elif entry.equilibrium == "feedback" and "gains" in res.info:
            from solvers.feedback_nash import check_ilq_result

            cert = check_ilq_result(game, p, res)
    return res, cert


def result_dict(
    game: PotentialGame, p: np.ndarray, res, cert=None, source: str | None = None
) -> dict:
    """The JSON object of one solve (see the module docstring). ``cert``: the check
    :func:`run_solve` returns (open-loop certificate or feedback check) or ``None``."""
    names = game.agent_names
    kind = getattr(cert, "kind", None)
    X = game.split_states(res.states)
    U = game.split_controls(res.controls)
    blocks = game.params.unpack(np.asarray(p, dtype=float))
    return _jsonable(
        {
            "format": RESULT_FORMAT,
            "game": source,
            "solver": res.solver,
            "status": res.status,
            "equilibrium": getattr(res, "equilibrium", None),
            "ok": bool(res.ok),
            "message": res.message,
            "iterations": int(res.iterations),
            "time_s": float(res.wall_time),
            "energy": float(res.energy),
            "grad_norm": float(res.grad_norm),
            "horizon": game.K,
            "dt": game.dt,
            "agents": names,
            "agent_costs": {a: float(c) for a, c in zip(names, res.agent_costs, strict=True)},
            "state_names": {a.name: list(a.dynamics.state_names) for a in game.agents},
            "control_names": {a.name: list(a.dynamics.control_names) for a in game.agents},
            "states": {a: X[i] for i, a in enumerate(names)},
            "controls": {a: U[i] for i, a in enumerate(names)},
            "params": blocks,
            "energy_history": energy_history(res),
            "certificate": cert.to_dict() if kind == "open-loop" else None,
            "feedback_check": cert.to_dict() if kind == "feedback" else None,
            "stop": res.info.get("stop"),
            "feedback_residual": res.info.get("stationarity") if res.solver == "ilq" else None,
            "options": res.info.get("options"),
            "attempts": res.info.get("attempts"),  # the continuation fallback's solves
        }
    )


def modes_dict(game: PotentialGame, mm) -> list[dict]:
    """JSON-ready list of the modes of a :class:`solvers.multimodal.MultiModalResult`."""
    names = game.agent_names
    out = []
    for m in mm.modes:
        X = game.split_states(m.states)
        U = game.split_controls(m.controls)
        out.append(
            _jsonable(
                {
                    "share": float(m.share),
                    "energy": float(m.energy),
                    "agent_costs": {a: float(c) for a, c in zip(names, m.cost, strict=True)},
                    "passing": list(m.passing),
                    "medoid": int(m.medoid),
                    "members": [int(i) for i in m.members],
                    "states": {a: X[i] for i, a in enumerate(names)},
                    "controls": {a: U[i] for i, a in enumerate(names)},
                }
            )
        )
    return out


def energy_history(res) -> np.ndarray:
    """Energy before each iteration and at the end, without the padding after the stop."""
    h = np.asarray(res.energy_history, dtype=float).reshape(-1)
    n = int(res.iterations) + 1
    return h[:n] if h.size > n else h


def write_result(data: dict, path: str | Path) -> Path:
    """Write a result object as strict JSON, atomically (all or nothing).

    Non-finite floats become ``null`` (see :func:`result_dict`); a path that cannot be
    written raises :class:`epo_casadi.errors.OutputError` and leaves no file behind.
    """
    data = _jsonable(data)  # idempotent; makes any caller's NaN/inf strict JSON
    # one line per top-level key: readable, and far shorter than an indented dump
    body = ",\n".join(
        f" {json.dumps(k)}: {json.dumps(v, allow_nan=False)}" for k, v in data.items()
    )
    return write_atomic(path, "{\n" + body + "\n}\n")


def read_result(path: str | Path, game: PotentialGame) -> tuple[np.ndarray, np.ndarray]:
    """Controls ``u`` and parameters ``p`` of a result file written for ``game``.

    Raises :class:`SpecError` naming the entry when the file does not fit the game.
    """
    path = Path(path)
    where = path.name
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise SpecError(
            where, f"invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}"
        ) from None
    if not isinstance(data, dict) or data.get("format") != RESULT_FORMAT:
        raise SpecError(f"{where}.format", f"expected an 'epo solve' result ({RESULT_FORMAT!r})")
    if data.get("agents") != game.agent_names:
        raise SpecError(
            f"{where}.agents",
            f"expected the agents {game.agent_names} of the game, got {data.get('agents')}",
        )
    ctrl = data.get("controls")
    if not isinstance(ctrl, dict):
        raise SpecError(f"{where}.controls", "expected a mapping agent -> (K, nu) controls")
    parts = []
    for i, a in enumerate(game.agent_names):
        try:
            arr = np.asarray(ctrl.get(a), dtype=float)
        except (TypeError, ValueError):
            raise SpecError(
                f"{where}.controls.{a}", "expected a list of lists of numbers"
            ) from None
        if arr.shape != (game.K, game.nu[i]):
            raise SpecError(
                f"{where}.controls.{a}", f"expected shape ({game.K}, {game.nu[i]}), got {arr.shape}"
            )
        parts.append(arr)
    u = game.join_controls(parts)
    params = data.get("params")
    if not isinstance(params, dict):
        raise SpecError(f"{where}.params", "expected a mapping block name -> values")
    try:
        p = game.params.pack(params)
    except SpecError as e:
        raise SpecError(f"{where}.{e.field}", e.message) from None
    if not np.all(np.isfinite(u)):
        raise SpecError(f"{where}.controls", "contains NaN or inf")
    return u, p


def _largest(values) -> float | None:
    """Largest entry of a list that may hold ``None`` (non-finite in JSON); ``None`` then."""
    vals = list(values or [])
    if not vals or any(v is None for v in vals):
        return None
    return max(vals)


def summary_lines(game: PotentialGame, data: dict) -> list[str]:
    """The printed summary of a result object; total over every status (a non-finite
    value, ``null`` in the file, prints as ``none (non-finite)``)."""
    costs = ", ".join(f"{a} {fmt_number(c)}" for a, c in data["agent_costs"].items())
    lines = [
        f"{data['solver']}: {data['status']} ({data['message']})",
        f"  energy {fmt_number(data['energy'])} after {data['iterations']} iterations in "
        f"{fmt_number(data['time_s'], '.3g')} s; |grad|_inf {fmt_number(data['grad_norm'], '.3g')}",
        f"  agent costs: {costs}",
    ]
    eq = data.get("equilibrium")
    if eq:
        lines.append(f"  equilibrium: {eq}")
    att = data.get("attempts")
    if att:  # solvers.continuation: the first attempt did not converge
        kept = next((a for a in att if a.get("kept")), att[-1])
        lines.append(
            f"  continuation: first attempt {att[0]['status']} after {att[0]['iterations']} "
            f"iterations; {len(att) - 1} more solves along the collision weight; kept: "
            f"{kept['stage']} at weight scale {fmt_number(kept['weight_scale'], '.3g')} "
            f"({kept['status']})"
        )
    c = data.get("certificate")
    f = data.get("feedback_check")
    if c is not None:
        lines.append(
            f"  Nash certificate: {_verdict_word(c)} ({_scope(c, 'agent')}; max |dC_i/du_i| "
            f"{fmt_number(_largest(c['stationarity']), '.3g')}, max best-response gap "
            f"{fmt_number(_largest(c['best_response_gap']), '.3g')}"
            + (f"; {c['time_s']:.3g} s)" if c.get("time_s") is not None else ")")
        )
        lines += _reason_lines(c, data.get("agents") or [])
    elif f is None and data.get("status") == Status.NONFINITE.value:
        lines.append("  Nash certificate: not computed (NaN or inf in the solution)")
    if f is not None:
        lines.append(
            f"  feedback Nash check: {_verdict_word(f)} ({_scope(f, 'player')}, sampled "
            f"policy deviations; largest own-cost decrease {fmt_number(_largest(f['gain']), '.3g')}"
            + (f"; {f['time_s']:.3g} s)" if f.get("time_s") is not None else ")")
        )
        lines += _reason_lines(f, data.get("agents") or [])
    if data.get("solver") == "ilq":
        lines.append(
            f"  feedback Nash residual max |a| {fmt_number(data.get('feedback_residual'), '.3g')}"
            " (iLQ's first-order condition; the open-loop certificate does not apply to a "
            "feedback equilibrium)"
        )
    return lines


def _verdict_word(check: dict) -> str:
    """``passes`` / ``FAILS`` / ``unknown`` of a check in a result file (files without a
    verdict: from ``ok``)."""
    v = check.get("verdict") or ("passes" if check.get("ok") else "fails")
    return {"fails": "FAILS"}.get(v, v)


def _scope(check: dict, who: str) -> str:
    """``local`` or ``local + K global starts per agent`` of a check in a result file."""
    k = check.get("global_starts")
    if k is None:
        k = (check.get("options") or {}).get("global_starts") or 0
    return "local" if not k else f"local + {k} global start{'s' if k > 1 else ''} per {who}"


def _reason_lines(check: dict, agents: list) -> list[str]:
    """One line per agent that does not pass: its verdict and why."""
    out = []
    verdicts = check.get("verdicts") or []
    for i, r in enumerate(check.get("reasons") or []):
        if r:
            name = agents[i] if i < len(agents) else f"player {i}"
            v = verdicts[i] if i < len(verdicts) else ""
            out.append(f"    {name}: {v + ': ' if v else ''}{r}")
    return out


def mode_lines(game: PotentialGame, modes: list[dict], n_samples: int, statuses: str) -> list[str]:
    """Printed summary of the modes of a multi-modal solve; total over every case."""
    kept = sum(len(m["members"]) for m in modes)
    lines = [f"  {len(modes)} mode(s) from {kept}/{n_samples} kept solves (solves: {statuses})"]
    for i, m in enumerate(modes):
        costs = ", ".join(f"{a} {fmt_number(c, '.4g')}" for a, c in m["agent_costs"].items())
        lines.append(
            f"  mode {i}: share {fmt_number(m['share'], '.2f')}, energy "
            f"{fmt_number(m['energy'], '.6g')}, {len(m['members'])} solves, passing "
            f"{tuple(m['passing'])}; costs {costs}"
        )
    if not modes:
        lines.append("  no mode: every solve was dropped (not converged or colliding)")
    return lines


class SolverName(click.ParamType):
    """A name of the solver table (:data:`solvers.registry.SOLVERS`). It is checked when
    the command runs, after the game file is loaded (so a solver that a module the file
    imports registers is accepted); an unknown name is one error line listing the table."""

    name = "solver"

    def get_metavar(self, param, ctx=None) -> str:
        """``[lm|ipopt|...]``: the table as it is when the help is shown."""
        from solvers.registry import SOLVERS

        return "[" + "|".join(SOLVERS) + "]"

    def convert(self, value, param, ctx):
        """The name as text (the command looks it up in the table)."""
        return str(value)


@click.command("solve")
@click.argument("game_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--solver",
    type=SolverName(),
    default="lm",
    show_default=True,
    help="A registered solver: Levenberg-Marquardt, IPOPT, the iLQ feedback Nash solver, "
    "SQP, or your own (solvers.registry).",
)
@click.option(
    "--steps",
    type=click.IntRange(min=0, max=MAX_STEPS),
    default=None,
    help="Iteration limit (LM steps / the others' max_iter); overrides the file's solver options.",
)
@click.option(
    "--modes",
    type=click.IntRange(min=1, max=10_000),
    default=None,
    metavar="N",
    help="Multi-modal solve from N seeded starts (--solver ilq, lm or a registered one): "
    "print and plot the modes.",
)
@click.option(
    "--seed",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Seed of the sampled starts of --modes.",
)
@click.option(
    "--set",
    "settings",
    multiple=True,
    metavar="NAME=VALUE",
    help="Replace a parameter, e.g. --set w.a0-a1.collision=50 --set goal.a0=3,0.5 (repeatable).",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write the result as JSON here.",
)
@click.option(
    "--plot",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write a trajectory figure (PNG) here.",
)
@click.option(
    "--certificate/--no-certificate",
    default=True,
    show_default=True,
    help="Run the equilibrium check: the local open-loop Nash certificate (a best-response "
    "solve per agent) or, for --solver ilq, the feedback Nash check of the policy.",
)
@allow_import_option
def solve(
    game_file: Path,
    solver: str,
    steps: int | None,
    settings: tuple[str, ...],
    out: Path | None,
    plot: Path | None,
    certificate: bool,
    modes: int | None,
    seed: int,
):
    """Solve GAME_FILE (YAML or JSON game file) and print a short summary."""
    from scenarios.gamefile import apply_settings, load_game
    from scenarios.plotting import check_image_path
    from solvers.registry import SOLVERS

    t0 = time.perf_counter()
    check_output_file(out, "--out")  # before any work: nothing is solved for an unwritable path
    if plot is not None:
        check_output_file(check_image_path(plot, "--plot"), "--plot")
    gf = load_game(game_file)
    entry = SOLVERS.entry(solver, "--solver")  # after the file: its modules may register one
    game = gf.game
    p = apply_settings(game, gf.params, settings)
    over = {}
    if steps is not None:
        if entry.iteration_limit is None:
            raise SpecError("--steps", f"the solver {solver!r} has no iteration limit option")
        over = {entry.iteration_limit: steps}
    opts = gf.options(solver, **over)
    if modes is not None:
        if not entry.multimodal:
            usable = [n for n, e in SOLVERS.items() if e.multimodal]
            raise SpecError(
                "--modes", f"expected --solver one of {usable} (no multi-start mode for {solver!r})"
            )
        return _solve_modes(game_file, game, p, solver, opts, modes, seed, out, plot, t0)
    res, cert = run_solve(game, p, solver, opts, certify=certificate)
    data = result_dict(game, p, res, cert, source=str(game_file))
    click.echo(
        f"{game_file}: {game.N} agents, K = {game.K}, n_u = {game.n_u}, {len(game.terms)} energy terms"
    )
    for line in summary_lines(game, data):
        click.echo(line)
    if "setup_s" in res.info:  # IPOPT: the NLP's set-up (Hessian built or read from the cache)
        how = {"disk": "read from the cache", "rebuilt": "rebuilt, cache file unusable"}
        src = res.info.get("setup_source")
        tail = f" (Hessian of the Lagrangian {how.get(src, src)})" if src is not None else ""
        click.echo(f"  set-up {fmt_number(res.info['setup_s'], '.2f')} s{tail}")
    if out is not None:
        write_result(data, out)
        click.echo(f"wrote {out}")
    if plot is not None:
        from scenarios.plotting import plot_trajectories

        plot_trajectories(
            game,
            res.states,
            p,
            plot,
            title=f"{game_file.name}: {solver}, E = {fmt_number(res.energy, '.4g')}",
        )
        click.echo(f"wrote {plot}")
    click.echo(f"total {time.perf_counter() - t0:.2f} s")
    _exit(res.status, res.message)


def _exit(status: Status, message: str) -> None:
    code = exit_code(status)
    if code == EXIT_STALLED:
        raise SolveExit(f"the solve stalled (exit {code}): {message}", code)
    if code:
        raise SolveExit(f"the solve did not give a usable solution: {message}", code)


def _solve_modes(game_file, game, p, solver, opts, n, seed, out, plot, t0) -> None:
    """``epo solve --modes N``: multi-modal solve, printed, written and plotted."""
    from solvers.multimodal import solve_multimodal

    mm = solve_multimodal(game, p, n_samples=n, seed=seed, solver=solver, options=opts)
    j = mm.modes[0].medoid if mm.modes else 0
    top = mm.results[j]
    data = result_dict(game, p, top, None, source=str(game_file))
    listed = modes_dict(game, mm)
    data["modes"] = listed
    data["samples"] = n
    data["seed"] = seed
    data["solves"] = mm.results.message
    click.echo(
        f"{game_file}: {game.N} agents, K = {game.K}, n_u = {game.n_u}, {solver} from {n} "
        f"seeded starts (seed {seed})"
    )
    for line in mode_lines(game, listed, n, mm.results.message):
        click.echo(line)
    if out is not None:
        write_result(data, out)
        click.echo(f"wrote {out}")
    if plot is not None:
        from scenarios.plotting import plot_modes

        plot_modes(game, mm.modes, p, plot, title=f"{game_file.name}: {solver}, {n} starts")
        click.echo(f"wrote {plot}")
    click.echo(f"total {time.perf_counter() - t0:.2f} s")
    if not mm.modes:
        raise SolveExit(f"no mode: all {n} solves were dropped ({mm.results.message})", EXIT_FAILED)
    _exit(top.status, top.message)
