"""Reliability of the exiD-layout reader (scenarios/exid.py): hostile tables and maps.

Every numeric cell the reader uses goes through one check (``read_table`` with the
``Column`` s of the three tables): a cell that is not finite, outside its physical bound or
not a whole number where an integer is meant is refused naming the file, the column and
the line. Structural defects (a second recordingMeta row, a recordingId that is not the
file name's, a duplicate track or frame) and recordings of which no sample can be made are
refused naming what is wrong; a map far from the tracks (another location's, lat/lon
swapped, a node moved away) is refused naming the map file and the distance. The raw set is
two short recordings of the generator (locations 0 and 1), written once.
"""

from __future__ import annotations

import re
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from epo_casadi.errors import SpecError
from scenarios.dataset import DatasetError
from scenarios.exid import (
    MAX_GRID_CELLS,
    Column,
    ExidRecipe,
    ExidScenario,
    find_recordings,
    read_recording,
    read_table,
)
from scenarios.highway import HighwayOptions, generate_raw
from tests.helpers import cli, one_error_line

MAP0 = "maps/lanelet2/0_onramp-2.osm"
MAP1 = "maps/lanelet2/1_offramp-3.osm"
EXTRACT = dict(neighbour_range=150, max_scenes_per_recording=8)


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("exid_rel") / "raw"
    o = HighwayOptions(recordings=2, duration=24.0, warmup=20.0, frame_rate=10.0, locations=(0, 1))
    generate_raw(d, o, seed=0)
    return d


def copy(raw: Path, dst: Path) -> Path:
    shutil.copytree(raw, dst)
    return dst


def table(d: Path, name: str) -> Path:
    return d / "data" / f"00_{name}.csv"


def set_cell(path: Path, column: str, row: int, value: str) -> None:
    """Write ``value`` as the text of one cell (row 0 is line 2 of the file)."""
    df = pd.read_csv(path, dtype=str, keep_default_na=False)
    df.loc[row, column] = value
    df.to_csv(path, index=False)


def extract(d: Path, unit: int = 0) -> dict:
    return ExidScenario.from_raw(d, **EXTRACT).run_unit(unit, None)


def test_the_raw_set_is_read(raw):
    """The unmodified set passes every check and gives finite samples."""
    out = extract(raw)
    assert len(out["history"]) == 8
    for k in ("history", "future", "goal_candidates", "lanes", "radius"):
        assert np.isfinite(out[k]).all(), k
    assert (out["radius"] > 0).all() and (out["length"] > 0).all()


# a cell of each table, the text written there, and what the error says (the class: non-
# finite, out-of-bounds and fractional cells of any table, each named by file/column/line)
CELLS = [
    ("tracks", "xCenter", 3, "inf", "expected a finite number in [-1000000.0, 1000000.0], got inf"),
    ("tracks", "xCenter", 3, "1e300", "got 1e+300"),
    ("tracks", "yCenter", 5, "-inf", "got -inf"),
    ("tracks", "yCenter", 3, "NaN", "expected a number, got 'NaN'"),
    ("tracks", "xVelocity", 9, "1e5", "in [-100.0, 100.0], got 100000.0"),
    ("tracks", "latAcceleration", 2, "inf", "in [-100.0, 100.0], got inf"),
    ("tracks", "heading", 3, "1e9", "in [-360.0, 360.0]"),
    ("tracks", "width", 3, "-1.8", "in (0.0, 10.0], got -1.8"),
    ("tracks", "length", 4, "0", "in (0.0, 50.0], got 0.0"),
    ("tracks", "frame", 0, "0.5", "expected an integer in [0, 10000000], got 0.5"),
    ("tracks", "frame", 0, "-5", "expected an integer in [0, 10000000], got -5"),
    ("tracks", "trackId", 0, "inf", "expected an integer in [0, 2147483647], got inf"),
    ("tracksMeta", "length", 0, "-5", "in (0.0, 50.0], got -5.0"),
    ("tracksMeta", "width", 1, "0", "in (0.0, 10.0], got 0.0"),
    ("tracksMeta", "initialFrame", 0, "-5", "expected an integer in [0, 10000000], got -5"),
    ("tracksMeta", "numFrames", 2, "1.5", "expected an integer in [1, 10000001], got 1.5"),
    ("tracksMeta", "trackId", 0, "1e12", "expected an integer in [0, 2147483647]"),
    ("recordingMeta", "frameRate", 0, "inf", "in [1.0, 1000.0], got inf"),
    ("recordingMeta", "frameRate", 0, "1e9", "in [1.0, 1000.0], got 1000000000.0"),
    ("recordingMeta", "xUtmOrigin", 0, "inf", "in [-10000000.0, 10000000.0], got inf"),
    ("recordingMeta", "yUtmOrigin", 0, "-1e300", "got -1e+300"),
    ("recordingMeta", "locationId", 0, "0.7", "expected an integer in [0, 32767], got 0.7"),
    ("recordingMeta", "recordingId", 0, "1e20", "expected an integer in [0, 32767]"),
    ("recordingMeta", "speedLimit", 0, "inf", "in [-1.0, 100.0], got inf"),
    ("recordingMeta", "lonLocation", 0, "200", "in [-180.0, 180.0], got 200.0"),
    ("recordingMeta", "latLocation", 0, "nan", "expected a number, got 'nan'"),
]


@pytest.mark.parametrize(("name", "column", "row", "text", "says"), CELLS)
def test_every_cell_is_finite_and_within_bounds(raw, tmp_path, name, column, row, text, says):
    d = copy(raw, tmp_path / "r")
    f = table(d, name)
    set_cell(f, column, row, text)
    with pytest.raises(DatasetError) as e:
        read_recording(d, 0)
    assert e.value.where == f"{f}:{column}"
    assert says in e.value.message and e.value.message.endswith(f"in line {row + 2}")


def test_read_table_names_the_line_after_blank_lines(tmp_path):
    f = tmp_path / "t.csv"
    f.write_text("a,b,c\n1,2,x\n\n3,inf,y\n")
    with pytest.raises(DatasetError, match=r"t\.csv:b: .*got inf in line 4$"):
        read_table(f, [Column("a"), Column("b"), Column("c", text=True)])
    f.write_text("a,b,c\n1,2,x\n\n3,4, y \n\n")
    cols, lines = read_table(f, [Column("a", 0, 9, integer=True), Column("c", text=True)])
    assert lines.tolist() == [2, 4] and cols["a"].tolist() == [1.0, 3.0]
    assert cols["c"].tolist() == ["x", "y"]
    # an optional column may be absent; where present its cells are checked
    assert "z" not in read_table(f, [Column("z", required=False)])[0]
    with pytest.raises(DatasetError, match=r"t\.csv:a: expected an integer in \[0, 2\], got 3"):
        read_table(f, [Column("a", 0, 2, integer=True)])


def test_negative_vehicle_size_never_reaches_a_sample(raw, tmp_path):
    # the tracksMeta length is the sample's length and radius L / 2
    d = copy(raw, tmp_path / "r")
    f = table(d, "tracksMeta")
    df = pd.read_csv(f)
    df["length"] = -df["length"]
    df.to_csv(f, index=False)
    with pytest.raises(DatasetError, match=r"00_tracksMeta\.csv:length: .*got -\S+ in line 2$"):
        extract(d)


def test_one_recording_meta_row_with_the_file_names_id(raw, tmp_path):
    d = copy(raw, tmp_path / "two")
    f = table(d, "recordingMeta")
    df = pd.read_csv(f, dtype=str)
    pd.concat([df, df]).to_csv(f, index=False)
    with pytest.raises(DatasetError) as e:
        read_recording(d, 0)
    assert e.value.where == str(f)
    assert e.value.message == "expected one row (one recording), found 2 (lines 2, 3)"
    # from_raw reads the same row (for the recipe's location): the same refusal
    with pytest.raises(DatasetError, match="expected one row"):
        ExidScenario.from_raw(d)
    for name, row in (("recordingMeta", 0), ("tracksMeta", 3), ("tracks", 40)):
        d = copy(raw, tmp_path / name)
        f = table(d, name)
        set_cell(f, "recordingId", row, "1")
        with pytest.raises(DatasetError) as e:
            read_recording(d, 0)
        assert e.value.where == f"{f}:recordingId"
        assert e.value.message == (
            f"expected 0 (the recording of the file name), got 1 in line {row + 2}"
        )


def test_duplicate_tracks_and_frames_are_named(raw, tmp_path):
    d = copy(raw, tmp_path / "meta")
    f = table(d, "tracksMeta")
    df = pd.read_csv(f, dtype=str)
    df.loc[4, "trackId"] = df.loc[1, "trackId"]
    df.to_csv(f, index=False)
    with pytest.raises(DatasetError) as e:
        read_recording(d, 0)
    tid = int(df.loc[1, "trackId"])
    assert e.value.where == f"{f}:trackId"
    assert e.value.message == (
        f"track {tid} has two rows (lines 3 and 6); expected one row per track"
    )
    d = copy(raw, tmp_path / "rows")
    f = table(d, "tracks")
    df = pd.read_csv(f, dtype=str)
    pd.concat([df.iloc[:5], df.iloc[3:4], df.iloc[5:]]).to_csv(f, index=False)
    with pytest.raises(DatasetError) as e:
        read_recording(d, 0)
    assert e.value.where == f"{f}:frame"
    assert e.value.message.startswith(
        f"track {int(df.loc[3, 'trackId'])} has frame {int(df.loc[3, 'frame'])} twice "
        "(lines 5 and 7)"
    )
    # a track without a tracksMeta row is named as such (not as a truncated file)
    d = copy(raw, tmp_path / "extra")
    f = table(d, "tracksMeta")
    df = pd.read_csv(f, dtype=str)
    df.drop(index=2).to_csv(f, index=False)
    with pytest.raises(DatasetError, match=r"have rows here but none in 00_tracksMeta\.csv"):
        read_recording(d, 0)


def test_recording_numbers_of_file_names(raw, tmp_path):
    for bad in ("99999999999", "007"):
        d = copy(raw, tmp_path / bad)
        for n in ("tracks", "tracksMeta", "recordingMeta"):
            shutil.move(table(d, n), d / "data" / f"{bad}_{n}.csv")
        with pytest.raises(DatasetError) as e:
            find_recordings(d)
        assert e.value.where == str(d / "data" / f"{bad}_recordingMeta.csv")
        assert "expected a recording number from 00 to 32767" in e.value.message


def test_lanelet_ids_are_ids(raw, tmp_path):
    d = copy(raw, tmp_path / "r")
    f = table(d, "tracks")
    set_cell(f, "laneletId", 6, "1e99")
    with pytest.raises(DatasetError) as e:
        read_recording(d, 0)
    assert e.value.where == f"{f}:laneletId" and e.value.message.endswith("'1e99' in line 8")
    set_cell(f, "laneletId", 6, "-1")  # none: found on the map
    assert read_recording(d, 0).rows["laneletId"].min() == -1


def test_no_sample_can_be_made_is_said(raw, tmp_path):
    # every track one frame long: zero samples was returned without a word
    d = copy(raw, tmp_path / "short")
    t, m = table(d, "tracks"), table(d, "tracksMeta")
    df = pd.read_csv(t, dtype=str)
    df.groupby("trackId", sort=False).head(1).to_csv(t, index=False)
    meta = pd.read_csv(m, dtype=str)
    meta["finalFrame"], meta["numFrames"] = meta["initialFrame"], "1"
    meta.to_csv(m, index=False)
    with pytest.raises(DatasetError) as e:
        extract(d)
    assert e.value.where == str(t)
    assert e.value.message.startswith(
        "recording 00: no sample can be made: a scene needs 4 tracks that each span 30 "
        "samples (5.8 s), 0 do; the longest spans 1 (a sample every 2 frames at frameRate 10 Hz)"
    )
    # a frame rate that leaves too few samples in every track
    d = copy(raw, tmp_path / "rate")
    set_cell(table(d, "recordingMeta"), "frameRate", 0, "1000")
    with pytest.raises(
        DatasetError, match="no sample can be made.*every 200 frames at frameRate 1000 Hz"
    ):
        extract(d)


def test_resampled_size_is_checked_before_it_is_built(raw, tmp_path):
    # half the tracks moved to frames near 10^7: 10^7 / 2 samples x tracks > MAX_GRID_CELLS
    d = copy(raw, tmp_path / "r")
    t, m = table(d, "tracks"), table(d, "tracksMeta")
    df, meta = pd.read_csv(t), pd.read_csv(m)
    late = meta["trackId"][::2]
    shift = 9_999_000 - int(df["frame"].max())
    df.loc[df["trackId"].isin(late), "frame"] += shift
    meta.loc[meta["trackId"].isin(late), ["initialFrame", "finalFrame"]] += shift
    df.to_csv(t, index=False)
    meta.to_csv(m, index=False)
    assert len(meta) * 9_999_000 // 2 > MAX_GRID_CELLS
    with pytest.raises(SpecError) as e:
        extract(d)
    assert e.value.field == f"{t}:frame"
    assert f"over the limit of {MAX_GRID_CELLS:,} (memory:" in e.value.message


def _map_error(d: Path) -> DatasetError:
    with pytest.raises(DatasetError) as e:
        extract(d)
    return e.value


def _distance(msg: str) -> float:
    return float(re.search(r"are ([\d,]+) m from track", msg).group(1).replace(",", ""))


def test_a_map_far_from_the_tracks_is_refused(raw, tmp_path):
    # another location's map: lanes 12 km from the agents were written to the samples
    d = copy(raw, tmp_path / "other")
    shutil.copy(d / MAP1, d / MAP0)
    e = _map_error(d)
    assert e.where == str(d / MAP0) and "expected every track within 200 m" in e.message
    assert 5_000 < _distance(e.message) < 50_000
    # lat and lon swapped: 7,000 km
    d = copy(raw, tmp_path / "swap")
    text = (d / MAP0).read_text()
    (d / MAP0).write_text(re.sub(r'lat="([^"]+)" lon="([^"]+)"', r'lat="\2" lon="\1"', text))
    e = _map_error(d)
    assert e.where == str(d / MAP0) and _distance(e.message) > 1e6


def _first_bound_node(path: Path) -> ET.Element:
    root = ET.parse(path).getroot()
    rel = next(r for r in root.iter("relation") if r.find("tag[@v='lanelet']") is not None)
    way_id = next(m.get("ref") for m in rel.iter("member") if m.get("role") == "left")
    way = root.find(f"way[@id='{way_id}']")
    return root, root.find(f"node[@id='{way.find('nd').get('ref')}']"), rel.get("id")


@pytest.mark.parametrize(
    ("attr", "value", "says"),
    [
        ("lat", "1e300", "lat: expected a finite number in [-90.0, 90.0], got 1e+300"),
        ("lon", "inf", "lon: expected a finite number in [-180.0, 180.0], got inf"),
        ("lat", "nan", "lat: expected a finite number in [-90.0, 90.0], got nan"),
        ("local_x", "inf", "local_x: expected a finite number in [-10000000.0, 10000000.0]"),
    ],
)
def test_map_nodes_are_finite(raw, tmp_path, attr, value, says):
    d = copy(raw, tmp_path / "r")
    root, node, _ = _first_bound_node(d / MAP0)
    if attr.startswith("local"):
        ET.SubElement(node, "tag", k=attr, v=value)
    else:
        node.set(attr, value)
    ET.ElementTree(root).write(d / MAP0)
    e = _map_error(d)
    assert e.where == f"{d / MAP0}:node {node.get('id')}" and says in e.message


def test_a_misplaced_node_is_refused(raw, tmp_path):
    # one node of a bound moved to the pole: the lanelet's centre and width went with it
    d = copy(raw, tmp_path / "r")
    root, node, rid = _first_bound_node(d / MAP0)
    node.set("lat", "89.9")
    ET.ElementTree(root).write(d / MAP0)
    e = _map_error(d)
    assert e.where == f"{d / MAP0}:relation {rid}"
    assert "apart on average; expected at most 30 m" in e.message


def test_each_samples_lanes_are_near_its_agent(raw, tmp_path):
    """A lanelet 1.1 km away, given as the laneletId of the rows of a busy lanelet: every
    track stays near the map, but the lanes of its samples would be 1.1 km away."""
    d = copy(raw, tmp_path / "r")
    t = table(d, "tracks")
    df = pd.read_csv(t, dtype=str, keep_default_na=False)
    busy = df["laneletId"].value_counts().index[0]
    root = ET.parse(d / MAP0).getroot()
    rel = root.find(f"relation[@id='{busy}']")
    nodes = {n.get("id"): n for n in root.iter("node")}
    far = ET.fromstring(ET.tostring(rel))
    far.set("id", "900000")
    for m in far.iter("member"):
        if m.get("role") in ("left", "right"):
            way = ET.fromstring(ET.tostring(root.find(f"way[@id='{m.get('ref')}']")))
            way.set("id", str(900000 + int(way.get("id"))))
            for nd in way.iter("nd"):
                n = ET.fromstring(ET.tostring(nodes[nd.get("ref")]))
                n.set("id", str(900000 + int(n.get("id"))))
                n.set("lat", f"{float(n.get('lat')) + 0.01:.11f}")
                nd.set("ref", n.get("id"))
                root.insert(0, n)
            root.append(way)
            m.set("ref", way.get("id"))
    root.append(far)
    ET.ElementTree(root).write(d / MAP0)
    df.loc[df["laneletId"] == busy, "laneletId"] = "900000"
    df.to_csv(t, index=False)
    e = _map_error(d)
    assert e.where == str(d / MAP0)
    assert re.search(
        r"lanelet 900000 is 1,\d{3} m from track \d+ of recording 00 at frame", e.message
    )
    assert "expected the lanes of a sample within 200 m of its agent" in e.message


def test_recipe_ids_and_sizes(tmp_path):
    with pytest.raises(SpecError, match=r"exid\.test_locations\[0\]: expected an integer"):
        ExidRecipe(test_locations=[0.7])
    with pytest.raises(SpecError, match=r"exid\.recordings\[0\]\[0\]: expected an integer"):
        ExidRecipe(recordings=[[1e20, 0]])
    with pytest.raises(SpecError, match=r"exid\.lane_points: 1,000,000,000 is over the limit"):
        ExidRecipe(lane_points=10**9)
    assert ExidRecipe(test_locations=[np.int64(2)]).test_locations == (2,)


def test_cli_one_line(raw, tmp_path, capsys):
    def generate(d, out, *extra):
        args = ["generate", "exid", "--raw", d, "--out", out, "--workers", "1", "--no-progress"]
        return cli(capsys, *args, *extra)

    d = copy(raw, tmp_path / "inf")
    set_cell(table(d, "tracks"), "xCenter", 3, "inf")
    rc, _, err = generate(d, tmp_path / "o1")
    one_error_line(rc, err, f"{table(d, 'tracks')}:xCenter:", "got inf in line 5")
    d = copy(raw, tmp_path / "map")
    shutil.copy(d / MAP1, d / MAP0)
    rc, _, err = generate(d, tmp_path / "o2")
    one_error_line(rc, err, f"{d / MAP0}: the map's lanes are", "within 200 m")
    rc, _, err = generate(raw, tmp_path / "o3", "--set", "test_locations=[0.7]")
    one_error_line(rc, err, "exid.test_locations[0]")
