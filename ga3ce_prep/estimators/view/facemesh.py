"""Head direction from MediaPipe's face mesh: BlazeFace short-range in the head box, the face ROI
rotated by the eye line, the 468-landmark mesh, and the facing direction in the camera frame.

This is a HEAD direction (where the face points), not an eye-gaze estimate: the registry has no
shippable learned 3D gaze model (docs/models/view.md, "Face mesh head direction"), so it stands in
for the paper's appearance network as the view prior v.

Steps (`FaceMeshEstimator.estimate`), all coordinates in image pixel-index coordinates
(estimators/runtime/crops.py):
1. the square around the head box, `box_scale` x its longer side, cropped (zeros outside the
   image) to BlazeFace's 128 x 128 input in [-1, 1];
2. 896 anchors (strides 8, 16, 16, 16), 16 regressors each (box + 6 keypoints: right eye, left
   eye, nose tip, mouth centre, right ear, left ear; "right" is the subject's), sigmoid scores,
   weighted NMS; the best detection;
3. the face ROI: the detection box's centre, side `roi_scale` x its longer side, rotated so that
   its x axis runs from the right eye to the left eye; cropped to 192 x 192 in [0, 1];
4. the mesh: 468 x (x, y, z) in crop pixels (z: relative depth, same scale as x, negative toward
   the camera) and the face flag (sigmoid); back to the image through the inverse affine (z times
   the crop's pixel size);
5. facing = normalize(cross(lm263 - lm33, lm10 - lm152)) (left minus right outer eye corner,
   forehead minus chin) in the image axes (x right, y down, z away from the camera): a frontal
   face gives (0, 0, -1). The mesh is an orthographic view along the ray through the face, so
   the direction is rotated by the look-at rotation from the optical axis to the ray through the
   face centre (the landmarks' mean pixel) with K (`geometry.look_at_rotation`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import FrameError
from ...frames import check_rgb
from ...geometry import look_at_rotation, normalize, pixel_ray
from ...params import param
from ..runtime.crops import SquareRoi, apply_affine, box_roi, continuous_to_index, crop, invert_affine
from ..runtime.litert import LiteModel, LiteParams, LiteTensor
from ..runtime.ssd import decode_detections, sigmoid, ssd_anchors

DETECTOR_SIZE = 128
DETECTOR_STRIDES = (8, 16, 16, 16)
N_KEYPOINTS = 6
RIGHT_EYE, LEFT_EYE = 0, 1  # BlazeFace keypoints (the subject's right and left)
MESH_SIZE = 192
N_LANDMARKS = 468
# face mesh landmarks of the direction formula
LM_RIGHT_EYE_OUTER, LM_LEFT_EYE_OUTER, LM_FOREHEAD, LM_CHIN = 33, 263, 10, 152

DETECTOR_INPUTS = [LiteTensor("input", (1, DETECTOR_SIZE, DETECTOR_SIZE, 3))]
DETECTOR_OUTPUTS = [LiteTensor("regressors", (1, 896, 4 + 2 * N_KEYPOINTS)), LiteTensor("classificators", (1, 896, 1))]
MESH_INPUTS = [LiteTensor("input_1", (1, MESH_SIZE, MESH_SIZE, 3))]
MESH_OUTPUTS = [LiteTensor("conv2d_21", (1, 1, 1, 3 * N_LANDMARKS)), LiteTensor("conv2d_31", (1, 1, 1, 1))]


@dataclass(frozen=True, kw_only=True)
class FaceMeshOptions(LiteParams):
    """Everything `FaceMeshEstimator` is configured with besides its two files."""

    box_scale: float = param(
        # detector crop side / the head box's longer side; BlazeFace short-range expects the
        # face to fill a fair part of its input, and 2 leaves room for a loose or offset box
        2.0, exclusiveMinimum=0)
    min_detection_score: float = param(
        0.5, minimum=0, maximum=1)  # BlazeFace score (sigmoid) below which there is no face; MediaPipe's default
    nms_iou: float = param(
        0.3, minimum=0, maximum=1)  # IoU above which detections merge in the weighted NMS; MediaPipe's default
    roi_scale: float = param(
        # face-mesh crop side / the detection box's longer side; MediaPipe's 1.5, the mesh was trained on it
        1.5, exclusiveMinimum=0)
    min_face_score: float = param(
        # face-mesh face flag (sigmoid) below which the crop holds no face; MediaPipe's default
        0.5, minimum=0, maximum=1)


@dataclass(frozen=True)
class FaceDetection:
    """One BlazeFace detection in image pixels: box (4,) x1, y1, x2, y2; keypoints (6, 2) x, y
    (right eye, left eye, nose tip, mouth centre, right ear, left ear); score in [0, 1]."""

    box: np.ndarray
    keypoints: np.ndarray
    score: float


@dataclass(frozen=True)
class FaceMeshResult:
    """One face's head direction.

    direction: (3,) float64 unit, camera frame (x right, y down, z forward), where the face points
    (toward the camera: z < 0). landmarks: (468, 3) float32 image pixels (x, y) and relative depth
    z in the same pixel units (negative toward the camera). face_score: the mesh's face flag in
    [0, 1]. detection: the BlazeFace detection. roi: the face crop the mesh read."""

    direction: np.ndarray
    landmarks: np.ndarray
    face_score: float
    detection: FaceDetection
    roi: SquareRoi


def blazeface_anchors() -> np.ndarray:
    """BlazeFace short-range's 896 anchor centres (896, 2), normalised."""
    return ssd_anchors(DETECTOR_SIZE, DETECTOR_STRIDES)


def face_roi(det: FaceDetection, roi_scale: float) -> SquareRoi:
    """The face mesh's crop: the detection box's centre, side roi_scale x its longer side, rotated
    by the eye line (right eye to left eye) so the face is upright in the crop."""
    roi = box_roi(det.box, roi_scale)
    d = det.keypoints[LEFT_EYE] - det.keypoints[RIGHT_EYE]
    return SquareRoi(roi.center, roi.size, float(np.arctan2(d[1], d[0])))


def facing_direction(landmarks: np.ndarray) -> np.ndarray:
    """normalize(cross(lm263 - lm33, lm10 - lm152)) of (468, 3) landmarks -> (3,) float64 unit, in
    the landmarks' axes (x right, y down, z away from the viewer: a frontal face gives (0, 0, -1))."""
    p = np.asarray(landmarks, np.float64)
    across = p[LM_LEFT_EYE_OUTER] - p[LM_RIGHT_EYE_OUTER]
    up = p[LM_FOREHEAD] - p[LM_CHIN]
    return normalize(np.cross(across, up))


def head_direction(landmarks: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The camera-frame head direction (3,) float64 unit from image-pixel landmarks (468, 3):
    `facing_direction` (relative to the viewing ray) turned by the look-at rotation from the
    optical axis to the ray through the landmarks' mean pixel."""
    ray = pixel_ray(np.asarray(landmarks, np.float64)[:, :2].mean(axis=0), K)
    return look_at_rotation(ray) @ facing_direction(landmarks)


class FaceMeshEstimator:
    """BlazeFace + face mesh on two TFLite files (LiteRT), and the head direction.

    detector, mesh: the `face_detection_short_range.tflite` and `face_landmark.tflite` paths
    (weights/registry.py keys "face_detection", "face_landmark"); both are checked against the
    contracts above on load (ModelFileError on a mismatch)."""

    def __init__(self, detector: str | Path, mesh: str | Path, options: FaceMeshOptions = FaceMeshOptions()):
        self.options = options
        self.detector = LiteModel(detector, DETECTOR_INPUTS, DETECTOR_OUTPUTS, options.threads, "BlazeFace")
        self.mesh = LiteModel(mesh, MESH_INPUTS, MESH_OUTPUTS, options.threads, "face mesh")
        self.anchors = blazeface_anchors()

    def detect(self, rgb: np.ndarray, head_box: np.ndarray) -> list[FaceDetection]:
        """Faces in the square around the head box, best first (empty: none above
        min_detection_score). rgb: (H, W, 3) uint8; head_box (4,) x1, y1, x2, y2 pixels."""
        o = self.options
        tensor, M = crop(check_rgb(rgb), box_roi(head_box, o.box_scale), DETECTOR_SIZE)
        out = self.detector(tensor[None].astype(np.float32) / 127.5 - 1.0)
        boxes, kps, scores = decode_detections(out["regressors"][0], out["classificators"][0], self.anchors,
                                               DETECTOR_SIZE, N_KEYPOINTS, invert_affine(M), o.min_detection_score,
                                               o.nms_iou)
        return [FaceDetection(boxes[i], kps[i], float(scores[i])) for i in range(len(scores))]

    def landmarks(self, rgb: np.ndarray, roi: SquareRoi) -> tuple[np.ndarray, float]:
        """The mesh in `roi`: landmarks (468, 3) float32 image pixels (x, y, z as in
        FaceMeshResult) and the face flag in [0, 1]."""
        tensor, M = crop(check_rgb(rgb), roi, MESH_SIZE)
        out = self.mesh(tensor[None].astype(np.float32) / 255.0)
        lm = out["conv2d_21"].reshape(N_LANDMARKS, 3).astype(np.float64)
        xy = apply_affine(invert_affine(M), continuous_to_index(lm[:, :2]))
        z = lm[:, 2] * (roi.size / MESH_SIZE)
        return np.column_stack([xy, z]).astype(np.float32), float(sigmoid(out["conv2d_31"].ravel()[0]))

    def estimate(self, rgb: np.ndarray, head_box: np.ndarray, K: np.ndarray) -> FaceMeshResult:
        """The head direction of the face in the head box. FrameError when there is no face
        (nothing detected above min_detection_score, or the face flag below min_face_score: a
        subject facing away, an occluded or tiny face)."""
        o = self.options
        dets = self.detect(rgb, head_box)
        if not dets:
            raise FrameError(f"no face detected in the head box {np.round(np.asarray(head_box, float), 1).tolist()} "
                             f"(BlazeFace score < {o.min_detection_score}): the subject may face away")
        roi = face_roi(dets[0], o.roi_scale)
        lm, flag = self.landmarks(rgb, roi)
        if flag < o.min_face_score:
            raise FrameError(f"the face mesh sees no face in the detected box (face flag {flag:.2f} < "
                             f"{o.min_face_score}): the subject may face away")
        return FaceMeshResult(head_direction(lm, K), lm, flag, dets[0], roi)


__all__ = ["FaceDetection", "FaceMeshEstimator", "FaceMeshOptions", "FaceMeshResult", "blazeface_anchors",
           "face_roi", "facing_direction", "head_direction"]
