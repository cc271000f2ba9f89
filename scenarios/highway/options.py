"""What one generated raw set is made of (:class:`HighwayOptions`) and the limits checked
before any work (:data:`MAX_RECORDINGS`, :data:`MAX_DURATION`, :data:`MAX_WARMUP`,
:data:`MAX_FRAMES`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from epo_casadi.errors import SpecError, check_number, check_size, short_repr

from .road import LOCATIONS

#: most recordings of one raw set (file names ``NN_*.csv``)
MAX_RECORDINGS = 10_000
#: most recorded seconds per recording (s)
MAX_DURATION = 3600.0
#: most simulated warm-up seconds before frame 0 (s)
MAX_WARMUP = 600.0
#: most recorded frames per recording (``duration x frame_rate``; held in memory)
MAX_FRAMES = 100_000


@dataclass(frozen=True)
class HighwayOptions:
    """Options of one generated raw set (frozen; unknown names are errors)."""

    recordings: int = 8  #: recordings, round-robin over ``locations``
    locations: tuple[int, ...] = (0, 1, 2, 3)
    duration: float = 120.0  #: recorded seconds per recording
    warmup: float = 30.0  #: simulated seconds before frame 0
    frame_rate: float = 25.0  #: Hz (exiD: 25)
    flow: tuple[float, float] = (0.25, 0.45)  #: main-road arrivals per lane (veh/s)
    ramp_flow: tuple[float, float] = (0.14, 0.28)  #: on-ramp arrivals (veh/s)
    exit_share: float = 0.3  #: share of main-road vehicles that take an off-ramp
    truck_share: float = 0.15

    def __post_init__(self):
        p = "highway"
        object.__setattr__(
            self,
            "recordings",
            check_size(f"{p}.recordings", self.recordings, MAX_RECORDINGS, "recordings of a set"),
        )
        locs = self.locations
        ids = sorted(LOCATIONS)
        if isinstance(locs, (str, bytes)) or not isinstance(locs, (list, tuple)):
            raise SpecError(
                f"{p}.locations",
                f"expected a list of location ids from {ids}, e.g. [0, 2], got {short_repr(locs)}",
            )
        bad = [
            x
            for x in locs
            if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x not in LOCATIONS
        ]
        if not locs or bad:
            raise SpecError(
                f"{p}.locations",
                f"expected a non-empty list of location ids from {ids}, got {short_repr(list(locs))}",
            )
        object.__setattr__(self, "locations", tuple(int(x) for x in locs))
        check_number(f"{p}.duration", self.duration, lo=1.0, hi=MAX_DURATION)
        check_number(f"{p}.warmup", self.warmup, lo=0.0, hi=MAX_WARMUP)
        check_number(f"{p}.frame_rate", self.frame_rate, lo=1.0, hi=100.0)
        frames = int(round(self.duration * self.frame_rate))
        check_size(
            f"{p}.duration",
            frames,
            MAX_FRAMES,
            f"recorded frames per recording, duration {self.duration:g} s x frame_rate "
            f"{self.frame_rate:g} Hz: memory",
        )
        for k in ("exit_share", "truck_share"):
            check_number(f"{p}.{k}", getattr(self, k), lo=0.0, hi=1.0)
        for k in ("flow", "ramp_flow"):
            v = getattr(self, k)
            ok = isinstance(v, (list, tuple)) and len(v) == 2
            ok = ok and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                for x in v
            )
            if not ok or not 0 <= v[0] <= v[1] <= 2:
                raise SpecError(
                    f"{p}.{k}",
                    f"expected [low, high] with 0 <= low <= high <= 2 veh/s, got {short_repr(v)}",
                )
            object.__setattr__(self, k, (float(v[0]), float(v[1])))
