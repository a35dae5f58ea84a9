"""MediaPipe's single-shot detector heads (BlazeFace, BlazePose's person detector): the anchor
grid, the decoding of the regressors, and the weighted non-maximum suppression.

Conventions (MediaPipe's `SsdAnchorsCalculator` with `fixed_anchor_size`, and
`TensorsToDetectionsCalculator`, reimplemented from their documented behaviour):
- anchors: for each run of layers sharing a stride, a grid of ceil(input / stride) cells per side,
  cells row-major (y, then x), and 2 anchors per layer at each cell centre ((x + 0.5) / grid,
  (y + 0.5) / grid, normalised); every anchor has width = height = 1;
- regressors per anchor: box centre offset (dx, dy) and size (w, h), then keypoints (kx, ky), all
  in input pixels (x before y): centre = anchor + d / input_size, size = (w, h) / input_size;
- scores are logits: sigmoid after clipping to +-clip.
"""
from __future__ import annotations

import itertools

import numpy as np


def ssd_anchors(input_size: int, strides: tuple[int, ...]) -> np.ndarray:
    """Anchor centres (N, 2) float32 (x, y), normalised to [0, 1], in the models' order.

    Consecutive layers with the same stride share one grid with 2 anchors per layer per cell:
    BlazeFace short range (128, (8, 16, 16, 16)) gives 16^2*2 + 8^2*6 = 896."""
    out = []
    for stride, run in itertools.groupby(strides):
        per_cell = 2 * len(list(run))
        grid = int(np.ceil(input_size / stride))
        c = (np.arange(grid, dtype=np.float32) + 0.5) / grid
        yy, xx = np.meshgrid(c, c, indexing="ij")
        cells = np.stack([xx.ravel(), yy.ravel()], axis=1)
        out.append(np.repeat(cells, per_cell, axis=0))
    return np.concatenate(out).astype(np.float32)


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
    """IoU of one box (4,) with boxes (N, 4), all (x1, y1, x2, y2) -> (N,)."""
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    area = np.prod(box[2:] - box[:2])
    areas = np.prod(boxes[:, 2:] - boxes[:, :2], axis=1)
    return inter / np.maximum(area + areas - inter, 1e-12)


def weighted_nms(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray,
                 iou_thresh: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MediaPipe's weighted NMS: take the best remaining detection, average the boxes and keypoints
    of every remaining detection overlapping it by IoU > iou_thresh (weights: their scores), keep
    the best score; repeat. One iteration per output detection.

    boxes (N, 4), keypoints (N, K, 2), scores (N,) -> the same, for the kept clusters, best first."""
    order = np.argsort(-scores, kind="stable")
    boxes, keypoints, scores = boxes[order], keypoints[order], scores[order]
    left = np.ones(len(scores), bool)
    out_b, out_k, out_s = [], [], []
    while left.any():
        i = int(np.flatnonzero(left)[0])
        members = left & (box_iou(boxes[i], boxes) > iou_thresh)
        members[i] = True
        w = scores[members] / scores[members].sum()
        out_b.append(w @ boxes[members])
        out_k.append(np.einsum("n,nkd->kd", w, keypoints[members]))
        out_s.append(scores[i])
        left &= ~members
    K = keypoints.shape[1] if keypoints.ndim == 3 else 0
    if not out_s:
        return np.zeros((0, 4)), np.zeros((0, K, 2)), np.zeros(0)
    return np.stack(out_b), np.stack(out_k), np.asarray(out_s)


__all__ = ["box_iou", "decode_regressors", "sigmoid", "ssd_anchors", "weighted_nms"]
