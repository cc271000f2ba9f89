"""The self-driving vehicle's (SDV's) strategy for control (paper Sec. 4.3).

Ours predicts ``M`` joint strategies of all agents and their scene probabilities. For
control, the SDV executes its own controls of the most likely joint mode (receding
horizon: the first control, or the first few, then predict again).
:func:`sdv_strategy` extracts them from a model output; :func:`plan` runs a model on a
scene batch in evaluation mode and does the same. Agent ``0`` is the SDV by convention
(the robot in RPI).

Works for every model that predicts joint controls (``"epo"``, ``"sc"``); the marginal
V-LSTM predicts positions per agent only and has no strategy to execute.

The network as a closed-loop planner
    :class:`NetworkPlanner` implements the :class:`solvers.control.types.Planner` protocol
    for such a model; :func:`load_planner` builds one from a training run directory
    (:mod:`learning.train`) for a world (:class:`solvers.control.types.World`). Every
    planning period it turns the observation into the scene the model was trained on
    (:func:`observation_scene`): the last ``H + 1`` states of every agent in the dataset's
    order (agent 0 = the ego, its exact states kept by the planner; the others' filtered
    states from :attr:`Estimate.history <solvers.control.types.Estimate>`), steps before
    the first one filled by the constant-velocity backward extrapolation the dataset
    generators use (:meth:`scenarios.rpi.RPIScenario.pre_history`) and marked ``False`` in
    ``history_valid``; the goals when the model reads given goals; everything in the
    dataset's frame (manifest ``meta.frame``: ``"world"``, the default and RPI's, or
    ``"agent"``: agent 0 at the origin with ``x`` along its current heading). It runs the
    model once (evaluation mode, no gradients, one torch thread), executes the most likely
    joint mode (:func:`sdv_strategy`) and returns a :class:`~solvers.control.types.Plan`
    in the world frame with every mode as a prediction. A failure at planning time
    (non-finite input or output, a model error) returns ``Plan(ok=False)``, never raises.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from epo_casadi.errors import EpoError, SpecError, check_size
from scenarios.sim import FRAMES, dataset_frame, world_scenario
from solvers.control.plan import failed_plan
from solvers.control.types import Estimate, Observation, Plan, world_member

from .layer import GameLayer

__all__ = [
    "SDVPlan",
    "sdv_strategy",
    "plan",
    "FRAMES",
    "SceneSpec",
    "SceneFrame",
    "PlannerOptions",
    "NetworkPlanner",
    "observation_scene",
    "load_planner",
    "model_planner",
    "sc_planner",
]


@dataclass(frozen=True)
class SDVPlan:
    """One agent's strategy in the most likely joint mode of every scene of a batch."""

    controls: torch.Tensor  #: (B, K, nu) controls u_1..u_K (unicycle: acceleration, turn rate)
    states: torch.Tensor  #: (B, K, nx) the states they lead to (x_1..x_K)
    mode: torch.Tensor  #: (B,) index of the most likely joint mode
    probability: torch.Tensor  #: (B,) its scene probability
    agent: int  #: the agent index

    @property
    def first_control(self) -> torch.Tensor:
        """``(B, nu)``: the control to apply now (receding horizon)."""
        return self.controls[:, 0]


def sdv_strategy(out: dict, agent: int = 0) -> SDVPlan:
    """The strategy of ``agent`` in the most likely joint mode of a model output.

    ``out`` is the dict of :class:`~learning.models.EPOModel` or
    :class:`~learning.models.SCModel` (``controls`` ``(B, M, N, K, nu)``, ``states``
    ``(B, M, N, K, nx)``, ``logits`` ``(B, M)``). Ties go to the lower mode index.
    """
    if "controls" not in out or "logits" not in out:
        raise SpecError(
            "model",
            "the output has no joint controls and scene probabilities (the marginal V-LSTM "
            "predicts positions only); use the 'epo' or 'sc' model",
        )
    U, X, logits = out["controls"], out["states"], out["logits"]
    B, M, N = U.shape[:3]
    if isinstance(agent, bool) or not isinstance(agent, int) or not 0 <= agent < N:
        raise SpecError("agent", f"expected an agent index in [0, {N}), got {agent!r}")
    probs = torch.softmax(logits.detach(), dim=-1)
    mode = probs.argmax(dim=-1)
    b = torch.arange(B, device=U.device)
    return SDVPlan(
        controls=U[b, mode, agent],
        states=X[b, mode, agent],
        mode=mode,
        probability=probs[b, mode],
        agent=agent,
    )


@torch.no_grad()
def plan(model: nn.Module, scene: dict, agent: int = 0) -> SDVPlan:
    """Run ``model`` on ``scene`` in evaluation mode and return ``agent``'s strategy
    (:func:`sdv_strategy`). The model's training flag is restored afterwards."""
    was = model.training
    model.eval()
    try:
        out = model(scene)
    finally:
        model.train(was)
    return sdv_strategy(out, agent)


# --------------------------------------------------------------------------------------
# the network as a closed-loop planner
# --------------------------------------------------------------------------------------
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


@dataclass(frozen=True)
class PlannerOptions:
    """Options of :class:`NetworkPlanner`. Frozen; unknown keys fail."""

    others_goals: str = "given"  #: "given": the world's task goals (the dataset gives goals,
    #: paper App. F.3 for RPI); "constant_velocity": where each other agent is after the
    #: horizon at its estimated speed and heading
    threads: int = 1  #: torch intra-op threads during a plan (1: one core), at most 256
    layer_backend: str = "fused"  #: Gauss-Newton backend of ours' game layer while planning:
    #: "fused" (solvers.fast_gn.FusedGN, compiled to C when a compiler is found, else
    #: interpreted; equal to the trained backend to 1e-12 and about 3-5x less CPU per plan,
    #: bench/bench_planning.py) or "model" (the backend the model was trained with)

    def __post_init__(self):
        if self.layer_backend not in ("fused", "model"):
            raise SpecError(
                "planner.layer_backend",
                f"expected 'fused' or 'model', got {self.layer_backend!r}",
            )
        if self.others_goals not in ("given", "constant_velocity"):
            raise SpecError(
                "planner.others_goals",
                f"expected 'given' or 'constant_velocity', got {self.others_goals!r}",
            )
        object.__setattr__(
            self, "threads", check_size("planner.threads", self.threads, 256, "threads")
        )

    @classmethod
    def from_dict(cls, d: Mapping) -> PlannerOptions:
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise SpecError("planner", f"unknown option(s) {unknown}; allowed: {sorted(names)}")
        return cls(**d)


def _fused_layer(layer: GameLayer) -> GameLayer:
    """``layer`` with the fused Gauss-Newton backend (compiled when a C compiler is found):
    the same solve to rounding, built for one problem at a time (planning), not for the
    large batches of training."""
    from solvers.codegen import CompilerError, find_compiler
    from solvers.fast_gn import FusedGN

    if isinstance(layer.core.backend, FusedGN):  # trained with it (the default)
        return layer
    try:
        find_compiler()
        compiled = True
    except CompilerError:
        compiled = False
    return GameLayer(
        layer.game,
        layer.options,
        backward=layer.backward,
        on_invalid=layer.on_invalid,
        backend=FusedGN(layer.game, compiled=compiled),
    )


def _world_checks(spec: SceneSpec, world, where: str) -> None:
    """Refuse a world whose shapes differ from the model's (agents, step, horizon, history)."""
    n = world.n_agents
    if n is not None and int(n) != spec.n_agents:
        raise SpecError(
            "world.n_agents",
            f"the model at {where} was trained on {spec.n_agents} agents, the world has {n}",
        )
    dt = world.dt
    if dt is None or not math.isclose(float(dt), spec.dt, rel_tol=1e-9, abs_tol=1e-12):
        raise SpecError(
            "world.dt",
            f"the model at {where} was trained on steps of {spec.dt} s, the world plans every "
            f"{dt!r} s",
        )
    for attr, want, what in (
        ("horizon", spec.horizon, "future steps"),
        ("history", spec.history_steps - 1, "history steps"),
    ):
        got = world_member(world, attr)
        if got is not None and int(got) != want:
            raise SpecError(
                f"world.{attr}",
                f"the model at {where} was trained on {want} {what}, the world has {got}",
            )
    scenario = world_scenario(world)
    if scenario is None:
        raise SpecError(
            "world.scenario",
            f"the world names no dataset scenario; the model at {where} was trained on "
            f"{spec.scenario!r} data",
        )
    if scenario != spec.scenario:
        raise SpecError(
            "world.scenario",
            f"the model at {where} was trained on {spec.scenario!r} data, the world "
            f"{world_member(world, 'name') or type(world).__name__!r} plays {scenario!r} scenes",
        )


class NetworkPlanner:
    """A trained joint-control model (``"epo"``, ``"sc"``) as a closed-loop planner.

    ``model``: the network (eval mode is set); ``spec``: what its dataset looked like
    (:class:`SceneSpec`; :func:`load_planner` reads it from a run); ``options``:
    :class:`PlannerOptions`. :meth:`reset` before every episode; :meth:`plan` once per
    planning period (the ego's history is recorded there, one state per call).
    """

    def __init__(self, model: nn.Module, spec: SceneSpec, options: PlannerOptions | None = None):
        if not isinstance(spec, SceneSpec):
            raise SpecError("spec", f"expected a SceneSpec, got {type(spec).__name__}")
        if spec.kind not in ("epo", "sc"):
            raise SpecError(
                "model.kind",
                f"expected a model that predicts joint controls ('epo' or 'sc'), got "
                f"{spec.kind!r}; the marginal V-LSTM has no strategy to execute",
            )
        if spec.frame not in FRAMES:
            raise SpecError("meta.frame", f"expected one of {list(FRAMES)}, got {spec.frame!r}")
        options = PlannerOptions() if options is None else options
        if not isinstance(options, PlannerOptions):
            raise SpecError("options", f"expected PlannerOptions, got {type(options).__name__}")
        self.model, self.spec, self.options = model.eval(), spec, options
        if options.layer_backend == "fused" and isinstance(
            getattr(model, "layer", None), GameLayer
        ):
            model.layer = _fused_layer(model.layer)
        self.world = None
        self._ego: list[np.ndarray] = []
        self._goals: np.ndarray | None = None
        #: what identifies the trained model: ``{"checkpoint": file name, "sha256": of the
        #: file, "epoch", "step"}`` (set by :func:`load_planner`; None for a model given here)
        self.identity: dict | None = None

    @property
    def history_steps(self) -> int:
        """``H + 1``: the filtered history length the estimator should keep."""
        return self.spec.history_steps

    def reset(self, world) -> None:
        """Forget the ego's history; check ``world`` against the model (:class:`SpecError`)."""
        _world_checks(self.spec, world, "this planner")
        self.world = world
        self._ego = []
        self._goals = None

    # ---- pieces (public for tests and tools) ----------------------------------------------
    def goals(self, est: Estimate) -> np.ndarray:
        """World goals ``(N, 2)``: the ego's task goal, the others' by ``options.others_goals``."""
        if self.world is None:
            raise ValueError("the planner was not reset with a world")
        ego = np.asarray(self.world.ego_task.goal, float).reshape(1, 2)
        if self.options.others_goals == "given":
            if self._goals is None:
                tasks = self.world.tasks()
                self._goals = np.stack([np.asarray(t.goal, float).reshape(2) for t in tasks[1:]])
            return np.concatenate([ego, self._goals])
        s = np.asarray(est.states, float)
        reach = s[:, 2:3] * self.spec.horizon * self.spec.dt
        ahead = s[:, :2] + reach * np.stack([np.cos(s[:, 3]), np.sin(s[:, 3])], -1)
        return np.concatenate([ego, ahead])

    def scene(self, obs: Observation, est: Estimate) -> tuple[dict[str, np.ndarray], SceneFrame]:
        """Record ``obs.ego`` and build the scene of this step (:func:`observation_scene`)."""
        self._ego.append(np.asarray(obs.ego, float).reshape(4).copy())
        del self._ego[: -self.spec.history_steps]
        goals = self.goals(est) if self.spec.reads_goals else None
        scene, frame = observation_scene(
            np.stack(self._ego), est.history, est.valid, self.spec, goals
        )
        from scenarios.sim import scene_fields

        scene.update(scene_fields(self.world, obs, est, frame, self.spec.recipe))  # map fields
        return scene, frame

    @torch.no_grad()
    def run(self, scene: Mapping[str, np.ndarray]) -> dict:
        """The model's output on one scene (batch of one), in the dataset's frame."""
        from .train import torch_threads

        batch = {k: torch.from_numpy(np.ascontiguousarray(v))[None] for k, v in scene.items()}
        with torch_threads(self.options.threads):
            return self.model(batch)

    # ---- the Planner protocol -------------------------------------------------------------
    def plan(self, obs: Observation, est: Estimate) -> Plan:
        """The ego's strategy in the most likely joint mode, in the world frame (see module doc)."""
        t0 = time.perf_counter()
        dt = self.spec.dt
        t = getattr(obs, "t", math.nan)
        try:
            t = float(t)
            if not math.isfinite(t):
                raise ValueError(f"expected an Observation with a finite time t, got {t!r}")
            scene, frame = self.scene(obs, est)
            out = self.run(scene)
            best = sdv_strategy(out, 0)
            probs = torch.softmax(out["logits"][0].double(), -1).numpy()
            X = out["states"][0].double().numpy()  # (M, N, K, 4)
            U = out["controls"][0, int(best.mode[0]), 0].double().numpy()  # (K, 2)
            ok = bool(np.isfinite(X).all() and np.isfinite(U).all() and np.isfinite(probs).all())
            info = {
                "mode": int(best.mode[0]),
                "probability": float(best.probability[0]),
                "latency_s": time.perf_counter() - t0,
            }
            if "status" in out:
                from .layer import decode_status

                info["solver_status"] = [s.name for s in decode_status(out["status"][0])]
            if not ok:
                return self._failed(t, "the model output is not finite", info)
            pred = frame.states_out(X)
            return Plan(
                t,
                dt,
                pred[best.mode[0].item(), 0],
                U,
                predictions=pred,
                probabilities=probs,
                info=info,
            )
        except Exception as e:  # noqa: BLE001 - a plan never raises (module docstring)
            return self._failed(
                t, f"{type(e).__name__}: {e}", {"latency_s": time.perf_counter() - t0}
            )

    def _failed(self, t, message: str, info: dict) -> Plan:
        try:
            t = float(t)
        except (TypeError, ValueError):
            t = math.nan
        return failed_plan(t, self.spec.dt, self.spec.horizon, message, **info)


# --------------------------------------------------------------------------------------
# loading a run
# --------------------------------------------------------------------------------------
def _run_schema(run: Path, data: Mapping) -> tuple[dict, dict]:
    """Schema shapes and meta of a run's training data: from ``config.json`` (``data.schema``,
    ``data.meta``), else from the dataset manifest it names, else ``({}, {})``."""
    cfg_path = run / "config.json"
    info = {}
    if cfg_path.is_file():
        try:
            info = json.loads(cfg_path.read_text()).get("data", {}) or {}
        except (OSError, ValueError, AttributeError):
            info = {}
    if "schema" in info:
        return dict(info["schema"]), dict(info.get("meta") or {})
    directory = info.get("directory")
    if directory and (Path(directory) / "manifest.json").is_file():
        from scenarios.dataset import read_manifest

        try:
            m = read_manifest(directory)
        except EpoError:
            m = None
        if m is not None and {k: m.get(k) for k in ("scenario", "recipe", "seed")} == {
            k: data.get(k) for k in ("scenario", "recipe", "seed")
        }:
            return {k: v["shape"] for k, v in m["schema"].items()}, dict(m.get("meta") or {})
    return {}, {}


def _checkpoint_file(d: Path, checkpoint: str) -> Path:
    """The checkpoint of run ``d`` to load: ``best.pt`` when asked and present, else
    ``checkpoint.pt``; a missing run or file is a ``CheckpointError``."""
    from .train import CheckpointError

    if not d.is_dir():
        raise CheckpointError(str(d), "no such run directory")
    if checkpoint not in ("best", "last"):
        raise SpecError("checkpoint", f"expected 'best' or 'last', got {checkpoint!r}")
    path = (
        d / "best.pt" if checkpoint == "best" and (d / "best.pt").exists() else d / "checkpoint.pt"
    )
    if not path.exists():
        raise CheckpointError(
            str(path), "missing: not a training run directory (or it never finished an epoch)"
        )
    return path


def _history_shape(d: Path, schema: Mapping, data: Mapping, ck: Mapping) -> list:
    """``[H + 1, N, 4]``: the schema's history shape, or for runs trained before
    ``config.json`` stored the schema, the recipe's ``H`` and the game's agents."""
    from .train import CheckpointError

    hist = schema.get("history")
    if hist is not None:
        return hist
    H = (data.get("recipe") or {}).get("history")
    if not isinstance(H, int):
        raise CheckpointError(
            f"{d / 'config.json'}.data.schema.history",
            "missing, and the dataset's recipe names no history length",
        )
    return [H + 1, len(ck["game"]["agents"]), 4]


def _goal_reading(d: Path, cfg, game, schema: Mapping, world, scenario: str) -> bool:
    """Whether ours reads the scene's given goals; refuses a model that reads goal
    candidates the world cannot build (``World.scene_field_names``)."""
    kind = cfg.model.kind
    reads = (
        kind == "epo"
        and cfg.model.goal_decoder == "given"
        and any(f"goal.{a}" in game.params for a in game.agent_names)
    )
    if (
        kind == "epo"
        and cfg.model.goal_decoder == "candidates"
        and "goal_candidates" in schema
        and "goal_candidates" not in world_member(world, "scene_field_names")
    ):
        raise SpecError(
            f"{d / 'config.json'}.data.schema.goal_candidates",
            f"the model reads goal candidates and the planner cannot build them for scenario "
            f"{scenario!r}: scenarios.sim.scene_fields must build them (World.scene_field_names)",
        )
    return reads


def load_planner(
    run_dir: str | os.PathLike,
    world,
    *,
    checkpoint: str = "best",
    options: PlannerOptions | Mapping | None = None,
    **option_values,
) -> NetworkPlanner:
    """A :class:`NetworkPlanner` of a training run (``best.pt``, see :func:`learning.train.load_model`)
    for ``world`` (a :class:`~solvers.control.types.World`, or a name for
    :func:`scenarios.sim.make_world` with default options). ``options``: a
    :class:`PlannerOptions`, a mapping of its fields, or its fields as keywords.

    Refused with one error naming the field (:class:`~learning.train.CheckpointError` or
    :class:`~epo_casadi.errors.SpecError`): a missing run directory or checkpoint; the
    marginal V-LSTM (``model.kind``); a model trained on another scenario than the world's
    (``world.scenario``); other shapes than the world's (``world.n_agents``, ``world.dt``,
    ``world.horizon``, ``world.history`` where the world states them); a unicycle state
    size other than 4 (``game.state_size``); dataset fields the planner cannot build.
    The planner's :attr:`~NetworkPlanner.identity` names the checkpoint file, its SHA-256
    and its epoch and step (``epo simulate`` records it, so a run is never resumed with
    another model).
    """
    from scenarios.dataset import sha256_file

    from .data import dataset_game
    from .train import CheckpointError, _checkpoint_config, load_checkpoint, load_model

    if option_values:
        if options is not None:
            raise SpecError("planner", "give either options or option keywords, not both")
        options = option_values
    if isinstance(options, Mapping):
        options = PlannerOptions.from_dict(options)
    if isinstance(world, str):
        from scenarios.sim import make_world

        world = make_world(world)
    d = Path(run_dir)
    path = _checkpoint_file(d, checkpoint)
    sha = sha256_file(path)
    ck = load_checkpoint(path)
    cfg = _checkpoint_config(ck, str(path))
    kind = cfg.model.kind
    if kind not in ("epo", "sc"):
        raise SpecError(
            "model.kind",
            f"the run {d} holds a {kind!r} model, which predicts marginal positions and has no "
            "strategy to execute; use an 'epo' or 'sc' run",
        )
    data = ck["data"]
    scenario = data.get("scenario") if isinstance(data, Mapping) else None
    if not scenario:
        raise CheckpointError(f"{path}.data.scenario", "missing: the run names no dataset scenario")
    schema, meta = _run_schema(d, data)
    hist = _history_shape(d, schema, data, ck)
    frame = dataset_frame(scenario, meta.get("frame", "world"))
    if frame not in FRAMES:
        raise SpecError(
            f"{d / 'config.json'}.data.meta.frame", f"expected one of {list(FRAMES)}, got {frame!r}"
        )
    spec0 = SceneSpec(
        scenario=scenario,
        kind=kind,
        n_agents=int(hist[1]),
        history_steps=int(hist[0]),
        horizon=int(ck["game"]["horizon"]),
        dt=float(ck["game"]["dt"]),
        frame=frame,
    )
    _world_checks(spec0, world, str(d))
    game = dataset_game({"scenario": scenario, "recipe": data.get("recipe")})
    nx = sorted({a.dynamics.nx for a in game.agents})
    if nx != [4] or int(hist[2]) != 4:
        raise SpecError(
            "game.state_size",
            f"the model at {d} uses states of size {nx} (history {hist[2]}); the closed loop "
            "plans unicycle states (x, y, v, theta) of size 4",
        )
    model, cfg, ck = load_model(d, game, which=checkpoint)
    reads_goals = _goal_reading(d, cfg, game, schema, world, scenario)
    spec = replace(
        spec0,
        reads_goals=reads_goals,
        fields=tuple(k for k in schema if k not in ("history", "future")),
        recipe=data.get("recipe"),
    )
    if sha256_file(path) != sha:
        raise CheckpointError(
            str(path), "changed while it was being read (a training run writing it?); try again"
        )
    planner = NetworkPlanner(model, spec, options)
    planner.identity = {
        "checkpoint": path.name,
        "sha256": sha,
        "epoch": int(ck["epoch"]),
        "step": int(ck["step"]) if ck.get("step") is not None else None,
    }
    planner.reset(world)
    return planner


# --------------------------------------------------------------------------------------
# the trained planners of the closed loop's table (scenarios.closed_loop.roles.PLANNERS)
# --------------------------------------------------------------------------------------
def _run_planner(config, kind: str) -> NetworkPlanner:
    """The planner of the trained run ``config.model`` for ``config.scenario`` (a world of
    default options), its options ``config.planner_options``; a run of another model kind
    than ``kind`` is refused naming the planner that plays it."""
    planner = load_planner(config.model, config.scenario, **config.planner_options)
    got = planner.spec.kind
    if got != kind:
        other = "model" if got == "epo" else "sc"
        raise SpecError(
            "planner", f"the run {config.model} holds a {got!r} model; use --planner {other} for it"
        )
    return planner


def model_planner(config) -> NetworkPlanner:
    """The closed loop's ``"model"`` planner: ours (an ``"epo"`` run) from a
    :class:`scenarios.closed_loop.SimConfig`."""
    return _run_planner(config, "epo")


def sc_planner(config) -> NetworkPlanner:
    """The closed loop's ``"sc"`` planner: the SC baseline (an ``"sc"`` run) from a
    :class:`scenarios.closed_loop.SimConfig`."""
    return _run_planner(config, "sc")
