"""The documentation site builds with ``mkdocs build --strict`` (a broken link or anchor, a
docstring griffe cannot read or a public object without a docstring fails it); every
relative link of README.md, which the site does not build, points to an existing file and
heading; every number of README's results table is on a results or benchmarks page; the
Python blocks of the start-from-zero guides run as written."""

import logging
import os
import pathlib
import re
import subprocess
import sys
import unicodedata

import pytest
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
MKDOCS = pathlib.Path(sys.executable).with_name("mkdocs")
EXTENSION = ROOT / "docs" / "_ext" / "epo_griffe.py"


def _mkdocs_missing() -> str | None:
    if not MKDOCS.exists():
        return f"mkdocs is not installed in this environment ({MKDOCS}); pip install -e '.[docs]'"
    return None


@pytest.mark.skipif(_mkdocs_missing() is not None, reason=str(_mkdocs_missing()))
def test_site_builds_strict(tmp_path):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "PYTHONDONTWRITEBYTECODE": "1"}
    site = tmp_path / "site"
    cmd = [str(MKDOCS), "build", "--strict", "-f", str(ROOT / "mkdocs.yml"), "-d", str(site)]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-6000:]
    assert "WARNING" not in proc.stderr, proc.stderr[-6000:]
    for page in ["index", "getting-started", "guide-control", "guide-data", "guide-learning"]:
        assert (site / page / "index.html").exists() or (site / f"{page}.html").exists(), page
    # the API reference was rendered from the docstrings (griffe, statically)
    api = (site / "api" / "solvers" / "index.html").read_text()
    assert "solve_lm" in api and "Levenberg" in api
    assert ":class:`" not in api  # reST roles became code


def _slug(heading: str) -> str:
    """Python-Markdown's default toc slug of a Markdown heading."""
    text = re.sub(r"[`*_]|\[([^\]]*)\]\([^)]*\)", lambda m: m.group(1) or "", heading)
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def _anchors(md: pathlib.Path) -> set[str]:
    text = re.sub(r"```.*?```", "", md.read_text(), flags=re.S)  # no headings in code blocks
    return {_slug(h) for h in re.findall(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, re.M)}


def test_readme_links_point_to_files_and_headings():
    text = (ROOT / "README.md").read_text()
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    relative = [u for u in links if not re.match(r"[a-z]+:", u)]
    assert len(relative) >= 10, relative  # the front page links the docs
    for link in relative:
        path, _, anchor = link.partition("#")
        target = (ROOT / path).resolve() if path else ROOT / "README.md"
        assert target.is_file(), f"README.md links to {link}: no file {target}"
        if anchor:
            assert anchor in _anchors(target), f"README.md links to {link}: no such heading"


def _results_table(text: str) -> str:
    section = text[text.index("## Results") :]
    return "\n".join(line for line in section.splitlines() if line.startswith("| "))


NUMBER = r"\d+(?:,\d{3})*(?:\.\d+)?"


def test_readme_results_are_on_the_results_pages():
    """A headline number of the front page is in the body of docs/results.md or
    docs/benchmarks.md (outside their own summary table), next to its command."""
    table = _results_table((ROOT / "README.md").read_text())
    assert table.count("\n") >= 5, table
    pages = ""
    for name in ("results.md", "benchmarks.md"):
        text = (ROOT / "docs" / name).read_text()
        if "## Summary" in text:  # leave the copy of the table out
            head, _, rest = text.partition("## Summary")
            text = head + rest[rest.index("\n## ") :]
        pages += text
    found = set(re.findall(NUMBER, pages))
    missing = [n for n in re.findall(NUMBER, table) if n not in found]
    assert not missing, f"README results not on docs/results.md or docs/benchmarks.md: {missing}"


GUIDES = sorted((ROOT / "docs").glob("guide-*.md"))
GUIDE_BLOCKS = [
    (g.name, i, block)
    for g in GUIDES
    for i, block in enumerate(re.findall(r"```python\n(.*?)```", g.read_text(), flags=re.S))
]


def test_every_guide_starts_from_setup():
    assert len(GUIDES) == 4, GUIDES
    for g in GUIDES:
        text = g.read_text()
        assert "make setup" in text.split("\n## 2")[0], f"{g.name} does not start from make setup"


@pytest.mark.parametrize(
    "name, index, block", GUIDE_BLOCKS, ids=[f"{n}[{i}]" for n, i, _ in GUIDE_BLOCKS]
)
def test_guide_example_runs(name, index, block, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    exec(compile(block, f"docs/{name}[python block {index}]", "exec"), {"__name__": "__guide__"})
    assert capsys.readouterr().out.strip(), f"docs/{name} block {index} printed nothing"


def test_slug_matches_markdown():
    assert _slug("`make demo` and `make test`") == "make-demo-and-make-test"
    assert _slug("The Riccati elimination in C (2026-11-30, evening)") == (
        "the-riccati-elimination-in-c-2026-11-30-evening"
    )


# --------------------------------------------------------------------------------------
# The griffe extension of the site (docs/_ext/epo_griffe.py)
# --------------------------------------------------------------------------------------
def _extension():
    pytest.importorskip("griffe", reason="griffe (mkdocstrings-python) is not installed")
    import importlib.util

    spec = importlib.util.spec_from_file_location("epo_griffe", EXTENSION)
    module = importlib.util.module_from_spec(spec)
    write, sys.dont_write_bytecode = sys.dont_write_bytecode, True  # no __pycache__ in docs/
    try:
        spec.loader.exec_module(module)
    finally:
        sys.dont_write_bytecode = write
    return module


def test_extension_turns_rest_into_markdown():
    md = _extension().markdown
    assert md(":class:`~solvers.lm.LMOptions` and :func:`solvers.solve_lm`") == (
        "`LMOptions` and `solvers.solve_lm`"
    )
    assert md(":meth:`LMOptions.paper`, :ref:`the docs <target>`") == (
        "`LMOptions.paper`, `the docs`"
    )
    assert md("Attributes\n----------\nx: one") == "**Attributes**\nx: one"
    assert md("Each step::\n\n    u <- u + du") == "Each step:\n\n    u <- u + du"


def _load(tmp_path, package: str, source: str, undocumented=()):
    import griffe

    ext = _extension().EpoDocstrings(undocumented=list(undocumented), packages=["epo_fake"])
    (tmp_path / package).mkdir()
    (tmp_path / package / "__init__.py").write_text('"""A package."""\n')
    (tmp_path / package / "mod.py").write_text(source)
    griffe.load(package, search_paths=[str(tmp_path)], extensions=griffe.load_extensions(ext))


SOURCE = '''"""A module."""
__all__ = ["documented", "bare", "Bare"]
def documented():
    """Has one."""
def bare():
    pass
class Bare:
    pass
def _private():
    pass
def not_exported():
    pass
'''


def test_extension_warns_about_public_objects_without_docstring(tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        _load(tmp_path, "epo_fake", SOURCE, undocumented=["epo_fake.mod.Bare"])
    warned = [r.getMessage() for r in caplog.records if "has no docstring" in r.getMessage()]
    assert len(warned) == 1, warned  # bare(); Bare is listed, _private and not_exported private
    assert "epo_fake/mod.py:5: public function epo_fake.mod.bare" in warned[0]


def test_extension_leaves_other_packages_alone(tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        _load(tmp_path, "epo_other", SOURCE)
    assert not [r for r in caplog.records if "has no docstring" in r.getMessage()]


def test_undocumented_list_names_only_undocumented_objects():
    """The exceptions in mkdocs.yml exist and still lack a docstring (else drop them)."""
    griffe = pytest.importorskip("griffe", reason="griffe (mkdocstrings-python) is not installed")

    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    (plugin,) = [p["mkdocstrings"] for p in config["plugins"] if isinstance(p, dict)]
    python = plugin["handlers"]["python"]["options"]
    (ext,) = python["extensions"]
    listed = next(iter(ext.values()))["undocumented"]
    assert listed == sorted(set(listed), key=listed.index)  # no duplicates
    loader = griffe.GriffeLoader(search_paths=[str(ROOT)])
    for path in listed:
        package = path.split(".")[0]
        if package not in loader.modules_collection:
            loader.load(package)
        obj = loader.modules_collection[path]
        assert obj.docstring is None, f"{path} has a docstring now: remove it from mkdocs.yml"
