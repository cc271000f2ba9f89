"""From an observation to the scene a trained model reads (scenario-agnostic).

:class:`SceneSpec` says what a model's dataset looked like (agents, history length, step,
frame, fields); :func:`observation_scene` turns the ego's exact history and the others'
filtered histories into that scene: the last ``H + 1`` states per agent, steps before
the first known one filled by the constant-velocity backward extrapolation of the dataset
generators (:meth:`scenarios.rpi.RPIScenario.pre_history`), in the dataset's frame
(:class:`SceneFrame`: ``"world"`` or ``"agent"``). Used by
:class:`learning.planner.NetworkPlanner` every planning period.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from scenarios.sim import FRAMES

__all__ = ["FRAMES", "SceneSpec", "SceneFrame", "observation_scene"]


@dataclass(frozen=True)
class SceneSpec:
    """What a trained model expects of a scene (read from a run directory).

    ``history_steps`` is ``H + 1`` (the current state included); ``frame`` one of
    :data:`FRAMES`; ``fields`` the dataset fields besides ``history`` and ``future``.
    """

    scenario: str  #: the dataset's scenario (manifest ``scenario``)
    kind: str  #: model kind, "epo" or "sc"
    n_agents: int  #: N, agents in the dataset's order (agent 0 = the ego)
    history_steps: int  #: H + 1 states per agent
    horizon: int  #: K, predicted steps
    dt: float  #: step of the history and of the prediction (s)
    state_size: int = 4  #: (x, y, v, theta)
    frame: str = "world"  #: the dataset's frame
    reads_goals: bool = False  #: the model reads the scene's goals (ours with given goals)
    fields: tuple[str, ...] = ()  #: dataset fields besides history and future
    recipe: Mapping | None = field(default=None, compare=False)  #: the dataset's recipe


@dataclass(frozen=True)
class SceneFrame:
    """A rigid frame: world point ``p`` maps to ``R(-heading) (p - origin)``.

    The world frame is ``SceneFrame()``; the agent frame of a state ``s`` is
    ``SceneFrame(s[:2], s[3])``.
    """

    origin: tuple[float, float] = (0.0, 0.0)
    heading: float = 0.0

    @property
    def identity(self) -> bool:
        return self.origin == (0.0, 0.0) and self.heading == 0.0

    def _rot(self, angle: float) -> np.ndarray:
        c, s = math.cos(angle), math.sin(angle)
        return np.array([[c, -s], [s, c]])

    def points_in(self, p: np.ndarray) -> np.ndarray:
        """World positions ``(..., 2)`` -> this frame."""
        if self.identity:
            return np.asarray(p, float)
        return (np.asarray(p, float) - np.asarray(self.origin)) @ self._rot(-self.heading).T

    def points_out(self, p: np.ndarray) -> np.ndarray:
        """Positions ``(..., 2)`` in this frame -> world."""
        if self.identity:
            return np.asarray(p, float)
        return np.asarray(p, float) @ self._rot(self.heading).T + np.asarray(self.origin)

    def states_in(self, x: np.ndarray) -> np.ndarray:
        """World states ``(..., 4)`` ``(x, y, v, theta)`` -> this frame (heading wrapped to [-pi, pi))."""
        x = np.asarray(x, float)
        if self.identity:
            return x.copy()
        out = x.copy()
        out[..., :2] = self.points_in(x[..., :2])
        out[..., 3] = (x[..., 3] - self.heading + math.pi) % (2 * math.pi) - math.pi
        return out

    def states_out(self, x: np.ndarray) -> np.ndarray:
        """States ``(..., 4)`` in this frame -> world (heading not wrapped)."""
        x = np.asarray(x, float)
        if self.identity:
            return x.copy()
        out = x.copy()
        out[..., :2] = self.points_out(x[..., :2])
        out[..., 3] = x[..., 3] + self.heading
        return out


def _continuous_headings(theta: np.ndarray) -> np.ndarray:
    """Headings ``(N, S)`` made continuous along each agent's history and shifted by the
    multiple of ``2 pi`` that puts its current (last) heading into ``(-pi, pi]``: the
    agent-frame convention of the datasets (:func:`scenarios.left_turn.LeftTurnScenario.cut`)."""
    th = np.unwrap(theta, axis=-1)
    return th - 2 * math.pi * np.ceil((th[:, -1:] - math.pi) / (2 * math.pi))


def _backfill(hist: np.ndarray, valid: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Replace the leading entries of every agent's history before its first valid, finite
    state by the constant-velocity backward extrapolation of that state.

    ``hist`` ``(A, T, 4)``, ``valid`` ``(A, T)``. The same extrapolation as the dataset
    generators (:meth:`scenarios.rpi.RPIScenario.pre_history`):
    ``p_j = p_0 + j dt v (cos theta, sin theta)`` for ``j = -1, -2, ...``, speed and heading
    kept. Returns the filled history and the validity (False where filled). An agent with
    no valid, finite state raises ``ValueError``.
    """
    good = valid & np.isfinite(hist).all(-1)
    if not good.any(-1).all():
        bad = int(np.flatnonzero(~good.any(-1))[0])
        raise ValueError(f"agent {bad}: no valid, finite state in its history")
    first = good.argmax(-1)  # (A,)
    A, T = good.shape
    a = np.arange(A)
    x0 = hist[a, first]  # (A, 4)
    j = np.arange(T)[None, :] - first[:, None]  # (A, T): steps relative to the first valid one
    ext = np.repeat(x0[:, None], T, axis=1)
    step = (j * dt)[..., None] * x0[:, None, 2:3]
    ext[..., 0] = x0[:, None, 0] + step[..., 0] * np.cos(x0[:, None, 3])
    ext[..., 1] = x0[:, None, 1] + step[..., 0] * np.sin(x0[:, None, 3])
    before = j < 0
    out = np.where(before[..., None], ext, hist)
    return out, np.where(before, False, valid)


def _window(hist: np.ndarray, valid: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """The last ``steps`` entries of ``(A, T, 4)`` / ``(A, T)``, padded in front with NaN /
    False when ``T < steps``."""
    A, T = valid.shape
    if T >= steps:
        return hist[:, T - steps :], valid[:, T - steps :]
    pad = steps - T
    return (
        np.concatenate([np.full((A, pad, hist.shape[-1]), np.nan), hist], 1),
        np.concatenate([np.zeros((A, pad), bool), valid], 1),
    )


def observation_scene(
    ego_history: np.ndarray,
    others_history: np.ndarray,
    others_valid: np.ndarray | None,
    spec: SceneSpec,
    goals: np.ndarray | None = None,
) -> tuple[dict[str, np.ndarray], SceneFrame]:
    """The scene (numpy, no batch axis) a model trained on ``spec``'s dataset reads.

    ``ego_history`` ``(T0, 4)``: the ego's exact states, oldest first, last = now;
    ``others_history`` ``(N-1, T1, 4)`` and ``others_valid`` ``(N-1, T1)`` (None: all
    valid): the others' filtered states (:attr:`Estimate.history`), last = now;
    ``goals`` ``(N, 2)`` world positions (only used when the model reads goals).
    Entries before the first valid, finite one are filled by the backward extrapolation of
    :func:`_backfill`; the window is the last ``spec.history_steps``. Returns the scene
    (``history`` ``(H+1, N, 4)`` float32, ``history_valid`` ``(H+1,)``, ``goals``
    ``(N, 2)`` float32 if read) and the :class:`SceneFrame` it is expressed in.
    """
    S, N = spec.history_steps, spec.n_agents
    ego = np.asarray(ego_history, float).reshape(-1, 4)
    oth = np.asarray(others_history, float)
    if oth.ndim != 3 or oth.shape[0] != N - 1 or oth.shape[2] != 4:
        raise ValueError(f"others' history: expected shape ({N - 1}, T, 4), got {oth.shape}")
    ov = (
        np.ones(oth.shape[:2], bool)
        if others_valid is None
        else np.asarray(others_valid, bool).reshape(oth.shape[:2])
    )
    eh, ev = _window(ego[None], np.ones((1, len(ego)), bool), S)
    oh, ov = _window(oth, ov, S)
    # a current state that is not finite cannot be planned from
    if not np.isfinite(eh[0, -1]).all():
        raise ValueError("the ego's current state is not finite")
    if not np.isfinite(oh[:, -1]).all():
        raise ValueError("an estimated current state of another agent is not finite")
    hist, valid = _backfill(
        np.concatenate([eh, oh], 0), np.concatenate([ev, ov], 0), spec.dt
    )  # (N, S, 4)
    cur = hist[0, -1]
    frame = SceneFrame((float(cur[0]), float(cur[1])), float(cur[3]))
    if spec.frame == "world":
        frame = SceneFrame()
    hist = frame.states_in(hist)
    if spec.frame == "agent":
        hist[..., 3] = _continuous_headings(hist[..., 3])
    scene = {
        "history": hist.transpose(1, 0, 2).astype(np.float32),
        "history_valid": valid.all(0),
    }
    if spec.reads_goals:
        if goals is None:
            raise ValueError("the model reads goals and none are known")
        g = np.asarray(goals, float).reshape(N, 2)
        if not np.isfinite(g).all():
            raise ValueError("a goal is not finite")
        scene["goals"] = frame.points_in(g).astype(np.float32)
    return scene, frame
