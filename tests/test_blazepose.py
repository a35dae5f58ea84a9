"""`pose/blazepose`: the detector decoding, the ROI crop, the camera placement and the mapping to
smpl+head_30 on hand-made values, then the real registry models on scikit-image's photos (the
models come from `make models`, which `make test` runs first)."""
import pickle
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import skimage.data
from PIL import Image

from ga3ce_prep.errors import FrameError, ModelFileError
from ga3ce_prep.estimators.pose import blazepose as bp
from ga3ce_prep.estimators.pose.blazepose_smpl import to_smpl_head30
from ga3ce_prep.estimators.pose.placement import refine_with_depth, sample_depth, solve_translation, weighted_median
from ga3ce_prep.estimators.runtime.crops import SquareRoi, apply_affine, invert_affine, letterbox_roi, roi_affine
from ga3ce_prep.estimators.runtime.ssd import decode_detections, ssd_anchors, weighted_nms
from ga3ce_prep.frames import DepthMap, FrameRef
from ga3ce_prep.geometry import project
from ga3ce_prep.pipeline import load_pipeline, run_pipeline
from ga3ce_prep.pipeline.tasks import task_stages
from ga3ce_prep.skeleton import HEAD_JOINTS, N_JOINTS, J
from ga3ce_prep.stages import backend_class
from ga3ce_prep.stages.base import BackendContext
from ga3ce_prep.store import open_store
from ga3ce_prep.synthetic.person import REST
from ga3ce_prep.testing.worlds import SMALL
from ga3ce_prep.weights import registry as registry_models

L = bp.L


# --- detector decoding ---------------------------------------------------------------------------
def test_ssd_anchors_count_order_and_centres():
    a = ssd_anchors(bp.DET_SIZE, bp.DET_STRIDES)
    assert a.shape == (2254, 2) == (28 * 28 * 2 + 14 * 14 * 2 + 7 * 7 * 6, 2)
    np.testing.assert_allclose(a[0], a[1])                        # 2 anchors per cell at stride 8
    np.testing.assert_allclose(a[0], [0.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(a[2], [1.5 / 28, 0.5 / 28])        # x varies fastest
    np.testing.assert_allclose(a[2 * 28], [0.5 / 28, 1.5 / 28])
    np.testing.assert_allclose(a[1568], [0.5 / 14, 0.5 / 14])     # stride 16 starts after 28*28*2
    np.testing.assert_allclose(a[1960:1966], [[0.5 / 7, 0.5 / 7]] * 6)  # three stride-32 layers: 6 per cell
    np.testing.assert_allclose(a[-1], [6.5 / 7, 6.5 / 7])


def test_decode_detection_by_hand_through_the_letterbox():
    # a 448x224 (W x H) image: letterbox scale 0.5, bars of 56 px above and below
    anchors = np.array([[0.5, 0.5], [0.25, 0.25]])
    raw = np.zeros((2, 12))
    raw[0, :4] = [22.4, -11.2, 44.8, 22.4]        # centre +0.1, -0.05; size 0.2 x 0.1 of the 224 input
    raw[0, 4:6] = [0.0, 44.8]                     # keypoint 0: anchor + (0, 0.2)
    logits = np.array([0.0, -1.0])                # sigmoid 0.5 (kept at 0.5), 0.27 (dropped)
    M = roi_affine(letterbox_roi((224, 448)), 224)
    det = bp.Detections(*decode_detections(raw, logits, anchors, 224, 4, invert_affine(M), 0.5, 0.3))
    assert len(det) == 1 and det.score[0] == pytest.approx(0.5)
    # centre (0.6, 0.45) of the input -> (134.4, 100.8) input px -> ((134.4) / 0.5, (100.8 - 56) / 0.5)
    # in continuous image px -> minus 0.5 for pixel centres at integers
    cx, cy, w, h = 268.8 - 0.5, 89.6 - 0.5, 0.2 * 224 / 0.5, 0.1 * 224 / 0.5
    np.testing.assert_allclose(det.box[0], [cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], atol=1e-9)
    np.testing.assert_allclose(det.keypoints[0, 0], [224 - 0.5, (0.7 * 224 - 56) / 0.5 - 0.5], atol=1e-9)
    np.testing.assert_allclose(det.keypoints[0, 1], [224 - 0.5, (112 - 56) / 0.5 - 0.5], atol=1e-9)


def test_letterbox_pixels_land_where_the_affine_says():
    rgb = np.zeros((100, 300, 3), np.uint8)
    rgb[40, 250] = 255
    x, M = bp.detector_input(rgb)
    s = 224 / 300                                  # the image's outer edges land on the input's: bars of 74.67 px
    np.testing.assert_allclose(M, [[s, 0, 0.5 * s - 0.5], [0, s, 0.5 * s + (224 - 100 * s) / 2 - 0.5]], atol=1e-12)
    assert x.shape == (1, 224, 224, 3) and x.min() == -1.0
    q = apply_affine(M, [250, 40])
    peak = np.unravel_index(np.argmax(x[0, ..., 0]), (224, 224))
    assert np.hypot(peak[1] - q[0], peak[0] - q[1]) < 1.0
    assert x[0, 0, 0, 0] == -1.0 and x[0, 112, 112, 0] == -1.0   # bar and black content both -1


def _dets(boxes, scores, kps=None):
    boxes = np.asarray(boxes, float)
    kps = np.zeros((len(boxes), 4, 2)) if kps is None else np.asarray(kps, float)
    return bp.Detections(boxes, kps, np.asarray(scores, float))


def test_plain_nms_keeps_the_best_of_each_cluster():
    """`weighted_nms: false`: the cluster is the weighted one's (test_facemesh), its box and
    keypoints the best member's."""
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60.0]])
    kps = np.zeros((3, 4, 2))
    kps[:, 0] = [[0, 0], [10, 10], [55, 55]]
    b, k, s = weighted_nms(boxes, kps, np.array([0.6, 0.9, 0.7]), 0.3, weighted=False)
    np.testing.assert_array_equal(s, [0.9, 0.7])
    np.testing.assert_array_equal(b, boxes[[1, 2]])
    np.testing.assert_array_equal(k, kps[[1, 2]])
    b, k, s = weighted_nms(np.zeros((0, 4)), np.zeros((0, 4, 2)), np.zeros(0), 0.3)
    assert b.shape == (0, 4) and k.shape == (0, 4, 2) and s.shape == (0,)


def test_choose_detection_by_body_box_then_head_box_then_score():
    kps = np.array([[[100, 300], [100, 100], [100, 150], [100, 50]],     # person A (left)
                    [[400, 300], [400, 100], [400, 150], [400, 50]]], float)  # person B (right)
    det = _dets([[80, 120, 120, 160], [380, 120, 420, 160]], [0.9, 0.6], kps)
    hw = (480, 640)
    assert bp.choose_detection(det, hw) == 0
    assert bp.choose_detection(det, hw, body_box=np.array([200, 100, 600, 479])) == 1
    assert bp.choose_detection(det, hw, body_box=np.full(4, np.nan), head_box=np.array([390, 90, 420, 120])) == 1
    assert bp.choose_detection(det, hw, head_box=np.array([600, 460, 630, 479])) == 0   # in no circle: best score
    with pytest.raises(FrameError, match="no person"):
        bp.choose_detection(_dets(np.zeros((0, 4)), []), hw)


# --- ROI and crop ----------------------------------------------------------------------------------
def test_roi_from_keypoints_upright_and_lying():
    roi = bp.roi_from_keypoints(np.array([100.0, 200.0]), np.array([100.0, 100.0]))
    assert roi.angle == pytest.approx(0.0) and roi.size == pytest.approx(250.0)
    np.testing.assert_allclose(roi.center, [100, 200])
    lying = bp.roi_from_keypoints(np.array([100.0, 200.0]), np.array([180.0, 200.0]))  # head to the right
    assert lying.angle == pytest.approx(np.pi / 2) and lying.size == pytest.approx(200.0)


@pytest.mark.parametrize("theta", [0.0, 0.7, -2.5])
def test_crop_affine_round_trip_and_orientation(theta):
    hip = np.array([300.0, 260.0])
    up = np.array([np.sin(theta), -np.cos(theta)])            # the body axis, turned by theta
    roi = bp.roi_from_keypoints(hip, hip + 80 * up)
    assert roi.angle == pytest.approx(theta)
    M = roi_affine(roi, bp.LMK_SIZE)
    pts = np.random.default_rng(0).uniform(0, 600, (20, 2))
    np.testing.assert_allclose(apply_affine(invert_affine(M), apply_affine(M, pts)), pts, atol=1e-9)
    np.testing.assert_allclose(apply_affine(M, hip), [127.5, 127.5], atol=1e-9)
    head = apply_affine(M, hip + 80 * up)                      # the scale point is straight up in the crop
    np.testing.assert_allclose(head, [127.5, 127.5 - 80 * 256 / 200], atol=1e-9)
    rgb = np.zeros((600, 640, 3), np.uint8)
    dot = np.array([340, 200])
    rgb[dot[1] - 1:dot[1] + 2, dot[0] - 1:dot[0] + 2] = 255
    x, M2 = bp.landmark_input(rgb, roi)
    np.testing.assert_array_equal(M2, M)
    assert x.shape == (1, 256, 256, 3) and 0 <= x.min() and x.max() <= 1
    ys, xs = np.nonzero(x[0, ..., 0] > 0.5)
    np.testing.assert_allclose([xs.mean(), ys.mean()], apply_affine(M, dot), atol=0.6)


def test_landmark_crop_repeats_the_border_outside_the_image():
    rgb = np.zeros((120, 160, 3), np.uint8)
    rgb[:, -1] = (200, 100, 50)                                    # the right-hand column
    roi = SquareRoi(np.array([150.0, 60.0]), 64.0, 0.0)            # half of it right of the image
    x, M = bp.landmark_input(rgb, roi)
    beyond = apply_affine(M, [[170.0, 60.0], [178.0, 35.0]])       # crop pixels of points right of the image
    for u, v in np.rint(beyond).astype(int):
        np.testing.assert_allclose(x[0, v, u], np.array([200, 100, 50]) / 255, atol=1e-6)


def test_decode_landmarks_inverts_the_crop_and_turns_the_world():
    roi = SquareRoi(np.array([200.0, 150.0]), 128.0, np.pi / 2)
    img = np.random.default_rng(1).uniform(100, 300, (bp.N_BODY, 2))
    crop_xy = apply_affine(roi_affine(roi, bp.LMK_SIZE), img) + 0.5  # the model's crop pixels: edges at 0
    raw = np.zeros((bp.N_MODEL, 5))
    raw[:bp.N_BODY, :2] = crop_xy
    raw[:, 3], raw[:, 4] = 2.0, -2.0
    world = np.zeros((bp.N_MODEL, 3))
    world[0] = [1.0, 0.0, 0.3]                                     # crop's x axis
    image, vis, pres, w = bp.decode_landmarks(raw.ravel(), world.ravel(), roi)
    np.testing.assert_allclose(image, img, atol=1e-9)
    np.testing.assert_allclose(vis, 1 / (1 + np.exp(-2.0)))
    np.testing.assert_allclose(pres, 1 / (1 + np.exp(2.0)))
    np.testing.assert_allclose(w[0], [0.0, 1.0, 0.3], atol=1e-12)  # crop x shows image down when turned 90 deg


# --- camera placement ------------------------------------------------------------------------------
K = np.array([[500.0, 0, 320], [0, 480.0, 240], [0, 0, 1]])


def _body(rng, n=20):
    return rng.uniform([-0.3, -0.8, -0.15], [0.3, 0.9, 0.15], (n, 3))


def test_solve_translation_recovers_a_known_T_and_ignores_zero_weights():
    rng = np.random.default_rng(2)
    world, T = _body(rng), np.array([0.4, -0.2, 3.1])
    uv = project(world + T, K)
    w = np.ones(len(world))
    np.testing.assert_allclose(solve_translation(world, uv, w, K), T, atol=1e-9)
    uv[3] += 200.0                                                 # a wrong landmark with weight 0
    w[3] = 0.0
    np.testing.assert_allclose(solve_translation(world, uv, w, K), T, atol=1e-9)
    with pytest.raises(FrameError, match="usable"):
        solve_translation(world, uv, np.eye(len(world))[0], K)


def test_sample_depth_and_weighted_median():
    depth = np.full((20, 30), 2.0)
    depth[:, 15:] = 4.0
    valid = np.ones_like(depth, bool)
    valid[0:5, 0:5] = False
    d = sample_depth(depth, np.array([[7.0, 10.0], [20.0, 10.0], [1.0, 1.0], [-50.0, 3.0], [np.nan, 2]]), valid)
    np.testing.assert_allclose(d[:2], [2.0, 4.0])
    assert np.isnan(d[2:]).all()                  # all invalid, outside, NaN pixel
    assert weighted_median(np.array([1.0, 2.0, 10.0]), np.array([1.0, 1.0, 5.0])) == 10.0


def test_depth_refinement_recovers_T_from_a_wrong_start_and_rejects_a_background_joint():
    rng = np.random.default_rng(3)
    world, T = _body(rng, 12), np.array([-0.3, 0.1, 2.5])
    uv = project(world + T, K)
    offset = 0.04
    depth = np.full((480, 640), 6.0)               # the wall behind
    for (u, v), z in zip(np.rint(uv).astype(int), (world + T)[:, 2]):
        depth[v - 2:v + 3, u - 2:u + 3] = z - offset
    u, v = np.rint(uv[5]).astype(int)
    depth[v - 2:v + 3, u - 2:u + 3] = 6.0           # joint 5 at a silhouette edge: the wall behind it
    w = np.ones(len(world))
    start = T * 1.2                                  # a 2D-only answer with the wrong size
    Tr, n = refine_with_depth(world, uv, w, K, start, depth, None, offset)
    np.testing.assert_allclose(Tr, T, atol=1e-9)
    assert n == len(world) - 1
    Tr, n = refine_with_depth(world, uv, w, K, start, np.zeros_like(depth))   # no depth: unchanged
    assert n == 0 and np.array_equal(Tr, start)


def test_placement_on_the_synthetic_world_2d_only_vs_depth_refined(synth_world_640):
    """Truth poses as a monocular estimator would give them (root-relative, 2 cm joint noise, 2 px
    2D noise, visible joints only; size right or 10% off), placed 2D-only and depth-refined on the
    world's sensor depth (noise and holes). Measured: 2D-only 3.5 / 30 cm median root error
    (size right / off), refined 2.6 / 4-5.5 cm."""
    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.stages.truth import truth_frame

    sensor = backend_class("depth", "sensor")({}, BackendContext(synth_world_640))
    rng = np.random.default_rng(0)
    err = {1.0: ([], []), 0.9: ([], [])}
    for fr in open_dataset("gfie", synth_world_640).frames():
        tf = truth_frame(synth_world_640 / "truth.h5", fr.id, maps=True)
        P = np.asarray(tf.pose, float)
        dm = sensor.depth(fr)
        uv = project(P, fr.K)
        H, W = dm.depth.shape
        inside = (uv >= 0).all(1) & (uv[:, 0] < W) & (uv[:, 1] < H)
        ui, vi = np.clip(np.rint(uv).astype(int), 0, [W - 1, H - 1]).T
        w = (inside & (np.abs(tf.depth[vi, ui] - P[:, 2]) < 0.15)).astype(float)   # not occluded
        offset = np.full(N_JOINTS, 0.05)
        offset[list(HEAD_JOINTS)] = 0.0
        root = 0.5 * (P[J["lhip"]] + P[J["rhip"]])
        for scale, (e2d, edepth) in err.items():
            world = (P - root) * scale + rng.normal(0, 0.02, P.shape)
            img = uv + rng.normal(0, 2.0, uv.shape)
            T2 = solve_translation(world, img, w, fr.K)
            Td, n = refine_with_depth(world, img, w, fr.K, T2, dm.depth, dm.valid, offset)
            assert n >= 5
            e2d.append(np.linalg.norm(T2 - root))
            edepth.append(np.linalg.norm(Td - root))
    (a2, ad), (b2, bd) = (np.median(e, axis=1) for e in err.values())
    assert ad < 0.05 and a2 < 0.08            # right size: both close
    assert bd < 0.08 and b2 > 0.15            # 10% too small: 2D-only is tens of cm off, depth fixes it


def test_place_landmarks_2d_only_and_with_depth():
    """A person 10% larger than the model's world shape: 2D-only lands 10% too near; the depth
    refinement (face landmarks on the skin, body joints 5 cm behind it) finds the true root."""
    rng = np.random.default_rng(4)
    lm_true, _ = _rest_landmarks()
    unused = np.isnan(lm_true).any(1)
    lm_true[unused] = lm_true[L["nose"]]                             # mouth, eye corners, thumbs, heels
    hip = 0.5 * (lm_true[L["left_hip"]] + lm_true[L["right_hip"]])
    world = (lm_true - hip) / 1.1
    uv = project(lm_true, K)
    vis = np.full(bp.N_BODY, 0.9)
    vis[rng.choice(bp.N_BODY, 5, replace=False)] = 0.1
    vis[unused] = 0.0
    lm = bp.PoseLandmarks(uv, vis, np.ones(bp.N_BODY), world, 1.0, 1.0, SquareRoi(hip[:2], 100.0, 0.0))
    depth = np.zeros((480, 640))
    order = np.argsort(-lm_true[:, 2])                               # nearer landmarks painted last
    for i in order:
        u, v = np.rint(uv[i]).astype(int)
        depth[v - 2:v + 3, u - 2:u + 3] = lm_true[i, 2] - (0.0 if i in bp.FACE else 0.05)
    flat = bp.place_landmarks(lm, K, 0.5, ray_alignment=False)
    assert np.linalg.norm(project(flat, K)[vis > 0.5] - uv[vis > 0.5], axis=1).max() < 25   # fits the 2D
    root2d = 0.5 * (flat[L["left_hip"]] + flat[L["right_hip"]])
    assert root2d[2] == pytest.approx(hip[2] / 1.1, rel=0.02)
    deep = bp.place_landmarks(lm, K, 0.5, ray_alignment=False, depth=depth, valid=depth > 0)
    rootd = 0.5 * (deep[L["left_hip"]] + deep[L["right_hip"]])
    assert np.linalg.norm(rootd - hip) < 0.03 < np.linalg.norm(root2d - hip)


# --- the mapping -------------------------------------------------------------------------------------
def _rest_landmarks():
    """BlazePose landmarks made from the synthetic rest skeleton, in camera axes (person facing the
    camera 3 m away): body frame (x forward, y left, z up) -> camera (x right, y down, z forward)."""
    rest = REST @ np.array([[0, 1, 0], [0, 0, -1], [-1, 0, 0]]).T + [0, 1.0, 3.0]   # x_c = y_b, y_c = -z_b, z_c = -x_b
    lm = np.full((bp.N_BODY, 3), np.nan)
    direct = {"nose": "nose", "left_eye": "leye", "right_eye": "reye", "left_ear": "lear", "right_ear": "rear",
              "left_shoulder": "lsho", "right_shoulder": "rsho", "left_elbow": "lelb", "right_elbow": "relb",
              "left_wrist": "lwri", "right_wrist": "rwri", "left_hip": "lhip", "right_hip": "rhip",
              "left_knee": "lkne", "right_knee": "rkne", "left_ankle": "lank", "right_ankle": "rank",
              "left_foot_index": "ltoe", "right_foot_index": "rtoe"}
    for name, j in direct.items():
        lm[L[name]] = rest[J[j]]
    for side, hand in (("left", "lhan"), ("right", "rhan")):
        lm[L[f"{side}_pinky"]] = rest[J[hand]] + [0, 0, 0.03]
        lm[L[f"{side}_index"]] = rest[J[hand]] - [0, 0, 0.03]
    return lm, rest


def test_mapping_reproduces_the_rest_skeleton():
    lm, rest = _rest_landmarks()
    out = to_smpl_head30(lm, np.ones(bp.N_BODY))
    assert out.shape == (N_JOINTS, 3)
    err = np.linalg.norm(out - rest, axis=1)
    direct = [J[n] for n in ("lhip", "rhip", "lkne", "rkne", "lank", "rank", "ltoe", "rtoe", "lsho", "rsho",
                             "lelb", "relb", "lwri", "rwri", "lhan", "rhan", "nose", "leye", "lear", "reye", "rear")]
    assert err[direct].max() < 1e-12
    for name in ("pelv", "bell", "spin", "thor", "neck", "lcla", "rcla", "head"):
        assert err[J[name]] < 0.015, (name, err[J[name]])       # REST's forward offsets are about 1 cm
    assert err[J["htop"]] < 0.025
    assert out[J["htop"], 1] < out[J["leye"], 1] - 0.08           # the head top is above the eyes (y down)


def test_mapping_leaves_low_visibility_joints_and_what_depends_on_them_nan():
    lm, _ = _rest_landmarks()
    vis = np.ones(bp.N_BODY)
    vis[L["left_hip"]] = 0.2
    vis[L["right_wrist"]] = 0.49
    out = to_smpl_head30(lm, vis, min_visibility=0.5)
    nan = {n for n, i in J.items() if np.isnan(out[i]).any()}
    assert nan == {"lhip", "pelv", "bell", "spin", "thor", "rwri"}
    assert np.isfinite(to_smpl_head30(lm, vis, min_visibility=0.1)).all()


# --- the real models on real photos ------------------------------------------------------------------
def _k_60deg(w: int, h: int) -> np.ndarray:
    f = (w / 2) / np.tan(np.radians(30))
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])


@pytest.fixture(scope="module", params=["full", "heavy"])
def estimator(request):
    return bp.BlazePoseEstimator(registry_models.model_path("pose_detection"),
                                 registry_models.model_path(f"pose_landmark_{request.param}"))


def _length(p, a, b):
    return float(np.linalg.norm(p[L[a]] - p[L[b]]))


def test_astronaut_upper_body_in_place_and_plausible_sizes(estimator):
    rgb = skimage.data.astronaut()
    lm = estimator(rgb)
    assert lm.score > 0.9 and lm.detection_score > 0.7
    face = [L[n] for n in ("nose", "left_eye", "right_eye", "left_ear", "right_ear")]
    x, y = lm.image[face].T                                         # the face: about x 170-290, y 60-190
    assert ((170 < x) & (x < 290) & (60 < y) & (y < 190)).all()
    x, y = lm.image[[L["left_shoulder"], L["right_shoulder"]]].T    # shoulders: x 60-360, y 180-300
    assert ((60 < x) & (x < 360) & (180 < y) & (y < 300)).all()
    assert lm.image[L["left_shoulder"], 0] > lm.image[L["right_shoulder"], 0] + 100   # facing us: left on the right
    assert lm.image[L["nose"], 1] < lm.image[[L["left_shoulder"], L["right_shoulder"]], 1].min() - 50
    assert lm.world[L["nose"], 1] < lm.world[[L["left_shoulder"], L["right_shoulder"]], 1].min()
    assert 0.25 < _length(lm.world, "left_shoulder", "right_shoulder") < 0.5
    for side in ("left", "right"):
        assert 0.2 < _length(lm.world, f"{side}_shoulder", f"{side}_elbow") < 0.4
    mirrored = estimator(np.ascontiguousarray(rgb[:, ::-1]))
    for a, b in (("left_shoulder", "right_shoulder"), ("right_shoulder", "left_shoulder"), ("nose", "nose")):
        assert abs(mirrored.image[L[a], 0] - (511 - lm.image[L[b], 0])) < 20   # the labels swap sides


def test_no_person_in_a_cat_or_a_grey_image(estimator):
    for rgb in (skimage.data.chelsea(), np.full((480, 640, 3), 128, np.uint8)):
        with pytest.raises(FrameError, match="no person"):
            estimator(rgb)


def test_ray_alignment_keeps_the_pose_consistent_when_the_camera_turns(estimator):
    """The photo seen by cameras turned by 25 deg left and right and 15 deg up (exact homographies
    K R K^-1 onto a 1000x800 frame): the body's orientation in each camera should differ from the
    unturned one's by R. MediaPipe's image-aligned world axes miss most of the turn (measured
    19-28 deg of error, both models); turned to the ray through the visible landmarks, 5-13 deg."""
    rgb = skimage.data.astronaut()
    K0, K2 = _k_60deg(512, 512), _k_60deg(1000, 800)
    K2[0, 0] = K2[1, 1] = K0[0, 0]
    upper = list(range(15))                                         # face, shoulders, elbows

    def angle(a, b):
        a, b = a[upper] - a[upper].mean(0), b[upper] - b[upper].mean(0)
        U, _, Vt = np.linalg.svd(b.T @ a)
        R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        return np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))

    def seen(R):
        lm = estimator(cv2.warpPerspective(rgb, K2 @ R @ np.linalg.inv(K0), (1000, 800)))
        return bp.place_landmarks(lm, K2, 0.5, True), bp.place_landmarks(lm, K2, 0.5, False)

    al0, pl0 = seen(np.eye(3))
    err_al, err_pl = [], []
    for rv in ([0, 25, 0], [0, -25, 0], [-15, 0, 0]):
        R = cv2.Rodrigues(np.radians(np.array(rv, float)))[0]
        al, pl = seen(R)
        err_al.append(angle(al, al0 @ R.T))
        err_pl.append(angle(pl, pl0 @ R.T))
    assert np.mean(err_al) < 12 and np.mean(err_al) < np.mean(err_pl) - 8, (err_al, err_pl)


# --- the backend ------------------------------------------------------------------------------------
def _frame(tmp_path: Path, rgb: np.ndarray, name: str = "a") -> FrameRef:
    path = tmp_path / f"{name}.png"
    Image.fromarray(rgb).save(path)
    h, w = rgb.shape[:2]
    return FrameRef(name, "test", "s", path, _k_60deg(w, h), (w, h), np.full(4, np.nan, np.float32))


def _unmeasured(rgb: np.ndarray) -> DepthMap:
    """A depth map with no measured pixel: the placement stays the 2D fit."""
    return DepthMap(np.zeros(rgb.shape[:2], np.float32), np.zeros(rgb.shape[:2], bool))


@pytest.mark.parametrize("variant", ["full", "heavy"])
def test_backend_astronaut_in_the_camera_frame(tmp_path, variant):
    b = backend_class("pose", "blazepose")({"variant": variant}, BackendContext(tmp_path))
    b.check()
    b.warm()
    rgb = skimage.data.astronaut()
    pose = b.pose(_frame(tmp_path, rgb), _unmeasured(rgb))
    assert pose.shape == (N_JOINTS, 3) and pose.dtype == np.float32
    for name in ("nose", "leye", "reye", "lear", "rear", "lsho", "rsho", "neck", "lcla", "rcla", "head", "htop"):
        assert np.isfinite(pose[J[name]]).all(), name
    sho_c = 0.5 * (pose[J["lsho"]] + pose[J["rsho"]])
    assert 0.4 < sho_c[2] < 3.0 and 0.1 < pose[J["nose"], 2] < sho_c[2]   # facing us: the nose is nearer
    assert 0.25 < np.linalg.norm(pose[J["lsho"]] - pose[J["rsho"]]) < 0.5
    assert pose[J["lsho"], 0] > pose[J["rsho"], 0]                 # camera x right: their left is on our right
    assert pose[J["htop"], 1] < pose[J["nose"], 1] < pose[J["neck"], 1]
    clone = pickle.loads(pickle.dumps(b))                          # interpreters stay behind
    assert getattr(clone, "_estimator", None) is None
    np.testing.assert_array_equal(clone.pose(_frame(tmp_path, rgb, "b"), _unmeasured(rgb)), pose)


def test_backend_shifts_the_pose_by_what_the_depth_refinement_gives(tmp_path):
    """The backend reads the depth stage's map (`needs`) and places the landmarks with it: the
    whole pose moves by refine_with_depth's T minus the 2D fit's, computed here from the same
    landmarks (a backdrop 20% farther than the 2D fit's root, 1 column in 3 unmeasured);
    `depth_refine: false` ignores the map."""
    rgb = skimage.data.astronaut()
    frame = _frame(tmp_path, rgb)
    make = backend_class("pose", "blazepose")
    b = make({"ray_alignment": False}, BackendContext(tmp_path))
    assert b.needs == ("depth",)
    lm = b.estimator()(rgb)
    w = np.where(lm.visibility >= 0.5, lm.visibility, 0.0)
    T2 = solve_translation(lm.world, lm.image, w, frame.K)
    depth = np.full(rgb.shape[:2], 1.2 * T2[2], np.float32)
    valid = np.ones(rgb.shape[:2], bool)
    valid[:, ::3] = False
    offset = np.where(np.isin(np.arange(bp.N_BODY), bp.FACE), 0.0, 0.05)
    Td, n = refine_with_depth(lm.world, lm.image, w, frame.K, T2, depth, valid, offset)
    assert n >= 5 and Td[2] > T2[2] + 0.1

    flat = b.pose(frame, _unmeasured(rgb))
    deep = b.pose(frame, DepthMap(depth, valid))
    np.testing.assert_array_equal(flat, to_smpl_head30(lm.world + T2, lm.visibility).astype(np.float32))
    np.testing.assert_array_equal(np.isnan(deep), np.isnan(flat))
    seen = np.isfinite(flat).all(1)
    np.testing.assert_allclose(deep[seen] - flat[seen], np.tile(Td - T2, (seen.sum(), 1)), atol=1e-6)
    off = make({"ray_alignment": False, "depth_refine": False}, BackendContext(tmp_path))
    np.testing.assert_array_equal(off.pose(frame, DepthMap(depth, valid)), flat)


def test_backend_no_person_raises_frame_error(tmp_path):
    b = backend_class("pose", "blazepose")({}, BackendContext(tmp_path))
    rgb = skimage.data.chelsea()
    with pytest.raises(FrameError, match="no person"):
        b.pose(_frame(tmp_path, rgb), _unmeasured(rgb))


def test_backend_check_refuses_a_damaged_or_missing_model(tmp_path, monkeypatch):
    for key in ("pose_detection", "pose_landmark_full"):
        dst = registry_models.file_path(key, tmp_path)
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(registry_models.model_path(key), dst)
    monkeypatch.setenv("GA3CE_MODELS", str(tmp_path))
    b = backend_class("pose", "blazepose")({}, BackendContext(tmp_path))
    b.check()
    path = registry_models.file_path("pose_landmark_full", tmp_path)
    data = bytearray(path.read_bytes())
    data[1000] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="ga3ce-prep models fetch"):
        b.check()
    with pytest.raises(ModelFileError, match="models fetch"):       # heavy is not in this folder
        backend_class("pose", "blazepose")({"variant": "heavy"}, BackendContext(tmp_path)).check()


# --- in the pipeline ---------------------------------------------------------------------------------
BLAZEPOSE = [*SMALL, "stages.pose.backend=blazepose", "stages.pose.params={}", "run.shard_size=5"]


def test_pipeline_runs_blazepose_with_the_depth_map(synth_world, tmp_path):
    """`run_pipeline` on the synthetic world (sensor depth) with `pose: blazepose`: the pose joins
    the geometry task and gets each frame's depth map. The synthetic people are shaded geometric
    meshes 40-67 px tall: the detector fires only on the test scene (scores 0.56-0.72, elsewhere
    at most 0.29), where the landmark model's pose flag is 0.74-0.99; the 8 other frames are kept
    with a NaN pose and a "degraded" failure record. Against a run with `depth_refine: false`,
    each found pose moves as a whole (0.7-1.6 m here: the 2D fit puts the small figure at about
    2.2 m)."""
    conf = load_pipeline("synthetic", synth_world, overrides=BLAZEPOSE, check_files=False)
    assert conf.upstream["pose"] == ("input", "depth")
    assert task_stages(conf.upstream)["geometry"] == ("depth", "objects", "pose", "head")  # the head reads the pose
    poses = {}
    for refine in (True, False):
        out = tmp_path / f"refine_{refine}.zarr"
        summary = run_pipeline("synthetic", synth_world, out, progress=False,
                               overrides=[*BLAZEPOSE, f"stages.pose.params.depth_refine={str(refine).lower()}"])
        s = open_store(out)
        lost = np.isnan(s.frames["pose"]).all(axis=(1, 2))
        ids = np.array([str(i) for i in s.frames["id"]])
        assert summary.counts.frames_kept == 12 and summary.counts.degraded_by_stage == {"pose": 8}
        assert summary.counts.failures == {"pose": {"FrameError": 8}}
        assert lost.sum() == 8 and all(i.startswith("test/") for i in ids[~lost])
        f = {k: [str(x) for x in v] for k, v in s.failures.items()}
        assert sorted(f["frame_id"]) == sorted(ids[lost])
        assert set(f["stage"]) == {"pose"} and set(f["action"]) == {"degraded"}
        assert all("no person" in m for m in f["message"])
        poses[refine] = dict(zip(ids, s.frames["pose"]))
    for fid in ids[~lost]:
        deep, flat = poses[True][fid], poses[False][fid]
        seen = np.isfinite(flat).all(1)
        assert seen.sum() >= 15 and np.array_equal(seen, np.isfinite(deep).all(1))
        shift = deep[seen] - flat[seen]
        np.testing.assert_allclose(shift, np.tile(shift[0], (seen.sum(), 1)), atol=1e-5)
        assert np.linalg.norm(shift[0]) > 0.3
