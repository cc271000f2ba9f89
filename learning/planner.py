"""The network as a closed-loop planner: a trained joint-control model (``"epo"``, ``"sc"``)
behind the :class:`solvers.control.types.Planner` protocol, for any world.

:class:`NetworkPlanner` implements the protocol for such a model; :func:`load_planner`
builds one from a training run directory (:mod:`learning.train`) for a world
(:class:`solvers.control.types.World`). Every planning period it turns the observation
into the scene the model was trained on (:func:`learning.observation.observation_scene`): the last ``H + 1``
states of every agent in the dataset's order (agent 0 = the ego, its exact states kept by
the planner; the others' filtered states from
:attr:`Estimate.history <solvers.control.types.Estimate>`), steps before the first one
filled by the constant-velocity backward extrapolation the dataset generators use
(:meth:`scenarios.rpi.RPIScenario.pre_history`) and marked ``False`` in
``history_valid``; the goals when the model reads given goals; everything in the
dataset's frame (manifest ``meta.frame``: ``"world"``, the default and RPI's, or
``"agent"``: agent 0 at the origin with ``x`` along its current heading). The scene
fields a world adds (maps, goal candidates) come from :func:`scenarios.sim.scene_fields`.
It runs the model once (evaluation mode, no gradients, one torch thread), executes the
most likely joint mode (:func:`learning.control.sdv_strategy`) and returns a
:class:`~solvers.control.types.Plan` in the world frame with every mode as a prediction.
A failure at planning time (non-finite input or output, a model error) returns
``Plan(ok=False)``, never raises.

:func:`model_planner` and :func:`sc_planner` are the closed loop's trained planners
(``"model"``, ``"sc"`` in :data:`scenarios.closed_loop.roles.PLANNERS`).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from epo_casadi.errors import EpoError, SpecError, check_size
from scenarios.sim import FRAMES, dataset_frame, world_scenario
from solvers.control.plan import failed_plan
from solvers.control.types import Estimate, Observation, Plan, world_member

from .control import sdv_strategy
from .layer import GameLayer
from .observation import SceneFrame, SceneSpec, observation_scene

__all__ = [
    "PlannerOptions",
    "NetworkPlanner",
    "observation_scene",
    "load_planner",
    "model_planner",
    "sc_planner",
]


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


def _history_shape(d: Path, schema: Mapping, data: Mapping, ck: Mapping) -> list:
    """``[H + 1, N, 4]``: the schema's history shape, or for runs trained before
    ``config.json`` stored the schema, the recipe's ``H`` and the game's agents."""
    from .checkpoint import CheckpointError

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


def _checkpoint_spec(d: Path, path: Path, ck: Mapping) -> tuple[SceneSpec, dict, list]:
    """What the checkpoint ``ck`` (file ``path`` of run ``d``) says of its scenes:
    ``(SceneSpec without goals and fields, dataset schema shapes, history shape)``;
    refuses the marginal V-LSTM, a run without a scenario and an unknown frame."""
    from .checkpoint import CheckpointError
    from .train import _checkpoint_config

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
    return spec0, schema, hist


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

    Refused with one error naming the field (:class:`~learning.checkpoint.CheckpointError` or
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

    from .checkpoint import CheckpointError, checkpoint_path, load_checkpoint
    from .data import dataset_game
    from .train import load_model

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
    path = checkpoint_path(d, checkpoint)
    sha = sha256_file(path)
    ck = load_checkpoint(path)
    spec0, schema, hist = _checkpoint_spec(d, path, ck)
    data = ck["data"]
    scenario = spec0.scenario
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
