"""BlazePose GHUM (MediaPipe's pose graph, CPU) through LiteRT: the person detector, the ROI it
defines, the rotated landmark crop, and the landmark decoding into image pixels and metric
world landmarks with camera-aligned axes.

The steps follow MediaPipe's `pose_detection` and `pose_landmark_by_roi` graphs (read, not
copied; the conventions are documented at each function). The building blocks are the face
mesh's: anchors, decoding and NMS in `runtime/ssd.py`, ROIs and crops as 2x3 affines in
`runtime/crops.py`.

1. `detector_input`: the image letterboxed into 224x224 (`crops.letterbox_roi`: aspect kept,
   black bars), RGB in [-1, 1].
2. `ssd.decode_detections`: 2254 SSD anchors (strides 8, 16, 32, 32, 32); box and 4 keypoints
   per anchor, sigmoid scores, weighted NMS on the boxes, back through the letterbox. Keypoint 0
   is the hip centre, keypoint 1 a point on the body axis whose distance to it is the
   body-circle radius, keypoints 2 and 3 the same for the upper body (shoulder centre).
   MediaPipe calls the box the face box; in this model it is a square over the lower face and
   neck, so only NMS uses it.
3. `roi_from_keypoints`: centre = keypoint 0, square side 2.5 x the radius, angle that turns
   the hip-to-keypoint-1 vector upright.
4. `landmark_input`: the ROI to 256x256 RGB in [0, 1] (border pixels repeated); the landmark
   model gives 39 x (x, y, z, visibility, presence) in crop pixels and 39 x 3 world landmarks
   (metres, origin mid-hip, axes of the crop); `decode_landmarks` maps them back through the
   inverse affine and turns the world landmarks by the ROI angle.

Pixel coordinates returned here follow the project's (and OpenCV's) convention: pixel centres
at integer coordinates, the one K uses. Landmark indices: `LANDMARK_NAMES` (33 body landmarks;
the model's 6 extra rows are ROI helpers).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import FrameError
from ...geometry import look_at_rotation, pixel_ray
from ...params import param
from ..runtime.crops import (
    SquareRoi,
    apply_affine,
    continuous_to_index,
    crop,
    invert_affine,
    letterbox_roi,
    roi_affine,
    rotation_2d,
)
from ..runtime.litert import LiteModel, LiteParams, LiteTensor
from ..runtime.ssd import box_iou, decode_detections, sigmoid, ssd_anchors
from .placement import refine_with_depth, solve_translation

LANDMARK_NAMES: tuple[str, ...] = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye", "right_eye_outer",
    "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder", "right_shoulder", "left_elbow",
    "right_elbow", "left_wrist", "right_wrist", "left_pinky", "right_pinky", "left_index", "right_index",
    "left_thumb", "right_thumb", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle",
    "right_ankle", "left_heel", "right_heel", "left_foot_index", "right_foot_index",
)
N_BODY = len(LANDMARK_NAMES)  # 33: the landmarks MediaPipe publishes
N_MODEL = 39                  # rows the landmark model outputs (33 + 6 ROI helpers)
L = {name: i for i, name in enumerate(LANDMARK_NAMES)}  # L["left_shoulder"] == 11
FACE = np.arange(L["mouth_right"] + 1)  # nose, eyes, ears, mouth: points on the skin, not joint centres

DET_SIZE = 224            # detector input side, pixels
DET_STRIDES = (8, 16, 32, 32, 32)  # 2 anchors per layer and cell (ssd.ssd_anchors): 2254
DET_KEYPOINTS = 4         # hip centre, full-body scale point, shoulder centre, upper-body scale point
LMK_SIZE = 256            # landmark model input side, pixels
ROI_SCALE = 1.25          # MediaPipe enlarges the body circle's box by this factor

DETECTOR_INPUTS = [LiteTensor("input_1", (1, DET_SIZE, DET_SIZE, 3))]
DETECTOR_OUTPUTS = [LiteTensor("Identity", (1, 2254, 12)), LiteTensor("Identity_1", (1, 2254, 1))]
LANDMARK_INPUTS = [LiteTensor("input_1", (1, LMK_SIZE, LMK_SIZE, 3))]
LANDMARK_OUTPUTS = [LiteTensor("Identity", (1, N_MODEL * 5)), LiteTensor("Identity_1", (1, 1)),
                    LiteTensor("Identity_4", (1, N_MODEL * 3))]


# --- detector -----------------------------------------------------------------------------------
@dataclass
class Detections:
    """Person detections in image pixels (pixel centres at integers).

    box: (N, 4) x1, y1, x2, y2 of the detector's box (see the module docstring); keypoints:
    (N, 4, 2) x, y (0 hip centre, 1 full-body scale point, 2 shoulder centre, 3 upper-body scale
    point); score: (N,) in [0, 1].
    """

    box: np.ndarray
    keypoints: np.ndarray
    score: np.ndarray

    def __len__(self) -> int:
        return len(self.score)


def detector_input(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) uint8 RGB -> the detector input (1, 224, 224, 3) float32 in [-1, 1], the image
    letterboxed (black bars are -1), and the image->input affine (2, 3)."""
    x, M = crop(rgb, letterbox_roi(rgb.shape[:2]), DET_SIZE)
    return (x.astype(np.float32) * np.float32(2 / 255) - 1)[None], M


def choose_detection(det: Detections, hw: tuple[int, int], body_box: np.ndarray | None = None,
                     head_box: np.ndarray | None = None, min_iou: float = 0.3) -> int:
    """Index of the detection that is the frame's annotated person, in an (H, W) image.

    1. body_box (4,) finite: the detection whose body-circle box (`body_boxes`, clipped to the
       image like an annotation) overlaps it most, if by at least `min_iou` IoU;
    2. head_box (4,) finite: among the detections whose upper-body circle (centre keypoint 2, the
       shoulder centre; radius its distance to keypoint 3) contains the head box centre, the one
       whose shoulder centre is nearest to it (the detector's own box is not used: it is not a
       face box in this model, e.g. 159-262 x 133-236 px on the astronaut, whose face is near
       (224, 115));
    3. else the best score. Raises FrameError when there is no detection.
    """
    if len(det) == 0:
        raise FrameError("no person found by the BlazePose detector")
    if body_box is not None and np.isfinite(body_box).all():
        boxes = np.clip(body_boxes(det), 0, [hw[1] - 1, hw[0] - 1, hw[1] - 1, hw[0] - 1])
        iou = box_iou(np.asarray(body_box, np.float64), boxes)
        if iou.max() >= min_iou:
            return int(np.argmax(iou))
    if head_box is not None and np.isfinite(head_box).all():
        c = 0.5 * (np.asarray(head_box[:2], np.float64) + head_box[2:])
        dist = np.linalg.norm(det.keypoints[:, 2] - c, axis=-1)
        radius = np.linalg.norm(det.keypoints[:, 3] - det.keypoints[:, 2], axis=-1)
        dist[dist > radius] = np.inf
        if np.isfinite(dist).any():
            return int(np.argmin(dist))
    return int(np.argmax(det.score))


def body_boxes(det: Detections) -> np.ndarray:
    """(N, 4) axis-aligned box of each detection's body circle (centre keypoint 0, radius the
    distance to keypoint 1), pixels."""
    c = det.keypoints[:, 0]
    r = np.linalg.norm(det.keypoints[:, 1] - c, axis=-1)[:, None]
    return np.hstack([c - r, c + r])


# --- ROI and crop -------------------------------------------------------------------------------
def roi_from_keypoints(hip: np.ndarray, scale_point: np.ndarray, scale: float = ROI_SCALE) -> SquareRoi:
    """MediaPipe's alignment ROI: centre the hip centre; angle = 90 deg - atan2(-dy, dx) of the
    hip-to-scale-point vector (so that vector points up in the crop), wrapped to [-pi, pi); side
    2 x radius x `scale`."""
    d = np.asarray(scale_point, np.float64) - hip
    theta = np.pi / 2 - np.arctan2(-d[1], d[0])
    theta = (theta + np.pi) % (2 * np.pi) - np.pi
    return SquareRoi(np.asarray(hip, np.float64), float(2 * np.hypot(*d) * scale), float(theta))


def landmark_input(rgb: np.ndarray, roi: SquareRoi) -> tuple[np.ndarray, np.ndarray]:
    """The ROI as the landmark model's input (1, 256, 256, 3) float32 RGB in [0, 1], the image's
    border pixels repeated outside it, and the image->crop affine (2, 3)."""
    x, M = crop(rgb, roi, LMK_SIZE, border="replicate")
    return (x.astype(np.float32) * np.float32(1 / 255))[None], M


# --- landmarks ----------------------------------------------------------------------------------
@dataclass
class PoseLandmarks:
    """One person's BlazePose output (the 33 published landmarks).

    image: (33, 2) pixels (centres at integers); visibility: (33,) in [0, 1], the chance the
    landmark is visible; presence: (33,) in [0, 1], the chance it lies inside the image;
    world: (33, 3) metres, origin mid-hip, axes of the image (x right, y down, z away from the
    camera); score: the landmark model's pose flag in [0, 1]; detection_score: the detector's;
    roi: the crop region.
    """

    image: np.ndarray
    visibility: np.ndarray
    presence: np.ndarray
    world: np.ndarray
    score: float
    detection_score: float
    roi: SquareRoi


def decode_landmarks(raw: np.ndarray, raw_world: np.ndarray, roi: SquareRoi, size: int = LMK_SIZE
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The landmark model's outputs back in the image.

    raw: (39 * 5,) x, y (crop pixels, 0 at the crop's left/top edge), z, visibility and presence
    logits; raw_world: (39 * 3,) metres in the crop's axes. Returns image (33, 2) pixels through
    the inverse crop affine, visibility (33,), presence (33,) (sigmoids), and world (33, 3) metres
    with x, y turned by the ROI angle (z unchanged), i.e. in the image's axes.
    """
    r = np.asarray(raw, np.float64).reshape(N_MODEL, 5)[:N_BODY]
    image = apply_affine(invert_affine(roi_affine(roi, size)), continuous_to_index(r[:, :2]))
    w = np.asarray(raw_world, np.float64).reshape(N_MODEL, 3)[:N_BODY]
    world = np.concatenate([w[:, :2] @ rotation_2d(roi.angle).T, w[:, 2:]], axis=1)
    return image, sigmoid(r[:, 3]), sigmoid(r[:, 4]), world


@dataclass(frozen=True, kw_only=True)
class BlazePoseOptions(LiteParams):
    """How BlazePose runs (the `pose/blazepose` backend's model parameters)."""

    min_detection_score: float = param(
        0.5, minimum=0, maximum=1)  # detector score below which a detection is dropped (MediaPipe's default)
    nms_iou: float = param(
        0.3, minimum=0, maximum=1)  # detector-box IoU above which detections merge (MediaPipe's pose detector)
    weighted_nms: bool = True  # merge clusters by score-weighted mean (MediaPipe) rather than keeping the best
    match_iou: float = param(
        # least IoU between the frame's body box and a detection's body-circle box to pick that detection
        0.3, minimum=0, maximum=1)
    min_pose_score: float = param(
        # landmark model's pose flag below which the frame has no person (MediaPipe's tracking default)
        0.5, minimum=0, maximum=1)


class BlazePoseEstimator:
    """The detector and one landmark model (full or heavy) as LiteRT interpreters.

    `estimator(rgb, body_box, head_box)` -> PoseLandmarks of the chosen person; FrameError when
    no person is found (no detection, or the pose flag below `min_pose_score`).
    """

    def __init__(self, detector: str | Path, landmark: str | Path, options: BlazePoseOptions = BlazePoseOptions()):
        self.o = options
        self.detector = LiteModel(detector, DETECTOR_INPUTS, DETECTOR_OUTPUTS, options.threads, "BlazePose detector")
        self.landmark = LiteModel(landmark, LANDMARK_INPUTS, LANDMARK_OUTPUTS, options.threads, "BlazePose landmark")
        self.anchors = ssd_anchors(DET_SIZE, DET_STRIDES)

    def detect(self, rgb: np.ndarray) -> Detections:
        """All people the detector finds in an (H, W, 3) uint8 RGB image, after NMS, best first."""
        x, M = detector_input(rgb)
        out = self.detector(x)
        o = self.o
        return Detections(*decode_detections(out["Identity"][0], out["Identity_1"][0], self.anchors, DET_SIZE,
                                             DET_KEYPOINTS, invert_affine(M), o.min_detection_score, o.nms_iou,
                                             o.weighted_nms))

    def landmarks(self, rgb: np.ndarray, roi: SquareRoi) -> tuple[PoseLandmarks, float]:
        """Run the landmark model on `roi`; returns the landmarks (detection_score NaN) and the pose flag."""
        out = self.landmark(landmark_input(rgb, roi)[0])
        image, vis, pres, world = decode_landmarks(out["Identity"][0], out["Identity_4"][0], roi)
        score = float(np.ravel(out["Identity_1"])[0])
        return PoseLandmarks(image, vis, pres, world, score, float("nan"), roi), score

    def __call__(self, rgb: np.ndarray, body_box: np.ndarray | None = None,
                 head_box: np.ndarray | None = None) -> PoseLandmarks:
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise FrameError(f"BlazePose needs an (H, W, 3) uint8 RGB image, got {rgb.shape} {rgb.dtype}")
        det = self.detect(rgb)
        i = choose_detection(det, rgb.shape[:2], body_box, head_box, self.o.match_iou)
        roi = roi_from_keypoints(det.keypoints[i, 0], det.keypoints[i, 1])
        lm, score = self.landmarks(rgb, roi)
        if not score >= self.o.min_pose_score:
            raise FrameError(f"no person: BlazePose pose score {score:.2f} < min_pose_score {self.o.min_pose_score}")
        lm.detection_score = float(det.score[i])
        return lm


def place_landmarks(lm: PoseLandmarks, K: np.ndarray, min_visibility: float, ray_alignment: bool = True,
                    depth: np.ndarray | None = None, valid: np.ndarray | None = None,
                    joint_depth_offset: float = 0.05) -> np.ndarray:
    """The 33 landmarks in the camera frame (33, 3), metres (x right, y down, z forward).

    Landmarks with visibility >= `min_visibility` are used, weighted by visibility. The world
    landmarks (image axes, MediaPipe's convention) are first turned so that their z axis is the
    ray through the used landmarks' weighted mean pixel (`ray_alignment`): the model sees a crop,
    i.e. the person as a camera looking along that ray sees them, and cannot know where in the
    frame the crop was. Then T: the 2D fit (`placement.solve_translation`) and, when a depth map
    (H, W) metres at the image's resolution is given, its depth refined from the measured depth
    at those landmarks (`placement.refine_with_depth`; body joints lie `joint_depth_offset`
    metres behind the surface, face landmarks on it); the `pose/blazepose` backend passes the
    depth stage's DepthMap (`depth_refine`).
    """
    w = np.where(lm.visibility >= min_visibility, lm.visibility, 0.0)
    world = lm.world
    if ray_alignment and w.sum() > 0:
        world = world @ look_at_rotation(pixel_ray(np.average(lm.image, axis=0, weights=w), K)).T
    T = solve_translation(world, lm.image, w, K)
    if depth is not None:
        offset = np.full(N_BODY, float(joint_depth_offset))
        offset[FACE] = 0.0
        T, _ = refine_with_depth(world, lm.image, w, K, T, depth, valid, offset)
    return world + T


__all__ = ["BlazePoseEstimator", "BlazePoseOptions", "Detections", "LANDMARK_NAMES", "PoseLandmarks", "body_boxes",
           "choose_detection", "decode_landmarks", "detector_input", "landmark_input", "place_landmarks",
           "roi_from_keypoints"]
