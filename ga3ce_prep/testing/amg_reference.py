"""A straightforward implementation of the automatic mask generator in the reference's order of
operations on the official ONNX files: one official-decoder call per grid point (masks upsampled to
full resolution inside the graph), every filter on the full-resolution logits, box NMS. The
candidates are the decoder's (`candidate_tokens`): the multimask outputs 1..3, or a single-mask
export's one mask per point.

It is slow on purpose (it is what `MobileSamSegmenter` is checked against in the tests and timed
against in `make bench-objects`); use MobileSamSegmenter for real work.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..estimators import amg
from ..estimators.mobilesam import ImageEncoder, OfficialDecoder, StepTimer, transform_coords


@dataclass
class ReferenceResult:
    """Kept masks in NMS order: masks (M, H, W) bool; scores, stability (M,); boxes (M, 4) XYXY;
    points (M, 2); candidates: every decoded (point index, token, predicted IoU) row; timings."""

    masks: np.ndarray
    scores: np.ndarray
    stability: np.ndarray
    boxes: np.ndarray
    points: np.ndarray
    candidates: np.ndarray
    timings: dict = field(default_factory=dict)


def reference_generate(encoder: ImageEncoder, decoder: OfficialDecoder, rgb: np.ndarray,
                       options: amg.AmgOptions) -> ReferenceResult:
    """The full-image crop only (crop_n_layers = 0) and no small-region postprocessing: the
    generator's default path."""
    if options.crop_n_layers or options.min_mask_region_area:
        raise ValueError("the reference path covers crop_n_layers = 0 and min_mask_region_area = 0")
    timer = StepTimer()
    h, w = rgb.shape[:2]
    with timer("encoder"):
        emb = encoder.embed(rgb)
    points = amg.build_point_grid(options.points_per_side) * np.array([w, h], np.float64)
    tokens = np.asarray(decoder.candidate_tokens)                # (k,)
    k = tokens.size
    masks, scores, stab, boxes, pts, cands = [], [], [], [], [], []
    for b0 in range(0, len(points), options.points_per_batch):
        batch = points[b0:b0 + options.points_per_batch]
        with timer("decoder"):
            full, iou = [], []
            for p in transform_coords(batch, (h, w)):       # one call per point, as the official export needs
                m, q = decoder(emb, np.array([[p, [0.0, 0.0]]]), np.array([[1.0, -1.0]]), (h, w),
                               outputs=("masks", "iou_predictions"))
                full.append(m[0, tokens])                    # the candidates: tokens 1..3, or the one mask
                iou.append(q[0, tokens])
        with timer("filters"):
            logits = np.concatenate(full)                    # (kB, H, W), point-major
            iou = np.concatenate(iou).astype(np.float32)
            point_of = np.repeat(np.arange(b0, b0 + len(batch)), k)
            cands.append(np.stack([point_of, np.tile(tokens, len(batch)), iou], axis=1))
            keep = iou > np.float32(options.pred_iou_thresh) if options.pred_iou_thresh > 0 \
                else np.ones(len(iou), bool)
            logits, iou, point_of = logits[keep], iou[keep], point_of[keep]
            s = amg.stability_score(logits, options.stability_score_offset)
            keep = s >= np.float32(options.stability_score_thresh) if options.stability_score_thresh > 0 \
                else np.ones(len(s), bool)
            binary = logits[keep] > 0.0
            masks.append(binary)
            scores.append(iou[keep])
            stab.append(s[keep])
            boxes.append(amg.masks_to_boxes(binary))
            pts.append(points[point_of[keep]])
    with timer("nms"):
        masks = np.concatenate(masks) if masks else np.zeros((0, h, w), bool)
        scores, stab = np.concatenate(scores), np.concatenate(stab)
        boxes, pts = np.concatenate(boxes), np.concatenate(pts)
        order = amg.box_nms(boxes, scores, options.box_nms_thresh)
    return ReferenceResult(masks=masks[order], scores=scores[order], stability=stab[order], boxes=boxes[order],
                           points=pts[order], candidates=np.concatenate(cands), timings=dict(timer.seconds))
