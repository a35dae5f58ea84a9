"""`view: gafa`: GAFA's inputs against hand-computed values (boxes, the pre-blurred body crop, head
masks, body velocity, normalisation), the contiguity rule, the whole pipeline on a synthetic
GAFA-format world with a model whose gaze is a known function of its inputs, and the export
script on a stand-in GAFA install."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from PIL import Image

from ga3ce_prep.datasets import open_dataset
from ga3ce_prep.errors import FrameError, ModelFileError
from ga3ce_prep.estimators.view.gafa import (
    GafaViewEstimator,
    body_crop,
    body_velocity,
    head_masks,
    normalize_crops,
    pre_blur,
    preprocessed_boxes,
)
from ga3ce_prep.frames import frame_windows, load_rgb
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.scripted import centroid_gaze, centroid_gazenet
from ga3ce_prep.testing.worlds import GAFA_GAP

REPO = Path(__file__).resolve().parents[1]


def test_boxes_follow_gafa_preprocessing_integer_math():
    kp = np.zeros((1, 25, 3), np.float32)
    kp[0, [0, 1, 15, 16, 17], :2] = [[500.7, 300.2], [500.3, 400.9], [490.2, 290.8], [510.9, 290.1], [480.5, 295.5]]
    kp[0, 4, :2] = [0, 350]          # u = 0: GAFA counts a joint only when both coordinates are non-zero
    kp[0, 11, :2] = [520.6, 900.4]
    kp[0, 7, :2] = [430.9, 600.0]
    head, body = preprocessed_boxes(kp)
    # head joints truncated: u 480..510, v 290..400 (w 30, h 110); pads l = r = int(3.0) = 3,
    # t = int(93.5) = 93, b = int(-22.0) = -22 -> (477, 197, 36, 181); square: u - (181 - 36) // 2
    np.testing.assert_array_equal(head, [[405, 197, 181, 181]])
    # all joints: u 430..520, v 290..900 (90 x 610); pads 18, 18, int(91.5) = 91, int(30.5) = 30
    # -> (412, 199, 126, 731); square -> (110, 199, 731, 731); 3:4: diff = 731 / 4 = 182.75,
    # u + 182.75 // 2 = 201, w = 548.25 (a float, as GAFA stores it)
    np.testing.assert_array_equal(body, [[201, 199, 548.25, 731]])


def test_body_crop_rounds_the_box_as_pillow_does_and_pads_black():
    """A 192 x 256 box is cut without resampling: where it lands is Pillow's rounding of the float
    box (half to even), and rows above the image are black."""
    rows, cols = np.mgrid[0:300, 0:256]
    img = Image.fromarray(np.stack([cols, rows % 256, np.full_like(cols, 7)], -1).astype(np.uint8))
    out = body_crop(img, np.array([10.5, -5, 192, 256]))       # round(10.5) = 10, round(202.5) = 202
    assert out.shape == (256, 192, 3) and out.dtype == np.uint8
    assert (out[:5] == 0).all()
    np.testing.assert_array_equal(out[5:, :, 0], np.tile(np.arange(10, 202), (251, 1)))
    np.testing.assert_array_equal(out[5:, 0, 1], np.arange(0, 251))
    np.testing.assert_array_equal(body_crop(img, np.array([11.5, 0, 192, 256]))[0, :3, 0], [12, 13, 14])
    same = body_crop(img, np.array([10.0, 0, 191.5, 256]))            # round(201.5) = 202
    np.testing.assert_array_equal(same[:, :, 0], np.tile(out[5, :, 0], (256, 1)))


def test_pre_blur_keeps_what_a_720_px_wide_frame_holds():
    """Resized to width 720 and back: a 1440-wide frame loses its 1-px stripes and keeps 16-px
    ones; a 720-wide frame is unchanged."""
    fine = np.zeros((1080, 1440, 3), np.uint8)
    fine[:, ::2] = 255
    coarse = np.zeros_like(fine)
    coarse[:, (np.arange(1440) // 16) % 2 == 0] = 255
    f, c = (np.asarray(pre_blur(Image.fromarray(a))) for a in (fine, coarse))
    assert f.shape == fine.shape
    assert np.abs(f[:, 4:-4].astype(int) - 128).max() <= 1
    assert (c[:, 2:13] == 255).all() and (c[:, 19:29] == 0).all()
    small = np.random.default_rng(0).integers(0, 256, (500, 720, 3)).astype(np.uint8)
    np.testing.assert_array_equal(np.asarray(pre_blur(Image.fromarray(small))), small)


def test_pre_blurred_crop_lands_where_the_box_says():
    """A 1440 x 1080 frame, bright left of x = 720: the box (600, -50, 300.5 -> 300, 400) is
    resized by 0.64, so the edge (crop x 120) lands at output x 76.8 and the 50 black rows above
    the frame end at output row 32."""
    a = np.full((1080, 1440, 3), 40, np.uint8)
    a[:, :720] = 200
    out = body_crop(pre_blur(Image.fromarray(a)), np.array([600.0, -50, 300.5, 400]))[..., 0].astype(int)
    assert (out[:31] == 0).all() and (out[34:, :72] == 200).all() and (out[34:, 82:] == 40).all()
    assert out[100, 76] > 120 > out[100, 77]                  # the half-way crossing
    assert out[31, 10] < 100 < out[32, 10]


def test_head_mask_and_velocity_match_the_loader_by_hand():
    head, body = np.array([[405, 197, 181, 181], [150, 250, 50, 50]], float), np.array([[201, 199, 548.25, 731]] * 2)
    m = head_masks(head, body)
    assert m.shape == (2, 1, 256, 192) and m.dtype == np.float32
    # x1 = 204 / 548.25 * 192 = 71.4, x2 = x1 + 181 / 548.25 * 192 = 134.8; y1 = -2 / 731 * 256 -> 0,
    # y2 = -0.70 + 63.39 = 62.7: ones in rows 0-61, columns 71-133
    expect = np.zeros((256, 192), np.float32)
    expect[0:62, 71:134] = 1
    np.testing.assert_array_equal(m[0, 0], expect)
    # left of the body box: x = -51 / 548.25 * 192 = -17.9 -> 0, x2 = -17.9 + 17.5 -> -0.4 -> 0: empty
    assert m[1].sum() == 0
    dv = body_velocity(np.array([[10, 20, 30, 40], [13, 20, 30, 44], [13, 20, 30, 44]]))
    # centres over sizes: (25/30, 40/40), (28/30, 42/44), unchanged
    np.testing.assert_allclose(dv, [[0.1, 42 / 44 - 1], [0, 0]], atol=1e-6)
    x = normalize_crops(np.broadcast_to(np.uint8([0, 128, 255]), (1, 256, 192, 3)))
    assert x.shape == (1, 3, 256, 192)
    np.testing.assert_allclose(x[0, :, 5, 5], [-0.485 / 0.229, (128 / 255 - 0.456) / 0.224, (1 - 0.406) / 0.225],
                               rtol=1e-5)


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("gafa_view") / "centroid.onnx"
    onnx.save(centroid_gazenet(), p)
    return p


def test_contract_refuses_a_model_without_gafa_interface(model, tmp_path):
    bad = tmp_path / "bad.onnx"
    onnx.save(centroid_gazenet(window=5), bad)
    with pytest.raises(ModelFileError, match=r"input 'image' expected shape \[1, 7, 3, 256, 192\]"):
        GafaViewEstimator(bad)
    assert GafaViewEstimator(model).names["gaze"] == "gaze"


def _pipeline(model: Path, shard_size: int) -> dict:
    return {"name": "gafa-view", "dataset": {"format": "gafa"},
            "stages": {"depth": {"backend": "oracle"}, "objects": {"backend": "oracle"}, "head": {"backend": "depth"},
                       "pose": {"backend": "oracle"},
                       "view": {"backend": "gafa", "params": {"model": str(model), "threads": 1}}},
            "run": {"shard_size": shard_size}}


def _expected(frames) -> dict[str, np.ndarray]:
    """v for every frame with a full window, from the frames by hand: raw numbers index-3..index+3
    of its camera sequence all present; the frame before the window is the latest numbered below
    index-3, else the sequence's last; inputs as GAFA builds them, the model in numpy."""
    by_key = {(f.sequence, f.index): f for f in frames}
    out = {}
    for f in frames:
        win = [by_key.get((f.sequence, f.index + k)) for k in range(-3, 4)]
        if any(g is None for g in win):
            continue
        seq = sorted(g.index for g in frames if g.sequence == f.sequence)
        before = [n for n in seq if n < f.index - 3]
        prev = by_key[(f.sequence, before[-1] if before else seq[-1])]
        head, body = preprocessed_boxes(np.stack([g.keypoints_2d for g in [prev, *win]]))
        crops = np.stack([body_crop(pre_blur(Image.fromarray(load_rgb(g.image_path))), b)
                          for g, b in zip(win, body[1:])])
        gaze = centroid_gaze(normalize_crops(crops)[None], head_masks(head[1:], body[1:])[None],
                             body_velocity(body)[None])[0, 3]
        out[f.id] = gaze / np.linalg.norm(gaze)
    return out


def test_every_kept_frame_gets_the_models_gaze_for_its_window(model, synth_gafa_world, tmp_path):
    frames = list(open_dataset("gafa", synth_gafa_world).frames())
    expected = _expected(frames)
    # 6 sequences of raw frames 0-9: centres 3-6 have full windows; the sequence with raw frame 1
    # missing has two (5, 6), and frame 5's window (2-8) has frame 0 before it, across the gap
    assert len(expected) == 5 * 4 + 2
    assert {fid for fid in expected if fid.startswith(GAFA_GAP[0])} == {f"{GAFA_GAP[0]}/00000{i}" for i in (5, 6)}
    stores = {}
    for size in (3, 7):
        out = tmp_path / f"s{size}.zarr"
        summary = run_pipeline(_pipeline(model, size), synth_gafa_world, out, progress=False)
        stores[size] = open_store(out)
        assert summary.counts.frames_kept == len(expected)
        assert summary.counts.dropped_by_stage == {"view": len(frames) - len(expected)}
    s = stores[3]
    assert sorted(s.frames["id"]) == sorted(expected)
    for fid, v in zip(s.frames["id"], s.frames["view"]):
        np.testing.assert_allclose(v, expected[fid], atol=2e-6, err_msg=fid)
    msgs = set(s.failures["message"])
    assert f"no 7-frame window around frame 4 of {GAFA_GAP[0]}: raw frame(s) [1] missing (GAFA uses only runs of 7 " \
           "consecutive frames)" in msgs
    assert any("raw frame(s) [10, 11, 12] missing" in m for m in msgs)   # the end of a sequence
    for group in ("frames", "failures"):
        a, b = getattr(s, group), getattr(stores[7], group)
        assert sorted(a) == sorted(b)
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"{group}/{name}")


def test_a_frame_without_keypoints_or_window_fails_clearly(model, synth_gafa_world):
    from ga3ce_prep.stages.base import BackendContext
    from ga3ce_prep.stages.view import GafaView

    frames = list(open_dataset("gafa", synth_gafa_world).frames())
    b = GafaView({"model": str(model)}, BackendContext(synth_gafa_world))
    w = frame_windows(frames, 7)
    with pytest.raises(FrameError, match=r"raw frame\(s\) \[-3, -2, -1\] missing"):
        b.view(frames[0], w[0])
    frames[2].keypoints_2d = None
    with pytest.raises(FrameError, match="needs OpenPose BODY_25 keypoints"):
        b.view(frames[3], w[3])


FAKE_GAZENET = '''
import torch
from torch import nn


class Swishy(nn.Module):
    """Stands in for efficientnet_pytorch: its memory-efficient swish cannot be exported."""

    def __init__(self):
        super().__init__()
        self.memory_efficient = True

    def set_swish(self, memory_efficient=True):
        self.memory_efficient = memory_efficient

    def forward(self, x):
        if self.memory_efficient:
            raise RuntimeError("the memory-efficient swish cannot be exported")
        return x * torch.sigmoid(x)


class GazeNet(nn.Module):
    def __init__(self, n_frames):
        super().__init__()
        self.act = Swishy()
        self.fc = nn.Linear(2, 3)

    def forward(self, img, head_mask, body_dv):
        d = self.fc(self.act(body_dv)) + img.mean((2, 3, 4))[..., None] + head_mask.mean((2, 3, 4))[..., None]
        return {"direction": d / d.norm(dim=-1, keepdim=True)}, {}, {}
'''


def test_export_script_on_a_stand_in_gafa_install(tmp_path):
    """scripts/export_gafa_view.py imports GazeNet from the --gafa folder, loads the checkpoint's
    state_dict, switches swish, and writes a file the backend accepts with the same outputs."""
    torch = pytest.importorskip("torch")
    gafa = tmp_path / "gafa"
    (gafa / "models" / "weights").mkdir(parents=True)
    (gafa / "models" / "gazenet.py").write_text(FAKE_GAZENET)
    code: dict = {}
    exec(FAKE_GAZENET, code)  # the same module in this process, to make the checkpoint and the reference
    torch.manual_seed(0)
    net = code["GazeNet"](7)
    torch.save({"state_dict": net.state_dict(), "epoch": 3}, gafa / "models" / "weights" / "gazenet_GAFA.pth")
    out = tmp_path / "models" / "gafa_view.onnx"                         # the name the gafa pipeline reads
    p = subprocess.run([sys.executable, str(REPO / "scripts" / "export_gafa_view.py"), "--gafa", str(gafa),
                        "--out", str(out.parent)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "max |ONNX - PyTorch|" in p.stdout
    est = GafaViewEstimator(out)
    rng = np.random.default_rng(1)
    x = (rng.normal(size=(7, 3, 256, 192)).astype(np.float32), (rng.random((7, 1, 256, 192)) < 0.2).astype(np.float32),
         rng.normal(size=(7, 2)).astype(np.float32))
    net.act.set_swish(memory_efficient=False)
    with torch.no_grad():
        want = net(*(torch.from_numpy(a)[None] for a in x))[0]["direction"][0].numpy()
    np.testing.assert_allclose(est.predict(*x), want, atol=1e-5)
