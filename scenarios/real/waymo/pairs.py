"""The pair rule of a Waymo record: which pairs of listed tracks make a scene, read from the
``objects_of_interest`` / ``tracks_to_predict`` lists, the types and the valid flags only
(no positions; the rule is in :mod:`scenarios.real.waymo`, "Agents")."""

from __future__ import annotations

import itertools

import numpy as np

from ..waymo_schema import OBJECT_TYPES
from .recipe import WaymoRecipe
from .records import _bad, _head, _message, _states


def _listed(r: WaymoRecipe, ids: np.ndarray, interest, pred) -> list[int]:
    """Track indices of the pair rule's list (order kept, duplicates dropped)."""
    by_id = {int(t): k for k, t in enumerate(ids)}
    inter = list(dict.fromkeys(by_id[i] for i in interest))
    predict = list(dict.fromkeys(k for k, _ in pred))
    if r.pairs == "interest" or (r.pairs == "auto" and len(inter) >= 2):
        return inter
    return predict


def _pairs(r: WaymoRecipe, where, ts, current, ids, types, valid_of, interest, pred):
    """``(pairs, skipped)``: the kept pairs (track indices, slot order) and the counts of
    skipped ones by reason (``type``, ``invalid``; ``no pair``: fewer than two listed)."""
    before, after = r.span
    S = len(ts)
    if current - before < 0 or current + after > S - 1:
        raise _bad(
            where,
            "current_time_index",
            f"the window needs {before} steps before and {after} after the current step "
            f"{current} (history {r.history} x step {r.step}, horizon {r.horizon} x step "
            f"{r.step}); the record has {S} steps",
        )
    listed = _listed(r, ids, interest, pred)
    skipped = {"type": 0, "invalid": 0, "no pair": 0}
    if len(listed) < 2:
        skipped["no pair"] = 1
        return [], skipped
    keep = {OBJECT_TYPES.index(t) for t in r.types}
    grid = r.grid(current)
    out = []
    for a, b in itertools.combinations(listed, 2):
        if int(types[a]) not in keep or int(types[b]) not in keep:
            skipped["type"] += 1
            continue
        if not (valid_of(a)[grid].all() and valid_of(b)[grid].all()):
            skipped["invalid"] += 1
            continue
        veh = [k for k in (a, b) if types[k] == 1]
        out.append((b, a) if veh == [b] else (a, b))
    return out, skipped


def _scan(r: WaymoRecipe, payload: bytes, where: str):
    """The pairs of one record, reading only the listed tracks' flags and types."""
    msg = _message(payload, where)
    ts, ids, types, pred, interest = _head(msg, where)
    cache: dict[int, np.ndarray] = {}

    def valid_of(k):
        if k not in cache:
            cache[k] = _states(msg, [k], where)[1][0]
        return cache[k]

    pairs, skipped = _pairs(
        r, where, ts, msg.current_time_index, ids, types, valid_of, interest, pred
    )
    return str(msg.scenario_id), pairs, skipped
