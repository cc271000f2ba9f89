"""The benchmark protocol on recorded data: the focal agent's best-of-M and top-1 errors
(joint and marginal), subsets of a split by a per-sample field (``epo evaluate --subset``),
the overlap rate with each sample's radius or the game's, datasets without sizes scored
with circles, ``lanes_mask`` in batches and the encoder, and the recorded-data figure."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import scenarios.plotting
from epo_casadi.errors import SpecError
from learning.data import SceneDataset
from learning.evaluate import evaluate, parse_subset
from learning.metrics import FOCAL_METRICS, all_metrics, focal_errors
from learning.models import ModelConfig, build_model
from learning.show import show_predictions
from scenarios.dataset import FieldSpec, Scenario, generate
from scenarios.real.eth_ucy import EthUcyRecipe, EthUcyScenario
from tests.helpers import cli, one_error_line

TINY = dict(hist_width=8, hist_layers=1, lane_width=8, global_width=16, heads=2, dec_width=16)


# --------------------------------------------------------------------------------------
# the focal metrics by hand
# --------------------------------------------------------------------------------------
def _pred():
    """B = 2 samples, M = 3 modes, N = 2 agents, T = 2 steps; the truth of agent 0 is
    (1, 0), (2, 0); its modes are off by (0, a), (0, b) at the two steps."""
    off = {0: [(0.0, 3.0), (0.0, 1.0), (0.0, 0.5)], 1: [(1.0, 1.0), (2.0, 0.0), (0.0, 4.0)]}
    pred = torch.zeros(2, 3, 2, 2, 2)
    gt = torch.zeros(2, 2, 2, 2)
    gt[:, 0, :, 0] = torch.tensor([1.0, 2.0])
    for b in range(2):
        for m, (a, c) in enumerate(off[b]):
            pred[b, m, 0, :, 0] = torch.tensor([1.0, 2.0])
            pred[b, m, 0, :, 1] = torch.tensor([a, c])
        pred[b, :, 1] = 50.0 + b  # agent 1: far off, never the focal one
    return pred, gt


def test_focal_best_of_m_and_top1_joint_by_hand():
    pred, gt = _pred()
    # errors (step 1, step 2) of agent 0 per mode: sample 0: (0, 3), (0, 1), (0, 0.5), so
    # ADE 1.5, 0.5, 0.25 and FDE 3, 1, 0.5; sample 1: (1, 1), (2, 0), (0, 4), so ADE 1, 1, 2
    # and FDE 1, 0, 4
    probs = torch.tensor([[0.6, 0.3, 0.1], [0.2, 0.3, 0.5]])  # top-1: mode 0, mode 2
    m = focal_errors(pred, gt, probs, focal=0)
    assert m["ADE_focal"].tolist() == [0.25, 1.0]
    assert m["FDE_focal"].tolist() == [0.5, 0.0]  # the minima are taken separately
    assert m["ADE_focal_top1"].tolist() == [1.5, 2.0]
    assert m["FDE_focal_top1"].tolist() == [3.0, 4.0]
    # all_metrics with focal=0 adds exactly these; without, none of them
    full = all_metrics(pred, gt, probs, torch.tensor([0.3, 0.3]), focal=0)
    for k in FOCAL_METRICS:
        assert torch.equal(full[k], m[k]), k
    assert not set(FOCAL_METRICS) & set(all_metrics(pred, gt, probs, torch.tensor([0.3, 0.3])))
    # another focal slot scores that agent: agent 1 is 50 m off everywhere
    assert focal_errors(pred, gt, probs, focal=1)["ADE_focal"][0].item() > 49
    # a pad in the focal slot: NaN for that sample only
    mask = torch.tensor([[True, True], [False, True]])
    pm = focal_errors(pred, gt, probs, focal=0, mask=mask)
    assert pm["ADE_focal"][0].item() == 0.25 and math.isnan(pm["ADE_focal"][1].item())
    with pytest.raises(ValueError, match="focal"):
        focal_errors(pred, gt, probs, focal=2)


def test_focal_top1_of_a_marginal_model_is_the_agents_own():
    """Marginal probabilities (B, N, M): top-1 is agent 0's own most likely mode, whatever
    agent 1's probabilities are; the best of M is the same as for joint modes."""
    pred, gt = _pred()
    probs = torch.tensor(
        [
            [[0.1, 0.2, 0.7], [0.8, 0.1, 0.1]],  # agent 0 -> mode 2; agent 1 would say 0
            [[0.5, 0.3, 0.2], [0.1, 0.1, 0.8]],  # agent 0 -> mode 0; agent 1 would say 2
        ]
    )
    m = focal_errors(pred, gt, probs, focal=0)
    assert m["ADE_focal_top1"].tolist() == [0.25, 1.0]
    assert m["FDE_focal_top1"].tolist() == [0.5, 1.0]
    assert m["ADE_focal"].tolist() == [0.25, 1.0] and m["FDE_focal"].tolist() == [0.5, 0.0]
    full = all_metrics(pred, gt, probs, torch.tensor([0.3, 0.3]), focal=0)  # before joining
    assert full["ADE_focal_top1"].tolist() == [0.25, 1.0]


# --------------------------------------------------------------------------------------
# a hand-made dataset in the layout of the recorded-data readers
# --------------------------------------------------------------------------------------
class Hand(Scenario):
    """TEST-ONLY: the same hand-made samples in a train and a test unit, under the eth-ucy
    game (N = 2, one past step, T = 2, M = 2); ``drop`` leaves schema fields out, ``sizes``
    adds zero ``length`` / ``width``, ``extra`` more fields."""

    name = "eth-ucy"

    def __init__(self, rows: dict, drop=(), sizes=False, extra=None, meta=None):
        self.recipe = EthUcyRecipe(agents=2, history=1, horizon=2, modes=2)
        self.rows = {k: v for k, v in rows.items() if k not in drop}
        self.extra = dict(extra or {})
        if sizes:
            n = len(rows["history"])
            self.extra["length"] = (FieldSpec((2,), "float32", "m"), np.zeros((n, 2)))
            self.extra["width"] = (FieldSpec((2,), "float32", "m"), np.zeros((n, 2)))
        self._meta = {"focal_slot": 0} if meta is None else meta

    @property
    def n_units(self):
        return 2

    @property
    def units_per_shard(self):
        return 1

    def split_units(self, seed):
        return {"train": [0], "val": [], "test": [1]}

    def schema(self):
        base = {
            "history": FieldSpec((2, 2, 4), "float32", ""),
            "future": FieldSpec((2, 2, 2, 4), "float32", ""),
            "agents_mask": FieldSpec((2,), "bool", ""),
            "radius": FieldSpec((2,), "float32", ""),
            "min_distance": FieldSpec((), "float32", ""),
        }
        out = {k: v for k, v in base.items() if k in self.rows}
        out.update({k: fs for k, (fs, _) in self.extra.items()})
        return out

    def meta(self):
        return self._meta

    def run_unit(self, index, seed):
        out = {k: np.asarray(v).astype(self.schema()[k].dtype) for k, v in self.rows.items()}
        for k, (fs, v) in self.extra.items():
            out[k] = np.asarray(v).astype(fs.dtype)
        return out


def hand_rows() -> dict:
    """Three samples (positions chosen so every number below is exact):

    - s0: agent 0 walks +x 1 m a step from (-1, 0); agent 1 from (3, 2) to (3, 1.5). CV
      predicts agent 0 at (1, 0), (2, 0) and agent 1 at (3, 1), (3, 0.5): 1.118 m apart at
      step 2. Truth of agent 0: (1, 0.5), (2, 1): ADE 0.75, FDE 1. Radii 0.6 (sample) ->
      an overlap (1.2 > 1.118), the game's 0.3 -> none. min_distance 0.4.
    - s1: as s0 with the truth on CV's line (errors 0), sample radii 0.3, min_distance 3.
    - s2: agent 1 a pad; agent 0's truth (1, 0), (2, 2): ADE 1, FDE 2; min_distance inf.
    """
    hist = np.zeros((3, 2, 2, 4))
    hist[:, :, 0, :2] = [[-1, 0], [0, 0]]
    hist[:, :, 1, :2] = [[3, 2], [3, 1.5]]
    fut = np.zeros((3, 2, 2, 2, 4))
    cv1 = np.array([[3, 1], [3, 0.5]])
    fut[0, :, 0, :, :2] = [[1, 0.5], [2, 1]]
    fut[1, :, 0, :, :2] = [[1, 0], [2, 0]]
    fut[2, :, 0, :, :2] = [[1, 0], [2, 2]]
    fut[:2, :, 1, :, :2] = cv1
    hist[2, :, 1] = 0.0  # the pad: zeros, as the readers write
    return {
        "history": hist,
        "future": fut,
        "agents_mask": np.array([[True, True], [True, True], [True, False]]),
        "radius": np.array([[0.6, 0.6], [0.3, 0.3], [0.6, 0.0]]),
        "min_distance": np.array([0.4, 3.0, np.inf]),
    }


def hand_dataset(root: Path, name: str, **kw) -> Path:
    d = root / name
    generate(Hand(hand_rows(), **kw), d, seed=0, workers=1, progress=False)
    return d


def test_evaluate_focal_subsets_and_sample_radii_on_a_hand_made_dataset(tmp_path):
    d = hand_dataset(tmp_path, "hand")
    rep = evaluate([], d, "test", cv=True, subsets=["interacting", "min_distance>=1"])
    (r,) = rep.results
    assert r.samples == 3
    m = r.metrics
    assert m["ADE_focal"] == pytest.approx((0.75 + 0 + 1) / 3, abs=1e-6)
    assert m["FDE_focal"] == pytest.approx((1 + 0 + 2) / 3, abs=1e-6)
    # CV's modes are identical: the most likely mode is the best one
    assert m["ADE_focal_top1"] == pytest.approx(m["ADE_focal"], abs=1e-7)
    assert m["OR"] == pytest.approx(1 / 3)  # s0 overlaps with its own radii (0.6 + 0.6 m)
    assert "OR_circle" not in m  # no sizes: circles only
    inter, far = rep.subsets
    assert inter.subset.text == "min_distance < 1" and far.subset.text == "min_distance >= 1"
    (ri,) = inter.results
    assert ri.samples == 1 and ri.metrics["ADE_focal"] == pytest.approx(0.75)
    assert ri.metrics["OR"] == 1.0 and ri.metrics["FDE_focal"] == pytest.approx(1.0)
    (rf,) = far.results
    assert rf.samples == 2 and rf.metrics["ADE_focal"] == pytest.approx(0.5)  # s1, s2 (inf)
    assert rf.metrics["OR"] == 0.0
    md = rep.markdown()
    assert "OR: circles of the sample radii (field radius)" in md
    assert "ADE_focal/FDE_focal: the focal agent (slot 0), best of the M modes" in md
    assert "Subset `interacting` (`min_distance < 1`) of split `test`" in md
    assert "(1 of 3 samples)" in md and "(2 of 3 samples)" in md
    assert md.splitlines()[2].endswith(
        "| ADE_focal | FDE_focal | ADE_focal_top1 | FDE_focal_top1 |"
    )
    paths = rep.write(tmp_path / "out" / "results")
    names = sorted(p.name for p in paths)
    assert names == sorted(
        [
            "results.md",
            "results.csv",
            "results_runs.csv",
            "results_interacting.csv",
            "results_interacting_runs.csv",
            "results_min_distance_ge_1.csv",
            "results_min_distance_ge_1_runs.csv",
        ]
    )
    rows = _csv(tmp_path / "out" / "results_interacting_runs.csv")
    assert rows[0]["subset"] == "min_distance < 1" and rows[0]["samples"] == "1"
    assert "subset" not in _csv(tmp_path / "out" / "results_runs.csv")[0]


def _csv(path: Path) -> list[dict]:
    import csv

    return list(csv.DictReader(path.read_text().splitlines()))


def test_overlap_uses_the_game_radii_without_a_radius_field(tmp_path):
    d = hand_dataset(tmp_path, "noradius", drop=("radius",))
    (r,) = evaluate([], d, "test", cv=True).results
    assert r.metrics["OR"] == 0.0  # 0.3 + 0.3 m < 1.118 m
    assert "OR: circles of the game's radii" in evaluate([], d, "test", cv=True).markdown()


def test_sizes_mean_boxes_and_the_circles_stay_the_sample_radii(tmp_path):
    """A dataset with length / width gets box OR (here size 0: never an overlap, the defect
    a reader avoids by not writing sizes it does not have) and OR_circle of the sample radii."""
    d = hand_dataset(tmp_path, "sizes", sizes=True)
    rep = evaluate([], d, "test", cv=True)
    (r,) = rep.results
    assert r.metrics["OR"] == 0.0 and r.metrics["OR_circle"] == pytest.approx(1 / 3)
    assert "OR_circle: circles of the sample radii (field radius)" in rep.markdown()


def test_no_focal_slot_no_focal_metrics(tmp_path):
    d = hand_dataset(tmp_path, "nofocal", meta={})
    rep = evaluate([], d, "test", cv=True)
    assert not set(FOCAL_METRICS) & set(rep.results[0].metrics)
    assert "ADE_focal" not in rep.markdown()


def test_subset_expressions_and_refusals(tmp_path, capsys):
    s = parse_subset("min_distance<1")
    assert (s.field, s.op, s.value, s.slug) == ("min_distance", "<", 1.0, "min_distance_lt_1")
    assert parse_subset("interacting").text == "min_distance < 1"
    assert parse_subset(" frame != 7 ").select(np.array([7, 8])).tolist() == [False, True]
    for bad in ("min_distance<<1", "min_distance", "1<min_distance", "x<nan", "x<abc"):
        with pytest.raises(SpecError, match="--subset"):
            parse_subset(bad)
    d = hand_dataset(tmp_path, "hand")
    base = ["evaluate", "--model", "cv", "--data", d]
    rc, _, err = cli(capsys, *base, "--subset", "speed<1")
    one_error_line(rc, err, "--subset", "'speed'", "min_distance")
    rc, _, err = cli(capsys, *base, "--subset", "history<1")  # not one number per sample
    one_error_line(rc, err, "--subset", "'history'")
    rc, _, err = cli(capsys, *base, "--subset", "min_distance<<1")
    one_error_line(rc, err, "--subset", "FIELD OP NUMBER")
    rc, out, err = cli(capsys, *base, "--subset", "interacting", "--out", tmp_path / "res")
    assert rc == 0, err
    assert "Subset `interacting`" in out and (tmp_path / "res" / "results_interacting.csv").exists()
    with SceneDataset(d, "test") as ds:
        assert ds.sample_field("min_distance").tolist() == [pytest.approx(0.4), 3.0, math.inf]
        assert "min_distance" in ds.scalar_fields() and "history" not in ds.scalar_fields()
        assert "min_distance" not in ds.batch([0])  # batches do not carry it
        with pytest.raises(SpecError, match="'nope' is not a field"):
            ds.sample_field("nope")


# --------------------------------------------------------------------------------------
# recorded datasets without sizes use circles
# --------------------------------------------------------------------------------------
def _write_eth(raw: Path) -> Path:
    """Four pedestrians side by side 2 m apart walking +x (biwi_eth.txt, the test scene),
    two more 0.8 m apart (interacting) later in the file, and a training file."""
    raw.mkdir(parents=True, exist_ok=True)
    rows = []
    for p in range(4):
        rows += [(10 * k, p + 1, 0.4 * k, 2.0 * p) for k in range(12)]
    rows += [(200 + 10 * k, 7, 0.4 * k, 30.0) for k in range(12)]
    rows += [(200 + 10 * k, 8, 0.4 * k, 30.8) for k in range(12)]
    for name, rs in (("biwi_eth.txt", rows), ("biwi_hotel.txt", rows)):
        rs = sorted(rs)
        (raw / name).write_text("".join(f"{f}.0\t{p}.0\t{x!r}\t{y!r}\n" for f, p, x, y in rs))
    return raw


@pytest.fixture(scope="module")
def eth_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("eth")
    raw = _write_eth(root / "raw")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sc = EthUcyScenario.from_raw(
            raw, agents=3, history=3, horizon=4, modes=3, val_fraction=0, context_agents=2
        )
    generate(sc, root / "data", seed=0, workers=1, progress=False)
    return root / "data"


def test_recorded_data_without_sizes_use_circles_of_the_sample_radius(eth_dataset):
    with SceneDataset(eth_dataset, "test") as ds:
        assert "length" not in ds.fields and "radius" in ds.fields
        b = ds.batch(np.arange(len(ds)))
    assert "length" not in b
    rep = evaluate([], eth_dataset, "test", cv=True, subsets=["interacting"])
    (r,) = rep.results
    assert "OR_circle" not in r.metrics and "OR: circles of the sample radii" in rep.markdown()
    # the straight walks are CV's own (zero error); the pair 0.8 m apart does not overlap
    # with circles of 0.3 m; the interacting subset is the pair's 2 x 5 scenes of 30
    assert r.metrics["ADE_focal"] == pytest.approx(0.0, abs=1e-5) and r.metrics["OR"] == 0.0
    (ri,) = rep.subsets[0].results
    assert r.samples == b["index"].numel() == 30 and ri.samples == 10


# --------------------------------------------------------------------------------------
# lanes_mask
# --------------------------------------------------------------------------------------
def _lanes(n):
    """Three lane slots of 4 points; slot 2 empty (mask False) and filled with odd values."""
    lanes = np.zeros((n, 3, 4, 2))
    lanes[:, 0] = np.stack([np.linspace(-5, 5, 4), np.full(4, -1.0)], 1)
    lanes[:, 1] = np.stack([np.linspace(-5, 5, 4), np.full(4, 1.0)], 1)
    lanes[:, 2] = 7.0
    mask = np.array([[True, True, False]] * n)
    return lanes, mask


def test_lanes_mask_reaches_the_batch_and_masks_a_lane(tmp_path):
    lanes, mask = _lanes(3)
    extra = {
        "lanes": (FieldSpec((3, 4, 2), "float32", ""), lanes),
        "lanes_mask": (FieldSpec((3,), "bool", ""), mask),
    }
    d = hand_dataset(tmp_path, "lanes", extra=extra)
    with SceneDataset(d, "test") as ds:
        batch, game = ds.batch(np.arange(3)), ds.game
    assert batch["lanes_mask"].dtype == torch.bool
    assert batch["lanes_mask"].tolist() == mask.tolist()
    torch.manual_seed(0)
    for kind in ("vlstm", "epo"):
        over = {"goal_decoder": "regress", "lm_steps": 1, "layer_compiled": "no"}
        over = over if kind == "epo" else {}
        model = build_model(ModelConfig(kind=kind, modes=2, **TINY, **over), game).eval()
        with torch.no_grad():
            ref = model(batch)
            moved = dict(batch, lanes=batch["lanes"].clone())
            moved["lanes"][:, 2] = torch.tensor([40.0, -25.0])  # the empty slot's values
            got = model(moved)
            open_ = dict(moved, lanes_mask=torch.ones_like(batch["lanes_mask"]))
            unmasked = model(open_)  # the same values unmasked: another output
        for k in ("pos",):
            assert torch.equal(got[k], ref[k]), (kind, k)
            assert not torch.equal(unmasked[k], ref[k]), (kind, k)


# --------------------------------------------------------------------------------------
# the figure
# --------------------------------------------------------------------------------------
def _figures(monkeypatch):
    figs = []
    monkeypatch.setattr(scenarios.plotting, "save_figure", lambda fig, *a, **k: figs.append(fig))
    return figs


def test_recorded_figure_draws_the_scene_in_the_world_frame(eth_dataset, tmp_path, monkeypatch):
    """ETH/UCY: the real agents' history (solid) and truth (dashed), every mode of every real
    agent, the others of the sample in grey (observed and future part each one line), in the
    recording's frame (the origin added back)."""
    from scenarios.dataset import SplitReader

    with SplitReader(eth_dataset, "test") as r:
        raw = r.read_all()
    # a sample of the four side by side: N = 3 of them, the fourth one of the others
    i = int(np.flatnonzero(raw["agents_mask"].all(1) & (raw["track_id"][:, 0] == 1))[0])
    o = raw["others"][i]  # (2, 8, 2): pedestrian 4 and a NaN row
    assert np.isfinite(o[0]).all() and np.isnan(o[1]).all()
    figs = _figures(monkeypatch)
    show_predictions("cv", eth_dataset, i, tmp_path / "a.png")
    show_predictions("cv", eth_dataset, i, tmp_path / "b.png", frame="scene")
    world, scene = (f.axes[0] for f in figs)
    lines = world.get_lines()
    solid = [ln for ln in lines if ln.get_linestyle() == "-"]
    dashed = [ln for ln in lines if ln.get_linestyle() == "--"]
    dotted = [ln for ln in lines if ln.get_linestyle() == ":"]
    # 3 histories + 3 modes x 3 agents + the other's observed part; 3 truths; its future
    assert (len(lines), len(solid), len(dashed), len(dotted)) == (3 + 9 + 1 + 3 + 1, 13, 3, 1)
    hist = [ln for ln in lines if ln.get_label().endswith(" history")]
    assert len(hist) == 3
    origin = raw["origin"][i]
    h = raw["history"][i]
    np.testing.assert_allclose(hist[0].get_xydata(), h[:, 0, :2] + origin, atol=1e-5)
    grey = [ln for ln in lines if ln.get_label() == "other recorded agents (observed)"]
    np.testing.assert_allclose(grey[0].get_xydata(), o[0, :4] + origin, atol=1e-5)
    hs = [ln for ln in scene.get_lines() if ln.get_label().endswith(" history")]
    np.testing.assert_allclose(hs[0].get_xydata(), h[:, 0, :2], atol=1e-6)
    assert len(figs[0].axes) == 2  # the scene and the probability colour bar
    assert "world frame" in world.get_title() and "scene eth" in world.get_title()
    monkeypatch.undo()  # now written for real
    out = show_predictions("cv", eth_dataset, i, tmp_path / "c.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000


def test_recorded_figure_draws_the_lane_map(tmp_path, monkeypatch):
    lanes, mask = _lanes(3)
    extra = {
        "lanes": (FieldSpec((3, 4, 2), "float32", ""), lanes),
        "lanes_mask": (FieldSpec((3,), "bool", ""), mask),
        "origin": (FieldSpec((2,), "float64", ""), np.tile([100.0, -50.0], (3, 1))),
    }
    d = hand_dataset(tmp_path, "map", extra=extra)
    figs = _figures(monkeypatch)
    show_predictions("cv", d, 2, tmp_path / "m.png")  # agent 1 a pad
    ax = figs[0].axes[0]
    lanes_drawn = [ln for ln in ax.get_lines() if ln.get_color() == "0.85"]
    assert len(lanes_drawn) == 2  # the empty slot is not drawn
    np.testing.assert_allclose(lanes_drawn[0].get_xydata(), lanes[0, 0] + [100.0, -50.0])
    # one real agent: history, truth, 2 modes
    assert len(ax.get_lines()) == 2 + 1 + 1 + 2


@pytest.mark.skipif(
    not (Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "eth_ucy").is_dir(),
    reason="../shared/realdata/eth_ucy not present: the shipped files are not part of the repository",
)
def test_shipped_eth_scene_gets_the_focal_metrics_and_the_interacting_subset(tmp_path):
    """The shipped biwi_eth.txt as the test scene (hotel to train): every sample has a
    min_distance, CV's focal errors are finite and the interacting subset is a part."""
    raw = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "eth_ucy"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sc = EthUcyScenario.from_raw(
            raw, files=[["biwi_eth.txt", "eth"], ["biwi_hotel.txt", "hotel"]]
        )
    generate(sc, tmp_path / "d", seed=0, workers=1, progress=False)
    rep = evaluate([], tmp_path / "d", "test", cv=True, subsets=["interacting"])
    (r,) = rep.results
    (ri,) = rep.subsets[0].results
    assert r.samples == 364 and 0 < ri.samples < r.samples
    assert all(np.isfinite(r.metrics[k]) for k in FOCAL_METRICS)
    assert r.metrics["ADE_focal"] < r.metrics["FDE_focal"]
