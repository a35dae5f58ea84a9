"""GFIE's gaze-following modules ("GFM": stereo FoV + heatmap network), its 3D step and its metrics
(estimators/view/gfie_net.py, train/gfm.py) against hand-computed cases and GFIE's formulas' behaviour
on edge cases, and `eval --gfm` end to end on the synthetic GFIE-format world.
No real GFIE weights exist here: the checkpoints are random networks saved as GFIE saves them."""
import json
import shutil

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.estimators.view.gfie_head import load_gfie_head
from ga3ce_prep.estimators.view.gfie_net import (
    RECIPES,
    GFIENet,
    gaze_point_3d,
    head_location,
    load_gfie_net,
    matrix_t,
    scene_input,
    stereo_fov,
)
from ga3ce_prep.estimators.view.head_crop import head_input
from ga3ce_prep.frames import load_depth, load_rgb
from ga3ce_prep.geometry import angular_error_deg, normalize
from ga3ce_prep.model import ModelConfig
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.paper_models import gfie_checkpoint, gfie_state, random_gfie_net
from ga3ce_prep.testing.worlds import SMALL
from ga3ce_prep.train import ContextDataset, TrainConfig, evaluate, predict, train
from ga3ce_prep.train.checkpoint import build_model, load_checkpoint
from ga3ce_prep.train.gfm import heatmap_auc
from ga3ce_prep.viz import find_frame_refs

torch.set_num_threads(1)
SMALL_MODEL = dict(num_encoder_layers=1, num_decoder_layers=1, dim_feedforward=128, head_hidden=128)


@pytest.fixture(scope="module")
def net() -> GFIENet:
    return random_gfie_net(seed=1)


@pytest.fixture(scope="module")
def ckpt(net, tmp_path_factory):
    path = tmp_path_factory.mktemp("gfm") / "gfiemodel.pt.tar"
    torch.save(gfie_checkpoint(gfie_state(net)), path)
    return path


# --- the network and its checkpoint --------------------------------------------------------------

def test_gfie_net_has_gfies_key_names_and_shapes(net):
    sd = net.state_dict()
    assert len(sd) == 675
    assert sum(k.startswith("egd_module.") for k in sd) == 322
    assert sum(k.startswith("ggh_module.encoder.") for k in sd) == 318
    shapes = {"ggh_module.encoder.conv1.weight": (64, 6, 7, 7), "ggh_module.encoder.layer4.2.bn3.running_var": (2048,),
              "ggh_module.decoder.compress_conv1.weight": (1024, 2048, 1, 1),
              "ggh_module.decoder.compress_bn2.bias": (512,),
              "ggh_module.decoder.deconv1.weight": (512, 256, 3, 3), "ggh_module.decoder.deconv2.bias": (128,),
              "ggh_module.decoder.deconv3.weight": (128, 1, 4, 4), "ggh_module.decoder.deconv_bn3.running_mean": (1,),
              "ggh_module.decoder.conv4.weight": (1, 1, 1, 1), "ggh_module.decoder.conv4.bias": (1,)}
    assert {k: tuple(sd[k].shape) for k in shapes} == shapes
    assert not any(k.startswith(("psfov", "ggh_module.encoder.fc", "ggh_module.encoder.avgpool")) for k in sd)
    x = torch.randn(2, 3, 224, 224)
    t = torch.nn.functional.normalize(torch.randn(2, 224, 224, 3), dim=-1)
    with torch.inference_mode():
        heat, g = net(x, x, torch.zeros(2, 1, 224, 224), t)
        assert net.ggh_module.encoder(torch.zeros(1, 6, 224, 224)).shape == (1, 2048, 7, 7)
    assert heat.shape == (2, 64, 64) and g.shape == (2, 3)
    np.testing.assert_allclose(g.norm(dim=1).numpy(), 1, atol=1e-6)
    assert not torch.allclose(heat[0], heat[1])


def test_gfie_checkpoint_loads_strictly_and_reproduces_the_network(net, ckpt):
    loaded = load_gfie_net(ckpt)
    assert not loaded.training
    x = torch.randn(1, 3, 224, 224)
    t = torch.nn.functional.normalize(torch.randn(1, 224, 224, 3), dim=-1)
    with torch.inference_mode():
        a, b = loaded(x, x, torch.ones(1, 1, 224, 224), t), net(x, x, torch.ones(1, 1, 224, 224), t)
        np.testing.assert_allclose(a[0].numpy(), b[0].numpy(), atol=1e-5)
        np.testing.assert_allclose(a[1].numpy(), b[1].numpy(), atol=1e-6)
        fresh = GFIENet().eval()(x, x, torch.ones(1, 1, 224, 224), t)[0]
    assert not torch.allclose(fresh, b[0], atol=1e-3)
    assert load_gfie_head(ckpt)  # the head branch's loader reads the same file


# --- the inputs ----------------------------------------------------------------------------------

def test_stereo_fov_by_hand():
    t = torch.tensor([[[[0, 0, 1.0], [1, 0, 0]], [[0, 0, -1], [0.6, 0, 0.8]]]])  # (1, 2, 2, 3)
    f = stereo_fov(t, torch.tensor([[0, 0, 1.0]]))
    assert f.shape == (1, 2, 2, 2)
    np.testing.assert_allclose(f[0, 0].numpy(), [[1, 0], [0, 0.8]], atol=1e-7)
    np.testing.assert_allclose(f[0, 1].numpy(), [[1, 0], [0, 0.512]], atol=1e-6)


def test_head_location_by_hand():
    # (10, 20, 30, 60) expanded: (8, 16, 32.2, 64.4); / (100, 200) * 224 = (17.92, 17.92, 72.128, 72.128) -> int
    m = head_location(np.array([10, 20, 30, 60], np.float32), (100, 200))
    assert m.shape == (1, 1, 224, 224) and m.dtype == np.float32
    assert m.sum() == 55 * 55 and m[0, 0, 17, 17] == 1 and m[0, 0, 71, 71] == 1
    assert m[0, 0, 16, 17] == 0 and m[0, 0, 72, 71] == 0
    whole = head_location(np.array([-10, -10, 300, 300], np.float32), (100, 100))  # clipped to [0, 223]
    assert whole.sum() == 223 * 223 and whole[0, 0, 223].sum() == 0


def test_matrix_t_by_hand():
    K = np.array([[200.0, 0, 224], [0, 200, 112], [0, 0, 1]])
    depth = np.full((224, 448), 2.0, np.float32)
    # grid (row 0, column 112) is pixel (224, 0): P = (0, (0 - 112) 2 / 200, 2) = (0, -1.12, 2)
    t = matrix_t(depth, (448, 224), K, np.zeros(3))
    assert t.shape == (1, 224, 224, 3) and t.dtype == np.float32
    np.testing.assert_allclose(t[0, 0, 112], normalize(np.array([0, -1.12, 2])), atol=1e-6)
    # a grid point at the eye itself: a zero vector, not NaN (grid (56, 112): P = (0, -0.56, 2))
    t = matrix_t(depth, (448, 224), K, np.array([0, -0.56, 2]))
    np.testing.assert_array_equal(t[0, 56, 112], 0)
    np.testing.assert_allclose(t[0, 0, 112], normalize(np.array([0, -0.56, 0])), atol=1e-6)
    # no depth: GFIE's T points from the eye to the camera; CAD-120's is 0
    eye = np.array([0.3, -0.2, 1.5])
    hole = np.zeros((224, 448), np.float32)
    np.testing.assert_allclose(matrix_t(hole, (448, 224), K, eye, RECIPES["gfie"])[0, 100, 100], normalize(-eye),
                               atol=1e-6)
    np.testing.assert_array_equal(matrix_t(hole, (448, 224), K, eye, RECIPES["cad120"]), 0)
    assert (RECIPES["gfie"].resample, RECIPES["cad120"].resample) == ("bicubic", "nearest")


# --- the 3D step ---------------------------------------------------------------------------------

K100 = np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]])  # a 100 x 100 image: 10 x 10 pixel windows


def _peak(row: int, col: int) -> np.ndarray:
    h = np.zeros((64, 64), np.float32)
    h[row, col] = 1
    return h


def test_3d_step_snaps_to_the_depth_pixel_along_g():
    depth = np.full((100, 100), 2.0, np.float32)
    target = np.array([(52 - 50) * 2 / 100, (47 - 50) * 2 / 100, 2.0])  # pixel (52, 47) at 2 m
    p = gaze_point_3d(depth, _peak(32, 32), normalize(target), np.zeros(3), K100)
    assert p.window == (45, 45, 55, 55)  # centre (50, 50), 0.1 W x 0.1 H
    np.testing.assert_allclose(p.point, target, atol=1e-12)
    np.testing.assert_allclose(p.direction, normalize(target), atol=1e-12)
    np.testing.assert_array_equal(p.target_2d, [0.5, 0.5])  # argmax / 64, no cell-centre offset
    assert float(np.linalg.norm(p.target_2d - [0.5, 0.75])) == pytest.approx(0.25)  # GFIE's L2
    # off the window, the window pixel closest in angle: the corner toward the target
    far = gaze_point_3d(depth, _peak(32, 32), normalize(np.array([-1.0, 1.0, 2.0])), np.zeros(3), K100)
    np.testing.assert_allclose(far.point, [(45 - 50) * 2 / 100, (54 - 50) * 2 / 100, 2], atol=1e-12)


def test_3d_step_window_at_the_image_border():
    depth = np.full((100, 100), 2.0, np.float32)
    g = normalize(np.array([0, 0, 1.0]))
    assert gaze_point_3d(depth, _peak(0, 0), g, np.zeros(3), K100).window == (0, 0, 10, 10)   # shifted right/down
    p = gaze_point_3d(depth, _peak(63, 63), g, np.zeros(3), K100)  # centre 98.4: shifted left/up
    assert p.window == (90, 90, 100, 100)
    np.testing.assert_allclose(p.point, [(90 - 50) * 0.02, (90 - 50) * 0.02, 2], atol=1e-12)  # nearest the axis
    np.testing.assert_array_equal(p.target_2d, [63 / 64, 63 / 64])


def test_3d_step_with_no_depth_gives_the_origin_and_a_zero_vector():
    eye, target = np.array([0.1, -0.2, 1.0]), np.array([0.5, 0.3, 3.0])
    p = gaze_point_3d(np.zeros((100, 100), np.float32), _peak(10, 50), normalize(target - eye), eye, K100)
    np.testing.assert_array_equal(p.point, 0)
    np.testing.assert_array_equal(p.direction, 0)
    assert angular_error_deg(p.direction, normalize(target - eye)) == pytest.approx(90)  # GFIE: arccos(0)
    assert float(np.linalg.norm(p.point - target)) == pytest.approx(np.linalg.norm(target))
    # every pixel with depth scores below 0 (g points back): GFIE's argmax takes a 0-depth pixel
    depth = np.full((100, 100), 2.0, np.float32)
    depth[52, 47] = 0
    p = gaze_point_3d(depth, _peak(32, 32), np.array([0, 0, -1.0]), np.zeros(3), K100)
    np.testing.assert_array_equal(p.point, 0)
    np.testing.assert_array_equal(p.direction, 0)


# --- the metrics ---------------------------------------------------------------------------------

def _sklearn_auc(labels: np.ndarray, scores: np.ndarray) -> float:
    """ROC AUC the way sklearn's roc_auc_score computes it: the ROC curve over the distinct scores
    (descending), integrated with the trapezoid rule."""
    order = np.argsort(-scores, kind="mergesort")
    s, y = scores[order], labels[order]
    last = np.r_[np.flatnonzero(np.diff(s)), len(s) - 1]  # the last index of each distinct score
    tps, fps = np.cumsum(y)[last], (last + 1) - np.cumsum(y)[last]
    tpr, fpr = np.r_[0, tps] / tps[-1], np.r_[0, fps] / fps[-1]
    return float(np.trapezoid(tpr, fpr))


def test_auc_by_hand():
    h = _peak(10, 20)
    assert heatmap_auc(h, [20.5 / 64, 10.5 / 64], (64, 64)) == 1.0
    assert heatmap_auc(h, [0.9, 0.9], (64, 64)) == pytest.approx(0.5 * 4094 / 4095)   # tied with every other 0
    # at twice the width each cell is 2 pixels: the target ties with its neighbour
    assert heatmap_auc(h, [40.5 / 128, 10.5 / 64], (128, 64)) == pytest.approx((8190 + 0.5) / 8191)
    flat = np.full((64, 64), 3.0, np.float32)
    assert heatmap_auc(flat, [0.3, 0.3], (640, 480)) == pytest.approx(0.5)


def test_auc_target_on_the_border_and_outside():
    h = _peak(63, 63)
    n, hot = 640 * 512, 10 * 8  # the (63, 63) cell covers columns 630-639 and rows 504-511
    expect = (n - hot + 0.5 * (hot - 1)) / (n - 1)
    for target in ([1.0, 1.0], [0.999, 0.999], [1.3, 1.0]):  # int(x W) clipped to W - 1, as GFIE
        assert heatmap_auc(h, target, (640, 512)) == pytest.approx(expect)
    for target in ([-0.1, 0.5], [0.5, -0.1], [np.nan, 0.5]):  # GFIE's roc_auc_score has no positive
        assert np.isnan(heatmap_auc(h, target, (640, 512)))


def test_auc_equals_sklearns_roc_auc_with_one_positive_pixel():
    rng = np.random.default_rng(0)
    for size in ((128, 64), (192, 128), (64, 256)):
        W, H = size
        heat = np.round(rng.normal(size=(64, 64)), 1).astype(np.float32)  # many ties
        up = np.repeat(np.repeat(heat, H // 64, 0), W // 64, 1)          # exact nearest upsampling
        for _ in range(5):
            gx, gy = rng.uniform(0, 1, 2)
            labels = np.zeros((H, W))
            labels[int(gy * H), int(gx * W)] = 1
            assert heatmap_auc(heat, [gx, gy], size) == pytest.approx(_sklearn_auc(labels.ravel(), up.ravel()),
                                                                      abs=1e-12)


def test_angle_as_gfie_computes_it():
    gt = normalize(np.array([1.0, 2.0, 3.0]))
    assert angular_error_deg(np.zeros(3), gt) == pytest.approx(90)   # a zero refined vector
    assert angular_error_deg(gt, gt) == 0                             # clipped: GFIE's arccos may give NaN
    assert angular_error_deg(-gt, gt) == pytest.approx(180)
    gt_zero = normalize(np.array([0.5, 0.5, 2.0]) - np.array([0.5, 0.5, 2.0]))  # target at the eye: GFIE's 0 vector
    np.testing.assert_array_equal(gt_zero, 0)
    assert angular_error_deg(gt, gt_zero) == pytest.approx(90)


# --- eval --gfm end to end -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def gfm_store(synth_world, ckpt, tmp_path_factory):
    """The synthetic GFIE-format world preprocessed with v from the random GFIE network's head."""
    out = tmp_path_factory.mktemp("gfmstore") / "s.zarr"
    over = [*SMALL, "stages.view.backend=gfie", f"stages.view.params={{checkpoint: {ckpt}}}"]
    assert run_pipeline("synthetic", synth_world, out, overrides=over, progress=False).counts.frames_kept == 12
    return out


def _train(store, out, **model):
    return train(TrainConfig(store=str(store), out=str(out), epochs=1, batch_size=16, warmup_epochs=1, progress=False,
                             model=ModelConfig(**SMALL_MODEL, **model))) / "best.pt"


def _by_hand(store, net, g, method):
    """Per-frame metrics of one method recomputed from the building blocks, one frame at a time."""
    st = open_store(store)
    rows = st.indices("test")
    refs = find_frame_refs(st, st.frames["id"][rows].tolist())
    out = []
    for k, i in enumerate(rows):
        f = refs[st.frames["id"][i]]
        rgb, depth = load_rgb(f.image_path), load_depth(f.depth_path, f.depth_scale)
        H, W = rgb.shape[:2]
        eye = f.eye.astype(np.float64)
        x = [torch.from_numpy(a) for a in (scene_input(rgb), head_input(rgb, f.head_box),
                                           head_location(f.head_box, (W, H)), matrix_t(depth, (W, H), f.K, eye))]
        with torch.inference_mode():
            heat, gv = net(*x, gaze=None if method == "gfie" else torch.from_numpy(g[k][None]))
        p = gaze_point_3d(depth, heat[0].numpy(), gv[0].numpy(), eye, f.K)
        t2 = f.gaze_2d.astype(np.float64) / [W, H]
        gt = normalize(f.gaze_target.astype(np.float64) - eye)
        out.append([heatmap_auc(heat[0].numpy(), t2, (W, H)), np.linalg.norm(p.target_2d - t2),
                    np.linalg.norm(p.point - f.gaze_target), angular_error_deg(p.direction, gt)])
    return np.array(out)


def test_eval_gfm_end_to_end(gfm_store, net, ckpt, synth_world, tmp_path):
    best = _train(gfm_store, tmp_path / "run")
    js = tmp_path / "e.json"
    res = CliRunner().invoke(cli, ["eval", "--store", str(gfm_store), "--checkpoint", str(best), "--cdf", "none",
                                   "--gfm", str(ckpt), "--gfm-batch-size", "3", "--threads", "1", "--json", str(js)])
    assert res.exit_code == 0, res.output
    assert "GFIE's Table 1 columns" in res.output and "4 of 4 frames" in res.output
    for label in ("GFIE ", "Ours ", "Ours + GFM "):
        assert any(line.startswith(label) for line in res.output.splitlines())
    r = json.loads(js.read_text())   # the JSON eval --json wrote
    m = r["gfm"]["methods"]
    assert r["gfm"]["n_scored"] == r["n_frames"] == 4 and not r["gfm"]["skipped"]
    assert m["ours"]["angle3d"] == pytest.approx(r["methods"]["model"]["mae3d"], abs=1e-3)
    assert all(np.isnan(m["ours"][k]) for k in ("auc", "l2", "dist3d"))
    # the batched pass (3 + 1 frames, GFIE's g and ours through one GFM pass) = frame by frame
    ds = ContextDataset(open_store(gfm_store), "test")
    g_ours = predict(build_model(load_checkpoint(best)), ds)
    for method in ("gfie", "ours_gfm"):
        hand = _by_hand(gfm_store, net, g_ours, "gfie" if method == "gfie" else "ours")
        got = [m[method][k] for k in ("auc", "l2", "dist3d", "angle3d")]
        np.testing.assert_allclose(got, np.nanmean(hand, axis=0), rtol=1e-4, atol=1e-4, err_msg=method)
        assert m[method]["n_auc"] == np.isfinite(hand[:, 0]).sum()
    assert 0 <= m["gfie"]["auc"] <= 1 and m["gfie"]["dist3d"] > 0
    # another g, other stereo-FoV maps, another heatmap (the random net's AUC moves by 1e-5 to 1e-3)
    assert m["gfie"]["auc"] != m["ours_gfm"]["auc"], m

    # a dataset copy that lost one frame's depth: that frame is listed and left out of every column
    data = tmp_path / "copy"
    shutil.copytree(synth_world, data)
    lost = ds.store.frames["id"][ds.rows[0]]
    (data / "depth" / f"{lost}.npy").unlink()
    r2 = evaluate(gfm_store, best, cdf_path=None, gfm=ckpt, data=data, threads=1)
    assert r2.gfm["n_scored"] == 3 and list(r2.gfm["skipped"]) == [lost]
    assert "depth file not found" in r2.gfm["skipped"][lost]
    assert r2.gfm["methods"]["gfie"]["n"] == 3


def test_ours_gfm_with_gfies_own_g_reproduces_gfie(gfm_store, ckpt, tmp_path):
    """An appearance-only checkpoint has g = v, and v here is GFIE's head network's own output: the
    "Ours + GFM" columns must then equal GFIE's."""
    r = evaluate(gfm_store, _train(gfm_store, tmp_path / "app", use_context=False), cdf_path=None, gfm=ckpt, threads=1)
    m = r.gfm["methods"]
    for k in ("auc", "l2", "dist3d", "angle3d"):
        assert m["ours_gfm"][k] == pytest.approx(m["gfie"][k], rel=1e-5, abs=1e-6), k
    assert m["ours"]["angle3d"] == pytest.approx(r.methods["view_prior"].mae3d, abs=1e-3)
