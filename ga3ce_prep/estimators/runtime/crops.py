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

A perspective crop (`look_at_crop`, `warp_homography`) is the MeTRAbs family's: a virtual camera
turned toward a box's centre, with its own intrinsics K', renders the square crop through the
homography K' R K^-1, so the crop is what a camera looking straight at the person would see.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from ...geometry import back_project, look_at_rotation


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


@dataclass(frozen=True)
class LookAtCrop:
    """A virtual camera at the image camera's centre, turned toward a box's centre, and its
    size x size image.

    K: (3, 3) its intrinsics K' = [[s fx, 0, size/2], [0, s fy, size/2], [0, 0, 1]] (crop pixels,
    index coordinates); R: (3, 3) camera frame -> crop camera frame, p_crop = R p_cam (its rows are
    the crop camera's axes in the camera frame; row vectors go back with `points @ R`); H: (3, 3)
    image pixels -> crop pixels, K' R K^-1 (index coordinates); size: the crop's side, pixels;
    zoom: s, crop pixels per image pixel along the turned optical axis (MeTRAbs's crop scale,
    which picks the antialiasing pyramid level, `pyramid_level`)."""

    K: np.ndarray
    R: np.ndarray
    H: np.ndarray
    size: int
    zoom: float


def look_at_crop(K: np.ndarray, box: np.ndarray, size: int, scale: float = 1.0,
                 up: tuple[float, float, float] = (0.0, -1.0, 0.0)) -> LookAtCrop:
    """The crop MeTRAbs and NLF feed their crop model: R turns the optical axis to the ray
    through the box centre, its x axis perpendicular to `up` (camera frame; (0, -1, 0): the
    image's up; `geometry.look_at_rotation`); the zoom s makes the box's larger side, measured
    between its side midpoints as the turned camera sees them, span size / scale crop pixels
    (scale > 1 leaves a margin); the principal point is at (size/2, size/2).

    K: (3, 3) image intrinsics (pixels); box: (4,) x1, y1, x2, y2 image pixels."""
    K = np.asarray(K, np.float64)
    x1, y1, x2, y2 = (float(c) for c in box)
    cx, cy = 0.5 * (x1 + x2), 0.5 * (y1 + y2)
    uv = np.array([[cx, cy], [cx, y1], [x2, cy], [cx, y2], [x1, cy]])   # centre, then top, right, bottom, left
    rays = back_project(uv[:, 0], uv[:, 1], np.ones(5), K)              # (5, 3)
    R = look_at_rotation(rays[0], np.asarray(up, np.float64)).T
    q = rays[1:] @ R.T                                                  # the side midpoints in the crop camera
    side = q[:, :2] / q[:, 2:] * np.array([K[0, 0], K[1, 1]])           # their pixels at zoom 1
    extent = max(np.linalg.norm(side[0] - side[2]), np.linalg.norm(side[1] - side[3]))
    s = size / (scale * extent)
    Kc = np.array([[s * K[0, 0], 0.0, size / 2], [0.0, s * K[1, 1], size / 2], [0.0, 0.0, 1.0]])
    return LookAtCrop(Kc, R, Kc @ R @ np.linalg.inv(K), int(size), float(s))


def _pyramid_down(image: np.ndarray) -> np.ndarray:
    """The 2x2 box average (an odd last row or column dropped): pixel i of the result is centred
    on 2i + 0.5 of the input (index coordinates)."""
    h, w = image.shape[0] // 2, image.shape[1] // 2
    return cv2.resize(image[:2 * h, :2 * w], (w, h), interpolation=cv2.INTER_AREA)  # exactly 2x: the 2x2 mean


def pyramid_level(zoom: float, levels: int = 3) -> int:
    """The antialiasing pyramid level MeTRAbs reads for a crop of zoom s (crop pixels per image
    pixel): floor(-log2 s), clipped to 0..levels-1, so level l serves shrinks by 2^l up to 2^(l+1)."""
    return int(np.clip(np.floor(-np.log2(max(float(zoom), 1e-12))), 0, levels - 1))


def warp_homography(image: np.ndarray, H: np.ndarray, size: int, zoom: float, levels: int = 3) -> np.ndarray:
    """The size x size bilinear warp of an (H, W[, C]) image by the homography H (3, 3) (image
    pixels -> output pixels, index coordinates), zeros outside the image, float32.

    Antialiasing as MeTRAbs's warp does it: the warp reads level `pyramid_level(zoom, levels)` of
    a 2x2 box-average pyramid of the whole image, zoom being the crop's scale (`LookAtCrop.zoom`;
    above 1/2: the image itself). Level l's pixel j averages image pixels 2^l j .. 2^l (j + 1) - 1,
    centred on 2^l j + (2^l - 1) / 2. Only the part of the image the output sees is pooled, cut
    on multiples of 2^l, so its blocks are the whole image's."""
    Hi = np.linalg.inv(np.asarray(H, np.float64))
    corners = np.array([[-0.5, -0.5, 1], [size - 0.5, -0.5, 1], [-0.5, size - 0.5, 1], [size - 0.5, size - 0.5, 1]])
    src = corners @ Hi.T
    h, w = image.shape[:2]
    level = pyramid_level(zoom, levels)
    x0, y0, x1, y1 = 0, 0, w, h
    if (src[:, 2] > 0).all():  # the footprint's bounding box, a margin of 2^levels pixels for the bilinear taps
        xy = src[:, :2] / src[:, 2:]
        m, b = 2 ** levels, 2 ** level
        x0, y0 = (max(0, int(np.floor(c)) - m) // b * b for c in xy.min(0))
        x1, y1 = (min(n, int(np.ceil(c)) + m) for c, n in zip(xy.max(0), (w, h)))
    if x1 <= x0 or y1 <= y0:
        return np.zeros((size, size, *image.shape[2:]), np.float32)
    img = image[y0:y1, x0:x1].astype(np.float32, copy=False)
    done = 0
    while done < level and min(img.shape[:2]) >= 2:
        img, done = _pyramid_down(img), done + 1
    f = 2.0 ** done
    up_to_image = np.array([[f, 0, x0 + (f - 1) / 2], [0, f, y0 + (f - 1) / 2], [0, 0, 1]])
    return cv2.warpPerspective(img, np.asarray(H, np.float64) @ up_to_image, (size, size), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)


__all__ = ["BORDERS", "LookAtCrop", "SquareRoi", "apply_affine", "box_roi", "continuous_to_index", "crop",
           "invert_affine", "letterbox_roi", "look_at_crop", "pyramid_level", "roi_affine", "rotation_2d",
           "warp_homography"]
