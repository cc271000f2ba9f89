"""Padded agents: the one place that knows how to neutralise them.

A scene of fewer than ``N`` recorded agents is padded to ``N``: the batch key
``agents_mask`` ``(B, N)`` bool is True on recorded agents and False on padding (the
padded slots' values are whatever the dataset wrote, zeros in the readers of
:mod:`scenarios.real`; nothing here relies on the real agents coming first). A scene
without the key, or with every agent True, has no padding, and every function below then
leaves it exactly as it is, so every number is the one computed without masks.

:func:`neutral_scene` replaces every per-agent value of a padded agent by a fixed finite
value with ``torch.where`` (never an arithmetic mix), so no value of a pad, however
extreme (1e30, inf, NaN), reaches an output or a gradient: ``torch.where`` passes no
gradient to the unselected branch. Per field (``B`` scenes, ``N`` agents; ``(px, py)`` the
pad's neutral position, :func:`pad_positions`):

==========================  ============================================================
field                       a padded agent's value
==========================  ============================================================
``history`` (B, H+1, N, 4)  ``(px, py, 0, 0)`` at every step: at rest, heading 0
``history_mask`` (B,H+1,N)  False (unobserved; the encoders mask the pad anyway)
``goals`` (B, N, 2)         ``(px, py)``
``goal_candidates``         ``(px + g + 1, py)`` for candidate ``g``: distinct points 1 m
(B, N, G, 2)                apart
``goal_candidates_mask``    True
``goal_lane`` (B, N, G)     -1 (on no lane)
``paths`` (B, N, P, 2)      ``(px + j, py)`` for vertex ``j``: a straight lane along x
``vref`` (B, N)             0
``radius``, ``length``,     1 (metres)
``width`` (B, N)
``gt`` (B, N, T, 2)         ``(px, py)``
``gt_states`` (B, N, T, 4)  ``(px, py, 0, 0)``
==========================  ============================================================

Every other key (``lanes``, ``lanes_mask``, ``history_valid``, ``index``, ...) holds no
per-agent value and is kept. ``lanes`` is the map, shared by all agents: a dataset that
stores per-agent lanes marks a pad's lanes False in ``lanes_mask``.

Neutral positions (:func:`pad_positions`): pad slot ``n`` of scene ``b`` stands at
``x = x_max + PAD_SPACING (n + 1)``, ``y = y_mean``, with ``x_max`` the largest and ``y_mean``
the mean observed ``x`` / ``y`` of the scene's real agents over the history (0 without
any). So every pad is at least :data:`PAD_SPACING` metres from every real agent's history
and from every other pad: no collision feature of a pair with a pad is active (and its
weight is zero as well, :func:`pair_mask`), and no two agents share a position (a
distance's derivative at zero is not finite). The positions are constants: they carry no
gradient.

:func:`pair_mask` gives, in a game's pair-weight order (``w.<a>-<b>.<feature>``, the order
of its ``w_pair`` parameter group, :mod:`epo_casadi.game`), True where both agents are
real; :func:`own_mask` the same for the ``w_own`` group. :func:`active` turns a mask into
``None`` when it marks no pad, the switch every masked code path uses to stay today's.
"""

from __future__ import annotations

import torch

from epo_casadi.errors import SpecError
from epo_casadi.game import PotentialGame

__all__ = [
    "NEUTRAL_FIELDS",
    "PAD_SPACING",
    "active",
    "agents_mask",
    "neutral_scene",
    "own_mask",
    "pad_positions",
    "pair_mask",
    "pairs_mask",
    "where_agents",
]

#: metres between a padded agent and the farthest real agent (and between two pads)
PAD_SPACING = 1000.0
#: the per-agent fields :func:`neutral_scene` replaces (see the module docstring)
NEUTRAL_FIELDS = (
    "history",
    "history_mask",
    "goals",
    "goal_candidates",
    "goal_candidates_mask",
    "goal_lane",
    "paths",
    "vref",
    "radius",
    "length",
    "width",
    "gt",
    "gt_states",
)
#: the value of a pad in the size fields (metres)
_UNIT_FIELDS = ("radius", "length", "width")


def agents_mask(scene: dict) -> torch.Tensor:
    """The scene's ``agents_mask`` ``(B, N)`` bool (all True when absent); a wrong shape is
    refused with :class:`SpecError` naming ``agents_mask``."""
    hist = scene["history"]
    B, N = hist.shape[0], hist.shape[2]
    m = scene.get("agents_mask")
    if m is None:
        return torch.ones(B, N, dtype=torch.bool, device=hist.device)
    m = torch.as_tensor(m)
    if m.shape != (B, N):
        raise SpecError("agents_mask", f"expected shape {(B, N)}, got {tuple(m.shape)}")
    return m.to(device=hist.device, dtype=torch.bool)


def active(mask: torch.Tensor | None) -> torch.Tensor | None:
    """``mask`` (bool) when it marks a padded agent (a False entry), else ``None``."""
    if mask is None:
        return None
    mask = torch.as_tensor(mask).to(torch.bool)
    return None if bool(mask.all()) else mask


def where_agents(mask: torch.Tensor, value: torch.Tensor, pad, agent_dim: int = 1):
    """``value`` on real agents, ``pad`` (a tensor or a number) on padded ones.

    ``mask`` ``(B, N)``; the agent axis of ``value`` is ``agent_dim`` (its batch axis 0);
    ``pad`` broadcasts against ``value``."""
    m = mask
    shape = [1] * value.ndim
    shape[0], shape[agent_dim] = mask.shape
    m = m.reshape(shape)
    if not isinstance(pad, torch.Tensor):
        pad = torch.full((), pad, dtype=value.dtype, device=value.device)
    return torch.where(m, value, pad.to(dtype=value.dtype, device=value.device))


def pad_positions(scene: dict, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Neutral positions ``(B, N, 2)`` of padded agents (module docstring; defined for every
    slot, used only on pads). Constants: detached from the scene."""
    hist = scene["history"].detach()
    B, T1, N = hist.shape[:3]
    mask = agents_mask(scene) if mask is None else mask
    xy = hist[..., :2]
    ok = mask[:, None, :].expand(B, T1, N)
    steps = scene.get("history_mask")
    if steps is not None:
        ok = ok & torch.as_tensor(steps).to(device=hist.device, dtype=torch.bool)
    ok = ok & torch.isfinite(xy).all(-1)
    okf = ok.flatten(1)
    x = xy[..., 0].flatten(1)
    y = xy[..., 1].flatten(1)
    lowest = torch.full((), -torch.inf, dtype=hist.dtype, device=hist.device)
    x_max = torch.where(okf, x, lowest).amax(1)
    any_real = okf.any(1)
    x_max = torch.where(any_real, x_max, torch.zeros_like(x_max))
    n = okf.sum(1).clamp(min=1).to(hist.dtype)
    y_mean = torch.where(okf, y, torch.zeros_like(y)).sum(1) / n
    slot = torch.arange(1, N + 1, dtype=hist.dtype, device=hist.device)
    px = x_max[:, None] + PAD_SPACING * slot  # (B, N)
    py = y_mean[:, None].expand(B, N)
    return torch.stack([px, py], -1)


def _field(scene: dict, key: str, shape: tuple, where_shape: str) -> torch.Tensor:
    t = scene[key]
    if tuple(t.shape[: len(shape)]) != shape:
        raise SpecError(key, f"expected shape {where_shape}, got {tuple(t.shape)}")
    return t


class _NeutralScene(dict):
    """A scene :func:`neutral_scene` returned (a plain dict otherwise): not neutralised twice."""


def neutral_scene(scene: dict) -> dict:
    """The scene with every per-agent value of a padded agent replaced by its neutral value
    (module docstring), as a new dict that keeps ``agents_mask``. Without padding (no
    ``agents_mask`` or all True) the scene itself, less ``agents_mask`` (so every consumer
    computes exactly what it computes without masks). Idempotent; a scene it returned is
    returned as it is."""
    if "agents_mask" not in scene or isinstance(scene, _NeutralScene):
        return scene
    mask = agents_mask(scene)
    if bool(mask.all()):
        return {k: v for k, v in scene.items() if k != "agents_mask"}
    out = _NeutralScene(scene)
    out["agents_mask"] = mask
    hist = scene["history"]
    B, T1, N = hist.shape[:3]
    pos = pad_positions(scene, mask).to(hist.dtype)  # (B, N, 2)
    state = torch.cat([pos, torch.zeros_like(pos)], -1)  # (B, N, 4): at rest, heading 0
    out["history"] = where_agents(mask, hist, state[:, None].to(hist.dtype), agent_dim=2)
    if "history_mask" in scene:
        hm = _field(scene, "history_mask", (B, T1, N), f"({B}, {T1}, {N})").to(torch.bool)
        out["history_mask"] = hm & mask[:, None]
    if "goals" in scene:
        g = _field(scene, "goals", (B, N), f"({B}, {N}, 2)")
        out["goals"] = where_agents(mask, g, pos.to(g.dtype))
    if "goal_candidates" in scene:
        c = _field(scene, "goal_candidates", (B, N), f"({B}, {N}, G, 2)")
        G = c.shape[2]
        off = torch.zeros(G, 2, dtype=c.dtype, device=c.device)
        off[:, 0] = torch.arange(1, G + 1, dtype=c.dtype, device=c.device)
        out["goal_candidates"] = where_agents(mask, c, pos.to(c.dtype)[:, :, None] + off)
    if "goal_candidates_mask" in scene:
        cm = _field(scene, "goal_candidates_mask", (B, N), f"({B}, {N}, G)").to(torch.bool)
        out["goal_candidates_mask"] = cm | ~mask[:, :, None]
    if "goal_lane" in scene:
        gl = _field(scene, "goal_lane", (B, N), f"({B}, {N}, G)")
        out["goal_lane"] = where_agents(mask, gl, -1)
    if "paths" in scene:
        pth = _field(scene, "paths", (B, N), f"({B}, {N}, P, 2)")
        P = pth.shape[2]
        off = torch.zeros(P, 2, dtype=pth.dtype, device=pth.device)
        off[:, 0] = torch.arange(P, dtype=pth.dtype, device=pth.device)
        out["paths"] = where_agents(mask, pth, pos.to(pth.dtype)[:, :, None] + off)
    if "vref" in scene:
        out["vref"] = where_agents(mask, _field(scene, "vref", (B, N), f"({B}, {N})"), 0.0)
    for k in _UNIT_FIELDS:
        if k in scene:
            out[k] = where_agents(mask, _field(scene, k, (B, N), f"({B}, {N})"), 1.0)
    if "gt" in scene:
        gt = _field(scene, "gt", (B, N), f"({B}, {N}, T, 2)")
        out["gt"] = where_agents(mask, gt, pos.to(gt.dtype)[:, :, None])
    if "gt_states" in scene:
        gs = _field(scene, "gt_states", (B, N), f"({B}, {N}, T, 4)")
        out["gt_states"] = where_agents(mask, gs, state.to(gs.dtype)[:, :, None])
    return out


def pairs_mask(pairs, mask: torch.Tensor) -> torch.Tensor:
    """``(B, len(pairs))`` bool: True where both agents ``(i, j)`` of a pair are real."""
    if not len(pairs):
        return torch.zeros(mask.shape[0], 0, dtype=torch.bool, device=mask.device)
    idx = torch.as_tensor(list(pairs), dtype=torch.long, device=mask.device)
    return mask[:, idx[:, 0]] & mask[:, idx[:, 1]]


def game_pairs(game: PotentialGame) -> list[tuple[int, int]]:
    """The agent pair of every pair weight, in the order of the game's ``w_pair`` group."""
    spec = game.spec
    return [p for pf in spec.pair_features for p in spec.pairs_of(pf)]


def pair_mask(game: PotentialGame, mask: torch.Tensor) -> torch.Tensor:
    """``(B, n_pairs)`` bool in the order of the game's pair weights (``w_pair`` group,
    ``w.<a>-<b>.<feature>``, ``a < b``): True where both agents are real."""
    pairs = game_pairs(game)
    n = len(game.params.group("w_pair"))
    if len(pairs) != n:  # the layout adds one weight per pair feature and pair
        raise SpecError("game", f"expected {n} pair weights, found {len(pairs)} pairs")
    return pairs_mask(pairs, mask)


def own_mask(game: PotentialGame, mask: torch.Tensor) -> torch.Tensor:
    """``(B, n_own)`` bool in the order of the game's own weights (``w_own`` group,
    ``w.<agent>.<feature>``): True where the weight's agent is real."""
    owner = [i for i, a in enumerate(game.spec.agents) for _ in a.features]
    if len(owner) != len(game.params.group("w_own")):
        raise SpecError("game", "expected one own weight per agent feature")
    return mask[:, torch.as_tensor(owner, dtype=torch.long, device=mask.device)]
