"""The one-call trial of :mod:`solvers.fast_ilq` on many starts at once.

:class:`CompiledWideTrial` evaluates :class:`~solvers.ilq_compiled.CompiledTrial` for
:data:`~solvers.ilq_wide.WIDE_LANES` starts per call: :func:`wide_trial_source` writes the
trial's stage functions on vectors of starts (:func:`~solvers.ilq_wide.wide_function_source`)
and its data movement as C around them (the driver ``_WIDE_DRIVER``), compiled by
:func:`solvers.codegen.compile_kernel`; each lane equals the scalar trial bit for bit.
:func:`wide_trial` builds it on a compiled solver's first batched solve, :func:`trial_stats`
computes its per-start statistics in numpy.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from .ilq_wide import _WIDE_HEAD, WIDE_LANES, WideUnsupported, wide_function_source

if TYPE_CHECKING:
    from .ilq_compiled import CompiledTrial

# the driver: one call evaluates EPO_W starts (inputs and outputs start after start, as
# CompiledTrial's function has them); every intermediate array holds vectors of starts
_WIDE_DRIVER = r"""
#if EPO_W == 8
typedef long long vi __attribute__((vector_size(64)));
/* the 8 x 8 block r[i][j] -> r[j][i] (three rounds of shuffles) */
static inline void tr8(vd* r) {
  const vi lo1 = {0, 8, 2, 10, 4, 12, 6, 14}, hi1 = {1, 9, 3, 11, 5, 13, 7, 15};
  const vi lo2 = {0, 1, 8, 9, 4, 5, 12, 13}, hi2 = {2, 3, 10, 11, 6, 7, 14, 15};
  const vi lo3 = {0, 1, 2, 3, 8, 9, 10, 11}, hi3 = {4, 5, 6, 7, 12, 13, 14, 15};
  vd t[8], u[8];
  int i;
  for (i = 0; i < 8; i += 2) {
    t[i] = __builtin_shuffle(r[i], r[i + 1], lo1);
    t[i + 1] = __builtin_shuffle(r[i], r[i + 1], hi1);
  }
  for (i = 0; i < 8; i += 4) {
    u[i] = __builtin_shuffle(t[i], t[i + 2], lo2);
    u[i + 2] = __builtin_shuffle(t[i], t[i + 2], hi2);
    u[i + 1] = __builtin_shuffle(t[i + 1], t[i + 3], lo2);
    u[i + 3] = __builtin_shuffle(t[i + 1], t[i + 3], hi2);
  }
  for (i = 0; i < 4; ++i) {
    r[i] = __builtin_shuffle(u[i], u[i + 4], lo3);
    r[i + 4] = __builtin_shuffle(u[i], u[i + 4], hi3);
  }
}
#endif
/* starts one after the other (src[l n + j]) -> vectors of starts (dst[j][l]) */
static EPO_CLONES void pack(const double* src, vd* dst, int n) {
  double* d = (double*)dst;
  int j = 0, l;
  if (!src) {
    for (j = 0; j < n * EPO_W; ++j) d[j] = 0.0;
    return;
  }
#if EPO_W == 8
  for (; j + 8 <= n; j += 8) {
    vd r[8];
    for (l = 0; l < 8; ++l) __builtin_memcpy(&r[l], src + l * n + j, sizeof(vd));
    tr8(r);
    for (l = 0; l < 8; ++l) dst[j + l] = r[l];
  }
#endif
  for (l = 0; l < EPO_W; ++l)
    for (int q = j; q < n; ++q) d[q * EPO_W + l] = src[l * n + q];
}
/* the inverse of pack, into rows of length stride from column at */
static EPO_CLONES void unpack(const vd* src, double* dst, int n, int stride, int at) {
  const double* s = (const double*)src;
  int j = 0, l;
  if (!dst) return;
#if EPO_W == 8
  for (; j + 8 <= n; j += 8) {
    vd r[8];
    for (l = 0; l < 8; ++l) r[l] = src[j + l];
    tr8(r);
    for (l = 0; l < 8; ++l) __builtin_memcpy(dst + l * stride + at + j, &r[l], sizeof(vd));
  }
#endif
  for (l = 0; l < EPO_W; ++l)
    for (int q = j; q < n; ++q) dst[l * stride + at + q] = s[q * EPO_W + l];
}
static EPO_CLONES void gather(const vd* all, const int* idx, vd* dst, int n) {
  int j;
  for (j = 0; j < n; ++j) dst[j] = all[idx[j]];
}
/* per start (solvers.ilq.iteration._Evaluation reads them): PA finite; X, U finite;
   max |a| (NaN if one is); sum of a*a exactly rounded (pairwise in long double, kept
   where both ends of its error bound round to the same double, else NaN); r*r finite
   and summing below 1e300 */
static EPO_CLONES void stats(const vd* PAr, const vd* V, const vd* ALL, double* st) {
  const vd zero = {0};
  const vl one = (vl)(zero == zero);
  const vd nan = zero + NAN;
  vl ok = one, good = one, isnan = (vl)zero, cok = one;
  vd r = zero, sq = zero, v;
  int j, i, k, l, h;
  for (j = 0; j < EPO_K * EPO_NPA; ++j) ok &= (PAr[j] - PAr[j]) == zero;
  for (j = 0; j < EPO_NV; ++j) good &= (V[j] - V[j]) == zero;
  for (k = 0; k < EPO_K; ++k)
    for (i = 0; i < EPO_NU; ++i) {
      v = (vd)((vl)PAr[k * EPO_NPA + i * (EPO_NXS + 1) + EPO_NXS] & ~(vl)(-zero));
      isnan |= v != v;
      r = epo_pick(v > r, v, r);
    }
  r = epo_pick(isnan, nan, r);
  for (j = 0; j < EPO_NR; ++j) {
    v = ALL[epo_tr[j]] * ALL[epo_tr[j]];
    cok &= (v - v) == zero;
    sq += v;
  }
  cok &= sq < zero + 1e300;
  for (l = 0; l < EPO_W; ++l) {
    long double b[EPO_NA2], e;
    double lo = NAN, hi = 0.0;
    if (ok[l]) {
      for (k = 0; k < EPO_K; ++k)
        for (i = 0; i < EPO_NU; ++i) {
          double a = PAr[k * EPO_NPA + i * (EPO_NXS + 1) + EPO_NXS][l];
          b[k * EPO_NU + i] = a * a;
        }
      for (j = EPO_K * EPO_NU; j < EPO_NA2; ++j) b[j] = 0.0L;
      for (h = EPO_NA2 / 2; h >= 1; h /= 2)
        for (i = 0; i < h; ++i) b[i] += b[i + h];
      e = b[0] * (long double)(EPO_DEPTH * LDBL_EPSILON);
      lo = (double)(b[0] - e);
      hi = (double)(b[0] + e);
      if (!(lo == hi)) lo = NAN;
    }
    st[l * 5 + 0] = ok[l] ? 1.0 : 0.0;
    st[l * 5 + 1] = good[l] ? 1.0 : 0.0;
    st[l * 5 + 2] = r[l];
    st[l * 5 + 3] = lo;
    st[l * 5 + 4] = cok[l] ? 1.0 : 0.0;
  }
}
static const long long int EPO_FN_sp_in[8][3] = EPO_SP_IN;
static const long long int EPO_FN_sp_out[6][3] = EPO_SP_OUT;
int EPO_FN_n_in(void) { return 8; }
int EPO_FN_n_out(void) { return 6; }
const long long int* EPO_FN_sparsity_in(long long int i) {
  return i >= 0 && i < 8 ? EPO_FN_sp_in[i] : 0;
}
const long long int* EPO_FN_sparsity_out(long long int i) {
  return i >= 0 && i < 6 ? EPO_FN_sp_out[i] : 0;
}
int EPO_FN_work(long long int* sz_arg, long long int* sz_res, long long int* sz_iw,
                long long int* sz_w) {
  if (sz_arg) *sz_arg = 8;
  if (sz_res) *sz_res = 6;
  if (sz_iw) *sz_iw = 0;
  if (sz_w) *sz_w = (long long int)EPO_NWORK * EPO_W + EPO_W;
  return 0;
}
EPO_CLONES int EPO_FN(const double** arg, double** res, long long int* iw, double* w,
                      int mem) {
  vd* wk = (vd*)(((uintptr_t)w + 8 * EPO_W - 1) & ~(uintptr_t)(8 * EPO_W - 1));
  vd *x0 = wk, *Xr = x0 + EPO_NX, *Ur = Xr + (EPO_K + 1) * EPO_NX;
  vd *PA = Ur + EPO_K * EPO_NU, *eps = PA + EPO_K * EPO_NPA, *p = eps + 1;
  vd *mu0 = p + EPO_NP, *del = mu0 + 1, *S = del + 1, *S2 = S + EPO_NS;
  vd *V = S2 + EPO_NS, *ALL = V + EPO_NV, *Z = ALL + EPO_NALL, *Z2 = Z + EPO_NZC;
  vd *PAr = Z2 + EPO_NZC, *mur = PAr + EPO_K * EPO_NPA, *lam = mur + EPO_K * EPO_N;
  vd *phi = lam + EPO_NLAM, *tmp = phi + EPO_NPHI, *sw;
  const vd zero = {0};
  int j, k, l;
  (void)iw;
  (void)mem;
  pack(arg[0], x0, EPO_NX);
  pack(arg[1], Xr, (EPO_K + 1) * EPO_NX);
  pack(arg[2], Ur, EPO_K * EPO_NU);
  pack(arg[3], PA, EPO_K * EPO_NPA);
  pack(arg[4], eps, 1);
  pack(arg[5], p, EPO_NP);
  pack(arg[6], mu0, 1);
  pack(arg[7], del, 1);
  /* closed-loop rollout: s = (x, dY), v = (vec(U), vec(X)) */
  for (j = 0; j < EPO_NX; ++j) S[j] = V[EPO_K * EPO_NU + j] = x0[j];
  for (j = EPO_NX; j < EPO_NS; ++j) S[j] = zero;
  for (k = 0; k < EPO_K; ++k) {
    const vd* in[5] = {S, Xr + k * EPO_NX, Ur + k * EPO_NU, PA + k * EPO_NPA, eps};
    vd* out[2] = {S2, V + k * EPO_NU};
    epo_roll(in, 0, out);
    for (j = 0; j < EPO_NX; ++j) V[EPO_K * EPO_NU + (k + 1) * EPO_NX + j] = S2[j];
    sw = S, S = S2, S2 = sw;
  }
  /* stage functions of the quadratization on their windows of v */
EPO_GROUPS
  ALL[EPO_NALL - 1] = zero;
  /* coupled Riccati recursion, stage K-1 first (PAr, mur: in stage order) */
  gather(ALL, epo_tz, Z, EPO_NZC);
  for (k = 0; k < EPO_K; ++k) {
    const vd* in[5] = {Z, ALL, ALL, mu0, del};
    const int* ix[5] = {0, epo_tlam + k * EPO_NLAM, epo_tphi + k * EPO_NPHI, 0, 0};
    vd* out[3] = {Z2, PAr + (EPO_K - 1 - k) * EPO_NPA, mur + (EPO_K - 1 - k) * EPO_N};
    epo_riccati(in, ix, out);
    sw = Z, Z = Z2, Z2 = sw;
  }
  unpack(V + EPO_K * EPO_NU, res[0], (EPO_K + 1) * EPO_NX, (EPO_K + 1) * EPO_NX, 0);
  unpack(V, res[1], EPO_K * EPO_NU, EPO_K * EPO_NU, 0);
  unpack(PAr, res[2], EPO_K * EPO_NPA, EPO_K * EPO_NPA, 0);
  unpack(mur, res[3], EPO_K * EPO_N, EPO_K * EPO_N, 0);
  gather(ALL, epo_tr, tmp, EPO_NR);
  unpack(tmp, res[4], EPO_NR, EPO_NR, 0);
  if (res[5]) stats(PAr, V, ALL, res[5]);
  (void)l;
  return 0;
}
"""


def _c_ints(name: str, values) -> str:
    v = np.asarray(values, dtype=np.int64).reshape(-1)
    body = ",".join(str(int(x)) for x in v) if v.size else "0"
    return f"static const int {name}[{max(v.size, 1)}] = {{{body}}};"


def wide_trial_source(trial: CompiledTrial, name: str) -> str:
    """C of :class:`CompiledWideTrial` for the one-call trial ``trial``: its stage
    functions on :data:`WIDE_LANES` starts (:func:`wide_function_source`) and the data
    movement of its graph (rollout fold, stage windows, the index tables into the
    Riccati fold and the outputs), as a ``casadi.external`` function whose inputs and
    outputs are ``trial.fn``'s for :data:`WIDE_LANES` starts, one after the other.
    :class:`WideUnsupported` where it cannot be written."""
    s, quad, lay = trial.s, trial.quad, trial.layout
    f = trial.fn
    for i in range(f.n_out()):
        if not f.sparsity_out(i).is_dense():
            raise WideUnsupported(f"ilq_trial: output {f.name_out(i)} is sparse")
    K, N, nx, nu, nxs, na = s.K, s.N, s.nx, s.nu, s.nxs, s.na
    npa = (nxs + 1) * nu
    g = lay["gathers"]
    parts = [
        wide_function_source(trial.roll.stage, "epo_roll"),
        wide_function_source(trial.ric.stage, "epo_riccati", indexed=(1, 2)),
    ]
    calls, max_win = [], 1
    for gi, (stage, (win, _), off) in enumerate(
        zip(quad.stages, quad.spec, lay["offsets"], strict=True)
    ):
        parts.append(wide_function_source(stage, f"epo_quad{gi}", indexed=(0,)))
        parts.append(_c_ints(f"epo_win{gi}", win))
        m, w = win.shape
        n_out = stage.numel_out(0)
        max_win = max(max_win, w)
        calls.append(
            f"  for (k = 0; k < {m}; ++k) {{\n"
            f"    const vd* in[2] = {{V, p}};\n"
            f"    const int* ix[2] = {{epo_win{gi} + k * {w}, 0}};\n"
            f"    vd* out[1] = {{ALL + {off} + k * {n_out}}};\n"
            f"    epo_quad{gi}(in, ix, out);\n"
            "  }"
        )
    tables = [
        _c_ints("epo_tz", g["Z"]),
        _c_ints("epo_tlam", g["lam"]),
        _c_ints("epo_tphi", g["phi"]),
        _c_ints("epo_tr", g["r"]),
    ]
    n_lam, n_phi = g["lam"].size // K, g["phi"].size // K
    sizes = {
        "EPO_W": WIDE_LANES,
        "EPO_K": K,
        "EPO_N": N,
        "EPO_NX": nx,
        "EPO_NU": nu,
        "EPO_NS": nx + na,
        "EPO_NPA": npa,
        "EPO_NP": s.game.n_p,
        "EPO_NV": K * nu + (K + 1) * nx,
        "EPO_NALL": lay["n_all"],
        "EPO_NZC": g["Z"].size,
        "EPO_NLAM": n_lam,
        "EPO_NPHI": n_phi,
        "EPO_NR": g["r"].size,
        "EPO_NXS": nxs,
        # the exact sum of a*a: 2^depth >= K nu terms, bound 2 depth u (u = LDBL_EPSILON/2)
        "EPO_NA2": 1 << max(1, (K * nu - 1).bit_length()),
        "EPO_DEPTH": max(1, (K * nu - 1).bit_length()),
    }
    tmp_n = max(max_win, g["r"].size)
    sizes["EPO_NWORK"] = (
        nx
        + (K + 1) * nx
        + K * nu
        + K * npa
        + 1
        + s.game.n_p
        + 2
        + 2 * (nx + na)
        + sizes["EPO_NV"]
        + lay["n_all"]
        + 2 * g["Z"].size
        + K * npa
        + K * N
        + n_lam
        + n_phi
        + tmp_n
    )
    sp_in = [[f.nnz_in(i) * WIDE_LANES, 1, 1] for i in range(f.n_in())]
    sp_out = [[f.nnz_out(i) * WIDE_LANES, 1, 1] for i in range(f.n_out())]
    sp_out.append([5 * WIDE_LANES, 1, 1])  # the per-start stats
    defs = "".join(f"#define {k} {v}\n" for k, v in sizes.items())
    arr = lambda rows: "{" + ",".join("{" + ",".join(map(str, r)) + "}" for r in rows) + "}"  # noqa: E731
    driver = (
        _WIDE_DRIVER.replace("EPO_GROUPS", "\n".join(calls))
        .replace("EPO_SP_IN", arr(sp_in))
        .replace("EPO_SP_OUT", arr(sp_out))
        .replace("EPO_FN", name)
    )
    return defs + _WIDE_HEAD + "\n".join(parts + tables) + driver


class CompiledWideTrial:
    """:class:`CompiledTrial` for many starts: ``__call__(*inputs)`` with every input
    ``(m, nnz)`` (``m`` starts, ``trial.fn``'s inputs one row each) returns its outputs
    ``(m, nnz)``, as :class:`solvers.batch.BatchFunction` of ``trial.fn`` does, bit for
    bit, and per start ``(ok, good, res, asum, c_ok)`` (:func:`trial_stats`), evaluating
    :data:`WIDE_LANES` starts per call of the kernel
    (:func:`wide_trial_source`, compiled by :func:`solvers.codegen.compile_kernel`; ``m``
    is padded to a multiple). :func:`wide_trial` builds it."""

    def __init__(self, trial: CompiledTrial):
        from .batch import default_threads
        from .codegen import compile_kernel

        s = trial.s
        name = f"epo_ilq_wide_n{s.N}_k{s.K}"
        src = wide_trial_source(trial, name)
        so, _ = compile_kernel(src, name)
        self.fn = ca.external(name, str(so))
        self.threads = default_threads()
        self.sizes_in = [trial.fn.nnz_in(i) for i in range(trial.fn.n_in())]
        self.sizes_out = [trial.fn.nnz_out(i) for i in range(trial.fn.n_out())] + [5]
        self._bound: dict[int, tuple] = {}

    def _buffers(self, m: int):
        """``(evaluate, inputs, outputs)`` for ``m`` starts: the kernel mapped over
        ``ceil(m / WIDE_LANES)`` calls, bound once to arrays of that many lanes (lanes
        past ``m`` hold earlier numbers; their outputs are not read)."""
        c = max(1, -(-m // WIDE_LANES))
        b = self._bound.get(c)
        if b is None:
            f = self.fn
            if c > 1:
                th = min(self.threads, c)
                f = f.map(c, "thread", th) if th > 1 else f.map(c, "serial")
            buf, ev = f.buffer()
            n = c * WIDE_LANES
            ins = [np.zeros((n, k)) for k in self.sizes_in]
            outs = [np.zeros((n, k)) for k in self.sizes_out]
            for i, a in enumerate(ins):
                buf.set_arg(i, memoryview(a))
            for i, o in enumerate(outs):
                buf.set_res(i, memoryview(o))
            b = self._bound[c] = (ev, ins, outs, buf)
        return b

    def inputs(self, m: int) -> list[np.ndarray]:
        """The input arrays ``(m, nnz)`` of the next :meth:`run` of ``m`` starts, to fill."""
        return [a[:m] for a in self._buffers(m)[1]]

    def run(self, m: int) -> list[np.ndarray]:
        """Evaluate the ``m`` starts of :meth:`inputs`: the outputs ``(m, nnz)`` (views of
        arrays the next run overwrites)."""
        ev, _, outs, _ = self._buffers(m)
        ev()
        return [o[:m] for o in outs]

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        m = np.shape(args[0])[0]
        for a, dst in zip(args, self.inputs(m), strict=True):
            dst[:] = np.reshape(a, dst.shape)
        return [o.copy() for o in self.run(m)]


def wide_trial(solver) -> CompiledWideTrial | None:
    """The :class:`CompiledWideTrial` of a compiled ``solver`` (built and compiled on first
    use, then kept on its one-call trial), or ``None`` where it cannot be written or
    compiled (:class:`WideUnsupported`, a compiler error): then the mapped scalar trial."""
    from .codegen import CompilerError

    ft = solver._ftrial
    if ft is None:
        return None
    if ft.wide is None:
        try:
            ft.wide = CompiledWideTrial(ft)
        except (WideUnsupported, CompilerError):
            ft.wide = False
    return ft.wide or None


def trial_stats(solver, X, U, PA, r) -> np.ndarray:
    """Per start of the one-call trial's outputs ``(m, nnz)``: ``(ok, good, res, asum,
    c_ok)`` as :class:`CompiledWideTrial` computes them in C: ``PA`` finite, ``X`` and
    ``U`` finite, ``max |a|`` (NaN where one is), ``asum`` NaN (the exact sum of ``a*a`` is
    left to the caller), ``r*r`` finite and summing below ``1e300``: ``(m, 5)``."""
    m = X.shape[0]
    st = np.empty((m, 5))
    with np.errstate(all="ignore"):
        st[:, 0] = np.isfinite(PA).all(axis=1)
        st[:, 1] = np.isfinite(X).all(axis=1) & np.isfinite(U).all(axis=1)
        a = PA.reshape(m, solver.K * solver.nu, solver.nxs + 1)[:, :, -1]
        st[:, 2] = np.max(np.abs(a), axis=1)
        st[:, 3] = np.nan
        r2 = r * r
        st[:, 4] = np.isfinite(r2).all(axis=1) & (np.sum(r2, axis=1) < 1e300)
    return st
