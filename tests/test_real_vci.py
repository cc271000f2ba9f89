"""Vehicle-crowd clips in the CITR layout (scenarios/real/vci.py): the reader against the csv
module, the resampling against hand-computed interpolations, gaps, --fps, both folder
layouts, several and no vehicles, padding and the interaction rule, the split by clip,
malformed files at the CLI, the shipped CITR clips (when ../shared/realdata is present) and
one training step of V-LSTM, SC and ours."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from epo_casadi.errors import SpecError
from scenarios.dataset import SPLITS, DatasetError, load_split, read_manifest
from scenarios.real.vci import (
    PED_SUFFIX,
    VEH_SUFFIX,
    VciRecipe,
    VciScenario,
    clip_tracks,
    experiment_type,
    find_clips,
    game_from_recipe,
    read_vci_pedestrians,
    read_vci_vehicles,
)
from tests.helpers import cli, one_error_line

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "citr"
PED_HEAD = "id,frame,label,x_est,y_est,vx_est,vy_est"
VEH_HEAD = "id,frame,label,x_est,y_est,psi_est,vel_est"
#: a short window for the small clips: 2 observed steps, 3 predicted
SMALL = ["--set", "history=2", "--set", "horizon=3", "--set", "modes=2"]


def _rows(tracks: dict[int, np.ndarray], label: str) -> list[str]:
    """CSV rows of ``{id: (n, 5) [frame, x, y, a, b]}``."""
    out = []
    for i, a in tracks.items():
        for f, x, y, p, q in np.asarray(a, float):
            out.append(f"{i},{int(f)},{label},{float(x)!r},{float(y)!r},{float(p)!r},{float(q)!r}")
    return out


def write_clip(folder: Path, name: str, peds: dict, vehs: dict | None = None) -> Path:
    """``<name>_traj_ped_filtered.csv`` (and ``_veh_`` when ``vehs``) in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}{PED_SUFFIX}").write_text("\n".join([PED_HEAD, *_rows(peds, "ped")]) + "\n")
    if vehs is not None:
        (folder / f"{name}{VEH_SUFFIX}").write_text(
            "\n".join([VEH_HEAD, *_rows(vehs, "veh")]) + "\n"
        )
    return folder


def line_track(frames, p0, v, fps):
    """A pedestrian at constant velocity ``v`` from ``p0`` at frame ``frames[0]``: rows
    ``[frame, x, y, vx, vy]``."""
    f = np.asarray(frames, float)
    t = (f - f[0])[:, None] / fps
    xy = np.asarray(p0, float) + t * np.asarray(v, float)
    return np.column_stack([f, xy, np.tile(v, (len(f), 1))])


def cart(frames, p0, speed, fps, heading=0.0):
    """A vehicle at constant ``speed`` and ``heading``: rows ``[frame, x, y, psi, vel]``."""
    f = np.asarray(frames, float)
    t = (f - f[0]) / fps
    d = np.array([math.cos(heading), math.sin(heading)])
    xy = np.asarray(p0, float) + t[:, None] * speed * d
    return np.column_stack([f, xy, np.full(len(f), heading), np.full(len(f), speed)])


def crowd(rng, frames, fps, n_peds, vehicles=1):
    """A vehicle (or several) driving +x through ``n_peds`` pedestrians crossing its path."""
    peds = {
        int(i): line_track(
            frames, [rng.uniform(2, 12), rng.uniform(-4, 4)], rng.uniform(-1.2, 1.2, 2), fps
        )
        for i in rng.choice(np.arange(1, 50), n_peds, replace=False)
    }
    vehs = {v + 1: cart(frames, [-3.0 * v, 0.5 * v], 2.0 + 0.3 * v, fps) for v in range(vehicles)}
    return peds, vehs


def generate(capsys, raw, out, *extra):
    rc, _, err = cli(
        capsys,
        "generate",
        "vci",
        "--raw",
        raw,
        "--out",
        out,
        "--workers",
        1,
        "--no-progress",
        *extra,
    )
    assert rc == 0, err
    return {s: load_split(out, s) for s in SPLITS}, read_manifest(out)


def all_samples(data):
    keys = data["train"].keys()
    return {k: np.concatenate([data[s][k] for s in SPLITS]) for k in keys}


# ---- the reader --------------------------------------------------------------------------
def test_reader_against_the_csv_module(tmp_path):
    f = tmp_path / f"c{PED_SUFFIX}"
    # spaces in the header and the cells, rows out of order, an extra column, a blank line
    f.write_text(
        " id , frame ,label, x_est,y_est,vx_est,vy_est,extra\n"
        "2,11,ped,1.5,2.5,0.1,0.2,z\n"
        " 1 ,10,ped,-3.25,4,0,0.5,z\n"
        "\n"
        "2,10,ped,1.25,2.0,0.1,0.2,z\n"
    )
    r = read_vci_pedestrians(f)
    assert r["id"].tolist() == [1, 2, 2] and r["frame"].tolist() == [10, 10, 11]
    assert r["x"].tolist() == [-3.25, 1.25, 1.5] and r["vy"].tolist() == [0.5, 0.2, 0.2]
    assert r["line"].tolist() == [3, 5, 2]
    g = tmp_path / f"c{VEH_SUFFIX}"
    rows = [[1, 5, "veh", 0.5, -0.5, 3.0, 2.5], [1, 6, "veh", 0.75, -0.5, -3.0, 2.25]]
    with g.open("w", newline="") as h:
        csv.writer(h).writerows([VEH_HEAD.split(","), *rows])
    v = read_vci_vehicles(g)
    assert v["psi"].tolist() == [3.0, -3.0] and v["vel"].tolist() == [2.5, 2.25]
    assert v["x"].tolist() == [0.5, 0.75] and v["frame"].tolist() == [5, 6]


def test_resampling_by_hand():
    """fps 12.5, dt 0.2: a grid step is 2.5 frames, so every other step lies between two rows."""
    f = np.arange(100, 110)
    ped = {"id": np.ones(10, np.int64), "frame": f, "x": (f - 100.0) ** 2, "y": 2.0 * (f - 100)}
    ped |= {"vx": f - 100.0, "vy": np.ones(10)}
    # the vehicle (same id as the pedestrian) from frame 101, its heading through +-pi
    fv = f[1:]
    psi = math.pi - 0.12 + 0.05 * (fv - 100)
    veh = {"id": np.ones(9, np.int64), "frame": fv, "x": 10.0 + (fv - 100), "y": -np.ones(9)}
    veh |= {"psi": np.angle(np.exp(1j * psi)), "vel": 1 + 0.1 * (fv - 100)}
    assert veh["psi"][2] < 0  # recorded wrapped: pi + 0.03 is written -pi + 0.03
    tracks, f0 = clip_tracks(ped, veh, fps=12.5, dt=0.2, vehicle_length=2.2, vehicle_width=1.2)
    assert f0 == 100
    p, c = tracks
    assert (p.id, p.kind, c.id, c.kind) == (2, 0, 3, 1)  # ids 2 id + kind: the files never meet
    u = np.array([0.0, 2.5, 5.0, 7.5])  # frames after f0 of grid steps 0..3
    assert p.frames.tolist() == [0, 1, 2, 3]
    assert np.allclose(p.xy[:, 0], [0.0, (4 + 9) / 2, 25.0, (49 + 64) / 2])
    assert np.allclose(p.xy[:, 1], 2 * u)
    assert np.allclose(p.speed, np.hypot(u, 1.0)) and np.allclose(p.heading, np.arctan2(1.0, u))
    assert (p.length, p.width) == (0.0, 0.0) and (c.length, c.width) == (2.2, 1.2)
    # the vehicle starts at frame 101: its first grid step is 1 (frame 102.5)
    assert c.frames.tolist() == [1, 2, 3]
    assert np.allclose(c.xy, np.column_stack([10 + u[1:], -np.ones(3)]))
    assert np.allclose(c.speed, 1 + 0.1 * u[1:])
    # unwrapped before interpolating: pi + 0.005 at 102.5, not the mean of pi - 0.02 and -pi + 0.03
    assert np.allclose(c.heading, math.pi - 0.12 + 0.05 * u[1:])


def test_fps_changes_the_times(tmp_path, capsys):
    frames = np.arange(30, 70)
    x = 0.01 * (frames - 30.0) ** 2
    veh = {1: np.column_stack([frames, x, np.zeros(40), np.zeros(40), np.ones(40)])}
    ped = {4: line_track(frames, [5.0, 1.0], [-1.0, 0.0], 10.0)}
    raw = write_clip(tmp_path / "raw" / "t", "clip_01", ped, veh)
    want = {  # fps: (frames per step, first time, first frame, first vehicle x, samples)
        10.0: (2.0, 3.4, 34, 0.16, 20 - 5),  # 0.2 s is 2 frames: steps at frames 30, 32, ...
        12.0: (2.4, 2.9, 35, 0.16 + 0.8 * 0.09, 17 - 5),  # 2.4 frames: step 2 at 34.8
    }
    for fps, (step, t, fr, x0, n) in want.items():
        d, m = generate(capsys, raw.parent, tmp_path / f"out{fps}", "--fps", fps, *SMALL)
        s = d["train"]
        assert m["recipe"]["fps"] == fps and m["meta"]["frames_per_step"] == pytest.approx(step)
        assert len(s["time"]) == n
        assert s["time"][0] == pytest.approx(t) and s["frame"][0] == fr
        assert np.allclose(np.diff(s["time"]), 0.2)
        assert s["origin"][0] == pytest.approx([x0, 0.0])
        # the future of the vehicle: x at frames 30 + (3 + j) * step, relative to the origin
        u = 30 + (3 + np.arange(3)) * step
        assert np.allclose(s["future"][0, 0, 0, :, 0], np.interp(u, frames, x) - x0)
    rc, _, err = cli(capsys, "generate", "vci", "--raw", raw, "--out", tmp_path / "o", "--fps", 5,
                     "--set", "fps=5")  # fmt: skip
    one_error_line(rc, err, "--set fps", "--fps")


def test_gaps_split_tracks(tmp_path, capsys):
    """No window spans a gap; a pedestrian with a gap is left out of the windows across it."""
    f = np.arange(0, 41)
    fv = f[(f < 20) | (f > 21)]  # frames 20 and 21 missing
    veh = {1: cart(fv, [0.0, 0.0], 2.0, 10.0)}
    veh[1][:, 1] = fv * 0.2  # x at 2 m/s from frame 0
    fp = f[(f < 10) | (f > 11)]
    peds = {
        1: line_track(f, [3.0, 2.0], [0.0, -0.5], 10.0),
        2: line_track(fp, [4.0, -2.0], [0.0, 0.5], 10.0),
    }
    raw = write_clip(tmp_path / "raw", "gap_01", peds, veh)
    d, _ = generate(capsys, raw, tmp_path / "o", "--fps", 10, "--agents", 3, *SMALL)
    s = all_samples(d)
    # runs: vehicle frames 0..19 (steps 0..9) and 22..40 (11..20); current steps 2..6, 13..17
    assert s["frame"].tolist() == [4, 6, 8, 10, 12, 26, 28, 30, 32, 34]
    # pedestrian 2: steps 0..4 and 6..20: in the windows from current step 8 on
    has2 = (s["track_id"] == 2).any(axis=1)
    assert has2.tolist() == [False] * 5 + [True] * 5
    assert (s["agents_mask"].sum(1) == np.where(has2, 3, 2)).all()
    # positions are the recorded ones: the vehicle at 2 m/s along x, 0.4 m a step
    assert np.allclose(s["history"][:, :, 0, 0], [[-0.8, -0.4, 0.0]] * 10)
    assert np.allclose(s["origin"][:, 0], 0.2 * s["frame"])
    # a tolerance of 3 frames joins the runs: windows at every current step 2..17
    d, _ = generate(capsys, raw, tmp_path / "o3", "--fps", 10, "--agents", 3, *SMALL,
                    "--set", "max_frame_gap=3")  # fmt: skip
    s = all_samples(d)
    assert s["frame"].tolist() == list(range(4, 36, 2)) and (s["agents_mask"].sum(1) == 3).all()


def test_both_layouts_and_the_experiment_types(tmp_path, capsys):
    rng = np.random.default_rng(3)
    frames = np.arange(5, 60)
    clips = {}
    for folder, name in (
        ("vci_back", "back_interaction_01"),
        ("vci_back", "back_interaction_02"),
        ("vci_lat_uni", "unidirection_yeild_01"),
        ("crossing", "crossing_03"),
    ):
        clips[(folder, name)] = crowd(rng, frames, 29.97, 4)
    for (folder, name), (p, v) in clips.items():
        write_clip(tmp_path / "by_type" / "sub" / folder, name, p, v)
        write_clip(tmp_path / "flat", name, p, v)
    write_clip(
        tmp_path / "flat", "unidirection_no_vehicle_02", clips[("crossing", "crossing_03")][0]
    )
    by_type = find_clips(tmp_path / "by_type")
    flat = find_clips(tmp_path / "flat")
    assert [c[1] for c in by_type] == ["crossing", "vci_back", "vci_back", "vci_lat_uni"]
    assert by_type[0][0] == "sub/crossing/crossing_03"
    assert {c[0]: c[1] for c in flat} == {
        "back_interaction_01": "vci_back",
        "back_interaction_02": "vci_back",
        "crossing_03": "crossing",
        "unidirection_no_vehicle_02": "p2p_uni",
        "unidirection_yeild_01": "vci_lat_uni",
    }
    assert [c[2] for c in flat] == [True, True, True, False, True]
    assert experiment_type("a/b/vci_front/x_01") == "vci_front" and experiment_type("x") == "x"
    # the same clips give the same samples in both layouts
    a, ma = generate(capsys, tmp_path / "by_type", tmp_path / "a", *SMALL)
    b, mb = generate(capsys, tmp_path / "flat", tmp_path / "b", *SMALL)
    sa, sb = all_samples(a), all_samples(b)
    ka = np.lexsort((sa["frame"], [ma["meta"]["clips"][c].split("/")[-1] for c in sa["clip"]]))
    kb = np.lexsort((sb["frame"], [mb["meta"]["clips"][c].split("/")[-1] for c in sb["clip"]]))
    assert len(ka) == len(kb) > 0
    for k in ("history", "future", "track_id", "origin", "time", "agent_kind"):
        assert np.array_equal(sa[k][ka], sb[k][kb]), k
    assert mb["meta"]["experiment_types"] == ["crossing", "p2p_uni", "vci_back", "vci_lat_uni"]
    assert mb["meta"]["types_with_vehicle"] == ["crossing", "vci_back", "vci_lat_uni"]
    assert mb["recipe"]["clips"][3] == ["unidirection_no_vehicle_02", "p2p_uni", False]


def test_several_vehicles_and_a_clip_without_one(tmp_path, capsys):
    rng = np.random.default_rng(5)
    frames = np.arange(0, 40)
    peds, vehs = crowd(rng, frames, 10.0, 3, vehicles=2)
    raw = write_clip(tmp_path / "raw", "two_01", peds, vehs)
    write_clip(raw, "none_01", peds)
    sc = VciScenario.from_raw(raw, fps=10.0, history=2, horizon=3)
    assert [c[0] for c in sc.recipe.clips] == ["none_01", "two_01"]
    empty = sc.run_unit(0, None)
    assert all(len(v) == 0 for v in empty.values()) and set(empty) == set(sc.schema())
    s = sc.run_unit(1, None)
    # each vehicle is the focal agent of its own scenes (steps 2..16 of 20), once per step
    assert sorted(s["track_id"][:, 0].tolist()) == [1] * 15 + [2] * 15
    assert (s["agent_kind"][:, 0] == 1).all() and (s["agent_kind"][:, 1:] == 0).all()
    assert set(s["track_id"][:, 1:].ravel()) == set(peds)
    assert np.allclose(s["history"][:, -1, 0, :2], 0.0)  # the vehicle is the origin
    # with vehicle_candidates the other vehicle competes for the slots (it drives beside)
    sc2 = VciScenario.from_raw(raw, fps=10.0, history=2, horizon=3, vehicle_candidates=True)
    s2 = sc2.run_unit(1, None)
    other = np.where(s2["track_id"][:, 0] == 1, 2, 1)
    assert ((s2["track_id"][:, 1:] == other[:, None]) & (s2["agent_kind"][:, 1:] == 1)).any(1).all()
    # the vehicle ids of the file are the track ids (no offset) and the radii are per kind
    assert np.allclose(s2["radius"][s2["agent_kind"] == 1], 1.1)
    assert np.allclose(s2["radius"][s2["agent_kind"] == 0], 0.3)


def test_padding_and_the_interaction_rule(tmp_path, capsys):
    fps, frames = 10.0, np.arange(0, 30)
    veh = {7: cart(frames, [0.0, 0.0], 2.0, fps)}
    peds = {
        5: line_track(frames, [6.0, 0.5], [-1.0, 0.0], fps),  # head on: meets the cart
        3: line_track(frames, [0.0, 5.0], [2.0, 0.0], fps),  # beside it, 5 m away, same speed
        9: line_track(frames, [-20.0, 30.0], [0.0, 0.0], fps),  # far, standing
    }
    raw = write_clip(tmp_path / "raw", "pad_01", peds, veh)
    d, m = generate(capsys, raw, tmp_path / "o", "--fps", fps, "--agents", 5, *SMALL)
    s = d["train"]
    n = len(s["frame"])
    assert (
        n == 15 - 5 and s["history"].shape == (n, 3, 5, 4) and s["future"].shape == (n, 2, 5, 3, 4)
    )
    assert m["recipe"]["dt"] == 0.2 and m["meta"]["kinds"] == ["pedestrian", "vehicle"]
    assert (s["track_id"] == [7, 5, 3, 9, -1]).all()
    assert (s["agents_mask"] == [True, True, True, True, False]).all()
    assert (s["agent_kind"] == [1, 0, 0, 0, 0]).all()
    assert np.allclose(s["radius"], [1.1, 0.3, 0.3, 0.3, 0.0])
    # no length / width fields (pedestrians have no recorded size: circles of radius); the
    # cart's size is in the meta
    assert "length" not in s and "width" not in s and m["meta"]["focal_slot"] == 0
    assert m["meta"]["vehicle_size"] == {"length": 2.2, "width": 1.2}
    assert s["others"].shape == (n, 16, 6, 2) and np.isnan(s["others"]).all()  # all in scene
    assert not s["history"][:, :, 4].any() and not s["future"][:, :, 4].any()
    # pedestrian 5 in the scene frame: its recorded position minus the cart's; speed, heading
    t = s["time"]
    k = t[:, None] + 0.2 * np.arange(-2, 1)  # observed times
    assert np.allclose(s["history"][:, :, 1, 0], (6.0 - k) - 2.0 * t[:, None], atol=1e-5)
    assert np.allclose(s["history"][:, :, 1, 1], 0.5, atol=1e-6)
    assert np.allclose(s["history"][:, :, 1, 2], 1.0) and np.allclose(
        s["history"][:, :, 1, 3], math.pi
    )
    assert np.allclose(s["future"][:, 0, 0, :, 0], 0.4 * np.arange(1, 4), atol=1e-5)
    assert (s["future"][:, 1] == s["future"][:, 0]).all() and (
        s["mode_valid"] == [True, False]
    ).all()
    # N = 3: the two closest approaches (head on 0.5 m, beside 5 m) win over the far one
    d, _ = generate(capsys, raw, tmp_path / "o3", "--fps", fps, "--agents", 3, *SMALL)
    assert (d["train"]["track_id"] == [7, 5, 3]).all()
    # others (figures only): pedestrian 9, the one left out, standing at (-20, 30) over the
    # whole window, in the scene frame (the cart's current position subtracted); no more
    o, origin = d["train"]["others"], d["train"]["origin"]
    assert o.shape == (n, 16, 6, 2) and np.isnan(o[:, 1:]).all()
    assert np.allclose(o[:, 0], np.array([-20.0, 30.0]) - origin[:, None], atol=1e-4)
    d, _ = generate(
        capsys, raw, tmp_path / "o0", "--fps", fps, "--agents", 3, *SMALL,
        "--set", "context_agents=0",
    )  # fmt: skip
    assert "others" not in d["train"]


def test_split_by_clip_within_every_type(tmp_path):
    rng = np.random.default_rng(0)
    frames = np.arange(0, 30)
    raw = tmp_path / "raw"
    for typ, n in (("vci_a", 5), ("vci_b", 3), ("vci_c", 2)):
        for i in range(n):
            write_clip(raw / typ, f"{typ}_{i:02d}", *crowd(rng, frames, 10.0, 2))
    write_clip(raw / "vci_b", "vci_b_novehicle", crowd(rng, frames, 10.0, 2)[0])
    for i in range(2):
        write_clip(raw / "p2p", f"p2p_{i:02d}", crowd(rng, frames, 10.0, 2)[0])
    sc = VciScenario.from_raw(raw, fps=10.0)
    clips = sc.recipe.clips
    seen = set()
    for seed in range(8):
        sp = sc.split_units(seed)
        assert sp == sc.split_units(seed)  # deterministic
        units = [u for s in SPLITS for u in sp[s]]
        assert sorted(units) == list(range(len(clips)))  # disjoint and complete
        for s in SPLITS:
            types = sorted(clips[u][1] for u in sp[s] if clips[u][2])
            if s == "train":
                assert types == ["vci_a"] * 3 + ["vci_b"] + ["vci_c"] * 2
            else:
                assert types == ["vci_a", "vci_b"], (s, types)
        assert all(not clips[u][2] or clips[u][1] != "vci_c" for u in sp["val"] + sp["test"])
        assert all(clips[u][2] for u in sp["val"] + sp["test"])  # no-vehicle clips train
        seen.add(json.dumps(sp))
    assert len(seen) > 1  # the seed permutes the clips
    assert sc.meta()["train_only_types"] == ["vci_c"]
    # no validation share: val is empty and two clips of a type suffice
    sp = VciScenario.from_raw(raw, fps=10.0, val_fraction=0.0).split_units(0)
    assert sp["val"] == [] and sorted(clips[u][1] for u in sp["test"]) == [
        "vci_a",
        "vci_b",
        "vci_c",
    ]


# ---- malformed files at the command line ---------------------------------------------------
def _good(tmp_path) -> tuple[Path, Path, Path]:
    rng = np.random.default_rng(1)
    raw = write_clip(tmp_path / "raw", "bad_01", *crowd(rng, np.arange(0, 30), 10.0, 2))
    return raw, raw / f"bad_01{PED_SUFFIX}", raw / f"bad_01{VEH_SUFFIX}"


def _edit(f: Path, how: str) -> tuple[str, int]:
    """Spoil ``f``; the column and line the error must name."""
    lines = f.read_text().splitlines()
    head = lines[0].split(",")
    if how == "missing":
        j = head.index("vy_est")
        lines = [",".join(c for i, c in enumerate(ln.split(",")) if i != j) for ln in lines]
        f.write_text("\n".join(lines) + "\n")
        return "vy_est", 1
    if how in ("text", "nan"):
        cells = lines[6].split(",")
        col = "x_est" if how == "text" else "y_est"
        cells[head.index(col)] = "abc" if how == "text" else "nan"
        lines[6] = ",".join(cells)
        f.write_text("\n".join(lines) + "\n")
        return col, 7
    if how == "duplicate":
        lines.append(lines[3])
        f.write_text("\n".join(lines) + "\n")
        return "frame", len(lines)
    if how == "truncated":
        last = lines[-1]
        f.write_text("\n".join(lines[:-1]) + "\n" + last[: last.index(",", last.index(",") + 1)])
        return "x_est", len(lines)
    if how == "speed":
        cells = lines[2].split(",")
        cells[head.index("vel_est")] = "500"
        lines[2] = ",".join(cells)
        f.write_text("\n".join(lines) + "\n")
        return "vel_est", 3
    raise AssertionError(how)


@pytest.mark.parametrize(
    ("how", "which"),
    [
        ("missing", "ped"),
        ("text", "ped"),
        ("nan", "ped"),
        ("duplicate", "ped"),
        ("truncated", "ped"),
        ("nan", "veh"),
        ("truncated", "veh"),
        ("speed", "veh"),
    ],
)
def test_malformed_files_are_one_line(tmp_path, capsys, how, which):
    raw, ped, veh = _good(tmp_path)
    f = ped if which == "ped" else veh
    col, line = _edit(f, how)
    rc, _, err = cli(
        capsys, "generate", "vci", "--raw", raw, "--out", tmp_path / "o", "--no-progress"
    )
    one_error_line(rc, err, f"{f}:{col}", f"line {line}")
    assert not (tmp_path / "o").exists()  # refused before any work


def test_raw_folder_and_recipe_errors(tmp_path, capsys):
    rc, _, err = cli(
        capsys, "generate", "vci", "--raw", tmp_path / "nowhere", "--out", tmp_path / "o"
    )
    one_error_line(rc, err, "no such folder")
    (tmp_path / "empty").mkdir()
    rc, _, err = cli(
        capsys, "generate", "vci", "--raw", tmp_path / "empty", "--out", tmp_path / "o"
    )
    one_error_line(rc, err, "holds no clip")
    rng = np.random.default_rng(2)
    peds, vehs = crowd(rng, np.arange(0, 30), 10.0, 2)
    write_clip(tmp_path / "noveh", "a_01", peds)
    rc, _, err = cli(
        capsys, "generate", "vci", "--raw", tmp_path / "noveh", "--out", tmp_path / "o"
    )
    one_error_line(rc, err, "no clip has a vehicle file")
    lone = write_clip(tmp_path / "lone", "a_01", peds, vehs)
    (lone / f"a_01{PED_SUFFIX}").rename(lone / f"b_01{PED_SUFFIX}")
    rc, _, err = cli(capsys, "generate", "vci", "--raw", lone, "--out", tmp_path / "o")
    one_error_line(rc, err, f"a_01{VEH_SUFFIX}", "without its pedestrian file")
    good = write_clip(tmp_path / "good", "a_01", peds, vehs)
    rc, _, err = cli(capsys, "generate", "vci", "--raw", good, "--out", tmp_path / "o",
                     "--set", "vehicle_radius=0")  # fmt: skip
    one_error_line(rc, err, "vci.vehicle_radius")
    with pytest.raises(SpecError, match=r"vci\.clips\[0\]\[0\].*relative"):
        VciRecipe(clips=(("../x", "t", True),))
    with pytest.raises(SpecError, match=r"vci\.clips\[0\]\[2\]"):
        VciRecipe(clips=(("x", "t", "yes"),))
    with pytest.raises(SpecError, match=r"vci\.fps"):
        VciRecipe(fps=0.0)
    with pytest.raises(SpecError, match=r"vci\.clips.*no such clip"):
        VciScenario.from_raw(good, clips=["zz"])
    with pytest.raises(DatasetError, match="no rows"):
        f = tmp_path / f"h{PED_SUFFIX}"
        f.write_text(PED_HEAD + "\n")
        read_vci_pedestrians(f)


# ---- the game and one training step --------------------------------------------------------
def test_game_from_recipe():
    r = VciRecipe(agents=3, horizon=6, dt=0.25).to_dict()
    g = game_from_recipe(json.loads(json.dumps(r)))
    assert g.N == 3 and g.K == 6 and g.dt == pytest.approx(0.25)
    assert [g.params[f"radius.a{i}"].group for i in range(3)] == ["radius"] * 3
    own = {n.split(".")[-1] for n in g.params.names if n.startswith("w.a0.")}
    assert own == {"goal", "velocity", "acceleration", "jerk", "turn_rate", "turn_acceleration"}


TINY = dict(hist_width=8, hist_layers=1, lane_width=8, global_width=16, heads=2, dec_width=16)


def _tiny_dataset(tmp_path, capsys, agents):
    rng = np.random.default_rng(7)
    raw = tmp_path / "raw"
    for i in range(3):
        write_clip(raw / "vci_x", f"x_{i:02d}", *crowd(rng, np.arange(0, 36), 10.0, 3))
    out = tmp_path / f"data{agents}"
    generate(capsys, raw, out, "--fps", 10, "--agents", agents, "--set", "history=3",
             "--set", "horizon=4", "--set", "modes=2")  # fmt: skip
    return out


def _train(tmp_path, capsys, data, kind):
    extra = ["--set", "goal_decoder=regress", "--lm-steps", "1"] if kind == "epo" else []
    run = tmp_path / f"run-{kind}-{data.name}"
    rc, _, err = cli(capsys, "train", "--model", kind, "--data", data, "--out", run,
                     "--epochs", 1, "--batch-size", 8, "--no-progress", *extra,
                     *[f"--set={k}={v}" for k, v in TINY.items()])  # fmt: skip
    assert rc == 0, err
    assert (run / "checkpoint.pt").exists()


@pytest.mark.parametrize("kind", ["vlstm", "sc", "epo"])
def test_one_training_step(tmp_path, capsys, kind):
    data = _tiny_dataset(tmp_path, capsys, agents=4)  # the cart and 3 pedestrians: no padding
    assert load_split(data, "train")["agents_mask"].all()
    _train(tmp_path, capsys, data, kind)
    data = _tiny_dataset(tmp_path, capsys, agents=6)  # 3 pedestrians for 5 slots: padded
    assert not load_split(data, "train")["agents_mask"][:, 4:].any()
    _train(tmp_path, capsys, data, kind)


# ---- the shipped CITR clips -----------------------------------------------------------------
def _real():
    if not REAL.is_dir():
        pytest.skip(f"../shared/realdata/citr not present: {REAL} (the CITR clips)")
    return REAL


def test_real_citr_clips_found_and_counted():
    raw = _real()
    clips = find_clips(raw)
    assert len(clips) == 38 and sum(c[2] for c in clips) == 26
    types = {c[1] for c in clips}
    assert types == {"p2p_bi", "p2p_uni", "vci_back", "vci_front", "vci_lat_bi", "vci_lat_uni"}
    assert all(c[2] == c[1].startswith("vci_") for c in clips)
    for name, _, has_veh in clips:
        with open(raw / f"{name}{PED_SUFFIX}", newline="") as h:
            rows = list(csv.DictReader(h))
        r = read_vci_pedestrians(raw / f"{name}{PED_SUFFIX}")
        assert len(r["id"]) == len(rows)
        assert len(np.unique(r["id"])) == len({row["id"] for row in rows})
        assert 8 <= len({row["id"] for row in rows}) <= 10
        if has_veh:
            with open(raw / f"{name}{VEH_SUFFIX}", newline="") as h:
                vrows = list(csv.DictReader(h))
            v = read_vci_vehicles(raw / f"{name}{VEH_SUFFIX}")
            assert len(v["id"]) == len(vrows) and {row["id"] for row in vrows} == {"1"}


def test_real_citr_scene_against_the_raw_rows():
    raw = _real()
    name = "trajectories_filtered/vci_back/back_interaction_02"
    sc = VciScenario.from_raw(raw, clips=[name])
    r = sc.recipe
    s = sc.run_unit(0, None)
    # the cart's file spans frames 58..405: grid steps 0..57 of 5.994 frames, windows of 21
    assert len(s["time"]) == 58 - 20
    i = 11
    H, T, fps = r.history, r.horizon, r.fps
    step = r.dt * fps

    def rows(suffix):
        with open(raw / f"{name}{suffix}", newline="") as h:
            out = {}
            for row in csv.DictReader(h):
                out.setdefault(int(row["id"]), []).append(
                    [float(row[k]) for k in row if k != "label"]
                )
        return {k: np.array(v) for k, v in out.items()}

    def at(a, u, col):  # linear interpolation of the raw rows (frames in column 1) by hand
        f = np.floor(u).astype(int)
        w = u - f
        lo = a[np.searchsorted(a[:, 1], f), col]
        hi = a[np.searchsorted(a[:, 1], f + 1), col]
        return lo + w * (hi - lo)

    peds, (veh,) = rows(PED_SUFFIX), rows(VEH_SUFFIX).values()
    u_now = s["time"][i] * fps
    assert u_now == pytest.approx(58 + (H + i) * step)
    assert s["frame"][i] == round(u_now)
    origin = [at(veh, u_now, 2), at(veh, u_now, 3)]
    assert s["origin"][i] == pytest.approx(origin, abs=1e-9)
    u = u_now + step * np.arange(-H, T + 1)
    states = np.concatenate(
        [s["history"][i], s["future"][i, 0].transpose(1, 0, 2)]
    )  # (H+T+1, N, 4)
    assert np.allclose(states[:, 0, 0], at(veh, u, 2) - origin[0], atol=1e-5)
    assert np.allclose(states[:, 0, 2], at(veh, u, 5), atol=1e-5)
    assert np.allclose(states[:, 0, 3], at(veh, u, 4), atol=1e-5)  # heading near 0 in this clip
    # the three pedestrians of closest approach, from the observed raw positions only
    obs = u[: H + 1]
    cart_xy = np.stack([at(veh, obs, 2), at(veh, obs, 3)], 1)
    score = {}
    for pid, a in peds.items():
        p = np.stack([at(a, obs, 2), at(a, obs, 3)], 1)
        k = np.arange(T + 1)[:, None]
        gap = (p[-1] + k * (p[-1] - p[-2])) - (cart_xy[-1] + k * (cart_xy[-1] - cart_xy[-2]))
        score[pid] = np.linalg.norm(gap, axis=1).min()
    best = sorted(score, key=lambda p: (score[p], p))[:3]
    assert s["track_id"][i].tolist() == [1, *best]
    for slot, pid in enumerate(best, start=1):
        a = peds[pid]
        assert np.allclose(states[:, slot, 0], at(a, u, 2) - origin[0], atol=1e-5)
        assert np.allclose(states[:, slot, 1], at(a, u, 3) - origin[1], atol=1e-5)
        assert np.allclose(states[:, slot, 2], np.hypot(at(a, u, 4), at(a, u, 5)), atol=1e-5)
