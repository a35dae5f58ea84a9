"""Cameras mounted like surveillance or Kinect cameras: one intrinsic matrix per dataset, a pose
per scene (height, distance to the person, yaw and pitch aimed near the person, x axis horizontal
unless a roll is asked for).

Pixel convention: pixel index (u, v) is the image point (u, v) under K, so `geometry.project` of a
3D point gives coordinates whose rounding is the pixel index. The rays cast for pixel (u, v) go
through ((u - cx) / fx, (v - cy) / fy, 1) in the camera frame. (Open3D's
`RaycastingScene.create_rays_pinhole` casts through pixel centres (u + 0.5, v + 0.5) instead, half
a pixel off this convention, so we build the rays ourselves.)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import project, scale_intrinsics
from .config import CameraConfig
from .meshes import cross3

UP = np.array([0.0, 0.0, 1.0])


@dataclass
class Camera:
    """A pinhole camera. R: (3, 3) world-to-camera rotation (rows: camera x right, y down, z
    forward in world coordinates); C: (3,) centre in the world (m)."""

    K: np.ndarray
    width: int
    height: int
    R: np.ndarray
    C: np.ndarray

    def to_cam(self, p: np.ndarray) -> np.ndarray:
        """World points (..., 3) to the camera frame."""
        return (np.asarray(p, np.float64) - self.C) @ self.R.T

    def dir_to_cam(self, d: np.ndarray) -> np.ndarray:
        """World directions (..., 3) to the camera frame."""
        return np.asarray(d, np.float64) @ self.R.T

    def project(self, p: np.ndarray) -> np.ndarray:
        """World points (..., 3) to pixels (..., 2); NaN behind the camera."""
        return project(self.to_cam(p), self.K)

    def in_image(self, p: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether world points (..., 3) project inside the image with a margin (px)."""
        uv = self.project(p)
        with np.errstate(invalid="ignore"):
            return ((uv[..., 0] >= margin) & (uv[..., 0] <= self.width - 1 - margin)
                    & (uv[..., 1] >= margin) & (uv[..., 1] <= self.height - 1 - margin))

    def rays(self, x0: int = 0, y0: int = 0, x1: int | None = None, y1: int | None = None) -> np.ndarray:
        """World rays (h, w, 6) float32 for pixels [y0:y1, x0:x1]: origin, then a direction whose
        camera-frame z is 1, so a hit's t is its depth z."""
        x1 = self.width if x1 is None else x1
        y1 = self.height if y1 is None else y1
        K, R = self.K, self.R.astype(np.float32)
        u = ((np.arange(x0, x1, dtype=np.float64) - K[0, 2]) / K[0, 0]).astype(np.float32)
        v = ((np.arange(y0, y1, dtype=np.float64) - K[1, 2]) / K[1, 1]).astype(np.float32)
        # direction_world = R^T @ (u, v, 1) = u * Rx + v * Ry + Rz (rows of R)
        out = np.empty((y1 - y0, x1 - x0, 6), np.float32)
        out[..., :3] = self.C
        d = out[..., 3:]
        d[...] = R[2]
        d += u[None, :, None] * R[0]
        d += v[:, None, None] * R[1]
        return out

    @property
    def R_cam2w(self) -> np.ndarray:
        return self.R.T

    @property
    def t_cam2w(self) -> np.ndarray:
        return self.C.copy()


def intrinsics(cfg: CameraConfig, width: int, height: int) -> np.ndarray:
    """The dataset's K (3, 3) at width x height, scaled from the config's reference size."""
    K = np.array([[cfg.fx, 0.0, cfg.cx], [0.0, cfg.fy, cfg.cy], [0.0, 0.0, 1.0]])
    return scale_intrinsics(K, width / cfg.ref_width, height / cfg.ref_height)


def default_height(cfg: CameraConfig, width: int) -> int:
    """The image height keeping the reference aspect ratio."""
    return int(round(width * cfg.ref_height / cfg.ref_width))


def look_rotation(forward: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """World-to-camera rotation looking along `forward` (3,) with the x axis horizontal, then
    rolled by `roll` rad about the optical axis."""
    z = np.asarray(forward, np.float64)
    z = z / np.linalg.norm(z)
    x = cross3(z, UP)
    x = x / np.linalg.norm(x)
    y = cross3(z, x)
    R = np.stack([x, y, z])
    if roll:
        c, s = np.cos(roll), np.sin(roll)
        R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ R
    return R


def sample_camera(rng: np.random.Generator, cfg: CameraConfig, K: np.ndarray, width: int, height: int,
                  room_size: np.ndarray, person_xy: np.ndarray, aim_z: float, must_see: np.ndarray,
                  clear, azimuth: float | None = None, tries: int = 60) -> Camera | None:
    """A camera inside the room at cfg.height and cfg.distance from the person at person_xy (2,),
    aimed at (person_xy, aim_z) off by up to cfg.yaw_offset / cfg.pitch_offset degrees, such that
    every world point of `must_see` (N, 3) projects inside the image (10% margin) and
    `clear(C, points)` says the view of them is not blocked. None if no such camera was found."""
    margin = 0.1 * min(width, height)
    for i in range(tries):
        az = rng.uniform(0, 2 * np.pi) if azimuth is None or i > tries // 2 else azimuth + rng.normal(0, 0.3)
        dist = rng.uniform(*cfg.distance)
        C = np.array([person_xy[0] + dist * np.cos(az), person_xy[1] + dist * np.sin(az), rng.uniform(*cfg.height)])
        if not (0.15 <= C[0] <= room_size[0] - 0.15 and 0.15 <= C[1] <= room_size[1] - 0.15
                and C[2] < room_size[2] - 0.1):
            continue
        aim = np.array([person_xy[0], person_xy[1], aim_z]) - C
        yaw = np.arctan2(aim[1], aim[0]) + np.radians(rng.uniform(-1, 1) * cfg.yaw_offset)
        pitch = np.arctan2(aim[2], np.hypot(aim[0], aim[1])) + np.radians(rng.uniform(-1, 1) * cfg.pitch_offset)
        fwd = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        roll = np.radians(rng.uniform(-1, 1) * cfg.roll) if cfg.roll else 0.0
        cam = Camera(K=K, width=width, height=height, R=look_rotation(fwd, roll), C=C)
        if not cam.in_image(must_see, margin).all():
            continue
        if not clear(C, must_see):
            continue
        return cam
    return None


def ellipsoid_bbox(K: np.ndarray, centre: np.ndarray, R: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Tight image box (x1, y1, x2, y2) px of an ellipsoid in the camera frame (centre (3,),
    axes as the columns of R (3, 3), semi-axes (3,)), from its projected dual conic
    C* = K [I|0] Q* [I|0]^T K^T, Q* = T diag(a^2, b^2, c^2, -1) T^T. The ellipsoid must lie in
    front of the camera."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre
    Q = T @ np.diag([*(np.asarray(axes, np.float64) ** 2), -1.0]) @ T.T
    P = np.asarray(K, np.float64) @ np.eye(3, 4)
    C = P @ Q @ P.T
    out = []
    for i in (0, 1):  # tangent lines u = x: C[i,i] - 2 x C[i,2] + x^2 C[2,2] = 0
        disc = np.sqrt(max(C[i, 2] ** 2 - C[i, i] * C[2, 2], 0.0))
        out.append(sorted(((C[i, 2] - disc) / C[2, 2], (C[i, 2] + disc) / C[2, 2])))
    return np.array([out[0][0], out[1][0], out[0][1], out[1][1]])
