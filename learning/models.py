"""Networks: observation encoders, parameter decoders and the three predictors.

Shapes: ``B`` scenes, ``N`` agents, ``H+1`` history steps (the last is the current
step), ``M`` modes, ``K`` future steps. A scene batch is a dict of tensors:

- ``history``: ``(B, H+1, N, 4)`` past states ``(x, y, v, theta)`` (only ``x, y`` are
  observed by the encoders, as in the paper; the current full state is the game's
  initial state);
- ``goals`` (optional): ``(B, N, 2)`` goal positions (given in RPI, paper App. F.3; read
  only by ours with ``goal_decoder="given"``);
- ``goal_candidates`` (optional): ``(B, N, G, 2)`` candidate goal points per agent, with
  ``goal_candidates_mask`` ``(B, N, G)`` (used by ``goal_decoder="candidates"``);
- ``lanes`` (optional): ``(B, L, P, 2)`` lane polylines, ``lanes_mask`` ``(B, L)``;
- ``paths`` (optional): ``(B, N, P, 2)`` each agent's reference lane and ``vref``
  (optional) ``(B, N)`` its reference speed: ours fills the game's ``path`` / ``vref``
  parameter blocks with them (left-turn and exiD-layout datasets);
- ``goal_lane`` (optional): ``(B, N, G)`` the index in ``lanes`` of the lane each goal
  candidate lies on (-1: none): ours' ``lane`` term follows the lane of each mode's goal
  (``ModelConfig.lane_path``, the paper's ``c_lane``).

Encoders (paper App. F.1): every agent's history is a polyline of vectors
``(start xy, end xy, time)``; a 3-layer LSTM of width 64 encodes it (V-LSTM); lanes go
through a PointNet-like encoder (3 layers, width 64, max-pool); a global interaction
graph of width 128 updates the agent features with one attention layer over agents
and lanes (``backbone="vlstm"``) or with the two-stage map-then-agent attention
(``backbone="vibes"``); HiVT-M (``backbone="hivt"``) encodes each history with a
transformer in the agent's own frame. The encoders live in :mod:`learning.backbones`.
``"tgl"`` (+ TGL, a convex QP layer on OSQP) is in :mod:`learning.tgl`.

Predictors (:func:`build_model`):

- ``"epo"`` (ours): an agent-weight decoder (per agent, shared, positive, batch norm), an
  interaction-weight decoder (all agents' features), an initial-strategy decoder (per
  agent, shared) feed the differentiable game layer (:mod:`learning.layer`), which runs
  ``S`` LM steps on all ``B x M`` problems; a scene-probability decoder reads
  ``[all agents' features, optimized states]``. The goals of the game come from the scene
  (``goal_decoder="given"``, RPI) or from a goal decoder (:class:`GoalDecoder`):
  ``"candidates"`` (TNT-style categorical over candidate points, the ``M`` most likely
  per agent become its goals in modes ``1..M``; exiD, CARLA) or ``"regress"`` (``M``
  goals per agent regressed; Waymo). Ablations: ``learned_init=False``
  (zeros as initial strategies), ``goal_features=False`` (the goal term's weight is
  fixed to zero, so the game has no goal feature).
- ``"sc"`` (V-LSTM + SC): the same encoder; controls are decoded directly per mode and
  rolled out through the game's own CasADi rollout (:class:`learning.bridge.GameRollout`:
  the same dynamics as the game, built-in or a user's; no solve), trained with the scene
  loss.
- ``"vlstm"`` (V-LSTM marginal): per agent ``M`` position trajectories and per-agent mode
  logits, trained with the marginal minADE loss plus classification.

Padded agents (scene ``agents_mask`` ``(B, N)`` False; :mod:`learning.masks`)
    Every forward starts from :func:`learning.masks.neutral_scene` (a pad's every value
    replaced by a fixed finite one, far from the real agents) and gives the encoder the
    mask (a pad's feature is zero and no other agent attends to it). Ours: a pad's own
    weights and the weights of every pair it is in are 0, so it adds no residual and no
    collision pair; its initial strategy is 0 and, with every column of ``J`` that belongs
    to it zero, the layer's damped steps leave it at 0: the pad stays at rest at its
    neutral position. The goal and agent-weight decoders run on the real agents only (their
    batch norm never sees a pad); a pad's goals are its position. + SC: a pad's controls
    are 0. V-LSTM: a pad's trajectory is its position, its mode logits 0. The decoders
    that read all agents at once (the pair-weight decoder, the scene-probability decoder)
    see for a pad a zero feature and zero displacements: a constant, whatever the pad's
    recorded values.
    Without a pad (no ``agents_mask``, or all True) every number is the one computed
    without the mask.

Modules. The settings (:class:`ModelConfig`, :data:`SIZE_LIMITS`, :data:`GOAL_DECODERS`,
:data:`OWN_NORMS`, :data:`LAYER_BACKENDS`, :data:`EXECUTION_SETTINGS`,
:func:`layer_execution`) live in :mod:`learning.model_config`; this module holds the
networks and :func:`build_model`, and every name stays importable from here.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import nn

from epo_casadi.errors import SpecError
from epo_casadi.features import Collision
from epo_casadi.game import PotentialGame
from solvers.lm import LMOptions

from . import backbones as _backbones
from . import masks as _masks
from .bridge import GameRollout
from .model_config import EXECUTION_SETTINGS as EXECUTION_SETTINGS
from .model_config import GOAL_DECODERS as GOAL_DECODERS
from .model_config import LAYER_BACKENDS as LAYER_BACKENDS
from .model_config import OWN_NORMS as OWN_NORMS
from .model_config import SIZE_LIMITS as SIZE_LIMITS
from .model_config import ModelConfig as ModelConfig
from .model_config import layer_execution as layer_execution

__all__ = [
    "GOAL_DECODERS",
    "GoalDecoder",
    "goal_candidates",
    "goal_paths",
    "scene_reference",
    "ModelConfig",
    "SIZE_LIMITS",
    "LAYER_BACKENDS",
    "OWN_NORMS",
    "EXECUTION_SETTINGS",
    "layer_execution",
    "build_model",
    "model_class",
    "MODEL_KINDS",
    "EPOModel",
    "SCModel",
    "VLSTMModel",
    "Encoder",
]


mlp = _backbones.mlp  # one MLP builder for the encoders and the decoders


def on_rows(net: nn.Module, inp: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    """``net`` on the rows ``rows`` (bool, ``(len(inp),)``) of ``inp`` ``(R, d)``, zeros on
    the others (None or all True: every row, the same numbers as ``net(inp)``). A batch
    norm in ``net`` then counts only those rows; in training with fewer than two of them
    (batch norm needs two) it runs on every row."""
    if rows is None or bool(rows.all()):
        return net(inp)
    idx = torch.nonzero(rows).flatten()
    if net.training and len(idx) < 2:
        return net(inp)
    out = net(inp[idx])
    return out.new_zeros(inp.shape[0], out.shape[1]).index_copy(0, idx, out)


# The observation encoders (V-LSTM, VIBES, HiVT-M) live in learning.backbones.
Encoder = _backbones.Encoder


def goal_candidates(scene: dict, cfg: ModelConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidate goal points ``(B, N, G, 2)`` and their mask ``(B, N, G)`` for every agent.

    In order of preference: the scene's ``goal_candidates`` (a dataset that extracts them,
    e.g. from the centerlines of the current and neighbouring lanes as in the paper); the
    points of the scene's lane polylines (shared by all agents, masked by ``lanes_mask``);
    otherwise a polar grid in each agent's heading frame around its current position:
    ``goal_rings`` rings up to ``goal_range`` metres times ``goal_angles`` directions
    (5 x 12 = 60 points by default, the paper's ``G``).
    """
    hist = scene["history"]
    B, N = hist.shape[0], hist.shape[2]
    if "goal_candidates" in scene:
        cand = scene["goal_candidates"].to(hist.dtype)
        if cand.ndim != 4 or cand.shape[:2] != (B, N) or cand.shape[-1] != 2:
            raise SpecError(
                "goal_candidates", f"expected shape ({B}, {N}, G, 2), got {tuple(cand.shape)}"
            )
        mask = scene.get("goal_candidates_mask")
        mask = (
            torch.ones(cand.shape[:3], dtype=torch.bool, device=cand.device)
            if mask is None
            else mask.bool()
        )
        return cand, mask
    lanes = scene.get("lanes")
    if lanes is not None:
        L, P = lanes.shape[1:3]
        cand = lanes.to(hist.dtype).reshape(B, 1, L * P, 2).expand(B, N, -1, -1)
        lm = scene.get("lanes_mask")
        lm = torch.ones(B, L, dtype=torch.bool, device=lanes.device) if lm is None else lm.bool()
        mask = lm[:, :, None].expand(B, L, P).reshape(B, 1, L * P).expand(B, N, -1)
        return cand, mask
    cur = hist[:, -1]  # (B, N, 4): x, y, v, heading
    R, A = cfg.goal_rings, cfg.goal_angles
    dev = hist.device
    radii = cfg.goal_range * torch.arange(1, R + 1, dtype=hist.dtype, device=dev) / R
    ang = (
        cur[..., 3:4] + 2 * torch.pi * torch.arange(A, dtype=hist.dtype, device=dev) / A
    )  # (B, N, A)
    dirs = torch.stack([torch.cos(ang), torch.sin(ang)], -1)  # (B, N, A, 2)
    cand = cur[:, :, None, None, :2] + radii[:, None, None] * dirs[:, :, None]  # (B, N, R, A, 2)
    cand = cand.reshape(B, N, R * A, 2)
    return cand, torch.ones(B, N, R * A, dtype=torch.bool, device=dev)


def scene_reference(scene: dict, field: str, agent: int, size: int) -> torch.Tensor:
    """Agent ``agent``'s fixed game reference from the scene, flattened to ``(B, size)``.

    ``paths`` ``(B, N, P, 2)`` fill the ``path`` block (``x_0, y_0, x_1, y_1, ...``, so
    ``size = 2 P``); ``vref`` ``(B, N)`` fills the ``vref`` block and ``radius`` ``(B, N)``
    the ``radius`` block (``size = 1``).
    """
    t = scene[field]
    B = scene["history"].shape[0]
    N = scene["history"].shape[2]
    if t.ndim < 2 or t.shape[:2] != (B, N) or int(np.prod(t.shape[2:])) != size:
        want = f"({B}, {N}, {size // 2}, 2)" if field == "paths" else f"({B}, {N})"
        raise SpecError(field, f"expected shape {want} for the game, got {tuple(t.shape)}")
    return t[:, agent].reshape(B, size)


def goal_paths(scene: dict, goal_index: torch.Tensor, size: int) -> torch.Tensor:
    """Each mode's reference lane ``(B, N, M, size)`` (``size = 2 P``, flattened like
    :func:`scene_reference`): the polyline ``lanes[goal_lane[b, i, goal_index[b, i, m]]]``
    the chosen goal candidate lies on, or the scene's ``paths`` (its current lane) where the
    candidate lies on no lane (``goal_lane`` -1). ``goal_index`` ``(B, N, M)`` indexes the
    scene's candidates. One gather over the batch, agents and modes."""
    lanes, gl = scene["lanes"], scene["goal_lane"]
    B, N, M = goal_index.shape
    if lanes.ndim != 4 or int(np.prod(lanes.shape[2:])) != size:
        raise SpecError(
            "lanes",
            f"expected shape ({B}, L, {size // 2}, 2) to give the game's path, got "
            f"{tuple(lanes.shape)}",
        )
    if gl.shape[:2] != (B, N):
        raise SpecError("goal_lane", f"expected shape ({B}, {N}, G), got {tuple(gl.shape)}")
    sel = gl.to(goal_index.device).long().gather(2, goal_index)  # (B, N, M) lane index or -1
    flat = lanes.reshape(B, lanes.shape[1], size)
    take = flat.gather(1, sel.clamp(min=0).reshape(B, N * M, 1).expand(B, N * M, size))
    take = take.reshape(B, N, M, size)
    cur = scene["paths"].reshape(B, N, 1, size).to(take.dtype).expand(B, N, M, size)
    return torch.where((sel >= 0)[..., None], take, cur)


class GoalDecoder(nn.Module):
    """Goal decoder ``phi_goal`` (paper Sec. 4.1, App. F.1), shared by all agents.

    ``"candidates"``: a 3-layer MLP (batch norm) scores ``[z_i, candidate - position_i]``
    for every candidate of :func:`goal_candidates`; the ``M`` most likely candidates of
    agent ``i`` are its goals in modes ``1..M``. ``"regress"``: a 3-layer MLP (batch norm)
    maps ``z_i`` to ``M`` goal offsets from the agent's current position.

    ``forward`` returns ``goals`` ``(B, M, N, 2)`` and, for candidates, ``goal_logits``
    ``(B, N, G)`` (masked candidates at the dtype's lowest value), ``goal_candidates``
    ``(B, N, G, 2)``, ``goal_candidates_mask`` and ``goal_index`` ``(B, N, M)`` (the
    candidates chosen for modes ``1..M``).
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        W, w, M = cfg.global_width, cfg.dec_width, cfg.modes
        out = 1 if cfg.goal_decoder == "candidates" else 2 * M
        inp = W + 2 if cfg.goal_decoder == "candidates" else W
        self.net = nn.Sequential(
            nn.Linear(inp, w), nn.BatchNorm1d(w), nn.ReLU(),
            nn.Linear(w, w), nn.BatchNorm1d(w), nn.ReLU(),
            nn.Linear(w, out),
        )  # fmt: skip

    def _net(self, inp: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
        """The MLP on the rows ``rows`` (bool, ``(len(inp),)``) of ``inp``, zeros on the others
        (None: every row; :func:`on_rows`). Batch norm then counts only those rows."""
        return on_rows(self.net, inp, rows)

    def forward(self, scene: dict, z: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
        """``mask`` ``(B, N)`` (None: every agent real): the MLP runs on the real agents'
        rows only (its batch norm never sees a pad); a pad's logits are 0 and its regressed
        goals are its current position."""
        B, N, W = z.shape
        M = self.cfg.modes
        cur = scene["history"][:, -1, :, :2].to(z.dtype)  # (B, N, 2)
        if self.cfg.goal_decoder == "regress":
            rows = None if mask is None else mask.reshape(B * N)
            off = self._net(z.reshape(B * N, W), rows).reshape(B, N, M, 2)
            return {"goals": (cur[:, :, None] + off).permute(0, 2, 1, 3)}
        cand, cand_mask = goal_candidates(scene, self.cfg)
        cand = cand.to(z.dtype)
        G = cand.shape[2]
        if G < M:
            raise SpecError(
                "goal_candidates", f"expected at least M = {M} candidates per agent, got {G}"
            )
        rel = cand - cur[:, :, None]
        inp = torch.cat([z[:, :, None].expand(B, N, G, W), rel], -1).reshape(B * N * G, W + 2)
        rows = None if mask is None else mask[:, :, None].expand(B, N, G).reshape(-1)
        logits = self._net(inp, rows).reshape(B, N, G)
        logits = logits.masked_fill(~cand_mask.to(logits.device), torch.finfo(logits.dtype).min)
        top = logits.topk(M, dim=-1).indices  # (B, N, M): most likely first
        goals = cand.gather(2, top[..., None].expand(B, N, M, 2))
        return {
            "goals": goals.permute(0, 2, 1, 3),
            "goal_logits": logits,
            "goal_candidates": cand,
            "goal_candidates_mask": cand_mask,
            "goal_index": top,
        }


class _Base(nn.Module):
    def __init__(self, cfg: ModelConfig, game: PotentialGame):
        super().__init__()
        if len(set(game.nx)) != 1 or len(set(game.nu)) != 1:
            raise ValueError(
                "game: the decoders are shared across agents, so all agents need dynamics "
                f"with the same numbers of states and controls, got nx {game.nx}, nu {game.nu}"
            )
        self.cfg, self.game = cfg, game
        self.N, self.K, self.nu = game.N, game.K, game.nu[0]
        #: the game's own rollout as a torch op (any dynamics; see learning.bridge)
        self.rollout = GameRollout(game)
        self.encoder = Encoder(cfg)
        W, M = cfg.global_width, cfg.modes
        self.prob = nn.Sequential(
            nn.Linear(self.N * W + self.N * self.K * 2, 16 * M),
            nn.BatchNorm1d(16 * M),
            nn.ReLU(),
            nn.Linear(16 * M, 16 * M),
            nn.BatchNorm1d(16 * M),
            nn.ReLU(),
            nn.Linear(16 * M, 1),
        )

    def scene_logits(self, z: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """Scene-probability decoder on ``[z_all, X^m]`` for every mode -> logits ``(B, M)``.

        ``X^m`` are the displacements from each agent's first predicted position. A padded
        agent contributes a constant: its feature is zero (the encoder's) and it stays at
        rest (zero displacements)."""
        B, M = pos.shape[:2]
        zin = z.reshape(B, 1, -1).expand(B, M, -1)
        inp = torch.cat([zin, (pos - pos[:, :, :, :1]).reshape(B, M, -1)], -1).reshape(B * M, -1)
        return self.prob(inp.to(z.dtype)).reshape(B, M)


class EPOModel(_Base):
    """Ours: decoders -> game layer (S LM steps on B x M problems) -> scene probabilities."""

    def __init__(self, cfg: ModelConfig, game: PotentialGame):
        game = model_game(game, cfg)
        super().__init__(cfg, game)
        from .layer import GameLayer

        L = game.params
        self.own_idx = torch.as_tensor(L.group("w_own"))
        self.pair_idx = torch.as_tensor(L.group("w_pair"))
        self.n_own = len(self.own_idx) // self.N
        if self.n_own * self.N != len(self.own_idx):
            raise ValueError("game: every agent needs the same own features")
        self.goal_w = [L[f"w.{a}.goal"].start for a in game.agent_names if f"w.{a}.goal" in L]
        self.goal_idx = [L[f"goal.{a}"].slice for a in game.agent_names if f"goal.{a}" in L]
        if cfg.goal_decoder != "given" and len(self.goal_idx) != self.N:
            raise SpecError(
                "model.goal_decoder",
                f"the game needs a goal parameter per agent to decode goals; it has "
                f"{len(self.goal_idx)} of {self.N}",
            )
        self.goal_dec = GoalDecoder(cfg) if cfg.goal_decoder != "given" else None
        W, M, w = cfg.global_width, cfg.modes, cfg.dec_width
        norm = "batch" if cfg.own_norm == "batch" else None
        self.own_dec = nn.Sequential(mlp(W, w, M * self.n_own, norm=norm), nn.Softplus())
        self.pair_dec = nn.Sequential(
            mlp(self.N * W, w, M * len(self.pair_idx), norm="layer"), nn.Softplus()
        )
        self.init_dec = mlp(W, w, M * self.K * self.nu, norm="layer")
        backend, compiled = layer_execution(cfg)
        run = {"backend": backend, "compiled": compiled and backend != "dense"}
        opts = LMOptions.paper(
            steps=cfg.lm_steps, step_size=cfg.step_size, damping=cfg.damping, **run
        )
        if cfg.backward == "implicit":
            opts = LMOptions(
                steps=max(cfg.lm_steps, 50),
                step_size=1.0,
                damping=cfg.damping,
                adaptive_damping=False,
                **run,
            )
        self.layer = GameLayer(game, opts, backward=cfg.backward, compiled=compiled)
        self.register_buffer("base_params", torch.as_tensor(L.defaults()), persistent=False)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """:meth:`torch.nn.Module.load_state_dict`; weights of an agent-weight decoder without
        batch norm (runs saved before ``ModelConfig.own_norm`` existed) into one with it are
        refused with one line naming the setting (a ``RuntimeError``, as for any misfit)."""
        if (
            self.cfg.own_norm == "batch"
            and "own_dec.0.2.weight" in state_dict
            and "own_dec.0.1.weight" not in state_dict
        ):
            raise RuntimeError(
                "agent-weight decoder saved without batch norm (a run from before "
                "model.own_norm): build the model with own_norm 'none'"
            )
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def decode_goals(self, scene: dict, z: torch.Tensor) -> dict:
        """Goals ``(B, M, N, 2)`` of every mode: the scene's, or the goal decoder's (and its
        logits). A padded agent's goals are its (neutral) current position."""
        scene = _masks.neutral_scene(scene)
        mask = scene.get("agents_mask")
        if self.goal_dec is not None:
            out = self.goal_dec(scene, z, mask)
            if mask is not None:
                cur = scene["history"][:, -1, :, :2].to(out["goals"].dtype)
                out["goals"] = _masks.where_agents(mask, out["goals"], cur[:, None], agent_dim=2)
            return {**out, "decoded_goals": True}
        if not self.goal_idx:
            return {}
        if "goals" not in scene:
            raise SpecError(
                "goals",
                "the scene has no goals; the model reads given goals (model.goal_decoder="
                "'given'): use a dataset with goals or goal_decoder 'candidates' or 'regress'",
            )
        g = scene["goals"].to(z.dtype)
        return {"goals": g[:, None].expand(g.shape[0], self.cfg.modes, -1, -1)}

    def game_params(
        self,
        scene: dict,
        z: torch.Tensor,
        goals: torch.Tensor | None = None,
        goal_index: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Parameters ``(B, M, n_p)``: current states from the scene, goals ``(B, M, N, 2)``
        (default: :meth:`decode_goals`), predicted weights; the ``path``, ``vref`` and
        ``radius`` (games with ``AgentSpec.radius_param``) blocks from the scene's
        ``paths``, ``vref`` and ``radius`` when present (:func:`scene_reference`), else the
        game's defaults. With ``lane_path="goal"`` and decoded candidates (``goal_index``
        ``(B, N, M)``) on a scene with ``goal_lane``, each mode's ``path`` is the lane of its
        goal (:func:`goal_paths`). A padded agent (scene ``agents_mask`` False) gets the
        neutral references of :func:`learning.masks.neutral_scene` and zero weights: its
        own weights and those of every pair it is in are 0 (no residual, no collision pair)."""
        scene = _masks.neutral_scene(scene)
        mask = scene.get("agents_mask")  # only where the scene has a pad
        B, M, N = z.shape[0], self.cfg.modes, self.N
        L = self.game.params
        p = self.base_params.to(z.dtype).expand(B, M, -1).clone()
        cur = scene["history"][:, -1]  # (B, N, 4)
        if goals is None and self.goal_idx:
            dec = self.decode_goals(scene, z)
            goals, goal_index = dec["goals"], dec.get("goal_index")
        for i, a in enumerate(self.game.agent_names):
            p[..., L[f"x0.{a}"].slice] = cur[:, None, i].to(z.dtype)
            if f"goal.{a}" in L:
                p[..., L[f"goal.{a}"].slice] = goals[:, :, i].to(z.dtype)
            # fixed references from the scene when it has them (else the game's defaults)
            for block, field in (("path", "paths"), ("vref", "vref"), ("radius", "radius")):
                if f"{block}.{a}" in L and field in scene:
                    ref = scene_reference(scene, field, i, L[f"{block}.{a}"].size)
                    p[..., L[f"{block}.{a}"].slice] = ref.to(z.dtype)[:, None]
        if self.cfg.lane_path == "goal" and goal_index is not None:
            names = self.game.agent_names
            if all(f"path.{a}" in L for a in names) and {"goal_lane", "paths"} <= scene.keys():
                size = L[f"path.{names[0]}"].size
                per_mode = goal_paths(scene, goal_index, size).to(z.dtype)  # (B, N, M, size)
                for i, a in enumerate(names):
                    p[..., L[f"path.{a}"].slice] = per_mode[:, i]
        if self.cfg.own_norm == "none":
            w_own = self.own_dec(z)
        else:  # batch norm over the real agents' rows (a pad's row is 0, then masked)
            rows = None if mask is None else mask.reshape(B * N)
            w_own = on_rows(self.own_dec, z.reshape(B * N, -1), rows)
        w_own = w_own.reshape(B, N, M, self.n_own).permute(0, 2, 1, 3).reshape(B, M, -1)
        w_pair = self.pair_dec(z.reshape(B, -1)).reshape(B, M, -1)
        if mask is not None:  # a pad: no residual, no collision pair
            zero = torch.zeros((), dtype=z.dtype, device=z.device)
            w_own = torch.where(_masks.own_mask(self.game, mask)[:, None], w_own, zero)
            w_pair = torch.where(_masks.pair_mask(self.game, mask)[:, None], w_pair, zero)
        p = p.index_copy(-1, self.own_idx.to(z.device), w_own)
        p = p.index_copy(-1, self.pair_idx.to(z.device), w_pair)
        if not self.cfg.goal_features and self.goal_w:
            p[..., self.goal_w] = 0.0
        return p

    def initial_strategies(self, z: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Initial strategies ``U_init`` ``(B, M, N * K * nu)`` of the layer from agent features
        ``z`` ``(B, N, W)`` (zeros for the ``learned_init=False`` ablation); zero for the
        padded agents of ``mask`` ``(B, N)`` (None: none)."""
        B, M = z.shape[0], self.cfg.modes
        u0 = self.init_dec(z).reshape(B, self.N, M, self.K * self.nu)
        if mask is not None:
            u0 = _masks.where_agents(mask, u0, 0.0)
        u0 = u0.permute(0, 2, 1, 3).reshape(B, M, -1)
        return u0 if self.cfg.learned_init else torch.zeros_like(u0)

    def forward(self, scene: dict) -> dict:
        scene = _masks.neutral_scene(scene)
        mask = scene.get("agents_mask")  # only where the scene has a pad
        z = self.encoder(scene)
        B, M = z.shape[0], self.cfg.modes
        goal_out = self.decode_goals(scene, z)
        p = self.game_params(scene, z, goal_out.get("goals"), goal_out.get("goal_index"))
        u0 = self.initial_strategies(z, mask)
        out = self.layer(p.double(), u0.double())
        x = out.states.to(z.dtype).reshape(B, M, self.N, self.K + 1, -1)[:, :, :, 1:]  # drop x_0
        pos = x[..., :2]
        init_pos = self.rollout.states(
            scene["history"][:, -1][:, None].to(z.dtype).expand(B, M, -1, -1),
            u0.reshape(B, M, self.N, self.K, self.nu),
        )[..., 1:, :2]
        return {
            "pos": pos,
            "states": x,
            "controls": out.controls.to(z.dtype).reshape(B, M, self.N, self.K, self.nu),
            "logits": self.scene_logits(z, pos),
            "params": p,
            "init_pos": init_pos,
            "status": out.status,
            **goal_out,
        }


class SCModel(_Base):
    """V-LSTM + SC: controls decoded per mode and rolled out, no game."""

    def __init__(self, cfg: ModelConfig, game: PotentialGame):
        super().__init__(cfg, game)
        self.ctrl_dec = mlp(
            cfg.global_width, cfg.dec_width, cfg.modes * self.K * self.nu, norm="layer"
        )

    def forward(self, scene: dict) -> dict:
        scene = _masks.neutral_scene(scene)
        mask = scene.get("agents_mask")  # only where the scene has a pad
        z = self.encoder(scene)
        B, M = z.shape[0], self.cfg.modes
        U = self.ctrl_dec(z).reshape(B, self.N, M, self.K, self.nu)
        if mask is not None:  # a pad stays at rest at its neutral position
            U = _masks.where_agents(mask, U, 0.0)
        U = U.permute(0, 2, 1, 3, 4)
        x0 = scene["history"][:, -1].to(z.dtype)[:, None].expand(B, M, -1, -1)
        x = self.rollout.states(x0, U)[..., 1:, :]  # drop x_0
        pos = x[..., :2]
        return {"pos": pos, "states": x, "controls": U, "logits": self.scene_logits(z, pos)}


class VLSTMModel(nn.Module):
    """V-LSTM marginal: per agent M position trajectories and per-agent mode logits."""

    def __init__(self, cfg: ModelConfig, game: PotentialGame):
        super().__init__()
        self.cfg, self.game, self.N, self.K = cfg, game, game.N, game.K
        self.encoder = Encoder(cfg)
        W, w, M = cfg.global_width, cfg.dec_width, cfg.modes
        self.traj_dec = mlp(W, w, M * self.K * 2, norm="layer")
        self.cls_dec = nn.Sequential(mlp(W, w, M))

    def forward(self, scene: dict) -> dict:
        scene = _masks.neutral_scene(scene)
        mask = scene.get("agents_mask")  # only where the scene has a pad
        z = self.encoder(scene)
        B, M = z.shape[0], self.cfg.modes
        cur = scene["history"][:, -1, :, :2].to(z.dtype)  # (B, N, 2)
        off = self.traj_dec(z).reshape(B, self.N, M, self.K, 2).cumsum(dim=3)
        logits = self.cls_dec(z)  # (B, N, M)
        if mask is not None:  # a pad: at rest at its neutral position, uniform modes
            off = _masks.where_agents(mask, off, 0.0)
            logits = _masks.where_agents(mask, logits, 0.0)
        pos = (cur[:, :, None, None] + off).permute(0, 2, 1, 3, 4)  # (B, M, N, K, 2)
        return {"pos": pos, "marginal_logits": logits}


#: model kind -> class, or its ``"module:Class"`` path, imported by :func:`model_class` on
#: first use (``"tgl"``: :mod:`learning.tgl` needs OSQP and SciPy's sparse matrices)
MODEL_KINDS: dict[str, type[nn.Module] | str] = {
    "epo": EPOModel,
    "sc": SCModel,
    "vlstm": VLSTMModel,
    "tgl": "learning.tgl:TGLModel",
}


def model_class(kind: str) -> type[nn.Module]:
    """The class of model kind ``kind``, importing its module when the table names a path."""
    cls = MODEL_KINDS[kind]
    if isinstance(cls, str):
        from epo_casadi.registry import load_class

        cls = MODEL_KINDS[kind] = load_class(cls, "model.kind")
    return cls


def model_game(game: PotentialGame, cfg: ModelConfig) -> PotentialGame:
    """The game of ours' layer: ``game`` with ``cfg.collision_margin`` (if set) as the margin
    of every collision feature; the same object when nothing changes."""
    m = cfg.collision_margin
    spec = game.spec
    if m is None or not any(isinstance(f, Collision) for f in spec.pair_features):
        return game
    pair = tuple(
        dataclasses.replace(f, margin=float(m)) if isinstance(f, Collision) else f
        for f in spec.pair_features
    )
    return PotentialGame(dataclasses.replace(spec, pair_features=pair))


def build_model(cfg: ModelConfig, game: PotentialGame) -> nn.Module:
    """The predictor named by ``cfg.kind`` for ``game`` (its agents, horizon and parameters)."""
    return model_class(cfg.kind)(cfg, game)


def count_parameters(model: nn.Module) -> int:
    return int(sum(np.prod(p.shape) for p in model.parameters() if p.requires_grad))
