"""The settings of a training run (:mod:`learning.train`): :class:`TrainConfig`, its result.

:class:`TrainConfig` holds every setting of a run (model kind, optimizer, loss weights,
batches, checkpoints) and checks them when built; :data:`PAPER_LOSS_WEIGHTS` gives the
paper's loss weights by model kind. :class:`TrainResult` is what :func:`learning.train.train`
returns. ``_checkpoint_config`` reads the settings back from a checkpoint and
``_check_same_run`` refuses a checkpoint of another run (other model or settings).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from epo_casadi.errors import SpecError

from .checkpoint import CheckpointError, setting_diff
from .losses import IMITATION_REDUCTIONS, LossWeights
from .models import ModelConfig

#: loss weights of the paper by model kind (imitation, goal, probability)
PAPER_LOSS_WEIGHTS = {
    "epo": LossWeights(1.0, 0.1, 0.1),
    "sc": LossWeights(1.0, 0.0, 1.0),
    "vlstm": LossWeights(1.0, 0.0, 1.0),
    "tgl": LossWeights(1.0, 0.0, 1.0),  # scene loss, as + SC (learning.tgl)
}


def _int(name, v, lo):
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise SpecError(f"train.{name}", f"expected an integer >= {lo}, got {v!r}")


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (with the dataset). Frozen; unknown keys fail."""

    model: ModelConfig = ModelConfig()  #: architecture, modes, game-layer steps (S, alpha, lambda)
    epochs: int = 10  #: passes over the training split
    batch_size: int = 32  #: samples per optimizer step (paper: 32)
    lr: float = 5e-5  #: Adam learning rate (paper, ours on RPI/exiD: 5e-5)
    seed: int = 0  #: initial weights and the shuffling of every epoch
    loss: LossWeights | None = None  #: None: PAPER_LOSS_WEIGHTS of the model kind
    checkpoint_steps: int = 0  #: also checkpoint every this many steps (0: at epoch ends only)
    eval_batch_size: int = 64  #: batch size of the validation pass
    val_split: str | None = "val"  #: split scored after every epoch (None: none)
    #: the imitation loss over the future steps: "mean" or "sum" (the paper's App. F.4)
    imitation_reduction: str = "mean"

    def __post_init__(self):
        if not isinstance(self.model, ModelConfig):
            raise SpecError(
                "train.model", f"expected a ModelConfig, got {type(self.model).__name__}"
            )
        if self.loss is not None and not isinstance(self.loss, LossWeights):
            raise SpecError("train.loss", f"expected LossWeights or None, got {self.loss!r}")
        _int("epochs", self.epochs, 1)
        _int("batch_size", self.batch_size, 1)
        _int("seed", self.seed, 0)
        _int("checkpoint_steps", self.checkpoint_steps, 0)
        _int("eval_batch_size", self.eval_batch_size, 1)
        lr = self.lr
        if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not 0 < lr < math.inf:
            raise SpecError("train.lr", f"expected a finite number > 0, got {lr!r}")
        if self.imitation_reduction not in IMITATION_REDUCTIONS:
            raise SpecError(
                "train.imitation_reduction",
                f"expected one of {list(IMITATION_REDUCTIONS)}, got {self.imitation_reduction!r}",
            )
        if self.val_split not in (None, "train", "val", "test"):
            raise SpecError(
                "train.val_split",
                f"expected 'val', 'test', 'train' or None, got {self.val_split!r}",
            )

    @property
    def loss_weights(self) -> LossWeights:
        """The loss weights used: ``loss``, or the paper's for the model kind."""
        return self.loss if self.loss is not None else PAPER_LOSS_WEIGHTS[self.model.kind]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["loss"] = asdict(self.loss_weights)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys (also in ``model`` and ``loss``) fail."""
        if not isinstance(d, dict):
            raise SpecError("train", f"expected a mapping, got {type(d).__name__}")
        d = dict(d)
        for key, klass in (("model", ModelConfig), ("loss", LossWeights)):
            sub = d.get(key)
            if isinstance(sub, dict):
                names = {f.name for f in fields(klass)}
                unknown = sorted(set(sub) - names)
                if unknown:
                    raise SpecError(
                        f"train.{key}", f"unknown field(s) {unknown}; allowed: {sorted(names)}"
                    )
                if key == "model" and "lane_path" not in sub:
                    # saved before ModelConfig.lane_path existed: ours used the current lane
                    sub = {**sub, "lane_path": "current"}
                if key == "model" and "own_norm" not in sub:
                    # saved before ModelConfig.own_norm existed: no batch norm in own_dec
                    sub = {**sub, "own_norm": "none"}
                d[key] = klass(**sub)
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise SpecError("train", f"unknown field(s) {unknown}; allowed: {sorted(names)}")
        return cls(**d)


@dataclass
class TrainResult:
    """What one :func:`train` call did."""

    run_dir: str
    epochs: int  #: epochs completed in the run (all calls)
    steps: int  #: optimizer steps completed in the run (all calls)
    history: list[dict]  #: the rows of metrics.csv
    seconds: float  #: wall time of this call
    resumed_from: int | None = None  #: step of the checkpoint this call resumed from
    step_losses: list[tuple[int, float]] = field(default_factory=list)  #: (step, loss) of this call


# --------------------------------------------------------------------------------------
# loading a run
# --------------------------------------------------------------------------------------
def _checkpoint_config(ck: dict, where: str) -> TrainConfig:
    try:
        return TrainConfig.from_dict(ck["config"])
    except (SpecError, TypeError) as e:
        raise CheckpointError(f"{where}.config", str(e)) from None


def _check_same_run(ck: dict, run_config: dict, path: Path) -> None:
    """Refuse a checkpoint whose settings differ from its run directory's (another run's file)."""
    diff = setting_diff(_checkpoint_config(ck, str(path)).to_dict(), run_config)
    if diff is not None:
        raise CheckpointError(
            str(path),
            f"belongs to another run: its {diff} differs from the run's config.json; "
            "copy back the run's own file or retrain",
        )
