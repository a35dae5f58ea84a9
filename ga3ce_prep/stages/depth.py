"""The depth stage: sensor depth with classical hole completion
(`estimators/depth_completion.py`, IP-Basic family), the synthetic world's exact depth, metric
monocular depth from an ONNX file (`onnx`: the user's ZoeDepth, Depth-Anything-V2-metric, ...
export; `fastdepth`: the registry's FastDepth; one runner, estimators/monodepth.py).

The raw validity mask (measured depth within [min_depth, max_depth]) is kept beside the completed
map: the head position uses measured pixels only, the object medians by default
(`objects.params.median_pixels`). For monocular depth "valid" means "predicted"
(nothing is measured): the pixels the network covered.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FrameError
from ..estimators.depth_completion import CompletionParams, complete_depth
from ..estimators.monodepth import PRESETS, MonoDepthOptions, Preset, resolve_options
from ..estimators.onnx_runtime import RuntimeParams
from ..frames import FrameRef, load_depth, load_rgb
from ..params import param
from .base import DepthBackend, DepthMap, ProcessEstimator
from .truth import TruthParams, check_truth_file, truth_frame

EXPORT_HINT = ("export it with scripts/export_monodepth.py from your ZoeDepth or Depth-Anything-V2 install "
               "(docs/models.md, \"Metric monocular depth from your ONNX file\")")


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


class MonoDepth(ProcessEstimator, DepthBackend):
    """Base of the ONNX metric monocular depth backends (estimators/monodepth.py): a model file run
    under resolved `MonoDepthOptions`. `valid` marks the predicted pixels, not measured ones: the
    object medians and the head position use them as they would sensor depth."""

    def model_file(self) -> Path:
        raise NotImplementedError

    def options(self) -> MonoDepthOptions:
        raise NotImplementedError

    def check(self) -> None:
        """Before any work: the registry files, the execution providers, and the file's interface
        (the estimator is kept: `warm()` reuses it)."""
        from ..estimators.onnx_runtime import resolve_providers

        super().check()
        resolve_providers(self.p.providers)
        self._estimator = self.build_estimator()

    def build_estimator(self):
        from ..estimators.monodepth import MonoDepthEstimator

        opt = self.options()
        fix = (f"stages.depth.params.units (now {opt.units})" if hasattr(self.p, "units")
               else "nothing here: the registry model writes metres; check the image")
        return MonoDepthEstimator(self.model_file(), opt, self.p, what=f"depth/{self.name}", fix=fix)

    def depth(self, frame: FrameRef) -> DepthMap:
        rgb = load_rgb(frame.image_path)
        dm = self.estimator().predict(rgb, frame.K).as_depth_map()
        check_resolution(frame, dm.depth.shape, f"depth/{self.name} of {frame.image_path}")
        return dm


class OnnxDepth(MonoDepth):
    """Metric monocular depth from the user's ONNX export (ZoeDepth, Depth-Anything-V2-metric and
    the like): a preset for the common exports, any of its options overridden (docs/models.md)."""

    name = "onnx"

    @dataclass(frozen=True, kw_only=True)
    class Params(MonoDepthOptions, RuntimeParams):
        model: Path = param(file="model", hint=EXPORT_HINT)  # the ONNX export (one image input, a metric depth output)
        preset: Preset = param()  # the export's preprocessing and output: zoedepth | depth-anything-v2-metric-indoor | depth-anything-v2-metric-outdoor | fastdepth | custom (nothing assumed); the options below override it

    def model_file(self) -> Path:
        return self.p.model

    def options(self) -> MonoDepthOptions:
        return resolve_options(self.p.preset, self.p)

    def provenance(self) -> dict[str, Any]:
        """The options that ran: the preset with the pipeline's overrides."""
        return {"options": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self.options()).items()}}


class FastDepth(MonoDepth):
    """FastDepth (NYU-Depth-v2) on the registry's ONNX file: the `fastdepth` preset, metric depth of
    the largest centred 4:3 crop, rescaled for the frame's focal length; 0 outside the crop. The
    depth is coarse (blurry edges, close-ups collapse to about 1-1.5 m): docs/models.md."""

    name = "fastdepth"

    @dataclass(frozen=True, kw_only=True)
    class Params(RuntimeParams):
        """RuntimeParams: ONNX Runtime providers and threads."""

    def registry_keys(self) -> tuple[str, ...]:
        return ("fastdepth",)

    def model_file(self) -> Path:
        from ..registry_models import model_path

        return model_path("fastdepth")

    def options(self) -> MonoDepthOptions:
        return PRESETS["fastdepth"]
