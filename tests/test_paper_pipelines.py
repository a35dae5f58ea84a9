"""The bundled paper pipelines (`ga3ce_prep/pipelines/gfie.yaml`, `cad120.yaml`, `gafa.yaml`) end to end on
the synthetic world in each format, with tiny models of the paper's models' interfaces in a model
folder (`ga3ce_prep.testing.paper_models`); a missing or mismatching model stops before any work."""
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.errors import ModelFileError
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.store import open_store
from ga3ce_prep.synthetic import generate
from ga3ce_prep.testing.paper_models import CROP_DEPTH_MM, write_paper_models

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch 2.13 on TorchScript
FAST = ["stages.objects.params.decoder_mode=official",  # the scripted decoder has no SAM weights to restructure
        "stages.objects.params.points_per_side=4"]


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    folder = tmp_path_factory.mktemp("models")
    write_paper_models(folder, depth_m=2.0)
    return folder


@pytest.fixture(scope="module")
def worlds(tmp_path_factory):
    root = tmp_path_factory.mktemp("worlds")
    for fmt in ("gfie", "cad120", "gafa"):
        generate(fmt, root / fmt, scenes=2, frames_per_scene=8, seed=3, width=160, progress=False)
    return root


@pytest.mark.parametrize("fmt", ["gfie", "cad120"])
def test_gfie_and_cad120_pipelines_run_the_papers_models(fmt, models, worlds, tmp_path):
    out = tmp_path / f"{fmt}.zarr"
    args = ["run", "-p", fmt, "-d", str(worlds / fmt), "-o", str(out), "--models", str(models), "-q"]
    for o in FAST:
        args += ["--set", o]
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    s = open_store(out)
    assert len(s) == 16                                                   # every frame kept
    np.testing.assert_allclose(np.linalg.norm(s.frames["view"], axis=1), 1, atol=1e-5)   # GFIE's network
    assert (s.frames["obj_count"] == 4).all()                             # the four label quadrants
    assert np.isfinite(s.frames["pose"]).all()
    dist = np.linalg.norm(s.frames["pose"], axis=2).mean(1)               # the crop model's joints, metres
    assert ((0.5 < dist) & (dist < 12)).all()
    st = s.attrs["stages"]
    assert st["pose"]["backend"] == "torchscript"
    assert st["view"]["backend"] == "gfie"
    assert st["objects"]["backend"] == "mobilesam"
    assert len(st["view"]["models"]) == 1                                 # the checkpoint's SHA-256


def test_gafa_pipeline_runs_the_papers_models(models, worlds, tmp_path):
    out = tmp_path / "gafa.zarr"
    summary = run_pipeline("gafa", worlds / "gafa", out, overrides=FAST, models=models, progress=False)
    s = open_store(out)
    assert len(s) == summary.counts.frames_kept > 0
    fails = s.failures
    windows = sum("7-frame window" in m for m in fails["message"].tolist())
    assert windows == summary.counts.dropped_by_stage["view"]             # only frames without a window
    np.testing.assert_allclose(np.linalg.norm(s.frames["view"], axis=1), 1, atol=1e-5)
    assert np.isfinite(s.frames["pose"]).all()
    assert s.attrs["stages"]["depth"]["backend"] == "onnx"
    assert s.attrs["stages"]["view"]["backend"] == "gafa"
    assert CROP_DEPTH_MM == 3000.0


def test_a_missing_or_mismatching_model_stops_before_any_work(models, worlds, tmp_path):
    partial = tmp_path / "partial"
    shutil.copytree(models, partial)
    (partial / "gfiemodel.pt.tar").unlink()
    with pytest.raises(ModelFileError, match=r"stages.view.params.checkpoint: model file .*gfiemodel.pt.tar does not "
                                              r"exist; GFIE's released checkpoint"):
        run_pipeline("gfie", worlds / "gfie", tmp_path / "a.zarr", overrides=FAST, models=partial, progress=False)
    shutil.copy(models / "zoedepth.onnx", partial / "gafa_view.onnx")     # a depth network where GAFA's should be
    with pytest.raises(ModelFileError, match=r"GAFA view ONNX .*gafa_view.onnx"):
        run_pipeline("gafa", worlds / "gafa", tmp_path / "b.zarr", overrides=FAST, models=partial, progress=False)
    assert not (tmp_path / "a.zarr").exists()
    assert not (tmp_path / "b.zarr.work").exists()
