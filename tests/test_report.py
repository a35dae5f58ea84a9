"""The paper's figures and `ga3ce-prep report` (its page rendered in headless chromium); the
attention hook's own tests are in test_model.py."""
import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from PIL import Image

from ga3ce_prep.cli import cli
from ga3ce_prep.model import ModelConfig
from ga3ce_prep.testing.toy_store import ToyKnobs, write_toy_store
from ga3ce_prep.train import ContextDataset, TrainConfig, ablate, train
from ga3ce_prep.train.checkpoint import build_model, load_checkpoint
from ga3ce_prep.train.evaluate import object_attention
from ga3ce_prep.train.figures import choose_frames, figure_frames, make_figures
from ga3ce_prep.train.report import ReportError, report

torch.set_num_threads(2)
SMALL = dict(num_encoder_layers=1, num_decoder_layers=2, dim_feedforward=128, head_hidden=128)


# --- the figures and the report, on a toy store ------------------------------------------------------------

@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """A toy store, a 1-epoch run and a 2-row ablation (appearance, full) of small models."""
    root = tmp_path_factory.mktemp("report")
    store = write_toy_store(root / "toy.zarr", 160, seed=5, frames_per_scene=20,
                            knobs=ToyKnobs(p_missing_pose=0.1, p_no_objects=0.1))
    cfg = TrainConfig(store=str(store), out=str(root / "run"), epochs=1, batch_size=16, train_frames=32,
                      val_frames=16, warmup_epochs=1, progress=False, model=ModelConfig(**SMALL))
    run = train(cfg)
    ablate(cfg, root / "abl", rows=["appearance", "full"])
    return store, run, root / "abl"


def test_figures_are_written(toy, tmp_path):
    store, run, _ = toy
    ckpt = load_checkpoint(run / "best.pt")
    ds = ContextDataset(store, "test")
    paths = make_figures(build_model(ckpt), ds, tmp_path, n=6)
    assert set(paths) == {"qualitative", "attention", "egocentric"}
    sizes = {k: Image.open(p).size for k, p in paths.items()}
    assert all(p.stat().st_size > 20_000 for p in paths.values()), sizes
    assert sizes["qualitative"][0] > 1200 and sizes["qualitative"][1] > 500       # 2 rows of 3-4 panels
    fr = figure_frames(build_model(ckpt), ds, n=6)
    assert len(fr.rows) == 6 and np.all(np.diff(fr.error) >= 0)                   # best to worst
    np.testing.assert_allclose(fr.attention.sum(1) + fr.null, 1, atol=1e-5)     # the last layer's mean over heads
    assert (fr.attention[~fr.mask] == 0).all()
    # the appearance-only model has no attention: no attention figure, the rest is drawn
    app = make_figures(build_model(load_checkpoint(toy[2] / "appearance" / "seed0" / "best.pt")), ds, tmp_path / "app",
                       n=2)
    assert set(app) == {"qualitative", "egocentric"}


def test_object_attention_weighs_the_gazed_object(toy):
    """The figures of where the weight goes, against the model's own weights on one batch: every
    frame gazes at its first object."""
    store, run, abl = toy
    model = build_model(load_checkpoint(run / "best.pt")).eval()
    ds = ContextDataset(store, "test")
    b = ds.batch(np.arange(len(ds)))
    with torch.no_grad():
        _, w = model.object_weights(b.view, b.pose, b.head_pos, b.objects, b.mask)
    w, mask = w.numpy().astype(np.float64), b.mask.numpy()
    has = mask[:, 0]
    assert 0 < has.sum() < len(ds)                                    # the toy has frames without objects
    a = object_attention(model, ds, np.where(has[:, None], b.objects.numpy()[:, 0], np.nan))
    assert a["frames"] == len(ds) and a["at_object_frames"] == has.sum()
    assert a["null"] == pytest.approx(w[:, 0].mean(), abs=1e-5)
    assert a["null"] + a["objects"] == pytest.approx(1, abs=1e-5)
    assert a["on_target"] == pytest.approx(w[has, 1].mean(), abs=1e-5)
    objs = np.where(mask[has], w[has, 1:], -np.inf)
    assert a["target_top"] == pytest.approx(np.mean(objs[:, 0] >= objs.max(1)))
    assert a["chance_top"] == pytest.approx(np.mean(1 / mask[has].sum(1)))
    n = mask[has].sum(1)
    others = (w[has, 1:] * mask[has]).sum(1) - w[has, 1]
    assert a["per_other"] == pytest.approx(np.nanmean(np.where(n > 1, others / np.maximum(n - 1, 1), np.nan)),
                                           abs=1e-5)
    assert object_attention(model, ds, np.full((len(ds), 3), np.nan))["at_object_frames"] == 0
    no_objects = build_model(load_checkpoint(abl / "appearance" / "seed0" / "best.pt"))
    assert object_attention(no_objects, ds, np.zeros((len(ds), 3))) is None   # nothing to weigh


def test_choose_frames_spreads_over_the_errors():
    e = np.array([5.0, 1.0, 9.0, 3.0, 7.0, 2.0, 8.0, 4.0, 6.0, 0.0])
    pos = choose_frames(e, 3)
    assert e[pos].tolist() == [0.0, 4.0, 9.0]                    # quantiles 5%, 50%, 95% of 10 frames
    assert len(choose_frames(e, 50)) == 10


def test_report_page_and_its_errors(toy, tmp_path):
    store, run, abl = toy
    page = report(abl, out=tmp_path / "r")                    # an ablation folder: its full row's run
    text = page.read_text()
    for name in ("curves", "cdf", "per_scene", "ablation", "qualitative", "attention", "egocentric"):
        assert (tmp_path / "r" / f"{name}.png").stat().st_size > 10_000, name
        assert f"({name}.png)" in text
    assert text.count('<img src="data:image/png;base64,') == 7
    assert "Table 4" in text and "GA3CE (paper)" in text and "GA3CE (model)" not in text
    assert json.loads((tmp_path / "r" / "eval.json").read_text())["split"] == "test"
    # a plain run folder: no ablation, the page says how to add one
    text = report(run, out=tmp_path / "plain").read_text()
    assert text.count("<img ") == 6 and "holds no ablation" in text
    # what is missing, and how to make it
    with pytest.raises(ReportError, match="not a folder.*ga3ce-prep train"):
        report(tmp_path / "nope")
    partial = tmp_path / "partial"
    partial.mkdir()
    (partial / "config.json").write_text((run / "config.json").read_text())
    with pytest.raises(ReportError, match=r"lacks history\.csv, best\.pt.*ga3ce-prep train --store STORE --out"):
        report(partial)
    with pytest.raises(ReportError, match="store .*gone.zarr.*--store"):
        report(run, store=tmp_path / "gone.zarr")
    with pytest.raises(ReportError, match="no split 'dev'"):
        report(run, split="dev", out=tmp_path / "x")
    lone = tmp_path / "lone"
    lone.mkdir()
    (lone / "ablation.json").write_text((abl / "ablation.json").read_text())
    with pytest.raises(ReportError, match="without its full row.*--rows full"):
        report(lone)
    res = CliRunner().invoke(cli, ["report", str(partial)])
    assert res.exit_code != 0 and "lacks history.csv" in str(res.exception)


# --- the page in a real browser -------------------------------------------------------------------------

# Marks, after the load event, how many of the page's images are complete with a decoded width.
CHECK = ('<script>addEventListener("load", () => { const im = [...document.images]; document.body.setAttribute('
         '"data-images", im.filter(i => i.complete && i.naturalWidth > 0).length + "/" + im.length); });</script>')


def _rendered_images(page: Path, tmp_path: Path) -> tuple[int, int]:
    """(loaded, total) images of `page` as headless chromium renders it (a copy with CHECK added)."""
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.fail("chromium is not installed: run `make setup` (scripts/setup.sh installs Debian's chromium, "
                    "which this test needs to render the report page)")
    probe = page.with_name(f"probe_{page.name}")
    probe.write_text(page.read_text().replace("</body>", CHECK + "</body>"))
    profile = tempfile.mkdtemp(dir=tmp_path)
    res = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                          "--disable-component-update", "--disable-sync", "--no-first-run",
                          f"--user-data-dir={profile}", "--dump-dom", probe.as_uri()],
                         capture_output=True, text=True, timeout=120)
    found = re.search(r'<body[^>]*data-images="(\d+)/(\d+)"', res.stdout)
    assert found, f"chromium did not finish loading {probe} (rc {res.returncode}):\n{res.stderr[-2000:]}"
    return int(found[1]), int(found[2])


def test_report_renders_in_headless_chromium(toy, tmp_path):
    page = report(toy[2], out=tmp_path / "r")
    n_img = page.read_text().count("<img ")
    assert _rendered_images(page, tmp_path) == (n_img, n_img) and n_img == 7
    # the check sees a broken image: one PNG's bytes cut short
    text = page.read_text()
    start = text.index("base64,") + len("base64,")
    broken = page.with_name("broken.html")
    broken.write_text(text[:start] + "iVBORw0KGgoAAAAN" + text[text.index('"', start):])
    assert _rendered_images(broken, tmp_path) == (n_img - 1, n_img)
