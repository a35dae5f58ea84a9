"""The head crop of a head-image gaze network, as GFIE makes it (github nkuhzx/GFIE,
dataset/gfie.py and utils/infer_engine.py: the same for GFIE and CAD-120), with its recipe as
parameters so that other head-crop networks exported to ONNX can state theirs (`view/onnx`).

GFIE's recipe, step by step (`head_input`):
1. expand the head box (x1, y1, x2, y2) by k = 0.1 *in sequence*: x1 -= k |x2 - x1|, then
   x2 += k |x2 - x1| with the moved x1 (the same for y): -0.10 w left and top, +0.11 w right and
   bottom; nothing is clipped to the image (`expand_box`);
2. crop with Pillow at the truncated corners `int(x1), int(y1), int(x2), int(y2)` (toward zero:
   int(-0.5) = 0); parts outside the image are black (`head_crop`);
3. resize to 224 x 224 with Pillow's bilinear filter (torchvision's `Resize` on a PIL image; the
   aspect ratio is not kept; Pillow's bilinear widens its support when it shrinks, so it
   antialiases), in the same step;
4. RGB / 255, minus the ImageNet mean, over the ImageNet std, as (1, 3, 224, 224) float32.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from PIL import Image

from ...errors import FrameError
from ...frames import check_rgb
from ...params import param

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True, kw_only=True)
class CropParams:
    """How a head-crop network's input is made from the image and the head box; GFIE's defaults."""

    box_expand: float = param(
        # k of GFIE's sequential box expansion: x1 -= k w, then x2 += k (x2 - x1) with the
        # moved x1 (-0.10 w left/top, +0.11 w right/bottom for 0.1); 0: the box as annotated
        0.1, minimum=0)
    input_size: int = param(
        # the crop is resized (Pillow bilinear, aspect ratio not kept) to input_size x input_size pixels
        224, minimum=1)
    channels: Literal["rgb", "bgr"] = "rgb"  # channel order the network reads
    mean: tuple[float, ...] = param(
        IMAGENET_MEAN, minItems=3, maxItems=3)  # per channel (in `channels` order), subtracted from pixel / 255
    std: tuple[float, ...] = param(
        # per channel (in `channels` order), divides (pixel / 255 - mean);
        # pixels 0-255 in: mean 0, std 1/255 = 0.00392156862745098
        IMAGENET_STD, minItems=3, maxItems=3, items={"exclusiveMinimum": 0})
    layout: Literal["nchw", "nhwc"] = "nchw"  # input tensor layout: (1, 3, S, S) or (1, S, S, 3)


def expand_box(box: np.ndarray, k: float) -> np.ndarray:
    """GFIE's expansion of a head box (4,) x1, y1, x2, y2 pixels -> (4,) float64, in its order
    of operations (x1 first, then x2 from the moved x1)."""
    x1, y1, x2, y2 = (float(c) for c in box)
    x1 -= k * abs(x2 - x1)
    y1 -= k * abs(y2 - y1)
    x2 += k * abs(x2 - x1)
    y2 += k * abs(y2 - y1)
    return np.array([x1, y1, x2, y2])


def head_crop(rgb: np.ndarray, box: np.ndarray, p: CropParams = CropParams()) -> np.ndarray:
    """Steps 1-3: the (S, S, 3) uint8 RGB crop of the expanded head box (4,) x1, y1, x2, y2
    pixels of an (H, W, 3) uint8 RGB image. FrameError for a non-finite or empty box."""
    box = np.asarray(box, np.float64)
    if box.shape != (4,) or not np.all(np.isfinite(box)):
        raise FrameError(f"head box {box.tolist()} is not 4 finite pixel coordinates")
    x1, y1, x2, y2 = (int(c) for c in expand_box(box, p.box_expand))  # int(): toward zero, as GFIE
    if x2 <= x1 or y2 <= y1:
        raise FrameError(f"head box {box.tolist()} crops to nothing ({x1}, {y1}, {x2}, {y2})")
    region = Image.fromarray(check_rgb(rgb)).crop((x1, y1, x2, y2))
    return np.asarray(region.resize((p.input_size, p.input_size), Image.Resampling.BILINEAR))


def head_input(rgb: np.ndarray, box: np.ndarray, p: CropParams = CropParams()) -> np.ndarray:
    """The network input for one head: (1, 3, S, S) ("nchw") or (1, S, S, 3) ("nhwc") float32,
    (pixel / 255 - mean) / std in `p.channels` order."""
    return network_input(head_crop(rgb, box, p), p)


def network_input(image: np.ndarray, p: CropParams = CropParams()) -> np.ndarray:
    """Step 4 on an (S, S, 3) uint8 RGB image: (1, 3, S, S) ("nchw") or (1, S, S, 3) ("nhwc")
    float32, (pixel / 255 - mean) / std in `p.channels` order."""
    x: np.ndarray = image.astype(np.float32) / np.float32(255)
    if p.channels == "bgr":
        x = x[..., ::-1]
    x = (x - np.asarray(p.mean, np.float32)) / np.asarray(p.std, np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1) if p.layout == "nchw" else x)[None]


__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "CropParams", "expand_box", "head_crop", "head_input", "network_input"]
