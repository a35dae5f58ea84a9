"""The torch runtime of `MobileSamSegmenter` (`runtime: torch`): MobileSAM's own modules, read
straight from the official checkpoint (`mobile_sam.pt`, the file the ONNX export starts from), on
the CPU or a CUDA device.

The model is the official `vit_t` (MobileSAM's `mobile_sam` package, mobilesam_code.py) with the
checkpoint's state dict loaded strictly, then `eval()` (after loading: TinyViT caches its attention
biases in eval()). `TorchEncoder` feeds the image encoder the ONNX path's input (Pillow resize,
normalise, pad: mobilesam_runners.resize_longest_side, normalise_and_pad); `TorchDecoder` is a
`mobilesam_runners.MaskDecoder`: the prompt encoder on the generator's (point, padding point) prompts as
the ONNX export embeds them, and the mask decoder's `predict_masks` (all 4 tokens), so the
generator's candidates, filters, NMS, crops and reuse are those of the ONNX path. `open_torch`
opens both for `MobileSamSegmenter.from_checkpoint`.

Batching: on CUDA the generator hands all prompts of a crop to one `predict_iou` (`batch_size`
None), which runs them through the decoder `CUDA_CHUNK` at a time and keeps their low-resolution
logits (B, 4, 256, 256) on the device; only the IoU predictions (B, 4) and the passing candidates'
logits (n, 256, 256) come back to the host. On the CPU, batches of `CPU_BATCH_SIZE` prompts.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from ...errors import ConfigError, ModelFileError
from .amg import MULTIMASK_TOKENS
from .mobilesam_code import FIX
from .mobilesam_runners import check_rgb, normalise_and_pad, resize_longest_side

if TYPE_CHECKING:
    import torch


def check_device(device: str) -> None:
    """ConfigError when `device` is neither cpu nor cuda, or is cuda without a CUDA device in this torch."""
    import torch

    if device not in ("cpu", "cuda"):
        raise ConfigError(f"device must be cpu or cuda, got {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device: cuda, but this torch ({torch.__version__}) sees no CUDA device: use device: cpu, "
                          "or install a CUDA build of torch (https://pytorch.org/get-started/locally/)")


def load_sam(checkpoint: str | Path, device: Literal["cpu", "cuda"] = "cpu"):
    """MobileSAM's `vit_t` Sam module with the checkpoint's weights, in eval mode on `device`.
    ModelFileError naming the checkpoint when it is missing or does not fit the model; ConfigError
    naming it and the fix when MobileSAM's code is not installed."""
    import torch

    from .mobilesam_code import import_mobile_sam

    path = Path(checkpoint)
    if not path.is_file():
        raise ModelFileError(f"MobileSAM checkpoint not found: {path} (runtime: torch reads the official weights, "
                             "weights/mobile_sam.pt of github.com/ChaoningZhang/MobileSAM; set checkpoint)")
    check_device(device)
    try:
        mobile_sam = import_mobile_sam()
    except ImportError as e:
        raise ConfigError(f"runtime: torch reads {path} with MobileSAM's model code, which does not import here "
                          f"({e}); install it: {FIX}") from e
    sam = mobile_sam.sam_model_registry["vit_t"](checkpoint=None)
    try:
        state = torch.load(str(path), map_location="cpu", weights_only=True)
        sam.load_state_dict(state, strict=True)
    except Exception as e:  # torch raises RuntimeError, pickle errors, ...
        raise ModelFileError(f"MobileSAM checkpoint {path} does not load into MobileSAM's vit_t model: {e}") from e
    sam.eval()   # after loading: TinyViT caches its attention biases here
    return sam.to(device)


class TorchEncoder:
    """The checkpoint's image encoder: `embed` as mobilesam_runners.ImageEncoder's.

    sam: the module `load_sam` returns; device: where it lives."""

    def __init__(self, sam, device: str):
        self.sam, self.device = sam, device

    def embed(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> image_embeddings (1, 256, 64, 64) float32 (host)."""
        import torch

        x = normalise_and_pad(resize_longest_side(check_rgb(rgb)))
        with torch.inference_mode():
            return self.sam.image_encoder(torch.from_numpy(x).to(self.device)).float().cpu().numpy()


class TorchDecoder:
    """The checkpoint's prompt encoder and mask decoder, a `mobilesam_runners.MaskDecoder` (multimask:
    candidates are tokens 1..3). The state of a `predict_iou` batch is its low-resolution logits
    (B, 4, 256, 256) on the device.

    sam: the module `load_sam` returns; device: where it lives."""

    CPU_BATCH_SIZE = 64   # prompts per predict_iou call on the CPU (the state: 16 MB per 16 prompts)
    CUDA_CHUNK = 128      # prompts per decoder forward on CUDA (bounds activation memory)
    candidate_tokens = MULTIMASK_TOKENS

    def __init__(self, sam, device: str):
        self.sam, self.device = sam, device
        self.batch_size: int | None = None if device == "cuda" else self.CPU_BATCH_SIZE
        self.chunk = self.CUDA_CHUNK if device == "cuda" else self.CPU_BATCH_SIZE
        self._emb: torch.Tensor | None = None
        self._pe: torch.Tensor | None = None

    def set_image(self, image_embeddings: np.ndarray) -> None:
        """image_embeddings (1, 256, 64, 64) float32."""
        import torch

        with torch.inference_mode():
            self._emb = torch.from_numpy(np.ascontiguousarray(image_embeddings, np.float32)).to(self.device)
            self._pe = self.sam.prompt_encoder.get_dense_pe()

    def predict_iou(self, point_coords: np.ndarray, point_labels: np.ndarray):
        """point_coords (B, N, 2) in the 1024 frame, point_labels (B, N) (1 fg, 0 bg, -1 padding, 2 and 3 a
        box's corners; the generator passes each point with its padding point, and a box as its click
        and corners, as the ONNX export is prompted) ->
        (iou_predictions (B, 4) float32, the low-res logits (B, 4, 256, 256) on the device)."""
        import torch

        if self._emb is None:
            raise RuntimeError("call set_image() before predict_iou()")
        pe, dec = self.sam.prompt_encoder, self.sam.mask_decoder
        coords = torch.from_numpy(np.asarray(point_coords, np.float32)).to(self.device)
        labels = torch.from_numpy(np.asarray(point_labels, np.float32)).to(self.device)
        ious, lows = [], []
        with torch.inference_mode():
            for c0 in range(0, len(coords), self.chunk):
                c, lab = coords[c0:c0 + self.chunk], labels[c0:c0 + self.chunk]
                sparse = pe._embed_points(c, lab, pad=False)                          # (b, N, 256)
                for corner in (2, 3):   # the box corners' embeddings (_embed_boxes'), as the ONNX export adds them
                    sparse = sparse + (lab == corner)[..., None] * pe.point_embeddings[corner].weight
                dense = pe.no_mask_embed.weight.reshape(1, -1, 1, 1).expand(len(c), -1, *pe.image_embedding_size)
                low, iou = dec.predict_masks(self._emb, self._pe, sparse, dense)      # (b, 4, 256, 256), (b, 4)
                lows.append(low)
                ious.append(iou)
            low = lows[0] if len(lows) == 1 else torch.cat(lows)
            iou = ious[0] if len(ious) == 1 else torch.cat(ious)
        return iou.float().cpu().numpy(), low

    def low_res_masks(self, state, index: np.ndarray) -> np.ndarray:
        """(K, 4, 256, 256) float32 logits of the prompts `index` of the batch."""
        import torch

        return state[torch.as_tensor(np.asarray(index, np.int64), device=state.device)].float().cpu().numpy()

    def candidate_masks(self, state, prompt: np.ndarray, token: np.ndarray) -> np.ndarray:
        """(n, 256, 256) float32 logits of candidates (prompt index in the batch, mask token 0..3),
        gathered on the device."""
        import torch

        p = torch.as_tensor(np.asarray(prompt, np.int64), device=state.device)
        t = torch.as_tensor(np.asarray(token, np.int64), device=state.device)
        return state[p, t].float().cpu().numpy()


def open_torch(checkpoint: str | Path, device: Literal["cpu", "cuda"],
               threads: int) -> tuple[TorchEncoder, TorchDecoder]:
    """The torch runtime's runners on `device`: `load_sam` (ModelFileError / ConfigError naming the
    checkpoint and the fix), then torch's intra-op threads set process-wide to `threads`."""
    import torch

    sam = load_sam(checkpoint, device)
    torch.set_num_threads(threads)
    return TorchEncoder(sam, device), TorchDecoder(sam, device)
