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

docs/models.md, "How the fast decoder is fast", writes the derivation out under the code's names.
Tokens are numbered as in the official decoder: 0 = IoU token, 1..4 = mask tokens (1..3 are the
"multimask" outputs), then the prompt points. Mask inputs (`has_mask_input` = 1) are not supported:
segment-everything never uses them.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import onnxruntime as ort

from .fast_decoder_graphs import (IMAGE_TENSORS, STATE, TOKEN_IMAGE_INPUTS, Derived, build_image_graph,
                                  build_mask_graph, raw_to_image)
from .fast_decoder_tokens import build_token_graph
from .fast_decoder_weights import decoder_weights
from .mobilesam import MULTIMASK_TOKENS
from .onnx_runtime import create_session

# ORT would fuse the mask graph's second bias + GELU into BiasGelu, whose CPU kernel is about 4x
# slower per element than Gelu's (onnxruntime 1.32, same outputs; docs/models.md "Speed")
MASK_GRAPH_DISABLED_OPTIMIZERS = ("BiasGeluFusion",)


class FastDecoder:
    """The restructured decoder on ONNX Runtime, a `mobilesam.MaskDecoder`: `set_image` once per image,
    then `predict_iou` for a batch of prompts and `low_res_masks` / `candidate_masks` for the prompts
    whose candidates are wanted.

    decoder_path: the official decoder ONNX (its weights are read from it).
    providers: resolved execution providers in preference order (onnx_runtime.resolve_providers).
    threads: intra-op threads of each of the three sessions."""

    # Prompts per token-graph call: 4 on CPU (measured per batch size in docs/models.md, "Speed"),
    # GPU_BATCH_SIZE on other providers.
    CPU_BATCH_SIZE = 4
    GPU_BATCH_SIZE = 64
    # Every token is decoded from the file's weights, a single-mask export's too: the generator's
    # candidates are the multimask outputs
    candidate_tokens = MULTIMASK_TOKENS

    def __init__(self, decoder_path: str | Path, providers: Sequence[str], threads: int):
        w = decoder_weights(decoder_path)
        d = Derived.from_weights(w)
        self.path = Path(decoder_path)
        self.batch_size = self.CPU_BATCH_SIZE if providers[0] == "CPUExecutionProvider" else self.GPU_BATCH_SIZE
        self._image = create_session(build_image_graph(w, d).SerializeToString(), providers, threads,
                                     "fast decoder (image)")
        self._tokens = create_session(build_token_graph(w, d).SerializeToString(), providers, threads,
                                      "fast decoder (tokens)")
        self._masks = create_session(build_mask_graph(w, d).SerializeToString(), providers, threads,
                                     "fast decoder (masks)", disabled_optimizers=MASK_GRAPH_DISABLED_OPTIMIZERS)
        self._token_outputs = [o.name for o in self._tokens.get_outputs()]
        self._img: dict[str, ort.OrtValue] | None = None

    def set_image(self, image_embeddings: np.ndarray) -> None:
        """image_embeddings (1, 256, 64, 64) float32 from the encoder."""
        emb = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(image_embeddings, np.float32))
        vals = self._image.run_with_ort_values(list(IMAGE_TENSORS), {"image_embeddings": emb})
        self._img = dict(zip(IMAGE_TENSORS, vals))

    def predict_iou(self, point_coords: np.ndarray,
                    point_labels: np.ndarray) -> tuple[np.ndarray, dict[str, ort.OrtValue]]:
        """point_coords (B, N, 2) in the 1024 input frame, point_labels (B, N) (1 fg, 0 bg, -1 padding).
        Returns (iou_predictions (B, 4) float32, state for `low_res_masks`)."""
        if self._img is None:
            raise RuntimeError("call set_image() before predict_iou()")
        feeds = {k: self._img[k] for k in TOKEN_IMAGE_INPUTS}
        feeds["point_coords"] = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(point_coords, np.float32))
        feeds["point_labels"] = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(point_labels, np.float32))
        vals = dict(zip(self._token_outputs, self._tokens.run_with_ort_values(self._token_outputs, feeds)))
        return vals["iou_predictions"].numpy(), {k: vals[k] for k in STATE}

    def low_res_raw(self, state: dict, index: np.ndarray) -> np.ndarray:
        """(K, 4096*16, 4) float32 mask logits of the prompts `index` of a predict_iou batch, in the
        mask graph's pixel order (see raw_to_image)."""
        feeds = dict(state)
        feeds["SC"] = self._img["SC"]
        feeds["index"] = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(index, np.int64))
        return self._masks.run_with_ort_values(["low_res_raw"], feeds)[0].numpy()

    def low_res_masks(self, state: dict, index: np.ndarray) -> np.ndarray:
        """(K, 4, 256, 256) float32 mask logits of the prompts `index` of a predict_iou batch."""
        return raw_to_image(np.moveaxis(self.low_res_raw(state, index), -1, 1))

    def candidate_masks(self, state: dict, prompt: np.ndarray, token: np.ndarray) -> np.ndarray:
        """(n, 256, 256) logits of candidates (prompt index in the batch, mask token 0..3); each
        prompt's masks are decoded once."""
        uniq, rows = np.unique(prompt, return_inverse=True)
        raw = self.low_res_raw(state, uniq)
        return raw_to_image(raw[rows, :, np.asarray(token)])
