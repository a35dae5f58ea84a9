"""The depth stage: sensor depth with classical hole completion
(`estimators/depth_completion.py`, IP-Basic family), the synthetic world's exact depth, or
FastDepth's coarse monocular depth (`estimators/fastdepth.py`, a registry model).

The raw validity mask (measured depth within [min_depth, max_depth]) is kept beside the completed
map: object medians and the head position use measured pixels only. For monocular depth "valid"
means "predicted" (nothing is measured): the pixels the network covered.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FrameError
from ..estimators.depth_completion import CompletionParams, complete_depth
from ..estimators.onnx_runtime import RuntimeParams
from ..frames import FrameRef, load_depth, load_rgb
from .base import DepthBackend, DepthMap, ProcessEstimator
from .truth import TruthParams, check_truth_file, truth_frame


def check_resolution(frame: FrameRef, shape: tuple[int, ...], what: str) -> None:
    """FrameError unless an (H, W) map matches the frame's image size (when the size is known)."""
    W, H = frame.image_size
    if W and H and tuple(shape) != (H, W):
        raise FrameError(f"{what} is {shape[1]}x{shape[0]} but the image is {W}x{H}; "
                         "depth must be registered to the RGB image at the same resolution")


class SensorDepth(DepthBackend):
    """Load the sensor depth the adapter points to (units per adapter) and complete its holes."""

    name = "sensor"

    Params = CompletionParams

    def depth(self, frame: FrameRef) -> DepthMap:
        if frame.depth_path is None:
            raise FrameError(f"frame {frame.id} has no depth map; this dataset needs a depth estimator "
                             "(stages.depth.backend) instead of 'sensor'")
        raw = load_depth(frame.depth_path, frame.depth_scale)
        check_resolution(frame, raw.shape, f"depth {frame.depth_path}")
        dm = complete_depth(raw, self.p)
        if not dm.valid.any():
            raise FrameError(f"depth {frame.depth_path} has no valid pixel in "
                             f"[{self.p.min_depth}, {self.p.max_depth}] m (wrong units? check depth_scale)")
        return dm


class OracleDepth(DepthBackend):
    """The synthetic world's exact depth (truth side-car): every rendered pixel is valid."""

    name = "oracle"
    Params = TruthParams

    def check(self) -> None:
        check_truth_file(self.p.truth)

    def depth(self, frame: FrameRef) -> DepthMap:
        d = np.asarray(truth_frame(self.p.truth, frame.id).depth, np.float32)
        check_resolution(frame, d.shape, "truth depth")
        valid = np.isfinite(d) & (d > 0)
        return DepthMap(np.where(valid, d, 0).astype(np.float32), valid)


class FastDepth(ProcessEstimator, DepthBackend):
    """FastDepth (NYU-Depth-v2) on the registry's ONNX file: metric depth of the largest centred 4:3
    crop, rescaled for the frame's focal length; 0 outside the crop.

    `valid` marks the predicted pixels (the crop), not measured ones: the object medians and the
    head position use them as they would sensor depth. The depth is coarse (blurry edges, close-ups
    collapse to about 1-1.5 m): docs/models.md."""

    name = "fastdepth"

    @dataclass(frozen=True, kw_only=True)
    class Params(RuntimeParams):
        """RuntimeParams: ONNX Runtime providers and threads."""

    def registry_keys(self) -> tuple[str, ...]:
        return ("fastdepth",)

    def check(self) -> None:
        from ..estimators.onnx_runtime import resolve_providers

        super().check()
        resolve_providers(self.p.providers)

    def build_estimator(self):
        from ..estimators.fastdepth import FastDepthEstimator
        from ..registry_models import model_path

        return FastDepthEstimator(model_path("fastdepth"), self.p)

    def depth(self, frame: FrameRef) -> DepthMap:
        rgb = load_rgb(frame.image_path)
        dm = self.estimator().predict(rgb, frame.K).as_depth_map()
        check_resolution(frame, dm.depth.shape, f"FastDepth of {frame.image_path}")
        return dm
