"""The weight-free geometric segmenter: planes by RANSAC, the rest by DBSCAN (Open3D).

`segment_geometric` works on a point cloud sampled from the completed depth on a pixel grid (every
`stride`-th pixel, so a 640x480 frame gives about 19k points at stride 4 instead of 307k):

1. Planes: up to `max_planes` times, RANSAC (`ransac_plane`, on every `plane_subsample`-th free
   point) finds the dominant plane of the remaining points (floor, walls,
   table tops); every free point within `plane_distance` joins it, and a plane with fewer than
   `min_plane_frac` of the points ends the search. A plane's members are split into connected
   pieces in the image grid (two table tops at one height are two segments). With `keep_planes`
   off, planes are only removed.
2. Clusters: DBSCAN (`cluster_eps` metres, `cluster_min_points`) on what is left; noise points get
   no label. A cluster with more than `band_frac` of its points within `plane_band` of a plane is
   that plane's noise (sensor noise grows with distance: a far wall leaves speckle off its plane)
   and is dropped; objects standing on a plane keep their points near it. Segments with fewer
   than `min_segment_points` grid points are dropped.
3. Back to pixels: each grid point's label covers its stride x stride cell (nearest-neighbour
   upsampling); a full-resolution pixel keeps it only if its depth is within `depth_tol` metres
   of the grid point's, so labels do not bleed across depth edges.
4. The subject: with `drop_subject`, the segment under the head box centre (the person whose gaze
   is estimated) is removed.

Returns the segments (`GeometricSegments`): an (H, W) int32 label image, -1 = no segment, for
`geometry.object_positions`, and which labels are plane pieces (the rest are clusters). RANSAC is
vectorised numpy with a generator seeded from the frame id, so a frame gives the same segments in
every run whatever the sharding, scheduler or order. (Open3D 0.20's `segment_plane` is not
reproducible run to run even with `o3d.utility.random.seed`: its parallel sampling depends on
thread scheduling, which would break identical resumes. Open3D's DBSCAN is reproducible.)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ...geometry import back_project
from ...params import param


@dataclass(frozen=True, kw_only=True)
class GeometricParams:
    """Parameters of `segment_geometric` (the steps of the module docstring)."""

    stride: int = param(4, minimum=1)  # pixels between sampled points (640x480 at 4: about 19k points)
    smooth: Literal[1, 3, 5] = 5  # median filter size on the depth before sampling (1: none)
    max_planes: int = param(4, minimum=0)  # at most this many RANSAC planes
    plane_distance: float = param(0.03, exclusiveMinimum=0)  # metres, RANSAC inlier distance
    plane_band: float = param(
        0.04, exclusiveMinimum=0)  # metres; free points this near a found plane leave the pool (its noisy band)
    band_frac: float = param(
        # a cluster with more than this fraction of its points in a plane's band is that plane's noise and is dropped
        0.7, minimum=0, maximum=1)
    noise_ref_depth: float = param(
        # metres; plane tolerances grow as (z / noise_ref_depth)^2 beyond it (Kinect-style noise)
        2.5, exclusiveMinimum=0)
    plane_iterations: int = param(200, minimum=1)  # RANSAC iterations per plane
    plane_subsample: int = param(
        4, minimum=1)  # RANSAC runs on every n-th free point (speed); all points are then assigned
    min_plane_frac: float = param(0.08, exclusiveMinimum=0, maximum=1)  # a plane needs this fraction of the points
    keep_planes: bool = True  # planes (split into connected pieces) are segments too; false: only removed
    cluster_eps: float = param(0.06, exclusiveMinimum=0)  # metres, DBSCAN neighbourhood
    cluster_min_points: int = param(5, minimum=1)  # DBSCAN core-point neighbours
    min_segment_points: int = param(6, minimum=1)  # segments with fewer grid points are dropped
    depth_tol: float = param(
        0.05, exclusiveMinimum=0)  # metres; a pixel keeps its grid point's label only within this depth
    drop_subject: bool = True  # remove the segment under the head box centre (the subject)
    max_range: float = param(8.0, exclusiveMinimum=0)  # metres; farther points are ignored


def _dbscan(o3d, pts: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """DBSCAN labels (n,) int32 of points (n, 3), -1 = noise."""
    if len(pts) == 0:
        return np.zeros(0, np.int32)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    return np.asarray(pc.cluster_dbscan(eps=eps, min_points=min_points, print_progress=False), np.int32)


def ransac_plane(pts: np.ndarray, distance: float, iterations: int,
                 rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """The plane (unit normal (3,), offset d; n . p + d = 0) with the most points of pts (n, 3)
    within `distance` metres among `iterations` random 3-point hypotheses, refitted by least
    squares to its inliers. Vectorised over hypotheses; reproducible for a given rng."""
    n = len(pts)
    idx = rng.integers(0, n, size=(iterations, 3))
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-9
    normals = normals[ok] / norm[ok, None]
    offsets = -np.sum(normals * a[ok], axis=1)
    if not len(normals):
        return np.array([0.0, 0.0, 1.0]), 0.0
    counts = (np.abs(pts @ normals.T + offsets) <= distance).sum(axis=0)
    best = int(np.argmax(counts))  # first of the ties
    inl = pts[np.abs(pts @ normals[best] + offsets[best]) <= distance]
    centre = inl.mean(axis=0)
    nrm = np.linalg.svd(inl - centre, full_matrices=False)[2][-1]  # least-squares normal
    return nrm, float(-nrm @ centre)


@dataclass(frozen=True)
class GeometricSegments:
    """The segments of one frame: labels (H, W) int32, -1 = none, 0..k-1 = a segment; plane (k,)
    bool, True for a connected piece of a RANSAC plane, False for a DBSCAN cluster."""

    labels: np.ndarray
    plane: np.ndarray


def _relabel_small(labels: np.ndarray, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Labels renumbered 0..k-1 in order of first appearance, segments under min_points -> -1;
    and (k,) the old label of each new one."""
    out = np.full_like(labels, -1)
    ok = labels >= 0
    if not ok.any():
        return out, np.zeros(0, labels.dtype)
    uniq, first, counts = np.unique(labels[ok], return_index=True, return_counts=True)
    big = counts >= min_points
    order = np.argsort(first[big], kind="stable")
    lut = np.full(int(labels.max()) + 1, -1, labels.dtype)
    lut[uniq[big][order]] = np.arange(int(big.sum()), dtype=labels.dtype)
    out[ok] = lut[labels[ok]]
    return out, uniq[big][order]


def segment_geometric(depth: np.ndarray, K: np.ndarray, p: GeometricParams, seed: int = 0,
                      head_box: np.ndarray | None = None) -> GeometricSegments:
    """The planes' pieces and the clusters of the completed depth (module docstring).

    depth: (H, W) float32 metres, 0 = unknown. K: (3, 3). head_box: (4,) x1, y1, x2, y2 pixels of
    the subject (for drop_subject). seed: RANSAC seed (derive it from the frame id).
    """
    import cv2
    import open3d as o3d

    H, W = depth.shape
    s = int(p.stride)
    off = s // 2
    vs = np.arange(off, H, s)
    us = np.arange(off, W, s)
    if p.smooth > 1:  # a median over the full-resolution depth tames sensor noise before sampling
        z16 = np.clip(depth * 1000.0 + 0.5, 0, 65535).astype(np.uint16)
        grid_z = (cv2.medianBlur(z16, int(p.smooth)) * np.float32(0.001))[np.ix_(vs, us)]
    else:
        grid_z = depth[np.ix_(vs, us)]
    ok = (grid_z > 0) & (grid_z <= p.max_range)
    gv, gu = np.nonzero(ok)
    pts = back_project(us[gu].astype(np.float64), vs[gv].astype(np.float64), grid_z[gv, gu].astype(np.float64), K)
    n = len(pts)
    tol_scale = np.maximum(1.0, (pts[:, 2] / p.noise_ref_depth) ** 2)
    grid = np.full((len(vs), len(us)), -1, np.int32)
    labels = np.full(n, -1, np.int32)
    free = np.ones(n, bool)  # not yet on a plane
    in_band = np.zeros(n, bool)  # within plane_band of some plane
    next_label = 0
    rng = np.random.default_rng(int(seed))
    sub = np.arange(0, n, max(1, int(p.plane_subsample)))  # RANSAC runs on a subsample...
    min_plane = max(3, int(p.min_plane_frac * n))
    for _ in range(int(p.max_planes)):
        cand = sub[free[sub]]
        if len(cand) * max(1, int(p.plane_subsample)) < min_plane or len(cand) < 3:
            break
        nrm, d0 = ransac_plane(pts[cand], p.plane_distance, int(p.plane_iterations), rng)
        # ...and the plane takes every free point near it; the tolerance grows with the sensor
        # noise, as (z / noise_ref_depth)^2 beyond noise_ref_depth (Kinect-style noise)
        dist = np.abs(pts @ nrm + d0) / tol_scale
        members = free & (dist <= p.plane_distance)
        if members.sum() < min_plane:
            break
        if p.keep_planes:  # connected pieces of the plane in the image grid (two table tops, not one)
            mask = np.zeros(grid.shape, np.uint8)
            mask[gv[members], gu[members]] = 1
            k, comp = cv2.connectedComponents(mask, connectivity=8)
            labels[members] = comp[gv[members], gu[members]] - 1 + next_label
            next_label += k - 1
        free &= ~members
        in_band |= dist <= p.plane_band
    rest = np.flatnonzero(free)
    sub_labels = _dbscan(o3d, pts[rest], p.cluster_eps, p.cluster_min_points)
    if len(rest) and sub_labels.max(initial=-1) >= 0:
        # a cluster lying mostly in a plane's band is that plane's noise (a far wall's speckle), not
        # an object; objects keep their points near the plane (their bottoms on a table)
        k = int(sub_labels.max()) + 1
        good = sub_labels >= 0
        size = np.bincount(sub_labels[good], minlength=k)
        banded = np.bincount(sub_labels[good], weights=in_band[rest[good]], minlength=k)
        sub_labels[good & (banded[np.maximum(sub_labels, 0)] > p.band_frac * size[np.maximum(sub_labels, 0)])] = -1
    good = sub_labels >= 0
    labels[rest[good]] = sub_labels[good] + next_label
    grid[gv, gu], old = _relabel_small(labels, int(p.min_segment_points))

    # nearest-neighbour upsampling: pixel (v, u) belongs to grid cell ((v - off + s/2) // s, ...)
    cell_v = np.clip((np.arange(H) - off + s // 2) // s, 0, len(vs) - 1)
    cell_u = np.clip((np.arange(W) - off + s // 2) // s, 0, len(us) - 1)
    full = grid[np.ix_(cell_v, cell_u)]
    ref_z = grid_z[np.ix_(cell_v, cell_u)]
    full[(np.abs(depth - ref_z) > p.depth_tol) | (depth <= 0)] = -1
    if p.drop_subject and head_box is not None and np.all(np.isfinite(head_box)):
        cu = int(np.clip(0.5 * (head_box[0] + head_box[2]), 0, W - 1))
        cv = int(np.clip(0.5 * (head_box[1] + head_box[3]), 0, H - 1))
        c = grid[cell_v[cv], cell_u[cu]]
        if c >= 0:
            full[full == c] = -1
    return GeometricSegments(full, old < next_label)   # plane pieces took the labels below next_label
