"""exiD layout (scenarios/exid.py) on data of the generator (scenarios/highway/): the reader
against pandas and highway-env, UTM against the meridian arc, the extraction (frames, dt,
lane-change filter, held-out map, goal candidates on lanes), malformed recordings, the
dataset files, and one training step of ours and SC."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest

from scenarios import dataset as ds
from scenarios.cli import main
from scenarios.dataset import DatasetError
from scenarios.exid import (
    TRACK_COLUMNS,
    ExidScenario,
    find_map,
    latlon_from_utm,
    read_lanelet_map,
    read_recording,
    utm_from_latlon,
)
from scenarios.highway import LOCATIONS, HighwayOptions, build_network, generate_raw

# three short recordings at 10 Hz (dt = 0.2 s is 2 frames), one per location 0, 1, 2
RAW = ["--recordings", "3", "--seed", "0", "--duration", "24", "--no-progress"]
RAW += ["--set", "warmup=20", "--set", "frame_rate=10", "--set", "locations=[0,1,2]"]
EXTRACT = dict(max_scenes_per_recording=8, neighbour_range=150)


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    d = tmp_path_factory.mktemp("exid") / "raw"
    assert main(["generate", "highway-raw", "--out", str(d), *RAW]) == 0
    return d


@pytest.fixture(scope="module")
def data(raw):
    d = raw.parent / "data"
    args = ["generate", "exid", "--raw", str(raw), "--out", str(d), "--workers", "1"]
    args += ["--no-progress", *[f"--set={k}={v}" for k, v in EXTRACT.items()]]
    assert main(args) == 0
    return d


def test_utm_meridian_arc_and_round_trip():
    # on the central meridian the northing is k0 times the meridian arc, computed here by
    # Gauss-Legendre quadrature of the WGS84 meridian radius of curvature
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    phi = np.radians(45.0)
    x, w = np.polynomial.legendre.leggauss(40)
    p = 0.5 * phi * (x + 1)
    arc = 0.5 * phi * np.sum(w * a * (1 - e2) / (1 - e2 * np.sin(p) ** 2) ** 1.5)
    e, n = utm_from_latlon(45.0, 9.0, 32)
    assert abs(e - 500000.0) < 1e-6 and abs(n - 0.9996 * arc) < 1e-3
    E = np.array([300000.0, 350000.0, 640000.0])
    N = np.array([5.0e6, 5.65e6, 6.0e6])
    lat, lon = latlon_from_utm(E, N, 32)
    e, n = utm_from_latlon(lat, lon, 32)
    assert np.abs(e - E).max() < 2e-3 and np.abs(n - N).max() < 2e-3


def test_reader_against_pandas_and_highway_env(raw):
    rec = read_recording(raw, 1)
    assert (rec.location, rec.frame_rate, rec.id) == (1, 10.0, 1)
    df = pd.read_csv(raw / "data" / "01_tracks.csv").sort_values(["trackId", "frame"])
    meta = pd.read_csv(raw / "data" / "01_tracksMeta.csv")
    assert rec.n_tracks == len(meta) and len(rec.rows["frame"]) == len(df)
    for c in TRACK_COLUMNS:
        np.testing.assert_array_equal(rec.rows[c], df[c].to_numpy(dtype=float))
    np.testing.assert_array_equal(rec.rows["laneletId"], df["laneletId"].to_numpy())
    assert set(rec.meta["class"]) <= {"car", "truck"}
    # the map: every lanelet's centre line is highway-env's lane centre (lat/lon -> UTM)
    loc = LOCATIONS[1]
    m = read_lanelet_map(find_map(raw, 1), rec.utm_origin, rec.lonlat, rec.speed_limit)
    net, ids, _ = build_network(loc)
    assert len(m.road_map.lanes) == len(ids)
    for (a, b, i), lid in ids.items():
        hl = net.get_lane((a, b, i))
        lane = m.road_map.lane(str(lid))
        s = np.linspace(0, hl.length, 7)
        want = np.array([hl.position(x, 0.0) for x in s])
        _, d = lane.project(want)
        curved = type(hl).__name__ == "SineLane"  # polyline of 2.5 m chords: < 1 cm off
        assert d.max() < (1e-2 if curved else 2e-3), (a, b, i, d.max())
        assert abs(lane.width - loc.lane_width) < 5e-3
    # neighbours share a boundary; the deceleration lane is right of the right-most lane
    main0, main1 = str(ids[("b", "c", 0)]), str(ids[("b", "c", 1)])
    aux = str(ids[("b", "c", loc.lanes)])
    assert m.left[main0] is None and m.right[main0] == main1 and m.left[main1] == main0
    assert m.right[str(ids[("b", "c", loc.lanes - 1)])] == aux and m.right[aux] is None
    assert str(ids[("c", "e", 0)]) in m.road_map.lane(aux).successors
    assert m.road_map.lane(main0).speed_limit == pytest.approx(120 / 3.6)


def test_extracted_dataset(raw, data):
    assert main(["data", "verify", str(data)]) == 0
    m = ds.read_manifest(data)
    assert m["scenario"] == "exid" and m["complete"]
    sp = {s: ds.load_split(data, s) for s in ds.SPLITS}
    assert all(len(sp[s]["history"]) > 0 for s in ds.SPLITS)
    # held-out map: location 0 is the test split only
    assert set(sp["test"]["location"]) == {0}
    assert 0 not in set(sp["train"]["location"]) | set(sp["val"]["location"])
    t = sp["train"]
    n = len(t["history"])
    assert t["history"].shape == (n, 10, 4, 4) and t["future"].shape == (n, 5, 4, 20, 4)
    assert t["goal_candidates"].shape == (n, 4, 60, 2) and t["lanes"].shape == (n, 12, 20, 2)
    assert (t["gt_mode"] == 0).all() and (t["mode_valid"] == (np.arange(5) == 0)).all()
    np.testing.assert_array_equal(t["future"][:, 1:], np.repeat(t["future"][:, :1], 4, axis=1))
    assert t["lane_change"].any(axis=1).all()  # every scene holds a lane change
    np.testing.assert_allclose(t["radius"], 0.5 * t["length"], rtol=1e-6)
    # frames and dt: states are the raw rows every 2 frames (10 Hz), shifted by the origin
    rid = int(t["recording"][0])
    df = pd.read_csv(raw / "data" / f"{rid:02d}_tracks.csv").set_index(["trackId", "frame"])
    f0 = int(t["frame"][0])
    for a, tid in enumerate(t["track_id"][0]):
        frames = f0 + 2 * np.arange(-9, 21)
        rows = df.loc[[(int(tid), int(f)) for f in frames]]
        xy = rows[["xCenter", "yCenter"]].to_numpy() - t["origin"][0]
        got = np.concatenate([t["history"][0, :, a, :2], t["future"][0, 0, a, :, :2]])
        np.testing.assert_allclose(got, xy, atol=1e-4)
        v = np.hypot(rows["xVelocity"], rows["yVelocity"]).to_numpy()
        np.testing.assert_allclose(t["history"][0, :, a, 2], v[:10], atol=1e-4)
    # goal candidates lie on lane centre lines (on_lane) or on a lane boundary (no neighbour)
    for s in ("train", "test"):
        X = sp[s]
        loc = int(X["location"][0])
        rec = read_recording(raw, int(X["recording"][0]))
        lm = read_lanelet_map(find_map(raw, loc), rec.utm_origin, rec.lonlat, rec.speed_limit)
        pts = (X["goal_candidates"][:3] + X["origin"][:3, None, None]).reshape(-1, 2)
        on = X["goal_candidate_on_lane"][:3].reshape(-1)
        d = np.stack([ln.project(pts)[1] for ln in lm.road_map.lanes])  # (lanes, Q)
        w = np.array([ln.width for ln in lm.road_map.lanes])[:, None]
        assert on.any() and d[:, on].min(0).max() < 1e-2
        if (~on).any():
            assert np.abs(d[:, ~on] - 0.5 * w).min(0).max() < 1e-2
    # a second run keeps every shard
    args = ["generate", "exid", "--raw", str(raw), "--out", str(data), "--workers", "1"]
    args += ["--no-progress", *[f"--set={k}={v}" for k, v in EXTRACT.items()]]
    assert main(args) == 0
    assert ds.read_manifest(data)["shards"] == m["shards"]


def _write_recording(d, loc, tracks: dict[int, np.ndarray], rate=10.0):
    """A hand-made recording 00 at ``loc``: per track ``(n, 2)`` positions from frame 0."""
    (d / "data").mkdir(parents=True)
    rows, meta = [], []
    for tid, xy in tracks.items():
        v = np.gradient(xy, 1 / rate, axis=0)
        h = np.degrees(np.arctan2(v[:, 1], v[:, 0]))
        for f in range(len(xy)):
            r = dict(recordingId=0, trackId=tid, frame=f, xCenter=xy[f, 0], yCenter=xy[f, 1])
            r.update(heading=h[f] % 360, width=1.8, length=4.5, xVelocity=v[f, 0])
            r.update(yVelocity=v[f, 1], xAcceleration=0.0, yAcceleration=0.0)
            r.update(lonVelocity=np.hypot(*v[f]), latVelocity=0.0, lonAcceleration=0.0)
            rows.append({**r, "latAcceleration": 0.0})
        meta.append(
            dict(recordingId=0, trackId=tid, initialFrame=0, finalFrame=len(xy) - 1)
            | dict(numFrames=len(xy), width=1.8, length=4.5, **{"class": "car"})
        )
    pd.DataFrame(rows).to_csv(d / "data" / "00_tracks.csv", index=False)
    pd.DataFrame(meta).to_csv(d / "data" / "00_tracksMeta.csv", index=False)
    o = loc.utm_origin
    pd.DataFrame(
        [dict(recordingId=0, locationId=loc.id, frameRate=rate, xUtmOrigin=o[0], yUtmOrigin=o[1])]
    ).to_csv(d / "data" / "00_recordingMeta.csv", index=False)


def test_lane_change_filter_by_hand(raw, tmp_path):
    # four cars at 25 m/s on the two main lanes of location 0, no laneletId column (the
    # reader finds the lanelets on the map): no lane change, no scene
    loc = LOCATIONS[0]
    t = np.arange(100) / 10.0
    x0 = {1: 60.0, 2: 80.0, 3: 40.0, 4: 100.0}
    y0 = {1: 0.0, 2: -3.75, 3: -3.75, 4: 0.0}

    def make(d, change: bool):
        tr = {}
        for k in x0:
            y = np.full_like(t, y0[k])
            if change and k == 1:  # smooth move into the right lane between 4 s and 7 s
                u = np.clip((t - 4.0) / 3.0, 0, 1)
                y = -3.75 * (3 * u**2 - 2 * u**3)
            tr[k] = np.stack([x0[k] + 25.0 * t, y], axis=1)
        (d / "maps").mkdir(parents=True)
        shutil.copy(find_map(raw, 0), d / "maps")
        _write_recording(d, loc, tr)
        return ExidScenario.from_raw(d, neighbour_range=150).run_unit(0, None)

    none = make(tmp_path / "straight", change=False)
    assert len(none["history"]) == 0
    out = make(tmp_path / "change", change=True)
    assert len(out["history"]) > 0
    assert (out["track_id"][:, 0] == 1).all() and out["lane_change"][:, 0].all()
    assert not out["lane_change"][:, 1:].any()


def test_malformed_recordings(raw, tmp_path, capsys):
    def copy(name):
        d = tmp_path / name
        shutil.copytree(raw / "maps", d / "maps")
        (d / "data").mkdir()
        for n in ("tracks", "tracksMeta", "recordingMeta"):
            shutil.copy(raw / "data" / f"00_{n}.csv", d / "data")
        return d, d / "data" / "00_tracks.csv"

    d, f = copy("missing")
    pd.read_csv(f).drop(columns=["xCenter"]).to_csv(f, index=False)
    with pytest.raises(DatasetError, match=r"00_tracks\.csv:xCenter: missing column"):
        read_recording(d, 0)
    d, f = copy("text")
    lines = f.read_text().splitlines()
    cols = lines[0].split(",")
    j = cols.index("yCenter")
    cells = lines[4].split(",")
    cells[j] = "abc"
    lines[4] = ",".join(cells)
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"00_tracks\.csv:yCenter: .*'abc' in line 5"):
        read_recording(d, 0)
    d, f = copy("truncated")
    text = f.read_text()
    cut = text.index("\n", len(text) // 2) + 1
    cut = text.index(",", text.index(",", cut) + 1)  # inside a row, after two fields
    f.write_text(text[:cut])
    with pytest.raises(DatasetError, match=r"00_tracks\.csv:\w+: .*truncated file"):
        read_recording(d, 0)
    d, _ = copy("meta")
    fm = d / "data" / "00_tracksMeta.csv"
    pd.read_csv(fm).drop(columns=["class"]).to_csv(fm, index=False)
    with pytest.raises(DatasetError, match=r"00_tracksMeta\.csv:class: missing column"):
        read_recording(d, 0)
    # at the CLI: one line naming the file and column, exit status 2
    d, f = copy("cli")  # the bad test recording 00 and a good one 01 (the split needs two)
    pd.read_csv(f).drop(columns=["heading"]).to_csv(f, index=False)
    for n in ("tracks", "tracksMeta", "recordingMeta"):
        shutil.copy(raw / "data" / f"01_{n}.csv", d / "data")
    capsys.readouterr()
    out = tmp_path / "out"
    args = ["generate", "exid", "--raw", str(d), "--out", str(out), "--workers", "1"]
    assert main([*args, "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "00_tracks.csv:heading: missing column" in err[0], err


def test_generator_is_deterministic(tmp_path):
    o = HighwayOptions(recordings=1, duration=2.0, warmup=4.0, frame_rate=10.0, locations=(3,))
    generate_raw(tmp_path / "a", o, seed=5)
    generate_raw(tmp_path / "b", o, seed=5)
    generate_raw(tmp_path / "c", o, seed=6)
    for n in ("data/00_tracks.csv", "data/00_tracksMeta.csv", "maps/lanelet2/3_offramp-2.osm"):
        assert (tmp_path / "a" / n).read_bytes() == (tmp_path / "b" / n).read_bytes()
    a = (tmp_path / "a" / "data" / "00_tracks.csv").read_bytes()
    assert a != (tmp_path / "c" / "data" / "00_tracks.csv").read_bytes()
    # two worker processes write the same files as one process
    o2 = HighwayOptions(recordings=2, duration=2.0, warmup=4.0, frame_rate=10.0, locations=(3,))
    generate_raw(tmp_path / "d", o2, seed=5)
    st = generate_raw(tmp_path / "e", o2, seed=5, workers=2)
    assert st["written"] == 2
    for n in ("00_tracks.csv", "01_tracks.csv", "01_tracksMeta.csv", "01_recordingMeta.csv"):
        assert (tmp_path / "d" / "data" / n).read_bytes() == (
            tmp_path / "e" / "data" / n
        ).read_bytes()
    assert generate_raw(tmp_path / "e", o2, seed=5, workers=2)["written"] == 0  # all kept


def test_game_and_training_steps(data, tmp_path):
    import torch

    from learning.data import SceneDataset

    with SceneDataset(data, "train") as sd:
        game, batch = sd.game, sd.batch(np.arange(2))
    assert game.N == 4 and game.K == 20 and game.dt == pytest.approx(0.2)
    own = {n.split(".")[-1] for n in game.params.names if n.startswith("w.v0.")}
    assert own == {"goal", "lane", "vref", "velocity", "acceleration", "jerk"} | {
        "turn_rate",
        "turn_acceleration",
    }
    coll = [tm for tm in game.terms if tm.feature == "collision"]
    assert coll and all(list(tm.steps) == [5, 10, 15, 20] for tm in coll)
    assert batch["goal_candidates"].shape == (2, 4, 60, 2) and batch["paths"].dtype == torch.float32
    # r = L / 2 per agent (the paper): a parameter of the game that ours fills from the scene
    assert [game.params[f"radius.v{i}"].group for i in range(4)] == ["radius"] * 4
    from learning.models import ModelConfig, build_model

    torch.manual_seed(0)
    cfg = ModelConfig(kind="epo", modes=5, goal_decoder="candidates", hist_width=8, hist_layers=1)
    model = build_model(cfg, game).eval()
    with torch.no_grad():
        z = model.encoder(batch)
        p = model.game_params(batch, z)
    idx = game.params.group("radius")
    want = batch["radius"].to(p.dtype)[:, None].expand(2, 5, 4)
    assert torch.equal(p[..., idx], want) and not torch.allclose(want, torch.tensor(2.5))
    # a dataset written before the field existed keeps its game's one fixed radius
    from learning.data import dataset_game
    from scenarios.dataset import read_manifest

    m = read_manifest(data)
    del m["recipe"]["radius_per_agent"]
    old = dataset_game(m)
    assert "radius.v0" not in old.params and old.radii().tolist() == [2.5] * 4
    small = dict(hist_width=8, hist_layers=1, lane_width=8, global_width=16, heads=2, dec_width=16)
    sets = [f"--set={k}={v}" for k, v in small.items()]
    for kind, extra in (
        ("epo", ["--set", "goal_decoder=candidates", "--lm-steps", "2"]),
        ("sc", []),
    ):
        run = tmp_path / kind
        args = ["train", "--model", kind, "--data", str(data), "--out", str(run), "--epochs", "1"]
        args += ["--batch-size", "16", "--no-progress", *extra, *sets]
        assert main(args) == 0
        assert (run / "checkpoint.pt").exists()


def test_lane_path_follows_each_modes_goal(data):
    """The paper's c_lane: each mode's ``path`` block is the lane its goal candidate lies on
    (App. F.3), against a per-sample, per-agent, per-mode loop over the stored fields; a
    candidate on a lane boundary keeps the current lane; ``lane_path="current"`` and runs
    saved before the setting existed keep the current lane in every mode."""
    import torch

    from learning.data import SceneDataset
    from learning.models import ModelConfig, build_model
    from learning.train import TrainConfig

    with SceneDataset(data, "train") as sd:
        game, batch = sd.game, sd.batch(np.arange(min(len(sd), 12)))
        raw = sd.reader.read(np.arange(len(batch["index"])))
    B, N, P = batch["paths"].shape[:3]
    lanes = batch["lanes"].numpy()
    assert lanes.shape[1] == 3 * N and batch["goal_lane"].dtype == torch.int64
    # the stored fields, read directly: candidate g of agent i lies on lanes[3 i + lane]
    on = raw["goal_candidate_on_lane"].astype(bool)
    assert not on.all()  # the test data has candidates on a boundary (no neighbouring lane)
    torch.manual_seed(0)
    small = dict(hist_width=8, hist_layers=1, lane_width=8, global_width=16, heads=2)
    cfg = ModelConfig(kind="epo", modes=5, goal_decoder="candidates", dec_width=16, **small)
    model = build_model(cfg, game).eval()
    L = game.params
    with torch.no_grad():
        z = model.encoder(batch)
        dec = model.decode_goals(batch, z)
        top = dec["goal_index"].numpy()
        p = model.game_params(batch, z).numpy()
        p_cur = build_model(ModelConfig(**{**cfg.to_dict(), "lane_path": "current"}), game)
        p_cur.load_state_dict(model.state_dict())
        p_cur = p_cur.eval().game_params(batch, z).numpy()
    changed = 0
    for b in range(B):
        for i in range(N):
            sl = L[f"path.v{i}"].slice
            for m in range(5):
                g = top[b, i, m]
                c = raw["goal_candidate_lane"][b, i, g]
                want = lanes[b, 3 * i + c] if on[b, i, g] else batch["paths"][b, i].numpy()
                np.testing.assert_array_equal(p[b, m, sl], want.reshape(-1))
                np.testing.assert_array_equal(p_cur[b, m, sl], batch["paths"][b, i].reshape(-1))
                np.testing.assert_array_equal(
                    dec["goals"][b, m, i].numpy(), batch["goal_candidates"][b, i, g].numpy()
                )
                changed += bool(on[b, i, g] and c != 1)
    assert changed > 0  # some modes' goals lie on a neighbouring lane
    # the current lane is the middle lane of the agent's three
    np.testing.assert_array_equal(lanes[:, 1::3], batch["paths"].numpy())
    # a run saved before the setting existed was trained with the current lane
    saved = TrainConfig(model=cfg).to_dict()
    del saved["model"]["lane_path"]
    assert TrainConfig.from_dict(saved).model.lane_path == "current"
    with pytest.raises(Exception, match="model.lane_path"):
        ModelConfig(lane_path="left")
