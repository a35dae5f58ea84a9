"""`objects/mobilesam`: MobileSAM segment-everything through ONNX Runtime (estimators/mobilesam.py).

Masks come straight at the depth map's resolution (the decoder's `orig_im_size` trick); the
shared `MaskObjects.objects` turns them into per-mask median 3D points. Scores are the predicted
IoUs.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..estimators.mobilesam import SegmenterOptions
from ..frames import FrameRef, load_rgb
from ..params import param
from .base import DepthMap, ProcessEstimator
from .objects import MaskObjects, MaskParams

EXPORT_HINT = "make it with `ga3ce-prep export-mobilesam --out DIR` from a MobileSAM checkpoint"


class MobileSAMObjects(ProcessEstimator, MaskObjects):
    """segment-anything's automatic mask generator with the user's MobileSAM ONNX files."""

    name = "mobilesam"

    @dataclass(frozen=True, kw_only=True)
    class Params(MaskParams, SegmenterOptions):
        encoder: Path = param(file="model", hint=EXPORT_HINT)  # MobileSAM image encoder ONNX
        decoder: Path = param(file="model", hint=EXPORT_HINT)  # MobileSAM mask decoder ONNX

    def check(self) -> None:
        """Before any work: the execution providers and both files' interfaces."""
        from ..estimators.mobilesam import ImageEncoder, OfficialDecoder
        from ..estimators.onnx_runtime import resolve_providers

        providers = resolve_providers(self.p.providers)
        ImageEncoder(self.p.encoder, providers, 1)
        OfficialDecoder(self.p.decoder, providers, 1)

    def build_estimator(self):
        from ..estimators.mobilesam import MobileSamSegmenter

        return MobileSamSegmenter(self.p.encoder, self.p.decoder, self.p)

    def masks(self, frame: FrameRef, depth: DepthMap) -> tuple[np.ndarray, np.ndarray]:
        seg = self.estimator().segment(load_rgb(frame.image_path), out_size=depth.depth.shape)
        return seg.masks, seg.scores
