"""Pieces every simulated world shares: the noisy sensor, option parsing, characters,
circle collisions, the gap rule of the hand-made drivers and the outcome latch."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size

__all__ = [
    "OUTCOMES",
    "Character",
    "Sensor",
    "build_options",
    "check_episode_sizes",
    "check_range",
    "check_sensor",
    "check_speed_fraction",
    "circles_overlap",
    "ego_interval",
    "gap_decision",
    "seeds",
    "time_to_cover",
    "zone_times",
]

OUTCOMES = ("running", "success", "collision", "timeout", "off_road")

#: most steps of an episode (``max_steps``) and of a dropout (``dropout_burst``): an episode's
#: log holds every step's plan and predictions
MAX_STEPS = 100_000
#: most points of an agent's task path (``n_path``)
MAX_PATH = 10_000


def build_options(cls, scenario: str, options: dict):
    """``cls(**options)`` for a frozen options dataclass; an unknown name is a SpecError
    naming it and the valid ones."""
    names = [f.name for f in dataclasses.fields(cls)]
    for k in options:
        if k not in names:
            raise SpecError(f"{scenario}.{k}", f"unknown option; valid: {', '.join(names)}")
    return cls(**options)


def check_range(field: str, value, lo=None, hi=None, ordered=True) -> tuple[float, float]:
    """A pair of finite numbers within ``[lo, hi]``, with ``low <= high`` if ``ordered``."""
    try:
        t = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        raise SpecError(field, f"expected two numbers (low, high), got {value!r}") from None
    if len(t) != 2 or not all(math.isfinite(x) for x in t):
        raise SpecError(field, f"expected two finite numbers (low, high), got {value!r}")
    if ordered and t[0] > t[1]:
        raise SpecError(field, f"expected low <= high, got {list(t)}")
    if (lo is not None and min(t) < lo) or (hi is not None and max(t) > hi):
        raise SpecError(field, f"expected values in [{lo}, {hi}], got {list(t)}")
    return t


def check_speed_fraction(field: str, value) -> tuple[float, float]:
    """A range of desired speeds as fractions of the speed limit, within ``[0.05, 1]``: the
    hand-made drivers are IDM vehicles, which never drive faster than their lane's limit, so
    a fraction above 1 would be a speed the world cannot drive (and a truth the oracle would
    be told); it is refused naming the field and the limit."""
    lo, hi = check_range(field, value)
    if hi > 1.0:
        raise SpecError(
            field,
            f"expected fractions of the speed limit in [0.05, 1.0] (the IDM drivers never drive "
            f"faster than the limit, so a desired speed above it cannot be honoured), got "
            f"{[lo, hi]}",
        )
    if lo < 0.05:
        raise SpecError(
            field, f"expected fractions of the speed limit in [0.05, 1.0], got {[lo, hi]}"
        )
    return lo, hi


def seeds(seed: int, n: int) -> list[np.random.Generator]:
    """``n`` independent generators from one episode seed (scene, character, sensor...)."""
    if isinstance(seed, np.integer):
        seed = int(seed)
    check_number("seed", seed, lo=0, integer=True)
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]


@dataclass(frozen=True)
class Character:
    """The hidden character of a hand-made road user.

    ``aggressiveness`` in ``[0, 1]``: 0 waits for large gaps, 1 forces its way;
    ``desired_speed`` (m/s); ``reaction`` (s): it acts on what it saw that long ago.
    """

    aggressiveness: float = 0.5
    desired_speed: float = 10.0
    reaction: float = 0.5

    def __post_init__(self):
        check_number("character.aggressiveness", self.aggressiveness, lo=0.0, hi=1.0)
        check_number("character.desired_speed", self.desired_speed, lo=0.0, lo_open=True)
        check_number("character.reaction", self.reaction, lo=0.0, hi=5.0)

    @classmethod
    def draw(
        cls,
        rng: np.random.Generator,
        aggressiveness: tuple[float, float],
        desired_speed: tuple[float, float],
        reaction: tuple[float, float],
    ) -> Character:
        a, v, r = rng.uniform(*zip(aggressiveness, desired_speed, reaction, strict=True))
        return cls(float(a), float(v), float(r))

    def margin(self, cautious: float, bold: float) -> float:
        """Accepted time margin (s): ``cautious`` at aggressiveness 0, ``bold`` at 1."""
        return cautious + self.aggressiveness * (bold - cautious)


def gap_decision(
    t_own_clear: float,
    t_ego_reach: float,
    t_ego_clear: float,
    margin: float,
) -> bool:
    """The hand-made gap rule of the other road users (True = go, False = yield).

    The user goes if the ego has already left the conflict zone (``t_ego_clear == 0``) or
    if the user clears the zone at least ``margin`` seconds before the ego reaches it
    (``t_own_clear + margin <= t_ego_reach``); otherwise it yields. A negative margin is a
    bold user who forces its way in. The ego's times are at its constant current speed, so
    an ego standing still before the zone never reaches it (``inf``: the user goes).
    """
    if t_ego_clear <= 0.0:
        return True
    return t_own_clear + margin <= t_ego_reach


def zone_times(s: float, v: float, zone: tuple[float, float], extra: float) -> tuple[float, float]:
    """Times to reach and to clear a zone ``(s_in, s_out)`` along a path from arc length
    ``s`` at constant speed ``v`` (``extra``: half a vehicle length on each side).
    ``(0, t)`` once inside; ``(0, 0)`` once past; ``inf`` when not moving towards it."""
    s_in, s_out = zone[0] - extra, zone[1] + extra
    if s >= s_out:
        return 0.0, 0.0
    if v <= 0.1:
        return (0.0, math.inf) if s >= s_in else (math.inf, math.inf)
    return max(0.0, (s_in - s) / v), (s_out - s) / v


def time_to_cover(dist: float, v0: float, acc: float, vmax: float) -> float:
    """Time (s) to cover ``dist`` from speed ``v0`` accelerating at ``acc`` up to ``vmax``."""
    if dist <= 0.0:
        return 0.0
    v0 = max(v0, 0.0)
    vmax = max(vmax, v0, 1e-6)
    t1 = (vmax - v0) / acc
    d1 = v0 * t1 + 0.5 * acc * t1 * t1
    if dist <= d1:
        return (-v0 + math.sqrt(v0 * v0 + 2 * acc * dist)) / acc
    return t1 + (dist - d1) / vmax


def circles_overlap(positions: np.ndarray, radii: np.ndarray, pairs=None) -> bool:
    """True if two circles overlap (``distance < r_i + r_j``); ``pairs``: index pairs to
    test (default: agent 0 against every other one)."""
    p = np.asarray(positions, dtype=float)
    r = np.asarray(radii, dtype=float)
    if pairs is None:
        d = np.linalg.norm(p[1:] - p[0], axis=1)
        return bool(np.any(d < r[0] + r[1:]))
    i, j = np.asarray(pairs).T
    return bool(np.any(np.linalg.norm(p[i] - p[j], axis=1) < r[i] + r[j]))


class Sensor:
    """Noisy positions of the other agents: Gaussian noise of std ``noise_std`` (m) on each
    coordinate and dropouts in bursts of ``dropout_burst`` steps (the rows are ``NaN``).

    ``dropout_prob`` ``p`` is the fraction of measurements lost, on average: an observed
    agent starts a burst with probability ``q = p / (L (1 - p) + p)`` per step (``L`` the
    burst length), so that the stationary lost fraction ``q L / (q L + 1 - q)`` is ``p``
    (``p = 1``: never observed; ``L = 1``: independent losses of probability ``p``). Noise is
    drawn every step for every agent, so the stream of numbers does not depend on the
    dropouts."""

    def __init__(self, n: int, noise_std: float, dropout_prob: float, dropout_burst: int):
        self.n = n
        self.noise_std = noise_std
        self.dropout_prob = dropout_prob
        self.dropout_burst = int(dropout_burst)
        p, L = float(dropout_prob), self.dropout_burst
        #: probability per step that an observed agent starts a burst
        self.start_prob = p / (L * (1.0 - p) + p) if p > 0 else 0.0
        self.rng: np.random.Generator | None = None
        self.left = np.zeros(n, dtype=np.int64)

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.left = np.zeros(self.n, dtype=np.int64)

    def measure(self, positions: np.ndarray) -> np.ndarray:
        """``(n, 2)`` measurements of the true ``positions`` ``(n, 2)``."""
        noise = self.rng.normal(0.0, 1.0, size=(self.n, 2)) * self.noise_std
        start = self.rng.random(self.n) < self.start_prob
        self.left = np.where((self.left == 0) & start, self.dropout_burst, self.left)
        out = np.asarray(positions, dtype=float) + noise
        out[self.left > 0] = np.nan
        self.left = np.maximum(self.left - 1, 0)
        return out


def check_sensor(scenario: str, noise_std, dropout_prob, dropout_burst) -> int:
    """Check the sensor options; returns ``dropout_burst`` as an int (at most MAX_STEPS)."""
    check_number(f"{scenario}.noise_std", noise_std, lo=0.0)
    check_number(f"{scenario}.dropout_prob", dropout_prob, lo=0.0, hi=1.0)
    return check_size(f"{scenario}.dropout_burst", dropout_burst, MAX_STEPS, "steps")


def check_episode_sizes(options, scenario: str) -> None:
    """``max_steps`` and ``n_path`` of a frozen world options object, bounded (check_size)."""
    for name, limit in (("max_steps", MAX_STEPS), ("n_path", MAX_PATH)):
        lo = 2 if name == "n_path" else 1
        v = check_size(f"{scenario}.{name}", getattr(options, name), limit, "memory", lo=lo)
        object.__setattr__(options, name, v)


class Latch:
    """The first terminal outcome sticks (the world keeps stepping if asked)."""

    def __init__(self):
        self.value = "running"

    def set(self, value: str) -> None:
        if self.value == "running" and value != "running":
            self.value = value


def check_command(command, names: str) -> np.ndarray:
    """The ego's command as 2 finite numbers (``names``, e.g. ``"a, delta"``), else
    :class:`SpecError` naming ``command``."""
    u = np.asarray(command, dtype=float).reshape(-1)
    if u.shape != (2,) or not np.all(np.isfinite(u)):
        raise SpecError("command", f"expected 2 finite numbers ({names}), got {command!r}")
    return u


def ego_interval(zone) -> tuple[float, float] | None:
    """The ego's arc-length interval ``zone.a`` of a :class:`scenarios.maps.ConflictZone`
    (None for no zone): what :meth:`solvers.control.types.World.conflict_zone` returns."""
    if zone is None:
        return None
    return (float(zone.a[0]), float(zone.a[1]))
