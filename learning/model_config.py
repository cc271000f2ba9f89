"""The settings of a predictor: :class:`ModelConfig` and the values its fields take.

:class:`ModelConfig` holds the architecture and layer settings that :mod:`learning.models`
builds from (paper App. F.1, F.3) and checks them when made: the kinds, backbones,
backward passes, goal decoders (:data:`GOAL_DECODERS`), norms (:data:`OWN_NORMS`) and layer
backends (:data:`LAYER_BACKENDS`) it accepts, the largest size of every width and count
(:data:`SIZE_LIMITS`), the settings that choose how the layer computes rather than what
(:data:`EXECUTION_SETTINGS`) and the backend a configuration resolves to on this machine
(:func:`layer_execution`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from epo_casadi.errors import SpecError, check_bool, check_number, check_size

from . import backbones as _backbones

GOAL_DECODERS = ("given", "candidates", "regress")

#: values of ``ModelConfig.own_norm``
OWN_NORMS = ("batch", "none")
#: values of ``ModelConfig.layer_backend``
LAYER_BACKENDS = ("auto", "fused", "structured", "dense")
#: model settings that choose how the layer computes, not what: a run may resume with others
EXECUTION_SETTINGS = ("layer_backend", "layer_compiled")


def layer_execution(cfg: ModelConfig) -> tuple[str, bool]:
    """The (backend name, compiled) pair that ``cfg``'s layer settings resolve to here.

    ``layer_compiled="yes"`` without a C compiler raises :class:`solvers.codegen.CompilerError`
    when the layer is built; ``"auto"`` falls back to the interpreter, and the ``"auto"``
    backend then to ``"structured"`` (faster than the interpreted fused backend in a batch).
    """
    from solvers.codegen import CompilerError, find_compiler

    compiled = cfg.layer_compiled == "yes"
    if cfg.layer_compiled == "auto":
        try:
            find_compiler()
            compiled = True
        except CompilerError:
            compiled = False
    backend = cfg.layer_backend
    if backend == "auto":
        backend = "fused" if compiled else "structured"
    return backend, compiled


#: the largest value of every size setting of :class:`ModelConfig` (checked before any
#: network is built: ``hist_width = 10**6`` would ask for terabytes). Widths up to 32x the
#: paper's, depths, modes, heads and LM steps far beyond any setting the paper uses.
SIZE_LIMITS = {
    "modes": 64,  # joint modes M: B x M games in the layer
    "hist_width": 2048,  # LSTM / transformer widths
    "hist_layers": 16,
    "lane_width": 2048,
    "global_width": 4096,
    "heads": 64,
    "dec_width": 2048,
    "lm_steps": 100,  # S: unrolled LM steps (the backward pass keeps every one)
    "goal_rings": 100,  # generated goal candidates: rings x angles
    "goal_angles": 360,
}


@dataclass(frozen=True)
class ModelConfig:
    """Architecture and layer settings (defaults: paper App. F.1, F.3).

    Every size setting (``modes``, the widths, ``hist_layers``, ``heads``, ``lm_steps``,
    ``goal_rings``, ``goal_angles``) is an integer from 1 to its limit in
    :data:`SIZE_LIMITS`; a larger one is refused with :class:`SpecError` naming the field
    and the limit before any network is built.
    """

    kind: str = "epo"  #: "epo" (ours), "sc" (+ SC), "vlstm" (marginal), "tgl" (+ TGL)
    modes: int = 2  #: M joint modes (RPI: 2)
    backbone: str = "vlstm"  #: "vlstm", "vibes" or "hivt" (HiVT-M): learning.backbones
    hist_width: int = 64  #: LSTM width
    hist_layers: int = 3  #: LSTM depth
    lane_width: int = 64  #: PointNet lane encoder width (3 layers)
    global_width: int = 128  #: width of the global interaction graph
    heads: int = 4  #: attention heads
    dec_width: int = 64  #: width of the 3-layer decoder MLPs
    lm_steps: int = 2  #: S, LM steps in the game layer
    step_size: float = 0.3  #: alpha
    damping: float = 10.0  #: lambda
    learned_init: bool = True  #: ablation: False uses zeros as initial strategies
    goal_features: bool = True  #: ablation: False removes the goal term (weight 0)
    backward: str = "unrolled"  #: game layer backward mode
    goal_decoder: str = "given"  #: ours: "given" (scene goals), "candidates" or "regress"
    goal_rings: int = 5  #: generated candidates (no scene candidates, no lanes): rings ...
    goal_angles: int = 12  #: ... x angles around the agent (paper: G = 60 goal points)
    goal_range: float = 5.0  #: radius in metres of the outermost candidate ring
    #: Gauss-Newton backend of ours' game layer (an execution detail: every backend gives the
    #: same steps to rounding, tested to 1e-12, so a run may resume with another): "auto"
    #: (fused with generated C when a C compiler is found, else structured: the fastest
    #: measured in a training batch, docs/layer.md), "fused", "structured" or "dense"
    layer_backend: str = "auto"
    #: generated C for the layer's functions (backend and backward pass): "auto" (when a C
    #: compiler is found; compiled once per game structure, cached on disk), "yes" or "no"
    layer_compiled: str = "auto"
    #: ours: the margin (m) of the model game's collision feature, whose reach is then
    #: ``r_i + r_j + collision_margin``; None keeps the dataset game's. The agents' radii,
    #: and with them the overlap rate, stay the dataset's (docs/experiment_rpi.md: the Peters
    #: ground truth interacts up to 1.5 m, beyond the RPI game's 0.65 m reach)
    collision_margin: float | None = None
    #: ours: the reference lane of each mode's ``lane`` term when the game has a ``path``
    #: block: "goal" (the paper's c_lane: the lane the mode's goal candidate lies on, from
    #: the scene's ``goal_lane``; the scene's ``paths`` where the candidate is on no lane or
    #: the scene has no ``goal_lane``) or "current" (the scene's ``paths`` for every mode).
    #: Runs saved before the field existed load as "current" (what they were trained with).
    lane_path: str = "goal"
    #: ours: normalization of the agent-weight decoder's hidden layers: "batch" (paper
    #: App. F: "the goal, agent weight, and scene probability decoder use batch
    #: normalization"; run on the real agents only, like the goal decoder) or "none".
    #: Runs saved before the field existed were trained with "none".
    own_norm: str = "batch"

    def __post_init__(self):
        if self.kind not in ("epo", "sc", "vlstm", "tgl"):
            raise SpecError(
                "model.kind", f"expected 'epo', 'sc', 'vlstm' or 'tgl', got {self.kind!r}"
            )
        if self.backbone not in _backbones.BACKBONES:
            raise SpecError(
                "model.backbone",
                f"expected one of {', '.join(map(repr, _backbones.BACKBONES))}, "
                f"got {self.backbone!r}",
            )
        if self.backward not in ("unrolled", "implicit"):
            raise SpecError(
                "model.backward", f"expected 'unrolled' or 'implicit', got {self.backward!r}"
            )
        if self.goal_decoder not in GOAL_DECODERS:
            raise SpecError(
                "model.goal_decoder",
                f"expected one of {', '.join(map(repr, GOAL_DECODERS))}, got {self.goal_decoder!r}",
            )
        if self.goal_decoder != "given" and self.kind != "epo":
            raise SpecError(
                "model.goal_decoder",
                f"only the 'epo' model decodes goals; the {self.kind!r} model needs 'given'",
            )
        for k, limit in SIZE_LIMITS.items():
            check_number(f"model.{k}", getattr(self, k), lo=1, integer=True)
            check_size(f"model.{k}", getattr(self, k), limit, "the model's memory and time")
        if self.global_width % self.heads:
            raise SpecError(
                "model.heads",
                f"expected a divisor of global_width {self.global_width}, got {self.heads}",
            )
        if self.backbone == "hivt" and self.hist_width % self.heads:
            raise SpecError(
                "model.heads",
                f"expected a divisor of hist_width {self.hist_width} (HiVT-M), got {self.heads}",
            )
        for k in ("step_size", "damping", "goal_range"):
            check_number(f"model.{k}", getattr(self, k), lo=0, lo_open=True)
        if self.collision_margin is not None:
            check_number("model.collision_margin", self.collision_margin, lo=0)
            if self.kind != "epo":
                raise SpecError(
                    "model.collision_margin",
                    f"only the 'epo' model has a game layer; the {self.kind!r} model needs null",
                )
        if self.layer_backend not in LAYER_BACKENDS:
            raise SpecError(
                "model.layer_backend",
                f"expected one of {', '.join(map(repr, LAYER_BACKENDS))}, got {self.layer_backend!r}",
            )
        if self.layer_compiled not in ("auto", "yes", "no"):
            raise SpecError(
                "model.layer_compiled",
                f"expected 'auto', 'yes' or 'no', got {self.layer_compiled!r}",
            )
        if self.lane_path not in ("goal", "current"):
            raise SpecError(
                "model.lane_path", f"expected 'goal' or 'current', got {self.lane_path!r}"
            )
        if self.own_norm not in OWN_NORMS:
            raise SpecError(
                "model.own_norm",
                f"expected one of {', '.join(map(repr, OWN_NORMS))}, got {self.own_norm!r}",
            )
        for k in ("learned_init", "goal_features"):
            check_bool(f"model.{k}", getattr(self, k))

    def to_dict(self) -> dict:
        return asdict(self)
