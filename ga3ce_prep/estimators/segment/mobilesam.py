"""MobileSAM segment-everything: `MobileSamSegmenter`, the object the `objects/mobilesam` backend
calls, segment-anything's `SamAutomaticMaskGenerator` side of its seam: the point grids, the crops,
the IoU and stability filters, NMS, small regions, and the crop plan through which reuse plugs in.

It runs segment-anything's automatic mask generator (amg.py) on the runners of one of two runtimes:
the encoder and decoder ONNX files through ONNX Runtime (mobilesam_runners.py: the preprocessing, the
encoder, the fast and official decoders, both a `MaskDecoder`), or, `MobileSamSegmenter.from_checkpoint`
(`runtime: torch`, mobilesam_torch.py), MobileSAM's own torch modules read from the official
checkpoint `mobile_sam.pt`, on the CPU or a CUDA device. Each crop's steps run through a `CropPlan`
(crop_plan.py): the exact generator's `EXACT` (every prompt), or reuse.SequenceReuse (reuse across
the frames of a static camera). The prompts of a crop are segment-anything's point grid, or, on the
full image, the caller's (prompts.Prompts: points and boxes; depth_prompts.py makes them from depth).
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np

from ...errors import ConfigError
from ...files import file_sha256
from . import amg
from .crop_plan import EXACT, CropPlan
from .mobilesam_runners import (
    ImageEncoder,
    MaskDecoder,
    OfficialDecoder,
    SegmenterOptions,
    check_rgb,
    mask_mode,
    open_onnx,
    verify_decoder,
)
from .prompts import Prompts
from .reuse import ReuseStep, SequenceReuse

if TYPE_CHECKING:
    from .mobilesam_torch import TorchEncoder


@dataclass
class Segmentation:
    """Masks of one image, in the reference generator's output order (NMS order: score-descending).

    masks: (M, h, w) bool at the requested output resolution.
    scores: (M,) float32 predicted IoU.
    areas: (M,) int64 pixels of the returned masks.
    stability: (M,) float32 stability scores.
    boxes: (M, 4) int64 XYXY at the image resolution (inclusive maxima).
    points: (M, 2) float64 prompt pixel (x, y).
    crop_boxes: (M, 4) XYXY of each mask's crop.
    timings: seconds per step (summed over the decoding threads).
    n_candidates: the masks decoded (they passed the IoU filter).
    n_mask_prompts: the prompts whose masks were decoded.
    n_prompts: the prompts decoded (the whole grid or the prompts given, fewer on a reuse frame).
    reuse: what reuse did on this frame (reuse.ReuseStep), None without reuse."""

    masks: np.ndarray
    scores: np.ndarray
    areas: np.ndarray
    stability: np.ndarray
    boxes: np.ndarray
    points: np.ndarray
    crop_boxes: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    n_candidates: int = 0
    n_mask_prompts: int = 0
    n_prompts: int = 0
    reuse: ReuseStep | None = None


@dataclass(frozen=True)
class _Counts:
    """What the decoder was asked for: candidates (masks decoded, they passed the IoU filter) and
    mask_prompts (prompts whose masks were decoded)."""

    candidates: int = 0
    mask_prompts: int = 0
    prompts: int = 0

    def __add__(self, other: _Counts) -> _Counts:
        return _Counts(self.candidates + other.candidates, self.mask_prompts + other.mask_prompts,
                       self.prompts + other.prompts)


def _resize_nearest(mask: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    if mask.shape == out_hw:
        return mask
    return cv2.resize(mask.astype(np.uint8), (out_hw[1], out_hw[0]), interpolation=cv2.INTER_NEAREST) > 0


DEFAULT_OPTIONS = SegmenterOptions()


class MobileSamSegmenter:
    """segment-anything's automatic mask generator on one of two runtimes: MobileSAM's ONNX files
    through ONNX Runtime (the constructor) or the official checkpoint through torch
    (`from_checkpoint`, mobilesam_torch.py). The runtime is the encoder (`embed`) and the
    `MaskDecoder` the generator calls; everything else is the same code.

    encoder: the image encoder ONNX path.
    decoder: the prompt encoder + mask decoder ONNX path.
    options: SegmenterOptions (generator, ONNX Runtime settings, decoder mode; runtime onnx).
    verify: on load, check the fast decoder against the official graph on a few prompts and refuse
      a mismatch (catches an export whose weights were read wrongly)."""

    checkpoint: Path  # runtime torch (from_checkpoint): the official checkpoint read

    def __init__(self, encoder: str | Path, decoder: str | Path, options: SegmenterOptions = DEFAULT_OPTIONS,
                 verify: bool = True):
        if options.runtime != "onnx":
            raise ConfigError(f"runtime: {options.runtime} reads a checkpoint: MobileSamSegmenter.from_checkpoint")
        options.check_runtime()
        r = open_onnx(encoder, decoder, options.providers, options.threads, options.decoder_mode, options.io_binding,
                      options.points_per_batch)
        self.options = options
        self.providers = r.providers
        self.encoder_path, self.decoder_path = Path(encoder), Path(decoder)
        self.encoder: ImageEncoder | TorchEncoder = r.encoder
        self.official: OfficialDecoder | None = r.official
        self.decoder: MaskDecoder = r.decoder
        self.decoder_mode = options.decoder_mode
        self._lock = threading.Lock()   # the decoders keep the current image: one segment() at a time
        self._pool: ThreadPoolExecutor | None = r.pool
        if verify and options.decoder_mode == "fast":
            self.verify()

    @classmethod
    def from_checkpoint(cls, checkpoint: str | Path, options: SegmenterOptions) -> MobileSamSegmenter:
        """The generator on the torch runtime: MobileSAM's modules with the official checkpoint's
        weights (`mobile_sam.pt`) on options.device (options.runtime "torch"; options.threads:
        torch's intra-op threads, process-wide). ModelFileError / ConfigError naming the checkpoint and
        the fix when it or MobileSAM's code is missing, or when CUDA is asked for and absent."""
        from .mobilesam_torch import open_torch

        if options.runtime != "torch":
            raise ConfigError("from_checkpoint runs runtime: torch; set it in the options")
        options.check_runtime()
        self = cls.__new__(cls)
        self.options = options
        self.checkpoint = Path(checkpoint)
        self.encoder, self.decoder = open_torch(checkpoint, options.device, int(options.threads))
        self.official = None
        self._lock = threading.Lock()
        self._pool = None
        return self

    @property
    def mask_mode(self) -> Literal["multimask", "single-mask"]:
        """"multimask" (3 candidates per grid point) or "single-mask" (the file's one mask per point)."""
        return mask_mode(self.decoder)

    def provenance(self) -> dict:
        """Backend parameters, model hashes and the mask mode for the store's provenance."""
        if self.options.runtime == "torch":
            return {"checkpoint": str(self.checkpoint), "checkpoint_sha256": file_sha256(self.checkpoint),
                    "mask_mode": self.mask_mode, **self.options.to_dict()}
        return {"encoder": str(self.encoder_path), "encoder_sha256": file_sha256(self.encoder_path),
                "decoder": str(self.decoder_path), "decoder_sha256": file_sha256(self.decoder_path),
                "mask_mode": self.mask_mode, **self.options.to_dict(), "providers": self.providers}

    def verify(self, n_prompts: int = 3, atol: float = 1e-3) -> float:
        """Compare the fast decoder with the official graph on a random embedding
        (mobilesam_runners.verify_decoder); returns the max abs difference of IoU predictions and
        low-res logits, raises ModelFileError above atol. The ONNX runtime only (the torch runtime
        runs the checkpoint's own modules)."""
        if self.official is None:
            raise ConfigError("verify() compares the fast decoder with the decoder ONNX: runtime onnx only")
        return verify_decoder(self.decoder, self.official, n_prompts, atol)

    # ------------------------------------------------------------------------------------------
    def segment(self, rgb: np.ndarray, out_size: tuple[int, int] | None = None,
                reuse: SequenceReuse | None = None, prompts: Prompts | None = None) -> Segmentation:
        """Segment everything in an (H, W, 3) uint8 RGB image. out_size = (h, w) of the returned masks
        (e.g. the depth map's; default the image's). Filters run at the image resolution, as the
        reference's; the returned masks are the kept candidates' logits resampled to out_size.
        reuse: the camera sequence's state (reuse.SequenceReuse, `start`ed with this frame's
        cues): decode only the prompts whose neighbourhood changed since its key frame (full-image
        crop only). prompts: the image's prompts in its pixels in place of the point grid
        (prompts.Prompts; full-image crop only). Thread-safe (calls are serialised)."""
        if reuse is not None and self.options.crop_n_layers:
            raise ConfigError("reuse covers the full-image crop only (crop_n_layers 0)")
        if prompts is not None and self.options.crop_n_layers:
            raise ConfigError("prompts replace the full-image crop's grid: crop_n_layers 0")
        with self._lock:
            return self._segment(check_rgb(rgb), out_size, reuse, prompts)

    def _segment(self, rgb: np.ndarray, out_size: tuple[int, int] | None,
                 reuse: SequenceReuse | None = None, prompts: Prompts | None = None) -> Segmentation:
        """The generator's steps over the crops, as the reference's `_generate_masks` and
        `postprocess_small_regions`."""
        opt = self.options
        img_hw: tuple[int, int] = rgb.shape[:2]
        out_hw = (out_size[0], out_size[1]) if out_size is not None else img_hw
        timer = amg.StepTimer()
        boxes, layers = amg.crop_boxes(img_hw, opt.crop_n_layers, opt.crop_overlap_ratio)
        crops = [amg.Crop(i, (x0, y0, x1, y1), layer, img_hw)
                 for i, ((x0, y0, x1, y1), layer) in enumerate(zip(boxes, layers))]
        grids = amg.layer_point_grids(opt.points_per_side, opt.crop_n_layers, opt.crop_n_points_downscale_factor)
        layer = EXACT if reuse is None else reuse
        parts = [self._process_crop(rgb, crop, Prompts.grid(grids[crop.layer], crop.hw) if prompts is None else prompts,
                                    timer, layer) for crop in crops]
        data = amg.MaskRecords.empty().cat(*(records for records, _ in parts))
        counts = sum((n for _, n in parts), _Counts())
        crop_boxes = np.array(boxes, np.int64)                                      # (crops, 4)
        # Remove duplicate masks between crops (the smaller crop wins)
        if len(crops) > 1:
            with timer("nms"):
                scores = 1.0 / amg.box_area(crop_boxes[data.crop_index].astype(np.float64))
                data = data.filter(amg.box_nms(data.box, scores, opt.crop_nms_thresh))
        # Remove small disconnected regions and holes
        changed: dict[int, np.ndarray] = {}
        if opt.min_mask_region_area > 0 and len(data):
            with timer("small regions"):
                data, changed = self._small_regions(data, crops)
        # Masks at the output resolution
        with timer("output masks"):
            masks = np.zeros((len(data), *out_hw), bool)
            for i, (low_res, ci) in enumerate(zip(data.low_res, data.crop_index)):
                masks[i] = _resize_nearest(changed[i], out_hw) if i in changed else crops[ci].mask(low_res, out_hw)
        return Segmentation(masks=masks, scores=data.iou, areas=masks.sum(axis=(1, 2), dtype=np.int64),
                            stability=data.stability, boxes=data.box, points=data.point,
                            crop_boxes=crop_boxes[data.crop_index], timings=dict(timer.seconds),
                            n_candidates=counts.candidates, n_mask_prompts=counts.mask_prompts,
                            n_prompts=counts.prompts, reuse=None if reuse is None else reuse.last)

    def _process_crop(self, rgb: np.ndarray, crop: amg.Crop, prompts: Prompts, timer: amg.StepTimer,
                      layer: CropPlan = EXACT) -> tuple[amg.MaskRecords, _Counts]:
        """One crop: encode, decode the prompts (in the crop's pixels) in batches, in-crop NMS. Boxes
        and points come back in image coordinates. `layer` plans the prompts to decode and merges their
        candidates with its own before NMS (CropPlan; EXACT: every prompt, nothing merged)."""
        x0, y0, x1, y1 = crop.box
        # Crop the image and calculate embeddings
        with timer("encoder"):
            emb = self.encoder.embed(rgb[y0:y1, x0:x1])
        with timer("decoder image"):
            self.decoder.set_image(emb)
        with timer(layer.step):
            prompts, plan = layer.plan(emb, prompts)                               # plan None: every prompt
        rows = np.arange(len(prompts)) if plan is None else np.flatnonzero(plan)
        margin = layer.margin
        # Generate masks for this crop in batches of one prompt kind (in parallel on 1-thread sessions), in
        # batch order; batch_size None: all at once; results do not depend on it
        batches = prompts.batches(rows, self.decoder.batch_size)

        def decode(b: np.ndarray) -> tuple[amg.MaskRecords, _Counts]:
            return self._decode_batch(prompts.filter(b), crop, timer, b, margin)

        parts = list(self._pool.map(decode, batches)) if self._pool else [decode(b) for b in batches]
        data = amg.MaskRecords.empty().cat(*(records for records, _ in parts))
        with timer(layer.step):
            data = layer.merge(data, self.options)
        # Remove duplicates within this crop
        with timer("nms"):
            keep = amg.box_nms(data.box, data.iou, self.options.box_nms_thresh)
            data = data.filter(keep)
        layer.settle(keep)
        # Return to the original image frame
        shift = np.array([x0, y0])
        data = replace(data, box=data.box + np.tile(shift, 2), point=data.point + shift)
        return data, sum((n for _, n in parts), _Counts())

    def _decode_batch(self, batch: Prompts, crop: amg.Crop, timer: amg.StepTimer,
                      prompts: np.ndarray, margin: float = 0.0) -> tuple[amg.MaskRecords, _Counts]:
        """One batch of prompts of one kind in crop pixels, and prompts (B,) their indices in the crop's:
        predicted IoUs, then masks only for the candidates that pass, filtered at the crop's
        resolution (the reference's `_process_batch`, IoU filter first). margin: lower the IoU and
        stability thresholds by this (the crop plan's, CropPlan.margin; 0 for the exact generator)."""
        opt = self.options
        tokens = np.asarray(self.decoder.candidate_tokens)                        # (k,): 1..3, or the one mask
        k = tokens.size
        # Predict the IoUs of the candidates (multimask outputs 1..3, or a single-mask export's one)
        with timer("decoder iou"):
            iou, state = self.decoder.predict_iou(*batch.decoder_inputs(crop.hw))
        iou = iou[:, tokens].reshape(-1).astype(np.float32)                        # (kB,) point-major
        # Filter by predicted IoU
        with timer("filters"):
            cand = np.flatnonzero(opt.iou_passes(iou, margin))
        if cand.size == 0:
            return amg.MaskRecords.empty(), _Counts(prompts=len(prompts))
        # Decode the candidates' masks (each prompt's once)
        with timer("decoder masks"):
            low_res = self.decoder.candidate_masks(state, cand // k, tokens[cand % k])   # (n, 256, 256)
        del state
        n = cand.size
        data = amg.MaskRecords(iou=iou[cand], stability=np.full(n, np.nan, np.float32),   # stability and
                               box=np.zeros((n, 4), np.int64), point=batch.points[cand // k],   # box: full res
                               low_res=low_res, crop_index=np.full(n, crop.index, np.int64),
                               prompt=np.asarray(prompts, np.int64)[cand // k])
        # Filter at the crop's resolution, 32 masks at a time (bounded memory)
        chunks = [self._filter_full_res(data.filter(slice(c0, c0 + 32)), crop, timer, margin) for c0 in range(0, n, 32)]
        return amg.MaskRecords.empty().cat(*chunks), _Counts(n, len(np.unique(cand // k)), len(prompts))

    def _filter_full_res(self, data: amg.MaskRecords, crop: amg.Crop, timer: amg.StepTimer,
                         margin: float = 0.0) -> amg.MaskRecords:
        """Candidates' stability scores and boxes from their logits at the crop's resolution, and the
        reference's filters on them (the stability threshold lowered by margin)."""
        opt = self.options
        with timer("upscale"):
            logits = amg.upscale_logits(data.low_res, crop.hw)                     # (n, h, w)
        with timer("filters"):
            # Calculate stability score
            data = replace(data, stability=amg.stability_score(logits, opt.stability_score_offset))
            if opt.stability_score_thresh > 0:
                keep = opt.stability_passes(data.stability, margin)
                data, logits = data.filter(keep), logits[keep]
            # Threshold masks and calculate boxes
            data = replace(data, box=amg.masks_to_boxes(logits > 0.0))
            # Filter boxes that touch crop boundaries
            image_box = [0, 0, crop.image_hw[1], crop.image_hw[0]]
            return data.filter(~amg.near_crop_edge(data.box, list(crop.box), image_box))

    def _small_regions(self, data: amg.MaskRecords,
                       crops: list[amg.Crop]) -> tuple[amg.MaskRecords, dict[int, np.ndarray]]:
        """min_mask_region_area (the reference's `postprocess_small_regions`): fill small holes, drop
        small islands at the image resolution; changed masks get new boxes and score 0 in a new NMS at
        max(box_nms_thresh, crop_nms_thresh), so unchanged ones win. Returns the kept records and
        {row: (H, W) bool} of the changed masks."""
        opt = self.options
        area = opt.min_mask_region_area
        new: list[np.ndarray] = []
        was_changed: list[bool] = []
        for low_res, ci in zip(data.low_res, data.crop_index):
            mask, holes = amg.remove_small_regions(crops[ci].mask(low_res, crops[ci].image_hw), area, "holes")
            mask, islands = amg.remove_small_regions(mask, area, "islands")
            new.append(mask)
            was_changed.append(holes or islands)
        changed = np.array(was_changed)
        boxes = amg.masks_to_boxes(np.stack(new))                                  # (n, 4)
        keep = amg.box_nms(boxes, (~changed).astype(np.float64), max(opt.box_nms_thresh, opt.crop_nms_thresh))
        data = replace(data, box=np.where(changed[:, None], boxes, data.box)).filter(keep)
        return data, {row: new[i] for row, i in enumerate(keep) if changed[i]}
