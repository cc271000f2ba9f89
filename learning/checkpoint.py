"""Checkpoint files of a training run: the format, writing, verified reading.

A checkpoint (``checkpoint.pt``, ``best.pt`` of a run directory, :mod:`learning.train`)
is one header line, :data:`CHECKSUM_MAGIC` followed by the 64 hex digits of the sha256 of
the payload and ``b"\\n"``, then the ``torch.save`` bytes of a dict of tensors, numbers,
strings, lists and dicts (format :data:`CHECKPOINT_FORMAT`: ``config``, ``game``,
``data``, ``model``, ``epoch``, ... see :func:`learning.train.train`). It is written
atomically (:func:`save_checkpoint`, :func:`scenarios.files.write_atomic`) and read with
``torch.load(weights_only=True)`` (:func:`load_checkpoint`): no class is pickled by its
module path, so a saved run does not depend on where the toolkit's classes live. A file
written before checksums existed (a plain ``torch.save`` zip) loads unverified with an
:class:`UncheckedCheckpointWarning`; a damaged or changed file is a
:class:`CheckpointError` naming it.
"""

from __future__ import annotations

import hashlib
import io
import os
import warnings
from pathlib import Path

import torch

from epo_casadi.errors import EpoError, SpecError
from scenarios.files import write_atomic

from .data import game_summary
from .models import EXECUTION_SETTINGS

__all__ = [
    "CHECKPOINT_FORMAT",
    "CHECKSUM_MAGIC",
    "RESUMABLE_CHANGES",
    "CheckpointError",
    "UncheckedCheckpointWarning",
    "check_game",
    "checkpoint_path",
    "comparable_settings",
    "load_checkpoint",
    "save_checkpoint",
    "setting_diff",
]

CHECKPOINT_FORMAT = 1
#: first bytes of a checkpoint file; 64 hex digits of the payload's sha256 and b"\n" follow
CHECKSUM_MAGIC = b"EPO-CHECKPOINT sha256="
_HEADER = len(CHECKSUM_MAGIC) + 65
_ZIP_MAGIC = b"PK\x03\x04"  # a plain torch.save file (checkpoints before checksums)
#: training settings that may change when a run is resumed
RESUMABLE_CHANGES = ("epochs", "checkpoint_steps", "eval_batch_size")


class CheckpointError(EpoError):
    """A run directory or checkpoint is missing, unreadable or belongs to another setup."""

    def __init__(self, where: str, message: str):
        self.where, self.message = where, message
        super().__init__(f"{where}: {message}")


class UncheckedCheckpointWarning(UserWarning):
    """A checkpoint written before checksums existed was loaded without verification."""


def save_checkpoint(obj, path: Path) -> None:
    """``torch.save`` bytes behind a sha256 header line, written atomically
    (:func:`scenarios.files.write_atomic`: a full disk leaves the previous file intact)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    payload = buf.getvalue()
    header = CHECKSUM_MAGIC + hashlib.sha256(payload).hexdigest().encode() + b"\n"
    write_atomic(path, lambda f: (f.write(header), f.write(payload)))


def load_checkpoint(path: str | os.PathLike) -> dict:
    """A checkpoint written by :func:`learning.train.train`; :class:`CheckpointError` if
    missing or corrupt."""
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


def checkpoint_path(run_dir: Path, which: str) -> Path:
    """The checkpoint of run ``run_dir`` to load: ``best.pt`` when ``which="best"`` and it
    exists (a run with no validation split yet has none), else ``checkpoint.pt``; a missing
    run or file is a :class:`CheckpointError`."""
    if not run_dir.is_dir():
        raise CheckpointError(str(run_dir), "no such run directory")
    if which not in ("best", "last"):
        raise SpecError("checkpoint", f"expected 'best' or 'last', got {which!r}")
    best = run_dir / "best.pt"
    path = best if which == "best" and best.exists() else run_dir / "checkpoint.pt"
    if not path.exists():
        raise CheckpointError(
            str(path), "missing: not a training run directory (or it never finished an epoch)"
        )
    return path


def check_game(saved: dict, game, where: str) -> None:
    """Refuse a model trained on a game that differs from ``game`` (agents, horizon, params)."""
    now = game_summary(game)
    for k, v in saved.items():
        if now.get(k) != v:
            raise CheckpointError(
                f"{where}.game.{k}",
                f"the run was trained on a game with {k} {v!r}, the dataset's game has {now.get(k)!r}",
            )


def comparable_settings(d: dict) -> dict:
    """A config dict without the model's execution settings (the layer's backend and
    compilation: the same steps to rounding), so a run may resume with others."""
    if isinstance(d.get("model"), dict):
        d = {**d, "model": {k: v for k, v in d["model"].items() if k not in EXECUTION_SETTINGS}}
    return d


def setting_diff(saved: dict, now: dict) -> str | None:
    """First training setting (``model.kind``, ``seed``, ...) in which two configs differ."""
    saved, now = comparable_settings(saved), comparable_settings(now)
    for k in now:
        if k in RESUMABLE_CHANGES or saved.get(k) == now[k]:
            continue
        if k == "model" and isinstance(saved.get(k), dict):
            sub = [j for j in now[k] if saved[k].get(j) != now[k][j]]
            if sub:
                return f"model.{sub[0]} ({saved[k].get(sub[0])!r}, run: {now[k][sub[0]]!r})"
        return f"{k} ({saved.get(k)!r}, run: {now[k]!r})"
    return None
