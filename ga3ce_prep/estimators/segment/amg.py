"""The automatic mask generator's ("segment everything") grid, crops and filters, on numpy and OpenCV.

The same algorithm as segment-anything's `SamAutomaticMaskGenerator` and `utils/amg.py` (identical in
MobileSAM): per crop, a grid of single-point prompts; keep the multimask outputs whose predicted IoU
exceeds `pred_iou_thresh`, whose stability score (IoU of the mask thresholded at +offset and at
-offset) reaches `stability_score_thresh`, and whose box is not cut by an inner crop edge; greedy box
NMS within the crop, then across crops; optionally remove small holes and islands. Boxes are XYXY in
pixels with inclusive maxima (x2 = last column of the mask), as the reference computes them. The
candidates flow through these steps as one columnar `MaskRecords` (the reference's `MaskData`).
"""
from __future__ import annotations

import math
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields

import cv2
import numpy as np

from ...errors import ConfigError
from ...params import param


@dataclass(frozen=True, kw_only=True)
class AmgOptions:
    """segment-anything's generator options, with its defaults (the MobileSAM app uses them all)."""

    points_per_side: int = param(32, minimum=1)  # grid of single-point prompts per side (32 = 1024 prompts)
    points_per_batch: int = param(
        # prompts per official-decoder call (decoder_mode official); the
        # fast decoder batches its own way; results do not depend on it
        64, minimum=1)
    pred_iou_thresh: float = 0.88  # keep masks whose predicted IoU exceeds this (0 = no filter)
    stability_score_thresh: float = 0.95  # keep masks whose stability score reaches this (0 = no filter)
    stability_score_offset: float = 1.0  # logit offset of the stability score
    box_nms_thresh: float = param(0.7, minimum=0, maximum=1)  # box IoU above which the lower-scored mask is dropped
    crop_n_layers: int = param(0, minimum=0)  # extra layers of image crops (0 = the whole image only)
    crop_nms_thresh: float = param(0.7, minimum=0, maximum=1)  # box NMS threshold across crops
    crop_overlap_ratio: float = 512 / 1500  # crop overlap as a fraction of the short side
    crop_n_points_downscale_factor: int = param(1, minimum=1)  # points per side divided by this per crop layer
    min_mask_region_area: int = param(
        0, minimum=0)  # fill holes and drop islands smaller than this many pixels (0 = off)

    def __post_init__(self):
        if self.points_per_side < 1 or self.points_per_batch < 1:
            raise ConfigError("points_per_side and points_per_batch must be >= 1")
        if self.crop_n_layers < 0 or self.crop_n_points_downscale_factor < 1:
            raise ConfigError("crop_n_layers must be >= 0 and crop_n_points_downscale_factor >= 1")
        for name in ("box_nms_thresh", "crop_nms_thresh"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        if self.min_mask_region_area < 0:
            raise ConfigError("min_mask_region_area must be >= 0")

    def to_dict(self) -> dict:
        return asdict(self)

    def iou_passes(self, iou: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(n,) bool: predicted IoUs (n,) float32 above pred_iou_thresh - margin (all with the filter off)."""
        if self.pred_iou_thresh <= 0:
            return np.ones(np.shape(iou), bool)
        return iou > np.float32(self.pred_iou_thresh - margin)

    def stability_passes(self, stability: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(n,) bool: stability scores (n,) float32 at least stability_score_thresh - margin (all with
        the filter off)."""
        if self.stability_score_thresh <= 0:
            return np.ones(np.shape(stability), bool)
        return stability >= np.float32(self.stability_score_thresh - margin)


LOW_RES = 256  # side of the decoder's low-resolution mask logits
# Candidates of one prompt in the generator: the multimask outputs (tokens 1..3), or a single-mask
# export's one output
MULTIMASK_TOKENS: tuple[int, ...] = (1, 2, 3)
SINGLE_MASK_TOKENS: tuple[int, ...] = (0,)


@dataclass(frozen=True)
class MaskRecords:
    """Candidate masks, one row each: the reference's `MaskData` with typed columns. Each filter is
    `records.filter(keep)`; batches and crops are gathered with `cat`."""

    iou: np.ndarray  # (n,) float32 predicted IoU
    stability: np.ndarray  # (n,) float32 stability score
    box: np.ndarray  # (n, 4) int64 XYXY, inclusive maxima
    point: np.ndarray  # (n, 2) float64 prompt pixel (x, y)
    low_res: np.ndarray  # (n, 256, 256) float32 low-resolution logits
    crop_index: np.ndarray  # (n,) int64 crop the mask was decoded in
    prompt: np.ndarray  # (n,) int64 index of the mask's prompt in its crop's point grid

    @classmethod
    def empty(cls) -> MaskRecords:
        return cls(iou=np.zeros(0, np.float32), stability=np.zeros(0, np.float32), box=np.zeros((0, 4), np.int64),
                   point=np.zeros((0, 2)), low_res=np.zeros((0, LOW_RES, LOW_RES), np.float32),
                   crop_index=np.zeros(0, np.int64), prompt=np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.iou)

    def filter(self, keep: np.ndarray | slice) -> MaskRecords:
        """The rows `keep`: a bool mask, indices (in the order given) or a slice."""
        return MaskRecords(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})

    def cat(self, *others: MaskRecords) -> MaskRecords:
        """These rows, then those of each of `others`."""
        parts = (self, *others)
        return MaskRecords(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(self)})


def build_point_grid(n_per_side: int) -> np.ndarray:
    """(n*n, 2) cell centres of an n x n grid over [0, 1]^2 as (x, y), x varying fastest."""
    offset = 1.0 / (2 * n_per_side)
    side = np.linspace(offset, 1 - offset, n_per_side)
    xs = np.tile(side[None, :], (n_per_side, 1))
    ys = np.tile(side[:, None], (1, n_per_side))
    return np.stack([xs, ys], axis=-1).reshape(-1, 2)


def crop_boxes(im_size: tuple[int, int], n_layers: int, overlap_ratio: float) -> tuple[list[list[int]], list[int]]:
    """Crop boxes XYXY (pixels) and their layer: layer 0 is the whole image, layer i has (2^i)^2
    overlapping crops, listed x0-major as the reference does (the order decides NMS ties).
    im_size = (H, W)."""
    im_h, im_w = im_size
    short = min(im_h, im_w)
    boxes, layers = [[0, 0, im_w, im_h]], [0]
    for i in range(n_layers):
        n = 2 ** (i + 1)
        overlap = int(overlap_ratio * short * (2 / n))
        w = int(math.ceil((overlap * (n - 1) + im_w) / n))
        h = int(math.ceil((overlap * (n - 1) + im_h) / n))
        for x0 in (int((w - overlap) * k) for k in range(n)):
            for y0 in (int((h - overlap) * k) for k in range(n)):
                boxes.append([x0, y0, min(x0 + w, im_w), min(y0 + h, im_h)])
                layers.append(i + 1)
    return boxes, layers


def layer_point_grids(n_per_side: int, n_layers: int, downscale: int) -> list[np.ndarray]:
    """The point grid of each crop layer: layer i has int(n / downscale**i) points per side."""
    return [build_point_grid(int(n_per_side / downscale ** i)) for i in range(n_layers + 1)]


def stability_score(logits: np.ndarray, offset: float, threshold: float = 0.0) -> np.ndarray:
    """IoU of the masks logits > threshold + offset and logits > threshold - offset, per mask.

    logits (n, H, W) float. An empty union gives NaN (which fails any threshold, as in the reference).
    """
    n = logits.shape[0]
    flat = logits.reshape(n, -1)
    inter = np.count_nonzero(flat > threshold + offset, axis=1)
    union = np.count_nonzero(flat > threshold - offset, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):  # float32, as the reference divides
        return inter.astype(np.float32) / union.astype(np.float32)


def masks_to_boxes(masks: np.ndarray) -> np.ndarray:
    """(n, H, W) bool -> (n, 4) int64 XYXY with inclusive maxima; an empty mask gives [0, 0, 0, 0]."""
    n = masks.shape[0]
    if n == 0:
        return np.zeros((0, 4), np.int64)
    cols = np.asarray(masks.any(axis=1))          # (n, W)
    rows = np.asarray(masks.any(axis=2))          # (n, H)
    W, H = cols.shape[1], rows.shape[1]
    has = cols.any(axis=1)
    x1 = np.argmax(cols, axis=1)
    x2 = W - 1 - np.argmax(cols[:, ::-1], axis=1)
    y1 = np.argmax(rows, axis=1)
    y2 = H - 1 - np.argmax(rows[:, ::-1], axis=1)
    boxes = np.stack([x1, y1, x2, y2], axis=1).astype(np.int64)
    boxes[~has] = 0
    return boxes


def box_area(boxes: np.ndarray) -> np.ndarray:
    return (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])


def box_nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy NMS as torchvision.ops.nms: visit boxes by decreasing score (ties in input order), drop
    every later box whose IoU with a kept one exceeds `iou_threshold`. IoU uses (x2-x1)*(y2-y1) areas.
    Returns the kept indices in visiting order."""
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    b = boxes.astype(np.float64)
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    area = box_area(b)
    suppressed = np.zeros(len(b), bool)
    keep = []
    for pos, i in enumerate(order):
        if suppressed[i]:
            continue
        keep.append(i)
        rest = order[pos + 1:]
        rest = rest[~suppressed[rest]]
        if rest.size == 0:
            break
        iw = np.clip(np.minimum(b[i, 2], b[rest, 2]) - np.maximum(b[i, 0], b[rest, 0]), 0, None)
        ih = np.clip(np.minimum(b[i, 3], b[rest, 3]) - np.maximum(b[i, 1], b[rest, 1]), 0, None)
        inter = iw * ih
        with np.errstate(invalid="ignore", divide="ignore"):
            iou = inter / (area[i] + area[rest] - inter)
        suppressed[rest[iou > iou_threshold]] = True
    return np.asarray(keep, np.int64)


def near_crop_edge(boxes: np.ndarray, crop_box: list[int], orig_box: list[int], atol: float = 20.0) -> np.ndarray:
    """Boxes (n, 4) in crop coordinates within `atol` px of a crop edge that is not an image edge."""
    crop = np.asarray(crop_box, np.float64)
    orig = np.asarray(orig_box, np.float64)
    b = boxes.astype(np.float64) + np.array([crop[0], crop[1], crop[0], crop[1]])
    near_crop = np.isclose(b, crop[None, :], atol=atol, rtol=0)
    near_image = np.isclose(b, orig[None, :], atol=atol, rtol=0)
    return np.any(near_crop & ~near_image, axis=1)


def remove_small_regions(mask: np.ndarray, area_thresh: float, mode: str) -> tuple[np.ndarray, bool]:
    """Fill holes ("holes") or drop islands ("islands") smaller than area_thresh (8-connectivity).
    Returns the new mask and whether it changed."""
    if mode not in ("holes", "islands"):
        raise ValueError(f"mode must be 'holes' or 'islands', got {mode!r}")
    correct_holes = mode == "holes"
    working = (correct_holes ^ mask).astype(np.uint8)
    _, regions, stats, _ = cv2.connectedComponentsWithStats(working, connectivity=8)
    sizes = stats[1:, cv2.CC_STAT_AREA]                    # label 0 is the background
    small = sizes < area_thresh
    if not small.any():
        return mask, False
    if correct_holes:   # the new mask: background label 0 plus the small components of the inverse
        keep_label = np.concatenate([[True], small])
    else:               # the large islands; the largest one if all are small
        keep_label = np.concatenate([[False], ~small])
        if not keep_label.any():
            keep_label[int(np.argmax(sizes)) + 1] = True
    return keep_label[regions], True


# ---------------------------------------------------------------------------------------------
# Low-resolution logits -> original resolution, as the decoder's postprocessing does it
# ---------------------------------------------------------------------------------------------
def preprocess_shape(h: int, w: int, long_side: int = 1024) -> tuple[int, int]:
    """(newh, neww) of ResizeLongestSide: scale the longest side to `long_side`, round half up."""
    scale = long_side / max(h, w)
    return int(h * scale + 0.5), int(w * scale + 0.5)


def transform_coords(points: np.ndarray, orig_hw: tuple[int, int]) -> np.ndarray:
    """(..., 2) pixel (x, y) in the original image -> the 1024 input frame (ResizeLongestSide.apply_coords)."""
    h, w = orig_hw
    newh, neww = preprocess_shape(h, w)
    out = np.array(points, dtype=np.float64, copy=True)
    out[..., 0] *= neww / w
    out[..., 1] *= newh / h
    return out


def upscale_logits(low_res: np.ndarray, orig_hw: tuple[int, int], out_hw: tuple[int, int] | None = None,
                   img_size: int = 1024) -> np.ndarray:
    """The decoder's mask postprocessing on (n, 256, 256) logits: bilinear (half-pixel, no
    antialiasing) to img_size x img_size, crop to the resized image (newh, neww) of `orig_hw`, bilinear
    to `out_hw` (default orig_hw). Returns (n, out_h, out_w) float32 logits. OpenCV's bilinear weights
    are float32: within 1e-4 of torch's F.interpolate.

    With out_hw smaller than orig_hw this is the decoder's `orig_im_size` trick: the masks come
    directly at the depth map's resolution."""
    newh, neww = preprocess_shape(*orig_hw, img_size)
    out_h, out_w = out_hw or orig_hw
    n_low = low_res.shape[-1]
    f = img_size // n_low                                   # 4
    # upsample only the low-res rows/columns the crop reads (+1 for the interpolation's second tap):
    # same scale, same coordinates, so the same values inside the crop
    rh, rw = min(n_low, -(-newh // f) + 1), min(n_low, -(-neww // f) + 1)
    out = np.empty((low_res.shape[0], out_h, out_w), np.float32)
    for i, m in enumerate(low_res):
        part = np.ascontiguousarray(m[:rh, :rw], np.float32)
        up = cv2.resize(part, (rw * f, rh * f), interpolation=cv2.INTER_LINEAR)
        out[i] = cv2.resize(up[:newh, :neww], (out_w, out_h), interpolation=cv2.INTER_LINEAR)
    return out


@dataclass(frozen=True)
class Crop:
    """One crop of the generator (`crop_boxes`): its index, box XYXY in image pixels, layer, and the
    image's (h, w)."""

    index: int
    box: tuple[int, int, int, int]
    layer: int
    image_hw: tuple[int, int]

    @property
    def hw(self) -> tuple[int, int]:
        return self.box[3] - self.box[1], self.box[2] - self.box[0]

    def output_box(self, out_hw: tuple[int, int]) -> tuple[int, int, int, int]:
        """The box XYXY at the output resolution (the whole output for the full-image crop)."""
        if self.hw == self.image_hw:
            return 0, 0, out_hw[1], out_hw[0]
        sy, sx = out_hw[0] / self.image_hw[0], out_hw[1] / self.image_hw[1]
        x0, y0, x1, y1 = self.box
        return int(round(x0 * sx)), int(round(y0 * sy)), int(round(x1 * sx)), int(round(y1 * sy))

    def mask(self, low_res: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
        """(256, 256) logits of a mask decoded in this crop -> (out_h, out_w) bool: the decoder's
        postprocessing straight into the crop's box at the output resolution, thresholded at 0."""
        x0, y0, x1, y1 = self.output_box(out_hw)
        out = np.zeros(out_hw, bool)
        out[y0:y1, x0:x1] = upscale_logits(low_res[None], self.hw, (y1 - y0, x1 - x0))[0] > 0.0
        return out


class StepTimer:
    """Seconds per named step, summed over calls and threads: `with timer("encoder"): ...`; a step
    None is not timed."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self._lock = threading.Lock()

    @contextmanager
    def __call__(self, step: str | None) -> Iterator[None]:
        if step is None:
            yield
            return
        t0 = time.perf_counter()
        try:
            yield
        finally:
            dt = time.perf_counter() - t0
            with self._lock:
                self.seconds[step] += dt
