"""depth/onnx (the generic metric depth runner and its presets) and depth/precomputed, on tiny ONNX
models whose output is a known function of the input: depth = a * (channel 0 of the network input) + b."""
from __future__ import annotations

import typing
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from ga3ce_prep.errors import ConfigError, FrameError, ModelFileError
from ga3ce_prep.estimators.depth.monodepth import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    PRESETS,
    MonoDepthEstimator,
    MonoDepthOptions,
    Preset,
    network_size,
    resolve_options,
)
from ga3ce_prep.frames import FrameRef
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.stages import backend_class
from ga3ce_prep.stages.base import BackendContext
from ga3ce_prep.store import open_store
from ga3ce_prep.synthetic.truth import TruthReader
from ga3ce_prep.testing.paper_models import linear_depth_model
from ga3ce_prep.testing.photos import K_from_hfov, photo, photo_frame
from ga3ce_prep.weights import registry as registry_models


def _rgb(h: int, w: int, r, g=40, b=200) -> np.ndarray:
    img = np.empty((h, w, 3), np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = r, g, b
    return img


K = K_from_hfov(64, 48)
CUSTOM = PRESETS["custom"]


def _est(path, fix: str = "units", **opt) -> MonoDepthEstimator:
    return MonoDepthEstimator(path, resolve_options("custom", MonoDepthOptions(**opt)), what="test", fix=fix)


def test_presets_sizes_follow_the_official_resize_rules():
    zoe, da = PRESETS["zoedepth"], PRESETS["depth-anything-v2-metric-indoor"]
    assert network_size(640, 480, zoe) == (384, 512)
    assert network_size(1920, 1080, zoe) == (384, 672)        # ZoeDepth's keep-aspect, sides multiples of 32
    assert network_size(640, 480, da) == (518, 686)           # lower bound 518, multiples of 14
    assert network_size(1920, 1080, da) == (518, 924)
    assert network_size(480, 640, da) == (686, 518)
    assert network_size(4000, 300, da) == (518, 6902)         # the other side to the nearest multiple
    assert network_size(1920, 1080, PRESETS["fastdepth"]) == (224, 224)
    assert (da.mean, da.std, da.interpolation) == (IMAGENET_MEAN, IMAGENET_STD, "cubic")
    assert PRESETS["depth-anything-v2-metric-outdoor"] == da
    assert set(typing.get_args(Preset)) == set(PRESETS)                   # the schema's names are the presets
    assert (zoe.input_range, zoe.mean, zoe.std, zoe.units) == ("0-1", (0, 0, 0), (1, 1, 1), "m")
    over = resolve_options("zoedepth", MonoDepthOptions(units="mm", size=(10, 20)))
    assert (over.units, over.size, over.multiple, over.resize) == ("mm", (10, 20), 32, "keep_aspect")


@pytest.mark.parametrize("layout", ["nchw", "nhwc"])
def test_normalisation_and_layout_reach_the_network(tmp_path, layout):
    m = linear_depth_model(tmp_path / "m.onnx", {"depth": (1.0, 0.0)}, layout=layout, size=(24, 32))
    img = _rgb(48, 64, 153)
    d = _est(m, layout=layout).predict(img, K).depth                       # 153 / 255 = 0.6
    np.testing.assert_allclose(d, 0.6, rtol=1e-6)
    d = _est(m, layout=layout, mean=(0.1, 0, 0), std=(0.25, 1, 1)).predict(img, K).depth
    np.testing.assert_allclose(d, (0.6 - 0.1) / 0.25, rtol=1e-6)           # (x - mean) / std
    d = _est(m, layout=layout, channels="bgr", mean=(0.3, 0, 0)).predict(img, K).depth
    np.testing.assert_allclose(d, 200 / 255 - 0.3, rtol=1e-6)               # blue comes first
    d = _est(m, layout=layout, input_range="0-255", std=(100.0, 1, 1)).predict(img, K).depth
    np.testing.assert_allclose(d, 1.53, rtol=1e-6)


def test_resize_back_keeps_the_image_layout(tmp_path):
    """A left/right split image through a network at another size and aspect comes back split
    where it was, at the image resolution."""
    m = linear_depth_model(tmp_path / "m.onnx", {"depth": (10.0, 0.0)})
    img = _rgb(48, 64, 51)
    img[:, 32:, 0] = 204
    for opt in (dict(size=(20, 20)), dict(size=(30, 40), resize="keep_aspect", multiple=7)):
        r = _est(m, interpolation="area", **opt).predict(img, K)
        assert r.depth.shape == (48, 64) and r.valid.all()
        np.testing.assert_allclose(r.depth[:, :26], 2.0, rtol=1e-5)
        np.testing.assert_allclose(r.depth[:, 38:], 8.0, rtol=1e-5)
        assert np.all(np.diff(r.depth[10]) >= -1e-5)                       # monotone across the edge
    e = _est(m, size=(30, 40), resize="keep_aspect", multiple=7)
    assert e.network_input(img).shape == (1, 3, 35, 42)                    # >= (30, 40), multiples of 7, aspect kept


def test_crop_and_focal_rescale(tmp_path):
    m = linear_depth_model(tmp_path / "m.onnx", {"depth": (0.0, 2.0)}, size=(30, 40))
    img = _rgb(40, 90, 100)                                                # wide: 4:3 crop is 53 x 40
    r = _est(m, crop_aspect=(4, 3), focal_px=50.0).predict(img, K)
    assert r.crop == (18, 0, 53, 40)
    assert not r.valid[:, :18].any() and not r.valid[:, 71:].any() and r.valid[:, 18:71].all()
    np.testing.assert_allclose(r.depth[:, 18:71], 2.0 * K[0, 0] * 40 / 53 / 50.0, rtol=1e-5)
    assert (r.depth[:, :18] == 0).all()


@pytest.mark.parametrize("units, b, metres", [("m", 2.5, 2.5), ("cm", 250.0, 2.5), ("mm", 2500.0, 2.5),
                                               ("inverse_m", 0.4, 2.5)])
def test_units_to_metres(tmp_path, units, b, metres):
    m = linear_depth_model(tmp_path / "m.onnx", {"depth": (0.0, b)}, size=(24, 32))
    np.testing.assert_allclose(_est(m, units=units).predict(_rgb(48, 64, 9), K).depth, metres, rtol=1e-6)


def test_implausible_depth_refused_naming_the_file_and_the_units(tmp_path):
    mm = linear_depth_model(tmp_path / "in_mm.onnx", {"depth": (0.0, 2400.0)}, size=(24, 32))
    with pytest.raises(FrameError, match=r"in_mm.onnx: median depth 2400 m \(read as units m\).*plausible 0.1-100 m; "
                                         r"read as .*mm \(2.4 m\).* it would be plausible: set the units"):
        _est(mm, fix="the units").predict(_rgb(48, 64, 9), K)
    metres = linear_depth_model(tmp_path / "in_m.onnx", {"depth": (0.0, 2.4)}, size=(24, 32))
    with pytest.raises(FrameError, match=r"in_m.onnx: median depth 0.0024 m \(read as units mm\).*m \(2.4 m\)"):
        _est(metres, units="mm").predict(_rgb(48, 64, 9), K)
    zero = linear_depth_model(tmp_path / "zero.onnx", {"depth": (0.0, 0.0)}, size=(24, 32))
    with pytest.raises(FrameError, match="no positive depth"):
        _est(zero).predict(_rgb(48, 64, 9), K)
    # inverse depth: pixels beyond the plausible maximum (near-zero inverse depth) become unknown
    inv = linear_depth_model(tmp_path / "inv.onnx", {"depth": (1.0, 0.0)}, size=(24, 32))
    img = _rgb(48, 64, 128)
    img[:, :20, 0] = 1                                                     # 1/255 -> 255 m
    r = _est(inv, units="inverse_m", interpolation="area").predict(img, K)
    assert not r.valid[:, :15].any() and (r.depth[:, :15] == 0).all()
    np.testing.assert_allclose(r.depth[:, 30:], 255 / 128, rtol=1e-5)


def test_output_by_name_or_index_and_interface_errors(tmp_path):
    m = linear_depth_model(tmp_path / "two.onnx", {"relative": (0.0, 7.0), "metric": (0.0, 2.0)}, size=(24, 32))
    img = _rgb(48, 64, 9)
    np.testing.assert_allclose(_est(m).predict(img, K).depth, 7.0)
    np.testing.assert_allclose(_est(m, output_index=1).predict(img, K).depth, 2.0)
    np.testing.assert_allclose(_est(m, output_name="metric").predict(img, K).depth, 2.0)
    with pytest.raises(ModelFileError,
                       match=r"two.onnx: no output named 'depth'; the outputs are \['relative', 'metric'\]"):
        _est(m, output_name="depth")
    with pytest.raises(ModelFileError, match="output_index 2 but the file has 2 outputs"):
        _est(m, output_index=2)
    with pytest.raises(ModelFileError, match="2 inputs"):
        _est(linear_depth_model(tmp_path / "in2.onnx", {"d": (1, 0)}, n_inputs=2, size=(24, 32)))
    with pytest.raises(ModelFileError, match=r"\[1, 24, 32, 3\] has 24 channels where layout nchw puts them; "
                                             r"expected 3 \(set layout: nhwc"):
        _est(linear_depth_model(tmp_path / "nhwc.onnx", {"d": (1, 0)}, layout="nhwc", size=(24, 32)))
    dyn = linear_depth_model(tmp_path / "dyn.onnx", {"d": (0, 2)})
    with pytest.raises(ModelFileError, match="no fixed height and width; set the depth backend's size"):
        _est(dyn)
    with pytest.raises(ModelFileError, match=r"fixed at 24x32 \(HxW\) but size is \[20, 20\]"):
        _est(m, size=(20, 20))
    fixed = _est(m, size=(30, 40), resize="keep_aspect", multiple=8)       # a 64x48 image needs 32x40 (HxW)
    with pytest.raises(FrameError, match=r"needs a 32x40 \(HxW\) input .* fixed at 24x32: export it at 32x40 "
                                         r"\(scripts/export_monodepth.py --image-size 64x48\), or set resize: stretch"):
        fixed.predict(img, K)
    with pytest.raises(ConfigError, match="crop_aspect"):
        _est(m, crop_aspect=(4,))


def _frame(tmp_path: Path, img: np.ndarray) -> FrameRef:
    path = tmp_path / "img.png"
    Image.fromarray(img).save(path)
    H, W = img.shape[:2]
    return FrameRef("f", "test", "s", path, K_from_hfov(W, H), (W, H), np.array([10, 10, 20, 20], np.float32))


def test_onnx_backend_resolves_its_preset(tmp_path):
    m = linear_depth_model(tmp_path / "m.onnx", {"depth": (1.0, 0.0)})           # dynamic size
    ctx = BackendContext(tmp_path)
    b = backend_class("depth", "onnx")({"model": str(m), "preset": "depth-anything-v2-metric-indoor", "threads": 1},
                                       ctx)
    b.check()
    dm = b.depth(_frame(tmp_path, _rgb(48, 64, 153)))
    np.testing.assert_allclose(dm.depth, (0.6 - 0.485) / 0.229, rtol=1e-4)  # ImageNet mean/std on red
    assert dm.valid.all()
    assert b.provenance()["options"]["size"] == [518, 518]
    with pytest.raises(ConfigError, match="preset: required"):
        backend_class("depth", "onnx")({"model": str(m)}, ctx)
    b = backend_class("depth", "onnx")({"model": str(m), "preset": "custom", "units": "mm"}, ctx)
    with pytest.raises(ModelFileError, match="no fixed height and width"):
        b.check()


def test_fastdepth_is_the_onnx_runner_with_the_fastdepth_preset(tmp_path):
    frame = photo_frame(tmp_path, "astronaut", photo("astronaut"), (150, 15, 300, 190))
    ctx = BackendContext(tmp_path)
    fast = backend_class("depth", "fastdepth")({"threads": 1}, ctx)
    generic = backend_class("depth", "onnx")({"model": str(registry_models.model_path("fastdepth")),
                                              "preset": "fastdepth", "threads": 1}, ctx)
    a, b = fast.depth(frame), generic.depth(frame)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.valid, b.valid)


def test_onnx_depth_end_to_end(tmp_path, synth_world):
    """A constant 3 m network through run_pipeline: head positions and object medians at z = 3 m."""
    m = linear_depth_model(tmp_path / "m.onnx", {"depth": (0.0, 3.0)}, size=(60, 80))
    s = run_pipeline("synthetic-oracle", synth_world, tmp_path / "s.zarr", progress=False, overrides={
        "stages.depth": {"backend": "onnx", "params": {"model": str(m), "preset": "custom", "threads": 1}}})
    st = open_store(tmp_path / "s.zarr")
    assert s.counts.frames_kept == 12
    np.testing.assert_allclose(st.frames["head_pos"][:, 2], 3.0, rtol=1e-6)
    assert len(st.objects["xyz"]) > 12
    np.testing.assert_allclose(st.objects["xyz"][:, 2], 3.0, rtol=1e-6)
    assert st.attrs["stages"]["depth"]["options"]["units"] == "m"


# ---------------------------------------------------------------------------------------------------
# depth/precomputed


def _truth_depths(world: Path) -> tuple[list[str], np.ndarray]:
    truth = TruthReader(world / "truth.h5")
    ids = list(truth.frame_ids)
    return ids, np.stack([truth.get(i).depth for i in ids])


def test_precomputed_depth_npz_equals_the_oracle_and_a_missing_frame_fails_alone(tmp_path, synth_world):
    ids, depth = _truth_depths(synth_world)
    np.savez(tmp_path / "d.npz", frame_id=np.array(ids[1:]), depth=depth[1:])
    over = {"stages.depth": {"backend": "precomputed", "params": {"file": str(tmp_path / "d.npz")}}}
    s = run_pipeline("synthetic-oracle", synth_world, tmp_path / "p.zarr", progress=False, overrides=over)
    run_pipeline("synthetic-oracle", synth_world, tmp_path / "o.zarr", progress=False, overrides=[
        "stages.depth.backend=oracle", "stages.depth.params={truth: '{data}/truth.h5'}"])
    p, o = open_store(tmp_path / "p.zarr"), open_store(tmp_path / "o.zarr")
    assert s.counts.frames_kept == 11
    assert s.counts.dropped_by_stage == {"depth": 1}
    assert f"frame {ids[0]} is not in" in p.failures["message"][0]
    assert ids[0] not in p.frames["id"].tolist()
    for i, fid in enumerate(p.frames["id"]):
        j = o.frames["id"].tolist().index(fid)
        np.testing.assert_allclose(p.objects_of(i), o.objects_of(j), atol=1e-6)
        np.testing.assert_allclose(p.frames["head_pos"][i], o.frames["head_pos"][j], atol=1e-6)


def test_precomputed_depth_hdf5_millimetres_and_units_checks(tmp_path, synth_world):
    import h5py

    ids, depth = _truth_depths(synth_world)
    mm = np.round(depth * 1000).astype(np.uint16)
    mm[0] *= 0                                                             # frames with no depth at all: the
    mm[3] *= 0                                                             # check reads the next one
    with h5py.File(tmp_path / "d.h5", "w") as f:
        f["frame_id"] = np.array(ids, dtype=h5py.string_dtype())
        f.create_dataset("depth", data=mm, chunks=(1, *mm.shape[1:]))
    ctx = BackendContext(synth_world)
    b = backend_class("depth", "precomputed")({"file": str(tmp_path / "d.h5"), "units": "mm"}, ctx)
    b.check()
    frames = {f.id: f for f in __import__("ga3ce_prep.datasets", fromlist=["open_dataset"]).open_dataset(
        "gfie", synth_world).frames()}
    dm = b.depth(frames[ids[1]])
    np.testing.assert_allclose(dm.depth, np.round(depth[1] * 1000) / 1000, atol=1e-6)
    np.testing.assert_array_equal(dm.valid, depth[1] > 0)
    with pytest.raises(FrameError, match=rf"depth of frame {ids[3]} in .*d.h5: no positive depth"):
        b.depth(frames[ids[3]])
    wrong = backend_class("depth", "precomputed")({"file": str(tmp_path / "d.h5")}, ctx)  # units m
    with pytest.raises(ConfigError, match=r"d.h5: median depth \d+ m \(read as units m\) is outside the plausible "
                                          r"0.1-100 m; read as .*mm \([\d.]+ m\).*: "
                                          r"set stages.depth.params.units \(now m\)"):
        wrong.check()
    small = frames[ids[1]]
    small.image_size = (80, 60)
    with pytest.raises(FrameError, match=r"160x120 but the image is 80x60"):
        b.depth(small)
    np.savez(tmp_path / "bad.npz", frame_id=np.array(ids), depth=depth[:, 0])
    with pytest.raises(ConfigError, match=r"'depth' has shape \(12, 160\) .*expected \(12, H, W\)"):
        backend_class("depth", "precomputed")({"file": str(tmp_path / "bad.npz")}, ctx).check()


def test_export_script_writes_a_file_the_runner_reads(tmp_path):
    """scripts/export_monodepth.py's export and check on a tiny torch network (depth = 1.5 + red)."""
    import importlib.util

    import torch

    spec = importlib.util.spec_from_file_location("export_monodepth",
                                                  Path(__file__).parents[1] / "scripts" / "export_monodepth.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)

    class Tiny(torch.nn.Module):
        def forward(self, x):
            return {"metric_depth": 1.5 + x[:, :1]}

    module = script.metric_module(lambda m, x: m(x)["metric_depth"])(Tiny())
    size = network_size(64, 48, PRESETS["zoedepth"])
    out = script.export(module, size, tmp_path / "zoe.onnx")
    check = script.verify(module, out, PRESETS["zoedepth"], (64, 48))
    assert check["input"] == [384, 512]
    assert check["max_abs_diff_m"] < 1e-6
    assert check["grey_median_m"] == pytest.approx(1.5 + 128 / 255, abs=1e-5)
    b = backend_class("depth", "onnx")({"model": str(out), "preset": "zoedepth", "threads": 1},
                                       BackendContext(tmp_path))
    b.check()
    np.testing.assert_allclose(b.depth(_frame(tmp_path, _rgb(48, 64, 51))).depth, 1.7, rtol=1e-5)
    with pytest.raises(FrameError, match=r"needs a 384x672 \(HxW\) input .* --image-size 1920x1080"):
        b.depth(_frame(tmp_path, _rgb(1080, 1920, 51)))
