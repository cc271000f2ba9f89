"""Observation encoders (backbones): one interface, three architectures (paper App. F.1).

Every backbone maps a scene dict to per-agent features ``z`` ``(B, N, W)`` with
``W = global_width``. It reads (shapes as in :mod:`learning.models`):

- ``history`` ``(B, H+1, N, 4)``: past states ``(x, y, v, theta)``, the last one current.
  Only ``x, y`` are encoded; HiVT-M also reads the current heading ``theta`` to build
  each agent's local frame.
- ``history_mask`` (optional) ``(B, H+1, N)`` bool: False marks an unobserved step of an
  agent. A vector (step ``t-1`` to ``t``) is used only if both ends are observed; a
  masked step's values cannot change any output.
- ``agents_mask`` (optional) ``(B, N)`` bool: False marks an absent agent (padding). Its
  history cannot change any other agent's feature, and its own feature is zero. The
  scene origin is the mean current position of the present agents.
- ``lanes`` (optional) ``(B, L, P, 2)`` lane polylines with ``lanes_mask`` ``(B, L)``.

``history_valid`` (extrapolated steps of RPI-style datasets) is deliberately not read:
those steps hold a plausible constant-velocity extrapolation the models were always
trained on. A dataset with truly missing observations writes ``history_mask``.

Backbones (``ModelConfig.backbone``):

- ``"vlstm"`` (V-LSTM): history polyline vectors ``(start xy, end xy, time)`` in the
  scene-centred frame through a 3-layer LSTM of width 64; lanes through a PointNet-like
  encoder (3 layers, width 64, max-pool); one attention layer of width 128 in which every
  agent attends to all agents and lanes.
- ``"vibes"`` (VIBES): the same history and lane encoders; the two-stage global graph:
  agents attend to the lanes (map features as keys), then to each other (agent features
  as keys), each with a residual connection and layer norm.
- ``"hivt"`` (HiVT-M): every agent's history is encoded on its own, in its local frame
  (origin at its current position, x axis along its current heading), by a transformer
  (depth ``hist_layers``, width ``hist_width``, layer norm) over the step vectors, read out
  through a learned summary token; the local feature plus an embedding of the agent's
  pose in the scene frame enter the same two-stage global graph as VIBES. The local
  encoding is invariant to rotating and translating the whole scene; the lanes are encoded
  in the scene frame, as for the other backbones (paper App. F.1), so the global features
  are not.

The V-LSTM and VIBES modules keep the parameter names and creation order they had in
:mod:`learning.models` (``lstm``, ``lane``, ``agent_proj``, ``lane_proj``, ``attn``,
``norm``, ``attn2``, ``norm2``): old checkpoints load and a seed gives the same weights.
"""

from __future__ import annotations

import torch
from torch import nn

from epo_casadi.errors import SpecError

__all__ = ["BACKBONES", "NORMS", "Encoder", "HistoryTransformer", "lane_features", "mlp"]

#: backbone names (``ModelConfig.backbone``) and their table labels
BACKBONES = {"vlstm": "V-LSTM", "vibes": "VIBES", "hivt": "HiVT-M"}


#: values of :func:`mlp`'s ``norm``
NORMS = (None, "layer", "batch")


def mlp(i: int, width: int, o: int, norm: str | None = None, layers: int = 3) -> nn.Sequential:
    """``layers`` linear layers of ``width`` with ReLU, each hidden one followed by LayerNorm
    (``norm="layer"``) or BatchNorm1d (``norm="batch"``: the input is ``(rows, i)``) before
    its ReLU, or by nothing (``None``)."""
    if norm not in NORMS:
        raise SpecError("norm", f"expected one of {NORMS}, got {norm!r}")
    mods: list[nn.Module] = []
    d = i
    for _ in range(layers - 1):
        mods.append(nn.Linear(d, width))
        if norm == "layer":
            mods.append(nn.LayerNorm(width))
        elif norm == "batch":
            mods.append(nn.BatchNorm1d(width))
        mods.append(nn.ReLU())
        d = width
    mods.append(nn.Linear(d, o))
    return nn.Sequential(*mods)


def _masks(scene: dict) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """``(step_mask (B, H+1, N), agents_mask (B, N))`` from the scene, ``None`` where absent."""
    hist = scene["history"]
    B, T1, N = hist.shape[:3]
    steps = scene.get("history_mask")
    agents = scene.get("agents_mask")
    if steps is not None:
        steps = steps.to(device=hist.device, dtype=torch.bool)
        if steps.shape != (B, T1, N):
            raise SpecError(
                "history_mask", f"expected shape {(B, T1, N)}, got {tuple(steps.shape)}"
            )
    if agents is not None:
        agents = agents.to(device=hist.device, dtype=torch.bool)
        if agents.shape != (B, N):
            raise SpecError("agents_mask", f"expected shape {(B, N)}, got {tuple(agents.shape)}")
        if steps is not None:
            steps = steps & agents[:, None]
        elif not bool(agents.all()):
            steps = agents[:, None].expand(B, T1, N)
    return steps, agents


def _origin(pos: torch.Tensor, agents: torch.Tensor | None) -> torch.Tensor:
    """Scene origin ``(B, 1, 1, 2)``: mean current position of the present agents."""
    cur = pos[:, -1]  # (B, N, 2)
    if agents is None:
        return cur.mean(dim=1)[:, None, None]
    w = agents.to(cur.dtype)[..., None]
    return ((cur * w).sum(1) / w.sum(1).clamp(min=1))[:, None, None]


def lane_features(
    lane_enc: nn.Module, lane_proj: nn.Module, scene: dict, origin: torch.Tensor
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """PointNet lane features ``(B, L, W)`` in the scene frame and the lane mask, or ``None``."""
    lanes = scene.get("lanes")
    if lanes is None:
        return None, None
    lanes = lanes.to(origin.dtype) - origin  # (B, 1, 1, 2) against (B, L, P, 2)
    lv = torch.cat([lanes[:, :, :-1], lanes[:, :, 1:]], -1)  # (B, L, P-1, 4)
    lz = lane_proj(lane_enc(lv).max(dim=2).values)  # (B, L, W)
    lmask = scene.get("lanes_mask")
    return lz, None if lmask is None else lmask.to(device=lz.device, dtype=torch.bool)


class Encoder(nn.Module):
    """V-LSTM / VIBES / HiVT-M: scene dict -> agent features ``(B, N, global_width)``.

    ``cfg`` is a :class:`learning.models.ModelConfig` (fields ``backbone``, ``hist_width``,
    ``hist_layers``, ``lane_width``, ``global_width``, ``heads``).
    """

    def __init__(self, cfg):
        super().__init__()
        self.cfg = cfg
        W, h = cfg.global_width, cfg.heads
        if cfg.backbone == "hivt":
            self.local = HistoryTransformer(cfg.hist_width, cfg.hist_layers, cfg.heads)
            # pose of the agent in the scene frame: (x, y, cos theta, sin theta)
            self.pose = mlp(4, cfg.hist_width, cfg.hist_width, norm="layer", layers=2)
        else:
            self.lstm = nn.LSTM(5, cfg.hist_width, num_layers=cfg.hist_layers, batch_first=True)
        self.lane = mlp(4, cfg.lane_width, cfg.lane_width, norm="layer")
        self.agent_proj = nn.Linear(cfg.hist_width, W)
        self.lane_proj = nn.Linear(cfg.lane_width, W)
        self.attn = nn.MultiheadAttention(W, h, batch_first=True)
        self.norm = nn.LayerNorm(W)
        if cfg.backbone in ("vibes", "hivt"):
            self.attn2 = nn.MultiheadAttention(W, h, batch_first=True)
            self.norm2 = nn.LayerNorm(W)

    # ----------------------------------------------------------------- agent histories
    def _lstm_features(self, hist, origin, steps) -> torch.Tensor:
        B, T1, N, _ = hist.shape
        h = hist - origin
        vec = torch.cat([h[:, :-1], h[:, 1:]], dim=-1)  # (B, H, N, 4)
        if steps is not None:  # a vector needs both ends observed
            ok = (steps[:, :-1] & steps[:, 1:])[..., None]
            vec = torch.where(ok, vec, torch.zeros_like(vec))
        t = torch.linspace(-1, 0, T1 - 1, dtype=h.dtype, device=h.device)[
            None, :, None, None
        ].expand(B, -1, N, 1)
        seq = torch.cat([vec, t], -1).permute(0, 2, 1, 3).reshape(B * N, T1 - 1, 5)
        _, (hn, _) = self.lstm(seq)
        return hn[-1].reshape(B, N, -1)

    def _hivt_features(self, hist, theta, origin, steps) -> torch.Tensor:
        loc = self.local(hist, theta, steps)  # (B, N, hist_width), frame-invariant
        cur = hist[:, -1] - origin[:, 0]  # (B, N, 2) in the scene frame
        pose = torch.cat([cur, torch.cos(theta)[..., None], torch.sin(theta)[..., None]], -1)
        return loc + self.pose(pose)

    # ----------------------------------------------------------------- forward
    def forward(self, scene: dict) -> torch.Tensor:
        hist = scene["history"][..., :2]  # (B, H+1, N, 2)
        B, T1, N, _ = hist.shape
        steps, agents = _masks(scene)
        if steps is not None:  # masked values never enter an arithmetic op
            hist = torch.where(steps[..., None], hist, torch.zeros_like(hist))
        origin = _origin(hist, agents)  # scene-centred coordinates
        if self.cfg.backbone == "hivt":
            theta = scene["history"][:, -1, :, 3].to(hist.dtype)
            if agents is not None:
                theta = torch.where(agents, theta, torch.zeros_like(theta))
            a = self._hivt_features(hist, theta, origin, steps)
        else:
            a = self._lstm_features(hist, origin, steps)
        z = self.agent_proj(a)  # (B, N, W)
        lz, lmask = lane_features(self.lane, self.lane_proj, scene, origin)
        if lz is None:
            lz = z[:, :0]
        apad = None if agents is None else ~agents  # key padding: True = ignore
        if self.cfg.backbone == "vlstm":
            kv = torch.cat([z, lz], 1)
            pad = None
            if lmask is not None or apad is not None:
                ap = torch.zeros(B, N, dtype=torch.bool, device=z.device) if apad is None else apad
                lp = (
                    torch.zeros(B, lz.shape[1], dtype=torch.bool, device=z.device)
                    if lmask is None
                    else ~lmask
                )
                pad = torch.cat([ap, lp], 1)
            out, _ = self.attn(z, kv, kv, key_padding_mask=pad)
            z = self.norm(z + out)
        else:
            # two-stage graph: agents attend to the map, then to each other
            if lz.shape[1]:
                lpad = None if lmask is None else ~lmask
                if lpad is not None:  # a scene without any lane: no map update (and no NaN)
                    none = lpad.all(1)
                    lpad = lpad & ~none[:, None]
                out, _ = self.attn(z, lz, lz, key_padding_mask=lpad)
                if lpad is not None:
                    out = torch.where(none[:, None, None], torch.zeros_like(out), out)
                z = self.norm(z + out)
            out, _ = self.attn2(z, z, z, key_padding_mask=apad)
            z = self.norm2(z + out)
        if agents is not None:
            z = torch.where(agents[..., None], z, torch.zeros_like(z))
        return z


class HistoryTransformer(nn.Module):
    """HiVT-M's local encoder: one agent's history in its own frame -> ``(B, N, width)``.

    Tokens are the step vectors ``(start xy, end xy)`` rotated into the agent's frame
    (origin: its current position, x axis: its current heading ``theta``) plus a learned
    embedding of the step index; a learned summary token is prepended and read out after
    ``layers`` pre-norm transformer layers (``heads`` heads, no dropout). Masked step
    vectors are padding keys; the summary token is always present.
    """

    def __init__(self, width: int, layers: int, heads: int, max_steps: int = 64):
        super().__init__()
        self.width, self.max_steps = width, max_steps
        self.embed = nn.Sequential(nn.Linear(4, width), nn.LayerNorm(width), nn.ReLU())
        self.step = nn.Parameter(torch.zeros(max_steps, width))
        self.summary = nn.Parameter(torch.zeros(width))
        nn.init.normal_(self.step, std=0.02)
        nn.init.normal_(self.summary, std=0.02)
        layer = nn.TransformerEncoderLayer(
            width, heads, dim_feedforward=2 * width, dropout=0.0, batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.out_norm = nn.LayerNorm(width)

    def local_vectors(self, hist: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """Step vectors ``(B, N, H, 4)`` in every agent's frame from positions ``(B, H+1, N, 2)``."""
        rel = hist - hist[:, -1:]  # origin at the current position
        c, s = torch.cos(theta)[:, None], torch.sin(theta)[:, None]  # (B, 1, N)
        x = c * rel[..., 0] + s * rel[..., 1]
        y = -s * rel[..., 0] + c * rel[..., 1]
        loc = torch.stack([x, y], -1)  # (B, H+1, N, 2)
        return torch.cat([loc[:, :-1], loc[:, 1:]], -1).permute(0, 2, 1, 3)

    def forward(
        self, hist: torch.Tensor, theta: torch.Tensor, steps: torch.Tensor | None = None
    ) -> torch.Tensor:
        B, T1, N, _ = hist.shape
        H = T1 - 1
        if H + 1 > self.max_steps:
            raise SpecError(
                "history", f"HiVT-M encodes at most {self.max_steps - 1} steps, got {H}"
            )
        vec = self.local_vectors(hist, theta)  # (B, N, H, 4)
        tok = self.embed(vec) + self.step[:H]
        tok = torch.cat([self.summary.expand(B, N, 1, self.width), tok], 2).reshape(
            B * N, H + 1, self.width
        )
        pad = None
        if steps is not None:
            ok = (steps[:, :-1] & steps[:, 1:]).permute(0, 2, 1).reshape(B * N, H)
            pad = torch.cat([torch.zeros(B * N, 1, dtype=torch.bool, device=ok.device), ~ok], 1)
            tok = torch.where(pad[..., None], torch.zeros_like(tok), tok)
        out = self.encoder(tok, src_key_padding_mask=pad)
        return self.out_norm(out[:, 0]).reshape(B, N, self.width)
