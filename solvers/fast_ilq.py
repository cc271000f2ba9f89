"""Generated C for :mod:`solvers.ilq` (``compiled=True``): stage functions, one call per trial.

:class:`solvers.ilq.ILQSolver` quadratizes the players' costs and linearizes the dynamics
with one interpreted CasADi function over the whole trajectory (``ilq_quadratize``, about
1k SX instructions per stage). Compiling that function whole took tens of seconds and ran no
faster at ``-O0``. This module splits it into *stage functions* instead, found from the
graph itself, so it works for any stage-structured costs without knowing the features:

1. Every output nonzero belongs to one stage ``k`` (where :meth:`ILQSolver.quadratize`
   scatters it: ``L_ik``, ``Phi_k``). The sparsity of the outputs' Jacobian w.r.t. the
   trajectory gives the stages ``lo_k..hi_k`` each stage's outputs depend on (``k-1..k+1``
   with jerk terms: the residual rows of the next stage enter this stage's gradient).
2. Stage ``k``'s outputs become a function ``(z_lo..z_hi, p) -> out_k`` of its stage
   window (``z_j = (U_j, X_j)``, ``z_K = X_K``); its outputs are ordered by their place in
   the stage matrices. Stages whose functions serialize identically (same graph, same
   constants, same relative window) form one group: the middle stages are one group, the
   first and last stages a few more.
3. Each group's function is mapped over its stages (``Function.map``, ``p`` shared). A
   call gathers the stage windows with one numpy index per group.

The costs ``C`` and the energy ``E`` (needed once per linearization, for the result and the
finiteness test): with the game's own costs, the residual rows go out with the stage of the
latest variable they involve and numpy sums them, ``C_i = 1/2 |r_i|^2`` over player ``i``'s
terms, ``E = 1/2 |r|^2`` (the game's definitions; only the summation order differs, so they
agree to rounding). With custom costs they stay one interpreted function over the
trajectory (28k SX instructions, 0.08 ms, for 3 unicycles and K = 100).

When the split does not pay or cannot be made (a stage depends on stages more than
:data:`MAX_WINDOW` away, as with a custom cost that couples the whole trajectory, or more
than :data:`MAX_GROUPS` distinct stage functions), :func:`build` returns ``None`` and the
solver keeps the interpreted function; :attr:`ILQSolver.quad_backend` says which is used.
The arithmetic is the interpreted function's, operation for operation (the same SX graph),
so the stage matrices agree to rounding (tested in ``tests/test_ilq_fast.py``).

One call per line-search trial (:class:`CompiledTrial`, the game's own costs): the
closed-loop rollout (:class:`CompiledRollout`), the stage groups on its windows, one index
table from their outputs to the Riccati fold's inputs (what the numpy scatter into
``Lam``/``Phi`` and the gather of ``CompiledRiccati.backward`` did) and the fold itself, as
one generated MX function around the same compiled SX functions: the separate calls'
numbers bit for bit, with Python once per trial instead of five calls with numpy glue.

Many starts at once (:class:`CompiledWideTrial`, built on the first batched solve by
:func:`wide_trial`): the one-call trial's SX stage functions written again on vectors of
:data:`WIDE_LANES` starts (:func:`wide_function_source`: one C statement per SX
instruction, GCC vector extensions, FMA contraction off, library functions lane by lane)
and its data movement as C around them (:func:`wide_trial_source`), compiled by
:func:`solvers.codegen.compile_kernel`; each lane equals the scalar trial bit for bit.

:func:`compile_solver` compiles all of it into one library per game structure
(``ilq_n<N>_k<K>_<cpu>``, cached on disk by the functions' serialization, never by
parameter values) with :data:`OPTIMIZE`: ``-O3`` vector code for this CPU, FMA contraction
off, so the numbers equal ``-O1``'s bit for bit (docs/ilq.md, "Benchmark").

Modules. This module holds :func:`compile_solver` and its flags; the pieces live beside it
and every name stays importable from here: :mod:`solvers.ilq_compiled` (the stage split,
the compiled rollout and the one-call trial), :mod:`solvers.ilq_wide` (SX functions as C
on vectors of starts) and :mod:`solvers.ilq_wide_trial` (the one-call trial on many starts).
"""

from __future__ import annotations

from .ilq_compiled import (
    MAX_GROUPS,
    MAX_WINDOW,
    CompiledQuadratize,
    CompiledRollout,
    CompiledTrial,
    build,
)
from .ilq_compiled import _Call as _Call
from .ilq_wide import _OP_NAMES as _OP_NAMES
from .ilq_wide import _WIDE_ARITH as _WIDE_ARITH
from .ilq_wide import _WIDE_HEAD as _WIDE_HEAD
from .ilq_wide import _WIDE_LIB as _WIDE_LIB
from .ilq_wide import _WIDE_MASK as _WIDE_MASK
from .ilq_wide import _WIDE_SELECT as _WIDE_SELECT
from .ilq_wide import WIDE_LANES, WideUnsupported, wide_function_external, wide_function_source
from .ilq_wide import _c_double as _c_double
from .ilq_wide import _sincos_pairs as _sincos_pairs
from .ilq_wide_trial import _WIDE_DRIVER as _WIDE_DRIVER
from .ilq_wide_trial import CompiledWideTrial, trial_stats, wide_trial, wide_trial_source
from .ilq_wide_trial import _c_ints as _c_ints

__all__ = [
    "MAX_GROUPS",
    "MAX_WINDOW",
    "OPTIMIZE",
    "WIDE_LANES",
    "CompiledQuadratize",
    "CompiledRollout",
    "CompiledTrial",
    "CompiledWideTrial",
    "WideUnsupported",
    "build",
    "compile_solver",
    "trial_stats",
    "wide_function_external",
    "wide_function_source",
    "wide_trial",
    "wide_trial_source",
]

#: gcc flags of the iLQ library (:func:`compile_solver`): vector code for this CPU at
#: ``-O3``, without FMA contraction, so the numbers equal ``-O1``'s bit for bit. The
#: library's name carries the CPU (:func:`_cpu_tag`): a cache shared by several machines
#: never loads it on another CPU. A compiler that rejects the flags gets ``-O1``.
OPTIMIZE = "-O3 -march=native -ffp-contract=off -fno-math-errno"


def _cpu_tag() -> str:
    """A short hash of this CPU's model and instruction-set flags (``/proc/cpuinfo``)."""
    import hashlib
    import platform

    info = platform.machine() + platform.processor()
    try:
        with open("/proc/cpuinfo") as fh:
            lines = fh.read().split("\n\n")[0].splitlines()
        info += "".join(ln for ln in lines if ln.split(":")[0].strip() in ("model name", "flags"))
    except OSError:
        pass
    return hashlib.sha256(info.encode()).hexdigest()[:8]


def compile_solver(solver, optimize: str | None = None, trial: bool = True) -> None:
    """Build and compile every generated-C path of ``solver`` as one library.

    Sets ``solver._compiled`` (the Riccati fold), ``_croll`` (the rollout), ``_cquad`` (the
    stage-split quadratization, or ``None``: :func:`build`) and ``_ftrial``
    (:class:`CompiledTrial`, with the game's own costs only, else ``None``). One library
    ``ilq_n<N>_k<K>_<cpu>``, compiled with ``optimize`` (default :data:`OPTIMIZE`; ``-O1``
    when the compiler rejects it) and cached on disk by the functions' serialization.
    ``trial=False`` leaves the one-call trial out (the separate calls: a benchmark's
    reference, ``bench/bench_ilq.py``).
    """
    from .codegen import CompilerError, compile_functions

    ric = solver.riccati_fold()  # the solver's own Riccati fold, not compiled yet
    quad = build(solver, *solver._quad_sym)
    roll = CompiledRollout(solver)
    funcs = [ric.acc, roll.fn] + ([] if quad is None else quad.fns)
    ftrial = None
    if trial and quad is not None and quad.costs is None:
        ftrial = CompiledTrial(solver, quad, roll, ric)
        funcs.append(ftrial.fn)
    name = f"ilq_n{solver.N}_k{solver.K}"
    try:
        lib = compile_functions(funcs, f"{name}_{_cpu_tag()}", optimize=optimize or OPTIMIZE)
    except CompilerError:  # a compiler without these flags: the portable -O1 build
        lib = compile_functions(funcs, name, optimize="-O1")
    for part in (ric, roll, quad, ftrial):
        if part is not None:
            part.attach(lib)
    solver._compiled, solver._croll, solver._cquad, solver._ftrial = ric, roll, quad, ftrial
    solver.quad_backend = "interpreted" if quad is None else "compiled"
