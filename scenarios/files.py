"""Output files and folders: atomic writes, one writer per folder, one recipe per folder.

:func:`write_atomic` writes into a temporary file beside the target, flushes it to disk
and renames it into place, so a full disk, a path through an existing file or an
interrupted run never leaves a partial file (and never destroys an older file of the same
name). Every failure is one :class:`epo_casadi.errors.OutputError` naming the path, which
the command line prints in one line with exit status 2.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import signal
import tempfile
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, BinaryIO

from epo_casadi.errors import EpoError, OutputError, SpecError, short_repr

__all__ = [
    "write_atomic",
    "ensure_dir",
    "check_output_dir",
    "output_lock",
    "claim_output",
    "recipe_difference",
    "sigterm_as_interrupt",
    "usable_cores",
    "BusyError",
    "RECIPE",
    "check_input_file",
    "check_output_file",
    "NAME_MAX",
    "MAX_INPUT_BYTES",
]

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


#: longest file or folder name (bytes) of the usual file systems (Linux NAME_MAX)
NAME_MAX = 255


def check_output_file(path: str | os.PathLike | None, option: str) -> Path | None:
    """Refuse, before any work, an output file that cannot be written (``None`` passes).

    One :class:`OutputError` for a folder at ``path``, a path through a file or a dangling
    link, a name longer than :data:`NAME_MAX` bytes, or a folder that cannot be written
    (read-only, no permission); the file itself is written later with
    :func:`write_atomic`, which reports anything else (a full disk).
    """
    if path is None:
        return None
    path = Path(path)
    for part in path.parts:  # first: stat() of a name too long fails
        n = len(os.fsencode(part))
        if n > NAME_MAX:
            raise OutputError(
                path, f"a name of {n} bytes is longer than the {NAME_MAX} file systems take"
            )
    if path.is_dir():
        raise OutputError(path, f"{option} names a folder, expected a file")
    near = path.parent  # the nearest folder that exists: the one to create or write in
    while not (near.exists() or near.is_symlink()) and near != near.parent:
        near = near.parent
    if not near.is_dir():  # a path through a file (or a dangling link)
        what = "a dangling link" if not near.exists() else "a file"
        raise OutputError(path, f"{near} is {what}, not a folder")
    if not os.access(near, os.W_OK | os.X_OK):
        raise OutputError(path, f"the folder {near} cannot be written (read-only or no permission)")
    return path


def write_atomic(path: str | os.PathLike, data: bytes | str | Callable[[BinaryIO], None]) -> Path:
    """Write ``data`` (bytes, text as UTF-8, or a function writing to a binary file) to
    ``path`` atomically; create missing parent folders. Returns ``path``."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(path, "it is a folder")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # the temporary name stays within NAME_MAX for any valid target name
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name[:100]}.", suffix=".tmp")
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


# ---- output folders: one writer at a time, one recipe per folder ----------------------------


class BusyError(EpoError):
    """An output folder is held by another running epo command (its ``.lock``)."""

    def __init__(self, path, message: str):
        self.path = str(path)
        super().__init__(f"{path}: {message}")


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def check_output_dir(path: str | os.PathLike) -> Path:
    """``path`` as a folder to create or reuse; :class:`OutputError` if it cannot be one.

    Refuses an existing file (or a dangling link) at ``path`` and a path whose nearest
    existing ancestor is a file (``--out notes.txt/run``), before anything is written.
    """
    p = Path(path)
    for a in (p, *p.parents):
        if a.exists() or a.is_symlink():
            if not a.is_dir():
                if a == p:
                    raise OutputError(p, "exists and is not a directory")
                raise OutputError(p, f"cannot create a directory here: {a} is a file")
            break
    return p


@contextlib.contextmanager
def output_lock(directory: str | os.PathLike, what: str = "epo run"):
    """Hold an exclusive lock on ``directory/.lock`` within the block (the folder is created).

    A second process asking for the same folder gets :class:`BusyError` at once ("another
    ``what`` is writing to this directory"), so two runs never mix or overwrite each other's
    files. The lock is the kernel's (``flock``): it goes with the process, also on SIGKILL.
    """
    d = ensure_dir(check_output_dir(directory))
    try:
        fd = os.open(d / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise OutputError(d / ".lock", _reason(e, d / ".lock")) from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise BusyError(d, f"another {what} is writing to this directory") from None
        yield d
    finally:
        os.close(fd)


def _canonical(value: Any) -> Any:
    return json.loads(json.dumps(value, default=str))


def recipe_difference(old: Mapping, new: Mapping) -> str | None:
    """``None`` when two recipes are equal (as JSON), else the differing fields in one text:
    ``"field 'seed' (0 there, 1 asked); field 'duration' ..."``."""
    a, b = _canonical(dict(old)), _canonical(dict(new))
    if a == b:
        return None
    diff = [f for f in {**a, **b} if a.get(f) != b.get(f)]
    return "; ".join(f"field {f!r} ({a.get(f)!r} there, {b.get(f)!r} asked)" for f in diff)


RECIPE = "recipe.json"


@contextlib.contextmanager
def claim_output(
    directory: str | os.PathLike,
    kind: str,
    recipe: Mapping,
    *,
    what: str | None = None,
    foreign_ok: Callable[[Path], bool] | None = None,
):
    """Own ``directory`` for one job: :func:`output_lock`, then ``directory/recipe.json``.

    A new folder gets ``{"kind": kind, "recipe": recipe}`` recorded (atomically) before any
    work; a folder that already records the same kind and recipe is resumed; one that
    records another is refused with :class:`SpecError` naming every differing field, and
    so is a non-empty folder without ``recipe.json`` (files of another job, or of an older
    layout), unless ``foreign_ok(path)`` accepts each of its entries. Yields the folder.
    """
    what = what or f"epo {kind}"
    with output_lock(directory, what) as d:
        path = d / RECIPE
        new = {"kind": kind, "recipe": _canonical(dict(recipe))}
        if path.exists():
            try:
                old = json.loads(path.read_text())
            except (OSError, ValueError) as e:
                raise SpecError(str(path), f"unreadable ({type(e).__name__}: {e})") from None
            if not isinstance(old, dict) or old.get("kind") != kind:
                got = old.get("kind") if isinstance(old, dict) else old
                raise SpecError(
                    str(path),
                    f"records a {short_repr(got)} job, not {kind}; use another output folder",
                )
            diff = recipe_difference(old.get("recipe") or {}, new["recipe"])
            if diff is not None:
                raise SpecError(
                    str(path),
                    f"records a {kind} job with another recipe: {diff}; use another output "
                    "folder, or the same options to resume",
                )
        else:
            others = [
                x for x in d.iterdir() if x.name != ".lock" and not (foreign_ok and foreign_ok(x))
            ]
            if others:
                raise SpecError(
                    str(d),
                    f"is not empty and records no {RECIPE} (it holds {others[0].name!r}); "
                    "choose a new or empty folder",
                )
            write_atomic(path, json.dumps(new, indent=2, sort_keys=True) + "\n")
        yield d


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Within the block, SIGTERM raises :class:`KeyboardInterrupt` like SIGINT (main thread only).

    Commands that write results use it so that ``kill PID`` shuts down as Ctrl-C does:
    finished shards and checkpoints are kept, worker processes are stopped and the command
    exits with status 130.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


#: the largest input file read whole into memory by default (game files, manifests, configs)
MAX_INPUT_BYTES = 64 * 2**20


def check_input_file(
    path: str | os.PathLike, field: str = "file", max_bytes: int | None = MAX_INPUT_BYTES
) -> Path:
    """``path`` if it is a regular file of at most ``max_bytes`` bytes, else :class:`SpecError`.

    The one check in front of every reader of a user's file: a missing path, a folder, a
    named pipe or a device (``/dev/zero`` would be read forever, a pipe blocks) and a file too
    large to read whole are refused in one line naming ``field`` and the path.
    """
    p = Path(path)
    name = "it" if field == str(p) else str(p)  # the field may be the path itself
    try:
        st = p.stat()
    except FileNotFoundError:
        why = "is a dangling link" if p.is_symlink() else "does not exist"
        raise SpecError(field, f"{name} {why}") from None
    except OSError as e:
        raise SpecError(field, f"{name}: {e.strerror or type(e).__name__}") from None
    import stat as _stat

    if _stat.S_ISDIR(st.st_mode):
        raise SpecError(field, f"{name} is a folder, expected a file")
    if not _stat.S_ISREG(st.st_mode):
        raise SpecError(field, f"{name} is not a regular file (a pipe, socket or device)")
    if max_bytes is not None and st.st_size > max_bytes:
        raise SpecError(
            field, f"{name} has {st.st_size:,} bytes, over the limit of {max_bytes:,} for this file"
        )
    return p
