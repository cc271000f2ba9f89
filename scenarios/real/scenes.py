"""Scenes of recorded tracks: windows, states from positions, the interaction rule, padding
and the crowd game. Shared by the readers of :mod:`scenarios.real`.

Tracks
    A :class:`Track` is one recorded agent on a common integer frame grid: sorted ``frames``,
    positions ``xy`` (metres, the recording's world frame) and optionally the recorded
    ``heading`` and ``speed``. A track with a gap (two frames further apart than the grid
    step) is split into its contiguous pieces by :func:`contiguous_pieces`; nothing is ever
    interpolated across a gap.

Windows
    A scene is cut at a current frame ``t``: ``H + 1`` observed steps ``t - H s .. t`` and ``T``
    future steps ``t + s .. t + T s`` (``s`` the grid step). An agent takes part only if its
    piece covers the whole window (the benchmark convention for ETH/UCY: every scored agent
    is present over the whole sequence).

States from positions
    :func:`unicycle_states` gives ``(x, y, v, theta)`` per step. Without recorded speeds and
    headings, ``v_k = |p_k - p_{k-1}| / dt`` and ``theta_k = atan2(p_k - p_{k-1})`` (backward
    differences, so a state never uses a later position); the first step takes the second's
    values, and a heading is held while the agent moves less than ``still`` metres a step.

The interaction rule (no future leak)
    :func:`closest_approach`: every candidate and the focal agent are extrapolated at
    constant velocity from their last two *observed* positions over the ``T`` future steps;
    a candidate's score is the smallest distance to the focal agent over the current and
    the extrapolated steps. :func:`select_agents` keeps the focal agent and the ``N - 1``
    candidates of smallest score (ties: the lower track id), dropping candidates farther
    than ``max_distance`` at their closest approach. Only observed positions enter the
    choice.

Padding
    A scene of fewer than ``N`` agents fills the remaining slots with zeros and marks them
    False in ``agents_mask`` (``N``, bool); real agents come first, the focal agent in slot
    0. ``track_id`` is ``-1`` on padded slots. Every model of :mod:`learning` masks padded
    agents (they change no output or gradient of the real ones).

Scene frame
    Positions are stored relative to ``origin`` (``(2,)`` float64): the focal agent's
    current position in the recording's frame. The axes stay those of the recording.

Sizes
    ``length`` / ``width`` (``(N,)``) are written only by readers that record a size for
    every agent (``scene_schema(..., sizes=True)``, Waymo). A reader without sizes for some
    agents (ETH/UCY, the pedestrians of CITR) leaves both fields out, so the overlap rate of
    :mod:`learning.metrics` uses circles of the sample's ``radius`` instead of boxes of
    size 0.

Context agents (figures only)
    ``window_scenes(..., context=C)`` adds ``others`` ``(C, H+1+T, 2)`` to each scene: the
    positions (scene frame, NaN where not recorded) over the whole window of the ``C``
    recorded agents that are not in the scene and come nearest to the focal agent at a
    common step of the window (ties: the lower id; fewer: NaN rows). It reads the future and
    is drawn by :func:`learning.show.show_predictions` only; no model or metric reads it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from epo_casadi import GameSpec
from epo_casadi.errors import SpecError
from epo_casadi.presets import driving_agents, driving_game_spec

from ..dataset import FieldSpec

__all__ = [
    "Track",
    "contiguous_pieces",
    "unicycle_states",
    "closest_approach",
    "select_agents",
    "window_scenes",
    "scene_schema",
    "stack_scenes",
    "crowd_game_spec",
]


@dataclass
class Track:
    """One agent's recorded piece on the frame grid (see the module docstring)."""

    id: int
    frames: np.ndarray  #: (n,) int64, sorted, strictly increasing
    xy: np.ndarray  #: (n, 2) float64 metres
    heading: np.ndarray | None = None  #: (n,) radians, when recorded
    speed: np.ndarray | None = None  #: (n,) m/s, when recorded
    kind: int = 0  #: agent class index (the reader's table, e.g. 0 pedestrian, 1 vehicle)
    length: float = 0.0  #: metres (0: unknown)
    width: float = 0.0


def contiguous_pieces(track: Track, step: int) -> list[Track]:
    """``track`` cut at every gap (consecutive frames more than ``step`` apart); each piece
    keeps the track id. Frames must be strictly increasing multiples of ``step`` apart."""
    f = np.asarray(track.frames, np.int64)
    if f.size == 0:
        return []
    d = np.diff(f)
    if (d <= 0).any():
        raise SpecError(f"track {track.id}.frames", "expected strictly increasing frames")
    cuts = np.flatnonzero(d != step) + 1
    out = []
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, f.size], strict=True):
        sl = slice(int(lo), int(hi))
        out.append(
            Track(
                track.id,
                f[sl],
                np.asarray(track.xy, np.float64)[sl],
                None if track.heading is None else np.asarray(track.heading)[sl],
                None if track.speed is None else np.asarray(track.speed)[sl],
                track.kind,
                track.length,
                track.width,
            )
        )
    return out


def unicycle_states(
    xy: np.ndarray,
    dt: float,
    heading: np.ndarray | None = None,
    speed: np.ndarray | None = None,
    still: float = 1e-3,
) -> np.ndarray:
    """``(x, y, v, theta)`` ``(..., n, 4)`` of positions ``xy`` ``(..., n, 2)`` (n >= 2) a step
    ``dt`` apart; recorded ``heading`` / ``speed`` ``(..., n)`` are used where given."""
    xy = np.asarray(xy, np.float64)
    n = xy.shape[-2]
    if n < 2:
        raise SpecError("positions", f"need at least 2 steps for velocities, got {n}")
    d = np.diff(xy, axis=-2)  # (..., n-1, 2)
    step = np.linalg.norm(d, axis=-1)
    v = np.concatenate([step[..., :1], step], axis=-1) / dt
    th = np.arctan2(d[..., 1], d[..., 0])
    # hold the heading while (nearly) standing: the last heading of a real move, forward
    # filled; before the first move, the first move's heading (0 if it never moves)
    moving = step > still
    idx = np.where(moving, np.arange(n - 1), -1)
    idx = np.maximum.accumulate(idx, axis=-1)
    first = np.argmax(moving, axis=-1)[..., None]
    idx = np.where(idx < 0, first, idx)
    th = np.take_along_axis(th, idx, axis=-1)
    th = np.where(moving.any(axis=-1, keepdims=True), th, 0.0)
    th = np.concatenate([th[..., :1], th], axis=-1)
    if heading is not None:
        th = np.asarray(heading, np.float64)
    if speed is not None:
        v = np.asarray(speed, np.float64)
    return np.concatenate([xy, v[..., None], th[..., None]], axis=-1)


def closest_approach(focal: np.ndarray, others: np.ndarray, horizon: int) -> np.ndarray:
    """Interaction score of each candidate: the smallest distance to the focal agent over
    the current step and ``horizon`` constant-velocity steps extrapolated from the last two
    observed positions. ``focal`` ``(H+1, 2)``, ``others`` ``(n, H+1, 2)`` (observed only)
    -> ``(n,)`` metres."""
    k = np.arange(horizon + 1, dtype=np.float64)[:, None]  # (T+1, 1)
    fv = focal[-1] - focal[-2]
    fp = focal[-1] + k * fv  # (T+1, 2)
    ov = others[:, -1] - others[:, -2]  # (n, 2)
    op = others[:, None, -1] + k[None] * ov[:, None]  # (n, T+1, 2)
    return np.linalg.norm(op - fp[None], axis=-1).min(axis=-1)


def select_agents(
    scores: np.ndarray, ids: np.ndarray, n_others: int, max_distance: float = math.inf
) -> np.ndarray:
    """Positions (into ``scores``) of the ``n_others`` candidates of smallest score within
    ``max_distance``; ties broken by the lower id."""
    keep = np.flatnonzero(scores <= max_distance)
    order = np.lexsort((ids[keep], scores[keep]))
    return keep[order[:n_others]]


def window_scenes(
    tracks: Sequence[Track],
    *,
    step: int,
    history: int,
    horizon: int,
    agents: int,
    dt: float,
    stride: int = 1,
    max_distance: float = math.inf,
    focal_ids: Sequence[int] | None = None,
    candidate_ids: Sequence[int] | None = None,
    context: int = 0,
) -> list[dict]:
    """Every scene of ``tracks`` (pieces without gaps on a grid of ``step`` frames).

    A scene per focal piece and current frame ``t`` (every ``stride``-th grid step at which
    the focal piece covers the window); the other agents are the pieces covering the same
    window, chosen by :func:`select_agents` on :func:`closest_approach`. ``focal_ids``
    limits the focal agents (default: all), ``candidate_ids`` the others (default: all).
    Returns scene dicts (the per-scene fields of :func:`scene_schema` without ``future``'s
    mode axis): ``history`` ``(H+1, N, 4)``, ``gt`` ``(N, T, 4)``, ``agents_mask``,
    ``track_id``, ``kind``, ``length``, ``width``, ``frame``, ``origin``, ``min_distance``;
    with ``context`` C > 0 also ``others`` ``(C, H+1+T, 2)`` (module docstring, "Context
    agents"; every piece of ``tracks`` counts, also one shorter than the window).
    """
    H, T, N = int(history), int(horizon), int(agents)
    span = (H + T) * step
    pieces = [p for p in tracks if p.frames.size and p.frames[-1] - p.frames[0] >= span]
    if not pieces:
        return []
    focal_set = None if focal_ids is None else {int(i) for i in focal_ids}
    rows = _rows(tracks) if context > 0 else None
    starts = np.array([p.frames[0] for p in pieces], np.int64)
    ends = np.array([p.frames[-1] for p in pieces], np.int64)
    ids = np.array([p.id for p in pieces], np.int64)
    allowed = (
        np.ones(ids.size, bool)
        if candidate_ids is None
        else np.isin(ids, np.asarray([int(i) for i in candidate_ids], np.int64))
    )
    out = []
    for fp in pieces:
        if focal_set is not None and fp.id not in focal_set:
            continue
        # current frames: the window [t - H s, t + T s] inside the focal piece, every stride
        first, last = fp.frames[0] + H * step, fp.frames[-1] - T * step
        for t in range(int(first), int(last) + 1, stride * step):
            lo, hi = t - H * step, t + T * step
            cand = np.flatnonzero((starts <= lo) & (ends >= hi) & allowed & (ids != fp.id))
            scene = _cut(fp, [pieces[j] for j in cand], lo, step, H, T, N, dt, max_distance)
            if rows is not None:
                scene["others"] = _others(rows, scene, fp, lo, step, H + T + 1, int(context))
            out.append(scene)
    return out


def _rows(tracks: Sequence[Track]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every recorded row of ``tracks`` sorted by frame: ``(frames, ids, xy)``."""
    ts = [t for t in tracks if t.frames.size]
    if not ts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
    f = np.concatenate([np.asarray(t.frames, np.int64) for t in ts])
    i = np.concatenate([np.full(t.frames.size, t.id, np.int64) for t in ts])
    xy = np.concatenate([np.asarray(t.xy, np.float64) for t in ts])
    o = np.argsort(f, kind="stable")
    return f[o], i[o], xy[o]


def _others(rows, scene: dict, fp: Track, lo: int, step: int, n: int, C: int) -> np.ndarray:
    """``others`` ``(C, n, 2)`` of a scene (module docstring, "Context agents")."""
    F, ids, XY = rows
    out = np.full((C, n, 2), np.nan)
    a, b = np.searchsorted(F, lo, "left"), np.searchsorted(F, lo + (n - 1) * step, "right")
    f, i, xy = F[a:b], ids[a:b], XY[a:b]
    k = (f - lo) // step
    keep = ~np.isin(i, scene["track_id"][scene["agents_mask"]]) & ((f - lo) % step == 0)
    f, i, xy, k = f[keep], i[keep], xy[keep], k[keep]
    if not i.size:
        return out
    focal = fp.xy[_window(fp, lo, step, n)]  # (n, 2): the focal piece covers the window
    d = np.linalg.norm(xy - focal[k], axis=-1)
    uid, inv = np.unique(i, return_inverse=True)
    best = np.full(uid.size, np.inf)
    np.minimum.at(best, inv, d)
    pick = np.lexsort((uid, best))[:C]
    slot = np.full(uid.size, -1)
    slot[pick] = np.arange(pick.size)
    s = slot[inv]
    sel = s >= 0
    out[s[sel], k[sel]] = xy[sel] - scene["origin"]
    return out


def _window(p: Track, lo: int, step: int, n: int) -> slice:
    i = int((lo - p.frames[0]) // step)
    return slice(i, i + n)


def _cut(fp, cands, lo, step, H, T, N, dt, max_distance) -> dict:
    n = H + T + 1
    sl = _window(fp, lo, step, n)
    obs = fp.xy[sl][: H + 1]
    chosen: list[Track] = []
    if cands and N > 1:
        others = np.stack([c.xy[_window(c, lo, step, n)][: H + 1] for c in cands])
        scores = closest_approach(obs, others, T)
        cid = np.array([c.id for c in cands], np.int64)
        chosen = [cands[j] for j in select_agents(scores, cid, N - 1, max_distance)]
    agents = [fp, *chosen]
    states = np.zeros((n, N, 4))
    wins = [_window(p, lo, step, n) for p in agents]
    # one batched call for every agent; recorded headings and speeds replace the differences
    states[:, : len(agents)] = unicycle_states(
        np.stack([p.xy[w] for p, w in zip(agents, wins, strict=True)]), dt
    ).transpose(1, 0, 2)
    for a, (p, w) in enumerate(zip(agents, wins, strict=True)):
        if p.heading is not None:
            states[:, a, 3] = p.heading[w]
        if p.speed is not None:
            states[:, a, 2] = p.speed[w]
    origin = states[H, 0, :2].copy()
    k = len(agents)
    states[:, :k, :2] -= origin
    mask = np.zeros(N, bool)
    mask[:k] = True
    pos = states[:, :k, :2]
    if k > 1:
        gap = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
        gap[:, np.arange(k), np.arange(k)] = np.inf
        min_distance = float(gap.min())
    else:
        min_distance = math.inf
    pad = N - k
    return {
        "history": states[: H + 1],
        "gt": states[H + 1 :].transpose(1, 0, 2),
        "agents_mask": mask,
        "track_id": np.array([p.id for p in agents] + [-1] * pad, np.int64),
        "kind": np.array([p.kind for p in agents] + [0] * pad, np.int64),
        "length": np.array([p.length for p in agents] + [0.0] * pad),
        "width": np.array([p.width for p in agents] + [0.0] * pad),
        "frame": int(lo + H * step),
        "origin": origin,
        "min_distance": min_distance,
    }


def scene_schema(
    agents: int, history: int, horizon: int, modes: int, sizes: bool = True, context: int = 0
) -> dict[str, FieldSpec]:
    """The per-sample fields every recorded-data scenario writes (N agents, H + 1 observed
    and T future steps, M future slots of which slot 0 is the recording). ``sizes``: write
    ``length`` and ``width`` (only for a reader that records a size for every agent; module
    docstring, "Sizes"); ``context`` C > 0: the figure-only field ``others`` ``(C, H+1+T,
    2)`` (module docstring, "Context agents")."""
    N, H1, T, M = int(agents), int(history) + 1, int(horizon), int(modes)
    out = {
        "history": FieldSpec(
            (H1, N, 4), "float32", "observed states (x, y, v, theta), scene frame"
        ),
        "history_valid": FieldSpec((H1,), "bool", "always True (complete windows only)"),
        "future": FieldSpec((M, N, T, 4), "float32", "recorded future in slot 0, copies after"),
        "mode_valid": FieldSpec((M,), "bool", "True only for the recorded slot"),
        "gt_mode": FieldSpec((), "int8", "slot of the recorded future (0)"),
        "agents_mask": FieldSpec((N,), "bool", "True: a recorded agent; False: padding"),
        "track_id": FieldSpec((N,), "int32", "track id in the recording (-1: padding)"),
        "agent_kind": FieldSpec((N,), "int8", "index in meta.kinds"),
        "length": FieldSpec((N,), "float32", "agent length (m; 0 where not recorded)"),
        "width": FieldSpec((N,), "float32", "agent width (m; 0 where not recorded)"),
        "radius": FieldSpec((N,), "float32", "collision radius of each agent (m)"),
        "frame": FieldSpec((), "int64", "current frame in the recording"),
        "origin": FieldSpec((2,), "float64", "scene origin in the recording's frame (m)"),
        "min_distance": FieldSpec(
            (),
            "float32",
            "closest distance of two recorded agents over the window (m; inf: one agent)",
        ),
    }
    if not sizes:
        del out["length"], out["width"]
    if int(context) > 0:
        out["others"] = FieldSpec(
            (int(context), H1 + T, 2),
            "float32",
            "figures only: positions (scene frame; NaN: not recorded) over the window of the "
            "recorded agents nearest the focal one that are not in the scene",
        )
    return out


def stack_scenes(
    scenes: Sequence[dict],
    schema: dict[str, FieldSpec],
    radius: np.ndarray | float,
    extra: dict | None = None,
) -> dict[str, np.ndarray]:
    """Samples ``(n, ...)`` of every schema field from :func:`window_scenes`' dicts.

    ``radius``: a collision radius per agent kind (indexed by ``kind``) or one for all;
    padded slots get 0. ``extra``: per-unit constant fields (e.g. ``{"clip": 3}``). Only
    the fields of ``schema`` are returned (``length`` / ``width`` / ``others`` when it has
    them; ``others`` needs ``window_scenes(..., context=C)``)."""
    if not scenes:
        return {k: np.zeros((0, *fs.shape), fs.dtype) for k, fs in schema.items()}
    M = schema["future"].shape[0]
    n = len(scenes)
    H1 = schema["history"].shape[0]
    gt = np.stack([s["gt"] for s in scenes])  # (n, N, T, 4)
    mask = np.stack([s["agents_mask"] for s in scenes])
    kind = np.stack([s["kind"] for s in scenes])
    rad = np.asarray(radius, np.float64)
    r = rad[kind] if rad.ndim else np.full(kind.shape, float(rad))
    out = {
        "history": np.stack([s["history"] for s in scenes]),
        "history_valid": np.ones((n, H1), bool),
        # cast before the M copies (the same values, M times less to convert)
        "future": np.repeat(gt.astype(schema["future"].dtype)[:, None], M, axis=1),
        "mode_valid": np.eye(1, M, dtype=bool).repeat(n, axis=0),
        "gt_mode": np.zeros(n, np.int8),
        "agents_mask": mask,
        "track_id": np.stack([s["track_id"] for s in scenes]),
        "agent_kind": kind,
        "length": np.stack([s["length"] for s in scenes]),
        "width": np.stack([s["width"] for s in scenes]),
        "radius": np.where(mask, r, 0.0),
        "frame": np.array([s["frame"] for s in scenes], np.int64),
        "origin": np.stack([s["origin"] for s in scenes]),
        "min_distance": np.array([s["min_distance"] for s in scenes]),
    }
    if "others" in schema:
        out["others"] = np.stack([s["others"] for s in scenes])
    for k, v in (extra or {}).items():
        out[k] = np.full(n, v)
    return {k: np.asarray(out[k]).astype(fs.dtype, copy=False) for k, fs in schema.items()}


def crowd_game_spec(recipe, names: Sequence[str] | None = None) -> GameSpec:
    """The game of recorded scenes: ``recipe.agents`` unicycles with the App. F.3 Waymo
    features (goal, vel, acc, jerk, turn rate, turn acceleration) weighted by the recipe's
    ``w_*`` fields, circle collisions every ``recipe.collision_every`` steps with weight
    ``w_collision``, horizon ``recipe.horizon`` at ``recipe.dt``. Each agent's radius is a
    game parameter (``radius_param``) that models set from the sample's ``radius``;
    ``recipe.radius`` is its default."""
    names = list(names or [f"a{i}" for i in range(recipe.agents)])
    agents = driving_agents(recipe, names, radius_param=True)
    return driving_game_spec(recipe, agents, every=recipe.collision_every)
