"""The fields every recorded-data recipe shares: window sizes, the interaction rule, the
crowd game's default weights (:func:`scenarios.real.scenes.crowd_game_spec`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from epo_casadi.errors import check_number, check_size, from_mapping
from epo_casadi.presets import check_weights

__all__ = ["SceneRecipe"]


@dataclass(frozen=True)
class SceneRecipe:
    """Window, agents and game of a recorded-data dataset. Frozen; unknown keys fail.
    Subclasses add their reader's fields and set :attr:`prefix` (the field prefix of errors)."""

    prefix = "real"

    agents: int = 4  #: N (scenes with fewer recorded agents are padded and masked)
    history: int = 7  #: H past steps (plus the current one)
    horizon: int = 12  #: T = K future steps
    modes: int = 20  #: M future slots (slot 0 the recording, the rest copies)
    dt: float = 0.4  #: step (s)
    stride: int = 1  #: current steps of one focal agent's scenes are this many steps apart
    max_distance: float = (
        1e9  #: others farther than this at their closest approach are left out (m)
    )
    radius: float = 0.3  #: default collision radius (m)
    collision_every: int = 1  #: the collision term every this many steps
    w_goal: float = 1.0  #: default weights of the game (the network predicts them)
    w_vel: float = 0.1
    w_acc: float = 1.0
    w_jerk: float = 0.1
    w_turn: float = 1.0
    w_turnacc: float = 0.1
    w_collision: float = 10.0

    def __post_init__(self):
        p = self.prefix
        for k, lo, hi in (
            ("agents", 1, 64),
            ("history", 1, 1000),
            ("horizon", 2, 1000),
            ("modes", 1, 100),
            ("stride", 1, 10**6),
            ("collision_every", 1, 1000),
        ):
            check_number(f"{p}.{k}", getattr(self, k), lo=lo, integer=True)
            check_size(f"{p}.{k}", getattr(self, k), hi, "the size of every sample", lo=lo)
        check_number(f"{p}.dt", self.dt, lo=0.01, hi=5.0)
        check_number(f"{p}.max_distance", self.max_distance, lo=0.0, lo_open=True)
        check_number(f"{p}.radius", self.radius, lo=0.0, lo_open=True, hi=100.0)
        check_weights(p, self)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict):
        """The recipe of a manifest's or ``--set``'s fields (unknown fields refused)."""
        return from_mapping(cls, d, cls.prefix, "recipe field")
