"""Rendering with Open3D's RaycastingScene: exact depth (z, metres), per-pixel instance ids and
Lambertian-shaded colour.

The room does not move within a scene, so each camera renders it once (`render_static`); each
frame then casts only the rays of the person's image bounding box against a small per-frame scene
holding the person (`render_person`) and keeps the nearer hit.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from .camera import Camera
from .config import RenderConfig
from .room import KINDS, Room

o3c = o3d.core


def _tensor(a: np.ndarray) -> o3c.Tensor:
    """An Open3D tensor of `a` (a copy, in its dtype, on the CPU)."""
    return o3c.Tensor(a)  # type: ignore[call-overload]  # open3d's stub omits the dtype and device defaults


def _lum(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.299, 0.587, 0.114], np.float32)


@dataclass
class View:
    """What one camera sees. depth: (H, W) float32 z in metres, 0 = no hit; instance: (H, W) int16,
    -1 = none; rgb: (H, W, 3) float32 shaded colour in [0, 1] (before sensor noise); albedo_lum:
    (H, W) float32 surface albedo luminance; shiny: (H, W) bool specular surface."""

    depth: np.ndarray
    instance: np.ndarray
    rgb: np.ndarray
    albedo_lum: np.ndarray
    shiny: np.ndarray

    def copy(self) -> View:
        return View(self.depth.copy(), self.instance.copy(), self.rgb.copy(), self.albedo_lum.copy(), self.shiny.copy())


class StaticScene:
    """The room's meshes in one RaycastingScene, with per-instance appearance tables."""

    def __init__(self, room: Room):
        self.room = room
        self.scene = o3d.t.geometry.RaycastingScene()
        n = len(room.instances)
        geom_to_inst = []
        for inst in room.instances:
            gid = self.scene.add_triangles(_tensor(inst.vertices.astype(np.float32)),
                                           _tensor(inst.triangles.astype(np.uint32)))
            geom_to_inst.append((gid, inst.id))
        lut = np.full(max(g for g, _ in geom_to_inst) + 2, -1, np.int16)
        for g, i in geom_to_inst:
            lut[g] = i
        self.geom_to_inst = lut
        self.albedo = np.stack([i.albedo for i in room.instances]).astype(np.float32)
        self.shiny = np.array([i.shiny for i in room.instances], bool)
        self.tex_dir = np.stack([i.tex_dir for i in room.instances]).astype(np.float32)
        self.tex_freq = np.array([i.tex_freq for i in room.instances], np.float32)
        self.kind = np.array([KINDS.index(i.kind) for i in room.instances], np.int8)
        assert n == len(self.albedo)

    def cast(self, rays: np.ndarray) -> dict[str, np.ndarray]:
        """Cast (N, 6) rays; returns t (N,) (inf = miss), instance (N,) int16 (-1 = miss),
        normal (N, 3) world."""
        out = self.scene.cast_rays(_tensor(np.ascontiguousarray(rays, np.float32)), nthreads=1)
        gid = out["geometry_ids"].numpy()
        hit = gid != o3d.t.geometry.RaycastingScene.INVALID_ID
        inst = np.full(gid.shape, -1, np.int16)
        inst[hit] = self.geom_to_inst[gid[hit]]
        return {"t": out["t_hit"].numpy(), "instance": inst, "normal": out["primitive_normals"].numpy()}

    def clear_path(self, origin: np.ndarray, points: np.ndarray, tol: float = 0.01) -> np.ndarray:
        """(N,) bool: nothing in the room lies between `origin` (3,) and each point (N, 3) (within
        tol metres of the point)."""
        points = np.atleast_2d(points)
        d = points - origin
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.broadcast_to(origin, d.shape), d], axis=1)
        t = self.cast(rays)["t"]
        return t >= 1.0 - tol / np.maximum(dist, 1e-9)


def shade(albedo: np.ndarray, normal: np.ndarray, view_dir: np.ndarray, points: np.ndarray,
          tex_dir: np.ndarray, tex_freq: np.ndarray, shiny: np.ndarray, light: np.ndarray,
          cfg: RenderConfig) -> np.ndarray:
    """Lambertian colour (N, 3) float32 of surface points.

    albedo (N, 3); normal (N, 3) unit world normals (flipped toward the viewer here); view_dir
    (N, 3) ray directions; points (N, 3) world; tex_dir (N, 3), tex_freq (N,) stripe texture;
    shiny (N,) adds a specular highlight; light (3,) direction the light travels.
    """
    f32 = np.float32
    light = np.asarray(light, f32)
    vd = view_dir.astype(f32, copy=False)
    vd = vd * (1.0 / np.sqrt(np.einsum("ij,ij->i", vd, vd)))[:, None]
    nrm = normal.astype(f32, copy=False)
    ndv = np.einsum("ij,ij->i", nrm, vd)
    sign = np.where(ndv > 0, f32(-1), f32(1))  # flip normals toward the viewer
    diffuse = np.maximum(f32(0), -sign * (nrm @ light))
    fill = np.abs(ndv)
    phase = (f32(2 * np.pi) * tex_freq.astype(f32, copy=False)) * np.einsum("ij,ij->i", points.astype(f32, copy=False),
                                                                           tex_dir.astype(f32, copy=False))
    lum = ((f32(cfg.ambient) + f32(cfg.diffuse) * diffuse + f32(cfg.fill) * fill)
           * (f32(1) + f32(cfg.texture) * np.sin(phase)))
    rgb = albedo.astype(f32, copy=False) * lum[:, None]
    if shiny.any():
        n = nrm * sign[:, None]
        r = light - 2 * (n @ light)[:, None] * n  # reflected light direction
        spec = np.maximum(f32(0), -np.einsum("ij,ij->i", r, vd)) ** 24
        rgb = rgb + (f32(0.7) * spec * shiny)[:, None]
    return rgb.astype(np.float32)


def render_static(static: StaticScene, cam: Camera, cfg: RenderConfig) -> View:
    """Render the room from `cam`."""
    H, W = cam.height, cam.width
    rays = cam.rays().reshape(-1, 6)
    hit = static.cast(rays)
    t, inst = hit["t"], hit["instance"]
    ok = inst >= 0
    sel = slice(None) if ok.all() else ok  # a closed room: every ray hits, skip the masking
    depth = np.where(ok, t, 0.0).astype(np.float32)
    rgb = np.full((H * W, 3), 0.05, np.float32)
    ii = inst[sel].astype(np.int64)
    d = rays[sel, 3:]
    pts = rays[sel, :3] + d * t[sel, None]
    rgb[sel] = shade(static.albedo[ii], hit["normal"][sel], d, pts, static.tex_dir[ii], static.tex_freq[ii],
                     static.shiny[ii], static.room.light, cfg)
    lum = np.zeros(H * W, np.float32)
    lum[sel] = _lum(static.albedo)[ii]
    shiny = np.zeros(H * W, bool)
    shiny[sel] = static.shiny[ii]
    return View(depth.reshape(H, W), inst.reshape(H, W), rgb.reshape(H, W, 3), lum.reshape(H, W), shiny.reshape(H, W))


def person_bbox(cam: Camera, vertices: np.ndarray) -> tuple[int, int, int, int] | None:
    """Pixel rectangle (x0, y0, x1, y1) (exclusive ends) covering the projected vertices, or None
    when the person is out of view."""
    pc = cam.to_cam(vertices)
    if (pc[:, 2] <= 0.05).all():
        return None
    if (pc[:, 2] <= 0.05).any():
        return 0, 0, cam.width, cam.height
    uv = cam.project(vertices)
    x0 = max(0, int(np.floor(uv[:, 0].min())) - 1)
    y0 = max(0, int(np.floor(uv[:, 1].min())) - 1)
    x1 = min(cam.width, int(np.ceil(uv[:, 0].max())) + 2)
    y1 = min(cam.height, int(np.ceil(uv[:, 1].max())) + 2)
    if x0 >= x1 or y0 >= y1:
        return None
    return x0, y0, x1, y1


class PersonScene:
    """One frame's person mesh in its own RaycastingScene."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, albedo: np.ndarray):
        self.vertices, self.albedo = vertices, albedo
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(_tensor(vertices.astype(np.float32)), _tensor(triangles.astype(np.uint32)))

    def cast(self, rays: np.ndarray) -> dict[str, np.ndarray]:
        out = self.scene.cast_rays(_tensor(np.ascontiguousarray(rays, np.float32)), nthreads=1)
        return {"t": out["t_hit"].numpy(), "prim": out["primitive_ids"].numpy(),
                "normal": out["primitive_normals"].numpy()}


def render_person(base: View, cam: Camera, person: PersonScene, person_id: int, light: np.ndarray,
                  cfg: RenderConfig) -> View:
    """`base` (not modified) with the person drawn over it where the person is nearer."""
    view = base.copy()
    box = person_bbox(cam, person.vertices)
    if box is None:
        return view
    x0, y0, x1, y1 = box
    rays = cam.rays(x0, y0, x1, y1).reshape(-1, 6)
    hit = person.cast(rays)
    t = hit["t"]
    zb = base.depth[y0:y1, x0:x1].ravel()
    near = np.isfinite(t) & ((zb == 0) | (t < zb))
    if not near.any():
        return view
    idx = np.flatnonzero(near)
    vv, uu = np.divmod(idx, x1 - x0)
    vv, uu = vv + y0, uu + x0
    alb = person.albedo[hit["prim"][idx]]
    d = rays[idx, 3:]
    pts = rays[idx, :3] + d * t[idx, None]
    n = len(idx)
    rgb = shade(alb, hit["normal"][idx], d, pts, np.tile([0.0, 0.0, 1.0], (n, 1)).astype(np.float32),
                np.full(n, 20.0, np.float32), np.zeros(n, bool), light, cfg)
    view.depth[vv, uu] = t[idx]
    view.instance[vv, uu] = person_id
    view.rgb[vv, uu] = rgb
    view.albedo_lum[vv, uu] = _lum(alb)
    view.shiny[vv, uu] = False
    return view
