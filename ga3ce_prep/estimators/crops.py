"""Square, optionally rotated crops of an image onto a model's input tensor, as 2x3 affines.

MediaPipe's detectors and landmark models (BlazeFace, face mesh, BlazePose) all read a square
region of the image, possibly rotated, resized to their input size; their outputs come back to the
image through the inverse affine. One convention everywhere here: **pixel-index coordinates**
(OpenCV's and `geometry.depth_to_points`'): pixel (i, j) has its centre at x = j, y = i. A model
that reports "continuous" coordinates (0 at the left edge of the first pixel, the input size at
the right edge of the last) is converted with `continuous_to_index` before the inverse affine.

Parts of a crop outside the image are padded with zeros (the letterbox: the aspect ratio is kept
and what the image lacks is filled; `letterbox_roi` is the whole image's), or with the image's
border pixels repeated (BlazePose's landmark crop).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np


@dataclass(frozen=True)
class SquareRoi:
    """A square region of an image: centre (2,) (x, y) image pixels (index coordinates), side
    `size` image pixels, and `angle` radians: the region's x axis points along (cos a, sin a) in
    the image (y down), i.e. a positive angle turns it clockwise on screen."""

    center: np.ndarray
    size: float
    angle: float = 0.0


def rotation_2d(angle: float) -> np.ndarray:
    """(2, 2) rotation by `angle` radians in image axes (x right, y down: a positive angle turns
    clockwise on screen). R(angle) maps a ROI's axes to the image's."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def roi_affine(roi: SquareRoi, out_size: int) -> np.ndarray:
    """The (2, 3) float64 affine taking image pixels to the pixels of an out_size x out_size crop
    of `roi` (both index coordinates): crop = L @ image + t, with L = s R(-angle), s = out_size /
    roi.size. The ROI's centre lands on the crop's centre, (out_size - 1) / 2."""
    L = (out_size / float(roi.size)) * rotation_2d(roi.angle).T
    t = 0.5 * (out_size - 1) - L @ np.asarray(roi.center, np.float64)
    return np.concatenate([L, t[:, None]], axis=1)


def invert_affine(M: np.ndarray) -> np.ndarray:
    """The inverse of a (2, 3) affine, (2, 3) float64."""
    L = np.asarray(M, np.float64)[:, :2]
    Li = np.linalg.inv(L)
    return np.concatenate([Li, -(Li @ np.asarray(M, np.float64)[:, 2])[:, None]], axis=1)


def apply_affine(M: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (..., 2) through a (2, 3) affine -> (..., 2) float64."""
    p = np.asarray(points, np.float64)
    return p @ M[:, :2].T + M[:, 2]


def continuous_to_index(points: np.ndarray) -> np.ndarray:
    """(..., 2) continuous pixel coordinates (edges at integers) -> index coordinates (centres at
    integers): minus half a pixel."""
    return np.asarray(points, np.float64) - 0.5


BORDERS = {"zero": cv2.BORDER_CONSTANT, "replicate": cv2.BORDER_REPLICATE}


def crop(image: np.ndarray, roi: SquareRoi, out_size: int,
         border: Literal["zero", "replicate"] = "zero") -> tuple[np.ndarray, np.ndarray]:
    """The out_size x out_size bilinear crop of `roi` from an (H, W[, C]) image (same dtype), and
    its image->crop affine (2, 3). Outside the image: zeros, or the nearest border pixel
    ("replicate"). Downscaling by more than about 2 aliases (bilinear taps, no prefilter); the
    models' crops of a face or head stay near 1x-3x, the letterbox of a 1920-wide frame to 224
    does not (the person detector was trained on such inputs)."""
    M = roi_affine(roi, out_size)
    out = cv2.warpAffine(image, M, (out_size, out_size), flags=cv2.INTER_LINEAR, borderMode=BORDERS[border],
                         borderValue=0)
    return out, M


def box_roi(box: np.ndarray, scale: float) -> SquareRoi:
    """The upright square around a box (x1, y1, x2, y2) image pixels: same centre, side `scale` x
    the box's longer side (the letterbox of the enlarged box)."""
    x1, y1, x2, y2 = (float(c) for c in box)
    return SquareRoi(np.array([0.5 * (x1 + x2), 0.5 * (y1 + y2)]), scale * max(x2 - x1, y2 - y1), 0.0)


def letterbox_roi(hw: tuple[int, int]) -> SquareRoi:
    """The upright square around a whole (H, W) image (its pixels' outer edges): cropping it
    letterboxes the image, the aspect ratio kept, centred, bars where the image is shorter."""
    h, w = hw
    return box_roi(np.array([-0.5, -0.5, w - 0.5, h - 0.5]), 1.0)


__all__ = ["BORDERS", "SquareRoi", "apply_affine", "box_roi", "continuous_to_index", "crop", "invert_affine",
           "letterbox_roi", "roi_affine", "rotation_2d"]
