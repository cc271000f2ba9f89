"""Reading a game file from disk (:func:`load_game`): its text as YAML (anchors, aliases
and merge keys) or JSON, duplicate keys refused, then :func:`parse_game`; and the
example files shipped with the toolkit (:data:`EXAMPLES`, :func:`example_path`)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from epo_casadi.errors import SpecError, short_repr
from scenarios.files import check_input_file

from .checks import MAX_DEPTH, _tname
from .parsing import GameFile, parse_game

EXAMPLES_DIR = Path(__file__).resolve().parent.parent / "examples"
#: names of the example files shipped in ``scenarios/examples`` (without ``.yaml``)
EXAMPLES = ("crossing2", "robot_pedestrian", "intersection4", "highway_merge")


def example_path(name: str) -> Path:
    """Path of a shipped example file, by name (``"crossing2"``) or file name."""
    stem = name[:-5] if name.endswith(".yaml") else name
    if stem not in EXAMPLES:
        raise SpecError(
            "example", f"unknown example {short_repr(name)}; expected one of {list(EXAMPLES)}"
        )
    return EXAMPLES_DIR / f"{stem}.yaml"


def load_game(path: str | Path, allow_imports: Sequence[str] = ()) -> GameFile:
    """Read a game file (``.yaml``/``.yml`` or ``.json``); see :mod:`scenarios.gamefile`.

    ``allow_imports``: modules whose ``module:Class`` names the file may import (with
    their submodules), besides those of ``$EPO_ALLOW_IMPORT`` and open
    :func:`epo_casadi.registry.allow_imports` blocks; any other is refused before it is
    imported. Raises :class:`SpecError` for every problem in the file (syntax included)
    and ``FileNotFoundError`` when there is no such file.
    """
    path = Path(path)
    where = path.name
    if path.exists():  # a pipe or a device would block or be read forever
        check_input_file(path, where)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise SpecError(
            where, f"not a UTF-8 text file (byte {e.start}); expected YAML or JSON"
        ) from None
    if not text.strip():
        raise SpecError(
            where, "the file is empty; expected a mapping with 'horizon', 'dt' and 'agents'"
        )
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text, object_pairs_hook=lambda pairs: _json_unique(pairs, where))
        except json.JSONDecodeError as e:
            raise SpecError(
                where, f"invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}"
            ) from None
        except RecursionError:  # the decoder recurses once per level of nesting
            raise SpecError(
                where, f"invalid JSON: nested more than {MAX_DEPTH} levels deep"
            ) from None
    else:
        data = _load_yaml(text, where)
    if data is None:
        raise SpecError(
            where, "the file holds no data; expected a mapping with 'horizon', 'dt' and 'agents'"
        )
    return parse_game(data, source=path, allow_imports=allow_imports)


def _load_yaml(text: str, where: str):
    import yaml

    class _Loader(yaml.SafeLoader):
        pass

    def _mapping(loader, node, deep=False):
        out, merged = {}, {}
        for knode, vnode in node.value:
            mark = knode.start_mark
            if knode.tag == "tag:yaml.org,2002:merge":  # '<<: *base' or '<<: [*a, *b]'
                for src in reversed(_merge_sources(loader, vnode, deep, mark)):
                    merged.update(src)  # the first mapping listed wins
                continue
            key = loader.construct_object(knode, deep=deep)
            try:
                hash(key)
            except TypeError:
                raise SpecError(
                    where,
                    f"a key at line {mark.line + 1}, column {mark.column + 1} is a "
                    f"{_tname(key)}; expected a name",
                ) from None
            if key in out:
                raise SpecError(
                    where,
                    f"duplicate key {short_repr(key)} at line {mark.line + 1}, column {mark.column + 1}",
                )
            out[key] = loader.construct_object(vnode, deep=deep)
        # YAML merge keys: the mapping's own keys override the merged ones, wherever written
        return {**{k: v for k, v in merged.items() if k not in out}, **out} if merged else out

    def _merge_sources(loader, vnode, deep, mark) -> list:
        """The mappings a merge key ``<<`` names (a mapping, or a list of mappings)."""
        nodes = vnode.value if isinstance(vnode, yaml.SequenceNode) else [vnode]
        out = []
        for n in nodes:
            if not isinstance(n, yaml.MappingNode):
                raise SpecError(
                    where,
                    f"the merge key '<<' at line {mark.line + 1}, column {mark.column + 1} "
                    "expects a mapping (an alias like *base) or a list of mappings",
                )
            out.append(loader.construct_object(n, deep=deep))
        return out

    _Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping)
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
    except RecursionError:
        raise SpecError(where, "invalid YAML: nested too deeply") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise SpecError(where, f"invalid YAML{at}: {problem}") from None


def _json_unique(pairs, where: str):
    out = {}
    for k, v in pairs:
        if k in out:
            raise SpecError(where, f"duplicate key {short_repr(k)}")
        out[k] = v
    return out
