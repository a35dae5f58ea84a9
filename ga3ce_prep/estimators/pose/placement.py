"""Placing a root-relative metric 3D pose in the camera frame: the translation T that makes
`world + T` project onto the 2D landmarks through K, then, where depth was measured, a refinement
of T's depth with the sensor's depth at the visible joints.

Units: metres; camera frame x right, y down, z forward; pixels with centres at integer
coordinates (the convention K uses).

A monocular estimator's world pose has the size of an average adult, so the 2D-only T puts a
smaller (or larger) person too far (or too near) in proportion: its error along the viewing ray
is the size error times the distance. One depth reading per visible joint fixes that; x and y then
follow from the 2D landmarks at the new depth.
"""
from __future__ import annotations

import numpy as np

from ...errors import FrameError
from ...geometry import back_project, project
from ...skeleton import HEAD_JOINTS, N_JOINTS


def _normalised(image: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) -> normalised image coordinates (N, 2): (x/z, y/z) of their rays
    (`geometry.back_project` at depth 1)."""
    uv = np.asarray(image, np.float64)
    return back_project(uv[:, 0], uv[:, 1], np.ones(len(uv)), np.asarray(K, np.float64))[:, :2]


def solve_translation(world: np.ndarray, image: np.ndarray, weight: np.ndarray, K: np.ndarray) -> np.ndarray:
    """T (3,) metres such that world + T projects onto `image` through K.

    world: (N, 3) metres, camera axes; image: (N, 2) pixels; weight: (N,) >= 0 (0 = unused). Linear
    least squares on x_n (Z + Tz) = X + Tx and y_n (Z + Tz) = Y + Ty, with (x_n, y_n) = K^-1 (u, v, 1),
    each equation scaled by sqrt(weight). FrameError with fewer than 2 weighted points or a
    solution behind the camera.
    """
    w = np.asarray(weight, np.float64)
    use = (w > 0) & np.isfinite(image).all(1) & np.isfinite(world).all(1)
    if use.sum() < 2:
        raise FrameError(f"cannot place the pose: {int(use.sum())} usable landmarks (need 2)")
    P, xy, sw = np.asarray(world, np.float64)[use], _normalised(image[use], K), np.sqrt(w[use])
    n = len(P)
    A = np.zeros((2 * n, 3))
    A[:n, 0] = A[n:, 1] = 1.0
    A[:, 2] = -np.concatenate([xy[:, 0], xy[:, 1]])
    b = np.concatenate([xy[:, 0] * P[:, 2] - P[:, 0], xy[:, 1] * P[:, 2] - P[:, 1]])
    T = np.linalg.lstsq(A * np.tile(sw, 2)[:, None], b * np.tile(sw, 2), rcond=None)[0]
    if not np.isfinite(T).all() or T[2] + np.min(P[:, 2]) <= 0:
        raise FrameError(f"cannot place the pose: translation {T} puts it behind the camera")
    return T


def sample_depth(depth: np.ndarray, image: np.ndarray, valid: np.ndarray | None = None, radius: int = 2) -> np.ndarray:
    """Median measured depth (N,) metres in a (2 radius + 1)^2 window around each pixel (N, 2).

    Only pixels inside the image, with depth > 0 and `valid` (H, W) true count; NaN where none does.
    """
    H, W = depth.shape
    ok_map = depth > 0 if valid is None else (valid & (depth > 0))
    off = np.arange(-radius, radius + 1)
    c = np.rint(np.nan_to_num(np.asarray(image, np.float64), nan=-1e9)).astype(np.int64)      # (N, 2)
    u = c[:, None, None, 0] + off[None, None, :]                                          # (N, 1, k)
    v = c[:, None, None, 1] + off[None, :, None]                                          # (N, k, 1)
    u, v = np.broadcast_arrays(u, v)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    uc, vc = np.clip(u, 0, W - 1), np.clip(v, 0, H - 1)
    vals = np.where(inside & ok_map[vc, uc], depth[vc, uc], np.nan).reshape(len(c), -1)
    out = np.full(len(c), np.nan)
    some = np.isfinite(vals).any(1)
    out[some] = np.nanmedian(vals[some], axis=1)
    return out


def weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """The weighted median of x (N,) with weights w (N,) > 0 (the lower one at a tie)."""
    o = np.argsort(x)
    cw = np.cumsum(w[o])
    return float(x[o][np.searchsorted(cw, 0.5 * cw[-1])])


def refine_with_depth(world: np.ndarray, image: np.ndarray, weight: np.ndarray, K: np.ndarray, T: np.ndarray,
                      depth: np.ndarray, valid: np.ndarray | None = None, surface_offset: np.ndarray | float = 0.0,
                      *, radius: int = 2, gate: float = 0.15, min_points: int = 3) -> tuple[np.ndarray, int]:
    """T (3,) with its depth taken from the measured depth; returns (T, joints used).

    world (N, 3) metres, camera axes; image (N, 2) pixels; weight (N,) >= 0; T (3,) the 2D-only
    solution; depth (H, W) metres (0 = unknown) at the image's resolution, valid (H, W) the pixels
    actually measured (None: every depth > 0). surface_offset (N,) or scalar, metres: how far
    behind the visible surface each landmark lies (a joint centre is about a limb radius behind
    the skin the sensor sees; face landmarks lie on it).

    Each weighted joint with a depth reading d votes Tz = d + offset - Z. The votes' weighted
    median, then the weighted mean of the votes within `gate` metres of it (depth edges, occluders
    and the background fall outside), gives Tz; Tx and Ty are then the weighted least-squares
    solution of the 2D equations at that Tz. With fewer than `min_points` agreeing joints T is
    returned unchanged (0 joints used).
    """
    if valid is not None and valid.shape != depth.shape:
        raise ValueError(f"depth {depth.shape} and valid {valid.shape} differ")
    w = np.asarray(weight, np.float64)
    P = np.asarray(world, np.float64)
    d = sample_depth(depth, image, valid, radius)
    votes = d + np.broadcast_to(np.asarray(surface_offset, np.float64), d.shape) - P[:, 2]
    use = (w > 0) & np.isfinite(votes)
    if use.sum() < min_points:
        return np.asarray(T, np.float64), 0
    tz0 = weighted_median(votes[use], w[use])
    use &= np.abs(votes - tz0) <= gate
    if use.sum() < min_points:
        return np.asarray(T, np.float64), 0
    tz = float(np.average(votes[use], weights=w[use]))
    ok = (w > 0) & np.isfinite(image).all(1)
    xy = _normalised(image[ok], K)
    txy = np.average(xy * (P[ok, 2:] + tz) - P[ok, :2], axis=0, weights=w[ok])
    return np.array([txy[0], txy[1], tz]), int(use.sum())


def pose_depth_translation(pose: np.ndarray, K: np.ndarray, depth: np.ndarray, valid: np.ndarray | None,
                           joint_depth_offset: float) -> tuple[np.ndarray, int]:
    """The translation (3,) metres that moves a camera-frame smpl+head_30 pose (30, 3) metres (NaN
    rows = missing) to the distance the depth map (H, W) metres measures at its joints' pixels
    (`refine_with_depth`: body joints `joint_depth_offset` metres behind the surface, the 6 face
    joints on it), and the joints that agreed; (0, 0, 0) and 0 with too few readings."""
    offset = np.full(N_JOINTS, float(joint_depth_offset))
    offset[list(HEAD_JOINTS)] = 0.0
    T, used = refine_with_depth(pose, project(pose, K), np.ones(N_JOINTS), K, np.zeros(3), depth, valid, offset)
    return T, used


__all__ = ["pose_depth_translation", "refine_with_depth", "sample_depth", "solve_translation", "weighted_median"]
