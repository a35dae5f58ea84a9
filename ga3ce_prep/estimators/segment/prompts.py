"""The prompts the generator decodes on one crop: `Prompts`, single points (segment-anything's grid,
depth_prompts.py's clicks) and boxes with a point inside them, and how each kind is handed to the
decoder.

A point prompt is the click and the padding point, as the reference prompts the decoder
(mobilesam_runners.single_point_prompts). A box prompt is the click (label 1) then the box's
corners (labels 2 and 3, segment-anything's `_embed_boxes`), three points and no padding, as SAM's
ONNX example prompts a box with a point. Either kind's candidates are the decoder's
`candidate_tokens`: the multimask outputs 1..3 (on the synthetic world they keep more true objects
from box prompts than the single-mask output, token 0), or a single-mask export's one mask, which
for three points is token 0 (mobilesam_runners.exported_token). Each decoder batch holds prompts of
one kind.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import amg
from .mobilesam_runners import single_point_prompts

BOX_LABELS = np.array([1.0, 2.0, 3.0])   # the click, the box's top-left and bottom-right corners


@dataclass(frozen=True)
class Prompts:
    """Prompts in a crop's pixels, one row each.

    points: (n, 2) float64 click (x, y).
    boxes: (n, 4) float64 XYXY box around the click (inclusive maxima, as amg's boxes), NaN for
      a point alone."""

    points: np.ndarray
    boxes: np.ndarray

    @classmethod
    def at(cls, points: np.ndarray) -> Prompts:
        """Single-point prompts at points (n, 2) pixel (x, y)."""
        points = np.asarray(points, np.float64).reshape(-1, 2)
        return cls(points, np.full((len(points), 4), np.nan))

    @classmethod
    def grid(cls, grid: np.ndarray, hw: tuple[int, int]) -> Prompts:
        """The point grid (n, 2) in [0, 1]^2 (amg.build_point_grid) over a crop of (h, w) pixels."""
        return cls.at(grid * np.array(hw[::-1], np.float64))

    def __len__(self) -> int:
        return len(self.points)

    @property
    def boxed(self) -> np.ndarray:
        """(n,) bool: the box prompts."""
        return ~np.isnan(self.boxes[:, 0])

    def filter(self, keep: np.ndarray | slice) -> Prompts:
        return Prompts(self.points[keep], self.boxes[keep])

    def cat(self, other: Prompts) -> Prompts:
        return Prompts(np.concatenate([self.points, other.points]), np.concatenate([self.boxes, other.boxes]))

    def batches(self, rows: np.ndarray, size: int | None) -> list[np.ndarray]:
        """rows (k,) of these prompts -> batches of at most `size` (None: no limit), each of one kind
        (points first, then boxes), in the order of `rows` within a kind."""
        rows = np.asarray(rows, np.int64)
        out = []
        for kind in (rows[~self.boxed[rows]], rows[self.boxed[rows]]):
            step = size or max(1, len(kind))
            out += [kind[b0:b0 + step] for b0 in range(0, len(kind), step)]
        return out

    def decoder_inputs(self, hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Prompts of one kind on a crop of (h, w) pixels -> point_coords (B, N, 2) in the 1024 frame
        and point_labels (B, N): N = 2 (click, padding) for points, 3 (click, corners) for boxes."""
        boxed = self.boxed
        if boxed.any() and not boxed.all():
            raise ValueError("a decoder batch holds prompts of one kind")
        if not boxed.any():
            return single_point_prompts(amg.transform_coords(self.points, hw))
        corners = np.concatenate([self.points[:, None], self.boxes.reshape(-1, 2, 2)], axis=1)   # (B, 3, 2)
        return amg.transform_coords(corners, hw), np.tile(BOX_LABELS, (len(self), 1))
