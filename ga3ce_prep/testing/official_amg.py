"""The official generator itself: MobileSAM's `SamAutomaticMaskGenerator` (the `mobile_sam` package,
estimators/segment/mobilesam_code.py) on a checkpoint, on the CPU or a CUDA device, for
`bench_objects.py --device` to time the torch runtime against and compare masks with.

Where torchvision does not load (PyPI's beside torch's CPU build), the four torchvision functions the
generator calls are served by equivalents: `to_pil_image` and `resize` of a uint8 image as Pillow's
bilinear resize (what torchvision does with a PIL image), `box_area`, and `batched_nms` by the greedy
NMS of `amg.box_nms` (torchvision.ops.nms's order and ties) per category. Where it loads, it is used.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..estimators.segment import amg
from ..estimators.segment.mobilesam_code import import_mobile_sam, torchvision_loads


@dataclass
class OfficialResult:
    """The generator's masks in its output order: masks (M, H, W) bool, scores (M,) predicted IoU,
    stability (M,), boxes (M, 4) int64 XYXY inclusive, points (M, 2) prompt pixels."""

    masks: np.ndarray
    scores: np.ndarray
    stability: np.ndarray
    boxes: np.ndarray
    points: np.ndarray


def _stand_in_torchvision() -> None:
    """Point the generator's torchvision names at the equivalents (module docstring)."""
    import importlib

    import torch
    from PIL import Image

    def batched_nms(boxes, scores, idxs, iou_threshold):
        b, s, c = (t.detach().cpu().numpy() for t in (boxes, scores, idxs))
        keep = [np.flatnonzero(c == k)[amg.box_nms(b[c == k], s[c == k], iou_threshold)] for k in np.unique(c)]
        keep = np.concatenate(keep) if keep else np.zeros(0, np.int64)
        keep = keep[np.argsort(-s[keep], kind="stable")]            # torchvision: by decreasing score
        return torch.as_tensor(keep, dtype=torch.int64, device=boxes.device)

    def box_area(boxes):
        return (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])

    # MobileSAM's modules (no type information), whose torchvision helpers are replaced
    generator: Any = importlib.import_module("mobile_sam.automatic_mask_generator")
    transforms: Any = importlib.import_module("mobile_sam.utils.transforms")
    generator.batched_nms, generator.box_area = batched_nms, box_area
    transforms.to_pil_image = Image.fromarray
    transforms.resize = lambda image, size: image.resize((size[1], size[0]), Image.Resampling.BILINEAR)


def official_generator(sam, options: amg.AmgOptions):
    """segment-anything's generator on the Sam module `sam` (mobilesam_torch.load_sam), with
    `options` (binary masks out)."""
    mobile_sam = import_mobile_sam()
    if not torchvision_loads():
        _stand_in_torchvision()
    o = options
    return mobile_sam.SamAutomaticMaskGenerator(
        sam, points_per_side=o.points_per_side, points_per_batch=o.points_per_batch, pred_iou_thresh=o.pred_iou_thresh,
        stability_score_thresh=o.stability_score_thresh, stability_score_offset=o.stability_score_offset,
        box_nms_thresh=o.box_nms_thresh, crop_n_layers=o.crop_n_layers, crop_nms_thresh=o.crop_nms_thresh,
        crop_overlap_ratio=o.crop_overlap_ratio, crop_n_points_downscale_factor=o.crop_n_points_downscale_factor,
        min_mask_region_area=o.min_mask_region_area, output_mode="binary_mask")


def official_generate(generator, rgb: np.ndarray) -> OfficialResult:
    """Run the generator on an (H, W, 3) uint8 RGB image."""
    import torch

    with torch.inference_mode():
        out = generator.generate(rgb)
    h, w = rgb.shape[:2]
    xywh = np.array([r["bbox"] for r in out], np.int64).reshape(-1, 4)
    return OfficialResult(
        masks=np.array([r["segmentation"] for r in out], bool).reshape(-1, h, w),
        scores=np.array([r["predicted_iou"] for r in out], np.float32),
        stability=np.array([r["stability_score"] for r in out], np.float32),
        boxes=np.concatenate([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]], axis=1),
        points=np.array([r["point_coords"][0] for r in out], np.float64).reshape(-1, 2))
