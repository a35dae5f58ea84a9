import numpy as np
import pytest

from ga3ce_prep.errors import FrameError
from ga3ce_prep.geometry import (
    angular_error_deg,
    back_project,
    depth_to_points,
    head_position,
    object_positions,
    project,
    scale_intrinsics,
)
from ga3ce_prep.stages.head import DepthHead

K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])


def test_project_back_project_round_trip():
    rng = np.random.default_rng(0)
    p = rng.uniform([-2, -1, 0.5], [2, 1, 6], (100, 3))
    uv = project(p, K)
    q = back_project(uv[:, 0], uv[:, 1], p[:, 2], K)
    np.testing.assert_allclose(q, p, atol=1e-9)
    assert np.isnan(project(np.array([0.0, 0.0, -1.0]), K)).all()


def test_depth_to_points_principal_point():
    d = np.full((480, 640), 2.0, np.float32)
    pts = depth_to_points(d, K)
    assert pts.shape == (480, 640, 3)
    np.testing.assert_allclose(pts[239, 319], [-0.5 * 2 / 525, -0.5 * 2 / 525, 2.0], atol=1e-6)
    np.testing.assert_allclose(pts[0, 0], [-319.5 * 2 / 525, -239.5 * 2 / 525, 2.0], atol=1e-5)


def test_angular_error():
    a = np.array([[1.0, 0, 0], [0, 0, 1], [0, 1, 1]])
    b = np.array([[0.0, 1, 0], [0, 0, -2], [0, 0, 3]])
    np.testing.assert_allclose(angular_error_deg(a, b), [90, 180, 45], atol=1e-9)


def test_scale_intrinsics():
    K2 = scale_intrinsics(K, 0.5, 0.5)
    assert K2[0, 0] == 262.5
    assert K2[1, 2] == 119.75
    assert K2[2, 2] == 1


def _scene(rng):
    depth = rng.uniform(1.0, 4.0, (48, 64)).astype(np.float32)
    labels = np.full((48, 64), -1, np.int32)
    labels[5:20, 5:30] = 0
    labels[25:40, 10:20] = 2          # label 1 absent
    labels[30:33, 40:43] = 3          # 9 pixels: below min_points=10 -> dropped
    valid = rng.random((48, 64)) > 0.2
    return depth, labels, valid


def test_object_positions_equals_numpy_median_label_image():
    rng = np.random.default_rng(1)
    depth, labels, valid = _scene(rng)
    res = object_positions(depth, K, labels, valid=valid, min_points=5)
    pts = depth_to_points(depth, K).astype(np.float64)
    assert res.index.tolist() == [0, 2, 3]
    for row, lab in enumerate(res.index):
        m = (labels == lab) & valid
        np.testing.assert_allclose(res.xyz[row], np.median(pts[m], axis=0), rtol=1e-6, atol=1e-6)
        assert res.area[row] == (labels == lab).sum()
        assert res.n_valid[row] == m.sum()
    res10 = object_positions(depth, K, labels, valid=valid, min_points=10)
    assert res10.index.tolist() == [0, 2]
    assert res10.n_dropped == 1


def test_object_positions_overlapping_stack_matches_label_path():
    rng = np.random.default_rng(2)
    depth, labels, valid = _scene(rng)
    stack = np.stack([labels == i for i in range(4)])
    stack = np.concatenate([stack, (labels >= 0)[None]])  # a 5th mask overlapping all others
    res = object_positions(depth, K, stack, valid=valid, min_points=5)
    ref = object_positions(depth, K, labels, valid=valid, min_points=5)
    assert res.index.tolist() == [0, 2, 3, 4]
    np.testing.assert_array_equal(res.xyz[:3], ref.xyz)
    pts = depth_to_points(depth, K).astype(np.float64)
    np.testing.assert_allclose(res.xyz[3], np.median(pts[(labels >= 0) & valid], axis=0), atol=1e-6)


def test_object_positions_even_count_median_is_mean_of_middle_pair():
    depth = np.ones((1, 4), np.float32) * np.array([1, 2, 3, 10], np.float32)
    res = object_positions(depth, np.eye(3), np.zeros((1, 4), np.int32), min_points=1)
    assert res.xyz[0, 2] == pytest.approx(2.5)


def test_head_position_uses_window_median_and_falls_back():
    w = DepthHead.Params()
    win = dict(window_fracs=w.window_fracs, min_points=w.min_points)  # the head stage's defaults
    depth = np.full((100, 100), 3.0, np.float32)
    depth[40:60, 40:60] = 2.0
    p = head_position(depth, K, np.array([30, 30, 70, 70]), **win)
    np.testing.assert_allclose(p, back_project(50.0, 50.0, 2.0, K), atol=1e-6)
    holes = depth.copy()
    holes[45:55, 45:55] = 0  # centre window empty -> the 0.5 window is used
    p2 = head_position(holes, K, np.array([30, 30, 70, 70]), **win)
    assert p2[2] == pytest.approx(2.0)
    with pytest.raises(FrameError, match="no valid depth"):
        head_position(np.zeros_like(depth), K, np.array([30, 30, 70, 70]), **win)
    with pytest.raises(FrameError, match="outside"):
        head_position(depth, K, np.array([200, 30, 240, 70]), **win)


def test_object_positions_with_no_kept_mask_is_empty():
    depth = np.ones((8, 8), np.float32)
    labels = np.full((8, 8), -1, np.int32)
    labels[0, :3] = 0  # 3 pixels < min_points
    for masks in (labels, np.zeros((2, 8, 8), bool), np.full((8, 8), -1, np.int32)):
        res = object_positions(depth, K, masks, min_points=10)
        assert res.xyz.shape == (0, 3)
        assert res.index.size == 0
    assert object_positions(depth, K, labels, min_points=10).n_dropped == 1


def test_object_positions_of_no_masks_is_empty():
    from ga3ce_prep.geometry import object_positions

    K = np.array([[100.0, 0, 8], [0, 100.0, 6], [0, 0, 1]])
    pos = object_positions(np.ones((12, 16), np.float32), K, np.zeros((0, 12, 16), bool), min_points=1)
    assert pos.xyz.shape == (0, 3) and pos.n_dropped == 0
