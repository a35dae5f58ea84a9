"""MobileSAM's mask decoder restructured for segment-everything, run by ONNX Runtime.

The official decoder export (MobileSAM `scripts/export_onnx_model.py`) costs about 1.8 GMAC per
prompt: its transformer multiplies the 4096x256 image embedding by 256x128 projections again and
again, and it upsamples 4 masks to full resolution for every prompt. `FastDecoder` computes the same
function from the same weights (fast_decoder_weights.py reads them from the official decoder ONNX)
with three ONNX graphs:

- **image graph**, once per image (fast_decoder_graphs.py): every projection of the image
  embedding that does not depend on the prompt.
- **token graph**, batched over prompts (fast_decoder_tokens.py): the 5 + N prompt tokens through
  both two-way layers and the final attention, giving `iou_predictions` (B, 4) without ever forming
  a 4096x256 tensor per prompt: the image stream is held as the factors of `LN(src + A0 M0)` and
  every product with it is re-associated through them, the LayerNorm statistics coming from Gram
  matrices (exact up to float rounding).
- **mask graph**, only for the prompts whose candidates pass the IoU filter (fast_decoder_graphs.py):
  the image stream after layer 1 through the output upscaling and the hypernetwork product, giving
  the 256x256 low-resolution mask logits.

docs/models/segment-everything.md, "How the fast decoder is fast", writes the derivation out under
the code's names.
Tokens are numbered as in the official decoder: 0 = IoU token, 1..4 = mask tokens (1..3 are the
"multimask" outputs), then the prompt points. Mask inputs (`has_mask_input` = 1) are not supported:
segment-everything never uses them.

Two ways to run the graphs (the same arithmetic, the same outputs):
- **plain** (CPU default): `run_with_ort_values`, prompts in small batches (`CPU_BATCH_SIZE`), which
  the segmenter decodes two at a time on 1-thread sessions. ONNX Runtime returns every output in
  host memory, so on a GPU the image tensors and the per-prompt state would cross the bus twice.
- **I/O binding** (`io_binding=True`, the default with the CUDA provider, `use_io_binding`): all
  prompts of a crop in one token-graph call (`batch_size` None); the image graph's outputs and the
  token graph's state (`STATE`: `A0cT`, `A1cT` (B, HT, 4096), ...) are bound as OrtValues on the
  provider's device and fed as they are to the next graph; only the IoU predictions (B, 4) and the
  wanted prompts' low-res logits come back to the host. The mask graph runs `MASK_CHUNK` prompts
  per call (bounded device memory: about 30 MB of activations per prompt). On CPU it runs the same
  code with device "cpu" (the tests compare it with the plain path there).
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
import onnxruntime as ort

from ..runtime.onnx_runtime import create_session
from .amg import MULTIMASK_TOKENS
from .fast_decoder_graphs import (
    IMAGE_TENSORS,
    STATE,
    TOKEN_IMAGE_INPUTS,
    Derived,
    build_image_graph,
    build_mask_graph,
    raw_to_image,
)
from .fast_decoder_tokens import build_token_graph
from .fast_decoder_weights import decoder_weights

# ONNX Runtime device of each provider the I/O binding path keeps tensors on (others: the host)
PROVIDER_DEVICE = {"CUDAExecutionProvider": "cuda", "TensorrtExecutionProvider": "cuda"}


def use_io_binding(setting: Literal["auto", "on", "off"], providers: Sequence[str]) -> bool:
    """Whether the fast decoder runs through I/O binding: "auto" = with the CUDA provider first in
    `providers` (resolved provider names); "on" = always (on CPU: for testing); "off" = never."""
    if setting not in ("auto", "on", "off"):
        raise ValueError(f"io_binding must be auto, on or off, got {setting!r}")
    return setting == "on" or (setting == "auto" and providers[0] == "CUDAExecutionProvider")


class FastDecoder:
    """The restructured decoder on ONNX Runtime, a `mobilesam_runners.MaskDecoder`: `set_image` once per image,
    then `predict_iou` for a batch of prompts and `low_res_masks` / `candidate_masks` for the prompts
    whose candidates are wanted.

    decoder_path: the official decoder ONNX (its weights are read from it).
    providers: resolved execution providers in preference order (onnx_runtime.resolve_providers).
    threads: intra-op threads of each of the three sessions.
    io_binding: run through I/O binding on the first provider's device, all prompts of a crop in one
      batch (module docstring); `use_io_binding` decides it from the segmenter's options."""

    # Prompts per token-graph call: 8 on CPU (other batch sizes measured in
    # docs/studies/2026-11-29-segment-everything-speed.md, "What was tried"),
    # GPU_BATCH_SIZE on other providers, None (all prompts of a crop) with I/O binding.
    CPU_BATCH_SIZE = 8
    GPU_BATCH_SIZE = 64
    # Prompts per mask-graph call with I/O binding
    MASK_CHUNK = 64
    # Prompts per mask-graph call at most on the CPU provider (4: the 8 of a token batch in two calls
    # keep the mask graph's slices in cache; docs/studies/2026-11-29-segment-everything-speed.md, "What was tried")
    CPU_MASK_BATCH = 4
    # Slices of the embedding's pixels the token and mask graphs run one after the other on the CPU
    # provider (build_token_graph, build_mask_graph; measured in
    # docs/studies/2026-11-29-segment-everything-speed.md, "What was tried"), 1 on others
    CPU_TOKEN_PIXEL_CHUNKS = 8
    CPU_MASK_PIXEL_CHUNKS = 32
    # Every token is decoded from the file's weights, a single-mask export's too: the generator's
    # candidates are the multimask outputs
    candidate_tokens = MULTIMASK_TOKENS

    def __init__(self, decoder_path: str | Path, providers: Sequence[str], threads: int, io_binding: bool = False):
        w = decoder_weights(decoder_path)
        d = Derived.from_weights(w)
        self.path = Path(decoder_path)
        self.io_binding = io_binding
        self.device = PROVIDER_DEVICE.get(providers[0], "cpu")   # where bound tensors live (device id 0)
        on_cpu = providers[0] == "CPUExecutionProvider"
        self.mask_batch = self.CPU_MASK_BATCH if on_cpu else None
        self.batch_size: int | None = None if io_binding else self.CPU_BATCH_SIZE if on_cpu else self.GPU_BATCH_SIZE
        self._image = create_session(build_image_graph(w, d).SerializeToString(), providers, threads,
                                     "fast decoder (image)")
        self._tokens = create_session(
            build_token_graph(w, d, self.CPU_TOKEN_PIXEL_CHUNKS if on_cpu else 1).SerializeToString(),
            providers, threads, "fast decoder (tokens)")
        self._masks = create_session(
            build_mask_graph(w, d, self.CPU_MASK_PIXEL_CHUNKS if on_cpu else 1).SerializeToString(),
            providers, threads, "fast decoder (masks)")
        self._img: dict[str, ort.OrtValue] | None = None

    def _value(self, array: np.ndarray, dtype: type = np.float32) -> ort.OrtValue:
        """A host array as an OrtValue where the graphs read it (the device with I/O binding)."""
        a: np.ndarray = np.ascontiguousarray(array, dtype)
        return ort.OrtValue.ortvalue_from_numpy(a, self.device, 0) if self.io_binding else \
            ort.OrtValue.ortvalue_from_numpy(a)

    def _run(self, session: ort.InferenceSession, feeds: dict[str, ort.OrtValue], on_device: Sequence[str],
             on_host: Sequence[str] = ()) -> dict[str, ort.OrtValue]:
        """One graph call. Plain: every output on the host. I/O binding: the feeds bound where they
        are, the outputs `on_device` left on the device for the next graph, those `on_host` copied
        to the host."""
        if not self.io_binding:
            names = [*on_device, *on_host]
            return dict(zip(names, session.run_with_ort_values(names, feeds)))
        binding = session.io_binding()
        for name, value in feeds.items():
            binding.bind_ortvalue_input(name, value)
        for name in on_device:
            binding.bind_output(name, self.device, 0)
        for name in on_host:
            binding.bind_output(name, "cpu")
        session.run_with_iobinding(binding)
        return dict(zip([*on_device, *on_host], binding.get_outputs()))

    def set_image(self, image_embeddings: np.ndarray) -> None:
        """image_embeddings (1, 256, 64, 64) float32 from the encoder."""
        self._img = self._run(self._image, {"image_embeddings": self._value(image_embeddings)}, list(IMAGE_TENSORS))

    def predict_iou(self, point_coords: np.ndarray,
                    point_labels: np.ndarray) -> tuple[np.ndarray, dict[str, ort.OrtValue]]:
        """point_coords (B, N, 2) in the 1024 input frame, point_labels (B, N) (1 fg, 0 bg, -1 padding).
        Returns (iou_predictions (B, 4) float32, state for `low_res_masks`)."""
        if self._img is None:
            raise RuntimeError("call set_image() before predict_iou()")
        feeds = {k: self._img[k] for k in TOKEN_IMAGE_INPUTS}
        feeds["point_coords"] = self._value(point_coords)
        feeds["point_labels"] = self._value(point_labels)
        vals = self._run(self._tokens, feeds, list(STATE), ["iou_predictions"])
        return vals["iou_predictions"].numpy(), {k: vals[k] for k in STATE}

    def low_res_raw(self, state: dict, index: np.ndarray) -> np.ndarray:
        """(K, 4096*16, 4) float32 mask logits of the prompts `index` of a predict_iou batch, in the
        mask graph's pixel order (see raw_to_image); `mask_batch` prompts per call at most on the CPU
        provider (`CPU_MASK_BATCH`), `MASK_CHUNK` with I/O binding."""
        assert self._img is not None  # set before predict_iou, which made the state
        index = np.asarray(index, np.int64)
        step = self.MASK_CHUNK if self.io_binding else self.mask_batch or max(1, len(index))
        parts = []
        for c0 in range(0, max(1, len(index)), step):   # one call for an empty index too
            feeds = {**state, "SC": self._img["SC"], "index": self._value(index[c0:c0 + step], np.int64)}
            parts.append(self._run(self._masks, feeds, [], ["low_res_raw"])["low_res_raw"].numpy())
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def low_res_masks(self, state: dict, index: np.ndarray) -> np.ndarray:
        """(K, 4, 256, 256) float32 mask logits of the prompts `index` of a predict_iou batch."""
        return raw_to_image(np.moveaxis(self.low_res_raw(state, index), -1, 1))

    def candidate_masks(self, state: dict, prompt: np.ndarray, token: np.ndarray) -> np.ndarray:
        """(n, 256, 256) logits of candidates (prompt index in the batch, mask token 0..3); each
        prompt's masks are decoded once."""
        uniq, rows = np.unique(prompt, return_inverse=True)
        raw = self.low_res_raw(state, uniq)
        return raw_to_image(raw[rows, :, np.asarray(token)])
