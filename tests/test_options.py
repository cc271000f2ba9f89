"""Options objects: frozen, unknown keys refused, and the defaults the docs print are the
defaults the code uses (tables in docs/ilq.md and docs/solvers.md)."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import pytest

from learning.losses import LossWeights
from solvers.ilq import ILQOptions
from solvers.ipopt import IpoptOptions
from solvers.lm import LMOptions, check_options
from solvers.multimodal import MultiModalOptions
from solvers.nash import NashOptions
from solvers.olne import OLNEOptions

DOCS = Path(__file__).resolve().parents[1] / "docs"
ALL = [LMOptions, ILQOptions, IpoptOptions, NashOptions, MultiModalOptions, LossWeights]


def _documented_defaults(doc: str, after: str) -> dict[str, str]:
    """``field -> default`` from the first ``| field | default | meaning |`` table after
    the line containing ``after``."""
    text = (DOCS / doc).read_text()
    text = text[text.index(after) :]
    out = {}
    started = False
    for line in text.splitlines():
        if line.startswith("| field | default |"):
            started = True
            continue
        if not started or line.startswith("|---"):
            continue
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        names = re.findall(r"`(\w+)`", cells[0])
        values = [v.strip() for v in cells[1].split(",")] if len(names) > 1 else [cells[1]]
        assert len(names) == len(values), line
        out.update(zip(names, values, strict=True))
    assert out, f"no options table after {after!r} in {doc}"
    return out


def _value(text: str):
    if text in ("None", "inf", "True", "False"):
        return {"None": None, "inf": math.inf, "True": True, "False": False}[text]
    if text.startswith(('"', "`")):
        return text.strip('`"')
    if text.startswith("("):  # a tuple of numbers, e.g. ILQOptions.kink_widths
        return tuple(float(v) for v in text.strip("()").split(",") if v.strip())
    return float(text)


@pytest.mark.parametrize(
    "cls, doc, after",
    [
        (ILQOptions, "ilq.md", "### Options (`ILQOptions`"),
        (IpoptOptions, "solvers.md", "IPOPT"),
        (OLNEOptions, "solvers.md", "### Options (`OLNEOptions`"),
    ],
)
def test_documented_defaults_are_the_code_defaults(cls, doc, after):
    documented = _documented_defaults(doc, after)
    defaults = cls()
    for name, text in documented.items():
        assert hasattr(defaults, name), f"{doc} documents {name}, which {cls.__name__} lacks"
        want, got = _value(text), getattr(defaults, name)
        if isinstance(want, float) and not isinstance(got, bool) and got is not None:
            assert float(got) == want, (name, got, text)
        else:
            assert got == want, (name, got, text)


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_options_are_frozen_and_refuse_unknown_keys(cls):
    opts = cls()
    field = dataclasses.fields(cls)[0].name
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(opts, field, getattr(opts, field))
    if cls is not LossWeights:  # the solver options go through check_options
        from epo_casadi import SpecError

        with pytest.raises(SpecError, match="unknown option"):
            check_options(cls, {"no_such_option": 1}, "x")
        assert check_options(cls, {}, "x") == cls()
