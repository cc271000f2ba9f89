"""Extension API: user features, pair features and dynamics, by name or by ``module:Class``.

A user extends the toolkit by subclassing in their own module, never by editing the
package:

- an own feature: a frozen dataclass subclass of :class:`epo_casadi.features.Feature`
  with a ``kind`` (its name), ``steps(K)`` and ``residual(ctx)``; it may declare its own
  parameter blocks with ``params()`` (:class:`epo_casadi.features.ParamSpec`);
- a pair feature: a subclass of :class:`epo_casadi.features.PairFeature` (``kind``,
  ``steps``, ``residual(a, b)``, symmetric in ``a, b``);
- a dynamics model: a subclass of :class:`epo_casadi.dynamics.Dynamics` with a ``name``,
  ``state_names``, ``control_names`` and ``step(x, u, dt)`` (plus the semantic quantities
  the features it is used with read: ``position``, ``speed``, ...).

Instances of such classes are accepted wherever a built-in one is (``AgentSpec``,
``GameSpec``, every solver, the layer). To name a class in a game file or a mapping
(``{"type": ..., options}``) either register it under a short name::

    from epo_casadi import register_feature
    register_feature("lane_keeping", LaneKeeping)      # or register_feature(LaneKeeping)

or write its import path, ``type: my_package.lanes:LaneKeeping``. A file (or any mapping
given to :meth:`Registry.resolve`) may only import a module the user allowed: one named
with ``--allow-import MODULE`` (``epo solve``, ``inspect``, ``export``, ``compare``), in
the environment variable :data:`ALLOW_ENV` (``EPO_ALLOW_IMPORT=my_package,other``) or by
:func:`allow_imports` in Python (``with allow_imports("my_package"): load_game(...)``);
allowing a package allows its submodules. Any other ``module:Class`` is refused before
anything is imported, so a game file from elsewhere runs no code. Registered names and
built-ins need no allowance, and neither does ``register_feature("module:Class")`` (the
caller's own code). A refused or failed import (whatever the module raises, ``SystemExit``
included; not ``KeyboardInterrupt``) or an object of the wrong kind is one
:class:`~epo_casadi.errors.SpecError` that names the field. A name of a built-in is
refused unless ``replace=True``.

When a game is written back (:func:`scenarios.gamefile.dump_game`, ``to_dict``) a class is
named by its registered name, or else by its ``module:Class`` path, so the file loads
again wherever that module can be imported.

The tables live in :data:`FEATURES`, :data:`PAIR_FEATURES` and :data:`DYNAMICS`; the
modules that define the base classes bind them at import (this module imports nothing
else of the package, so every arrow points one way: ``dynamics``/``features`` ->
``registry``).
"""

from __future__ import annotations

import contextlib
import importlib
import os
import re
import threading
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import fields, is_dataclass
from typing import Any

from .errors import SpecError, short_repr

__all__ = [
    "Registry",
    "FEATURES",
    "PAIR_FEATURES",
    "DYNAMICS",
    "register_feature",
    "register_pair_feature",
    "register_dynamics",
    "load_class",
    "allow_imports",
    "allowed_imports",
    "import_allowed",
    "ALLOW_ENV",
    "freeze",
    "NAME_RE",
]

#: a registered name, a feature ``kind``, a dynamics ``name``, a parameter block name
NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_ENTRY_RE = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")
_MODULE_RE = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")

#: environment variable: comma-separated modules a game file may import
ALLOW_ENV = "EPO_ALLOW_IMPORT"

_allow_lock = threading.Lock()
_allowed: list[str] = []  # modules allowed by the open allow_imports() blocks (a multiset)


def _module_names(items: Iterable[Any], where: str) -> list[str]:
    """Module names from strings, each one name or several separated by commas."""
    names = []
    for item in items:
        if not isinstance(item, str):
            raise SpecError(where, f"expected module names, got {short_repr(item)}")
        for m in item.split(","):
            m = m.strip()
            if not m:
                continue
            if not _MODULE_RE.match(m):
                raise SpecError(
                    where, f"expected a module name like 'my_package.lanes', got {short_repr(m)}"
                )
            names.append(m)
    return names


@contextlib.contextmanager
def allow_imports(*modules: str, where: str = "allow_imports") -> Iterator[None]:
    """Within the block, ``module:Class`` names of these modules (and their submodules)
    may be imported by :meth:`Registry.resolve` (game files, mappings). Each argument is
    one module name or several separated by commas. Process-wide (every thread), nested
    blocks add up."""
    names = _module_names(modules, where)
    with _allow_lock:
        _allowed.extend(names)
    try:
        yield
    finally:
        with _allow_lock:
            for m in names:
                _allowed.remove(m)


def allowed_imports() -> tuple[str, ...]:
    """The modules allowed now: those of open :func:`allow_imports` blocks and of
    ``$EPO_ALLOW_IMPORT``."""
    env = _module_names([os.environ.get(ALLOW_ENV, "")], ALLOW_ENV)
    with _allow_lock:
        scoped = list(_allowed)
    return tuple(dict.fromkeys(scoped + env))


def import_allowed(module: str) -> bool:
    """Whether ``module`` is allowed (it or a package above it is in :func:`allowed_imports`)."""
    return any(module == a or module.startswith(a + ".") for a in allowed_imports())


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}".rstrip(": ")


def freeze(v: Any) -> Any:
    """Lists (from YAML/JSON) as tuples, recursively: options of frozen dataclasses stay
    hashable (games group alike agents by their dynamics and features)."""
    if isinstance(v, (list, tuple)):
        return tuple(freeze(x) for x in v)
    return v


def load_class(entry: str, where: str = "type", *, check_allowed: bool = False) -> type:
    """The object named by ``"package.module:Class"`` (imported now).

    With ``check_allowed`` a module that :func:`import_allowed` refuses is a
    :class:`SpecError` before anything is imported. Raises :class:`SpecError` at
    ``where`` with the error in one line when the module cannot be imported (whatever it
    raises, ``SystemExit`` included; ``KeyboardInterrupt`` passes) or has no such
    attribute.
    """
    if not isinstance(entry, str) or not _ENTRY_RE.match(entry):
        raise SpecError(where, f"expected 'package.module:Class', got {short_repr(entry)}")
    module, _, qual = entry.partition(":")
    if check_allowed and not import_allowed(module):
        raise SpecError(
            where,
            f"{entry!r} would import the module {module!r}, which is not allowed (a file runs "
            f"no code unless you allow it): pass --allow-import {module} or set "
            f"{ALLOW_ENV}={module} (Python: epo_casadi.registry.allow_imports({module!r}))",
        )
    try:
        obj: Any = importlib.import_module(module)
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # noqa: BLE001 - whatever user code raises is a spec error
        raise SpecError(where, f"cannot import {module!r} for {entry!r} ({_one_line(e)})") from None
    for part in qual.split("."):
        try:
            obj = getattr(obj, part)
        except KeyboardInterrupt:
            raise
        except AttributeError:
            raise SpecError(
                where, f"module {module!r} has no attribute {qual!r} (for {entry!r})"
            ) from None
        except BaseException as e:  # noqa: BLE001 - a module __getattr__ of user code
            raise SpecError(where, f"cannot read {qual!r} of {module!r} ({_one_line(e)})") from None
    return obj


class Registry:
    """Name -> class table of one kind of model (features, pair features or dynamics).

    ``what`` is how messages call the kind (``"feature"``), ``attr`` the class attribute
    holding a class's own name (``kind`` for features, ``name`` for dynamics), ``fixed``
    the dataclass fields that are no options (e.g. a dynamics model's state names).
    :meth:`bind` (by the module that defines the base class) sets the base class and the
    built-ins.
    """

    def __init__(self, what: str, attr: str, fixed: Iterable[str] = ()):
        self.what = what
        self.attr = attr
        self.fixed = frozenset(fixed)
        self.base: type | None = None
        self.table: dict[str, type] = {}
        self.builtins: frozenset[str] = frozenset()
        self._originals: dict[str, type] = {}

    # ---- set-up -------------------------------------------------------------------------
    def bind(self, base: type, builtins: Iterable[type]) -> None:
        self.base = base
        for cls in builtins:
            self.table[getattr(cls, self.attr)] = cls
        self.builtins = frozenset(self.table)
        self._originals = dict(self.table)

    def names(self) -> list[str]:
        return sorted(self.table)

    def __contains__(self, name: object) -> bool:
        return name in self.table

    # ---- checks -------------------------------------------------------------------------
    def check_class(self, cls: Any, where: str) -> type:
        """``cls`` if it is a usable subclass of the base, else :class:`SpecError`."""
        base = self.base
        assert base is not None, "registry not bound"
        if not isinstance(cls, type) or not issubclass(cls, base) or cls is base:
            got = cls.__name__ if isinstance(cls, type) else f"a {type(cls).__name__}"
            raise SpecError(
                where,
                f"expected a subclass of {base.__module__}.{base.__name__} (a {self.what}), "
                f"got {got}",
            )
        own = getattr(cls, self.attr, None)
        if not isinstance(own, str) or not NAME_RE.match(own):
            raise SpecError(
                where,
                f"{cls.__name__}.{self.attr} must name the {self.what} (letters, digits, '_'), "
                f"got {short_repr(own)}",
            )
        needed = ("step",) if self.attr == "name" else ("steps", "residual")
        missing = [m for m in needed if getattr(cls, m) is getattr(base, m)]
        if missing:
            raise SpecError(where, f"{cls.__name__} does not define {', '.join(missing)}()")
        return cls

    # ---- registration -------------------------------------------------------------------
    def register(self, name: Any, cls: Any = None, *, replace: bool = False) -> type:
        """Register ``cls`` (a class or ``"module:Class"``) under ``name``; return the class.

        ``register(cls)`` uses the class's own name (its ``kind`` / ``name``). A name of a
        built-in or of another registered class is refused unless ``replace=True``.
        """
        if cls is None:
            name, cls = None, name
        where = f"register_{self.what.replace(' ', '_')}"
        if isinstance(cls, str):
            cls = load_class(cls, where)
        cls = self.check_class(cls, where)
        name = getattr(cls, self.attr) if name is None else name
        if not isinstance(name, str) or not NAME_RE.match(name):
            raise SpecError(
                f"{where}.name", f"expected letters, digits and '_', got {short_repr(name)}"
            )
        old = self.table.get(name)
        same = old is not None and (old.__module__, old.__qualname__) == (
            cls.__module__,
            cls.__qualname__,
        )
        if old is not None and old is not cls and not replace and not same:
            which = "built-in" if name in self.builtins else "registered"
            raise SpecError(
                f"{where}.name",
                f"{name!r} is already the {which} {self.what} {old.__qualname__}; pick another "
                f"name or pass replace=True",
            )
        self.table[name] = cls
        return cls

    def unregister(self, name: str) -> None:
        """Remove a user's name; a replaced built-in gets its original class back."""
        if name in self._originals:
            if self.table.get(name) is self._originals[name]:
                raise SpecError("unregister", f"{name!r} is a built-in {self.what}")
            self.table[name] = self._originals[name]
            return
        if name not in self.table:
            raise SpecError("unregister", f"no {self.what} registered as {name!r}")
        del self.table[name]

    # ---- resolution ---------------------------------------------------------------------
    def resolve(self, type_: Any, where: str) -> type:
        """The class a ``type`` entry names: a registered name or ``"module:Class"`` of a
        module the user allowed (see :func:`allow_imports`)."""
        if isinstance(type_, str) and ":" in type_:
            return self.check_class(load_class(type_, where, check_allowed=True), where)
        if not isinstance(type_, str) or type_ not in self.table:
            raise SpecError(
                where,
                f"unknown {self.what} {short_repr(type_)}; expected one of {self.names()} "
                f"or 'package.module:Class'",
            )
        return self.table[type_]

    def type_name(self, cls: type) -> str:
        """What a file calls ``cls``: its registered name, else ``module:Class``."""
        own = getattr(cls, self.attr, None)
        if own is not None and self.table.get(own) is cls:
            return own
        for name, c in self.table.items():
            if c is cls:
                return name
        return f"{cls.__module__}:{cls.__qualname__}"

    def options(self, cls: type) -> list[str]:
        """Option names of ``cls`` (its dataclass fields less the fixed ones)."""
        if not is_dataclass(cls):
            return []
        return [f.name for f in fields(cls) if f.init and f.name not in self.fixed]

    def construct(self, spec: Any, where: str) -> Any:
        """An instance from a name, a mapping ``{"type": ..., options}`` or an instance.

        An instance of any subclass of the base (registered or not) is returned as is.
        """
        base = self.base
        assert base is not None, "registry not bound"
        if isinstance(spec, base):
            self.check_class(type(spec), where)
            return spec
        if isinstance(spec, str):
            spec = {"type": spec}
        if not isinstance(spec, Mapping) or "type" not in spec:
            raise SpecError(
                where,
                f"expected a {self.what} name, a mapping with 'type' or a {base.__name__} "
                f"instance, got {short_repr(spec)}",
            )
        cls = self.resolve(spec["type"], f"{where}.type")
        names = self.options(cls)
        opts = {k: freeze(v) for k, v in spec.items() if k != "type"}
        unknown = sorted(set(opts) - set(names))
        if unknown:
            raise SpecError(
                where,
                f"unknown option(s) {unknown} for {self.what} {spec['type']!r}; "
                f"allowed: {sorted(names)}",
            )
        try:
            return cls(**opts)
        except SpecError:
            raise
        except (TypeError, ValueError) as e:  # wrong value types, the class's own checks
            raise SpecError(where, _one_line(e)) from None


#: own features (bound by :mod:`epo_casadi.features`)
FEATURES = Registry("feature", "kind")
#: pair features (bound by :mod:`epo_casadi.features`)
PAIR_FEATURES = Registry("pair feature", "kind")
#: dynamics models (bound by :mod:`epo_casadi.dynamics`)
DYNAMICS = Registry("dynamics", "name", fixed=("state_names", "control_names"))


def register_feature(name: Any, cls: Any = None, *, replace: bool = False) -> type:
    """Register an own feature class (a :class:`~epo_casadi.features.Feature` subclass or
    ``"module:Class"``) under ``name``; ``register_feature(cls)`` uses ``cls.kind``.

    Returns the class (so it also works as a decorator without arguments). A built-in
    name is refused unless ``replace=True``.
    """
    return FEATURES.register(name, cls, replace=replace)


def register_pair_feature(name: Any, cls: Any = None, *, replace: bool = False) -> type:
    """Register a pair feature class (a :class:`~epo_casadi.features.PairFeature`
    subclass); see :func:`register_feature`."""
    return PAIR_FEATURES.register(name, cls, replace=replace)


def register_dynamics(name: Any, cls: Any = None, *, replace: bool = False) -> type:
    """Register a dynamics class (a :class:`~epo_casadi.dynamics.Dynamics` subclass);
    ``register_dynamics(cls)`` uses ``cls.name``; see :func:`register_feature`."""
    return DYNAMICS.register(name, cls, replace=replace)
