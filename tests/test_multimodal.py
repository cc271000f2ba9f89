"""Multi-modal solves (solvers.multimodal): modes of a symmetric crossing, filters, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from epo_casadi import SpecError
from solvers.multimodal import (
    MultiModalOptions,
    passing_sides,
    sinusoid_sampler,
    solve_multimodal,
    trajectory_distances,
)
from solvers.result import Status

from .helpers import crossing_game

N_SAMPLES = 32


@pytest.fixture(scope="module")
def head_on():
    """Two unicycles head-on on the x axis, goals mirrored: passing left or right is equally
    good (the game is symmetric under y -> -y), and the sampler is symmetric too."""
    g = crossing_game(N=2, K=40, offset=0.0)
    p = g.default_params()
    return g, p, solve_multimodal(g, p, n_samples=N_SAMPLES, seed=0)


def mirror(pos):
    out = pos.copy()
    out[..., 1] *= -1
    return out


def test_symmetric_crossing_has_two_equal_modes(head_on):
    g, p, res = head_on
    assert res.kept.all() and len(res.modes) == 2
    a, b = res.modes
    # each share is Binomial(32, 1/2) / 32 by symmetry (std 0.09): near 0.5
    assert a.share + b.share == pytest.approx(1.0)
    assert abs(a.share - 0.5) <= 0.2 and a.share >= b.share
    # opposite passing sides, by the swept angle of the relative position (about +-pi)
    assert a.passing == (-b.passing[0],) and a.passing[0] != 0
    assert passing_sides(g, a.states)[0] == a.passing[0]
    # the two representatives are mirror images with equal costs (converged to 1e-5)
    pa, pb = g.positions(a.states), g.positions(b.states)
    np.testing.assert_allclose(pa, mirror(pb), atol=1e-5)  # measured 7e-7
    np.testing.assert_allclose(a.cost, b.cost, rtol=1e-6)  # measured 1.4e-7
    # the modes are far apart, the members of a mode close together
    D = trajectory_distances(g, res.results.states)
    within = max(D[np.ix_(m.members, m.members)].max() for m in res.modes)
    across = D[np.ix_(a.members, b.members)].min()
    assert within < 0.01 < 0.3 < across
    # labels and members agree; the medoid is a member and its own solve
    for m_idx, m in enumerate(res.modes):
        assert set(np.nonzero(res.labels == m_idx)[0]) == set(m.members) and m.medoid in m.members
        np.testing.assert_array_equal(m.controls, res.results.controls[m.medoid])
        assert res.results[m.medoid].status is Status.CONVERGED


def test_passing_clustering_agrees(head_on):
    g, p, res = head_on
    by_side = solve_multimodal(g, p, n_samples=N_SAMPLES, seed=0, clustering={"cluster": "passing"})
    np.testing.assert_array_equal(by_side.labels, res.labels)
    assert [m.share for m in by_side.modes] == [m.share for m in res.modes]


def test_deterministic_for_a_seed(head_on):
    g, p, res = head_on
    again = solve_multimodal(g, p, n_samples=N_SAMPLES, seed=0)
    np.testing.assert_array_equal(again.initial_controls, res.initial_controls)
    np.testing.assert_array_equal(again.labels, res.labels)
    for m, n in zip(again.modes, res.modes, strict=True):
        np.testing.assert_array_equal(m.controls, n.controls)
        assert m.share == n.share and m.medoid == n.medoid
    other = sinusoid_sampler(g, p, N_SAMPLES, np.random.default_rng(1))
    assert not np.allclose(other, res.initial_controls)


def test_sampler_shape_and_amplitudes(head_on):
    g, p, res = head_on
    U = res.initial_controls
    assert U.shape == (N_SAMPLES, g.n_u)
    for u in g.split_controls(U):  # (B, K, 2): acceleration, turn rate
        c = np.cos(np.arange(g.K) * np.pi / g.K)
        acc_amp = u[:, 0, 0] / -0.05  # c_0 = 1: the drawn amplitudes
        turn_amp = u[:, 0, 1]
        np.testing.assert_allclose(u[:, :, 0], acc_amp[:, None] * -0.05 * c[None])
        np.testing.assert_allclose(u[:, :, 1], turn_amp[:, None] * c[None])
        assert np.all((acc_amp >= 1.5) & (acc_amp <= 2.5))
        assert np.all(np.abs(turn_amp) <= np.deg2rad(15.0))
        assert (turn_amp > 0).any() and (turn_amp < 0).any()


def test_lm_variant_finds_the_same_modes(head_on):
    g, p, res = head_on
    lm = solve_multimodal(g, p, n_samples=8, seed=0, solver="lm")
    assert lm.info["solver"] == "lm" and lm.results.solver == "lm" and lm.kept.all()
    assert sorted(m.passing for m in lm.modes) == [(-1,), (1,)]


def test_colliding_solves_are_dropped():
    """Without the collision term the agents drive through each other: every solve is
    dropped by the clearance filter and no mode is left."""
    g = crossing_game(N=2, K=40, offset=0.0)
    p = g.params.pack({"w.a0-a1.collision": 0.0})
    res = solve_multimodal(g, p, n_samples=4, seed=0)
    assert res.info["dropped_collision"] == 4 and res.modes == [] and (res.labels == -1).all()
    assert np.all(res.info["clearance"] < -0.05)


def test_inputs_are_checked(head_on):
    g, p, _ = head_on
    with pytest.raises(SpecError, match="solver"):
        solve_multimodal(g, p, n_samples=2, solver="ipopt")
    with pytest.raises(SpecError, match="n_samples"):
        solve_multimodal(g, p, n_samples=0)
    with pytest.raises(SpecError, match="multimodal: unknown option"):
        solve_multimodal(g, p, n_samples=2, clustering={"tol": 1})
    with pytest.raises(SpecError, match="multimodal.cluster"):
        MultiModalOptions(cluster="kmeans")
    with pytest.raises(SpecError, match="sampler"):
        solve_multimodal(g, p, n_samples=2, sampler=lambda game, p, n, rng: np.zeros((n, 3)))


@pytest.fixture(scope="module")
def cut_short():
    """Eight LM solves of the head-on game cut at 17 steps: those that need more steps
    (20, 33, 19, 25, 19 when run to convergence) stop at max_iter, three converge."""
    from solvers.lm import LMOptions

    g = crossing_game(N=2, K=40, offset=0.0)
    p = g.default_params()
    full = solve_multimodal(g, p, n_samples=8, seed=0, solver="lm")
    assert (full.results.status == Status.CONVERGED).all()
    need = full.results.iterations
    run = {
        accept: solve_multimodal(
            g,
            p,
            n_samples=8,
            seed=0,
            solver="lm",
            options=LMOptions(steps=17),
            clustering={"accept_max_iter": accept},
        )
        for accept in (False, True)
    }
    return g, need, run


def test_max_iter_solves_are_dropped_unless_accepted(cut_short):
    g, need, run = cut_short
    short = need > 17
    assert 0 < short.sum() < short.size  # the regime: some, not all, solves are cut short
    res = run[False]
    status = np.asarray(res.results.status)
    assert list(status == Status.MAX_ITER) == list(short)  # real max_iter stops, not faked
    assert (res.results.iterations[short] == 17).all()
    np.testing.assert_array_equal(res.kept, ~short)
    np.testing.assert_array_equal(res.labels[short], -1)
    assert res.info["dropped_failed"] == short.sum() and res.info["dropped_collision"] == 0
    assert sum(len(m.members) for m in res.modes) == (~short).sum()
    assert sum(m.share for m in res.modes) == pytest.approx(1.0)
    for m in res.modes:
        assert not short[m.members].any() and status[m.medoid] is Status.CONVERGED
    # accepting max_iter keeps every solve (none collides) and the same solves
    acc = run[True]
    assert acc.kept.all() and (acc.labels >= 0).all() and acc.info["dropped_failed"] == 0
    np.testing.assert_array_equal(acc.results.controls, res.results.controls)
    assert sum(len(m.members) for m in acc.modes) == short.size
    assert any(short[m.members].any() for m in acc.modes)
    assert sorted(m.passing for m in acc.modes) == [(-1,), (1,)]


def _circling_states(g, angles, radius=1.0):
    """Joint states (agent-major, (x, y, v, theta) per step) where agent 1 moves on a circle
    around agent 0 (at the origin) through ``angles`` (K+1 values)."""
    K1 = g.K + 1
    a = np.zeros((K1, 4))
    b = np.zeros((K1, 4))
    b[:, 0], b[:, 1] = radius * np.cos(angles), radius * np.sin(angles)
    return np.concatenate([a.ravel(), b.ravel()])


def test_swept_angles_and_passing_sides_by_hand():
    from solvers.multimodal import swept_angles

    g = crossing_game(N=2, K=12)
    turn = np.linspace(0.2, 0.2 + 1.5 * np.pi, g.K + 1)  # 3/4 of a turn, counter-clockwise
    X = np.stack([_circling_states(g, turn), _circling_states(g, turn[::-1])])
    np.testing.assert_allclose(swept_angles(g, X)[:, 0], [1.5 * np.pi, -1.5 * np.pi], rtol=1e-12)
    assert passing_sides(g, X).tolist() == [[1], [-1]]
    small = _circling_states(g, np.linspace(0.0, 0.3, g.K + 1))
    assert passing_sides(g, small[None]).tolist() == [[0]]  # |0.3| < pass_angle 0.5
    # exactly at the threshold it counts as a pass ("0 when |angle| < pass_angle")
    at = float(swept_angles(g, small[None])[0, 0])
    assert passing_sides(g, small[None], pass_angle=at).tolist() == [[1]]
    assert passing_sides(g, small[None], pass_angle=np.nextafter(at, 1.0)).tolist() == [[0]]


def test_sampler_for_double_integrators():
    """Longitudinal along the initial velocity (x axis at rest), lateral across it."""
    from epo_casadi import AgentSpec, GameSpec, Goal, PotentialGame

    K = 10
    agents = [
        AgentSpec("mv", "double_integrator", [Goal()], x0=[0, 0, 0.6, 0.8], goal=[1, 1]),
        AgentSpec("rest", "double_integrator", [Goal()], x0=[2, 0, 0.0, 0.0], goal=[0, 1]),
    ]
    g = PotentialGame(GameSpec(agents, horizon=K, dt=0.1))
    U = sinusoid_sampler(g, g.default_params(), 16, np.random.default_rng(0))
    c = np.cos(np.arange(K) * np.pi / K)
    lat_seen = []
    for u, e in zip(g.split_controls(U), ([0.6, 0.8], [1.0, 0.0]), strict=True):  # (16, K, 2)
        e = np.array(e)
        n = np.array([-e[1], e[0]])
        lon, lat = u @ e, u @ n
        A = lon[:, 0] / -0.05  # c_0 = 1
        L = lat[:, 0] / 0.5
        np.testing.assert_allclose(lon, -0.05 * A[:, None] * c[None], atol=1e-15)
        np.testing.assert_allclose(lat, 0.5 * L[:, None] * c[None], atol=1e-15)
        assert np.all((A >= 1.5) & (A <= 2.5)) and np.all(np.abs(L) <= 1.0)
        lat_seen.append(L)
    assert np.ptp(np.concatenate(lat_seen)) > 0.5  # lateral draws really vary


def test_custom_costs_need_ilq(head_on):
    g, p, _ = head_on
    with pytest.raises(SpecError, match="costs"):
        solve_multimodal(g, p, n_samples=2, solver="lm", costs=g.function("agent_costs"))


# --------------------------------------------------------------------------------------
# clustering: scikit-learn's DBSCAN against the rules it replaces
# --------------------------------------------------------------------------------------
def _dbscan_loop(D, eps, min_points):
    """DBSCAN written out (the toolkit's own loop before scikit-learn): core points have at
    least ``min_points`` points (themselves included) at ``D < eps``; clusters grow from the
    first unlabelled core point in index order; a border point keeps the first cluster."""
    n = D.shape[0]
    labels = np.full(n, -1, dtype=int)
    near = D < eps
    core = near.sum(axis=1) >= min_points
    c = 0
    for i in range(n):
        if not core[i] or labels[i] >= 0:
            continue
        labels[i] = c
        stack = [i]
        while stack:
            j = stack.pop()
            for q in np.nonzero(near[j] & (labels < 0))[0]:
                labels[q] = c
                if core[q]:
                    stack.append(int(q))
        c += 1
    return labels


def _components(D, tol):
    """Connected components of the graph ``D <= tol`` (breadth first), numbered by their
    smallest member."""
    n = D.shape[0]
    lab = np.full(n, -1, dtype=int)
    c = 0
    for i in range(n):
        if lab[i] >= 0:
            continue
        lab[i], todo = c, [i]
        while todo:
            j = todo.pop()
            for q in np.nonzero((D[j] <= tol) & (lab < 0))[0]:
                lab[q] = c
                todo.append(int(q))
        c += 1
    return lab


def _canonical(labels):
    """Labels renumbered by first appearance (noise stays -1): equal for equal partitions."""
    out, seen = np.full(len(labels), -1), {}
    for i, v in enumerate(labels):
        if v >= 0:
            out[i] = seen.setdefault(int(v), len(seen))
    return out


def _sq_state_distances(S):
    sq = np.sum(S**2, axis=1)
    D = np.maximum(sq[:, None] + sq[None, :] - 2 * S @ S.T, 0.0)
    np.fill_diagonal(D, 0.0)
    return D


def _point_sets():
    rng = np.random.default_rng(0)
    P = rng.normal(0, 1, (40, 2)) + np.repeat([[0, 0], [6, 0], [3, 5]], [15, 15, 10], axis=0)
    yield np.sum((P[:, None] - P[None]) ** 2, axis=-1)
    grid = np.arange(12.0)  # distances exactly on eps (ties): 1, 2, ... apart
    yield np.abs(grid[:, None] - grid[None])


def test_dbscan_is_the_written_out_rule(head_on):
    from solvers.multimodal import dbscan

    g, p, res = head_on
    sets = list(_point_sets())
    sets.append(_sq_state_distances(res.results.states))  # the Peters clustering's distance
    sets.append(trajectory_distances(g, res.results.states))
    for D in sets:
        scale = np.median(D[D > 0])
        for eps in (0.0, 1.0, 2.0, 0.3 * scale, scale, 3.0 * scale, np.inf):
            for k in (1, 2, 3, 5):
                got = dbscan(D, eps, k)
                np.testing.assert_array_equal(got, _dbscan_loop(D, eps, k))  # numbering too
    # on the solved set (modes 0.3 m apart, members within 0.01 m) DBSCAN finds the modes
    D = trajectory_distances(g, res.results.states)
    np.testing.assert_array_equal(_canonical(dbscan(D, 0.3, 2)), _canonical(res.labels))
    with pytest.raises(SpecError, match="min_points"):
        dbscan(D, 1.0, 0)


def test_single_linkage_is_dbscan_with_one_point(head_on):
    """The single-linkage dendrogram cut at ``tol`` (scipy, cophenetic distance <= tol) is
    the connected components of ``D <= tol``, which is DBSCAN with ``min_points = 1`` and
    ``eps`` just above ``tol`` (``D < eps``): the same partition, ties at ``tol`` included."""
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    from solvers.multimodal import _agglomerate, dbscan

    g, p, res = head_on
    sets = [*_point_sets(), trajectory_distances(g, res.results.states)]
    for D in sets:
        Z = linkage(squareform(D, checks=False), method="single")
        for tol in (0.5, 1.0, 2.0, 3.0, float(np.median(D))):
            want = _canonical(fcluster(Z, t=tol, criterion="distance"))
            np.testing.assert_array_equal(_canonical(_agglomerate(D, tol, "single")), want)
            np.testing.assert_array_equal(_canonical(_components(D, tol)), want)
            just_above = np.nextafter(tol, np.inf)
            np.testing.assert_array_equal(_canonical(dbscan(D, just_above, 1)), want)
    # solve_multimodal with single linkage: the same modes as the default average linkage
    # on this well separated set
    single = solve_multimodal(g, p, n_samples=N_SAMPLES, seed=0, clustering={"linkage": "single"})
    np.testing.assert_array_equal(single.labels, res.labels)


def test_clustering_library_is_imported_on_use_only():
    import subprocess
    import sys

    code = (
        "import sys, solvers, solvers.multimodal, scenarios.rpi_peters\n"
        "print('sklearn' in sys.modules)\n"
        "solvers.multimodal.dbscan([[0.0]], 1.0, 1)\n"
        "print('sklearn' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-2:] == ["False", "True"]
