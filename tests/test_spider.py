"""Spider plots (learning.spider, ``epo show-weights``): per-agent own and pairwise weights,
normalized per mode, by hand; what the figure draws against the model run independently;
the lane-changer titles; bad input as ``epo show-predictions``."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from epo_casadi.errors import SpecError
from learning.data import SceneDataset
from learning.models import ModelConfig
from learning.spider import MARGIN, agent_titles, spider_weights, weight_spider
from learning.train import TrainConfig, train
from tests.helpers import cli, one_error_line
from tests.test_models import TINY, synthetic_dataset

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One epoch each of ours and SC, tiny widths, on the synthetic RPI set."""
    root = tmp_path_factory.mktemp("spider")
    for kind in ("epo", "sc"):
        cfg = TrainConfig(model=ModelConfig(kind=kind, **TINY), epochs=1, batch_size=4, seed=0)
        train(synthetic_dataset(), root / kind, cfg, progress=False)
    return root


def test_spider_weights_by_hand():
    names = ["w.a.goal", "w.a.lane", "w.b.goal", "w.b.lane", "w.a-b.collision", "radius.a"]
    groups = {"w_own": [0, 1, 2, 3], "w_pair": [4]}
    game = SimpleNamespace(
        params=SimpleNamespace(names=names, group=groups.__getitem__), agent_names=["a", "b"]
    )
    p = np.array([[1.0, 10.0, 100.0, 1.0, 10.0, 7.0], [2.0, 20.0, 200.0, 2.0, 20.0, 7.0]])
    w, axes = spider_weights(p, game)
    assert axes == ["goal", "lane", "collision"]
    # geometric mean of (1, 10, 100, 1, 10) is 10^(4/5); mode 1 is mode 0 scaled by 2: same plot
    want = np.log10(np.array([[1.0, 10.0, 10.0], [100.0, 1.0, 10.0]])) - 0.8
    np.testing.assert_allclose(w[0], want)
    np.testing.assert_allclose(w[1], want)


def test_agent_titles_from_the_lane_change_field():
    names = ["v0", "v1", "v2"]
    assert agent_titles({}, names) == names  # no field (RPI): no label
    flags = np.array([False, True, True])
    assert agent_titles({"lane_change": flags}, names) == [
        "v0",
        "v1 (lane changer)",
        "v2 (lane changer)",
    ]
    assert agent_titles({"lane_change": np.zeros(3, bool)}, names) == names
    with pytest.raises(SpecError, match="lane_change"):
        agent_titles({"lane_change": np.ones(2, bool)}, names)


def _distinct_probabilities(monkeypatch):
    """After one epoch the modes are about equally likely (0.50 / 0.50): shift the loaded
    model's logits by 0, 0.8, 1.6, ... so that a legend showing another mode's probability
    would be seen."""
    import learning.train

    load = learning.train.load_model

    def shift(module, inputs, out):
        return {**out, "logits": out["logits"] + 0.8 * torch.arange(out["logits"].shape[-1])}

    def load_shifted(*args, **kwargs):
        model, cfg, ck = load(*args, **kwargs)
        model.register_forward_hook(shift)
        return model, cfg, ck

    monkeypatch.setattr(learning.train, "load_model", load_shifted)
    return load_shifted


def test_show_weights_draws_the_models_weights(runs, tmp_path, capsys, monkeypatch):
    data, index = synthetic_dataset(), 2
    load_model = _distinct_probabilities(monkeypatch)
    png = tmp_path / "cli" / "w.png"
    rc, out, err = cli(capsys, "show-weights", runs / "epo", "--data", data, "--index", index,
                       "--out", png)  # fmt: skip
    assert rc == 0, err
    assert out.strip() == f"wrote {png}"
    assert png.read_bytes()[:8] == PNG and png.stat().st_size > 10_000

    res = weight_spider(runs / "epo", data, index, tmp_path / "b.png", return_data=True)
    assert res.path == tmp_path / "b.png" and res.path.read_bytes()[:8] == PNG
    # the reference: the saved model run directly on the sample, its parameters converted
    with SceneDataset(data, "test") as sd:
        game, batch = sd.game, sd.batch([index])
    model, _, _ = load_model(runs / "epo", game)
    with torch.no_grad():
        o = model(batch)
    probs = torch.softmax(o["logits"][0].double(), -1).numpy()
    ref, axes = spider_weights(o["params"][0].double().numpy(), game)
    M, N, F = ref.shape
    assert N == game.N and M > 1
    assert res.axes == axes and axes[-1] == "collision" and F > 3
    # the modes and agents differ, so a swapped mode or agent would be seen
    assert np.abs(ref[0] - ref[1]).max() > 1e-4 and np.abs(ref[:, 0] - ref[:, 1]).max() > 1e-2
    np.testing.assert_allclose(res.probs, probs, rtol=1e-6)
    assert np.diff(np.sort(probs)).min() > 0.05
    # what was drawn: one closed polygon per mode in each agent's polar panel, radius = the
    # normalized log10 weight minus one offset, the smallest radius MARGIN
    offset = np.nanmin(ref) - MARGIN
    panels = [ax for ax in res.figure.axes if ax.name == "polar"]
    assert len(panels) == N
    ang = np.linspace(0, 2 * np.pi, F, endpoint=False)
    for i, ax in enumerate(panels):
        assert ax.get_title() == game.agent_names[i]  # RPI has no lane_change field
        seen = []
        for line in ax.get_lines():
            m = int(re.fullmatch(r"mode (\d+) \(p=[0-9.]+\)", line.get_label()).group(1))
            seen.append(m)
            r, th = np.asarray(line.get_ydata()), np.asarray(line.get_xdata())
            assert r[-1] == r[0] and th[-1] == th[0]
            np.testing.assert_allclose(th[:-1], ang)
            np.testing.assert_allclose(r[:-1], ref[m, i] - offset, rtol=0, atol=1e-9)
        assert sorted(seen) == list(range(M))
        assert seen == list(np.argsort(-probs, kind="stable"))  # most likely drawn first
    assert min(np.min(ln.get_ydata()) for ax in panels for ln in ax.get_lines()) == pytest.approx(
        MARGIN
    )
    # the legend: every mode with its scene probability
    legend = [t.get_text() for t in panels[0].get_legend().get_texts()]
    got = {int(m): float(p) for m, p in (re.fullmatch(r"mode (\d+) \(p=(.*)\)", t).groups()
                                         for t in legend)}  # fmt: skip
    assert sorted(got) == list(range(M))
    for m in range(M):
        assert got[m] == pytest.approx(probs[m], abs=0.005 + 1e-9)


def test_show_weights_bad_input(runs, tmp_path, capsys):
    data = synthetic_dataset()
    png = tmp_path / "w.png"
    # not a run of ours: one line naming run_dir and what was expected
    rc, _, err = cli(capsys, "show-weights", runs / "sc", "--data", data, "--out", png)
    one_error_line(rc, err, "run_dir", "kind 'epo'", "'sc'", str(runs / "sc"))
    with pytest.raises(SpecError, match="run_dir"):
        weight_spider(runs / "sc", data, 0, png)
    # the checks of show-predictions, with its messages: index, run directory, split
    with SceneDataset(data, "test") as sd:
        n = len(sd)
    bad = [
        ["--index", n],
        ["--index", -1],
        ["--split", "dev"],
        ["--checkpoint", "first"],
    ]
    for extra in bad:
        for run in (runs / "epo", tmp_path / "no-run"):
            rc, _, err = cli(capsys, "show-weights", run, "--data", data, "--out", png, *extra)
            line = one_error_line(rc, err)
            rc, _, err2 = cli(capsys, "show-predictions", run, "--data", data, "--out", png, *extra)
            assert err2.strip() == line.replace("show-weights", "show-predictions")
    rc, _, err = cli(capsys, "show-weights", runs / "epo", "--data", data, "--index", n)
    one_error_line(rc, err, "index", f"[0, {n})", f"got {n}")
    rc, _, err = cli(capsys, "show-weights", tmp_path / "no-run", "--data", data, "--out", png)
    one_error_line(rc, err, str(tmp_path / "no-run"), "no such run directory")
    rc, _, err2 = cli(capsys, "show-predictions", tmp_path / "no-run", "--data", data)
    assert err2 == err
    rc, _, err = cli(capsys, "show-weights", runs / "epo", "--data", tmp_path / "no-data")
    one_error_line(rc, err, str(tmp_path / "no-data"))
    # an output path through a file: one line naming it, nothing written
    (tmp_path / "f").write_text("x")
    rc, _, err = cli(capsys, "show-weights", runs / "epo", "--data", data, "--out",
                     tmp_path / "f" / "w.png")  # fmt: skip
    one_error_line(rc, err, str(tmp_path / "f" / "w.png"), "is a file")
    assert not png.exists()
