"""Adapters read hand-built miniature datasets in each real format; values checked by hand."""
import json
import os
import pickle

import cv2
import numpy as np
import pytest
from PIL import Image

from ga3ce_prep.datasets import open_dataset
from ga3ce_prep.datasets.base import gaze_direction
from ga3ce_prep.datasets.gafa import body_boxes, head_boxes, keypoint_box
from ga3ce_prep.datasets.safe_pickle import load_pickle
from ga3ce_prep.errors import DatasetFormatError, FrameError
from ga3ce_prep.frames import load_depth, load_rgb, read_depth

W, H = 160, 120


def _write_csv(path, header, rows):
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")


def _gfie(tmp_path, scale=1.0):
    root = tmp_path / "GFIE_dataset"
    root.mkdir()
    np.save(root / "CameraKinect.npy", np.array([200.0, 210.0, 80.0, 60.0]))
    header = ["gaze_Z", "frame_id", "scene_id", "h_x_min", "h_y_min", "h_x_max", "h_y_max", "eye_u", "eye_v",
              "eye_X", "eye_Y", "eye_Z", "gaze_u", "gaze_v", "gaze_X", "gaze_Y", "extra"]
    rows = {"train": [[3.0 * scale, 0, 2, 10, 12, 30, 34, 20, 20, 0.1 * scale, -0.2 * scale, 2.0 * scale, 50, 60,
                       1.1 * scale, -0.2 * scale, "x"],
                      [2.0 * scale, 7, 2, 11, 12, 31, 34, 21, 20, 0.1 * scale, -0.2 * scale, 2.0 * scale, 51, 60,
                       0.1 * scale, 0.8 * scale, "y"]],
            "test": [[4.0 * scale, 3, 1, 60, 10, 80, 30, 70, 20, 0.5 * scale, -0.5 * scale, 2.5 * scale, 10, 10,
                      0.5 * scale, -0.5 * scale, "z"]]}
    for folder, rs in rows.items():
        _write_csv(root / f"{folder}_annotation.txt", header, rs)
        for r in rs:
            sid, fnum = r[2], r[1]
            (root / "rgb" / folder / f"scene{sid}").mkdir(parents=True, exist_ok=True)
            (root / "depth" / folder / f"scene{sid}").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / "rgb" / folder / f"scene{sid}" / f"{fnum:04d}.jpg"), np.zeros((H, W, 3), np.uint8))
            d = np.full((H, W), 2.0 * scale, np.float32)
            d[:10] = np.nan
            np.save(root / "depth" / folder / f"scene{sid}" / f"{fnum:04d}.npy", d)
    return root


def test_gfie_adapter_reads_columns_by_name(tmp_path):
    frames = list(open_dataset("gfie", _gfie(tmp_path)).frames())
    assert [f.id for f in frames] == ["train/scene2/0000", "train/scene2/0007", "test/scene1/0003"]
    f = frames[0]
    assert f.split == "train"
    assert f.scene == "train/scene2"
    assert f.image_size == (W, H)
    np.testing.assert_array_equal(f.K, [[200, 0, 80], [0, 210, 60], [0, 0, 1]])
    np.testing.assert_allclose(f.head_box, [10, 12, 30, 34])
    np.testing.assert_allclose(f.eye, [0.1, -0.2, 2.0])
    np.testing.assert_allclose(f.gaze, np.array([1.0, 0, 1.0]) / np.sqrt(2), atol=1e-6)
    np.testing.assert_allclose(f.gaze_2d, [50, 60])
    assert frames[2].split == "test"
    d = load_depth(f.depth_path, f.depth_scale)
    assert d.dtype == np.float32
    assert (d[:10] == 0).all()
    assert np.allclose(d[10:], 2.0)
    assert load_rgb(f.image_path).shape == (H, W, 3)


def test_gfie_millimetres_detected(tmp_path):
    f = next(open_dataset("gfie", _gfie(tmp_path, scale=1000.0)).frames())
    assert f.depth_scale == pytest.approx(0.001)
    np.testing.assert_allclose(f.eye, [0.1, -0.2, 2.0], rtol=1e-6)
    np.testing.assert_allclose(load_depth(f.depth_path, f.depth_scale)[50, 50], 2.0, rtol=1e-6)


def test_gfie_structural_errors_name_the_fix(tmp_path):
    root = _gfie(tmp_path)
    text = (root / "train_annotation.txt").read_text().replace("h_x_min", "hx")
    (root / "train_annotation.txt").write_text(text)
    with pytest.raises(DatasetFormatError, match=r"missing column\(s\) \['h_x_min'\]"):
        open_dataset("gfie", root)
    os.remove(root / "CameraKinect.npy")
    with pytest.raises(DatasetFormatError, match="CameraKinect.npy not found"):
        open_dataset("gfie", root)


def test_frame_loaders_fail_per_frame_with_the_file(tmp_path):
    f = next(open_dataset("gfie", _gfie(tmp_path)).frames())
    data = f.image_path.read_bytes()
    f.image_path.write_bytes(data[: len(data) // 2])
    with pytest.raises(FrameError, match="cannot decode image"):
        load_rgb(f.image_path)
    os.remove(f.depth_path)
    with pytest.raises(FrameError, match="depth file not found"):
        load_depth(f.depth_path)


def test_frames_load_with_pillows_pixel_limit_lifted(tmp_path, monkeypatch):
    # Image.MAX_IMAGE_PIXELS = None is Pillow's documented way to lift its decompression-bomb limit
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", None)
    cv2.imwrite(str(tmp_path / "frame.png"), np.full((H, W, 3), 7, np.uint8))
    assert load_rgb(tmp_path / "frame.png").shape == (H, W, 3)
    cv2.imwrite(str(tmp_path / "depth.png"), np.full((H, W), 2000, np.uint16))
    assert read_depth(tmp_path / "depth.png").shape == (H, W)


def test_cad120_normalised_boxes_and_mm_depth(tmp_path):
    root = tmp_path / "CAD120"
    (root / "rgb" / "D1S1A001").mkdir(parents=True)
    (root / "depth" / "D1S1A001").mkdir(parents=True)
    np.save(root / "CameraKinect.npy", np.array([525.0, 525.0, 80.0, 60.0]))
    _write_csv(root / "annotation.txt",
               ["dataset_id", "frame_index", "x_initial", "y_initial", "w", "h", "eye_x", "eye_y", "eye_X", "eye_Y",
                "eye_Z", "gaze_x", "gaze_y", "gaze_X", "gaze_Y", "gaze_Z"],
               [["D1S1A001", 17, 0.25, 0.5, 0.125, 0.25, 0.3, 0.55, 0, 0, 2, 0.5, 0.75, 0, 1, 2]])
    cv2.imwrite(str(root / "rgb" / "D1S1A001" / "RGB_17.png"), np.zeros((H, W, 3), np.uint8))
    depth = np.full((H, W), 2500, np.uint16)
    depth[0, 0] = 0
    cv2.imwrite(str(root / "depth" / "D1S1A001" / "Depth_17.png"), depth)
    (f,) = list(open_dataset("cad120", root).frames())
    assert f.id == "D1S1A001/17"
    assert f.split == "test"
    np.testing.assert_allclose(f.head_box, [40, 60, 60, 90])
    np.testing.assert_allclose(f.gaze_2d, [80, 90])
    np.testing.assert_allclose(f.gaze, [0, 1, 0], atol=1e-7)
    d = load_depth(f.depth_path, f.depth_scale)
    assert d[0, 0] == 0
    assert d[5, 5] == pytest.approx(2.5)



def test_gaze_direction_is_nan_where_eye_and_target_coincide_or_are_unknown():
    eye = np.array([[0.0, 0, 1], [1, 1, 1], [np.nan, 0, 0]])
    target = np.array([[0.0, 0, 3], [1, 1, 1], [0, 0, 1]])
    g = gaze_direction(eye, target)
    np.testing.assert_array_equal(g[0], [0, 0, 1])
    assert np.isnan(g[1:]).all()

def _body25(n, shift=0.0):
    kp = np.zeros((n, 25, 3), np.float32)
    kp[:, 0, :2] = [100, 50]   # nose
    kp[:, 1, :2] = [100, 80]   # neck
    kp[:, 15, :2] = [95, 45]   # REye
    kp[:, 16, :2] = [105, 45]  # LEye
    kp[:, 17, :2] = [90, 48]   # REar
    kp[:, 18, :2] = [110, 48]  # LEar
    kp[:, 8, :2] = [100, 150]  # MidHip
    kp[:, 11, :2] = [96, 230]  # RAnkle
    kp[..., 2] = (kp[..., 0] != 0)
    kp[..., 0] += shift
    return kp


def test_gafa_boxes_follow_gafa_preprocessing():
    kp = _body25(1)
    # head joints span u 90..110, v 45..80 -> w 20, h 35; expand t=.85 (29), b=-.2 (-7), l=r=.1 (2)
    # -> u 88, v 16, w 24, h 57; square of side 57 centred on u: u = 88 - floor(33/2) = 72
    np.testing.assert_allclose(head_boxes(kp)[0], [72, 16, 129, 73])
    # all joints span u 90..110, v 45..230 -> w 20, h 185; pads l=r=int(4.0)=4, t=int(27.75)=27,
    # b=int(9.25)=9 -> u 86, v 18, w 28, h 221 -> square side 221, u = 86 - 96 = -10;
    # width int(221*0.75)=165, u = -10 + floor(56/2) = 18
    np.testing.assert_allclose(body_boxes(kp)[0], [18, 18, 183, 239])



def test_gafa_keypoint_box_counts_a_joint_only_with_both_coordinates_and_truncates():
    """GAFA's KeypointsToBB (data/preprocessed/transforms.py): `kp[np.all(kp != 0, axis=1)]`, then
    `astype(int)` before the min/max. The adapter's head box and view/gafa's share it."""
    from ga3ce_prep.estimators.view.gafa import preprocessed_boxes

    kp = np.zeros((2, 25, 3), np.float32)
    kp[:, 0, :2] = [100.7, 50.2]   # nose
    kp[:, 1, :2] = [100.3, 80.9]   # neck
    kp[:, 15, :2] = [95.5, 45.5]   # REye
    kp[1, 17, :2] = [0, 40]        # REar with u = 0: not detected, although v is not 0
    kp[1, 18, :2] = [130, 0]       # LEar with v = 0: not detected either
    box = keypoint_box(kp, (0, 1, 15, 16, 17, 18))
    np.testing.assert_array_equal(box, [[95, 45, 5, 35], [95, 45, 5, 35]])   # u 95..100, v 45..80
    assert np.isnan(keypoint_box(kp, (17, 18))).all()
    head, _ = preprocessed_boxes(kp)
    np.testing.assert_array_equal(head_boxes(kp), np.concatenate([head[:, :2], head[:, :2] + head[:, 2:]], axis=1))

def _gafa(tmp_path, sessions=("library/1029_2", "kitchen/1015_4", "lab/1013_1", "lab/9999_9")):
    root = tmp_path / "raw_data"
    root.mkdir()
    K = np.array([[100.0, 0, 80], [0, 100, 60], [0, 0, 1]])
    np.savez(root / "intrinsics.npz", cam_mat=K, dist_coeffs=np.zeros((1, 12)))
    n = 4
    for s in sessions:
        cam = root / s / "Camera1_0"
        cam.mkdir(parents=True)
        for i in range(n):
            cv2.imwrite(str(cam / f"{i:06d}.jpg"), np.zeros((H, W, 3), np.uint8))
        kp = _body25(n)
        kp[2] = 0  # frame 2: nobody detected -> skipped
        head_pos = np.tile([0.2, -0.1, 1.0], (n, 1))  # projects to (100, 50): the nose
        gaze = np.tile([0.0, 0.0, -2.0], (n, 1))
        d = {"keypoints2d": kp, "gaze": {"direction": gaze}, "head": {"direction": gaze, "position": head_pos},
             "chest": {"direction": gaze, "position": head_pos}, "R_cam2w": np.eye(3), "t_cam2w": np.zeros(3)}
        with open(root / s / "Camera1_0.pkl", "wb") as f:
            pickle.dump(d, f, protocol=2)
    return root


def test_gafa_adapter_split_skip_and_vectors(tmp_path):
    # accepts the parent of raw_data
    frames = list(open_dataset("gafa", _gafa(tmp_path).parent, val="sessions").frames())
    ids = [f.id for f in frames]
    assert ids[:3] == ["library/1029_2/Camera1_0/000000", "library/1029_2/Camera1_0/000001",
                       "library/1029_2/Camera1_0/000003"]
    assert not any("9999" in i for i in ids)  # session outside the published split
    splits = {f.scene: f.split for f in frames}
    assert splits == {"library/1029_2": "test", "kitchen/1015_4": "val", "lab/1013_1": "train"}
    f = frames[0]
    np.testing.assert_allclose(f.gaze, [0, 0, -1])
    np.testing.assert_allclose(f.eye, [0.2, -0.1, 1.0], rtol=1e-6)
    np.testing.assert_allclose(f.head_box, [72, 16, 129, 73])
    assert f.keypoints_2d.shape == (25, 3)
    assert f.image_size == (W, H)
    assert f.depth_path is None
    np.testing.assert_array_equal(f.K, [[100, 0, 80], [0, 100, 60], [0, 0, 1]])


def test_gafa_transposed_k_chosen_when_it_fits(tmp_path):
    root = _gafa(tmp_path, sessions=("lab/1013_1",))
    # intrinsics that only fit after swapping fx/fy and cx/cy
    np.savez(root / "intrinsics.npz", cam_mat=np.array([[300.0, 0, 60], [0, 100, 80], [0, 0, 1]]),
             dist_coeffs=np.zeros((1, 12)))
    kp = _body25(4)
    d = load_pickle(root / "lab/1013_1/Camera1_0.pkl")
    d["keypoints2d"] = kp
    d["head"]["position"] = np.tile([0.2, -0.1 * 100 / 300, 1.0], (4, 1))  # (100, 50) under the transpose
    pickle.dump(d, open(root / "lab/1013_1/Camera1_0.pkl", "wb"))
    f = next(open_dataset("gafa", root).frames())
    np.testing.assert_array_equal(f.K, [[100, 0, 80], [0, 300, 60], [0, 0, 1]])


def test_gafa_refuses_unsafe_pickle(tmp_path):
    root = _gafa(tmp_path, sessions=("lab/1013_1",))

    class Evil:
        def __reduce__(self):
            return (os.system, ("true",))

    pickle.dump({"keypoints2d": Evil()}, open(root / "lab/1013_1/Camera1_0.pkl", "wb"))
    with pytest.raises(DatasetFormatError, match="posix.system' is not allowed"):
        list(open_dataset("gafa", root).frames())


def test_folder_adapter(tmp_path):
    root = tmp_path / "rec"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    (root / "intrinsics.json").write_text(json.dumps({"fx": 500, "fy": 500, "cx": 80, "cy": 60}))
    for name in ("a", "b"):
        cv2.imwrite(str(root / "rgb" / f"{name}.png"), np.zeros((H, W, 3), np.uint8))
        cv2.imwrite(str(root / "depth" / f"{name}.png"), np.full((H, W), 1500, np.uint16))
    _write_csv(root / "heads.csv", ["name", "x1", "y1", "x2", "y2", "split"],
               [["a", 1, 2, 3, 4, "train"], ["b", 5, 6, 7, 8, "test"], ["b", 9, 9, 19, 19, "test"]])
    frames = list(open_dataset("folder", root).frames())
    assert [f.id for f in frames] == ["a", "b/0", "b/1"]
    assert [f.split for f in frames] == ["train", "test", "test"]
    assert frames[0].scene == "rec"
    assert frames[0].image_size == (W, H)
    assert np.isnan(frames[0].gaze).all()
    assert load_depth(frames[1].depth_path, frames[1].depth_scale)[0, 0] == pytest.approx(1.5)
    _write_csv(root / "heads.csv", ["name", "x1", "y1", "x2", "y2", "split"], [["a", 1, 2, 3, 4, "training"]])
    with pytest.raises(DatasetFormatError, match="training"):
        open_dataset("folder", root)
