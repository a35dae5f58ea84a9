"""Gaze targets: a point on an object both the person and the camera can see, a point in empty
space in view, or a surface point out of the camera's view.

`target_kind` codes in the truth: 0 object, 1 space, 2 out_of_view (config.TARGET_KINDS order).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .config import TARGET_KINDS, GazeConfig
from .gaze import unit, wrap
from .render import StaticScene, View
from .room import Room

OBJECT, SPACE, OUT_OF_VIEW = 0, 1, 2


@dataclass
class Target:
    kind: int            # OBJECT, SPACE or OUT_OF_VIEW
    instance: int        # the object's instance id (any surface hit for OUT_OF_VIEW), -1 for SPACE
    point: np.ndarray    # (3,) world


class TargetSampler:
    """Draws targets for one scene, checked against the primary camera's static view."""

    def __init__(self, room: Room, static: StaticScene, cams: list[Camera], views: list[View], cfg: GazeConfig,
                 in_front: bool):
        """cams/views: the scene's cameras and static renders; the first one is primary (space
        targets must be in its view, out-of-view targets outside it); object targets must be seen
        by at least one camera."""
        self.room, self.static, self.cams, self.views, self.cfg = room, static, cams, views, cfg
        self.cam = cams[0]
        self.in_front = in_front  # out-of-view targets must still lie in front of the camera (2D annotation)
        n = len(room.instances)
        self.pixels = sum((np.bincount(v.instance[v.instance >= 0].astype(np.int64), minlength=n)[:n] for v in views),
                          np.zeros(n, np.int64))
        self.min_pixels = max(2, int(round(30 * self.cam.width * self.cam.height / (640 * 480))))
        self.objects = np.array([i.id for i in room.instances if i.kind == "object"], np.int64)
        kinds = list(TARGET_KINDS)
        self.mix = np.array([cfg.target_mix.get(k, 0.0) for k in kinds])
        self.mix = self.mix / self.mix.sum()

    def sample(self, rng: np.random.Generator, eye: np.ndarray, heading: float, turn: bool = False) -> Target:
        """A target for a person whose eye is near `eye` (3,) facing `heading` (rad); with `turn`
        (a standing person, who can turn round) objects in any direction qualify."""
        kind = int(rng.choice(3, p=self.mix))
        order = {OBJECT: (OBJECT, SPACE, OUT_OF_VIEW), SPACE: (SPACE, OBJECT, OUT_OF_VIEW),
                 OUT_OF_VIEW: (OUT_OF_VIEW, SPACE, OBJECT)}[kind]
        for k in order:
            t = self._object(rng, eye, heading, turn) if k == OBJECT else \
                (self._space, self._out_of_view)[k - 1](rng, eye, heading)
            if t is not None:
                return t
        # nothing fits (e.g. facing a wall at close range): look at the space ahead
        d = np.array([np.cos(heading), np.sin(heading), -0.2])
        return Target(SPACE, -1, eye + 0.8 * unit(d))

    def _camera_sees(self, pts: np.ndarray, inst: int) -> np.ndarray:
        """(N,) bool: the surface points are visible (unoccluded) in at least one camera."""
        out = np.zeros(len(pts), bool)
        for cam, view in zip(self.cams, self.views):
            pc = cam.to_cam(pts)
            uv = cam.project(pts)
            ok = np.isfinite(uv).all(axis=1)
            u = np.round(np.nan_to_num(uv[:, 0], nan=-1)).astype(int)
            v = np.round(np.nan_to_num(uv[:, 1], nan=-1)).astype(int)
            ok &= (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
            i = np.flatnonzero(ok)
            z = view.depth[v[i], u[i]]
            out[i] |= (view.instance[v[i], u[i]] == inst) & (np.abs(z - pc[i, 2]) < 0.01 + 0.01 * pc[i, 2])
        return out

    def _object(self, rng, eye, heading, turn=False) -> Target | None:
        cfg = self.cfg
        objs = self.objects[self.pixels[self.objects] >= self.min_pixels] if len(self.objects) else self.objects
        if not len(objs):
            return None
        cen = np.stack([self.room.instances[i].centroid for i in objs])
        d = cen - eye
        dist = np.linalg.norm(d, axis=1)
        yaw = np.abs([wrap(np.arctan2(y, x) - heading) for x, y in d[:, :2]])
        pitch = np.arcsin(np.clip(d[:, 2] / np.maximum(dist, 1e-9), -1, 1))
        ok = ((dist >= cfg.object_distance[0]) & (dist <= cfg.object_distance[1])
              & ((yaw <= np.radians(cfg.max_target_yaw)) | turn) & (pitch > np.radians(-65)) & (pitch < np.radians(45)))
        cand = objs[ok]
        for inst in rng.permutation(cand)[:12]:
            samples = self.room.instances[int(inst)].samples
            pts = samples[rng.choice(len(samples), size=min(16, len(samples)), replace=False)].astype(np.float64)
            good = self._camera_sees(pts, int(inst))
            if not good.any():
                continue
            pts = pts[good]
            seen = self.static.clear_path(eye, pts, tol=0.01)
            if seen.any():
                return Target(OBJECT, int(inst), pts[int(np.flatnonzero(seen)[0])])
        return None

    def _directions(self, rng, heading, yaw_lim, pitch_range, n) -> np.ndarray:
        yaw = heading + np.radians(rng.uniform(-yaw_lim, yaw_lim, n))
        pitch = np.radians(rng.uniform(*pitch_range, n))
        return np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=1)

    def _cast(self, eye, d) -> dict[str, np.ndarray]:
        rays = np.concatenate([np.broadcast_to(eye, d.shape), d], axis=1).astype(np.float32)
        return self.static.cast(rays)

    def _space(self, rng, eye, heading) -> Target | None:
        """A point in mid-air in the primary view, short of the first surface along its ray."""
        d = self._directions(rng, heading, 60.0, (-35.0, 10.0), 24)
        t = self._cast(eye, d)["t"]
        dist = np.minimum(rng.uniform(0.8, 3.0, len(d)), 0.85 * t)
        p = eye + dist[:, None] * d
        ok = (dist >= 0.4) & self.cam.in_image(p, 0.02 * self.cam.width)
        if not ok.any():
            return None
        return Target(SPACE, -1, p[int(np.flatnonzero(ok)[0])])

    def _out_of_view(self, rng, eye, heading) -> Target | None:
        """A surface point the person can see that the primary camera does not."""
        d = self._directions(rng, heading, 0.7 * self.cfg.max_target_yaw, (-35.0, 20.0), 48)
        hit = self._cast(eye, d)
        t = hit["t"]
        ok = np.isfinite(t) & (t >= 0.4)
        p = eye + np.where(ok, t, 1.0)[:, None] * d
        ok &= ~self.cam.in_image(p)
        if self.in_front:
            ok &= self.cam.to_cam(p)[:, 2] >= 0.1
        if not ok.any():
            return None
        i = int(np.flatnonzero(ok)[0])
        return Target(OUT_OF_VIEW, int(hit["instance"][i]), p[i])
