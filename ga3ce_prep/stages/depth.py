"""The depth stage: sensor depth with classical hole completion
(`estimators/depth/completion.py`, IP-Basic family), the synthetic world's exact depth, metric
monocular depth from an ONNX file (`onnx`: the user's ZoeDepth, Depth-Anything-V2-metric, ...
export; `fastdepth`: the registry's FastDepth; one runner, estimators/depth/monodepth.py), or depth maps
computed elsewhere (`precomputed`).

The raw validity mask (measured depth within [min_depth, max_depth]) is kept beside the completed
map: the head position uses measured pixels only, the object medians by default
(`objects.params.median_pixels`). For monocular and precomputed depth "valid" means "predicted"
(nothing is measured): the pixels the network covered, or the file gives.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FrameError
from ..estimators.depth.completion import CompletionParams, complete_depth
from ..estimators.depth.monodepth import PRESETS, MonoDepthOptions, Preset, resolve_options
from ..estimators.runtime.onnx_runtime import RuntimeParams
from ..frames import FrameRef, load_depth, load_rgb
from ..params import param
from ..units import DISTANCE_RANGE_M, LENGTH_UNITS, Units, check_plausible, to_metres, units_name
from .base import DepthBackend, DepthMap, ProcessEstimator
from .precomputed import precomputed_table
from .truth import TruthParams, check_truth_file, truth_frame

EXPORT_HINT = ("export it with scripts/export_monodepth.py from your ZoeDepth or Depth-Anything-V2 install "
               "(docs/models/depth.md, \"Exporting ZoeDepth or Depth-Anything-V2-metric\")")


def check_resolution(frame: FrameRef, shape: tuple[int, ...], what: str) -> None:
    """FrameError unless an (H, W) map matches the frame's image size (when the size is known)."""
    W, H = frame.image_size
    if W and H and tuple(shape) != (H, W):
        raise FrameError(f"{what} is {shape[1]}x{shape[0]} but the image is {W}x{H}; "
                         "depth must be registered to the RGB image at the same resolution")


class SensorDepth(DepthBackend):
    """Load the sensor depth the adapter points to (units per adapter, recorded in the dataset's
    provenance), refuse a map whose median is not a plausible distance (`units.DISTANCE_RANGE_M`:
    this file is in another unit), and complete its holes."""

    name = "sensor"
    version = "2"  # 2: a map with an implausible median fails (a file in another unit)

    Params = CompletionParams

    def depth(self, frame: FrameRef) -> DepthMap:
        if frame.depth_path is None:
            raise FrameError(f"frame {frame.id} has no depth map in the dataset's layout; this dataset needs a depth "
                             "estimator (stages.depth.backend) instead of 'sensor'")
        raw = load_depth(frame.depth_path, frame.depth_scale)
        check_resolution(frame, raw.shape, f"depth {frame.depth_path}")
        if (raw > 0).any():
            check_plausible(raw, raw / np.float32(frame.depth_scale), units_name(frame.depth_scale), DISTANCE_RANGE_M,
                            f"depth {frame.depth_path}", "the dataset's depth units (dataset.options) or re-export "
                            "this file in them", candidates=LENGTH_UNITS)
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
    """Base of the ONNX metric monocular depth backends (estimators/depth/monodepth.py): a model file run
    under resolved `MonoDepthOptions`. `valid` marks the predicted pixels, not measured ones: the
    object medians and the head position use them as they would sensor depth."""

    def model_file(self) -> Path:
        raise NotImplementedError

    def options(self) -> MonoDepthOptions:
        raise NotImplementedError

    def check(self) -> None:
        """Before any work: the registry files, the execution providers, and the file's interface
        (the estimator is kept: `warm()` reuses it)."""
        from ..estimators.runtime.onnx_runtime import resolve_providers

        super().check()
        resolve_providers(self.p.providers)
        self._estimator = self.build_estimator()

    def build_estimator(self):
        from ..estimators.depth.monodepth import MonoDepthEstimator

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
    the like): a preset for the common exports, any of its options overridden
    (docs/models/depth.md, "Presets")."""

    name = "onnx"

    @dataclass(frozen=True, kw_only=True)
    class Params(MonoDepthOptions, RuntimeParams):
        model: Path = param(file="model", hint=EXPORT_HINT)  # the ONNX export (one image input, a metric depth output)
        preset: Preset = param(
            # the export's preprocessing and output: zoedepth | depth-anything-v2-metric-indoor |
            # depth-anything-v2-metric-outdoor | fastdepth | custom (nothing assumed); the options below override it
        )

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
    depth is coarse (blurry edges, close-ups collapse to about 1-1.5 m):
    docs/models/depth.md, "FastDepth (`depth: fastdepth`)"."""

    name = "fastdepth"

    @dataclass(frozen=True, kw_only=True)
    class Params(RuntimeParams):
        """RuntimeParams: ONNX Runtime providers and threads."""

    def registry_keys(self) -> tuple[str, ...]:
        return ("fastdepth",)

    def model_file(self) -> Path:
        from ..weights.registry import model_path

        return model_path("fastdepth")

    def options(self) -> MonoDepthOptions:
        return PRESETS["fastdepth"]


class PrecomputedDepth(DepthBackend):
    """Depth maps computed elsewhere, keyed by frame id (stages/precomputed.py layout: frame_id (N,)
    str, depth (N, H, W) in `units`, at each frame's image resolution). `valid` = the pixels with a
    positive finite depth. A frame missing from the file fails alone; a frame whose median depth is
    implausible is refused (the first frame's before any work)."""

    name = "precomputed"

    @dataclass(frozen=True, kw_only=True)
    class Params:
        file: Path = param(
            # HDF5/npz: frame_id (N,) str, depth (N, H, W) at the image resolution
            file="data", hint="write it with the layout in docs/pipeline.md (frame_id, depth)")
        units: Units = (
            # the stored depth's unit: m, cm, mm, or inverse_m (1 / metres);
            # 0, negative and non-finite values are unknown
            "m")
        plausible_depth: tuple[float, ...] = param(
            # metres [min, max]: a frame whose median depth is outside is refused (wrong units?)
            (0.1, 100.0), minItems=2, maxItems=2, items={"exclusiveMinimum": 0})

    def _table(self):
        return precomputed_table(self.p.file, "depth", ("H", "W"), "stages.depth.params.file")

    def _metres(self, frame_id: str, raw: np.ndarray) -> np.ndarray:
        """The frame's stored depth in metres (0 = unknown); FrameError when implausible."""
        d = to_metres(np.where(np.isfinite(raw), raw, 0), self.p.units)
        check_plausible(d, raw, self.p.units, self.p.plausible_depth, f"depth of frame {frame_id} in {self.p.file}",
                        f"stages.depth.params.units (now {self.p.units})")
        d[(d < 0) | (d > self.p.plausible_depth[1])] = 0
        return d

    def check(self) -> None:
        """Before any work: the file's layout, and the units on the first frame with a positive depth
        (among the first ten)."""
        self._table().check_first(self._metres, lambda raw: bool(np.any(raw > 0)))

    def depth(self, frame: FrameRef) -> DepthMap:
        d = self._metres(frame.id, self._table().get(frame.id))
        check_resolution(frame, d.shape, f"depth of frame {frame.id} in {self.p.file}")
        return DepthMap(d, d > 0)
