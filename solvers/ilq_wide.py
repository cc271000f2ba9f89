"""SX functions written again as C on vectors of starts (:mod:`solvers.fast_ilq`).

:func:`wide_function_source` writes one C statement per SX instruction on vectors of
:data:`WIDE_LANES` doubles (GCC vector extensions, FMA contraction off, library functions
lane by lane), so each lane equals CasADi's compiled code for one double bit for bit;
:class:`WideUnsupported` for what it does not write. ``_WIDE_HEAD`` is the C prelude of
every such kernel, :func:`wide_function_external` wraps one function as a
``casadi.external`` (the per-operation check of ``tests/test_ilq_batch.py``). The batched
one-call trial built from them is :mod:`solvers.ilq_wide_trial`.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

#: starts one call of :class:`CompiledWideTrial` evaluates together: 8 doubles fill one
#: AVX-512 register (two AVX2 or four SSE2 ones)
WIDE_LANES = 8

# C of each SX operation on vectors of WIDE_LANES doubles (GCC vector extensions), as
# CasADi's generated C writes it for one double (casadi_sq(x) = x*x, (2.*x), (1./x), ...):
# arithmetic on whole vectors; comparisons and logic as masks (-1 or 0 per lane) turned
# into 1.0 or 0.0; library functions lane by lane (the same libm calls)
_WIDE_ARITH = {
    "ADD": "{a}+{b}",
    "SUB": "{a}-{b}",
    "MUL": "{a}*{b}",
    "DIV": "{a}/{b}",
    "NEG": "-{a}",
    "SQ": "{a}*{a}",
    "TWICE": "2.*{a}",
    "INV": "1./{a}",
    "ASSIGN": "{a}",
}
_WIDE_MASK = {
    "LT": "{a}<{b}",
    "LE": "{a}<={b}",
    "EQ": "{a}=={b}",
    "NE": "{a}!={b}",
    "NOT": "{a}==0",
    "AND": "({a}!=0)&({b}!=0)",
    "OR": "({a}!=0)|({b}!=0)",
}
# selections on whole vectors: fabs clears the sign bit; fmax and fmin as glibc's x86-64
# fmax/fmin (maxsd/minsd: the second argument on ties and for a NaN first one, the first
# for a NaN second one), elsewhere glibc's functions lane by lane (EPO_SELECT)
_WIDE_SELECT = {
    "FABS": "(vd)((vl){a} & ~(vl)(-zero))",
    "FMAX": "EPO_FMAX({a},{b})",
    "FMIN": "EPO_FMIN({a},{b})",
}
_WIDE_LIB = {
    "SQRT": "sqrt({a})",
    "SIGN": "({a}<0 ? -1 : {a}>0 ? 1 : {a})",
    "SIN": "sin({a})",
    "COS": "cos({a})",
    "TAN": "tan({a})",
    "ASIN": "asin({a})",
    "ACOS": "acos({a})",
    "ATAN": "atan({a})",
    "ATAN2": "atan2({a},{b})",
    "SINH": "sinh({a})",
    "COSH": "cosh({a})",
    "TANH": "tanh({a})",
    "ASINH": "asinh({a})",
    "ACOSH": "acosh({a})",
    "ATANH": "atanh({a})",
    "EXP": "exp({a})",
    "LOG": "log({a})",
    "POW": "pow({a},{b})",
    "CONSTPOW": "pow({a},{b})",
    "FLOOR": "floor({a})",
    "CEIL": "ceil({a})",
    "FMOD": "fmod({a},{b})",
    "REMAINDER": "remainder({a},{b})",
    "COPYSIGN": "copysign({a},{b})",
    "ERF": "erf({a})",
}
_OP_NAMES = {getattr(ca, k): k[3:] for k in dir(ca) if k.startswith("OP_")}


def _c_double(v: float) -> str:
    """``v`` as an exact C literal (hexadecimal; INFINITY, NAN)."""
    v = float(v)
    if math.isnan(v):
        return "NAN"
    if math.isinf(v):
        return "INFINITY" if v > 0 else "(-INFINITY)"
    return f"({v.hex()})"


class WideUnsupported(ValueError):
    """An SX operation or a sparsity that :func:`wide_function_source` does not write."""


def _sincos_pairs(f: ca.Function, code: list[str]) -> dict[int, str]:
    """Statements for the SIN and COS instructions of ``f`` that take the same value (no
    write to its work variable between them): the first computes both lane by lane with
    ``sincos`` (as gcc does for the scalar code) into a temporary, the second copies it."""
    out: dict[int, str] = {}
    n = len(code)
    for k in range(n):
        if code[k] not in ("SIN", "COS") or k in out:
            continue
        a, o1 = f.instruction_input(k)[0], f.instruction_output(k)[0]
        if o1 == a:  # the value is overwritten by the first one
            continue
        want = "COS" if code[k] == "SIN" else "SIN"
        for q in range(k + 1, n):
            if q not in out and code[q] == want and f.instruction_input(q)[0] == a:
                o2 = f.instruction_output(q)[0]
                first, second = ("s", "c") if code[k] == "SIN" else ("c", "s")
                out[k] = f"  EPO_SINCOS(w{a}, s{k}, c{k}); w{o1} = {first}{k};"
                out[q] = f"  w{o2} = {second}{k};"
                break
            if code[q] != "OUTPUT" and f.instruction_output(q)[0] == a:
                break  # the value was overwritten
    return out


def wide_function_source(f: ca.Function, name: str, indexed=()) -> str:
    """C of the SX function ``f`` on :data:`WIDE_LANES` lanes at once: ``static void
    name(const vd* const* in, const int* const* ix, vd* const* out)``, every input and
    output as vectors ``vd`` of its nonzeros (outputs as all their entries, structural
    zeros written as 0); an input ``i`` in ``indexed`` is read through its index table,
    nonzero ``j`` at ``in[i][ix[i][j]]`` (a gather without a copy).

    One C statement per instruction of ``f`` in ``f``'s order, each lane computing what
    CasADi's generated C computes for one double (:data:`_WIDE_ARITH` and the tables
    beside it), so with FMA contraction off every lane equals ``f``'s compiled code bit
    for bit. :class:`WideUnsupported` for an operation outside the tables or a sparse input.
    """
    if not f.is_a("SXFunction"):
        raise WideUnsupported(f"{f.name()}: not an SX function")
    for i in range(f.n_in()):
        if not f.sparsity_in(i).is_dense():
            raise WideUnsupported(f"{f.name()}: input {i} is sparse")
    rows = []  # per output: entry (column-major) of each nonzero
    body = []
    for i in range(f.n_out()):
        sp = f.sparsity_out(i)
        r, c = (np.asarray(v, dtype=int) for v in sp.get_triplet())
        ent = c * sp.size1() + r
        rows.append(ent)
        for e in sorted(set(range(sp.numel())) - set(ent.tolist())):
            body.append(f"  out[{i}][{e}] = zero;")
    W = WIDE_LANES
    code = [_OP_NAMES.get(f.instruction_id(k), "?") for k in range(f.n_instructions())]
    pairs = _sincos_pairs(f, code)
    for k in range(f.n_instructions()):
        op = code[k]
        ins, outs = f.instruction_input(k), f.instruction_output(k)
        if k in pairs:  # sin and cos of the same value: one sincos, the second kept
            body.append(pairs[k])
            continue
        if op == "INPUT":
            j = f"ix[{ins[0]}][{ins[1]}]" if ins[0] in indexed else str(ins[1])
            body.append(f"  w{outs[0]} = in[{ins[0]}][{j}];")
            continue
        if op == "OUTPUT":
            body.append(f"  out[{outs[0]}][{rows[outs[0]][outs[1]]}] = w{ins[0]};")
            continue
        o = f"w{outs[0]}"
        if op == "CONST":
            body.append(f"  {o} = zero + {_c_double(f.instruction_constant(k))};")
            continue
        a = f"w{ins[0]}"
        b = f"w{ins[1]}" if len(ins) > 1 else None
        if op in _WIDE_ARITH:
            body.append(f"  {o} = " + _WIDE_ARITH[op].format(a=a, b=b) + ";")
        elif op in _WIDE_MASK:
            body.append(f"  {o} = (vd)((" + _WIDE_MASK[op].format(a=a, b=b) + ") & one);")
        elif op in _WIDE_SELECT:
            body.append(f"  {o} = " + _WIDE_SELECT[op].format(a=a, b=b) + ";")
        elif op == "IF_ELSE_ZERO":  # (a ? b : 0)
            body.append(f"  {o} = (vd)(({a}!=0) & (vl){b});")
        elif op in _WIDE_LIB:
            e = _WIDE_LIB[op].format(a=f"{a}[l]", b=f"{b}[l]" if b else None)
            body.append(f"  {{ vd t; for (l = 0; l < {W}; ++l) t[l] = {e}; {o} = t; }}")
        else:
            raise WideUnsupported(f"{f.name()}: operation {op}")
    n = max(f.sz_w(), 1)
    head = [
        f"static EPO_CLONES void {name}(const vd* const* in, const int* const* ix, "
        "vd* const* out) {",
        "  const vd zero = {0};",
        "  const vl one = (vl)(zero + 1.0);",
        "  vd " + ", ".join(f"w{j}" for j in range(n)) + ";",
        "  int l;",
        "  (void)l;",
        "  (void)one;",
        "  (void)ix;",
    ]
    return "\n".join(head + body + ["}"])


_WIDE_HEAD = r"""
#define _GNU_SOURCE
#include <float.h>
#include <math.h>
#include <stdint.h>
#pragma GCC optimize("fp-contract=off")
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11 && defined(__x86_64__) && \
    defined(__linux__)
#define EPO_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define EPO_CLONES
#endif
typedef double vd __attribute__((vector_size(8 * EPO_W)));
typedef long long vl __attribute__((vector_size(8 * EPO_W)));
static inline vd epo_pick(vl m, vd a, vd b) { return (vd)(((vl)a & m) | ((vl)b & ~m)); }
#if defined(__x86_64__) && defined(__GLIBC__)
#define EPO_FMAX(a, b) epo_pick(((a) > (b)) | ((b) != (b)), (a), (b))
#define EPO_FMIN(a, b) epo_pick(((a) < (b)) | ((b) != (b)), (a), (b))
#else
static inline vd epo_fmax(vd a, vd b) {
  int l;
  for (l = 0; l < EPO_W; ++l) a[l] = fmax(a[l], b[l]);
  return a;
}
static inline vd epo_fmin(vd a, vd b) {
  int l;
  for (l = 0; l < EPO_W; ++l) a[l] = fmin(a[l], b[l]);
  return a;
}
#define EPO_FMAX(a, b) epo_fmax((a), (b))
#define EPO_FMIN(a, b) epo_fmin((a), (b))
#endif
#if defined(__GLIBC__)
#define EPO_SINCOS1(x, s, c) sincos((x), &(s), &(c))
#else
#define EPO_SINCOS1(x, s, c) ((s) = sin(x), (c) = cos(x))
#endif
/* s = sin(x), c = cos(x) lane by lane (declares s and c) */
#define EPO_SINCOS(x, s, c)                  \
  vd s, c;                                   \
  for (l = 0; l < EPO_W; ++l) {              \
    double s_, c_;                           \
    EPO_SINCOS1((x)[l], s_, c_);             \
    s[l] = s_;                               \
    c[l] = c_;                               \
  }
"""


def wide_function_external(f: ca.Function, name: str) -> str:
    """C of a ``casadi.external`` function evaluating the SX function ``f`` (dense
    outputs) on :data:`WIDE_LANES` lanes: every input and output holds the lanes one after
    the other (``(WIDE_LANES, nnz)``), lane ``l`` computing ``f`` on its own numbers bit for
    bit (:func:`wide_function_source`; the per-operation check of ``tests/test_ilq_batch.py``)."""
    n_in, n_out = f.n_in(), f.n_out()
    for i in range(n_out):
        if not f.sparsity_out(i).is_dense():
            raise WideUnsupported(f"{f.name()}: output {i} is sparse")
    W = WIDE_LANES
    sz_in = [f.nnz_in(i) for i in range(n_in)]
    sz_out = [f.nnz_out(i) for i in range(n_out)]
    sp = lambda szs: "{" + ",".join(f"{{{k * W},1,1}}" for k in szs) + "}"  # noqa: E731
    body = [
        f"static const long long int {name}_spi[{n_in}][3] = {sp(sz_in)};",
        f"static const long long int {name}_spo[{n_out}][3] = {sp(sz_out)};",
        f"int {name}_n_in(void) {{ return {n_in}; }}",
        f"int {name}_n_out(void) {{ return {n_out}; }}",
        f"const long long int* {name}_sparsity_in(long long int i) {{ return {name}_spi[i]; }}",
        f"const long long int* {name}_sparsity_out(long long int i) {{ return {name}_spo[i]; }}",
        f"int {name}(const double** arg, double** res, long long int* iw, double* w, int mem) {{",
        f"  vd in_[{max(sum(sz_in), 1)}], out_[{max(sum(sz_out), 1)}];",
        f"  const vd* in[{max(n_in, 1)}];",
        f"  vd* out[{max(n_out, 1)}];",
        "  int i, j, l;",
        "  (void)iw, (void)w, (void)mem;",
    ]
    off = 0
    for i, k in enumerate(sz_in):
        body.append(f"  in[{i}] = in_ + {off};")
        body.append(f"  for (j = 0; j < {k}; ++j) for (l = 0; l < {W}; ++l)")
        body.append(f"    in_[{off} + j][l] = arg[{i}] ? arg[{i}][l * {k} + j] : 0.0;")
        off += k
    off = 0
    for i, _ in enumerate(sz_out):
        body.append(f"  out[{i}] = out_ + {off};")
        off += sz_out[i]
    body.append(f"  {name}_f(in, 0, out);")
    off = 0
    for i, k in enumerate(sz_out):
        body.append(f"  if (res[{i}]) for (j = 0; j < {k}; ++j) for (l = 0; l < {W}; ++l)")
        body.append(f"    res[{i}][l * {k} + j] = out_[{off} + j][l];")
        off += k
    body += ["  (void)i;", "  return 0;", "}"]
    head = f"#define EPO_W {W}\n" + _WIDE_HEAD
    return head + wide_function_source(f, f"{name}_f") + "\n" + "\n".join(body) + "\n"
