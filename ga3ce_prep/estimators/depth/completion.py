"""Classical depth completion (IP-Basic family) for Kinect-style sensor depth.

`complete_depth` follows IP-Basic's `fill_in_fast` (Ku et al. 2018; kujason/ip_basic),
written for Kinect-style depth: invert valid depths (so dilation prefers nearer surfaces), dilate
with a 5x5 diamond, close with a 5x5 square, fill what is still empty from a 7x7 dilation, median
blur, blur, invert back. Differences from the LiDAR original, each a parameter:

- `extrapolate` (default off): IP-Basic's column-top extension assumes LiDAR, which has no
  returns near the top of the image; Kinect-style depth does not need it.
- `keep_valid` (default on): measured pixels keep their sensor value; only holes are filled (the
  dilation would otherwise pull object edges toward the nearer surface).
- `large_holes: pushpull` (default): holes wider than the 7x7 fill reaches (IP-Basic leaves ~5%
  unfilled without extrapolation) are filled by a push-pull pyramid (valid-weighted averages of
  ever coarser levels, pulled back down), so the completed map has no zeros inside the image.

The raw validity mask (measured depth within [min_depth, max_depth]) is kept beside the completed
map: object medians and the head position use measured pixels only.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from ...frames import DepthMap
from ...params import param


@dataclass(frozen=True, kw_only=True)
class CompletionParams:
    """Parameters of `complete_depth`."""

    min_depth: float = param(0.1, minimum=0)  # metres; nearer sensor values count as unknown
    max_depth: float = param(
        # metres; farther sensor values count as unknown (at most 64: the morphology's 16-bit millimetres)
        10.0, exclusiveMinimum=0, maximum=64)
    extrapolate: bool = False  # IP-Basic's column-top extension and 31x31 fill (LiDAR); off for Kinect-style depth
    blur: Literal["gaussian", "bilateral", "none"] = "gaussian"  # blur of filled pixels (IP-Basic step 7)
    keep_valid: bool = True  # measured pixels keep their sensor value; only holes are filled
    large_holes: Literal["pushpull", "none"] = "pushpull"  # fallback for holes the 7x7 fill does not reach
    bilateral_sigma_color: float = param(0.1, exclusiveMinimum=0)  # metres, blur: bilateral
    bilateral_sigma_space: float = param(2.0, exclusiveMinimum=0)  # pixels, blur: bilateral


DIAMOND_5 = np.array([[0, 0, 1, 0, 0],
                      [0, 1, 1, 1, 0],
                      [1, 1, 1, 1, 1],
                      [0, 1, 1, 1, 0],
                      [0, 0, 1, 0, 0]], np.uint8)
FULL_5 = np.ones((5, 5), np.uint8)
FULL_7 = np.ones((7, 7), np.uint8)
FULL_31 = np.ones((31, 31), np.uint8)


def _push_pull(d: np.ndarray) -> np.ndarray:
    """Fill every zero of d (H, W) float32 from valid-weighted averages of coarser pyramid levels
    (push: halve until a level has no hole; pull: upsample back, keeping each level's own averages
    where it has data). Returns a new array; pixels > 0 are unchanged; an all-zero map stays zero."""
    w = (d > 0).astype(np.float32)
    if not w.any():
        return d.copy()
    levels: list[tuple[np.ndarray, np.ndarray]] = [(d * w, w)]
    while min(levels[-1][0].shape) > 1 and levels[-1][1].min() <= 0:
        s, c = levels[-1]
        h, ww = s.shape
        size = (max(1, (ww + 1) // 2), max(1, (h + 1) // 2))
        levels.append((cv2.resize(s, size, interpolation=cv2.INTER_AREA),
                       cv2.resize(c, size, interpolation=cv2.INTER_AREA)))
    s, c = levels[-1]
    filled: np.ndarray = np.zeros_like(s)
    np.divide(s, c, out=filled, where=c > 0)
    for s, c in reversed(levels[:-1]):
        h, ww = s.shape
        filled = cv2.resize(filled, (ww, h), interpolation=cv2.INTER_LINEAR)
        np.divide(s, c, out=filled, where=c > 1e-6)
    out = d.copy()
    np.copyto(out, filled, where=d <= 0)
    return out


def complete_depth(raw: np.ndarray, p: CompletionParams = CompletionParams()) -> DepthMap:
    """Complete the holes of a depth map (IP-Basic fill_in_fast, see the module docstring).

    raw: (H, W) float metres, 0 or NaN = unknown. Values outside [p.min_depth, p.max_depth] count
    as unknown. blur "gaussian" is IP-Basic's, on filled pixels only, normalised so holes do not
    bleed in; "bilateral" costs about 2 ms more per 640x480 frame. The morphology runs on the
    inverted depth in integer millimetres (OpenCV's 16-bit paths are 2-4x faster than float), so
    filled values are quantised to 1 mm; with keep_valid, measured pixels are returned unchanged.
    Returns DepthMap(depth (H, W) float32 completed, valid (H, W) bool measured pixels).
    """
    min_depth, max_depth, blur = p.min_depth, p.max_depth, p.blur
    raw = np.array(raw, np.float32)
    cv2.patchNaNs(raw, 0.0)
    valid = (raw >= min_depth) & (raw <= max_depth)
    if not valid.any():
        return DepthMap(np.zeros_like(raw), valid)
    if max_depth + 1.0 > 65.0:
        raise ValueError(f"max_depth {max_depth} m is beyond the 16-bit millimetre range (64 m)")
    top = np.float32(max_depth + 1.0)  # inversion constant: any value above max_depth works
    inv = top - raw
    inv *= valid
    d16: np.ndarray = (inv * 1000.0 + 0.5).astype(np.uint16)  # inverted depth, mm; 0 = unknown
    d16 = cv2.dilate(d16, DIAMOND_5)
    d16 = cv2.morphologyEx(d16, cv2.MORPH_CLOSE, FULL_5)
    np.copyto(d16, cv2.dilate(d16, FULL_7), where=d16 < 100)
    if p.extrapolate:
        has = d16 >= 100
        col_has = np.asarray(has.any(axis=0))
        first = np.argmax(has, axis=0)  # top-most valid row per column
        top_vals = d16[first, np.arange(d16.shape[1])]
        rows = np.arange(d16.shape[0])[:, None]
        above = (rows < first[None, :]) & col_has[None, :]
        d16 = np.where(above, top_vals[None, :], d16).astype(np.uint16)
        np.copyto(d16, cv2.dilate(d16, FULL_31), where=d16 < 100)
    d16 = cv2.medianBlur(d16, 5)
    d = d16.astype(np.float32)
    d *= 0.001
    filled = d > 0.1
    if blur == "bilateral":
        np.copyto(d, cv2.bilateralFilter(d, 5, p.bilateral_sigma_color, p.bilateral_sigma_space), where=filled)
    elif blur == "gaussian":
        # normalised convolution: unknown (0) pixels must not pull the blur toward zero
        wsum = cv2.GaussianBlur(filled.astype(np.float32), (5, 5), 0)
        np.divide(cv2.GaussianBlur(d, (5, 5), 0), wsum, out=d, where=filled)
    elif blur != "none":
        raise ValueError(f"blur must be bilateral, gaussian or none, not {blur!r}")
    depth = top - d
    depth *= filled
    if p.keep_valid:
        np.copyto(depth, raw, where=valid)
    if p.large_holes == "pushpull":
        if not filled.all():
            depth = _push_pull(depth)
    elif p.large_holes != "none":
        raise ValueError(f"large_holes must be pushpull or none, not {p.large_holes!r}")
    return DepthMap(depth, valid)
