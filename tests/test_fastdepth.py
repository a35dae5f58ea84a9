"""depth/fastdepth: the 4:3 crop, the focal rescale, and the registry model on real photos
(`make models` fetches it)."""
import numpy as np
import pytest

from ga3ce_prep.errors import ModelFileError
from ga3ce_prep.estimators.depth.fastdepth import NET_FOCAL_PX, FastDepthEstimator, centre_crop_4x3, focal_rescale
from ga3ce_prep.estimators.runtime.onnx_runtime import RuntimeParams
from ga3ce_prep.stages import backend_class
from ga3ce_prep.stages.base import BackendContext
from ga3ce_prep.testing.photos import K_from_hfov, photo, photo_frame
from ga3ce_prep.weights import registry as registry_models

ASTRONAUT_FACE = (slice(100, 160), slice(200, 250))      # rows, columns of the face in the 512x512 photo
ASTRONAUT_BACKDROP = (slice(80, 200), slice(380, 500))   # the grey studio backdrop right of her head


@pytest.fixture(scope="module")
def estimator() -> FastDepthEstimator:
    return FastDepthEstimator(registry_models.model_path("fastdepth"), RuntimeParams(threads=1))


def test_largest_centred_4x3_crop():
    assert centre_crop_4x3(640, 480) == (0, 0, 640, 480)
    assert centre_crop_4x3(512, 512) == (0, 64, 512, 384)
    assert centre_crop_4x3(600, 400) == (33, 0, 533, 400)
    assert centre_crop_4x3(1920, 1080) == (240, 0, 1440, 1080)
    assert centre_crop_4x3(300, 600) == (0, 187, 300, 225)   # portrait: full width, 3/4 of it high


def test_focal_rescale_formula():
    assert NET_FOCAL_PX == 199.0
    assert focal_rescale(199.0 * 640 / 224, 640) == pytest.approx(1.0)   # FastDepth's own camera
    assert focal_rescale(500.0, 640) == pytest.approx(500 * 224 / 640 / 199)


def test_astronaut_depths_are_plausible(estimator):
    img = photo("astronaut")
    r = estimator.predict(img, K_from_hfov(512, 512))
    assert r.depth.shape == (512, 512)
    assert r.depth.dtype == np.float32
    assert r.crop == (0, 64, 512, 384)
    face = float(np.median(r.depth[ASTRONAUT_FACE]))
    backdrop = float(np.median(r.depth[ASTRONAUT_BACKDROP]))
    assert 0.8 < face < 2.5
    assert backdrop > face + 0.3
    np.testing.assert_array_equal(r.valid, r.depth > 0)
    assert r.valid[64:448].all()
    assert not r.valid[:64].any()
    assert not r.valid[448:].any()


def test_doubling_the_focal_doubles_the_depth(estimator):
    img = photo("astronaut")
    K = K_from_hfov(512, 512)
    K2 = K.copy()
    K2[0, 0] *= 2
    K2[1, 1] *= 2
    d1, d2 = estimator.predict(img, K).depth, estimator.predict(img, K2).depth
    np.testing.assert_allclose(d2, 2 * d1, rtol=1e-6)


def test_wide_image_keeps_the_resolution_and_zeros_outside_the_crop(estimator):
    img = photo("coffee")                                   # 600x400 (3:2)
    r = estimator.predict(img, K_from_hfov(600, 400))
    assert r.depth.shape == (400, 600)
    assert (r.depth[:, :33] == 0).all()
    assert (r.depth[:, 566:] == 0).all()
    assert (r.depth[:, 33:566] > 0).all()
    np.testing.assert_array_equal(r.valid[:, 33:566], True)


def test_backend_depth_and_check(tmp_path, monkeypatch):
    frame = photo_frame(tmp_path, "astronaut", photo("astronaut"), (150, 15, 300, 190))
    backend = backend_class("depth", "fastdepth")({"threads": 1}, BackendContext(tmp_path))
    backend.check()
    dm = backend.depth(frame)
    assert dm.depth.shape == (512, 512)
    assert dm.valid.sum() == 512 * 384
    assert 0.8 < float(np.median(dm.depth[ASTRONAUT_FACE])) < 2.5
    monkeypatch.setenv("GA3CE_MODELS", str(tmp_path / "models"))
    p = registry_models.file_path("fastdepth")
    p.parent.mkdir(parents=True)
    p.write_bytes(b"damaged")
    with pytest.raises(ModelFileError, match=r"stages.depth.*pinned SHA-256.*ga3ce-prep models fetch"):
        backend.check()
