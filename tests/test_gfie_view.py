"""`view/gfie` (GFIE's head network in torch, from GFIE's checkpoint layout) and `view/onnx` (any
head-crop network): the ResNet-50, the strict checkpoint loading, GFIE's head crop against
hand-computed values, the ONNX recipe, and both backends end to end on the synthetic world.
No real GFIE weights exist here: the checkpoints are random networks saved as GFIE saves them."""
import io
import pickle
import zipfile

import numpy as np
import onnx
import pytest
import torch
from click.testing import CliRunner
from onnx import TensorProto, helper

from ga3ce_prep.errors import ConfigError, FrameError, ModelFileError
from ga3ce_prep.estimators.cli import export_gfie_view
from ga3ce_prep.estimators.view.gfie_head import GFIEHeadEstimator, GFIEHeadNet, load_gfie_head
from ga3ce_prep.estimators.view.gfie_net import load_gfie_net
from ga3ce_prep.estimators.view.head_crop import CropParams, expand_box, head_crop, head_input
from ga3ce_prep.estimators.view.head_onnx import HeadOnnxEstimator, HeadOnnxOptions
from ga3ce_prep.estimators.view.resnet import ResNet50
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.paper_models import gfie_checkpoint, gfie_state, random_gfie_net
from ga3ce_prep.testing.worlds import SMALL

torch.set_num_threads(1)

# (c / 255 - ImageNet mean) / ImageNet std of the RGB colour (200, 100, 50), by hand
RGB = (200, 100, 50)
RGB_NORMALISED = np.array([(200 / 255 - 0.485) / 0.229, (100 / 255 - 0.456) / 0.224, (50 / 255 - 0.406) / 0.225])


@pytest.fixture(scope="module")
def gfie_full():
    """GFIE's whole network, random: the checkpoints hold all of it, as GFIE's does."""
    return random_gfie_net()


@pytest.fixture(scope="module")
def gfie_net(gfie_full) -> GFIEHeadNet:
    return gfie_full.egd_module


@pytest.fixture(scope="module")
def ckpt_path(gfie_full, tmp_path_factory):
    path = tmp_path_factory.mktemp("gfie") / "gfiemodel.pt.tar"
    torch.save(gfie_checkpoint(gfie_state(gfie_full)), path)
    return path


def uniform_image(h: int, w: int, rgb=RGB) -> np.ndarray:
    return np.broadcast_to(np.array(rgb, np.uint8), (h, w, 3)).copy()


def gradient_image(h: int, w: int) -> np.ndarray:
    """Pixel (row i, column j) = (5 j, 3 i, 7) mod 256: every pixel says where it is."""
    i, j = np.mgrid[:h, :w]
    return np.stack([5 * j % 256, 3 * i % 256, np.full_like(i, 7)], -1).astype(np.uint8)


# --- ResNet-50 and the head network --------------------------------------------------------------

def test_resnet50_has_the_standard_parameter_count_and_torchvisions_keys():
    m = ResNet50()
    assert sum(p.numel() for p in m.parameters()) == 25_557_032
    sd = m.state_dict()
    assert len(sd) == 320  # 53 convs, 53 BNs x 5 (weight, bias, running mean/var, num_batches_tracked), fc
    shapes = {"conv1.weight": (64, 3, 7, 7), "bn1.running_var": (64,), "layer1.0.downsample.0.weight": (256, 64, 1, 1),
              "layer2.0.conv2.weight": (128, 128, 3, 3), "layer3.5.bn3.weight": (1024,),
              "layer4.2.conv3.weight": (2048, 512, 1, 1), "fc.weight": (1000, 2048), "fc.bias": (1000,)}
    assert {k: tuple(sd[k].shape) for k in shapes} == shapes
    assert "layer3.6.conv1.weight" not in sd and "layer1.1.downsample.0.weight" not in sd
    assert m.layer2[0].conv2.stride == (2, 2) and m.layer2[0].conv1.stride == (1, 1)  # torchvision's v1.5
    assert ResNet50(num_classes=None)(torch.zeros(1, 3, 64, 64)).shape == (1, 2048, 1, 1)


def test_head_network_has_gfies_key_names_and_a_unit_output(gfie_net):
    sd = GFIEHeadNet().state_dict()
    assert len(sd) == 318 + 4
    assert tuple(sd["backbone.0.weight"].shape) == (64, 3, 7, 7)
    assert tuple(sd["backbone.4.0.downsample.0.weight"].shape) == (256, 64, 1, 1)
    assert tuple(sd["backbone.7.2.bn3.running_var"].shape) == (2048,)
    assert tuple(sd["fc.0.weight"].shape) == (256, 2048) and tuple(sd["fc.2.weight"].shape) == (3, 256)
    assert not any(k.startswith(("backbone.2.", "backbone.3.", "backbone.8.", "backbone.9.")) for k in sd)
    with torch.inference_mode():
        v = gfie_net(torch.randn(3, 3, 224, 224))
    assert v.shape == (3, 3)
    np.testing.assert_allclose(v.norm(dim=1).numpy(), 1.0, atol=1e-6)
    assert not torch.allclose(v[0], v[1])


# --- the checkpoint ------------------------------------------------------------------------------

def test_gfie_checkpoint_loads_strictly_and_matches_the_model_in_memory(gfie_net, ckpt_path):
    x = torch.randn(2, 3, 224, 224)
    loaded = load_gfie_head(ckpt_path)
    assert not loaded.training
    with torch.inference_mode():
        np.testing.assert_allclose(loaded(x).numpy(), gfie_net(x).numpy(), atol=1e-6)
        assert not torch.allclose(GFIEHeadNet().eval()(x), gfie_net(x), atol=1e-3)


def _refused(tmp_path, state: dict, name: str = "bad.pth.tar", load=load_gfie_head) -> str:
    path = tmp_path / name
    torch.save(gfie_checkpoint(state), path)
    with pytest.raises(ModelFileError) as e:
        load(path)
    assert str(path) in str(e.value)
    return str(e.value)


def test_a_renamed_key_is_refused_naming_it(gfie_full, tmp_path):
    state = gfie_state(gfie_full)
    state["egd_module.fc.3.weight"] = state.pop("egd_module.fc.2.weight")
    msg = _refused(tmp_path, state)
    assert "missing keys: egd_module.fc.2.weight" in msg and "unexpected keys: egd_module.fc.3.weight" in msg


def test_an_extra_key_is_refused_naming_it(gfie_full, tmp_path):
    msg = _refused(tmp_path, {**gfie_state(gfie_full), "egd_module.backbone.8.weight": torch.zeros(1)})
    assert "unexpected keys: egd_module.backbone.8.weight" in msg and "missing" not in msg
    msg = _refused(tmp_path, {**gfie_state(gfie_full), "scene_branch.weight": torch.zeros(1)})
    assert "unexpected keys: scene_branch.weight" in msg


def test_a_misshapen_tensor_and_a_dataparallel_prefix_are_refused(gfie_full, tmp_path):
    state = gfie_state(gfie_full)
    state["egd_module.fc.2.weight"] = torch.zeros(2, 256)
    assert "wrong shapes: egd_module.fc.2.weight (2, 256) (expected (3, 256))" in _refused(tmp_path, state)
    msg = _refused(tmp_path, {"module." + k: v for k, v in gfie_state(gfie_full).items()})
    assert "missing keys: egd_module.backbone.0.weight" in msg and "(and 317 more)" in msg
    assert "unexpected keys: module.egd_module.backbone.0.weight" in msg and "DataParallel" in msg


def test_a_renamed_or_missing_heatmap_key_is_refused_naming_it(gfie_full, tmp_path):
    state = gfie_state(gfie_full)
    state["ggh_module.decoder.conv5.weight"] = state.pop("ggh_module.decoder.conv4.weight")
    msg = _refused(tmp_path, state, load=load_gfie_net)
    assert "missing keys: ggh_module.decoder.conv4.weight" in msg
    assert "unexpected keys: ggh_module.decoder.conv5.weight" in msg
    state = gfie_state(gfie_full)
    state["ggh_module.encoder.conv1.weight"] = torch.zeros(64, 3, 7, 7)  # a plain ResNet's conv1
    msg = _refused(tmp_path, state, load=load_gfie_net)
    assert "wrong shapes: ggh_module.encoder.conv1.weight (64, 3, 7, 7) (expected (64, 6, 7, 7))" in msg
    head_only = {k: v for k, v in gfie_state(gfie_full).items() if k.startswith("egd_module.")}
    msg = _refused(tmp_path, head_only, load=load_gfie_net)
    assert "missing keys: ggh_module.encoder.conv1.weight" in msg and "(and 348 more)" in msg
    path = tmp_path / "head_only.pth.tar"
    torch.save(gfie_checkpoint(head_only), path)
    load_gfie_head(path)  # enough for v


def _with_numpy1_names(obj) -> bytes:
    """torch.save of obj, its numpy scalars pickled under numpy 1.x's module name (GFIE saved its
    checkpoint with numpy 1.19: numpy.core.multiarray.scalar)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    src, out = zipfile.ZipFile(io.BytesIO(buf.getvalue())), io.BytesIO()
    with zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            dst.writestr(info, data.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
                         if info.filename.endswith("data.pkl") else data)
    return out.getvalue()


def test_weights_only_admits_numpy_1_scalars_and_nothing_that_runs_code(tmp_path):
    path = tmp_path / "numpy1.pth.tar"
    path.write_bytes(_with_numpy1_names(gfie_checkpoint({})))
    assert b"numpy.core.multiarray\nscalar" in zipfile.ZipFile(path).read("archive/data.pkl")
    with pytest.raises(ModelFileError, match="missing keys: egd_module.backbone.0.weight"):  # read, then refused
        load_gfie_head(path)
    evil = tmp_path / "evil.pth.tar"
    torch.save({"state_dict": {}, "x": pickle.loads}, evil)
    with pytest.raises(ModelFileError,
                       match=r"cannot read GFIE checkpoint .*evil.pth.tar with weights_only=True .*: "
                             r"Unsupported global: GLOBAL pickle.loads was not an allowed global by default$"):
        load_gfie_head(evil)
    torch.save({"model": {}}, evil)
    with pytest.raises(ModelFileError, match="is not a GFIE checkpoint: expected a dict with a 'state_dict'"):
        load_gfie_head(evil)
    with pytest.raises(ModelFileError, match="GFIE checkpoint not found"):
        load_gfie_head(tmp_path / "nope.pth.tar")


# --- GFIE's head crop ----------------------------------------------------------------------------

def test_box_expansion_is_gfies_sequential_one():
    np.testing.assert_allclose(expand_box(np.array([10, 20, 30, 60]), 0.1), [8, 16, 32.2, 64.4])  # -0.1 w, +0.11 w
    np.testing.assert_allclose(expand_box(np.array([10, 20, 30, 60]), 0.0), [10, 20, 30, 60])


def test_head_crop_truncates_the_expanded_corners_and_pads_with_black():
    img = gradient_image(50, 60)
    # (10, 10, 30, 30) -> (8, 8, 32.2, 32.2) -> pixels 8..31: 24 x 24, no resize at input_size 24
    np.testing.assert_array_equal(head_crop(img, np.array([10, 10, 30, 30]), CropParams(input_size=24)),
                                  img[8:32, 8:32])
    # x1 = 0.5 - 1.0 = -0.5 truncates toward zero, to 0 (not -1: no black column); x2 = 11.6 -> 11
    np.testing.assert_array_equal(head_crop(img, np.array([0.5, 0.5, 10.5, 10.5]), CropParams(input_size=11)),
                                  img[0:11, 0:11])
    # (-10, -10, 5, 5) -> (-11.5, -11.5, 6.65, 6.65) -> (-11, -11, 6, 6): 11 black rows and columns
    crop = head_crop(img, np.array([-10, -10, 5, 5]), CropParams(input_size=17))
    assert crop[:11].max() == 0 and crop[:, :11].max() == 0
    np.testing.assert_array_equal(crop[11:, 11:], img[0:6, 0:6])
    with pytest.raises(FrameError, match="crops to nothing"):
        head_crop(img, np.array([5, 5, 5.2, 9]), CropParams(box_expand=0.0))
    with pytest.raises(FrameError, match="not 4 finite"):
        head_crop(img, np.array([np.nan, 5, 9, 9]))


def test_the_resize_is_pillows_antialiased_bilinear():
    """1-px black/white stripes shrunk 3x: Pillow's bilinear averages them (113-142), a bilinear
    tap sampler (cv2.INTER_LINEAR) would keep 0 and 255."""
    img = np.zeros((700, 700, 3), np.uint8)
    img[:, 1::2] = 255
    crop = head_crop(img, np.array([0, 0, 672, 672]), CropParams(box_expand=0.0))
    assert crop.shape == (224, 224, 3) and 100 < crop.min() <= crop.max() < 155


def test_head_input_is_imagenet_normalised_rgb_nchw():
    x = head_input(uniform_image(120, 160), np.array([40, 30, 70, 80]))
    assert x.shape == (1, 3, 224, 224) and x.dtype == np.float32
    np.testing.assert_allclose(x[0, :, 0, 0], RGB_NORMALISED, rtol=1e-6)
    np.testing.assert_allclose(x[0, :, 223, 111], RGB_NORMALISED, rtol=1e-6)
    p = CropParams(channels="bgr", layout="nhwc", mean=(0.0, 0.0, 0.0), std=(1 / 255, 1 / 255, 1 / 255), input_size=8)
    y = head_input(uniform_image(120, 160), np.array([40, 30, 70, 80]), p)
    assert y.shape == (1, 8, 8, 3)
    np.testing.assert_allclose(y[0, 3, 5], [50, 100, 200], rtol=1e-6)


# --- view/onnx -----------------------------------------------------------------------------------

def channel_mean_onnx(path, size: int = 224, layout: str = "nchw", output: str = "out") -> None:
    """A model whose output (1, 3) is the mean of each input channel."""
    shape, axes = ([1, 3, size, size], [2, 3]) if layout == "nchw" else ([1, size, size, 3], [1, 2])
    nodes = [helper.make_node("ReduceMean", ["input"], ["m"], axes=axes, keepdims=0),
             helper.make_node("Identity", ["m"], [output])]
    graph = helper.make_graph(nodes, "channel_mean", [helper.make_tensor_value_info("input", TensorProto.FLOAT, shape)],
                              [helper.make_tensor_value_info(output, TensorProto.FLOAT, [1, 3])])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)]), str(path))


def test_onnx_view_applies_the_crop_recipe_and_the_axes(tmp_path):
    img, box = uniform_image(120, 160), np.array([40, 30, 70, 80])
    channel_mean_onnx(tmp_path / "m.onnx")
    v = HeadOnnxEstimator(tmp_path / "m.onnx", HeadOnnxOptions(threads=1)).estimate(img, box)
    np.testing.assert_allclose(v, RGB_NORMALISED / np.linalg.norm(RGB_NORMALISED), atol=5e-5)  # float32 mean of 50,176
    # BGR, NHWC, 32 px, no mean, std 1/255 (pixels 0-255): the model sees (50, 100, 200); its x is
    # our z, its y our -x, its z our -y
    channel_mean_onnx(tmp_path / "h.onnx", size=32, layout="nhwc", output="gaze")
    p = HeadOnnxOptions(channels="bgr", layout="nhwc", input_size=32, mean=(0, 0, 0), std=(1 / 255,) * 3,
                        axes=("z", "-x", "-y"), output="gaze", threads=1)
    v = HeadOnnxEstimator(tmp_path / "h.onnx", p).estimate(img, box)
    np.testing.assert_allclose(v, np.array([-100, -200, 50]) / np.linalg.norm([-100, -200, 50]), rtol=1e-5)


def test_onnx_view_refuses_a_model_that_does_not_fit_and_bad_axes(tmp_path):
    channel_mean_onnx(tmp_path / "m.onnx", size=112)
    with pytest.raises(ModelFileError, match=r"m.onnx: input 'input' .*expected shape \[1, 3, 224, 224\], "
                                             r"found \[1, 3, 112, 112\]"):
        HeadOnnxEstimator(tmp_path / "m.onnx", HeadOnnxOptions(threads=1))
    with pytest.raises(ModelFileError, match=r"no output named 'gaze'; its outputs: \['out'\]"):
        HeadOnnxEstimator(tmp_path / "m.onnx", HeadOnnxOptions(input_size=112, output="gaze", threads=1))
    with pytest.raises(ConfigError, match=r"axes: \['x', 'x', 'z'\] must name each of x, y, z once"):
        HeadOnnxEstimator(tmp_path / "m.onnx", HeadOnnxOptions(input_size=112, axes=("x", "x", "z"), threads=1))


# --- end to end ----------------------------------------------------------------------------------

def test_gfie_and_onnx_views_end_to_end(synth_world, ckpt_path, tmp_path):
    """Every frame of the synthetic world gets a unit v from the random GFIE network; exported to
    ONNX (`ga3ce-prep export-gfie-view`), `view/onnx` with its defaults gives the same v."""
    out = tmp_path / "s.zarr"
    gfie = [*SMALL, "stages.view.backend=gfie", f"stages.view.params={{checkpoint: {ckpt_path}}}"]
    assert run_pipeline("synthetic", synth_world, out, overrides=gfie, progress=False).counts.frames_kept == 12
    s = open_store(out)
    v_gfie = np.asarray(s.frames["view"], np.float64)
    np.testing.assert_allclose(np.linalg.norm(v_gfie, axis=1), 1.0, atol=1e-6)
    assert np.ptp(v_gfie, axis=0).max() > 1e-4  # the frames' crops differ, and so do their v
    assert s.attrs["stages"]["view"]["backend"] == "gfie"
    assert list(s.attrs["stages"]["view"]["models"]) == [str(ckpt_path)]  # with its SHA-256

    model = tmp_path / "gfie_head.onnx"
    res = CliRunner().invoke(export_gfie_view, ["--checkpoint", str(ckpt_path), "--out", str(model)])
    assert res.exit_code == 0, res.output
    onnx_view = [*SMALL, "stages.view.backend=onnx", f"stages.view.params={{model: {model}, threads: 1}}"]
    again = run_pipeline("synthetic", synth_world, out, overrides=onnx_view, progress=False)
    assert again.counts.frames_kept == 12 and again.computed_shards["depth"] == 0
    np.testing.assert_allclose(np.asarray(open_store(out).frames["view"]), v_gfie, atol=1e-4)


def test_onnx_view_end_to_end_with_a_tiny_model(synth_world, tmp_path):
    channel_mean_onnx(tmp_path / "m.onnx")
    out = tmp_path / "s.zarr"
    over = [*SMALL, "stages.view.backend=onnx", f"stages.view.params={{model: {tmp_path / 'm.onnx'}, threads: 1}}"]
    assert run_pipeline("synthetic", synth_world, out, overrides=over, progress=False).counts.frames_kept == 12
    v = np.asarray(open_store(out).frames["view"], np.float64)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-6)


def test_gfie_estimator_on_one_frame_equals_the_network_on_gfies_crop(gfie_net, ckpt_path):
    img, box = gradient_image(120, 160), np.array([60.4, 20.7, 80.2, 45.9], np.float32)
    v = GFIEHeadEstimator(ckpt_path).estimate(img, box)
    with torch.inference_mode():
        expected = gfie_net(torch.from_numpy(head_input(img, box)))[0].numpy()
    assert v.dtype == np.float32
    np.testing.assert_allclose(v, expected, atol=1e-6)


def test_a_network_that_gives_no_direction_fails_the_frame(ckpt_path):
    est = GFIEHeadEstimator(ckpt_path)
    with torch.no_grad():
        est.net.fc[2].weight.zero_()
        est.net.fc[2].bias.zero_()
    with pytest.raises(FrameError, match="not a direction"):
        est.estimate(uniform_image(120, 160), np.array([40, 30, 70, 80]))


def test_batched_views_equal_one_by_one_and_a_bad_image_fails_only_its_frame(synth_world, ckpt_path, tmp_path):
    """view/gfie runs a shard's heads in batches: the same v as one head per forward pass, and a
    frame whose image is damaged becomes a failure record while its batch neighbours are kept."""
    import shutil

    def views(batch: int, world, out):
        over = [*SMALL, "stages.view.backend=gfie", "run.shard_size=12",
                f"stages.view.params={{checkpoint: {ckpt_path}, batch_size: {batch}}}"]
        run_pipeline("synthetic", world, out, overrides=over, progress=False)
        return open_store(out)

    one, five = views(1, synth_world, tmp_path / "a.zarr"), views(5, synth_world, tmp_path / "b.zarr")
    np.testing.assert_array_equal(one.frames["id"], five.frames["id"])
    np.testing.assert_allclose(five.frames["view"], one.frames["view"], atol=1e-5)
    world = tmp_path / "world"
    shutil.copytree(synth_world, world)
    bad = sorted((world / "rgb").rglob("*.jpg"))[2]
    bad.write_bytes(bad.read_bytes()[:200])                     # truncated JPEG
    s = views(5, world, tmp_path / "c.zarr")
    assert len(s) == 11
    assert s.failures["stage"].tolist() == ["input"]            # caught by the input check, not the batch
