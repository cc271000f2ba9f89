"""Griffe extension for the documentation site (mkdocs.yml, mkdocstrings' python handler).

Two jobs, both on the docstrings griffe reads statically (nothing is imported):

- The docstrings are prose with reST roles (``:class:`~solvers.lm.LMOptions```) and reST
  section underlines; the site renders Markdown. Roles become code (`` `LMOptions` ``), an
  underlined section title becomes a bold line, a literal-block ``::`` a colon.
- A public module, class or function of the toolkit's packages without a docstring is a
  warning, so ``mkdocs build --strict`` (``make docs``, ``tests/test_docs.py``) fails. Public
  is griffe's rule: listed in ``__all__`` where a module has one, else no leading underscore.
  ``undocumented`` (the extension's option in mkdocs.yml) lists the known exceptions by path;
  ``packages`` names the checked packages (default: the toolkit's four).
"""

from __future__ import annotations

import re

from griffe import Extension, Module, Object, logger

PACKAGES = ("epo_casadi", "solvers", "scenarios", "learning")

_ROLE = re.compile(r":(?:py:)?(?:class|meth|func|mod|attr|data|obj|exc|const|ref|term):`([^`]+)`")
_UNDERLINE = re.compile(r"^([ \t]*)(\S[^\n]*)\n\1(?:-{3,}|={3,})[ \t]*$", re.M)
_LITERAL = re.compile(r"(\S)::[ \t]*$", re.M)


def _role(m: re.Match) -> str:
    text = m.group(1)
    label = re.match(r"(.*?)\s*<[^>]+>$", text)  # :ref:`text <target>`
    if label:
        text = label.group(1)
    elif text.startswith("~"):
        text = text[1:].rsplit(".", 1)[-1]
    return f"`{text}`"


def markdown(text: str) -> str:
    """The docstring ``text`` with reST roles, section underlines and ``::`` in Markdown."""
    text = _ROLE.sub(_role, text)
    text = _UNDERLINE.sub(r"\1**\2**", text)
    return _LITERAL.sub(r"\1:", text)


class EpoDocstrings(Extension):
    """Markdown for reST roles; a warning for each public object without a docstring."""

    def __init__(self, undocumented: list[str] | None = None, packages=PACKAGES) -> None:
        super().__init__()
        self.undocumented = set(undocumented or ())
        self.packages = tuple(packages)

    def on_object(self, *, obj: Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown(obj.docstring.value)

    def on_package(self, *, pkg: Module, **kwargs) -> None:
        if pkg.name in self.packages:
            self._check(pkg)

    def _check(self, module: Module) -> None:
        if module.docstring is None:
            self._warn(module)
        for member in module.members.values():
            if member.is_alias:
                continue
            if member.is_module:
                if not member.name.startswith("_"):
                    self._check(member)
            elif (member.is_class or member.is_function) and member.is_public:
                if member.docstring is None:
                    self._warn(member)

    def _warn(self, obj: Object) -> None:
        if obj.path in self.undocumented:
            return
        where = f"{obj.relative_filepath}:{obj.lineno or 1}"
        logger.warning(f"{where}: public {obj.kind.value} {obj.path} has no docstring")
