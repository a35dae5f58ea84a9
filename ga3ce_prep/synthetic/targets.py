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

    def __init__(self, room: Room, static: StaticScene, cam: Camera, view: View, cfg: GazeConfig,
                 in_front: bool):
        self.room, self.static, self.cam, self.view, self.cfg = room, static, cam, view, cfg
        self.in_front = in_front  # out-of-view targets must still lie in front of the camera (2D annotation)
        inst = view.instance[view.instance >= 0].astype(np.int64)
        self.pixels = np.bincount(inst, minlength=len(room.instances))
        self.min_pixels = max(8, int(30 * cam.width * cam.height / (640 * 480)))
        self.objects = np.array([i.id for i in room.instances if i.kind == "object"], np.int64)
        kinds = list(TARGET_KINDS)
        self.mix = np.array([cfg.target_mix.get(k, 0.0) for k in kinds])
        self.mix = self.mix / self.mix.sum()

    def sample(self, rng: np.random.Generator, eye: np.ndarray, heading: float) -> Target:
        """A target for a person whose eye is near `eye` (3,) facing `heading` (rad)."""
        kind = int(rng.choice(3, p=self.mix))
        order = {OBJECT: (OBJECT, SPACE, OUT_OF_VIEW), SPACE: (SPACE, OBJECT, OUT_OF_VIEW),
                 OUT_OF_VIEW: (OUT_OF_VIEW, SPACE, OBJECT)}[kind]
        for k in order:
            t = (self._object, self._space, self._out_of_view)[k](rng, eye, heading)
            if t is not None:
                return t
        # nothing fits (e.g. facing a wall at close range): look at the space ahead
        d = np.array([np.cos(heading), np.sin(heading), -0.2])
        return Target(SPACE, -1, eye + 0.8 * unit(d))

    def _camera_sees(self, pts: np.ndarray, inst: int) -> np.ndarray:
        pc = self.cam.to_cam(pts)
        uv = self.cam.project(pts)
        ok = np.isfinite(uv).all(axis=1)
        u = np.round(np.nan_to_num(uv[:, 0], nan=-1)).astype(int)
        v = np.round(np.nan_to_num(uv[:, 1], nan=-1)).astype(int)
        ok &= (u >= 0) & (v >= 0) & (u < self.cam.width) & (v < self.cam.height)
        out = np.zeros(len(pts), bool)
        i = np.flatnonzero(ok)
        z = self.view.depth[v[i], u[i]]
        out[i] = (self.view.instance[v[i], u[i]] == inst) & (np.abs(z - pc[i, 2]) < 0.01 + 0.01 * pc[i, 2])
        return out

    def _object(self, rng, eye, heading) -> Target | None:
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
              & (yaw <= np.radians(cfg.max_target_yaw)) & (pitch > np.radians(-65)) & (pitch < np.radians(45)))
        cand = objs[ok]
        for inst in rng.permutation(cand)[:6]:
            samples = self.room.instances[int(inst)].samples
            pts = samples[rng.choice(len(samples), size=min(12, len(samples)), replace=False)].astype(np.float64)
            good = self._camera_sees(pts, int(inst))
            if not good.any():
                continue
            pts = pts[good]
            seen = self.static.clear_path(eye, pts, tol=0.01)
            if seen.any():
                return Target(OBJECT, int(inst), pts[int(np.flatnonzero(seen)[0])])
        return None

    def _space(self, rng, eye, heading) -> Target | None:
        for _ in range(12):
            yaw = heading + np.radians(rng.uniform(-60, 60))
            pitch = np.radians(rng.uniform(-35, 10))
            d = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
            t = float(self.static.cast(np.concatenate([eye, d])[None].astype(np.float32))["t"][0])
            dist = min(rng.uniform(0.8, 3.0), 0.85 * t)
            if dist < 0.4:
                continue
            p = eye + dist * d
            if self.cam.in_image(p, 0.02 * self.cam.width):
                return Target(SPACE, -1, p)
        return None

    def _out_of_view(self, rng, eye, heading) -> Target | None:
        lim = self.cfg.max_target_yaw
        for _ in range(16):
            yaw = heading + np.radians(rng.uniform(-lim, lim))
            pitch = np.radians(rng.uniform(-40, 20))
            d = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
            hit = self.static.cast(np.concatenate([eye, d])[None].astype(np.float32))
            t, inst = float(hit["t"][0]), int(hit["instance"][0])
            if not np.isfinite(t) or t < 0.4:
                continue
            p = eye + t * d
            if self.cam.in_image(p):
                continue
            if self.in_front and self.cam.to_cam(p)[2] < 0.1:
                continue
            return Target(OUT_OF_VIEW, inst, p)
        return None
