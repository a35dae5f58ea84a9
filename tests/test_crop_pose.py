"""`pose/onnx` and `pose/torchscript`: the MeTRAbs family's crop contract (estimators/pose/crop.py)
on tiny TorchScript and ONNX models whose outputs are known functions of their inputs: the
homography crop, the way back to the camera frame, the input's dtype, range and gamma, the joints
by name, the checks before any work, the depth refinement, and the backends through
`run_pipeline` on the synthetic world. The real MeTRAbs / NLF weights cannot be fetched here."""
import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ga3ce_prep.errors import ConfigError, FrameError, ModelFileError
from ga3ce_prep.estimators.pose.crop import (
    CropPoseEstimator,
    CropPoseOptions,
    TorchScriptCropModel,
    body_box,
    crop_to_camera,
    place_with_depth,
    read_joint_names,
    select_joints,
)
from ga3ce_prep.estimators.pose.crop_export import WithResolution, save_crop_model
from ga3ce_prep.estimators.runtime.crops import look_at_crop, pyramid_level, warp_homography
from ga3ce_prep.frames import DepthMap, FrameRef
from ga3ce_prep.geometry import pixel_ray, project
from ga3ce_prep.pipeline import load_pipeline, run_pipeline
from ga3ce_prep.skeleton import JOINT_NAMES
from ga3ce_prep.stages import backend_class
from ga3ce_prep.stages.base import BackendContext
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.paper_models import Constant
from ga3ce_prep.testing.worlds import SMALL

# torch 2.13 deprecates TorchScript and the legacy ONNX exporter, which the tiny models are written with
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

S = 64
K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
BOX = np.array([420.0, 100.0, 500.0, 300.0])  # 80 x 200 px, right of and above the principal point
CENTRE = np.array([460.0, 200.0])
BACKENDS = ("onnx", "torchscript")


# --- tiny models: forward(image [N,S,S,3], intrinsics [N,3,3]) -> [N,J,3] mm in the crop camera --------


class Probe(torch.nn.Module):
    """Every joint at (K'[0,0], bytes per element, 1000 x the image's mean): what the model was fed."""

    def forward(self, image: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        m = image.float().mean(dim=(1, 2, 3))
        size = torch.full_like(m, float(image.element_size()))
        return torch.stack([intrinsics[:, 0, 0], size, 1000.0 * m], -1)[:, None, :].expand(-1, 30, 3)


class ChannelsFirst(torch.nn.Module):
    """A model that wants image [N, 3, S, S] (the wrong layout for the contract)."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 2, 1)

    def forward(self, image: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        x = self.conv(image).mean(dim=(1, 2, 3))
        return (x[:, None, None] + intrinsics[:, :1, :1].sum()).expand(-1, 30, 3)


def write_model(module: torch.nn.Module, stem: Path, kind: str, names=JOINT_NAMES, dtype=torch.float32,
                shape=(1, S, S, 3), fixed: bool = True) -> Path:
    """The module as `stem.onnx` (torch.onnx.export; `fixed`: S fixed in the file, else dynamic) or
    `stem.pt` (torch.jit.script with `input_resolution`), and `stem.joints.txt`."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".joints.txt").write_text("\n".join(names) + "\n")
    image = torch.zeros(shape, dtype=dtype)
    if kind == "torchscript":
        path = stem.with_suffix(".pt")
        torch.jit.save(torch.jit.script(WithResolution(torch.jit.script(module), S)), str(path))
        return path
    path = stem.with_suffix(".onnx")
    axes = {"image": {0: "n"} if fixed else {0: "n", 1: "h", 2: "w"}, "intrinsics": {0: "n"}, "poses3d": {0: "n"}}
    torch.onnx.export(module, (image, torch.eye(3)[None]), str(path), dynamo=False, input_names=["image", "intrinsics"],
                      output_names=["poses3d"], dynamic_axes=axes)
    return path


def backend(kind: str, tmp_path: Path, **params):
    return backend_class("pose", kind)(params, BackendContext(tmp_path))


def estimator(kind: str, model: Path, **options) -> CropPoseEstimator:
    b = backend(kind, model.parent, model=model, **options)
    b.check()
    return b.estimator()


# --- the homography crop ---------------------------------------------------------------------------


def test_look_at_crop_by_hand_centred_box():
    """A box centred on the principal point: R = I, and the box's 200 px height spans the crop:
    K' = [[500 S/200, 0, S/2], [0, 500 S/200, S/2], [0, 0, 1]]."""
    crop = look_at_crop(K, np.array([269.5, 139.5, 369.5, 339.5]), S)
    np.testing.assert_allclose(crop.R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(crop.K, [[500 * S / 200, 0, S / 2], [0, 500 * S / 200, S / 2], [0, 0, 1]], atol=1e-9)
    crop2 = look_at_crop(K, np.array([269.5, 139.5, 369.5, 339.5]), S, scale=2.0)
    assert crop2.K[0, 0] == pytest.approx(crop.K[0, 0] / 2)


def test_look_at_crop_off_centre_box_and_its_marked_centre():
    """Off-centre: R's third row is the unit ray through the box centre, its first row is
    horizontal (perpendicular to the image's up, MeTRAbs's look-at), R is a rotation; H = K' R
    K^-1 sends a 3D point's pixel to where K' sees R X; the box's side midpoints, seen by the
    turned camera, span S crop pixels vertically (the larger side); a bright blob at the box
    centre lands at the crop's principal point (S/2, S/2)."""
    crop = look_at_crop(K, BOX, S)
    R = crop.R
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[2], pixel_ray(CENTRE, K), atol=1e-12)
    assert abs(R[0, 1]) < 1e-12 and R[0, 0] > 0 and R[1, 1] > 0
    assert crop.K[0, 2] == crop.K[1, 2] == S / 2 and crop.K[0, 0] == pytest.approx(crop.K[1, 1])
    X = np.array([0.7, -0.4, 3.1])
    uv = np.append(project(X, K), 1.0)
    h = crop.H @ uv
    np.testing.assert_allclose(h[:2] / h[2], project(R @ X, crop.K), atol=1e-9)
    mids = np.array([[460, 100, 1], [460, 300, 1.0]]) @ crop.H.T
    mids = mids[:, :2] / mids[:, 2:]
    assert np.linalg.norm(mids[0] - mids[1]) == pytest.approx(S, rel=1e-9)

    image = np.zeros((480, 640, 3), np.float32)
    image[198:203, 458:463] = 1.0
    out = warp_homography(image, crop.H, S, crop.zoom)
    assert np.unravel_index(out[..., 0].argmax(), out.shape[:2]) == (S // 2, S // 2)
    assert out[..., 0].max() > 0.3 and out[..., 0][np.abs(np.arange(S) - S // 2)[:, None].repeat(S, 1) > 4].max() == 0


def test_warp_identity_and_antialiasing_pyramid():
    """H = I gives the image back; shrinking a 1-pixel checkerboard 4x reads the 2x2-averaged
    pyramid level (flat 0.5), where a plain bilinear warp aliases."""
    rng = np.random.default_rng(0)
    img = rng.random((40, 50, 3)).astype(np.float32)
    np.testing.assert_allclose(warp_homography(img, np.eye(3), 40, 1.0)[:, :40], img[:, :40], atol=1e-6)
    board = (np.indices((256, 256)).sum(0) % 2).astype(np.float32)
    H = np.diag([0.25, 0.25, 1.0])
    H[:2, 2] = -0.25  # out pixel i samples in pixel 4i + 1: all zeros, without the pyramid
    out = warp_homography(board, H, 64, 0.25)
    assert np.abs(out[2:-2, 2:-2] - 0.5).max() < 1e-6
    assert np.abs(warp_homography(board, H, 64, 0.25, levels=1)[2:-2, 2:-2] - 0.5).max() > 0.4


# --- against MeTRAbs's own crop, computed by hand ---------------------------------------------------
# MeTRAbs (metrabs_pytorch/multiperson: multiperson_model.py `_get_new_rotation_and_scale`,
# `_get_crops`; warping.py `warp_images_with_pyramid`, `warp_single_image`), written out in numpy
# for one crop (num_aug=1: scale 1, no rotation or flip), no lens distortion.

FULL_HD_K = np.array([[1000.0, 0, 959.5], [0, 1000.0, 539.5], [0, 0, 1]])


def metrabs_rotation_and_scale(K: np.ndarray, box: np.ndarray, size: int) -> tuple[np.ndarray, float]:
    """MeTRAbs's R (rows x, y, z of the turned camera) and zoom s for a box (x1, y1, x2, y2): the
    centre and the 4 side midpoints unprojected; z the centre's ray, x = z x up, y = z x x; the
    midpoints projected by K R; s = size / the larger of their two spans."""
    x, y, w, h = box[0], box[1], box[2] - box[0], box[3] - box[1]
    pts = np.array([[x + w / 2, y + h / 2], [x + w / 2, y], [x + w, y + h / 2], [x + w / 2, y + h], [x, y + h / 2]])
    cam = np.c_[pts, np.ones(5)] @ np.linalg.inv(K).T
    z = cam[0] / np.linalg.norm(cam[0])
    xa = np.cross(z, [0.0, -1.0, 0.0])
    xa /= np.linalg.norm(xa)
    R = np.stack([xa, np.cross(z, xa), z])
    side = cam[1:] @ (K @ R).T
    side = side[:, :2] / side[:, 2:]
    return R, size / max(np.linalg.norm(side[0] - side[2]), np.linalg.norm(side[1] - side[3]))


def metrabs_level(s: float, levels: int = 3) -> int:
    return int(np.clip(np.floor(-np.log2(s)), 0, levels - 1))


def metrabs_crop(image: np.ndarray, K: np.ndarray, box: np.ndarray, size: int) -> tuple[np.ndarray, int]:
    """MeTRAbs's crop (size, size, C) and pyramid level: the whole image 2x2-average-pooled to the
    level (an odd last row or column dropped), K moved to that level by the corner-aligned scale
    [[f, 0, (f-1)/2], [0, f, (f-1)/2]] (f = 2^-l); each output pixel (x, y) goes through
    (K' R)^-1, is projected, then through the level's K, and samples bilinearly in index
    coordinates with zeros outside (grid_sample, align_corners=True, padding 'zeros')."""
    R, s = metrabs_rotation_and_scale(K, box, size)
    level = metrabs_level(s)
    Kn = np.array([[K[0, 0] * s, K[0, 1] * s, size / 2], [K[1, 0] * s, K[1, 1] * s, size / 2], [0, 0, 1]])
    img = image.astype(np.float64)
    for _ in range(level):
        hh, ww = img.shape[0] // 2, img.shape[1] // 2
        img = img[:2 * hh, :2 * ww].reshape(hh, 2, ww, 2, -1).mean((1, 3))
    f = 2.0 ** -level
    Kl = np.array([[f, 0, (f - 1) / 2], [0, f, (f - 1) / 2], [0, 0, 1]]) @ K
    gx, gy = np.meshgrid(np.arange(size), np.arange(size))
    ray = np.stack([gx, gy, np.ones_like(gx)], -1) @ np.linalg.inv(Kn @ R).T
    old = (np.concatenate([ray[..., :2] / ray[..., 2:], np.ones((size, size, 1))], -1) @ Kl.T)[..., :2]
    i0 = np.floor(old).astype(int)
    frac = old - i0
    out = np.zeros((size, size, img.shape[2]))
    for dx in (0, 1):
        for dy in (0, 1):
            xi, yi = i0[..., 0] + dx, i0[..., 1] + dy
            wgt = (frac[..., 0] if dx else 1 - frac[..., 0]) * (frac[..., 1] if dy else 1 - frac[..., 1])
            inside = (xi >= 0) & (xi < img.shape[1]) & (yi >= 0) & (yi < img.shape[0])
            tap = img[yi.clip(0, img.shape[0] - 1), xi.clip(0, img.shape[1] - 1)]
            out += np.where(inside, wgt, 0.0)[..., None] * tap
    return out, level


def height_at_zoom(centre, aspect: float, target: float, size: int) -> float:
    """The height of a box (width aspect x height) centred on `centre` whose MeTRAbs zoom is `target`
    (bisection; the zoom falls as the box grows)."""
    lo, hi = 1.0, 5000.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        box = np.array([centre[0] - aspect * mid / 2, centre[1] - mid / 2, centre[0] + aspect * mid / 2,
                        centre[1] + mid / 2])
        lo, hi = (mid, hi) if metrabs_rotation_and_scale(FULL_HD_K, box, size)[1] > target else (lo, mid)
    return 0.5 * (lo + hi)


# (centre, width / height, the zoom 2^-k at a level boundary): centred, and off-centre where the
# old rule (the level from the warp's Jacobian at the crop centre, det J = 1 / (s^2 cos^3)) picked
# one level coarser just above the boundary
BOUNDARY_CASES = [((959.5, 539.5), 0.5, 0.5), ((1700.0, 200.0), 0.45, 0.5), ((250.0, 880.0), 0.6, 0.25),
                  ((1500.0, 620.0), 0.4, 0.25)]


@pytest.mark.parametrize("centre,aspect,zoom", BOUNDARY_CASES)
@pytest.mark.parametrize("side", [-1, 1])
def test_crop_matches_metrabs_by_hand_either_side_of_a_level_boundary(centre, aspect, zoom, side):
    """A box 0.2 % smaller (side -1: zoom just above 2^-k, level k - 1) or larger (level k) than
    the one at the boundary: our zoom, R, level and crop equal MeTRAbs's; the crop differs from the
    neighbouring level's by far more than the tolerance, which allows for OpenCV 4's warp on a
    1/32-pixel grid (OpenCV 5's agrees to about 1e-5)."""
    S = 64
    k = round(-np.log2(zoom))
    h = height_at_zoom(centre, aspect, zoom, S) * (1 + 0.002 * side)
    box = np.array([centre[0] - aspect * h / 2, centre[1] - h / 2, centre[0] + aspect * h / 2, centre[1] + h / 2])
    R, s = metrabs_rotation_and_scale(FULL_HD_K, box, S)
    geo = look_at_crop(FULL_HD_K, box, S)
    assert geo.zoom == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(geo.R, R, atol=1e-12)
    want_level = k - 1 if side < 0 else k
    assert metrabs_level(s) == pyramid_level(geo.zoom) == want_level

    rng = np.random.default_rng(k)
    image = rng.random((1080, 1920, 3)).astype(np.float32)
    want, level = metrabs_crop(image, FULL_HD_K, box, S)
    assert level == want_level
    ours = warp_homography(image, geo.H, S, geo.zoom)
    err = np.abs(ours - want)
    assert err.max() < 0.06 and err.mean() < 0.01
    # the neighbouring level's crop (the zoom across the boundary) is far off, so the level is really checked
    other = warp_homography(image, geo.H, S, geo.zoom * 2.0 ** side)
    assert np.abs(other - want).mean() > 0.04


def test_pyramid_level_is_metrabs_on_random_person_boxes():
    """3,000 random person boxes in a 1920 x 1080 frame (f = 1000 px, S = 384): our level is
    MeTRAbs's, floor(-log2 s) clipped to 0..2, for every box. (The earlier rule, the level from
    the warp's Jacobian at the crop centre, picked one level coarser for 595 of these, 19.8 %.)"""
    S = 384
    rng = np.random.default_rng(0)
    h = rng.uniform(100, 1080, 3000)
    w = h * rng.uniform(0.3, 0.8, 3000)
    cx, cy = rng.uniform(0, 1920, 3000), rng.uniform(0, 1080, 3000)
    ours, theirs = [], []
    for box in np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], 1):
        ours.append(pyramid_level(look_at_crop(FULL_HD_K, box, S).zoom))
        theirs.append(metrabs_level(metrabs_rotation_and_scale(FULL_HD_K, box, S)[1]))
    assert ours == theirs
    assert set(theirs) == {0, 1}  # level 2 needs a box over 4 S = 1536 px tall


# --- the runner: geometry back to the camera frame, input encoding, joints by name -----------------


@pytest.mark.parametrize("kind", BACKENDS)
def test_constant_joints_land_on_the_box_ray_in_metres(tmp_path, kind):
    """Joints at (0, 0, 3000) mm in the crop camera are 3 m along the ray through the box centre;
    one at (+100, 0, 3000) mm is 0.1 m along the crop's x axis (horizontal in the camera frame)."""
    joints = np.tile([0.0, 0.0, 3000.0], (30, 1))
    joints[5, 0] = 100.0
    est = estimator(kind, write_model(Constant(joints), tmp_path / "const", kind))
    pose = est(np.zeros((480, 640, 3), np.uint8), K, BOX)
    ray = pixel_ray(CENTRE, K)
    np.testing.assert_allclose(np.delete(pose, 5, 0), np.tile(3.0 * ray, (29, 1)), atol=1e-6)
    d = pose[5] - 3.0 * ray
    assert np.linalg.norm(d) == pytest.approx(0.1, abs=1e-6)
    assert abs(d @ ray) < 1e-6 and abs(d[1]) < 1e-6 and d[0] > 0


def test_crop_to_camera_millimetres_to_metres():
    R = look_at_crop(K, BOX, S).R
    np.testing.assert_allclose(crop_to_camera([[0, 0, 1234.0]], np.eye(3)), [[0, 0, 1.234]])
    p = np.array([[120.0, -40.0, 2500.0]])
    np.testing.assert_allclose(crop_to_camera(p, R), (R.T @ p[0] / 1000)[None], atol=1e-12)


@pytest.mark.parametrize("kind", BACKENDS)
@pytest.mark.parametrize("dtype,value_range,gamma,gamma_aug", [
    ("float32", (0.0, 1.0), 2.2, 0.8),     # MeTRAbs: (v/255)^2.2 warped, then ^(0.8/2.2): (v/255)^0.8
    ("float32", (-1.0, 1.0), 1.0, 1.0),    # plain sRGB in [-1, 1]
    ("float16", (0.0, 1.0), 2.2, 2.2),     # gamma undone exactly: v/255
    ("uint8", (0.0, 255.0), 2.2, 0.8),     # bytes, rounded
])
def test_the_model_is_fed_the_dtype_range_and_gamma(tmp_path, kind, dtype, value_range, gamma, gamma_aug):
    """A grey image (v = 100) inside the crop: the model sees its K', its dtype (bytes per
    element) and a mean of lo + (hi - lo) (v/255)^gamma_aug; the output comes back along the box
    ray, in metres."""
    tdtype = {"float32": torch.float32, "float16": torch.float16, "uint8": torch.uint8}[dtype]
    model = write_model(Probe(), tmp_path / f"probe_{dtype}", kind, dtype=tdtype)
    est = estimator(kind, model, input_dtype=dtype, value_range=list(value_range), gamma=gamma, gamma_aug=gamma_aug)
    rgb = np.full((480, 640, 3), 100, np.uint8)
    box = np.array([300.0, 200.0, 340.0, 280.0])   # the crop sees only the grey image
    image, geo = est.crop(rgb, K, box)
    lo, hi = value_range
    want = lo + (hi - lo) * (100 / 255) ** gamma_aug
    want = np.rint(want) if dtype == "uint8" else want
    assert image.dtype == np.dtype(dtype) and image.shape == (S, S, 3)
    np.testing.assert_allclose(image.astype(np.float64), want, atol=2e-3 * (hi - lo) + (0.5 if dtype == "uint8" else 0))
    raw = est.raw(image, geo.K)
    size = {"float32": 4, "float16": 2, "uint8": 1}[dtype]
    np.testing.assert_allclose(raw[0], [geo.K[0, 0], size, 1000 * image.astype(np.float64).mean()], rtol=1e-3)
    pose = est(rgb, K, box)
    np.testing.assert_allclose(pose, crop_to_camera(raw, geo.R)[[0] * 30], rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("kind", BACKENDS)
def test_joints_are_selected_by_name_from_a_shuffled_list(tmp_path, kind):
    """34 model joints (30 shuffled + 4 others), joint i at (10 i, 0, 3000) mm: smpl+head_30 joint
    k comes from the row its name has in the list."""
    names = [*JOINT_NAMES, "lfoo", "rfoo", "spine_x", "jaw"]
    order = np.random.default_rng(3).permutation(len(names))
    names = [names[i] for i in order]
    joints = np.stack([10.0 * np.arange(34), np.zeros(34), np.full(34, 3000.0)], 1)
    est = estimator(kind, write_model(Constant(joints), tmp_path / "shuffled", kind, names=names))
    pose = est(np.zeros((480, 640, 3), np.uint8), K, BOX)
    R = look_at_crop(K, BOX, S).R
    rows = (pose * 1000) @ R[0]  # the crop x coordinate, mm
    np.testing.assert_allclose(rows, [10.0 * names.index(n) for n in JOINT_NAMES], atol=1e-3)
    np.testing.assert_array_equal(select_joints(names, "x"), [names.index(n) for n in JOINT_NAMES])


@pytest.mark.parametrize("kind", BACKENDS)
def test_a_missing_joint_name_is_refused_naming_it_before_any_work(tmp_path, kind):
    names = ["nose" if n == "nose_coco" else n for n in JOINT_NAMES]
    model = write_model(Constant(np.zeros((30, 3))), tmp_path / "old", kind, names=names)
    with pytest.raises(ModelFileError, match=r"no joint named 'nose_coco'") as e:
        backend(kind, tmp_path, model=model).check()
    assert str(model) in str(e.value)
    (tmp_path / "old.joints.txt").unlink()
    with pytest.raises(ModelFileError, match=r"joint-name list .*old.joints.txt not found"):
        backend(kind, tmp_path, model=model).check()
    other = tmp_path / "names.txt"
    other.write_text("\n".join(JOINT_NAMES[:5] + JOINT_NAMES[:1]))
    with pytest.raises(ModelFileError, match=r"\['pelv_smpl'\] appear more than once"):
        read_joint_names(other)


def test_a_model_with_the_wrong_input_shape_is_refused_naming_file_tensor_and_shapes(tmp_path):
    onnx = write_model(ChannelsFirst(), tmp_path / "nchw", "onnx", shape=(1, 3, S, S))
    with pytest.raises(ModelFileError) as e:
        backend("onnx", tmp_path, model=onnx).check()
    msg = str(e.value)
    assert str(onnx) in msg and "'image'" in msg and "[?, ?, ?, 3]" in msg and f"3, {S}, {S}]" in msg
    ts = write_model(ChannelsFirst(), tmp_path / "nchw", "torchscript", shape=(1, 3, S, S))
    with pytest.raises(ModelFileError) as e:
        backend("torchscript", tmp_path, model=ts).check()
    msg = str(e.value)
    assert str(ts) in msg and f"input image [1, {S}, {S}, 3] float32" in msg and "channels" in msg
    # a declared crop side other than the one asked for; the ONNX output with a joint count the list does not have
    with pytest.raises(ModelFileError,
                       match=rf"{tmp_path}.*'image' expected shape \[\?, 128, 128, 3\], found \[n, {S}, {S}, 3\]"):
        backend("onnx", tmp_path, model=write_model(Probe(), tmp_path / "p", "onnx"), resolution=128).check()
    short = write_model(Constant(np.zeros((29, 3))), tmp_path / "short", "torchscript")
    with pytest.raises(ModelFileError, match=rf"{ts.parent}.*output poses3d has shape \[1, 29, 3\].*\[1, 30, 3\]"):
        backend("torchscript", tmp_path, model=short).check()


def test_the_crop_side_comes_from_the_model_or_the_parameter(tmp_path):
    dynamic = write_model(Probe(), tmp_path / "dyn", "onnx", fixed=False)
    with pytest.raises(ConfigError, match="dynamic size: set `resolution`"):
        backend("onnx", tmp_path, model=dynamic).check()
    assert estimator("onnx", dynamic, resolution=48).model.resolution == 48
    plain = tmp_path / "plain.pt"
    torch.jit.save(torch.jit.script(Probe()), str(plain))
    plain.with_suffix(".joints.txt").write_text("\n".join(JOINT_NAMES))
    with pytest.raises(ConfigError, match="no `input_resolution` attribute: set `resolution`"):
        TorchScriptCropModel(plain, "cpu", 1, None)
    assert estimator("torchscript", plain, resolution=32).model.resolution == 32


def test_body_box_from_the_frame_or_grown_from_the_head_box():
    o = CropPoseOptions()
    np.testing.assert_array_equal(body_box(np.array([1, 2, 30, 80.0]), np.array([0, 0, 10, 10.0]), o), [1, 2, 30, 80])
    # head box 20 x 16 px at x 100..120: side 20, 3 sides wide, 0.25 above, 6.5 below
    np.testing.assert_allclose(body_box(np.full(4, np.nan), np.array([100, 50, 120, 66.0]), o), [80, 45, 140, 196])
    with pytest.raises(FrameError, match="no usable body box"):
        body_box(np.full(4, np.nan), np.full(4, np.nan), o)


def test_depth_refinement_moves_the_pose_to_the_measured_distance():
    """All joints 3 m along the box ray, the map measures 2 m everywhere: with no joint offset the
    pose moves along the ray to z = 2; with body joints 5 cm behind the surface, to
    z = 2 + 24 x 0.05 / 30 = 2.04 (the 6 face joints on the surface); too few readings: unchanged."""
    ray = pixel_ray(CENTRE, K)
    pose = np.tile(3.0 * ray / ray[2], (30, 1))
    depth = np.full((480, 640), 2.0, np.float32)
    moved = place_with_depth(pose, K, depth, None, 0.0)
    np.testing.assert_allclose(moved, np.tile(2.0 * ray / ray[2], (30, 1)), atol=1e-9)
    assert place_with_depth(pose, K, depth, None, 0.05)[:, 2] == pytest.approx(np.full(30, 2.04))
    np.testing.assert_array_equal(place_with_depth(pose, K, np.zeros_like(depth), None, 0.05), pose)


def test_backend_pose_refines_with_the_depth_map(tmp_path):
    joints = np.tile([0.0, 0.0, 3000.0], (30, 1))
    model = write_model(Constant(joints), tmp_path / "c", "onnx")
    rgb = tmp_path / "im.png"
    from PIL import Image
    Image.fromarray(np.zeros((480, 640, 3), np.uint8)).save(rgb)
    frame = FrameRef("f", "test", "s", rgb, K, (640, 480), np.array([440, 100, 480, 140], np.float32),
                     body_box=BOX.astype(np.float32))
    depth = DepthMap(np.full((480, 640), 2.5, np.float32), np.ones((480, 640), bool))
    flat = backend("onnx", tmp_path, model=model, depth_refine=False).pose(frame, depth)
    deep = backend("onnx", tmp_path, model=model, joint_depth_offset=0.0).pose(frame, depth)
    ray = pixel_ray(CENTRE, K)
    np.testing.assert_allclose(flat, np.tile(3.0 * ray, (30, 1)), atol=1e-6)
    np.testing.assert_allclose(deep, np.tile(2.5 * ray / ray[2], (30, 1)), atol=1e-5)


# --- the export helper and the pipeline -----------------------------------------------------------


def test_save_crop_model_writes_files_the_backends_load(tmp_path):
    joints = np.random.default_rng(1).normal(0, 200, (30, 3)) + [0, 0, 3000]
    out = save_crop_model(Constant(joints), S, list(JOINT_NAMES), tmp_path / "m" / "tiny")
    assert out.torchscript == tmp_path / "m" / "tiny.pt" and out.onnx == tmp_path / "m" / "tiny.onnx"
    assert out.onnx_error is None and max(out.max_diff_mm.values()) < 1e-3
    assert read_joint_names(out.joints) == list(JOINT_NAMES)
    assert TorchScriptCropModel(out.torchscript, "cpu", 1, None).resolution == S
    with pytest.raises(ValueError, match=r"returns \[1, 30, 3\] for one crop; expected \[1, 29, 3\]"):
        save_crop_model(Constant(joints), S, list(JOINT_NAMES[:29]), tmp_path / "bad")


def test_pipeline_stores_what_the_model_says_in_metres_in_the_camera_frame(synth_world, tmp_path):
    """`run_pipeline` on the synthetic world with `pose: onnx` and `pose: torchscript` (the files
    `save_crop_model` writes, a shuffled name list, no depth refinement): every kept frame's pose is
    the model's joints turned back from the crop around the box grown from the frame's head box
    (GFIE has no body box), in metres, by name. Both backends read the depth (geometry task)."""
    names = list(np.random.default_rng(7).permutation(JOINT_NAMES))
    joints = np.random.default_rng(2).normal(0, 300, (30, 3)) + [0, 0, 2500]
    out = save_crop_model(Constant(joints), S, names, tmp_path / "models" / "tiny")
    index = [names.index(n) for n in JOINT_NAMES]
    for kind, model in (("onnx", out.onnx), ("torchscript", out.torchscript)):
        overrides = [*SMALL, f"stages.pose.backend={kind}", "stages.pose.params={}",
                     f"stages.pose.params.model={model}", "stages.pose.params.depth_refine=false", "run.shard_size=5"]
        conf = load_pipeline("synthetic", synth_world, overrides=overrides, check_files=False)
        assert conf.upstream["pose"] == ("input", "depth")
        store = tmp_path / f"{kind}.zarr"
        summary = run_pipeline("synthetic", synth_world, store, progress=False, overrides=overrides)
        s = open_store(store)
        assert summary.counts.frames_kept == 12 and summary.counts.failures == {}
        for pose, Kf, head in zip(s.frames["pose"], s.frames["K"], s.frames["head_box"]):
            box = body_box(np.full(4, np.nan), head, CropPoseOptions())
            want = crop_to_camera(joints, look_at_crop(Kf.astype(np.float64), box, S).R)[index]
            np.testing.assert_allclose(pose, want, atol=2e-6)
        prov = s.attrs["stages"]["pose"]
        assert prov["backend"] == kind and set(prov["models"]) == {str(model), str(out.joints)}


def _export_script():
    path = Path(__file__).resolve().parent.parent / "scripts" / "export_crop_pose.py"
    spec = importlib.util.spec_from_file_location("export_crop_pose", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return path, module


class FakeMetrabs(torch.nn.Module):
    """MeTRAbs's crop model's call convention, forward((image NCHW, intrinsics)) -> [N, n, 3]:
    joint i at (mean of channel i % 3, K'[0, 0], i)."""

    def forward(self, inp):
        image, intrinsics = inp
        ch = image.mean(dim=(2, 3))                                   # [N, 3]
        i = torch.arange(5, dtype=torch.float32)
        return torch.stack([ch[:, [0, 1, 2, 0, 1]], intrinsics[:, :1, 0].expand(-1, 5),
                            i.expand(image.shape[0], 5)], -1)


def test_export_script_help_and_its_metrabs_wrapper(tmp_path):
    """The script's --help says where the weights are; its MeTRAbs wrapper feeds NCHW, applies the
    joint transform (n, N) and the skeleton's indices, and goes through save_crop_model. (The
    authors' classes themselves are not importable here.)"""
    path, script = _export_script()
    out = subprocess.run([sys.executable, str(path), "metrabs", "--help"], capture_output=True, text=True, check=True)
    assert "bit.ly/metrabs_l_pt" in out.stdout and "unverified" in out.stdout
    transform = np.zeros((5, 4))
    transform[[0, 1, 2, 3], [0, 1, 2, 3]] = 1.0
    transform[4, 3] = 1.0                                             # joint 3' = joint 3 + joint 4
    wrapped = script.MetrabsCrop(FakeMetrabs(), transform, np.array([3, 0, 2]))
    image = torch.zeros(1, S, S, 3)
    image[..., 0], image[..., 1], image[..., 2] = 0.25, 0.5, 0.75
    K = torch.tensor([[[100.0, 0, 32], [0, 100, 32], [0, 0, 1]]])
    got = wrapped(image, K)[0].numpy()
    np.testing.assert_allclose(got, [[0.25 + 0.5, 200, 7], [0.25, 100, 0], [0.75, 100, 2]], atol=1e-6)
    saved = save_crop_model(wrapped, S, ["c", "a", "b"], tmp_path / "fake")
    assert max(saved.max_diff_mm.values()) < 1e-3 and read_joint_names(saved.joints) == ["c", "a", "b"]


def test_a_pipeline_naming_a_bad_model_stops_before_any_work(synth_world, tmp_path):
    """`run_pipeline` runs each backend's check() first: an NCHW model is refused, no store is made."""
    bad = write_model(ChannelsFirst(), tmp_path / "nchw", "onnx", shape=(1, 3, S, S))
    out = tmp_path / "s.zarr"
    with pytest.raises(ModelFileError, match=r"nchw.onnx: input 'image' expected shape \[\?, \?, \?, 3\]"):
        run_pipeline("synthetic", synth_world, out, progress=False,
                     overrides=[*SMALL, "stages.pose.backend=onnx", "stages.pose.params={}",
                                f"stages.pose.params.model={bad}"])
    assert not out.exists() and not (tmp_path / "s.zarr.work").exists()
