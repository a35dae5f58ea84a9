"""Depth completion (IP-Basic family) and the sensor depth backend."""
import numpy as np
import pytest

from ga3ce_prep.errors import FrameError
from ga3ce_prep.estimators.depth.completion import CompletionParams, complete_depth
from ga3ce_prep.frames import FrameRef
from ga3ce_prep.stages.base import BackendContext
from ga3ce_prep.stages.depth import SensorDepth

H, W = 120, 160


def _plane():
    v, u = np.mgrid[0:H, 0:W]
    return (2.0 + 0.004 * u + 0.002 * v).astype(np.float32)


def _holes(rng, d):
    raw = d.copy()
    raw[rng.random(d.shape) < 0.15] = 0
    raw[10:14, 20:25] = np.nan
    raw[60:100, 90:150] = 0  # a hole far wider than the 7x7 fill reaches
    return raw


def test_completion_fills_holes_near_truth_and_keeps_measured_pixels():
    rng = np.random.default_rng(0)
    gt = _plane()
    raw = _holes(rng, gt)
    dm = complete_depth(raw)
    valid = np.isfinite(raw) & (raw > 0)
    np.testing.assert_array_equal(dm.valid, valid)
    np.testing.assert_array_equal(dm.depth[valid], raw[valid])  # keep_valid: measured untouched
    assert (dm.depth > 0).all()                                # push-pull leaves no hole
    small = ~valid
    small[60:100, 90:150] = False
    assert np.abs(dm.depth[small] - gt[small]).max() < 0.03    # small holes: within 3 cm on a slope
    big = np.zeros_like(valid)
    big[60:100, 90:150] = True
    assert np.abs(dm.depth[big] - gt[big]).mean() < 0.1


def test_completion_without_large_hole_fallback_leaves_the_big_hole():
    raw = _holes(np.random.default_rng(1), _plane())
    dm = complete_depth(raw, CompletionParams(large_holes="none"))
    assert (dm.depth[70:90, 105:135] == 0).all()
    assert (dm.depth[:40] > 0).all()


def test_completion_prefers_the_nearer_surface_at_edges():
    d = np.full((H, W), 4.0, np.float32)
    d[:, :80] = 1.0  # near surface on the left
    raw = d.copy()
    raw[:, 78:83] = 0  # hole across the edge
    dm = complete_depth(raw, CompletionParams(blur="none"))
    assert np.all(dm.depth[:, 78:80] == 1.0)  # dilation of the inverted depth takes the near value


def test_range_limits_and_all_invalid():
    raw = np.full((H, W), 12.0, np.float32)  # beyond max_depth
    dm = complete_depth(raw, CompletionParams(max_depth=10.0))
    assert not dm.valid.any()
    assert not dm.depth.any()


def _frame(tmp_path, depth, size=(W, H)):
    p = tmp_path / "d.npy"
    np.save(p, depth)
    K = np.array([[100.0, 0, W / 2], [0, 100.0, H / 2], [0, 0, 1]])
    return FrameRef(id="f", split="test", scene="s", image_path=tmp_path / "x.jpg", K=K, image_size=size,
                    head_box=np.array([10, 10, 30, 30], np.float32), depth_path=p)


PARAMS = dict(min_depth=0.1, max_depth=10.0, extrapolate=False, blur="gaussian", keep_valid=True,
              large_holes="pushpull", bilateral_sigma_color=0.1, bilateral_sigma_space=2.0)


def test_sensor_backend_errors_name_the_file(tmp_path):
    b = SensorDepth(PARAMS, BackendContext(tmp_path))
    f = _frame(tmp_path, _plane(), size=(200, 100))
    with pytest.raises(FrameError, match="160x120 but the image is 200x100"):
        b.depth(f)
    f = _frame(tmp_path, np.full((H, W), np.nan, np.float32))
    with pytest.raises(FrameError, match="no valid pixel"):
        b.depth(f)
    f.depth_path = tmp_path / "missing.npy"
    with pytest.raises(FrameError, match="missing.npy"):
        b.depth(f)
    f.depth_path = None
    with pytest.raises(FrameError, match="needs a depth estimator"):
        b.depth(f)
