"""Opt-in generated C for small CasADi functions, compiled once and cached on disk.

:func:`compile_functions` writes the C code of a few :class:`casadi.Function` objects
into one file (``casadi.CodeGenerator``), compiles it into a shared library with the
system C compiler (a ``subprocess`` call) and loads every function back with
``casadi.external``. The loaded functions have the same names, inputs, outputs and
sparsity as the originals and work with :class:`solvers.batch.BatchFunction` (``map``
with threads) like interpreted ones.

Cache
    The library is stored as ``<name>_<hash>.so`` in ``directory``, else
    ``$EPO_CACHE_DIR``, else ``~/.cache/epo``. ``hash`` covers the CasADi version, the
    compiler's name, the flags and every function's serialization, so a changed game,
    feature or compiler gives a new file and an unchanged one is loaded without compiling.
    Files are written under a temporary name and renamed, so two processes compiling the
    same functions at once do not read a half-written library.

    Every library (and kernel object file) is used only after a check: when it is built,
    the SHA-256 digest of its file name and bytes is written beside it
    (``NAME.so.sha256``), and before a library is loaded or linked its bytes must match
    that digest (hashed once per process and file). A library without a digest or with
    another one (a truncated file, a file put there by something else, a copy of another
    cached library) is never loaded: it is compiled again and replaced. Builds of one
    library hold a lock (``.NAME.so.lock``), so a checked library is never replaced by a
    concurrent build. The cache folder must belong to the current user and not be
    writable by group or others (:class:`CacheError` otherwise; ``chmod go-w FOLDER``);
    a folder created here is private (mode 700).

:func:`compile_libraries` does the same for several libraries at once, running their
compilers in parallel (one process per library, at most one per usable core): the fused
Gauss-Newton backend compiles its linearization, solve and energy that way.

:func:`compile_kernel` compiles hand-written C with CasADi's external-function interface
(``-O3``, whatever ``optimize`` says) into an object file, linked into the libraries of
the functions that call it (``objects``), and a shared library for ``casadi.external``:
loops over dense blocks that the compiler vectorizes, where unrolled SX code would run
one scalar instruction after the other (the fused backend's Riccati elimination).

Keep what you compile small: residuals, partial Jacobians, stage functions. Compile time
grows faster than linearly with the size of the expression graph: a symbolic dense ``J'J``
of a 160-control game took minutes, the structured backend's functions
(:mod:`solvers.structured`) take a few seconds for 2 agents (``-O1``) and about half a
minute for 12 (``-O0``). ``optimize`` picks the gcc level; ``"auto"`` uses ``-O1`` up to
:data:`AUTO_O1_LIMIT` instructions and ``-O0`` above. ``-O0`` code of a very long function
is about as fast as CasADi's interpreter, so for large games compiling buys little.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import stat
import subprocess
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX
    fcntl = None

import casadi as ca
import numpy as np

from epo_casadi.errors import EpoError, SpecError

__all__ = [
    "AUTO_O1_LIMIT",
    "KERNEL_FLAGS",
    "BufferCall",
    "CacheError",
    "CompilerError",
    "cache_dir",
    "compile_functions",
    "compile_kernel",
    "compile_libraries",
    "find_compiler",
]

#: ``optimize="auto"`` compiles with ``-O1`` up to this many CasADi instructions (summed
#: over the functions), ``-O0`` above (gcc's optimizer is superlinear on long functions).
AUTO_O1_LIMIT = 60_000


class CompilerError(EpoError, RuntimeError):
    """No C compiler was found, or compiling the generated code failed."""


class CacheError(EpoError):
    """The cache folder cannot be trusted: not the current user's, or writable by others
    (whoever can write there could put code into every process that loads from it)."""

    def __init__(self, folder, reason: str):
        self.folder = str(folder)
        self.reason = reason
        super().__init__(
            f"{folder}: refusing the compiled-code cache folder: {reason}; run "
            f"'chmod go-w {folder}' or set EPO_CACHE_DIR to a folder of your own"
        )


def cache_dir(directory: str | os.PathLike | None = None) -> Path:
    """The cache folder: ``directory``, else ``$EPO_CACHE_DIR``, else ``~/.cache/epo``.

    Created (mode 700) when missing. Raises :class:`CacheError` when the folder belongs
    to another user or is writable by group or others.
    """
    if directory is not None:
        d = Path(directory)
    elif os.environ.get("EPO_CACHE_DIR"):
        d = Path(os.environ["EPO_CACHE_DIR"])
    else:
        d = Path.home() / ".cache" / "epo"
    if not d.is_dir():
        d.parent.mkdir(parents=True, exist_ok=True)
        d.mkdir(mode=0o700, exist_ok=True)  # FileExistsError if it is a file
    _check_folder(d)
    return d


def _check_folder(d: Path) -> None:
    st = d.stat()
    if hasattr(os, "geteuid") and st.st_uid != os.geteuid():
        raise CacheError(d, f"it belongs to user id {st.st_uid}, not to you ({os.geteuid()})")
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise CacheError(
            d, f"it is writable by group or others (mode {stat.S_IMODE(st.st_mode):o})"
        )


# ---- digests of cached files ----------------------------------------------------------
_DIGEST_SUFFIX = ".sha256"
_verified: dict[str, tuple] = {}  # path -> (dev, inode, size, mtime) when its digest matched
_verified_lock = threading.Lock()


def _sha256(path: Path, name: str) -> str:
    """Digest of the file's name (its cache key) and bytes: a copy of another cached
    library, digest file included, does not match under this name."""
    h = hashlib.sha256(name.encode() + b"\0")
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _digest_path(path: Path) -> Path:
    return path.with_name(path.name + _DIGEST_SUFFIX)


def _stat_key(path: Path) -> tuple | None:
    try:
        st = path.stat()
    except OSError:
        return None
    if not stat.S_ISREG(st.st_mode):
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def _is_intact(path: Path) -> bool:
    """Whether ``path`` exists and its bytes match the digest recorded beside it."""
    key = _stat_key(path)
    if key is None:
        return False
    with _verified_lock:
        if _verified.get(str(path)) == key:
            return True
    try:
        with open(_digest_path(path), "rb") as fh:
            recorded = fh.read(256).split()
        if not recorded or _sha256(path, path.name) != recorded[0].decode("ascii", "replace"):
            return False
    except OSError:
        return False
    if _stat_key(path) != key:  # changed while it was hashed
        return False
    with _verified_lock:
        _verified[str(path)] = key
    return True


def _install(built: str | os.PathLike, target: Path) -> None:
    """Move the freshly built file ``built`` to ``target`` and record its digest (both
    renamed into place, so readers see whole files; a reader between the two renames
    finds a mismatch and builds again)."""
    digest = _sha256(Path(built), target.name)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}_")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(f"{digest}  {target.name}\n")
        os.replace(built, target)  # atomic: readers see the old or the whole library
        os.replace(tmp, _digest_path(target))
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    key = _stat_key(target)
    if key is not None:
        with _verified_lock:
            _verified[str(target)] = key


@contextlib.contextmanager
def _building(paths: Sequence[Path]):
    """Exclusive locks (``flock`` on ``.NAME.lock`` beside each file, taken in sorted
    order) while files are checked and built: of two processes missing the same library,
    the second waits and then finds it built, so a checked library is never replaced."""
    with contextlib.ExitStack() as stack:
        if fcntl is not None:
            for p in sorted({str(p) for p in paths}):
                lock = Path(p).with_name(f".{Path(p).name}.lock")
                fh = stack.enter_context(open(lock, "a"))  # noqa: SIM115
                fcntl.flock(fh, fcntl.LOCK_EX)
        yield


def _load(names: Sequence[str], lib: Path) -> dict[str, ca.Function]:
    """The functions of a verified library (a :class:`CompilerError` if it is not)."""
    if not _is_intact(lib):  # pragma: no cover - replaced between the build and the load
        raise CompilerError(f"{lib} changed after it was built and checked; run again")
    return {n: ca.external(n, str(lib)) for n in names}


def find_compiler() -> str:
    """Path of the C compiler: ``$CC``, else the first of ``gcc``, ``cc``, ``clang`` found.

    Raises :class:`CompilerError` when there is none.
    """
    candidates = [os.environ["CC"]] if os.environ.get("CC") else ["gcc", "cc", "clang"]
    for c in candidates:
        path = shutil.which(c)
        if path:
            return path
    raise CompilerError(
        f"no C compiler found (looked for {', '.join(candidates)}); install gcc or set CC, "
        "or use the interpreted functions (compiled=False)"
    )


def _flags(funcs: Sequence[ca.Function], optimize: str) -> list[str]:
    if optimize == "auto":
        n = sum(f.n_instructions() for f in funcs)
        optimize = "-O1" if n <= AUTO_O1_LIMIT else "-O0"
    # a level, then optionally code-generation flags ("-O3 -march=native -ffp-contract=off":
    # the caller then keys the library's name by the CPU, solvers.fast_ilq does)
    level, *extra = optimize.split() or [""]
    if level not in ("-O0", "-O1", "-O2", "-O3", "-Os") or not all(
        f[:2] in ("-f", "-m") for f in extra
    ):
        raise SpecError(
            "optimize",
            "expected 'auto', '-O0', '-O1', '-O2', '-O3' or '-Os' (then optionally -f/-m "
            f"flags), got {optimize!r}",
        )
    return [level, *extra, "-fPIC", "-shared"]


def compile_functions(
    funcs: list[ca.Function],
    name: str,
    directory: str | os.PathLike | None = None,
    *,
    optimize: str = "auto",
    objects: Sequence[str | os.PathLike] = (),
) -> dict[str, ca.Function]:
    """Generate C for ``funcs``, compile (or reuse the cached library) and load them.

    ``name`` is the library's base name (a C identifier); the result maps each function's
    name to its compiled ``casadi.external`` counterpart. Function names must be unique.
    ``objects``: object files linked into the library (from :func:`compile_kernel`: the
    hand-written C that ``funcs`` call through ``casadi.external``). See the module
    docstring for the cache and ``optimize``.
    """
    return compile_libraries([(funcs, name, objects)], directory, optimize=optimize)[0]


def compile_libraries(
    libraries: Sequence[tuple],
    directory: str | os.PathLike | None = None,
    *,
    optimize: str = "auto",
) -> list[dict[str, ca.Function]]:
    """:func:`compile_functions` for several libraries ``(funcs, name)`` at once: the C code
    is generated one library after the other, the compilers of the libraries missing from
    the cache run in parallel (one process each, at most as many as usable cores), then
    every library is loaded. An entry may be ``(funcs, name, objects)`` (see
    :func:`compile_functions`). Returns one name-to-function dict per library, in order."""
    plans = [
        _plan(list(lb[0]), lb[1], directory, optimize, tuple(lb[2]) if len(lb) > 2 else ())
        for lb in libraries
    ]
    todo = [pl for pl in plans if not _is_intact(pl[-1])]  # missing, or not what was built
    if todo:
        with _building([pl[-1] for pl in todo]), contextlib.ExitStack() as stack:
            todo = [pl for pl in todo if not _is_intact(pl[-1])]  # built by another process
            jobs = [_generate(*pl, stack) for pl in todo]
            procs: list[subprocess.Popen] = []
            try:
                for cmd, _, _ in jobs:
                    while sum(p.poll() is None for p in procs) >= _usable_cores():
                        next(p for p in procs if p.poll() is None).wait()
                    err = stack.enter_context(open(cmd[-2] + ".err", "w+"))  # noqa: SIM115
                    procs.append(subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err))
                for (cmd, out, lib), proc in zip(jobs, procs, strict=True):
                    proc.wait()
                    if proc.returncode != 0:
                        err = Path(cmd[-2] + ".err").read_text(errors="replace")
                        raise CompilerError(
                            f"compiling {Path(cmd[-2]).name} failed ({' '.join(cmd)}):\n"
                            f"{err[-2000:]}"
                        )
                    _install(out, lib)
            finally:
                for p in procs:
                    if p.poll() is None:
                        p.kill()
                        p.wait()
    return [_load(pl[1], pl[-1]) for pl in plans]


#: Flags of :func:`compile_kernel`: loops of hand-written C vectorize from ``-O3`` on (the
#: instruction set is the compiler's default, so a shared cache works on any x86-64 machine).
KERNEL_FLAGS = ("-O3", "-fno-math-errno", "-fPIC")


def compile_kernel(
    source: str, name: str, directory: str | os.PathLike | None = None
) -> tuple[Path, Path]:
    """Compile hand-written C ``source`` (cached): ``(shared library, object file)``.

    The shared library is for ``casadi.external`` (a ``casadi.Function`` with the
    source's name, called by other functions' graphs); the object file is linked into the
    libraries of the functions that call it (``objects`` of :func:`compile_functions`),
    whose generated C declares and calls the same symbol. Both are compiled with
    :data:`KERNEL_FLAGS` whatever the ``optimize`` of the generated code, and cached as
    ``<name>_<hash>.so`` / ``.o`` (hash of the compiler, flags and source), each with its
    digest (see the module docstring); a pair that does not match its digests is
    compiled again.
    """
    if not name.isidentifier():
        raise SpecError("name", f"expected a C identifier, got {name!r}")
    cc = find_compiler()
    h = hashlib.sha256()
    for part in (os.path.basename(cc), " ".join(KERNEL_FLAGS), source):
        h.update(part.encode())
        h.update(b"\0")
    folder = cache_dir(directory)
    stem = folder / f"{name}_{h.hexdigest()[:20]}"
    so, obj = stem.with_suffix(".so"), stem.with_suffix(".o")
    if _is_intact(so) and _is_intact(obj):
        return so, obj
    with _building([so]), tempfile.TemporaryDirectory(dir=folder, prefix=f".{name}_") as tmp:
        if _is_intact(so) and _is_intact(obj):  # built by another process meanwhile
            return so, obj
        src = os.path.join(tmp, f"{name}.c")
        Path(src).write_text(source)
        t_obj, t_so = os.path.join(tmp, f"{name}.o"), os.path.join(tmp, f"{name}.so")
        for cmd in (
            [cc, *KERNEL_FLAGS, "-c", "-o", t_obj, src],
            [cc, "-shared", "-o", t_so, t_obj, "-lm"],
        ):
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                raise CompilerError(
                    f"compiling {name}.c failed ({' '.join(cmd)}):\n{done.stderr[-2000:]}"
                )
        _install(t_obj, obj)
        _install(t_so, so)
    return so, obj


def _usable_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


def _plan(funcs, name, directory, optimize, objects=()):
    """Checks, flags and the cache path of one library: ``(funcs, names, name, cc, flags,
    objects, lib)``."""
    if not funcs:
        raise SpecError("funcs", "expected at least one casadi.Function")
    for f in funcs:
        if not isinstance(f, ca.Function):
            raise SpecError("funcs", f"expected casadi.Function objects, got {type(f).__name__}")
    names = [f.name() for f in funcs]
    if len(set(names)) != len(names):
        raise SpecError("funcs", f"function names must be unique, got {names}")
    if not name.isidentifier():
        raise SpecError("name", f"expected a C identifier, got {name!r}")
    objects = [str(o) for o in objects]
    for o in objects:
        if not Path(o).is_file():
            raise SpecError("objects", f"expected compiled object files, {o!r} does not exist")
    cc = find_compiler()
    flags = _flags(funcs, optimize)
    h = hashlib.sha256()
    # objects from compile_kernel are named by the hash of their source and flags
    names_o = [os.path.basename(o) for o in objects]
    for part in (ca.__version__, os.path.basename(cc), " ".join(flags), *names_o):
        h.update(part.encode())
        h.update(b"\0")
    for f in funcs:
        h.update(f.serialize().encode())
        h.update(b"\0")
    folder = cache_dir(directory)
    lib = folder / f"{name}_{h.hexdigest()[:20]}.so"
    return funcs, names, name, cc, flags, objects, lib


def _generate(funcs, names, name, cc, flags, objects, lib: Path, stack: contextlib.ExitStack):
    """Write the C file of one library into a temporary folder next to ``lib`` (removed
    when ``stack`` closes); returns the compiler command, its output file and ``lib``."""
    tmp = stack.enter_context(tempfile.TemporaryDirectory(dir=lib.parent, prefix=f".{name}_"))
    cg = ca.CodeGenerator(f"{name}.c", {"with_header": False})
    for f in funcs:
        cg.add(f)
    cg.generate(tmp + os.sep)
    src = os.path.join(tmp, f"{name}.c")
    out = os.path.join(tmp, f"{name}.so")
    return [cc, *flags, "-o", out, *objects, src, "-lm"], out, lib


class BufferCall:
    """A casadi.Function called through its buffer interface on preallocated numpy arrays."""

    def __init__(self, f: ca.Function):
        self.f = f
        self.buf, self.ev = f.buffer()
        self.outs = [np.empty(f.nnz_out(i)) for i in range(f.n_out())]
        for i, o in enumerate(self.outs):
            self.buf.set_res(i, memoryview(o))
        self._ins = [None] * f.n_in()
        self._sizes = [f.nnz_in(i) for i in range(f.n_in())]

    def __call__(self, *args):
        for i, a in enumerate(args):
            a = np.ascontiguousarray(a, dtype=np.float64).reshape(-1)
            if a.size != self._sizes[i]:
                raise ValueError(
                    f"{self.f.name()}: input {i} needs {self._sizes[i]} numbers, got {a.size}"
                )
            self._ins[i] = a  # keep alive while CasADi reads it
            self.buf.set_arg(i, memoryview(a))
        self.ev()
        return self.outs
