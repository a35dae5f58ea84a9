"""`objects/mobilesam`: MobileSAM segment-everything through ONNX Runtime (estimators/mobilesam.py).

Masks come straight at the depth map's resolution (the decoder's `orig_im_size` trick); the
shared `MaskObjects.objects` turns them into per-mask median 3D points. Scores are the predicted
IoUs. Parameters (schemas/pipeline.schema.json `$defs/objects.mobilesam`): the encoder and
decoder ONNX files, `providers` ("cpu", "cuda", ... in preference order), `threads`,
`decoder_mode` ("fast" or "official") and the generator's options (points_per_side,
pred_iou_thresh, stability_score_thresh, ...).
"""
from __future__ import annotations

import numpy as np

from ..frames import FrameRef, load_rgb
from .base import DepthMap
from .objects import MaskObjects

AMG_KEYS = ("points_per_side", "points_per_batch", "pred_iou_thresh", "stability_score_thresh",
            "stability_score_offset", "box_nms_thresh", "crop_n_layers", "crop_nms_thresh",
            "crop_overlap_ratio", "crop_n_points_downscale_factor", "min_mask_region_area")


class MobileSAMObjects(MaskObjects):
    """segment-anything's automatic mask generator with the user's MobileSAM ONNX files."""

    name = "mobilesam"

    def _options(self):
        from ..estimators.amg import AmgOptions

        return AmgOptions(**{k: self.params[k] for k in AMG_KEYS if k in self.params})

    def check(self) -> None:
        """Before any work: the options, the execution providers and both files' interfaces."""
        from ..estimators.mobilesam import ImageEncoder, OfficialDecoder
        from ..estimators.onnx_runtime import resolve_providers

        self._options()
        providers = resolve_providers(self.params.get("providers", "cpu"))
        ImageEncoder(self.params["encoder"], providers, 1)
        OfficialDecoder(self.params["decoder"], providers, 1)

    def warm(self) -> None:
        self.segmenter()

    def segmenter(self):
        """The process's segmenter (sessions built once, on first use)."""
        if getattr(self, "_segmenter", None) is None:
            from ..estimators.mobilesam import MobileSamSegmenter

            self._segmenter = MobileSamSegmenter(
                self.params["encoder"], self.params["decoder"], self._options(),
                providers=self.params.get("providers", "cpu"), threads=int(self.params.get("threads", 2)),
                decoder_mode=self.params.get("decoder_mode", "fast"))
        return self._segmenter

    def __getstate__(self):  # sessions stay in the process that made them (dask workers rebuild theirs)
        state = dict(self.__dict__)
        state.pop("_segmenter", None)
        return state

    def masks(self, frame: FrameRef, depth: DepthMap) -> tuple[np.ndarray, np.ndarray]:
        seg = self.segmenter().segment(load_rgb(frame.image_path), out_size=depth.depth.shape)
        return seg.masks, seg.scores
