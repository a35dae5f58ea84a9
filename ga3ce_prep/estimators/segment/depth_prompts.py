"""Segment-everything prompted by depth (`objects.params.prompts: depth`): the generator's prompts
from the geometric segmenter's segments (geometric.py) instead of segment-anything's 32x32 grid.

The rule, per frame, on the segments of `segment_geometric` at its defaults (each DBSCAN cluster and
each connected piece of a RANSAC plane; the subject's segment removed):
1. One click per segment, at the segment's pixel nearest its centroid (on the segment, whatever its
   shape); with `prompt_boxes`, the click goes with the segment's pixel box (a box prompt).
2. The points of a `prompt_grid` x `prompt_grid` grid that fall on a cluster: a cluster often holds
   several objects standing side by side (a table's clutter within DBSCAN's 6 cm), one click finds
   one of them.
3. With `prompt_sparse_grid` n > 0, the points of an n x n grid on pixels no segment claims, for
   what depth misses (no depth of their own, far).
Segments and prompts are in the image's pixels (the segments, at the depth map's resolution, are
scaled). Order: the clicks (boxes) in label order, then the grid points.

Why this rule (docs/studies/2026-12-06-segment-everything-prompted-by-depth.md): decoding costs
about 11 ms a prompt on 2 cores besides the encoder's 0.6 s, so a second and a half a frame holds
about 65 prompts. Clicks find more true objects than boxes of the same segments, with fewer
spurious masks (a box round a cluster of several objects is decoded as the group); the grid's
points on clusters add the objects beside the clicked one; a sparse grid elsewhere adds walls and
floor, not objects.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ...params import param
from . import amg
from .geometric import GeometricSegments
from .prompts import Prompts


@dataclass(frozen=True, kw_only=True)
class DepthPromptParams:
    """What the generator prompts: segment-anything's grid or the depth rule (module docstring)."""

    prompts: Literal["grid", "depth"] = (
        # grid: segment-anything's points_per_side x points_per_side grid (the paper's); depth: a click per
        # segment of the geometric segmenter and grid points on its clusters (full-image crop only;
        # docs/models/segment-everything.md, "Prompts from depth")
        "grid")
    prompt_grid: int = param(
        # depth: points per side of the grid whose points on a cluster are prompts (0: none)
        16, minimum=0)
    prompt_boxes: bool = False  # depth: each segment's click goes with its box (a box prompt)
    prompt_sparse_grid: int = param(
        # depth: points per side of a grid whose points on no segment are prompts (0: none)
        0, minimum=0)


def depth_prompts(segments: GeometricSegments, image_hw: tuple[int, int], p: DepthPromptParams) -> Prompts:
    """The frame's prompts (module docstring) in image pixels: segments' labels (h, w) at any
    resolution, image_hw = (H, W) of the image."""
    labels = np.asarray(segments.labels)
    h, w = labels.shape
    H, W = image_hw
    scale = np.array([W / w, H / h])                                                  # image px per label px
    boxes, clicks = segment_boxes(labels)
    # a label pixel (x, y) covers [x, x + 1) x scale image px: its centre at (x + 0.5) * scale - 0.5
    points = (clicks + 0.5) * scale - 0.5
    if p.prompt_boxes:
        lo = boxes[:, :2] * scale
        hi = (boxes[:, 2:] + 1) * scale - 1
        prompts = Prompts(points, np.concatenate([lo, hi], axis=1))
    else:
        prompts = Prompts.at(points)
    cluster = np.r_[~np.asarray(segments.plane, bool), False]   # per label, and label -1 (the last): none
    for side, on in ((p.prompt_grid, lambda lab: cluster[lab]), (p.prompt_sparse_grid, lambda lab: lab < 0)):
        if side:
            grid = amg.build_point_grid(side) * np.array([W, H], np.float64)             # (g, 2) image px
            cell = np.clip((grid / scale).astype(np.int64), 0, [w - 1, h - 1])          # their label pixels
            prompts = prompts.cat(Prompts.at(grid[on(labels[cell[:, 1], cell[:, 0]])]))
    return prompts


def segment_boxes(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A label image (h, w) int, -1 = none -> per present label, in label order: its pixel box (k, 4)
    float64 XYXY (inclusive maxima) and its click (k, 2) float64 (x, y), the segment's pixel nearest
    its centroid."""
    ys, xs = np.nonzero(labels >= 0)
    lab = labels[ys, xs]
    order = np.lexsort((xs, ys, lab))   # by label (pixels in raster order within one)
    ys, xs, lab = ys[order], xs[order], lab[order]
    present, start, count = np.unique(lab, return_index=True, return_counts=True)
    if not len(present):
        return np.zeros((0, 4)), np.zeros((0, 2))
    box = np.stack([np.minimum.reduceat(xs, start), np.minimum.reduceat(ys, start),
                    np.maximum.reduceat(xs, start), np.maximum.reduceat(ys, start)], axis=1).astype(np.float64)
    centre = np.stack([np.add.reduceat(xs, start), np.add.reduceat(ys, start)], axis=1) / count[:, None]
    group = np.repeat(np.arange(len(present)), count)
    d2 = (xs - centre[group, 0]) ** 2 + (ys - centre[group, 1]) ** 2
    nearest = np.lexsort((d2, group))[start]   # the first pixel of each group by distance (ties: raster order)
    return box, np.stack([xs[nearest], ys[nearest]], axis=1).astype(np.float64)
