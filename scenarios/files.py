"""Atomic output files: a result or figure is either written whole or not at all.

:func:`write_atomic` writes into a temporary file beside the target, flushes it to disk
and renames it into place, so a full disk, a path through an existing file or an
interrupted run never leaves a partial file (and never destroys an older file of the same
name). Every failure is one :class:`epo_casadi.errors.OutputError` naming the path, which
the command line prints in one line with exit status 2.
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from epo_casadi.errors import OutputError

__all__ = ["write_atomic", "ensure_dir"]

_UMASK = os.umask(0)  # read once at import: new files get the usual mode, not 0600
os.umask(_UMASK)


def _reason(e: OSError, path: Path) -> str:
    if e.errno in (errno.ENOTDIR, errno.EEXIST) or isinstance(e, (NotADirectoryError,)):
        for parent in path.parents:
            if parent.exists() and not parent.is_dir():
                return f"{parent} is a file, not a folder"
    if e.errno == errno.ENOSPC:
        return "no space left on the device"
    if isinstance(e, IsADirectoryError) or path.is_dir():
        return "it is a folder"
    return e.strerror or type(e).__name__


def ensure_dir(path: str | os.PathLike) -> Path:
    """Create the folder ``path`` (and its parents); :class:`OutputError` if that fails."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(path, _reason(e, path)) from None
    return path


def write_atomic(path: str | os.PathLike, data: bytes | str | Callable[[BinaryIO], None]) -> Path:
    """Write ``data`` (bytes, text as UTF-8, or a function writing to a binary file) to
    ``path`` atomically; create missing parent folders. Returns ``path``."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(path, "it is a folder")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as e:
        raise OutputError(path, _reason(e, path)) from None
    try:
        with os.fdopen(fd, "wb") as f:
            if callable(data):
                data(f)
            else:
                f.write(data.encode("utf-8") if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(e, OSError):
            raise OutputError(path, _reason(e, path)) from None
        raise
    return path
