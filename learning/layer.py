"""The differentiable game layer (the paper's EPOL, Sec. 4.2): LM solves as a torch op.

Shapes, index orders and the parameter layout follow the problem contract in
:mod:`epo_casadi.game`. The layer maps predicted parameters ``p`` (``(..., n_p)``) and
initial joint strategies ``u_init`` (``(..., n_u)``) to optimized strategies ``u``
(``(..., n_u)``), their rolled-out states ``x(u, p)`` (``(..., n_x)``) and a status code per
problem (``(...)``, int64, not differentiable; :data:`STATUS_CODES`, :func:`decode_status`).
All leading dimensions (e.g. batch ``B`` x modes ``M``) are flattened into one batch of
problems that are solved together by a Gauss-Newton backend of :mod:`solvers.lm`
(the one ``options.backend`` names: :class:`solvers.structured.StructuredGN` by default,
:class:`solvers.fast_gn.FusedGN` with ``backend="fused"``, :class:`solvers.gn.DenseGN`
with ``backend="dense"``; any object with the same
``linearize`` / ``solve`` / ``energy`` methods can be plugged in); CasADi evaluates every
problem of the batch in one mapped call, never a Python loop per problem.

Forward pass
    Each of the ``S`` steps (paper Sec. 4.2, App. F.3: ``S = 2``, ``alpha = 0.3``,
    ``lambda = 10``, :meth:`solvers.lm.LMOptions.paper`) is::

        (J'J + lambda I) du_s = -J'r,     u_{s+1} = u_s + alpha du_s

    with ``r = r(u_s, p)`` and ``J = dr/du``. The outputs are exactly those of
    :func:`solvers.lm.solve_lm` with the same options and backend (tested bit for bit).

Backward modes (explicit choice, ``backward=``)
    ``"unrolled"`` (default)
        The exact vector-Jacobian product of the ``S`` steps. With ``A = J'J + lambda I``,
        one step's VJP for a cotangent ``ubar`` of ``u_{s+1}`` is::

            z    = A^{-1} (alpha ubar)                  (one solve, same backend, same A)
            a    = J du_s + r,   b = J z                (fixed vectors)
            phi  = a' J(u, p) z + b' (J(u, p) du_s + r(u, p))
            ubar_s = ubar - d phi / du,   pbar -= d phi / dp

        (differentiate ``A du = -J'r``: ``d du = -A^{-1}(dA du + d(J'r))``). ``phi`` is a
        CasADi function (:func:`~learning.layer_core.layer_functions`) built once from the
        symbolic graph of the game (forward ``jtimes`` for ``J z`` and ``J du``, then one
        reverse sweep), so the VJP costs one linear solve plus about one Hessian-vector
        product per step and problem. ``phi``'s gradient is evaluated either as that one graph over the whole
        trajectory (``vjp="monolithic"``, the reference) or stage-wise
        (``vjp="staged"``, :mod:`solvers.fast_vjp`: a tangent rollout, one small
        function per stage pattern mapped over its stages, an adjoint sweep; equal to
        rounding), which in generated C compiles in seconds where the one graph of a long
        horizon does not compile at all (``vjp="auto"``: staged with ``compiled=True``
        for large graphs). The forward pass stores its iterates ``u_s``, steps ``du_s`` and the
        backend's linearizations (for :class:`~solvers.lm.DenseGN` that is ``J`` and
        ``J'J``: ``S (n_r + n_u) n_u`` doubles per problem). The damping is fixed (no
        adaptive rejection, as in the paper); options with ``adaptive_damping=True`` or
        ``ellipsoidal=True`` are refused for this mode. With ``gtol``/``ftol`` > 0 a problem
        that stops early is frozen, exactly as in ``solve_lm``, and its later steps are the
        identity.
    ``"implicit"``
        The forward pass is :func:`solvers.lm.solve_lm` run to a tolerance (the options
        must set ``gtol`` or ``ftol`` > 0; default :class:`~solvers.lm.LMOptions`). At the
        solution ``grad_u E(u*, p) = 0``, so by the implicit function theorem, with the
        exact Hessian ``H = d^2E/du^2`` (``game.function('hessian')``)::

            w = H^{-1} ubar,      pbar = -(d grad_u E / dp)' w

        the second term being one reverse sweep of ``w' grad_u E(u, p)`` w.r.t. ``p`` (a
        CasADi function). The initial strategy gets a **zero** gradient: at a true local
        optimum the solution does not depend on where the solver started (the same
        convention as CasADi ``nlpsol`` sensitivities and Theseus' implicit mode). The
        gradient is only as good as the convergence: read the status (``CONVERGED`` vs
        ``MAX_ITER``). A singular ``H`` falls back to the pseudo-inverse. A control no
        residual depends on (a row of ``H`` exactly zero) gets ``w = 0`` on its own,
        without the fallback: see *Padded agents* below.

    The states output ``x(u, p)`` adds ``dx/du' xbar`` and ``dx/dp' xbar`` (a CasADi reverse
    function of the rollout) in both modes.

Padded agents
    An agent whose own weights and pair weights are all zero (a padded agent of a scene
    with fewer agents, :mod:`learning.masks`) adds no residual: its rows of ``r`` are
    zero and so are its columns of ``J`` (``w * dc/du`` with ``w = 0``). With ``D = I``
    (``ellipsoidal=False``, which both modes use) the row of the damped system
    ``(J'J + lambda I) du = -J'r`` for such a control reads ``lambda du = 0``: its controls
    never move from their initial value (0 for a pad) and are not optimized. The unrolled
    backward solves with the same matrix (non-singular for ``lambda > 0``); the implicit
    backward's exact Hessian has a zero row and column there, which its solve treats as
    decoupled (``w = 0`` on those controls, the pseudo-inverse's answer) instead of
    falling back to the pseudo-inverse of the whole system.

Precision and devices
    Inputs may be float32 or float64; the layer computes in float64 and casts the
    outputs (and the gradients) back to the input dtype (``promote_types`` of ``p`` and
    ``u_init``). CPU only inside: a CUDA tensor is copied to the CPU, solved there and the
    results copied back to its device (the solver is CasADi + numpy; there is no GPU code
    path and none has been tested).

Invalid inputs
    A ``meta`` tensor (a shape without values) or a sparse one is refused with
    :class:`epo_casadi.SpecError` naming the input. NaN/inf in ``p`` or ``u_init`` and
    negative weights (``w_own``/``w_pair`` groups)
    raise :class:`epo_casadi.SpecError` (a ``ValueError``) naming the input, the
    parameter entries and the problem index. With ``on_invalid="mask"`` such a problem is
    solved on safe stand-in values instead and masked: its outputs are zeros, its status
    is ``NONFINITE`` and its gradients are zero; the other problems are unaffected. A
    problem whose solve turns non-finite (status ``NONFINITE``, frozen at its last finite
    iterate as in ``solve_lm``) also gets zero gradients.

Numeric core
    The CasADi functions, the backend and the float64 solves and VJPs are
    :mod:`learning.layer_core` (numpy only); this module is the torch side (the autograd
    function and the module). :data:`STATUS_CODES` and :func:`status_code` are defined
    there, next to the code that writes the statuses, and are part of this module's
    interface (they decode :attr:`LayerOutput.status`).

Not thread-safe (the mapped CasADi functions share their buffers); double backward is
not supported.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
import torch
from torch import nn
from torch.autograd.function import once_differentiable

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame
from solvers.lm import LMOptions, check_options

from .layer_core import _NONFINITE, STATUS_CODES, _Core, status_code

__all__ = [
    "BACKWARD_MODES",
    "STATUS_CODES",
    "VJP_MODES",
    "GameLayer",
    "GameLayerFunction",
    "LayerOutput",
    "decode_status",
    "status_code",
]

BACKWARD_MODES = ("unrolled", "implicit")
#: how the unrolled mode evaluates one step's VJP (``GameLayer(vjp=...)``)
VJP_MODES = ("auto", "monolithic", "staged")
ON_INVALID = ("raise", "mask")


def decode_status(codes: torch.Tensor | np.ndarray) -> np.ndarray:
    """Object array of :class:`~solvers.result.Status` from a tensor of status codes."""
    c = codes.detach().cpu().numpy() if isinstance(codes, torch.Tensor) else np.asarray(codes)
    out = np.empty(c.shape, dtype=object)
    out.reshape(-1)[:] = [STATUS_CODES[int(v)] for v in c.reshape(-1)]
    return out


class LayerOutput(NamedTuple):
    """What :class:`GameLayer` returns (leading dims of the inputs kept)."""

    controls: torch.Tensor  #: optimized joint strategies ``(..., n_u)``
    states: torch.Tensor  #: rolled-out joint states ``(..., n_x)``
    status: torch.Tensor  #: int64 status codes ``(...)``, see :data:`STATUS_CODES`


# --------------------------------------------------------------------------------------
# torch
# --------------------------------------------------------------------------------------
def _to_numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to(device="cpu", dtype=torch.float64).contiguous().numpy().copy()


def _check_holds_values(name: str, t: torch.Tensor) -> None:
    """Refuse a tensor without values to solve on: a ``meta`` tensor (shape only) or a
    sparse one; :class:`SpecError` naming the input."""
    if t.is_meta:
        raise SpecError(
            name,
            "expected a tensor with values, got a 'meta' tensor (a shape without data); "
            "give a tensor on the CPU or a CUDA device",
        )
    if t.layout != torch.strided:
        raise SpecError(name, f"expected a dense (strided) tensor, got layout {t.layout}")


class GameLayerFunction(torch.autograd.Function):
    """``apply(core, p, u_init, batch_shape) -> (controls, states, status)`` on 2-D inputs.

    ``p``: ``(B, n_p)``, ``u_init``: ``(B, n_u)``; ``core`` is :attr:`GameLayer.core`.
    Use :class:`GameLayer`, which also broadcasts leading dimensions.
    """

    @staticmethod
    def forward(ctx, core: _Core, p: torch.Tensor, u_init: torch.Tensor, batch_shape: tuple = ()):
        game = core.game
        if p.ndim != 2 or p.shape[1] != game.n_p:
            raise SpecError("p", f"expected shape (B, {game.n_p}), got {tuple(p.shape)}")
        if u_init.ndim != 2 or u_init.shape != (p.shape[0], game.n_u):
            raise SpecError(
                "u_init", f"expected shape ({p.shape[0]}, {game.n_u}), got {tuple(u_init.shape)}"
            )
        for name, t in (("p", p), ("u_init", u_init)):
            _check_holds_values(name, t)
            if not t.is_floating_point():
                raise SpecError(name, f"expected a floating-point tensor, got {t.dtype}")
        dtype = torch.promote_types(p.dtype, u_init.dtype)
        device = p.device
        P, U0 = _to_numpy(p), _to_numpy(u_init)
        if P.shape[0] == 0:  # an empty batch: empty outputs, nothing to solve
            ctx.core, ctx.saved, ctx.P, ctx.ok = core, None, P, np.zeros(0, dtype=bool)
            ctx.dtypes = (p.dtype, u_init.dtype)
            ctx.devices = (p.device, u_init.device)
            out_s = torch.zeros(0, dtype=torch.int64, device=device)
            ctx.mark_non_differentiable(out_s)
            return (
                torch.zeros(0, game.n_u, dtype=dtype, device=device),
                torch.zeros(0, game.n_x, dtype=dtype, device=device),
                out_s,
            )
        shape = tuple(batch_shape)
        if int(np.prod(shape)) != P.shape[0]:
            shape = (P.shape[0],)
        valid = core.validate(U0, P, shape)
        if not valid.all():
            P = np.where(valid[:, None], P, core.defaults)
            U0 = np.where(valid[:, None], U0, 0.0)
        U, X, status, saved = core.forward(U0, P)
        U, X = np.array(U), np.array(X)
        U[~valid], X[~valid] = 0.0, 0.0
        status[~valid] = _NONFINITE
        ctx.core, ctx.saved, ctx.P = core, saved, P
        ctx.ok = status != _NONFINITE
        ctx.dtypes = (p.dtype, u_init.dtype)
        ctx.devices = (p.device, u_init.device)
        out_u = torch.from_numpy(U).to(device=device, dtype=dtype)
        out_x = torch.from_numpy(X).to(device=device, dtype=dtype)
        out_s = torch.from_numpy(status).to(device=device)
        ctx.mark_non_differentiable(out_s)
        return out_u, out_x, out_s

    @staticmethod
    @once_differentiable
    def backward(ctx, g_u, g_x, _g_status):
        core = ctx.core
        B = ctx.P.shape[0]
        if B == 0:  # an empty batch has empty gradients
            gp = gu = None
            if ctx.needs_input_grad[1]:
                gp = torch.zeros(0, core.game.n_p, device=ctx.devices[0], dtype=ctx.dtypes[0])
            if ctx.needs_input_grad[2]:
                gu = torch.zeros(0, core.game.n_u, device=ctx.devices[1], dtype=ctx.dtypes[1])
            return None, gp, gu, None
        gU = _to_numpy(g_u) if g_u is not None else np.zeros((B, core.game.n_u))
        gX = _to_numpy(g_x) if g_x is not None else None
        ok = ctx.ok[:, None]
        gU = np.where(ok, gU, 0.0)
        if gX is not None:
            gX = np.where(ok, gX, 0.0)
        pbar, ubar = core.vjp(ctx.saved, ctx.P, gU, gX)
        pbar = np.where(ok, pbar, 0.0)
        ubar = np.where(ok, ubar, 0.0)
        gp = gu = None
        if ctx.needs_input_grad[1]:
            gp = torch.from_numpy(pbar).to(device=ctx.devices[0], dtype=ctx.dtypes[0])
        if ctx.needs_input_grad[2]:
            gu = torch.from_numpy(ubar).to(device=ctx.devices[1], dtype=ctx.dtypes[1])
        return None, gp, gu, None


class GameLayer(nn.Module):
    """Differentiable potential-game solve: ``layer(p, u_init) -> LayerOutput``.

    Parameters
    ----------
    game: the :class:`~epo_casadi.game.PotentialGame` (contract in :mod:`epo_casadi.game`).
    options: :class:`~solvers.lm.LMOptions` (or a dict of them). Default:
        ``LMOptions.paper()`` (S = 2, alpha = 0.3, lambda = 10) for ``"unrolled"``,
        ``LMOptions()`` (adaptive LM to ``gtol``) for ``"implicit"``.
    backward: ``"unrolled"`` or ``"implicit"`` (see the module docstring).
    on_invalid: ``"raise"`` (NaN/inf inputs or negative weights raise ``SpecError``) or
        ``"mask"`` (such problems give zeros, status ``NONFINITE`` and zero gradients).
    backend: a Gauss-Newton backend instance (``linearize``/``solve``/``energy`` as
        :class:`solvers.lm.DenseGN`); default: the one ``options.backend`` names. For
        speed with two to four agents pass ``solvers.fast_gn.FusedGN(game, compiled=True)``
        (and ``compiled=True``): about 3x less CPU than ``StructuredGN(compiled=True)``
        on the RPI setting (``bench/bench_layer.py``).
    compiled: evaluate the backward pass's CasADi functions as generated C
        (:func:`solvers.codegen.compile_functions`, compiled once and cached on disk in
        ``cache_dir``; needs a C compiler). Values are unchanged up to rounding; the
        forward rollout always stays interpreted, and so does any function above
        :data:`~learning.layer_core.MAX_COMPILED_INSTRUCTIONS` (named in
        :attr:`interpreted`).
    vjp: how the unrolled mode evaluates one step's VJP: ``"monolithic"`` (one CasADi
        graph of the whole trajectory, :func:`~learning.layer_core.layer_functions`; the
        reference), ``"staged"`` (:func:`solvers.fast_vjp.staged_step_vjp`: stage
        functions, a tangent rollout and an adjoint sweep; equal to rounding; an error for
        games without stage structure) or ``"auto"``: staged with ``compiled=True`` where
        the one graph is large (above
        :data:`~learning.layer_core.STAGED_VJP_MIN_INSTRUCTIONS`: there the staged C is 2
        to 9x faster (:mod:`solvers.fast_vjp`, ``bench/bench_layer.py --part vjp``), where the one graph compiles at ``-O0`` in
        minutes or not at all), else monolithic (small graphs compile well and run faster;
        interpreted, both cost about the same). :attr:`vjp` says which is used.
    """

    def __init__(
        self,
        game: PotentialGame,
        options: LMOptions | dict | None = None,
        backward: str = "unrolled",
        *,
        on_invalid: str = "raise",
        backend=None,
        compiled: bool = False,
        cache_dir: str | None = None,
        vjp: str = "auto",
    ):
        super().__init__()
        if not isinstance(game, PotentialGame):
            raise SpecError("game", f"expected a PotentialGame, got {type(game).__name__}")
        if backward not in BACKWARD_MODES:
            raise SpecError("backward", f"expected one of {BACKWARD_MODES}, got {backward!r}")
        if vjp not in VJP_MODES:
            raise SpecError("vjp", f"expected one of {VJP_MODES}, got {vjp!r}")
        if on_invalid not in ON_INVALID:
            raise SpecError("on_invalid", f"expected one of {ON_INVALID}, got {on_invalid!r}")
        if options is None:
            options = LMOptions.paper() if backward == "unrolled" else LMOptions()
        options = check_options(LMOptions, options, "options")
        if backward == "unrolled":
            if options.adaptive_damping:
                raise SpecError(
                    "options.adaptive_damping",
                    "the unrolled layer uses a fixed damping (as the paper); set adaptive_damping=False "
                    "(e.g. LMOptions.paper()) or use backward='implicit'",
                )
            if options.ellipsoidal:
                raise SpecError(
                    "options.ellipsoidal",
                    "the unrolled layer supports D = I only; set ellipsoidal=False",
                )
        elif options.gtol <= 0 and options.ftol <= 0:
            raise SpecError(
                "options",
                "backward='implicit' needs a converged solve: set gtol or ftol > 0 (e.g. LMOptions())",
            )
        self.game = game
        self.options = options
        self.backward = backward
        self.on_invalid = on_invalid
        self.compiled = bool(compiled)
        self.core = _Core(
            game, options, backward, on_invalid, backend, self.compiled, cache_dir, vjp
        )
        #: the backward-pass functions left interpreted despite ``compiled`` (too large)
        self.interpreted: list[str] = list(self.core.interpreted)
        #: how one step's VJP is evaluated: ``"staged"``, ``"monolithic"`` (None: implicit)
        self.vjp: str | None = self.core.vjp_mode

    def extra_repr(self) -> str:
        o = self.options
        return (
            f"N={self.game.N}, K={self.game.K}, n_u={self.game.n_u}, n_p={self.game.n_p}, "
            f"backward={self.backward!r}, steps={o.steps}, step_size={o.step_size}, damping={o.damping}"
        )

    # ---- forward --------------------------------------------------------------------------
    def forward(self, p: torch.Tensor, u_init: torch.Tensor | None = None) -> LayerOutput:
        """Solve every problem; ``p`` ``(..., n_p)``, ``u_init`` ``(..., n_u)`` (zeros if None).

        Leading dimensions broadcast against each other and are kept in the outputs.
        """
        g = self.game
        if not isinstance(p, torch.Tensor):
            raise SpecError("p", f"expected a torch.Tensor, got {type(p).__name__}")
        if p.ndim < 1 or p.shape[-1] != g.n_p:
            raise SpecError(
                "p", f"expected last dimension n_p = {g.n_p}, got shape {tuple(p.shape)}"
            )
        if u_init is None:
            u_init = torch.zeros(g.n_u, dtype=p.dtype, device=p.device)
        if not isinstance(u_init, torch.Tensor):
            raise SpecError("u_init", f"expected a torch.Tensor, got {type(u_init).__name__}")
        if u_init.ndim < 1 or u_init.shape[-1] != g.n_u:
            raise SpecError(
                "u_init", f"expected last dimension n_u = {g.n_u}, got shape {tuple(u_init.shape)}"
            )
        for name, t in (("p", p), ("u_init", u_init)):
            _check_holds_values(name, t)
        try:
            lead = torch.broadcast_shapes(p.shape[:-1], u_init.shape[:-1])
        except RuntimeError:
            raise SpecError(
                "p/u_init",
                f"leading dimensions do not broadcast: {tuple(p.shape)} and {tuple(u_init.shape)}",
            ) from None
        P = p.expand(*lead, g.n_p).reshape(-1, g.n_p)
        U = u_init.expand(*lead, g.n_u).reshape(-1, g.n_u)
        u, x, s = GameLayerFunction.apply(self.core, P, U, tuple(lead))
        return LayerOutput(u.reshape(*lead, g.n_u), x.reshape(*lead, g.n_x), s.reshape(lead))

    # ---- parameters -----------------------------------------------------------------------
    def default_params(self, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
        """The spec's default parameter vector ``(n_p,)``."""
        return torch.as_tensor(self.game.params.defaults(), dtype=dtype, device=device)

    def param_index(self, group: str) -> torch.Tensor:
        """Indices into ``p`` of a parameter group (``x0``, ``goal``, ``vref``, ``path``,
        ``w_own``, ``w_pair``), in the order of :attr:`PotentialGame.params`."""
        return torch.as_tensor(self.game.params.group(group), dtype=torch.long)

    def assemble_params(
        self,
        base: torch.Tensor | None = None,
        *,
        x0: torch.Tensor | None = None,
        goal: torch.Tensor | None = None,
        vref: torch.Tensor | None = None,
        path: torch.Tensor | None = None,
        w_own: torch.Tensor | None = None,
        w_pair: torch.Tensor | None = None,
        blocks: Mapping[str, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Differentiable ``p`` ``(..., n_p)``: ``base`` with groups / named blocks replaced.

        A group value has the group's entries last, ``(..., size)``, in parameter order
        (e.g. ``goal`` is ``goal.<a0>.x, goal.<a0>.y, goal.<a1>.x, ...``); a trailing
        ``(N, size / N)`` is accepted too. ``blocks`` maps block names of
        :attr:`PotentialGame.params` (``"w.robot.goal"``) to ``(..., block size)`` values.
        ``base`` defaults to :meth:`default_params` in the (promoted) dtype of the values,
        float64 if there are none. Leading dimensions broadcast; the result is
        differentiable w.r.t. ``base`` and every value (an index copy).
        """
        layout = self.game.params
        parts: list[tuple[str, np.ndarray, torch.Tensor]] = []
        for group, v in (
            ("x0", x0),
            ("goal", goal),
            ("vref", vref),
            ("path", path),
            ("w_own", w_own),
            ("w_pair", w_pair),
        ):
            if v is not None:
                parts.append((group, layout.group(group), v))
        for name, v in (blocks or {}).items():
            b = layout[name]
            parts.append((name, np.arange(b.start, b.start + b.size), v))
        given = [v for _, _, v in parts if isinstance(v, torch.Tensor)]
        if base is not None:
            dtype, device = base.dtype, base.device
        else:
            floats = [v.dtype for v in given if v.is_floating_point()]
            dtype = floats[0] if floats else torch.float64
            for d in floats[1:]:
                dtype = torch.promote_types(dtype, d)
            device = given[0].device if given else None
        p = self.default_params(dtype, device) if base is None else base
        if p.shape[-1] != layout.size:
            raise SpecError(
                "base", f"expected last dimension n_p = {layout.size}, got {tuple(p.shape)}"
            )
        vals = []
        for name, idx, v in parts:
            v = torch.as_tensor(v, dtype=dtype, device=device)
            k = idx.size
            if k == 0:
                raise SpecError(name, "this game has no parameters in that group")
            if v.ndim >= 2 and v.shape[-1] != k and v.shape[-2] * v.shape[-1] == k:
                v = v.reshape(*v.shape[:-2], k)
            if v.ndim == 0 or v.shape[-1] != k:
                raise SpecError(
                    name, f"expected a last dimension of {k} entries, got shape {tuple(v.shape)}"
                )
            vals.append((name, torch.as_tensor(idx, dtype=torch.long, device=device), v))
        try:
            lead = torch.broadcast_shapes(p.shape[:-1], *[v.shape[:-1] for _, _, v in vals])
        except RuntimeError:
            raise SpecError(
                "params", "leading dimensions of base and values do not broadcast"
            ) from None
        p = p.expand(*lead, layout.size)
        for _, idx, v in vals:
            p = p.index_copy(p.ndim - 1, idx, v.expand(*lead, v.shape[-1]))
        return p

    # ---- status ---------------------------------------------------------------------------
    decode_status = staticmethod(decode_status)
