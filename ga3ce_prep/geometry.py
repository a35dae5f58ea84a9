"""Camera geometry and the 3D context points GA3CE consumes: `object_positions`, `head_position`.

Camera frame: metres, x right, y down, z forward (OpenCV). K is the 3x3 pinhole matrix in pixels;
pixel (u, v) has u along x. Depth maps are (H, W) float32 metres with 0 = unknown.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import FrameError


def normalize(v: np.ndarray, axis: int = -1, eps: float = 1e-12) -> np.ndarray:
    """Unit vectors along `axis`; zero vectors stay zero."""
    v = np.asarray(v)
    n = np.linalg.norm(v, axis=axis, keepdims=True)
    return v / np.maximum(n, eps)


def unit_direction(v: np.ndarray, what: str, min_norm: float = 1e-6) -> np.ndarray:
    """v / |v| as float32, the direction a view estimate stands for; FrameError "<what> is [...], not
    a direction" when |v| is not finite or is below min_norm."""
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < min_norm:
        raise FrameError(f"{what} is {np.asarray(v).tolist()}, not a direction")
    return (v / n).astype(np.float32)


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between direction vectors a and b (..., 3), any lengths."""
    cos = np.sum(normalize(a) * normalize(b), axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def back_project(u: np.ndarray | float, v: np.ndarray | float, z: np.ndarray | float, K: np.ndarray) -> np.ndarray:
    """Pixels (u, v) at depth z (metres) to camera-frame points (..., 3)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = np.asarray(z)
    return np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=-1)


def depth_to_points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Back-project a whole (H, W) depth map to (H, W, 3) float32 points (0-depth pixels give 0)."""
    H, W = depth.shape
    u = np.arange(W, dtype=np.float32)[None, :]
    v = np.arange(H, dtype=np.float32)[:, None]
    pts = back_project(u, v, depth.astype(np.float32), K.astype(np.float32))
    return pts.astype(np.float32, copy=False)


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points (..., 3) to pixels (..., 2); points at z <= 0 give NaN."""
    p = np.asarray(points, dtype=np.float64)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        zs = np.where(z > 0, z, np.nan)
        u = K[0, 0] * p[..., 0] / zs + K[0, 2]
        v = K[1, 1] * p[..., 1] / zs + K[1, 2]
    return np.stack([u, v], axis=-1)


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K for an image resized by (sx, sy) (new size = old size * s), pixel-corner convention."""
    K2 = np.array(K, dtype=np.float64, copy=True)
    K2[0, :] *= sx
    K2[1, :] *= sy
    K2[2, :] = (0.0, 0.0, 1.0)
    return K2


def look_at_rotation(ray: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """The (3, 3) rotation taking the optical axis (0, 0, 1) to the unit direction of `ray` (3,).
    It turns a direction measured relative to the viewing ray (as a crop seen frontally would give
    it) into the camera frame; its columns are the rotated camera's axes in the camera frame.

    up None: the shortest arc (about the axis z x ray, no roll); the ray must point into the
    half-space z > -1 (any ray through a pixel does). up (3,), e.g. (0, -1, 0): the rotated x
    axis is ray x up, perpendicular to `up` (no roll about the world's vertical: MeTRAbs's
    look-at); a ray along `up` falls back to the shortest arc.
    """
    r = normalize(np.asarray(ray, np.float64))
    if up is not None:
        x = np.cross(r, np.asarray(up, np.float64))
        if np.linalg.norm(x) > 1e-9:
            x = normalize(x)
            return np.stack([x, np.cross(r, x), r], axis=1)
    k = np.array([-r[1], r[0], 0.0])  # (0, 0, 1) x r: sin(angle) times the unit axis
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + Kx + Kx @ Kx / (1.0 + r[2])  # Rodrigues with cos(angle) = r_z


def pixel_ray(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The unit camera-frame direction (..., 3) of the ray through pixel(s) uv (..., 2)."""
    uv = np.asarray(uv, np.float64)
    return normalize(back_project(uv[..., 0], uv[..., 1], np.ones(uv.shape[:-1]), np.asarray(K, np.float64)))


@dataclass
class ObjectPositions:
    """Per-mask median 3D points, GA3CE's P_object.

    xyz: (M', 3) float32 per-axis median of each kept mask's valid back-projected points, metres.
    area: (M',) int32 mask pixels (valid depth or not). n_valid: (M',) int32 points used.
    index: (M',) int64 position of each kept mask in the input (label value for a label image).
    n_dropped: masks (with at least one pixel) dropped for having fewer than min_points valid points.
    """

    xyz: np.ndarray
    area: np.ndarray
    n_valid: np.ndarray
    index: np.ndarray
    n_dropped: int


def _grouped_valid_pixels(masks: np.ndarray, ok: np.ndarray, min_points: int):
    """Pixels of each mask with usable depth, grouped by mask.

    Returns (pix, area, n_valid, keep): flat indices of the kept masks' valid pixels sorted by
    mask, every mask's area and valid count, and which masks have at least min_points.
    """
    okf = ok.ravel()
    if masks.ndim == 3:  # (M, H, W) bool stack, masks may overlap
        M = masks.shape[0]
        flat: np.ndarray = masks.reshape(M, okf.size)  # (not -1: no masks is a (0, H*W) stack)
        area = np.count_nonzero(flat, axis=1)
        mask_id, pix = np.nonzero(flat)  # row-major: grouped by mask already
        sel = okf[pix]
        mask_id, pix = mask_id[sel], pix[sel]
        n_valid = np.bincount(mask_id, minlength=M)
        keep = n_valid >= min_points
        if not keep.all():
            pix = pix[keep[mask_id]]
        return pix, area, n_valid, keep
    if masks.ndim == 2:  # (H, W) int label image, negative = no mask
        flat = masks.ravel()
        labelled = flat >= 0
        ids_all = flat[labelled]
        M = int(ids_all.max()) + 1 if ids_all.size else 0
        area = np.bincount(ids_all, minlength=M)
        pix = np.flatnonzero(labelled & okf)
        ids = flat[pix]
        n_valid = np.bincount(ids, minlength=M)
        keep = n_valid >= min_points
        if not keep.all():
            sel = keep[ids]
            pix, ids = pix[sel], ids[sel]
        # numpy's stable sort is a radix sort for 16-bit keys: 3x faster than on int32
        key = ids.astype(np.int16) if M <= np.iinfo(np.int16).max else ids
        return pix[np.argsort(key, kind="stable")], area, n_valid, keep
    raise ValueError(f"masks must be (M, H, W) bool or (H, W) int labels, got shape {masks.shape}")


def mask_pixel_counts(masks: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Pixels of each mask where `ok` (H, W) bool holds: (M,) int64 for (M, H, W) bool masks, or
    (n_labels,) for an (H, W) int label image (negative = no mask)."""
    if masks.ndim == 3:
        return np.count_nonzero(masks.reshape(len(masks), -1) & ok.reshape(1, -1), axis=1)
    sel = masks[ok & (masks >= 0)]
    return np.bincount(sel, minlength=int(masks.max(initial=-1)) + 1)


def _median_sorted_groups(values: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Median of each contiguous group values[s:s+c] (numpy's convention: mean of the two middle
    values for even c). One O(c) selection per group; no per-pixel Python work."""
    out = np.empty(len(starts), np.float32)
    for g, (s, c) in enumerate(zip(starts.tolist(), counts.tolist())):
        seg = values[s:s + c]
        k = c // 2
        if c % 2:
            out[g] = np.partition(seg, k)[k]
        else:
            p = np.partition(seg, (k - 1, k))
            out[g] = 0.5 * (p[k - 1] + p[k])
    return out


def object_positions(depth: np.ndarray, K: np.ndarray, masks: np.ndarray,
                     valid: np.ndarray | None = None, *, min_points: int) -> ObjectPositions:
    """GA3CE's object points: back-project each mask with depth and K and keep the per-axis median
    of its valid 3D points.

    depth: (H, W) float32 metres (completed depth is fine). valid: (H, W) bool, the pixels whose
    depth may be used (default depth > 0); pass the raw sensor validity to keep filled-in pixels
    out of the medians. masks: (M, H, W) bool, possibly overlapping (segment-everything), or an
    (H, W) int label image with negative = background, at the depth map's resolution.
    Masks with fewer than `min_points` valid points are dropped and counted.
    """
    H, W = depth.shape
    if masks.shape[-2:] != (H, W):
        raise ValueError(f"masks {masks.shape[-2:]} and depth {(H, W)} differ in resolution")
    ok = (depth > 0) if valid is None else (valid & (depth > 0))
    pix, area, n_valid, keep = _grouped_valid_pixels(masks, ok, min_points)
    n_dropped = int(np.count_nonzero((area > 0) & ~keep))
    index = np.flatnonzero(keep)
    counts = n_valid[index]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])[:len(counts)].astype(np.int64)  # [] when no mask is kept

    # contiguous per-axis arrays: each median is a selection over one contiguous segment
    z = depth.ravel()[pix].astype(np.float32)
    v = np.floor((pix + 0.5) * (1.0 / W))  # pix // W without integer division (exact below 2**40)
    u = (pix - v * W).astype(np.float32)
    fx, fy, cx, cy = (np.float32(c) for c in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    x = (u - cx) * z / fx
    y = (v.astype(np.float32) - cy) * z / fy
    xyz = np.stack([_median_sorted_groups(a, starts, counts) for a in (x, y, z)], axis=-1)
    return ObjectPositions(xyz=xyz.reshape(-1, 3),
                           area=area[index].astype(np.int32), n_valid=counts.astype(np.int32),
                           index=index.astype(np.int64), n_dropped=n_dropped)


def head_box_centre(head_box: np.ndarray, width: int, height: int) -> tuple[float, float, float]:
    """(u, v, side) of a head box x1, y1, x2, y2 (4,) pixels: its centre and its shorter side, px.
    Raises FrameError when the box is not finite or empty, or its centre lies outside the
    width x height image."""
    x1, y1, x2, y2 = (float(c) for c in head_box)
    if not np.all(np.isfinite([x1, y1, x2, y2])) or x2 <= x1 or y2 <= y1:
        raise FrameError(f"invalid head box {list(head_box)}")
    cu, cv = 0.5 * (x1 + x2), 0.5 * (y1 + y2)
    if not (0 <= cu < width and 0 <= cv < height):
        raise FrameError(f"head box centre ({cu:.1f}, {cv:.1f}) lies outside the {width}x{height} image")
    return cu, cv, min(x2 - x1, y2 - y1)


def window_median_depth(depth: np.ndarray, ok: np.ndarray, cu: float, cv: float, side: float, *,
                        window_fracs: tuple[float, ...], min_points: int) -> float | None:
    """The median depth (metres) of the pixels `ok` (H, W) bool in a square window of side
    window_frac * side (at least 3 px) around pixel (cu, cv), clipped to the image; each fraction
    in turn until a window holds `min_points` such pixels. None when none does."""
    H, W = depth.shape
    for frac in window_fracs:
        r = max(1.5, 0.5 * frac * side)
        u0, u1 = int(max(0, np.floor(cu - r))), int(min(W, np.ceil(cu + r)))
        v0, v1 = int(max(0, np.floor(cv - r))), int(min(H, np.ceil(cv + r)))
        win = depth[v0:v1, u0:u1][ok[v0:v1, u0:u1]]
        if win.size >= min_points:
            return float(np.median(win))
    return None


def head_position(depth: np.ndarray, K: np.ndarray, head_box: np.ndarray, valid: np.ndarray | None = None, *,
                  window_fracs: tuple[float, ...], min_points: int) -> np.ndarray:
    """t_object: the head box centre back-projected at the median valid depth of a small window.

    The window is a square of side window_frac * min(box w, box h) (at least 3 px) around the box
    centre, clipped to the image; if it has fewer than `min_points` valid pixels the next, larger
    fraction is tried (`window_median_depth`). Returns (3,) float32 metres. Raises FrameError when
    the box is outside the image or no window has valid depth. The head stage's defaults and its
    fallbacks when none has: `stages.head.DepthHead`.
    """
    H, W = depth.shape
    cu, cv, side = head_box_centre(head_box, W, H)
    ok = (depth > 0) if valid is None else (valid & (depth > 0))
    z = window_median_depth(depth, ok, cu, cv, side, window_fracs=window_fracs, min_points=min_points)
    if z is None:
        raise FrameError(f"no valid depth in the head box {[round(float(c), 1) for c in head_box]}")
    return back_project(cu, cv, z, K).astype(np.float32)
