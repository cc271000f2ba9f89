"""ETH/UCY reader (scenarios/real/eth_ucy.py): files the tests write (rows, frame step,
shapes, dt, frames, leave-one-scene-out and the validation carve, the interaction rule
without future leak, padding, gaps, malformed files at the CLI, --dt), the shipped files
in ../shared/realdata/eth_ucy when present (counts per file, one scene by hand, the test
split sizes), and one training step of V-LSTM, SC and ours."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from scenarios.dataset import SplitReader
from scenarios.real.eth_ucy import (
    SCENES,
    EthUcyScenario,
    game_from_recipe,
    read_eth_ucy,
    read_eth_ucy_file,
)
from tests.helpers import cli as _cli
from tests.helpers import one_error_line

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "eth_ucy"
SHIPPED = (
    "biwi_eth.txt",
    "biwi_hotel.txt",
    "students001.txt",
    "students003.txt",
    "crowds_zara01.txt",
    "crowds_zara02.txt",
    "crowds_zara03.txt",
    "uni_examples.txt",
)
SCENE_FILES = {
    "eth": ["biwi_eth.txt"],
    "hotel": ["biwi_hotel.txt"],
    "univ": ["students001.txt", "students003.txt"],
    "zara1": ["crowds_zara01.txt"],
    "zara2": ["crowds_zara02.txt"],
}
H, T = 7, 12  # the default window: 8 observed, 12 future rows


def walk(ped, n, p0, v, f0=0, step=10):
    """Rows ``(frame, ped, x, y)`` of a straight walk: ``n`` rows from ``p0``, ``v`` a row."""
    return [(f0 + step * k, ped, p0[0] + k * v[0], p0[1] + k * v[1]) for k in range(n)]


def write(path: Path, rows, sep="\t") -> Path:
    """The rows in the benchmark's layout: frame and ped as floats (``780.0``)."""
    rows = sorted(rows, key=lambda r: (r[0], r[1]))
    path.write_text(
        "".join(
            f"{float(f)}{sep}{float(p)}{sep}{float(x)!r}{sep}{float(y)!r}\n" for f, p, x, y in rows
        )
    )
    return path


def lanes(n_ped, n_rows, y0=0.0, speed=0.4):
    """``n_ped`` pedestrians side by side 2 m apart, all walking +x for ``n_rows`` rows."""
    return [r for i in range(n_ped) for r in walk(i + 1, n_rows, (0.0, y0 + 2.0 * i), (speed, 0))]


def make_dir(d: Path, files: dict) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    for name, rows in files.items():
        write(d / name, rows)
    return d


def scenario(d, **over) -> EthUcyScenario:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return EthUcyScenario.from_raw(d, **over)


def samples(sc: EthUcyScenario, file: str) -> dict:
    """All samples of every unit of ``file`` (by the scenario's own run_unit)."""
    fi = [n for n, _ in sc.recipe.files].index(file)
    outs = [sc.run_unit(u, None) for u, (i, _) in enumerate(sc.units) if i == fi]
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}


def focal(s: dict, ped: int, frame: int | None = None) -> np.ndarray:
    sel = s["track_id"][:, 0] == ped
    if frame is not None:
        sel &= s["frame"] == frame
    return np.flatnonzero(sel)


def cli(capsys, *args):
    """``epo ARGS`` with warnings printed as the CLI prints them (the suite makes them errors)."""
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        return _cli(capsys, *args)


def generate(capsys, raw, out, *args) -> int:
    rc, _, err = cli(
        capsys, "generate", "eth-ucy", "--raw", raw, "--out", out, "--workers", "1",
        "--no-progress", *args,
    )  # fmt: skip
    assert rc == 0, err
    return rc


# --------------------------------------------------------------------------------------
# files the test writes
# --------------------------------------------------------------------------------------
def test_reader_rows_tracks_and_step(tmp_path):
    p = tmp_path / "mine.txt"
    # spaces and tabs, ids written as floats, a blank line, rows not grouped by pedestrian,
    # pedestrian 5 skips a row (a gap: the step is still the most common difference, 10)
    p.write_text(
        "780.0\t5.0\t1.5\t-2.25\n780.0 2.0  0.5 0.75\n790.0\t2.0\t0.75\t1.0\n\n"
        "800.0\t2.0\t1.0\t1.25\n810.0\t5.0\t2.0\t-2.0\n"
    )
    f = read_eth_ucy_file(p)
    assert (f.step, f.first, f.last, f.rows, f.pedestrians) == (10, 780, 810, 5, 2)
    tr = read_eth_ucy(p)
    assert [t.id for t in tr] == [2, 5]
    assert tr[0].frames.tolist() == [780, 790, 800]
    assert tr[0].xy.tolist() == [[0.5, 0.75], [0.75, 1.0], [1.0, 1.25]]
    assert tr[1].frames.tolist() == [780, 810] and tr[1].xy.tolist() == [[1.5, -2.25], [2.0, -2.0]]
    # a file whose rows are 6 frames apart (the step is the file's own)
    write(p, walk(1, 4, (0, 0), (1, 0), f0=3, step=6) + walk(2, 3, (0, 1), (1, 0), f0=9, step=6))
    f = read_eth_ucy_file(p)
    assert (f.step, f.first, f.last) == (6, 3, 21)


def test_shapes_dt_frames_and_manifest(tmp_path, capsys):
    raw = make_dir(
        tmp_path / "raw",
        {"biwi_eth.txt": lanes(3, 25), "biwi_hotel.txt": lanes(2, 60), "notes.md": []},
    )
    (raw / "notes.md").write_text("not a track file\n")
    out = tmp_path / "data"
    rc, stdout, err = cli(
        capsys, "generate", "eth-ucy", "--raw", raw, "--out", out, "--workers", "1",
        "--no-progress", "--set", "val_fraction=0.5",
    )  # fmt: skip
    assert rc == 0, err
    # the ignored file is named in one warning line and in the manifest
    warned = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(warned) == 1 and "ignoring 1 file(s)" in warned[0] and "notes.md" in warned[0]
    m = json.loads((out / "manifest.json").read_text())
    assert m["scenario"] == "eth-ucy" and m["meta"]["ignored_files"] == ["notes.md"]
    assert m["recipe"]["files"] == [["biwi_eth.txt", "eth"], ["biwi_hotel.txt", "hotel"]]
    assert m["meta"]["dt"] == 0.4 and "0.667" in m["meta"]["dt_note"]
    assert m["meta"]["frame_steps"] == {"biwi_eth.txt": 10, "biwi_hotel.txt": 10}
    sch = {k: tuple(v["shape"]) for k, v in m["schema"].items()}
    assert sch["history"] == (8, 4, 4) and sch["future"] == (20, 4, 12, 4)
    assert sch["agents_mask"] == (4,) and sch["scene"] == () and sch["file"] == ()
    with SplitReader(out, "test") as r:
        s = r.read_all()
    # 3 pedestrians x (25 - 19) current frames 70 .. 120, 3 real agents and one pad
    assert len(s["frame"]) == 18 and sorted(set(s["frame"].tolist())) == list(range(70, 121, 10))
    assert s["agents_mask"].sum(1).tolist() == [3] * 18
    i = int(focal(s, 2, 90)[0])
    # the focal pedestrian 2 at (0.4 * 9, 2) is the origin; others 2 m to either side
    assert np.allclose(s["origin"][i], [3.6, 2.0])
    assert sorted(s["track_id"][i].tolist()) == [-1, 1, 2, 3] and s["track_id"][i, 0] == 2
    assert np.allclose(s["history"][i, :, 0, 0], np.arange(-7, 1) * 0.4, atol=1e-6)
    assert np.allclose(s["history"][i, :, :3, 2], 1.0) and np.allclose(s["history"][i, :, :3, 3], 0)
    assert np.allclose(s["future"][i, 0, 0, :, 0], np.arange(1, 13) * 0.4, atol=1e-6)
    assert (s["future"][i] == s["future"][i, :1]).all() and s["mode_valid"][i].tolist() == [
        True
    ] + [False] * 19
    assert (s["scene"] == 0).all() and (s["file"] == 0).all()
    game = game_from_recipe(m["recipe"])
    assert game.N == 4 and game.K == 12 and game.dt == pytest.approx(0.4)


def test_leave_one_scene_out_and_validation_carve(tmp_path, capsys):
    files = {n: lanes(2, 60) for ns in SCENE_FILES.values() for n in ns}
    files["crowds_zara03.txt"] = lanes(2, 60)
    files["uni_examples.txt"] = lanes(2, 60)
    raw = make_dir(tmp_path / "raw", files)
    names = list(files)
    from scenarios.commands.generate_eth_ucy import _SCENES

    assert _SCENES == SCENES  # the command's choices (kept there to load the CLI fast)
    for test in SCENES:
        sc = scenario(raw, test_scene=test, val_fraction=0.5)
        sp = sc.split_units(0)
        by_part = {s: {(sc.recipe.files[sc.units[u][0]][0]) for u in sp[s]} for s in sp}
        assert by_part["test"] == set(SCENE_FILES[test])
        assert by_part["train"] == by_part["val"] == set(names) - set(SCENE_FILES[test])
        assert sorted(u for s in sp.values() for u in s) == list(range(sc.n_units))
    # zara3 and uni_examples are never test; a scene without its file is refused
    out = tmp_path / "data"
    generate(capsys, raw, out, "--test-scene", "HOTEL", "--set", "val_fraction=0.5")
    m = json.loads((out / "manifest.json").read_text())
    assert m["recipe"]["test_scene"] == "hotel"
    cut = {f["file"]: f["val_from_frame"] for f in m["meta"]["files"]}
    # frames 0 .. 590: the cut at 0 + round(0.5 * 59) * 10 = 300 (half up)
    assert cut["biwi_hotel.txt"] is None and cut["biwi_eth.txt"] == 300
    got = {}
    for split in ("train", "val", "test"):
        with SplitReader(out, split) as r:
            got[split] = r.read_all()
    scenes = m["meta"]["scenes"]
    assert {scenes[k] for k in got["test"]["scene"]} == {"hotel"}
    assert "hotel" not in {scenes[k] for k in got["train"]["scene"]} | {
        scenes[k] for k in got["val"]["scene"]
    }
    # per pedestrian and file: 41 test windows (60 - 19); train: current 70 .. 170 (the
    # window ends before frame 300), val: current 370 .. 470 (starts at 300 or later)
    assert len(got["test"]["frame"]) == 2 * 41
    n_train_files = len(names) - 1
    for split, frames in (("train", range(70, 171, 10)), ("val", range(370, 471, 10))):
        s = got[split]
        assert len(s["frame"]) == n_train_files * 2 * len(frames)
        assert set(s["frame"].tolist()) == set(frames)
    lo = got["val"]["frame"] - H * 10
    hi = got["train"]["frame"] + T * 10
    assert lo.min() >= 300 and hi.max() < 300
    keys = {
        s: {
            (int(f), int(fr), int(p))
            for f, fr, p in zip(v["file"], v["frame"], v["track_id"][:, 0], strict=True)
        }
        for s, v in got.items()
    }
    assert not (keys["train"] & keys["val"]) and not (keys["train"] & keys["test"])
    assert not (keys["val"] & keys["test"])
    assert len(keys["train"]) == len(got["train"]["frame"])  # no sample twice
    # the test scene must have a file
    del_dir = make_dir(tmp_path / "raw2", {"biwi_eth.txt": lanes(2, 30)})
    rc, _, err = cli(
        capsys, "generate", "eth-ucy", "--raw", del_dir, "--out", tmp_path / "o2",
        "--test-scene", "zara1", "--no-progress",
    )  # fmt: skip
    one_error_line(rc, err, "eth_ucy.test_scene", "'zara1'")
    rc, _, err = cli(
        capsys, "generate", "eth-ucy", "--raw", raw, "--out", tmp_path / "o3",
        "--test-scene", "zara3", "--no-progress",
    )  # fmt: skip
    one_error_line(rc, err, "--test-scene")


def interaction_dir(tmp_path, leak_future: bool):
    """Focal pedestrian 1 walks +x at 0.4 m a row, rows 0 .. 19 (the one window: current
    row 7, frame 70). 2: 4 m ahead at the current step, walking towards it (extrapolated
    closest approach 0.5 m); 3: 1.9 m beside now (closer) but walking away; 4: 3 m beside
    over the observed rows, then swerving to 0.3 m in the future (``leak_future``; else it
    stays 3 m away); 5: 2 m beside all the time."""
    k = np.arange(20)
    rows = [(10 * i, 1, 0.4 * i, 0.0) for i in k]
    rows += [(10 * i, 2, 6.8 - 0.4 * (i - 7), 0.5) for i in k]
    rows += [(10 * i, 3, 0.4 * i, 1.5 + 0.4 * max(i - 6, 0)) for i in k]
    y4 = [3.0 if i <= 7 or not leak_future else max(3.0 - 0.7 * (i - 7), 0.3) for i in k]
    rows += [(10 * i, 4, 0.4 * i, y4[i]) for i in k]
    rows += [(10 * i, 5, 0.4 * i, -2.0) for i in k]
    d = tmp_path / ("leak" if leak_future else "noleak")
    return make_dir(d, {"biwi_eth.txt": rows, "biwi_hotel.txt": lanes(2, 30)})


def test_interaction_rule_without_future_leak(tmp_path):
    raw = interaction_dir(tmp_path, leak_future=True)
    got = {}
    for n in (2, 3, 4, 5):
        s = samples(scenario(raw, agents=n), "biwi_eth.txt")
        (i,) = focal(s, 1, 70)
        got[n] = s["track_id"][i].tolist()
    # scores (observed only): 2 -> 0.5 (approaching), 5 -> 2.0, 3 -> 1.9 (closest now,
    # walking away), 4 -> 3.0 (its future comes within 0.3 m but its observed part does not)
    assert got[2] == [1, 2]  # approaching beats closer-now-but-walking-away
    assert got[3] == [1, 2, 3] and got[4] == [1, 2, 3, 5] and got[5] == [1, 2, 3, 5, 4]
    # without 2 and 3 as candidates (agents 2, other focal-1 scene): 5 is chosen over 4
    rows = [r for r in np.loadtxt(raw / "biwi_eth.txt") if r[1] in (1, 4, 5)]
    raw2 = make_dir(
        tmp_path / "two", {"biwi_eth.txt": [tuple(r) for r in rows], "biwi_hotel.txt": lanes(2, 30)}
    )
    s = samples(scenario(raw2, agents=2), "biwi_eth.txt")
    (i,) = focal(s, 1, 70)
    assert s["track_id"][i].tolist() == [1, 5]
    # pedestrian 4's future closes to 0.3 m: recorded in the future of the 3-agent scene
    s3 = samples(scenario(raw2, agents=3), "biwi_eth.txt")
    (j,) = focal(s3, 1, 70)
    assert s3["track_id"][j].tolist() == [1, 5, 4]
    assert s3["min_distance"][j] == pytest.approx(0.3, abs=1e-5)
    # the future of 4 changes nothing of the choice or the observed part
    raw3 = interaction_dir(tmp_path, leak_future=False)
    for n in (2, 3, 4, 5):
        a = samples(scenario(raw, agents=n), "biwi_eth.txt")
        b = samples(scenario(raw3, agents=n), "biwi_eth.txt")
        (i,) = focal(a, 1, 70)
        (j,) = focal(b, 1, 70)
        assert a["track_id"][i].tolist() == b["track_id"][j].tolist()
        assert np.array_equal(a["history"][i], b["history"][j])


def test_padding_of_small_scenes(tmp_path):
    raw = make_dir(tmp_path / "raw", {"biwi_eth.txt": lanes(2, 20), "biwi_hotel.txt": lanes(1, 20)})
    sc = scenario(raw, val_fraction=0)
    s = samples(sc, "biwi_eth.txt")
    assert len(s["frame"]) == 2  # one window per pedestrian
    assert s["agents_mask"].tolist() == [[True, True, False, False]] * 2
    assert (s["history"][:, :, 2:] == 0).all() and (s["future"][:, :, 2:] == 0).all()
    assert (s["track_id"][:, 2:] == -1).all() and sorted(s["track_id"][:, 0].tolist()) == [1, 2]
    assert s["radius"].tolist() == [[pytest.approx(0.3), pytest.approx(0.3), 0.0, 0.0]] * 2
    # no recorded size: no length / width fields (the overlap rate uses circles of radius)
    assert "length" not in s and "width" not in s and (s["agent_kind"] == 0).all()
    assert "length" not in sc.schema() and sc.meta()["focal_slot"] == 0
    assert s["others"].shape == (2, 16, 8 + 12, 2) and np.isnan(s["others"]).all()  # no other
    assert not (s["history"][:, :, :2] == 0).all()
    one = samples(sc, "biwi_hotel.txt")  # alone: slot 0 only, min_distance inf
    assert one["agents_mask"].tolist() == [[True, False, False, False]]
    assert np.isinf(one["min_distance"]).all()


def test_others_are_the_nearest_pedestrians_left_out(tmp_path):
    """The figure-only field ``others``: the pedestrians not in the scene, nearest the focal
    one at a common step of the window first (ties: the lower id), at their recorded
    positions in the scene frame, NaN where not recorded (also one too short for a scene)."""
    rows = lanes(5, 20) + walk(9, 4, (1.2, -1.0), (0.4, 0), f0=30)  # 9: rows 3 .. 6 only
    raw = make_dir(tmp_path / "raw", {"biwi_eth.txt": rows, "biwi_hotel.txt": lanes(2, 20)})
    sc = scenario(raw, val_fraction=0, agents=2, context_agents=4)
    s = samples(sc, "biwi_eth.txt")
    assert s["others"].shape == (5, 4, H + 1 + T, 2)
    k = np.arange(H + 1 + T)
    for ped, chosen, order in ((1, 2, [9, 3, 4, 5]), (3, 2, [4, 1, 5, 9])):
        (i,) = focal(s, ped)
        assert s["track_id"][i].tolist() == [ped, chosen]
        origin = np.array([0.4 * H, 2.0 * (ped - 1)])
        for c, other in enumerate(order):
            want = np.full((H + 1 + T, 2), np.nan)
            if other == 9:
                want[3:7] = np.stack([0.4 * k[3:7], np.full(4, -1.0)], 1)
            else:
                want[:] = np.stack([0.4 * k, np.full(k.size, 2.0 * (other - 1))], 1)
            np.testing.assert_allclose(s["others"][i, c], want - origin, atol=1e-5)
    sc0 = scenario(raw, val_fraction=0, agents=2, context_agents=0)
    assert "others" not in sc0.schema() and "others" not in samples(sc0, "biwi_eth.txt")


def test_gaps_split_tracks(tmp_path):
    # pedestrian 1: rows 0 .. 30 without frame 60 (pieces 0 .. 50 and 70 .. 300);
    # pedestrian 2: rows 0 .. 30 complete, 2 m beside
    r1 = [r for r in walk(1, 31, (0, 0), (0.4, 0)) if r[0] != 60]
    r2 = walk(2, 31, (0, 2), (0.4, 0))
    raw = make_dir(tmp_path / "raw", {"biwi_eth.txt": r1 + r2, "biwi_hotel.txt": lanes(1, 20)})
    s = samples(scenario(raw, agents=2), "biwi_eth.txt")
    # focal 1: windows inside 70 .. 300 only: current 140 .. 180
    assert s["frame"][focal(s, 1)].tolist() == [140, 150, 160, 170, 180]
    # focal 2: current 70 .. 180; 1 takes part only where its window misses frame 60
    i = focal(s, 2)
    assert s["frame"][i].tolist() == list(range(70, 181, 10))
    with_1 = s["frame"][i][s["agents_mask"][i, 1]].tolist()
    assert with_1 == [140, 150, 160, 170, 180]
    assert (s["track_id"][i][~s["agents_mask"][i, 1], 1] == -1).all()
    # the stored window of 1 in 2's scene at 140 starts at frame 70 (its row 70, not 60)
    (j,) = focal(s, 2, 140)
    assert np.allclose(s["history"][j, 0, 1, :2] + s["origin"][j], [0.4 * 7, 0.0])


def test_dt_override_changes_velocities(tmp_path, capsys):
    raw = make_dir(
        tmp_path / "raw", {"biwi_eth.txt": lanes(2, 20, speed=0.5), "biwi_hotel.txt": lanes(2, 40)}
    )
    for dt in (None, 0.667):
        out = tmp_path / f"data{dt}"
        generate(capsys, raw, out, *(["--dt", str(dt)] if dt else []))
        with SplitReader(out, "test") as r:
            s = r.read_all()
        m = json.loads((out / "manifest.json").read_text())
        want = 0.4 if dt is None else 0.667
        assert m["recipe"]["dt"] == want and m["meta"]["dt"] == want
        # 0.5 m a row: v = 0.5 / dt everywhere (observed and future)
        assert np.allclose(s["history"][:, :, :2, 2], 0.5 / want, rtol=1e-6)
        assert np.allclose(s["future"][:, 0, :2, :, 2], 0.5 / want, rtol=1e-6)
        assert game_from_recipe(m["recipe"]).dt == pytest.approx(want)
    for bad in ("0", "nan", "9"):
        rc, _, err = cli(
            capsys, "generate", "eth-ucy", "--raw", raw, "--out", tmp_path / "x", "--dt", bad
        )
        one_error_line(rc, err, "--dt")
    rc, _, err = cli(
        capsys, "generate", "eth-ucy", "--raw", raw, "--out", tmp_path / "x", "--dt", "0.5",
        "--set", "dt=0.3",
    )  # fmt: skip
    one_error_line(rc, err, "--set dt")


GOOD = "0.0\t1.0\t1.5\t2.5\n0.0\t2.0\t3.0\t4.0\n10.0\t1.0\t1.9\t2.5\n10.0\t2.0\t3.4\t4.0\n"


@pytest.mark.parametrize(
    "text, words",
    [
        (GOOD.replace("1.9\t2.5", "1.9\t2.5\t7"), [":3:", "column 5", "4 (frame ped x y)"]),
        (GOOD.replace("\t4.0\n10.0", "\n10.0", 1), [":2:", "column 4 (y)", "missing"]),
        (GOOD[:-6], [":4:", "column 4 (y)", "truncated file"]),
        (GOOD.replace("3.4", "abc"), [":4:", "column 3 (x)", "'abc'"]),
        (GOOD.replace("0.0\t2.0", "0.0\t2.5"), [":2:", "column 2 (ped)", "whole number"]),
        (GOOD.replace("10.0\t1.0", "10.5\t1.0"), [":3:", "column 1 (frame)", "whole number"]),
        (GOOD.replace("2.5\n10", "nan\n10"), [":3:", "column 4 (y)", "finite", "'nan'"]),
        (GOOD.replace("3.0\t4.0", "inf\t4.0"), [":2:", "column 3 (x)", "finite"]),
        (GOOD.replace("3.0\t4.0", "3e5\t4.0"), [":2:", "column 3 (x)", "10000"]),
        (GOOD.replace("0.0\t2.0", "0.0\t-1.0"), [":2:", "column 2 (ped)", "padding"]),
        (GOOD + "0.0\t1.0\t1.5\t2.5\n", [":5:", "columns 1-2 (frame, ped)", "line 1"]),
        (GOOD + "15.0\t3.0\t1.5\t2.5\n", [":5:", "column 1 (frame)", "off the file's grid"]),
        ("", [":1:", "no rows"]),
    ],
    ids=[
        "five-columns", "three-columns", "truncated", "text", "ped-fraction",
        "frame-fraction", "nan", "inf", "far", "negative-ped", "duplicate", "off-grid", "empty",
    ],
)  # fmt: skip
def test_malformed_files_one_error_line(tmp_path, capsys, text, words):
    raw = make_dir(tmp_path / "raw", {"biwi_hotel.txt": lanes(2, 30)})
    (raw / "biwi_eth.txt").write_text(text)
    rc, _, err = cli(
        capsys, "generate", "eth-ucy", "--raw", raw, "--out", tmp_path / "out", "--no-progress"
    )
    one_error_line(rc, err, f"{raw / 'biwi_eth.txt'}:", *words)
    assert not (tmp_path / "out" / "manifest.json").exists()


def test_other_files_and_named_files(tmp_path, capsys):
    raw = make_dir(
        tmp_path / "raw",
        {"biwi_eth.txt": lanes(2, 25), "mine.txt": lanes(3, 25), "biwi_hotel.txt": lanes(2, 25)},
    )
    (raw / "VERIFY.txt").write_text("== a summary, not rows\n")
    with pytest.warns(UserWarning, match=r"ignoring 2 file\(s\).*VERIFY\.txt, mine\.txt"):
        sc = EthUcyScenario.from_raw(raw)
    assert [n for n, _ in sc.recipe.files] == ["biwi_eth.txt", "biwi_hotel.txt"]
    # named files: a file of the same format with its own scene label trains
    out = tmp_path / "data"
    generate(
        capsys, raw, out, "--set", 'files=[["biwi_eth.txt","eth"],["mine.txt","mine"]]',
        "--set", "val_fraction=0",
    )  # fmt: skip
    m = json.loads((out / "manifest.json").read_text())
    assert m["meta"]["scenes"][-1] == "mine" and m["meta"]["ignored_files"] == [
        "VERIFY.txt",
        "biwi_hotel.txt",
    ]
    with SplitReader(out, "train") as r:
        s = r.read_all()
    assert len(s["frame"]) == 3 * 6 and set(s["scene"].tolist()) == {5}
    assert set(s["file"].tolist()) == {1}
    # a different file content refuses to resume the same folder
    write(raw / "mine.txt", lanes(3, 26))
    rc, _, err = cli(
        capsys, "generate", "eth-ucy", "--raw", raw, "--out", out, "--no-progress",
        "--set", 'files=[["biwi_eth.txt","eth"],["mine.txt","mine"]]', "--set", "val_fraction=0",
    )  # fmt: skip
    one_error_line(rc, err, "raw_digest")
    for files, word in (
        ('[["nope.txt","eth"]]', "nope.txt"),
        ('[["../x.txt","eth"]]', "inside the raw folder"),
        ('[["mine.txt","a b"]]', "scene label"),
        ('"mine.txt"', "eth_ucy.files"),
    ):
        rc, _, err = cli(
            capsys, "generate", "eth-ucy", "--raw", raw, "--out", tmp_path / "o",
            "--set", f"files={files}",
        )  # fmt: skip
        one_error_line(rc, err, word)
    for bad in (tmp_path / "none", raw / "mine.txt", tmp_path / "empty"):
        if bad.name == "empty":
            bad.mkdir()
        rc, _, err = cli(capsys, "generate", "eth-ucy", "--raw", bad, "--out", tmp_path / "o")
        one_error_line(rc, err, str(bad))


# --------------------------------------------------------------------------------------
# the shipped files
# --------------------------------------------------------------------------------------
def shipped():
    if not all((SHARED / n).is_file() for n in SHIPPED):
        pytest.skip(f"{SHARED} not present: the shipped ETH/UCY files are not on this machine")
    return SHARED


def plain_rows(path: Path) -> list[tuple[int, int, float, float]]:
    """The rows by plain Python: split on whitespace, int(float()) for the ids."""
    out = []
    for line in path.read_text().splitlines():
        c = line.split()
        if c:
            assert len(c) == 4
            out.append((int(float(c[0])), int(float(c[1])), float(c[2]), float(c[3])))
    return out


def test_shipped_counts_per_file():
    d = shipped()
    total = 0
    for n in SHIPPED:
        rows = plain_rows(d / n)
        f = read_eth_ucy_file(d / n)
        peds = {p for _, p, _, _ in rows}
        assert (f.rows, f.pedestrians, f.step) == (len(rows), len(peds), 10), n
        assert (f.first, f.last) == (min(r[0] for r in rows), max(r[0] for r in rows))
        by = {}
        for fr, p, x, y in rows:
            by.setdefault(p, []).append((fr, x, y))
        for t in f.tracks:
            want = sorted(by[t.id])
            assert t.frames.tolist() == [w[0] for w in want]
            assert t.xy.tolist() == [[w[1], w[2]] for w in want]
        total += len(peds)
    assert total == 2205  # the data's README


def test_shipped_scene_by_hand():
    d = shipped()
    sc = scenario(d, agents=4)
    s = sc.run_unit(sc.split_units(0)["test"][0], None)  # biwi_eth.txt, whole
    rows = plain_rows(d / "biwi_eth.txt")
    pos = {(fr, p): (x, y) for fr, p, x, y in rows}
    # the first scene with four pedestrians
    i = int(np.flatnonzero(s["agents_mask"].all(1))[0])
    t, ids = int(s["frame"][i]), s["track_id"][i].tolist()
    frames = [t + 10 * k for k in range(-H, T + 1)]
    p = np.array([[pos[(fr, a)] for a in ids] for fr in frames])  # (20, 4, 2)
    origin = p[H, 0]
    assert np.allclose(s["origin"][i], origin)
    d_ = np.diff(p, axis=0)
    v = np.linalg.norm(d_, axis=-1) / 0.4
    th = np.arctan2(d_[..., 1], d_[..., 0])
    want = np.concatenate(
        [p - origin, np.r_[v[:1], v][..., None], np.r_[th[:1], th][..., None]], -1
    )
    got = np.concatenate([s["history"][i], s["future"][i, 0].transpose(1, 0, 2)], 0)
    moving = np.r_[d_[:1], d_]
    moving = np.linalg.norm(moving, axis=-1) > 1e-3
    assert np.allclose(got[..., :3], want[..., :3], atol=1e-5)
    assert np.allclose(np.angle(np.exp(1j * (got[..., 3] - want[..., 3])))[moving], 0, atol=1e-5)
    # the chosen others: the 3 of smallest constant-velocity closest approach among every
    # pedestrian recorded over the whole window (by hand from the rows)
    cands = sorted({a for (fr, a) in pos if fr == t} - {ids[0]})
    cands = [a for a in cands if all((fr, a) in pos for fr in frames)]
    obs = lambda a, k: np.array(pos[(t + 10 * k, a)])  # noqa: E731
    fv = obs(ids[0], 0) - obs(ids[0], -1)
    score = {}
    for a in cands:
        av = obs(a, 0) - obs(a, -1)
        score[a] = min(
            np.linalg.norm(obs(a, 0) + j * av - obs(ids[0], 0) - j * fv) for j in range(T + 1)
        )
    assert ids[1:] == sorted(cands, key=lambda a: (score[a], a))[:3]


def count_windows(path: Path) -> int:
    """Windows of 20 consecutive rows (10 frames apart) of one pedestrian, by plain Python."""
    frames = {}
    for fr, p, _, _ in plain_rows(path):
        frames.setdefault(p, set()).add(fr)
    return sum(
        all(t + 10 * k in fs for k in range(-H, T + 1)) for fs in frames.values() for t in fs
    )


#: test samples per left-out scene with the defaults (every pedestrian recorded over a
#: whole window of 20 rows is a focal agent at each current frame), measured
TEST_SIZES = {"eth": 364, "hotel": 1197, "univ": 24334, "zara1": 2356, "zara2": 5910}


def test_shipped_test_split_sizes():
    d = shipped()
    for scene, files in SCENE_FILES.items():
        want = sum(count_windows(d / n) for n in files)
        assert want == TEST_SIZES[scene]
        sc = scenario(d, test_scene=scene, agents=1)  # the choice of others changes no count
        got = sum(len(sc.run_unit(u, None)["frame"]) for u in sc.split_units(0)["test"])
        assert got == want, scene


# --------------------------------------------------------------------------------------
# one training step per model
# --------------------------------------------------------------------------------------
SMALL = dict(hist_width=8, hist_layers=1, global_width=16, heads=2, dec_width=16)


def tiny_dataset(tmp_path, capsys, padded: bool) -> Path:
    """Four pedestrians walking side by side (train frames 0 .. 130, val 400 .. 530); with
    ``padded`` one more walks alone at frames 140 .. 270 (scenes of one agent and pads)."""
    eth = lanes(4, 14)
    hotel = lanes(4, 14) + [(f + 400, p + 10, x, y) for f, p, x, y in lanes(4, 14)]
    if padded:
        hotel += walk(9, 14, (5.0, 40.0), (0.0, 0.4), f0=140)
    raw = make_dir(tmp_path / f"raw{padded}", {"biwi_eth.txt": eth, "biwi_hotel.txt": hotel})
    out = tmp_path / f"data{padded}"
    generate(
        capsys, raw, out, "--agents", "4", "--set", "history=3", "--set", "horizon=6",
        "--set", "modes=3", "--set", "val_fraction=0.3",
    )  # fmt: skip
    with SplitReader(out, "train") as r:
        mask = r.read_all()["agents_mask"]
    assert mask.all() != padded and len(mask) > 0
    return out


def train_once(tmp_path, capsys, data, kind):
    extra = ["--set", "goal_decoder=regress", "--lm-steps", "1"] if kind == "epo" else []
    run = tmp_path / f"run-{kind}-{data.name}"
    rc, out, err = cli(
        capsys, "train", "--model", kind, "--data", data, "--out", run, "--epochs", "1",
        "--batch-size", "8", "--no-progress", *extra, *[f"--set={k}={v}" for k, v in SMALL.items()],
    )  # fmt: skip
    assert rc == 0, err
    assert (run / "checkpoint.pt").exists()
    line = out.strip().splitlines()[-1]
    loss = float(line.split("train loss ")[1].split(",")[0])
    assert math.isfinite(loss), line


@pytest.mark.parametrize("kind", ["vlstm", "sc", "epo"])
def test_training_step(tmp_path, capsys, kind):
    train_once(tmp_path, capsys, tiny_dataset(tmp_path, capsys, padded=False), kind)


@pytest.mark.parametrize("kind", ["vlstm", "sc", "epo"])
def test_training_step_padded(tmp_path, capsys, kind):
    train_once(tmp_path, capsys, tiny_dataset(tmp_path, capsys, padded=True), kind)
