"""Small games and CLI helpers shared by the tests."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from epo_casadi import (
    Acceleration,
    AccelerationBound,
    AgentSpec,
    Collision,
    GameSpec,
    Goal,
    Jerk,
    JointDynamics,
    PotentialGame,
    TurnRate,
    TurnRateBound,
    Velocity,
    VelocityBound,
)


def crossing_spec(
    N: int = 2, K: int = 20, dt: float = 0.1, collision_weight: float = 10.0, offset: float = 0.0
) -> GameSpec:
    """N unicycles on a circle of radius 3 m, each heading to the opposite side.

    ``offset`` shifts every goal sideways (m) to break the symmetry of the head-on case.
    """
    agents = []
    for i in range(N):
        ang = 2 * np.pi * i / N
        c, s = np.cos(ang), np.sin(ang)
        agents.append(
            AgentSpec(
                f"a{i}",
                "unicycle",
                [
                    Goal(weight=3.0),
                    Velocity(weight=0.5),
                    Acceleration(),
                    TurnRate(),
                    VelocityBound(lower=0.0, upper=2.0, weight=5.0),
                    AccelerationBound(lower=-2.0, upper=2.0, weight=5.0),
                    TurnRateBound(lower=-1.5, upper=1.5, weight=5.0),
                ],
                radius=0.25,
                x0=[3 * c, 3 * s, 1.0, ang + np.pi],
                goal=[-3 * c - offset * s, -3 * s + offset * c],
            )
        )
    return GameSpec(agents, [Collision(weight=collision_weight)], horizon=K, dt=dt)


def crossing_game(**kw) -> PotentialGame:
    return PotentialGame(crossing_spec(**kw))


def solved_crossing():
    """``(game, p, u0, sol)``: the 2-agent crossing ``crossing_game(offset=0.3)``, its
    default parameters, the start ``u0`` (every control ``[1, 0]``) and IPOPT's potential
    minimizer from it (converged, with the collision term active: the agents interact)."""
    from solvers.ipopt import solve_ipopt
    from solvers.result import Status

    g = crossing_game(offset=0.3)
    p = g.default_params()
    u0 = g.join_controls([np.tile([1.0, 0.0], (g.K, 1)) for _ in range(g.N)])
    sol = solve_ipopt(g, p, u0)
    assert sol.status is Status.CONVERGED
    coll = next(t.index for t in g.terms if t.feature_type == "collision")
    assert float(g.function("term_energies")(sol.controls, p)[coll]) > 1e-3
    return g, p, u0, sol


@dataclass(frozen=True)
class LinearJoint(JointDynamics):
    """``x_{k+1} = A x_k + B u_k`` over the members' stacked states and controls (4 states
    per member, in member order)."""

    name = "linear_joint"
    A: tuple = ()
    B: tuple = ()

    def step(self, xs, us, dt):
        x = ca.mtimes(ca.DM(self.A), ca.vertcat(*xs)) + ca.mtimes(ca.DM(self.B), ca.vertcat(*us))
        return [x[4 * j : 4 * j + 4] for j in range(len(xs))]


#: left-turn world options: a bold oncoming driver (aggressiveness 0.8..1, time margin down
#: to -2 s: it takes its right of way) that is slow (0.5..1.5 m/s) 8..12 m before the zone
#: when the ego, 7..9 m before it at about 5 m/s, observes it, and then accelerates late
LATE_ACCELERATOR = dict(
    aggressiveness=(0.8, 1.0),
    margin=(2.0, -2.0),
    ego_distance=(7.0, 9.0),
    ego_speed=(4.5, 5.5),
    other_distance=(8.0, 12.0),
    other_speed=(0.5, 1.5),
)


def _family_features(dynamics: str, jerk: bool) -> list:
    feats = [
        Goal(weight=3.0),
        Velocity(weight=0.5),
        Acceleration(),
        TurnRate(),
        VelocityBound(lower=0.0, upper=2.5, weight=5.0),
        AccelerationBound(lower=-3.0, upper=3.0, weight=5.0),
    ]
    if jerk:
        feats.append(Jerk(weight=0.05))
    return feats


def family_spec(
    layout: str,
    N: int,
    dynamics: str = "unicycle",
    collision_weight: float = 10.0,
    seed: int = 0,
    K: int = 25,
    jerk: bool = False,
) -> GameSpec:
    """One seeded game of a family beyond the shipped examples (tests/test_defaults.py).

    ``layout``: ``"crossing"`` (``N`` agents on a circle of radius 2 m, each to the opposite
    side), ``"intersection"`` (agents from the four arms of a crossroads, in turn W, S, E, N,
    2 m out, a second round 1.2 m further back, going straight across) or ``"merge"`` (pairs
    2 m apart along ``x``: one in the lane ``y = 0``, one on a ramp 1 m to the right heading
    into it). Every agent starts at 1.5 m/s. Starts and goals
    get a seeded jitter of up to 0.2 m (0.3 m sideways on goals), so no layout is exactly
    symmetric. ``dynamics``: ``"unicycle"`` or ``"bicycle"`` (wheelbase 0.5 m, radius 0.3 m).
    Every straight-line start brings some pair inside the collision distance.
    """
    rng = np.random.default_rng(seed)
    radius = 0.3 if dynamics == "bicycle" else 0.25
    dyn = {"type": "bicycle", "wheelbase": 0.5} if dynamics == "bicycle" else "unicycle"
    v0 = 1.5
    starts, goals = [], []
    for i in range(N):
        j = rng.uniform(-0.2, 0.2, size=2)
        side = rng.uniform(-0.3, 0.3)
        if layout == "crossing":
            ang = 2 * np.pi * i / N
            c, s = np.cos(ang), np.sin(ang)
            starts.append([2 * c + j[0], 2 * s + j[1], v0, ang + np.pi])
            goals.append([-2 * c - side * s, -2 * s + side * c])
        elif layout == "intersection":
            ang = np.pi * (i % 4) / 2
            back = 2.0 + 1.2 * (i // 4)
            c, s = np.cos(ang), np.sin(ang)
            lane = 0.15  # right of the arm's centre line
            starts.append([-back * c + lane * s + j[0], -back * s - lane * c + j[1], v0, ang])
            goals.append([2.5 * c + (lane + side) * s, 2.5 * s - (lane + side) * c])
        elif layout == "merge":
            x = -3.0 + 2.0 * (i // 2) + j[0]
            if i % 2:  # on the ramp, heading into the main lane y = 0
                starts.append([x, -1.0 + j[1], v0, float(np.arctan2(1.0, 3.0))])
            else:
                starts.append([x, 0.0, v0, 0.0])
            goals.append([x + 4.5 + side, 0.0])
        else:
            raise ValueError(f"unknown layout {layout!r}")
    agents = [
        AgentSpec(
            f"a{i}",
            dyn,
            _family_features(dynamics, jerk),
            radius=radius,
            x0=starts[i],
            goal=goals[i],
        )
        for i in range(N)
    ]
    return GameSpec(agents, [Collision(weight=collision_weight)], horizon=K, dt=0.1)


#: The family swept by tests/test_defaults.py: (layout, N, dynamics, collision weight, seed,
#: jerk). N = 2..6, unicycles and bicycles, collision weights 1..100, three layouts.
FAMILY = (
    ("crossing", 2, "unicycle", 1.0, 0, False),
    ("crossing", 3, "bicycle", 10.0, 1, False),
    ("crossing", 6, "unicycle", 100.0, 2, False),
    ("intersection", 4, "unicycle", 30.0, 3, False),
    ("intersection", 5, "bicycle", 3.0, 4, False),
    ("merge", 2, "bicycle", 20.0, 5, True),
    ("merge", 4, "unicycle", 50.0, 6, True),
    ("crossing", 2, "bicycle", 100.0, 7, False),
)


def cli(capsys, *args) -> tuple[int, str, str]:
    """``epo ARGS`` in-process: exit status, stdout, stderr."""
    from scenarios.cli import main

    rc = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def one_error_line(rc: int, err: str, *words: str) -> str:
    """Exit 2, one ``error:`` line on stderr that contains ``words``, no traceback."""
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("error: "), (rc, err)
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def proc_children(pid: int) -> list[int]:
    """Live (not zombie) child processes of ``pid``, read from ``/proc`` (Linux)."""
    from pathlib import Path

    out = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                stat = (p / "stat").read_text()
            except OSError:
                continue
            state, ppid = stat[stat.rindex(")") + 2 :].split()[:2]
            if int(ppid) == pid and state != "Z":
                out.append(int(p.name))
    return out


def proc_alive(pid: int) -> bool:
    """Whether ``pid`` runs (exists and is not a zombie), read from ``/proc`` (Linux)."""
    from pathlib import Path

    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2] != "Z"


def process_family(pid: int) -> set[int]:
    """The live children and grandchildren of ``pid`` (a pool's workers and their helpers)."""
    family = set(proc_children(pid))
    for c in list(family):
        family |= set(proc_children(c))
    return family


def survivors(family, wait: float = 10.0) -> list[int]:
    """The processes of ``family`` still alive after up to ``wait`` seconds; each is then
    killed (SIGKILL), so a failing test leaves none behind."""
    import os
    import signal
    import time

    t0 = time.monotonic()
    while any(proc_alive(c) for c in family) and time.monotonic() - t0 < wait:
        time.sleep(0.05)
    alive = [c for c in family if proc_alive(c)]
    for c in alive:
        os.kill(c, signal.SIGKILL)
    return alive
