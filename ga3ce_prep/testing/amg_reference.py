"""A straightforward port of segment-anything's `SamAutomaticMaskGenerator` order of operations onto
the official ONNX files, full-image crop: the encoder once; per batch of `points_per_batch` grid
points (`_process_batch`), one official-decoder call per point (the exported decoder takes one prompt
per call; it returns the masks upsampled to the image resolution inside the graph, as
`predict_torch(..., return_logits=True)` does), the predicted-IoU filter, the stability score on the
full-resolution logits and its filter, the binary masks' boxes and the crop-edge filter; then box NMS
over the crop's candidates by predicted IoU. The candidates are the decoder's (`candidate_tokens`):
the multimask outputs 1..3, or a single-mask export's one mask per point.

Nothing is restructured: every grid point costs one full decoder call with its full-resolution masks.
The one liberty is memory: a point's candidates that fail the IoU filter are dropped as its call
returns instead of after the batch (the filter is per candidate, so the same candidates pass), so the
batch's 3 x 64 full-resolution masks are never held at once.

It is what `MobileSamSegmenter` is checked against in the tests and timed against in
`make bench-objects`; use MobileSamSegmenter for real work.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..estimators.segment import amg
from ..estimators.segment.amg import StepTimer
from ..estimators.segment.mobilesam_runners import ImageEncoder, OfficialDecoder, single_point_prompts


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
    generator's default path. rgb (H, W, 3) uint8; masks come at (H, W)."""
    if options.crop_n_layers or options.min_mask_region_area:
        raise ValueError("the reference path covers crop_n_layers = 0 and min_mask_region_area = 0")
    timer = StepTimer()
    h, w = rgb.shape[:2]
    crop_box = [0, 0, w, h]
    with timer("encoder"):
        emb = encoder.embed(rgb)
    points = amg.build_point_grid(options.points_per_side) * np.array([w, h], np.float64)   # (n, 2) pixels
    coords = amg.transform_coords(points, (h, w))                                           # (n, 2) 1024 frame
    tokens = np.asarray(decoder.candidate_tokens)                                           # (k,)
    iou_thresh = np.float32(options.pred_iou_thresh)
    batches, cands = [], []
    for b0 in range(0, len(points), options.points_per_batch):
        # the batch's candidates that pass the IoU filter
        logit_parts: list[np.ndarray] = []
        iou_parts: list[np.ndarray] = []
        point_parts: list[np.ndarray] = []
        for i in range(b0, min(b0 + options.points_per_batch, len(points))):
            with timer("decoder"):                         # one call per point: masks (1, M, H, W), IoUs (1, M)
                masks, q = decoder(emb, *single_point_prompts(coords[i:i + 1]), (h, w),
                                   outputs=("masks", "iou_predictions"))
            with timer("filters"):
                q = q[0, tokens].astype(np.float32)
                cands.append(np.stack([np.full(tokens.size, i), tokens, q], axis=1))
                # Filter by predicted IoU
                keep = q > iou_thresh if options.pred_iou_thresh > 0 else np.ones(tokens.size, bool)
                logit_parts.append(masks[0, tokens[keep]])
                iou_parts.append(q[keep])
                point_parts.append(np.full(int(keep.sum()), i))
        with timer("filters"):
            logits, iou, point_of = np.concatenate(logit_parts), np.concatenate(iou_parts), np.concatenate(point_parts)
            # Calculate the stability score, filter by it
            stab = amg.stability_score(logits, options.stability_score_offset)
            keep = stab >= np.float32(options.stability_score_thresh) if options.stability_score_thresh > 0 \
                else np.ones(len(stab), bool)
            # Threshold masks and calculate boxes
            binary = logits[keep] > 0.0
            del logits
            boxes = amg.masks_to_boxes(binary)
            # Filter boxes that touch crop boundaries (none for the full-image crop)
            edge = amg.near_crop_edge(boxes, crop_box, crop_box)
            batches.append((binary[~edge], iou[keep][~edge], stab[keep][~edge], boxes[~edge],
                            points[point_of[keep][~edge]]))
    with timer("nms"):
        masks, scores, stab, boxes, pts = (np.concatenate(col) for col in zip(*batches))
        # Remove duplicates within the crop
        order = amg.box_nms(boxes, scores, options.box_nms_thresh)
    return ReferenceResult(masks=masks[order], scores=scores[order], stability=stab[order], boxes=boxes[order],
                           points=pts[order], candidates=np.concatenate(cands), timings=dict(timer.seconds))
