"""MobileSAM segment-everything through ONNX Runtime: preprocessing, the encoder and decoder runners,
and `MobileSamSegmenter`, the object the `objects/mobilesam` backend calls.

The user brings two ONNX files (docs/models.md says how to export them from `mobile_sam.pt`):
- the image encoder, either form: `[1, 3, 1024, 1024]` normalised and zero-padded (a plain
  torch.onnx.export of `sam.image_encoder`), or samexporter's `--use-preprocess` form `[H, W, 3]` RGB
  0-255 already resized so that the long side is 1024; output `image_embeddings [1, 256, 64, 64]`;
- the prompt encoder + mask decoder exported by MobileSAM's `scripts/export_onnx_model.py`
  (inputs image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size;
  outputs masks, iou_predictions, low_res_masks).

`MobileSamSegmenter.segment` runs segment-anything's automatic mask generator (amg.py) with the
restructured decoder of fast_decoder.py (`decoder="fast"`, default) or the official graph
(`decoder="official"`, one call per prompt unless its batch axis is dynamic).
"""
from __future__ import annotations

import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Literal, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import ConfigError, FrameError, ModelFileError
from . import amg
from .onnx_runtime import (RuntimeParams, TensorSpec, check_contract, create_session, file_sha256, input_dims,
                           resolve_providers)

IMG_SIZE = 1024
PIXEL_MEAN = np.array([123.675, 116.28, 103.53], np.float32)   # RGB, 0-255
PIXEL_STD = np.array([58.395, 57.12, 57.375], np.float32)
EMBEDDING_SHAPE = (1, 256, 64, 64)

ENCODER_OUTPUTS = [TensorSpec("image_embeddings", EMBEDDING_SHAPE)]
DECODER_INPUTS = [
    TensorSpec("image_embeddings", EMBEDDING_SHAPE),
    TensorSpec("point_coords", ("batch", "num_points", 2)),
    TensorSpec("point_labels", ("batch", "num_points")),
    TensorSpec("mask_input", (1, 1, 256, 256)),
    TensorSpec("has_mask_input", (1,)),
    TensorSpec("orig_im_size", (2,)),
]
DECODER_OUTPUTS = [TensorSpec("masks", ("b", "m", "h", "w")), TensorSpec("iou_predictions", ("b", 4)),
                   TensorSpec("low_res_masks", ("b", 4, 256, 256))]


# ---------------------------------------------------------------------------------------------
# Preprocessing
# ---------------------------------------------------------------------------------------------
def resize_longest_side(rgb: np.ndarray, long_side: int = IMG_SIZE) -> np.ndarray:
    """(H, W, 3) uint8 RGB resized so that its longest side is `long_side` ((newh, neww) rounded
    half up), with Pillow's bilinear filter as the reference's torchvision resize of a PIL image."""
    newh, neww = amg.preprocess_shape(rgb.shape[0], rgb.shape[1], long_side)
    return np.asarray(Image.fromarray(rgb).resize((neww, newh), Image.BILINEAR))


def normalise_and_pad(resized: np.ndarray) -> np.ndarray:
    """(newh, neww, 3) RGB 0-255 -> (1, 3, 1024, 1024) float32: (x - mean) / std, then zeros padded at
    the bottom and right (a padded pixel is 0 after normalisation)."""
    x = (resized.astype(np.float32) - PIXEL_MEAN) / PIXEL_STD
    out = np.zeros((1, 3, IMG_SIZE, IMG_SIZE), np.float32)
    out[0, :, :x.shape[0], :x.shape[1]] = x.transpose(2, 0, 1)
    return out


def transform_coords(points: np.ndarray, orig_hw: tuple[int, int]) -> np.ndarray:
    """(..., 2) pixel (x, y) in the original image -> the 1024 input frame (ResizeLongestSide.apply_coords)."""
    h, w = orig_hw
    newh, neww = amg.preprocess_shape(h, w)
    out = np.array(points, dtype=np.float64, copy=True)
    out[..., 0] *= neww / w
    out[..., 1] *= newh / h
    return out


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise FrameError(f"expected an (H, W, 3) uint8 RGB image, got {rgb.shape} {rgb.dtype}")
    return np.ascontiguousarray(rgb)


# ---------------------------------------------------------------------------------------------
# Runners
# ---------------------------------------------------------------------------------------------
class ImageEncoder:
    """The image encoder ONNX, in either form (see module docstring).

    path: the encoder ONNX file.
    providers: resolved execution providers in preference order (onnx_runtime.resolve_providers).
    threads: intra-op threads of the session."""

    def __init__(self, path: str | Path, providers: Sequence[str], threads: int):
        self.path = Path(path)
        self.session = create_session(self.path, providers, threads, "MobileSAM encoder")
        ins = self.session.get_inputs()
        if len(ins) != 1:
            raise ModelFileError(f"MobileSAM encoder ONNX {self.path}: expected 1 input, found "
                                 f"{[i.name for i in ins]}")
        self.input_name = ins[0].name
        rank = len(ins[0].shape)
        if rank == 4:
            self.preprocessed_input = False
            spec = TensorSpec(self.input_name, (1, 3, IMG_SIZE, IMG_SIZE))
        elif rank == 3:   # samexporter --use-preprocess: resized RGB (H, W, 3), normalised in-graph
            self.preprocessed_input = True
            spec = TensorSpec(self.input_name, ("height", "width", 3))
        else:
            raise ModelFileError(f"MobileSAM encoder ONNX {self.path}: input {self.input_name!r} expected shape "
                                 f"[1, 3, 1024, 1024] or [H, W, 3], found {ins[0].shape}")
        check_contract(self.session, [spec], ENCODER_OUTPUTS, self.path, "MobileSAM encoder")

    def embed(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> image_embeddings (1, 256, 64, 64) float32."""
        resized = resize_longest_side(_check_rgb(rgb))
        x = resized.astype(np.float32) if self.preprocessed_input else normalise_and_pad(resized)
        return self.session.run(["image_embeddings"], {self.input_name: x})[0]


class OfficialDecoder:
    """The official decoder ONNX (prompt encoder + mask decoder + postprocessing).

    Batches prompts when the file's batch axis is dynamic, loops one prompt per call when it is
    fixed (the official export). Also usable through the fast decoder's interface
    (set_image / predict_iou / low_res_masks), keeping each batch's low-res masks.

    path: the decoder ONNX file.
    providers: resolved execution providers in preference order (onnx_runtime.resolve_providers).
    threads: intra-op threads of the session."""

    def __init__(self, path: str | Path, providers: Sequence[str], threads: int):
        self.path = Path(path)
        self.session = create_session(self.path, providers, threads, "MobileSAM decoder")
        check_contract(self.session, DECODER_INPUTS, DECODER_OUTPUTS, self.path, "MobileSAM decoder")
        self.batched = input_dims(self.session, "point_coords")[0] is None
        self.max_batch = 8
        self._emb: np.ndarray | None = None

    def __call__(self, image_embeddings: np.ndarray, point_coords: np.ndarray, point_labels: np.ndarray,
                 orig_hw: tuple[int, int], outputs=("masks", "iou_predictions", "low_res_masks")) -> list[np.ndarray]:
        """Prompts (B, N, 2) in the 1024 frame and labels (B, N) -> the requested outputs, batch-first
        (masks (B, 4, H, W) logits at orig_hw, iou_predictions (B, 4), low_res_masks (B, 4, 256, 256))."""
        base = {"image_embeddings": np.ascontiguousarray(image_embeddings, np.float32),
                "mask_input": np.zeros((1, 1, 256, 256), np.float32),
                "has_mask_input": np.zeros(1, np.float32),
                "orig_im_size": np.asarray(orig_hw, np.float32)}
        coords = np.asarray(point_coords, np.float32)
        labels = np.asarray(point_labels, np.float32)
        step = self.max_batch if self.batched else 1   # the graph upsamples 4 masks per prompt: bound memory
        parts = [self.session.run(list(outputs), {**base, "point_coords": coords[i:i + step],
                                                  "point_labels": labels[i:i + step]})
                 for i in range(0, len(coords), step)]
        return [np.concatenate([p[k] for p in parts]) for k in range(len(outputs))]

    # fast-decoder interface -----------------------------------------------------------------
    def set_image(self, image_embeddings: np.ndarray) -> None:
        self._emb = image_embeddings

    def predict_iou(self, point_coords: np.ndarray, point_labels: np.ndarray):
        iou, low = self(self._emb, point_coords, point_labels, (IMG_SIZE, IMG_SIZE),
                        outputs=("iou_predictions", "low_res_masks"))
        return iou, low

    def low_res_masks(self, state: np.ndarray, index: np.ndarray) -> np.ndarray:
        return state[np.asarray(index)]

    def candidate_masks(self, state: np.ndarray, prompt: np.ndarray, token: np.ndarray) -> np.ndarray:
        return state[np.asarray(prompt), np.asarray(token)]


# ---------------------------------------------------------------------------------------------
# Segment everything
# ---------------------------------------------------------------------------------------------
@dataclass
class Segmentation:
    """Masks of one image, in the reference generator's output order (NMS order: score-descending).

    masks (M, h, w) bool at the requested output resolution; scores (M,) float32 predicted IoU;
    areas (M,) int64 pixels of the returned masks; stability (M,) float32; boxes (M, 4) int64 XYXY at
    the image resolution (inclusive maxima); points (M, 2) float64 prompt pixel (x, y);
    crop_boxes (M, 4) XYXY; timings seconds per step; n_candidates the masks decoded (they passed the
    IoU filter), n_mask_prompts the prompts whose masks were decoded."""

    masks: np.ndarray
    scores: np.ndarray
    areas: np.ndarray
    stability: np.ndarray
    boxes: np.ndarray
    points: np.ndarray
    crop_boxes: np.ndarray
    timings: dict = field(default_factory=dict)
    n_candidates: int = 0
    n_mask_prompts: int = 0


class _Timer:
    def __init__(self):
        self.t = defaultdict(float)

    def add(self, key: str, t0: float) -> float:
        now = time.perf_counter()
        self.t[key] += now - t0
        return now


def _crop_output_box(crop: list[int], img_hw: tuple[int, int], out_hw: tuple[int, int]) -> list[int]:
    """A crop box (image pixels) at the output resolution."""
    sy, sx = out_hw[0] / img_hw[0], out_hw[1] / img_hw[1]
    return [int(round(crop[0] * sx)), int(round(crop[1] * sy)), int(round(crop[2] * sx)), int(round(crop[3] * sy))]


@dataclass(frozen=True, kw_only=True)
class SegmenterOptions(amg.AmgOptions, RuntimeParams):
    """Everything `MobileSamSegmenter` is configured with besides its two files: the generator's
    options (AmgOptions), the ONNX Runtime settings (RuntimeParams) and the decoder mode."""

    decoder_mode: Literal["fast", "official"] = "fast"  # fast: restructured decoder built from the decoder file's weights, IoU filter first (same masks, several times faster); official: the exported decoder graph, one call per prompt


class MobileSamSegmenter:
    """segment-anything's automatic mask generator with MobileSAM's ONNX files.

    encoder, decoder: the ONNX paths. options: SegmenterOptions (generator, runtime, decoder mode).
    verify: on load, check the fast decoder against the official graph on a few prompts and refuse
    a mismatch (catches an export whose weights were read wrongly)."""

    def __init__(self, encoder: str | Path, decoder: str | Path, options: SegmenterOptions = SegmenterOptions(),
                 verify: bool = True):
        decoder_mode, threads = options.decoder_mode, options.threads
        if decoder_mode not in ("fast", "official"):
            raise ModelFileError(f"decoder_mode must be 'fast' or 'official', got {decoder_mode!r}")
        self.options = options
        self.providers = resolve_providers(options.providers)
        self.encoder_path, self.decoder_path = Path(encoder), Path(decoder)
        self.encoder = ImageEncoder(encoder, self.providers, threads)
        self.official = OfficialDecoder(decoder, self.providers, threads)
        self.decoder_mode = decoder_mode
        self._lock = threading.Lock()   # the decoders keep the current image: one segment() at a time
        self._pool = None
        if decoder_mode == "fast":
            from concurrent.futures import ThreadPoolExecutor

            try:
                from .fast_decoder import FastDecoder
            except ImportError as e:   # the fast decoder reads and writes ONNX graphs with the onnx package
                raise ConfigError(f"decoder_mode 'fast' needs the onnx package ({e}): pip install onnx, "
                                  "or use decoder_mode 'official'") from e

            # CPU: `threads` batches at once on 1-thread sessions (less synchronisation than one
            # batch on `threads` threads); other providers: one batch at a time
            parallel = threads > 1 and self.providers[0] == "CPUExecutionProvider"
            self.decoder = FastDecoder(decoder, self.providers, 1 if parallel else threads)
            if parallel:
                self._pool = ThreadPoolExecutor(threads, thread_name_prefix="mobilesam")
            if verify:
                self.verify()
        else:
            self.decoder = self.official

    def provenance(self) -> dict:
        """Backend parameters and model hashes for the store's provenance."""
        return {"encoder": str(self.encoder_path), "encoder_sha256": file_sha256(self.encoder_path),
                "decoder": str(self.decoder_path), "decoder_sha256": file_sha256(self.decoder_path),
                **self.options.to_dict(), "providers": self.providers}

    def verify(self, n_prompts: int = 3, atol: float = 1e-3) -> float:
        """Compare the fast decoder with the official graph on a random embedding; returns the max
        abs difference of IoU predictions and low-res logits, raises ModelFileError above atol."""
        rng = np.random.default_rng(0)
        emb = rng.standard_normal(EMBEDDING_SHAPE).astype(np.float32)
        coords = np.stack([rng.uniform(0, IMG_SIZE, (n_prompts, 2)), np.zeros((n_prompts, 2))], axis=1)
        labels = np.tile(np.array([1.0, -1.0]), (n_prompts, 1))
        ref_iou, ref_low = self.official(emb, coords, labels, (IMG_SIZE, IMG_SIZE),
                                         outputs=("iou_predictions", "low_res_masks"))
        self.decoder.set_image(emb)
        iou, state = self.decoder.predict_iou(coords, labels)
        low = self.decoder.low_res_masks(state, np.arange(n_prompts))
        err = float(max(np.abs(iou - ref_iou).max(), np.abs(low - ref_low).max()))
        if not err <= atol:
            raise ModelFileError(f"decoder ONNX {self.decoder_path}: the fast decoder built from its weights differs "
                                 f"from the graph by {err:.2e} (> {atol}); use decoder_mode='official' and report the "
                                 "export command")
        return err

    # ------------------------------------------------------------------------------------------
    def segment(self, rgb: np.ndarray, out_size: tuple[int, int] | None = None) -> Segmentation:
        """Segment everything in an (H, W, 3) uint8 RGB image. out_size = (h, w) of the returned masks
        (e.g. the depth map's; default the image's). Filters run at the image resolution, as the
        reference's; the returned masks are the kept candidates' logits resampled to out_size.
        Thread-safe (calls are serialised)."""
        with self._lock:
            return self._segment(_check_rgb(rgb), out_size)

    def _segment(self, rgb: np.ndarray, out_size) -> Segmentation:
        opt = self.options
        img_hw = rgb.shape[:2]
        out_hw = tuple(out_size) if out_size is not None else img_hw
        timer = _Timer()
        t0 = time.perf_counter()
        boxes_c, layers = amg.crop_boxes(img_hw, opt.crop_n_layers, opt.crop_overlap_ratio)
        grids = amg.layer_point_grids(opt.points_per_side, opt.crop_n_layers, opt.crop_n_points_downscale_factor)
        kept: list[dict] = []
        n_candidates = 0
        self._n_mask_prompts = 0
        for ci, (crop, layer) in enumerate(zip(boxes_c, layers)):
            res, n = self._process_crop(rgb, crop, grids[layer], img_hw, timer)
            n_candidates += n
            for r in res:
                r["crop_index"] = ci
            kept += res
        t0 = time.perf_counter()
        if len(boxes_c) > 1 and kept:
            areas = np.array([amg.box_area(np.array([boxes_c[r["crop_index"]]], np.float64))[0] for r in kept])
            order = amg.box_nms(np.array([r["box"] for r in kept]), 1.0 / areas, opt.crop_nms_thresh)
            kept = [kept[i] for i in order]
        t0 = timer.add("nms", t0)
        changed: dict[int, np.ndarray] = {}
        if opt.min_mask_region_area > 0 and kept:
            kept, changed = self._small_regions(kept, boxes_c, img_hw, timer)
        t0 = time.perf_counter()
        masks = np.zeros((len(kept), *out_hw), bool)
        for i, r in enumerate(kept):
            if i in changed:
                m = changed[i]
                if m.shape != out_hw:
                    import cv2
                    m = cv2.resize(m.astype(np.uint8), (out_hw[1], out_hw[0]), interpolation=cv2.INTER_NEAREST) > 0
                masks[i] = m
                continue
            crop = boxes_c[r["crop_index"]]
            crop_hw = (crop[3] - crop[1], crop[2] - crop[0])
            ob = _crop_output_box(crop, img_hw, out_hw) if crop_hw != img_hw else [0, 0, out_hw[1], out_hw[0]]
            region = amg.upscale_logits(r["low_res"][None], crop_hw, (ob[3] - ob[1], ob[2] - ob[0]))[0]
            masks[i, ob[1]:ob[3], ob[0]:ob[2]] = region > 0.0
        timer.add("output masks", t0)
        n = len(kept)
        return Segmentation(
            masks=masks,
            scores=np.array([r["iou"] for r in kept], np.float32).reshape(n),
            areas=masks.sum(axis=(1, 2), dtype=np.int64),
            stability=np.array([r["stability"] for r in kept], np.float32).reshape(n),
            boxes=np.array([r["box"] for r in kept], np.int64).reshape(n, 4),
            points=np.array([r["point"] for r in kept], np.float64).reshape(n, 2),
            crop_boxes=np.array([boxes_c[r["crop_index"]] for r in kept], np.int64).reshape(n, 4),
            timings=dict(timer.t), n_candidates=n_candidates, n_mask_prompts=self._n_mask_prompts)

    def _process_crop(self, rgb, crop, grid, img_hw, timer) -> tuple[list[dict], int]:
        """One crop: encode, decode the grid in batches, filter; in-crop NMS. Boxes and points come
        back in image coordinates; `low_res` keeps each kept mask's 256x256 logits."""
        opt = self.options
        x0, y0, x1, y1 = crop
        crop_hw = (y1 - y0, x1 - x0)
        t0 = time.perf_counter()
        emb = self.encoder.embed(rgb[y0:y1, x0:x1])
        t0 = timer.add("encoder", t0)
        self.decoder.set_image(emb)
        t0 = timer.add("decoder image", t0)
        points = grid * np.array([crop_hw[1], crop_hw[0]], np.float64)       # crop pixels (x, y)
        coords = transform_coords(points, crop_hw)
        step = getattr(self.decoder, "batch_size", None) or opt.points_per_batch   # results do not depend on it
        starts = range(0, len(points), step)
        if self._pool is None:
            parts = [self._decode_batch(coords[b0:b0 + step], points[b0:b0 + step], crop, crop_hw, img_hw)
                     for b0 in starts]
        else:   # batches in parallel (1-thread sessions), results in batch order
            parts = list(self._pool.map(lambda b0: self._decode_batch(coords[b0:b0 + step], points[b0:b0 + step],
                                                                      crop, crop_hw, img_hw), starts))
        kept: list[dict] = []
        n_candidates = 0
        for res, n_cand, n_prompts, times in parts:
            kept += res
            n_candidates += n_cand
            self._n_mask_prompts += n_prompts
            for k, v in times.items():
                timer.t[k] += v
        t0 = time.perf_counter()
        if kept:
            order = amg.box_nms(np.array([r["box"] for r in kept]), np.array([r["iou"] for r in kept], np.float32),
                                opt.box_nms_thresh)
            kept = [kept[i] for i in order]
            shift = np.array([x0, y0, x0, y0])
            for r in kept:
                r["box"] = r["box"] + shift
                r["point"] = r["point"] + np.array([x0, y0])
        timer.add("nms", t0)
        return kept, n_candidates

    def _decode_batch(self, coords, points, crop, crop_hw, img_hw):
        """One batch of grid points (1024 frame, crop pixels): predicted IoUs, then masks only for
        the candidates that pass, filtered at the crop's resolution. Returns (kept candidates,
        n candidates, n prompts decoded, seconds per step)."""
        opt = self.options
        timer = _Timer()
        iou_thr = np.float32(opt.pred_iou_thresh)
        stab_thr = np.float32(opt.stability_score_thresh)
        batch_coords = np.stack([coords, np.zeros_like(coords)], axis=1)          # point + padding point
        batch_labels = np.tile(np.array([1.0, -1.0]), (len(coords), 1))
        t0 = time.perf_counter()
        iou, state = self.decoder.predict_iou(batch_coords, batch_labels)
        t0 = timer.add("decoder iou", t0)
        cand_iou = iou[:, 1:4].reshape(-1).astype(np.float32)                     # point-major, 3 per point
        cand = np.flatnonzero(cand_iou > iou_thr) if opt.pred_iou_thresh > 0 else np.arange(cand_iou.size)
        t0 = timer.add("filters", t0)
        kept: list[dict] = []
        if cand.size == 0:
            return kept, 0, 0, timer.t
        cand_low = self.decoder.candidate_masks(state, cand // 3, cand % 3 + 1)   # (n, 256, 256)
        del state
        t0 = timer.add("decoder masks", t0)
        for c0 in range(0, len(cand), 32):                                        # bounded memory at full res
            sl = slice(c0, c0 + 32)
            logits = amg.upscale_logits(cand_low[sl], crop_hw)
            t0 = timer.add("upscale", t0)
            stab = amg.stability_score(logits, opt.stability_score_offset)
            ok = stab >= stab_thr if opt.stability_score_thresh > 0 else np.ones(len(stab), bool)
            masks = logits[ok] > 0.0
            boxes = amg.masks_to_boxes(masks)
            edge = amg.near_crop_edge(boxes, crop, [0, 0, img_hw[1], img_hw[0]])
            idx = np.flatnonzero(ok)[~edge]
            for j, box in zip(idx, boxes[~edge]):
                c = cand[c0 + j]
                kept.append({"iou": float(cand_iou[c]), "stability": float(stab[j]), "box": box,
                             "point": points[c // 3], "low_res": cand_low[c0 + j].copy()})
            t0 = timer.add("filters", t0)
        return kept, len(cand), len(np.unique(cand // 3)), timer.t

    def _small_regions(self, kept, boxes_c, img_hw, timer):
        """min_mask_region_area: fill small holes, drop small islands (image resolution); changed masks
        score 0 in a new NMS at max(box_nms_thresh, crop_nms_thresh), so unchanged ones win."""
        opt = self.options
        t0 = time.perf_counter()
        full = []
        for r in kept:
            crop = boxes_c[r["crop_index"]]
            crop_hw = (crop[3] - crop[1], crop[2] - crop[0])
            m = np.zeros(img_hw, bool)
            m[crop[1]:crop[3], crop[0]:crop[2]] = amg.upscale_logits(r["low_res"][None], crop_hw)[0] > 0.0
            full.append(m)
        new, scores = [], []
        for m in full:
            m, ch1 = amg.remove_small_regions(m, opt.min_mask_region_area, "holes")
            m, ch2 = amg.remove_small_regions(m, opt.min_mask_region_area, "islands")
            new.append(m)
            scores.append(0.0 if (ch1 or ch2) else 1.0)
        boxes = amg.masks_to_boxes(np.stack(new))
        order = amg.box_nms(boxes, np.array(scores), max(opt.box_nms_thresh, opt.crop_nms_thresh))
        out, changed = [], {}
        for i in order:
            r = kept[i]
            if scores[i] == 0.0:
                r = dict(r, box=boxes[i])
                changed[len(out)] = new[i]
            out.append(r)
        timer.add("small regions", t0)
        return out, changed
