"""Training: :class:`TrainConfig` and :func:`train` (paper Sec. 4.3, 5, App. F.4).

Optimizer and losses
    Adam, batch size 32, learning rate ``5e-5`` (the paper's for ours on RPI and exiD).
    Loss weights ``(lambda_imit, lambda_goal, lambda_prob)`` by model kind
    (:data:`PAPER_LOSS_WEIGHTS`): ours ``(1, 0.1, 0.1)``; V-LSTM + SC ``(1, 0, 1)``
    (``L_imit + L_prob``, Sec. 5); V-LSTM marginal: minADE + classification ``(1, -, 1)``.
    The goal loss is zero on RPI (goals are given). The networks train in float32; the game
    layer solves in float64 inside and casts back (:mod:`learning.layer`).

A run directory (``out_dir``)::

    config.json      TrainConfig, dataset identity (scenario, recipe, seed), game summary
    checkpoint.pt    the latest state: model, optimizer, torch RNG, epoch, step, history
    best.pt          model weights of the epoch with the lowest validation minSADE
    metrics.csv      one row per epoch: train loss parts, samples/s, validation metrics
    loss.png         training loss and validation minADE/minSADE per epoch
    tb/              TensorBoard events (only when ``tensorboard`` is installed)
    .lock            held (flock) while a training runs: a second ``train`` into the
                     same folder is refused at once (:func:`scenarios.files.output_lock`)

A run folder is never a dataset folder (one holding ``manifest.json``): :func:`train`
refuses one (:func:`check_run_dir`) before anything is written.

Checkpoints and resume
    A checkpoint is written at the end of every epoch (and every ``checkpoint_steps``
    optimizer steps, if set) to a temporary file, fsynced and renamed
    (:func:`scenarios.files.write_atomic`, like every file of the run): a run killed at
    any moment, or stopped by a full disk or a read-only folder (one
    :class:`~epo_casadi.errors.OutputError` naming the file), leaves the previous
    checkpoint intact and no partial file. ``checkpoint.pt`` and ``best.pt``
    carry a sha256 of their content (:data:`CHECKSUM_MAGIC` header line, then the
    ``torch.save`` bytes); :func:`load_checkpoint` verifies it and refuses a changed or
    damaged file naming it. A file written before checksums existed (a plain
    ``torch.save`` zip) still loads, with a :class:`UncheckedCheckpointWarning`; the
    next checkpoint of a resumed run is written with a checksum.
    :func:`train` on a directory that holds a checkpoint continues from it: same model,
    optimizer and RNG states, and the batches of an epoch come from the permutation of
    ``(seed, epoch)`` (:meth:`learning.data.SceneDataset.order`), so the resumed run takes
    exactly the steps the uninterrupted one would have taken (tested: equal next-step
    loss). Raising
    ``epochs`` and running again trains on; a different setting (other than ``epochs``,
    ``checkpoint_steps``, ``eval_batch_size``) or another dataset is refused, and so is a
    ``best.pt`` of another run (other model or settings). A directory that holds
    ``best.pt`` or ``metrics.csv`` but no ``checkpoint.pt`` is refused rather than
    trained from scratch over that history. A loss or parameters that become non-finite
    stop the run with one line naming the epoch and step (and suggesting a lower
    learning rate); the last checkpoint is kept.

BatchNorm in the scene-probability decoder needs two values per channel: a training batch
of one sample with ``modes = 1`` is skipped (only possible for a last, partial batch).
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import math
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import torch

from epo_casadi.errors import EpoError, SpecError
from scenarios.dataset import MANIFEST, DatasetError, check_output_dir
from scenarios.files import output_lock, write_atomic

from .data import SceneDataset, game_summary
from .losses import LossWeights, goal_loss, marginal_loss, scene_loss
from .models import EXECUTION_SETTINGS, ModelConfig, build_model, count_parameters
from .scoring import METRICS, evaluate_model

__all__ = [
    "PAPER_LOSS_WEIGHTS",
    "CheckpointError",
    "TrainConfig",
    "TrainResult",
    "UncheckedCheckpointWarning",
    "check_run_dir",
    "compute_loss",
    "load_checkpoint",
    "load_model",
    "torch_threads",
    "train",
]

CHECKPOINT_FORMAT = 1
#: first bytes of a checkpoint file; 64 hex digits of the payload's sha256 and b"\n" follow
CHECKSUM_MAGIC = b"EPO-CHECKPOINT sha256="
_HEADER = len(CHECKSUM_MAGIC) + 65
_ZIP_MAGIC = b"PK\x03\x04"  # a plain torch.save file (checkpoints before checksums)
#: loss weights of the paper by model kind (imitation, goal, probability)
PAPER_LOSS_WEIGHTS = {
    "epo": LossWeights(1.0, 0.1, 0.1),
    "sc": LossWeights(1.0, 0.0, 1.0),
    "vlstm": LossWeights(1.0, 0.0, 1.0),
    "tgl": LossWeights(1.0, 0.0, 1.0),  # scene loss, as + SC (learning.tgl)
}
#: settings that may change when a run is resumed
RESUMABLE_CHANGES = ("epochs", "checkpoint_steps", "eval_batch_size")


class CheckpointError(EpoError):
    """A run directory or checkpoint is missing, unreadable or belongs to another setup."""

    def __init__(self, where: str, message: str):
        self.where, self.message = where, message
        super().__init__(f"{where}: {message}")


class UncheckedCheckpointWarning(UserWarning):
    """A checkpoint written before checksums existed was loaded without verification."""


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
# checkpoints
# --------------------------------------------------------------------------------------
def _atomic_torch_save(obj, path: Path) -> None:
    """``torch.save`` bytes behind a sha256 header line, written atomically
    (:func:`scenarios.files.write_atomic`: a full disk leaves the previous file intact)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    payload = buf.getvalue()
    header = CHECKSUM_MAGIC + hashlib.sha256(payload).hexdigest().encode() + b"\n"
    write_atomic(path, lambda f: (f.write(header), f.write(payload)))


def _atomic_text(path: Path, text: str) -> None:
    write_atomic(path, text)


def load_checkpoint(path: str | os.PathLike) -> dict:
    """A checkpoint written by :func:`train`; :class:`CheckpointError` if missing or corrupt."""
    p = Path(path)
    if not p.is_file():
        raise CheckpointError(str(p), "no such checkpoint file")
    raw = p.read_bytes()
    if raw.startswith(CHECKSUM_MAGIC):
        digest, payload = raw[len(CHECKSUM_MAGIC) : _HEADER - 1], raw[_HEADER:]
        if (
            raw[_HEADER - 1 : _HEADER] != b"\n"
            or hashlib.sha256(payload).hexdigest().encode() != digest
        ):
            raise CheckpointError(
                str(p),
                "sha256 checksum mismatch: the checkpoint is damaged or was changed after it "
                "was written; restore it from a backup or train into a new directory",
            )
    elif raw.startswith(_ZIP_MAGIC):
        payload = raw
        warnings.warn(
            f"{p}: written without a checksum (before checksums were added); loaded "
            "unverified (checkpoints written from now on carry one)",
            UncheckedCheckpointWarning,
            stacklevel=2,
        )
    else:
        raise CheckpointError(
            str(p), "unreadable checkpoint (no checkpoint header: not written by epo train)"
        )
    try:
        ck = torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many kinds for a damaged file
        msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise CheckpointError(
            str(p), f"unreadable checkpoint ({type(e).__name__}: {msg[:120]})"
        ) from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        got = ck.get("format") if isinstance(ck, dict) else type(ck).__name__
        raise CheckpointError(f"{p}.format", f"expected {CHECKPOINT_FORMAT}, got {got!r}")
    for key in ("config", "game", "data", "model", "epoch"):
        if key not in ck:
            raise CheckpointError(f"{p}.{key}", "missing")
    return ck


def _checkpoint_config(ck: dict, where: str) -> TrainConfig:
    try:
        return TrainConfig.from_dict(ck["config"])
    except (SpecError, TypeError) as e:
        raise CheckpointError(f"{where}.config", str(e)) from None


def _settings(d: dict) -> dict:
    """A config dict without the model's execution settings (the layer's backend and
    compilation: the same steps to rounding), so a run may resume with others."""
    if isinstance(d.get("model"), dict):
        d = {**d, "model": {k: v for k, v in d["model"].items() if k not in EXECUTION_SETTINGS}}
    return d


def _run_setting_diff(saved: dict, now: dict) -> str | None:
    """First training setting (``model.kind``, ``seed``, ...) in which two configs differ."""
    saved, now = _settings(saved), _settings(now)
    for k in now:
        if k in RESUMABLE_CHANGES or saved.get(k) == now[k]:
            continue
        if k == "model" and isinstance(saved.get(k), dict):
            sub = [j for j in now[k] if saved[k].get(j) != now[k][j]]
            if sub:
                return f"model.{sub[0]} ({saved[k].get(sub[0])!r}, run: {now[k][sub[0]]!r})"
        return f"{k} ({saved.get(k)!r}, run: {now[k]!r})"
    return None


def _check_same_run(ck: dict, run_config: dict, path: Path) -> None:
    """Refuse a checkpoint whose settings differ from its run directory's (another run's file)."""
    diff = _run_setting_diff(_checkpoint_config(ck, str(path)).to_dict(), run_config)
    if diff is not None:
        raise CheckpointError(
            str(path),
            f"belongs to another run: its {diff} differs from the run's config.json; "
            "copy back the run's own file or retrain",
        )


def check_game(saved: dict, game, where: str) -> None:
    """Refuse a model trained on a game that differs from ``game`` (agents, horizon, params)."""
    now = game_summary(game)
    for k, v in saved.items():
        if now.get(k) != v:
            raise CheckpointError(
                f"{where}.game.{k}",
                f"the run was trained on a game with {k} {v!r}, the dataset's game has {now.get(k)!r}",
            )


def load_model(run_dir: str | os.PathLike, game, which: str = "best"):
    """Model of a run directory for ``game`` in eval mode: ``(model, TrainConfig, checkpoint)``.

    ``which``: ``"best"`` (``best.pt``, falling back to ``checkpoint.pt`` when a run has
    no validation split yet) or ``"last"`` (``checkpoint.pt``).
    """
    d = Path(run_dir)
    if not d.is_dir():
        raise CheckpointError(str(d), "no such run directory")
    if which not in ("best", "last"):
        raise SpecError("checkpoint", f"expected 'best' or 'last', got {which!r}")
    path = d / "best.pt" if which == "best" and (d / "best.pt").exists() else d / "checkpoint.pt"
    if not path.exists():
        raise CheckpointError(
            str(path), "missing: not a training run directory (or it never finished an epoch)"
        )
    ck = load_checkpoint(path)
    cfg = _checkpoint_config(ck, str(path))
    info = d / "config.json"
    if info.is_file():  # the run's own settings: a file copied from another run is refused
        try:
            run_config = TrainConfig.from_dict(json.loads(info.read_text())["train"]).to_dict()
        except (ValueError, KeyError, TypeError, SpecError) as e:
            raise CheckpointError(str(info), f"unreadable run settings ({e})") from None
        _check_same_run(ck, run_config, path)
    check_game(ck["game"], game, str(path))
    model = build_model(cfg.model, game)
    try:
        model.load_state_dict(ck["model"])
    except (RuntimeError, KeyError, TypeError) as e:
        raise CheckpointError(
            f"{path}.model", f"weights do not fit the model ({str(e).splitlines()[0][:160]})"
        ) from None
    model.eval()
    return model, cfg, ck


# --------------------------------------------------------------------------------------
# losses, records
# --------------------------------------------------------------------------------------
def compute_loss(
    kind: str, out: dict, gt: torch.Tensor, weights: LossWeights
) -> dict[str, torch.Tensor]:
    """The training loss of a model's output: scene loss (ours, SC) or marginal loss (V-LSTM),
    plus ``weights.goal`` times the goal loss when the model decodes goals (part ``goal``,
    zero otherwise)."""
    if kind == "vlstm":
        parts = marginal_loss(out["pos"], out["marginal_logits"], gt, weights)
    else:
        parts = scene_loss(out["pos"], out["logits"], gt, weights)
    g = goal_loss(out, gt)
    if g is None:
        parts["goal"] = torch.zeros((), dtype=parts["loss"].dtype)
    else:
        parts["goal"] = g
        parts["loss"] = parts["loss"] + weights.goal * g
    return parts


def _zero_sums() -> dict:
    return {
        "loss": 0.0,
        "imitation": 0.0,
        "probability": 0.0,
        "goal": 0.0,
        "samples": 0,
        "seconds": 0.0,
    }


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    keys = list(rows[0])
    for r in rows[1:]:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    w.writerows(rows)
    _atomic_text(path, buf.getvalue())


def plot_history(rows: list[dict], out_png: str | os.PathLike, title: str = "") -> None:
    """Training loss parts and validation minADE/minSADE per epoch (matplotlib, Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.6))
    FigureCanvasAgg(fig)
    a1, a2 = fig.subplots(1, 2)
    ep = [r["epoch"] for r in rows]
    parts = [("train_loss", "-o"), ("train_imitation", "--"), ("train_probability", ":")]
    if all(r.get("train_goal", 0) > 0 for r in rows):  # a goal decoder's loss
        parts.append(("train_goal", "-."))
    for k, style in parts:
        a1.plot(ep, [r[k] for r in rows], style, label=k.replace("train_", ""))
    a1.set_yscale("log")
    a1.set_xlabel("epoch")
    a1.set_title("training loss")
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    for k in ("val_minADE", "val_minSADE", "val_minFDE", "val_minSFDE"):
        vals = [r.get(k, math.nan) for r in rows]
        if any(math.isfinite(v) for v in vals):
            a2.plot(ep, vals, "-o", ms=3, label=k[4:])
    a2.set_xlabel("epoch")
    a2.set_ylabel("m")
    a2.set_title("validation")
    if a2.lines:
        a2.legend(fontsize=8)
    a2.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    write_atomic(out_png, lambda f: fig.savefig(f, format="png", dpi=100))


@contextlib.contextmanager
def torch_threads(n: int | None):
    """Run a block with ``n`` torch intra-op threads (None: leave as is), then restore.

    One thread is the default of the commands: these networks are small, and on a shared
    2-core machine two OpenMP threads made a training step 10-20x slower than one
    (measured in ``docs/learning.md``).
    """
    if n is None:
        yield
        return
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise SpecError("threads", f"expected an integer >= 1 or None, got {n!r}")
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _tensorboard(log_dir: Path, purge_step: int):
    """A SummaryWriter when tensorboard is installed, else None."""
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from torch.utils.tensorboard import SummaryWriter
    except Exception:  # not installed (ImportError) or broken: TensorBoard is optional
        return None
    return SummaryWriter(str(log_dir), purge_step=purge_step)


def _diverged_error(epoch: int, step: int, lr: float, ck_path: Path, what: str) -> EpoError:
    kept = "the last checkpoint is kept" if ck_path.exists() else "no checkpoint was written yet"
    return EpoError(
        f"train: the loss diverged at epoch {epoch + 1}, step {step} ({what} became "
        f"non-finite); {kept}; try a lower learning rate than {lr:g} (--lr)"
    )


@contextlib.contextmanager
def _diverged(epoch: int, step: int, lr: float, ck_path: Path, what: str):
    """Turn the game layer's refusal of non-finite inputs into the divergence message.

    Huge weights after a step with a huge learning rate decode to inf/NaN game weights,
    which :class:`learning.layer.GameLayer` refuses; that message speaks of the layer's
    options, which a user of ``epo train`` cannot act on.
    """
    try:
        yield
    except SpecError as e:
        if getattr(e, "field", None) not in ("p", "u_init"):  # the layer's inputs only
            raise
        raise _diverged_error(epoch, step, lr, ck_path, what) from None


# --------------------------------------------------------------------------------------
# training
# --------------------------------------------------------------------------------------
def train(
    data_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    config: TrainConfig = TrainConfig(),
    *,
    progress: bool = True,
    on_step: Callable[[int, dict], None] | None = None,
    threads: int | None = 1,
) -> TrainResult:
    """Train ``config.model`` on the train split of ``data_dir``; resume ``out_dir`` if it has a checkpoint.

    ``on_step(step, parts)`` runs after every optimizer step (and its checkpoint, if
    one is due) with the loss parts as floats; tests raise from it to simulate a kill.
    ``threads``: torch threads during the call (:func:`torch_threads`; None: unchanged).
    Returns a :class:`TrainResult`; see the module docstring for the files written.
    """
    if not isinstance(config, TrainConfig):
        raise SpecError("config", f"expected a TrainConfig, got {type(config).__name__}")
    out = check_run_dir(out_dir, data_dir)
    with torch_threads(threads), output_lock(out, "epo train"):
        return _train(data_dir, out, config, progress, on_step)


def check_run_dir(
    out_dir: str | os.PathLike, data_dir: str | os.PathLike | None = None, field: str = "out"
) -> Path:
    """``out_dir`` as a run folder to create or resume; refused before anything is written.

    A path through a file is a :class:`CheckpointError`; a dataset folder (one holding
    ``manifest.json``, or ``data_dir`` itself) is a :class:`SpecError` naming ``field``:
    a run's files never go into a dataset.
    """
    out = Path(out_dir)
    try:
        check_output_dir(out)
    except DatasetError as e:
        raise CheckpointError(e.where, e.message) from None
    same = data_dir is not None and out.exists() and out.resolve() == Path(data_dir).resolve()
    if same or (out / MANIFEST).is_file():
        raise SpecError(
            field,
            f"{out} is a dataset folder (it holds {MANIFEST}); give a run folder of its own, "
            "e.g. runs/NAME",
        )
    return out


def _train(data_dir, out_dir, config: TrainConfig, progress: bool, on_step) -> TrainResult:
    t_call = time.perf_counter()
    cfg = config
    kind = cfg.model.kind
    train_ds = SceneDataset(data_dir, "train")
    if len(train_ds) == 0:
        raise SpecError("data", f"{data_dir}: the train split has no samples")
    game = train_ds.game
    m = cfg.model
    has_goal_param = any(f"goal.{a}" in game.params for a in game.agent_names)
    if kind == "epo" and m.goal_decoder == "given" and has_goal_param:
        if "goals" not in train_ds.fields:
            raise DatasetError(
                f"{Path(data_dir) / MANIFEST}.schema.goals",
                "missing; the model reads given goals (model.goal_decoder='given'): "
                "use --set goal_decoder=candidates or --set goal_decoder=regress",
            )
    val_ds = None
    if cfg.val_split is not None:
        val_ds = SceneDataset(data_dir, cfg.val_split)
        if len(val_ds) == 0:
            val_ds = None
    out = Path(out_dir)  # created and locked by train()
    ck_path, best_path = out / "checkpoint.pt", out / "best.pt"
    summary = game_summary(game)
    fingerprint = train_ds.fingerprint

    state = None
    history_files = [f for f in (best_path, out / "metrics.csv") if f.exists()]
    if not ck_path.exists() and history_files:
        raise CheckpointError(
            str(ck_path),
            f"missing, but {' and '.join(f.name for f in history_files)} of an earlier run "
            "exist and training from scratch would overwrite them; restore checkpoint.pt, "
            "or train into a new directory",
        )
    if ck_path.exists():
        state = load_checkpoint(ck_path)
        old = _settings(_checkpoint_config(state, str(ck_path)).to_dict())
        new = _settings(cfg.to_dict())
        for k in new:
            if k not in RESUMABLE_CHANGES and old.get(k) != new[k]:
                raise CheckpointError(
                    str(ck_path),
                    f"holds a run with a different {k} ({old.get(k)!r}, now {new[k]!r}); "
                    "use another output directory",
                )
        if json.dumps(state["data"], sort_keys=True) != json.dumps(fingerprint, sort_keys=True):
            raise CheckpointError(
                str(ck_path), f"holds a run trained on another dataset than {data_dir}"
            )
        check_game(state["game"], game, str(ck_path))
        if best_path.exists():  # verified now, and refused if it belongs to another run
            _check_same_run(load_checkpoint(best_path), cfg.to_dict(), best_path)

    torch.manual_seed(cfg.seed)
    model = build_model(cfg.model, game)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    history: list[dict] = []
    epoch, step, start_batch = 0, 0, 0
    sums = _zero_sums()
    best = math.inf
    if state is not None:
        try:
            model.load_state_dict(state["model"])
            opt.load_state_dict(state["optimizer"])
            torch.set_rng_state(state["rng"])
        except (RuntimeError, KeyError, ValueError, TypeError) as e:
            raise CheckpointError(
                str(ck_path), f"does not fit the model ({str(e).splitlines()[0][:160]})"
            ) from None
        epoch, step, start_batch = (
            int(state["epoch"]),
            int(state["step"]),
            int(state["step_in_epoch"]),
        )
        sums = dict(state["sums"])
        history = list(state["history"])
        best = float(state["best"])
    resumed_from = step if state is not None else None

    info = {
        "train": cfg.to_dict(),
        "data": {
            "directory": str(Path(data_dir).resolve()),
            **fingerprint,
            "counts": train_ds.manifest.get("counts"),
            # shapes and meta (frame) of the samples: what a closed-loop planner rebuilds
            "schema": {k: v["shape"] for k, v in train_ds.manifest["schema"].items()},
            "meta": train_ds.manifest.get("meta", {}),
        },
        "game": summary,
        "parameters": count_parameters(model),
        "torch": torch.__version__,
    }
    _atomic_text(out / "config.json", json.dumps(info, indent=1) + "\n")

    def snapshot(ep: int, st: int, in_epoch: int) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "config": cfg.to_dict(),
            "game": summary,
            "data": fingerprint,
            "model": model.state_dict(),
            "optimizer": opt.state_dict(),
            "rng": torch.get_rng_state(),
            "epoch": ep,
            "step": st,
            "step_in_epoch": in_epoch,
            "sums": dict(sums),
            "history": history,
            "best": best,
        }

    writer = _tensorboard(out / "tb", step) if epoch < cfg.epochs else None
    weights = cfg.loss_weights
    step_losses: list[tuple[int, float]] = []
    nb = train_ds.num_batches(cfg.batch_size)
    bar = None
    try:
        while epoch < cfg.epochs:
            if progress:
                from tqdm import tqdm

                bar = tqdm(
                    total=nb,
                    initial=start_batch,
                    desc=f"{kind} epoch {epoch + 1}/{cfg.epochs}",
                    unit="batch",
                    dynamic_ncols=True,
                    leave=False,
                )
            model.train()
            t0 = time.perf_counter() - sums["seconds"]
            for b, batch in enumerate(
                train_ds.batches(
                    cfg.batch_size, shuffle=True, seed=cfg.seed, epoch=epoch, start=start_batch
                ),
                start=start_batch,
            ):
                n = int(batch["history"].shape[0])
                if n * cfg.model.modes < 2:  # BatchNorm needs two values per channel
                    continue
                with _diverged(epoch, step + 1, cfg.lr, ck_path, "the model's output"):
                    res = model(batch)
                parts = compute_loss(kind, res, batch["gt"], weights)
                loss = parts["loss"]
                if not torch.isfinite(loss):
                    raise _diverged_error(epoch, step + 1, cfg.lr, ck_path, "the loss")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                step += 1
                if not all(bool(torch.isfinite(p).all()) for p in model.parameters()):
                    raise _diverged_error(epoch, step, cfg.lr, ck_path, "the weights")
                vals = {k: v.item() for k, v in parts.items()}
                for k in ("loss", "imitation", "probability", "goal"):
                    sums[k] = sums.get(k, 0.0) + vals[k] * n
                sums["samples"] += n
                sums["seconds"] = time.perf_counter() - t0
                step_losses.append((step, vals["loss"]))
                if writer is not None:
                    for k, v in vals.items():
                        writer.add_scalar(f"train/{k}", v, step)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(
                        loss=f"{vals['loss']:.4g}",
                        rate=f"{sums['samples'] / max(sums['seconds'], 1e-9):.1f} samples/s",
                    )
                if cfg.checkpoint_steps and step % cfg.checkpoint_steps == 0 and b + 1 < nb:
                    _atomic_torch_save(snapshot(epoch, step, b + 1), ck_path)
                if on_step is not None:
                    on_step(step, vals)
            if bar is not None:
                bar.close()
                bar = None
            # ---- end of epoch: validate, record, checkpoint
            seconds = time.perf_counter() - t0
            ns = max(sums["samples"], 1)
            row = {
                "epoch": epoch + 1,
                "step": step,
                "seconds": round(seconds, 3),
                "samples_per_s": round(sums["samples"] / max(seconds, 1e-9), 3),
                "train_loss": sums["loss"] / ns,
                "train_imitation": sums["imitation"] / ns,
                "train_probability": sums["probability"] / ns,
                "train_goal": sums.get("goal", 0.0) / ns,
            }
            if val_ds is not None:
                t1 = time.perf_counter()
                with _diverged(epoch, step, cfg.lr, ck_path, "the validation output"):
                    vm = evaluate_model(model, val_ds, batch_size=cfg.eval_batch_size)
                row.update({f"val_{k}": vm[k] for k in METRICS})
                row["val_seconds"] = round(time.perf_counter() - t1, 3)
            else:
                row.update({f"val_{k}": math.nan for k in METRICS})
            history.append(row)
            epoch += 1
            start_batch = 0
            sums = _zero_sums()
            score = row["val_minSADE"]
            improved = val_ds is None or score < best
            if improved and val_ds is not None:
                best = score
            snap = snapshot(epoch, step, 0)
            if improved:
                _atomic_torch_save(
                    {
                        k: snap[k]
                        for k in ("format", "config", "game", "data", "model", "epoch", "step")
                    }
                    | {"metrics": row},
                    best_path,
                )
            _write_csv(out / "metrics.csv", history)
            plot_history(history, out / "loss.png", title=f"{kind}: {out.name}")
            # the checkpoint last: it commits the epoch, so a failed write of any file
            # (a full disk) leaves the previous epoch's checkpoint, and a rerun redoes the
            # epoch and writes every file again
            _atomic_torch_save(snap, ck_path)
            if writer is not None:
                for k, v in row.items():
                    if k.startswith(("val_", "train_")) and math.isfinite(v):
                        writer.add_scalar(f"epoch/{k}", v, step)
                writer.flush()
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
        train_ds.close()
        if val_ds is not None:
            val_ds.close()
    return TrainResult(
        str(out), epoch, step, history, time.perf_counter() - t_call, resumed_from, step_losses
    )
