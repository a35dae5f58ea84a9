"""The objects stage: a segmenter's masks -> GA3CE's P_object (per-mask median 3D points).

Every backend is a `MaskObjects`: it only says how to get masks (`masks`); the shared step
`MaskObjects.objects` back-projects each mask with the completed depth and K and keeps the
per-axis median of its points (`geometry.object_positions`, vectorised): the *measured* ones
(`DepthMap.valid`) or every pixel of the completed map (`median_pixels`); masks with fewer than
`min_points` such points are dropped and counted.

Backends: `geometric` (Open3D planes + DBSCAN, weight-free, estimators/segment/geometric.py), `oracle` (the
synthetic world's instance masks) and `mobilesam` (segment-everything, stages/objects_mobilesam.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from ..estimators.segment.geometric import GeometricParams, GeometricSegments, segment_geometric
from ..frames import FrameRef
from ..geometry import ObjectPositions, mask_pixel_counts, object_positions
from ..params import param
from .base import DepthMap, FrameObjects, ObjectsBackend
from .oracle_noise import frame_rng
from .truth import TruthParams, check_truth_file, truth_frame, truth_object_kinds


@dataclass(frozen=True, kw_only=True)
class MaskParams:
    """Parameters every mask-producing backend shares."""

    min_points: int = param(10, minimum=1)  # masks with fewer median pixels are dropped (and counted)
    median_pixels: Literal["measured", "completed"] = (
        # the pixels whose back-projections enter a mask's median: measured (the raw sensor validity)
        # or completed (every pixel with depth after hole filling); measured finds more true objects
        # within 10 cm with the geometric segmenter (docs/pipeline.md, "Object positions")
        "measured")


class MaskObjects(ObjectsBackend):
    """Base of mask-producing backends; subclasses implement `masks`."""

    def masks(self, frame: FrameRef, depth: DepthMap) -> tuple[np.ndarray, np.ndarray | None]:
        """Masks at the depth map's resolution: (M, H, W) bool (may overlap) or an (H, W) int label
        image (-1 = none), and optional scores (M,) or (n_labels,) (None: the measured fraction)."""
        raise NotImplementedError

    def placed(self, frame: FrameRef, depth: DepthMap) -> tuple[np.ndarray, np.ndarray | None, ObjectPositions]:
        """The masks at the depth map's resolution (`masks`' forms), their scores, and the positions of
        those kept (`ObjectPositions.index`: which masks): the objects' masks as `objects` places them."""
        masks, scores = self.masks(frame, depth)
        H, W = depth.depth.shape
        if masks.shape[-2:] != (H, W):  # a segmenter working at its own resolution
            if masks.ndim == 3:
                masks = np.stack([cv2.resize(m.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0
                                  for m in masks]) if len(masks) else np.zeros((0, H, W), bool)
            else:
                masks = cv2.resize(masks.astype(np.int32), (W, H), interpolation=cv2.INTER_NEAREST)
        measured = self.p.median_pixels == "measured"
        return masks, scores, object_positions(depth.depth, frame.K, masks, valid=depth.valid if measured else None,
                                               min_points=self.p.min_points)

    def objects(self, frame: FrameRef, depth: DepthMap) -> FrameObjects:
        masks, scores, pos = self.placed(frame, depth)
        measured = self.p.median_pixels == "measured"
        if scores is None:  # the fraction of the mask with measured depth, whichever pixels the median used
            n_measured = pos.n_valid if measured else mask_pixel_counts(masks, depth.valid)[pos.index]
            score = n_measured / np.maximum(pos.area, 1)
        else:
            score = np.asarray(scores, np.float32)[pos.index]
        return FrameObjects(xyz=pos.xyz.astype(np.float32), area=pos.area.astype(np.int32),
                            score=np.asarray(score, np.float32), n_dropped=int(pos.n_dropped))


class GeometricObjects(MaskObjects):
    """Weight-free segments: RANSAC planes and DBSCAN clusters of the completed depth (Open3D).
    Score: the fraction of the segment's pixels with measured depth."""

    name = "geometric"

    @dataclass(frozen=True, kw_only=True)
    class Params(MaskParams, GeometricParams):
        seed: int = 0  # RANSAC seed (combined with the frame id)

    def warm(self) -> None:
        import open3d  # noqa: F401  (about 1.5 s the first time in a process)

    def masks(self, frame: FrameRef, depth: DepthMap) -> tuple[np.ndarray, None]:
        return frame_segments(frame, depth, self.p, self.p.seed).labels, None


def frame_segments(frame: FrameRef, depth: DepthMap, p: GeometricParams, seed: int = 0) -> GeometricSegments:
    """The geometric segmenter's segments of a frame's completed depth, RANSAC seeded from (seed,
    the frame id): the same segments in every run and for every backend that asks."""
    rng_seed = int(frame_rng(seed, "objects/geometric", frame.id).integers(0, 2**31 - 1))
    return segment_geometric(depth.depth, frame.K, p, seed=rng_seed, head_box=frame.head_box)


class OracleObjects(MaskObjects):
    """The synthetic world's exact instance masks, restricted to the chosen object kinds
    (default object + furniture; structure = floor/walls/ceiling, person = the subject). Score 1."""

    name = "oracle"

    @dataclass(frozen=True, kw_only=True)
    class Params(MaskParams, TruthParams):
        kinds: tuple[Literal["object", "furniture", "structure", "person"], ...] = param(
            ("object", "furniture"), minItems=1, uniqueItems=True)  # truth instance kinds kept as objects

    def check(self) -> None:
        check_truth_file(self.p.truth)

    def masks(self, frame: FrameRef, depth: DepthMap) -> tuple[np.ndarray, np.ndarray]:
        rec = truth_frame(self.p.truth, frame.id)
        inst = np.asarray(rec.instance)
        names = truth_object_kinds(self.p.truth)
        ids = np.asarray(rec.objects.instance, np.int64)
        kinds = np.array([names[k] for k in np.asarray(rec.objects.kind, np.int64)], dtype=str)
        keep_ids = ids[np.isin(kinds, list(self.p.kinds))]
        n = int(max(inst.max(initial=-1), ids.max(initial=-1))) + 1
        lut = np.full(n + 1, -1, np.int32)  # lut[-1] (= lut[n]) stays -1: "no instance" maps to -1
        lut[keep_ids] = keep_ids
        return lut[inst.astype(np.int64)], np.ones(n, np.float32)
