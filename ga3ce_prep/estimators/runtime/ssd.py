"""MediaPipe's single-shot detector heads (BlazeFace, BlazePose's person detector): the anchor
grid, the decoding of the regressors, and the weighted non-maximum suppression.

Conventions (MediaPipe's `SsdAnchorsCalculator` with `fixed_anchor_size`, and
`TensorsToDetectionsCalculator`, reimplemented from their documented behaviour):
- anchors: for each run of layers sharing a stride, a grid of ceil(input / stride) cells per side,
  cells row-major (y, then x), and 2 anchors per layer at each cell centre ((x + 0.5) / grid,
  (y + 0.5) / grid, normalised); every anchor has width = height = 1;
- regressors per anchor: box centre offset (dx, dy) and size (w, h), then keypoints (kx, ky), all
  in input pixels (x before y): centre = anchor + d / input_size, size = (w, h) / input_size;
- scores are logits: sigmoid after clipping to +-clip;
- weighted non-maximum suppression in the input's normalised coordinates, then the detections go
  back to the image through the inverse of the affine that made the input (`crops.py`).
"""
from __future__ import annotations

import itertools

import numpy as np

from .crops import apply_affine, continuous_to_index


def ssd_anchors(input_size: int, strides: tuple[int, ...]) -> np.ndarray:
    """Anchor centres (N, 2) float64 (x, y), normalised to [0, 1], in the models' order.

    Consecutive layers with the same stride share one grid with 2 anchors per layer per cell:
    BlazeFace short range (128, (8, 16, 16, 16)) gives 16^2*2 + 8^2*6 = 896, BlazePose's person
    detector (224, (8, 16, 32, 32, 32)) 28^2*2 + 14^2*2 + 7^2*6 = 2254."""
    out = []
    for stride, run in itertools.groupby(strides):
        per_cell = 2 * len(list(run))
        grid = int(np.ceil(input_size / stride))
        c = (np.arange(grid) + 0.5) / grid
        yy, xx = np.meshgrid(c, c, indexing="ij")
        cells = np.stack([xx.ravel(), yy.ravel()], axis=1)
        out.append(np.repeat(cells, per_cell, axis=0))
    return np.concatenate(out)


def decode_regressors(raw: np.ndarray, anchors: np.ndarray, input_size: int,
                      n_keypoints: int) -> tuple[np.ndarray, np.ndarray]:
    """Decode (N, 4 + 2K) regressors against (N, 2) anchors.

    Returns boxes (N, 4) (x1, y1, x2, y2) and keypoints (N, K, 2) (x, y), both normalised to the
    input's [0, 1] continuous coordinates (0 = the first pixel's left edge)."""
    raw = np.asarray(raw, np.float64)
    a = np.asarray(anchors, np.float64)
    centre = a + raw[:, 0:2] / input_size
    half = 0.5 * raw[:, 2:4] / input_size
    boxes = np.concatenate([centre - half, centre + half], axis=1)
    kp = raw[:, 4:4 + 2 * n_keypoints].reshape(-1, n_keypoints, 2) / input_size + a[:, None, :]
    return boxes, kp


def sigmoid(logits: np.ndarray, clip: float = 100.0) -> np.ndarray:
    """Logistic function of logits clipped to [-clip, clip] (MediaPipe's score clipping)."""
    return 1.0 / (1.0 + np.exp(-np.clip(np.asarray(logits, np.float64), -clip, clip)))


def box_iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU of one box (4,) with boxes (N, 4), all (x1, y1, x2, y2) -> (N,); a box with x2 < x1 or
    y2 < y1 has no area, and no overlap gives 0."""
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    area = np.prod(np.clip(box[2:] - box[:2], 0, None))
    areas = np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 0, None), axis=1)
    return inter / np.maximum(area + areas - inter, 1e-12)


def weighted_nms(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray, iou_thresh: float,
                 weighted: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MediaPipe's non-maximum suppression: take the best remaining detection and every remaining
    one overlapping it by IoU > iou_thresh; weighted, the cluster's box and keypoints are their
    score-weighted mean, else the best one's; its score is the best one's; repeat. One iteration
    per output detection.

    boxes (N, 4), keypoints (N, K, 2), scores (N,) -> the same, for the kept clusters, best first."""
    order = np.argsort(-scores, kind="stable")
    boxes, keypoints, scores = boxes[order], keypoints[order], scores[order]
    left = np.ones(len(scores), bool)
    out_b, out_k, out_s = [], [], []
    while left.any():
        i = int(np.flatnonzero(left)[0])
        members = left & (box_iou(boxes[i], boxes) > iou_thresh)
        members[i] = True
        if weighted:
            w = scores[members] / scores[members].sum()
            out_b.append(w @ boxes[members])
            out_k.append(np.einsum("n,nkd->kd", w, keypoints[members]))
        else:
            out_b.append(boxes[i])
            out_k.append(keypoints[i])
        out_s.append(scores[i])
        left &= ~members
    K = keypoints.shape[1] if keypoints.ndim == 3 else 0
    if not out_s:
        return np.zeros((0, 4)), np.zeros((0, K, 2)), np.zeros(0)
    return np.stack(out_b), np.stack(out_k), np.asarray(out_s)


def decode_detections(raw: np.ndarray, logits: np.ndarray, anchors: np.ndarray, input_size: int,
                      n_keypoints: int, to_image: np.ndarray, min_score: float, iou_thresh: float,
                      weighted: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A detector head's outputs -> its detections in image pixels, best first.

    raw: (N, 4 + 2K) regressors, logits: (N,) or (N, 1) score logits, anchors: (N, 2) normalised;
    to_image: (2, 3) affine from the input's pixels to the image's (the inverse of the crop's,
    `crops.invert_affine`), both index coordinates. Scores below `min_score` are dropped, the rest
    decoded (`decode_regressors`) and merged (`weighted_nms`), then mapped back. The input must be
    an upright crop (a scale and a shift) for the boxes to stay axis-aligned.
    Returns boxes (M, 4) x1, y1, x2, y2 and keypoints (M, K, 2) x, y, image pixels; scores (M,)."""
    scores = sigmoid(np.reshape(logits, -1))
    keep = scores >= min_score
    boxes, kps = decode_regressors(np.asarray(raw)[keep], np.asarray(anchors)[keep], input_size, n_keypoints)
    boxes, kps, scores = weighted_nms(boxes, kps, scores[keep], iou_thresh, weighted)
    boxes = apply_affine(to_image, continuous_to_index(boxes.reshape(-1, 2, 2) * input_size)).reshape(-1, 4)
    return boxes, apply_affine(to_image, continuous_to_index(kps * input_size)), scores


__all__ = ["box_iou", "decode_detections", "decode_regressors", "sigmoid", "ssd_anchors", "weighted_nms"]
