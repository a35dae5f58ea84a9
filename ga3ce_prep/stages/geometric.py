"""The weight-free geometric segmenter (Open3D): planes by RANSAC, the rest by DBSCAN.

`segment_geometric` works on a point cloud sampled from the completed depth on a pixel grid (every
`stride`-th pixel, so a 640x480 frame gives about 19k points at stride 4 instead of 307k):

1. Planes: up to `max_planes` times, Open3D's RANSAC (`segment_plane`) finds the dominant plane of
   the remaining points (floor, walls, table tops); a plane with fewer than `min_plane_frac` of the
   points ends the search. Each plane's inliers are split into connected pieces by DBSCAN (two
   table tops at one height are two segments). With `keep_planes` off, planes are only removed.
2. Clusters: DBSCAN (`cluster_eps` metres, `cluster_min_points`) on what is left; noise points get
   no label.
3. Back to pixels: each grid point's label covers its stride x stride cell (nearest-neighbour
   upsampling); a full-resolution pixel keeps it only if its depth is within `depth_tol` metres
   of the grid point's, so labels do not bleed across depth edges.
4. The subject: with `drop_subject`, the segment under the head box centre (the person whose gaze
   is estimated) is removed.

Returns an (H, W) int32 label image, -1 = no segment, for `geometry.object_positions`. RANSAC is
seeded per frame (Open3D's global seed), so a frame gives the same segments in every run.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import back_project


@dataclass
class GeometricParams:
    """Parameters of `segment_geometric` (metres, pixels); defaults in schemas/pipeline.schema.json."""

    stride: int = 4
    max_planes: int = 4
    plane_distance: float = 0.02
    plane_iterations: int = 200
    min_plane_frac: float = 0.08
    keep_planes: bool = True
    cluster_eps: float = 0.06
    cluster_min_points: int = 8
    depth_tol: float = 0.05
    drop_subject: bool = True
    max_range: float = 8.0


def _dbscan(o3d, pts: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """DBSCAN labels (n,) int32 of points (n, 3), -1 = noise."""
    if len(pts) == 0:
        return np.zeros(0, np.int32)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    return np.asarray(pc.cluster_dbscan(eps=eps, min_points=min_points, print_progress=False), np.int32)


def segment_geometric(depth: np.ndarray, K: np.ndarray, p: GeometricParams, seed: int = 0,
                      head_box: np.ndarray | None = None) -> np.ndarray:
    """Label image (H, W) int32 of planes and clusters of the completed depth (module docstring).

    depth: (H, W) float32 metres, 0 = unknown. K: (3, 3). head_box: (4,) x1, y1, x2, y2 pixels of
    the subject (for drop_subject). seed: RANSAC seed (derive it from the frame id).
    """
    import open3d as o3d

    H, W = depth.shape
    s = int(p.stride)
    off = s // 2
    vs = np.arange(off, H, s)
    us = np.arange(off, W, s)
    grid_z = depth[np.ix_(vs, us)]
    ok = (grid_z > 0) & (grid_z <= p.max_range)
    gv, gu = np.nonzero(ok)
    pts = back_project(us[gu].astype(np.float64), vs[gv].astype(np.float64), grid_z[gv, gu].astype(np.float64), K)
    labels = np.full(len(pts), -1, np.int32)
    next_label = 0
    remaining = np.arange(len(pts))
    o3d.utility.random.seed(int(seed) & 0x7FFFFFFF)
    min_plane = max(3, int(p.min_plane_frac * len(pts)))
    for _ in range(int(p.max_planes)):
        if len(remaining) < min_plane:
            break
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[remaining]))
        _, inl = pc.segment_plane(distance_threshold=p.plane_distance, ransac_n=3,
                                  num_iterations=int(p.plane_iterations))
        inl = np.asarray(inl, np.int64)
        if len(inl) < min_plane:
            break
        members = remaining[inl]
        if p.keep_planes:
            sub = _dbscan(o3d, pts[members], p.cluster_eps, p.cluster_min_points)
            good = sub >= 0
            labels[members[good]] = sub[good] + next_label
            next_label += int(sub.max()) + 1 if good.any() else 0
        keep = np.ones(len(remaining), bool)
        keep[inl] = False
        remaining = remaining[keep]
    sub = _dbscan(o3d, pts[remaining], p.cluster_eps, p.cluster_min_points)
    good = sub >= 0
    labels[remaining[good]] = sub[good] + next_label

    grid = np.full((len(vs), len(us)), -1, np.int32)
    grid[gv, gu] = labels
    # nearest-neighbour upsampling: pixel (v, u) belongs to grid cell ((v - off + s/2) // s, ...)
    cell_v = np.clip((np.arange(H) - off + s // 2) // s, 0, len(vs) - 1)
    cell_u = np.clip((np.arange(W) - off + s // 2) // s, 0, len(us) - 1)
    full = grid[np.ix_(cell_v, cell_u)]
    ref_z = grid_z[np.ix_(cell_v, cell_u)]
    full[(np.abs(depth - ref_z) > p.depth_tol) | (depth <= 0)] = -1
    if p.drop_subject and head_box is not None and np.all(np.isfinite(head_box)):
        cu = int(np.clip(0.5 * (head_box[0] + head_box[2]), 0, W - 1))
        cv = int(np.clip(0.5 * (head_box[1] + head_box[3]), 0, H - 1))
        c = grid[min(len(vs) - 1, max(0, (cv - off + s // 2) // s)), min(len(us) - 1, max(0, (cu - off + s // 2) // s))]
        if c >= 0:
            full[full == c] = -1
    return full
