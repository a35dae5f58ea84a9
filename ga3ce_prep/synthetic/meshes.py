"""Triangle meshes as plain numpy arrays: unit templates made once with Open3D, then scaled,
rotated and moved with numpy (building Open3D meshes per object or per frame would cost more
than rendering them).

A mesh is `(vertices (V, 3) float32 metres, triangles (F, 3) int32)`.
"""
from __future__ import annotations

from functools import cache

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def _from_o3d(m) -> Mesh:
    return np.asarray(m.vertices, np.float64), np.asarray(m.triangles, np.int32)


@cache
def template(name: str) -> Mesh:
    """A unit template centred at the origin, z up.

    Shapes fit the box [-0.5, 0.5]^3 (the torus is 1 x 1 x 0.25): box, cylinder, sphere, cone,
    torus, ellipsoid (= sphere, scaled per axis later), octahedron. Body parts (person): "limb"
    (cylinder of radius 1 from z=0 to z=1, 10 sides) and "ball" (sphere of radius 1, coarse).
    """
    import open3d as o3d

    g = o3d.geometry.TriangleMesh
    if name == "box":
        v, f = _from_o3d(g.create_box(1.0, 1.0, 1.0))
        v = v - 0.5
    elif name == "cylinder":
        v, f = _from_o3d(g.create_cylinder(radius=0.5, height=1.0, resolution=20, split=1))
    elif name in ("sphere", "ellipsoid"):
        v, f = _from_o3d(g.create_sphere(radius=0.5, resolution=10))
    elif name == "cone":
        v, f = _from_o3d(g.create_cone(radius=0.5, height=1.0, resolution=20, split=1))
        v = v - np.array([0.0, 0.0, 0.5])
    elif name == "torus":
        v, f = _from_o3d(g.create_torus(torus_radius=0.375, tube_radius=0.125, radial_resolution=20,
                                        tubular_resolution=10))
    elif name == "octahedron":
        v, f = _from_o3d(g.create_octahedron(radius=0.5))
    elif name == "limb":
        v, f = _from_o3d(g.create_cylinder(radius=1.0, height=1.0, resolution=10, split=1))
        v = v + np.array([0.0, 0.0, 0.5])
    elif name == "ball":
        v, f = _from_o3d(g.create_sphere(radius=1.0, resolution=6))
    elif name == "head":
        v, f = _from_o3d(g.create_sphere(radius=1.0, resolution=12))
    else:
        raise KeyError(f"no mesh template {name!r}")
    v.setflags(write=False)
    f.setflags(write=False)
    return v, f


def transformed(name: str, scale, R: np.ndarray | None = None, t=(0.0, 0.0, 0.0)) -> Mesh:
    """Template `name` scaled per axis by `scale` (3,), rotated by R (3, 3), moved by t (3,)."""
    v, f = template(name)
    v = v * np.asarray(scale, np.float64)
    if R is not None:
        v = v @ np.asarray(R, np.float64).T
    return (v + np.asarray(t, np.float64)).astype(np.float32), f


def box(lo, hi) -> Mesh:
    """An axis-aligned box from corner lo (3,) to corner hi (3,)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return transformed("box", hi - lo, None, 0.5 * (lo + hi))


def quad(corners) -> Mesh:
    """A planar quad from 4 corners in order (two triangles)."""
    return np.asarray(corners, np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def merge(meshes: list[Mesh]) -> Mesh:
    """One mesh from many (vertex indices offset)."""
    vs, fs, n = [], [], 0
    for v, f in meshes:
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs).astype(np.float32), np.concatenate(fs).astype(np.int32)


def rot_z(a: float) -> np.ndarray:
    """Rotation by angle a (rad) about z."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    """Rotation by angle a (rad) about y."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(a: float) -> np.ndarray:
    """Rotation by angle a (rad) about x."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def cross3(a, b) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs ~20 us per call on single vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def align_z(d: np.ndarray) -> np.ndarray:
    """A rotation taking +z to the unit direction d (3,)."""
    d = np.asarray(d, np.float64)
    d = d / max(np.linalg.norm(d), 1e-12)
    z = np.array([0.0, 0.0, 1.0])
    c = float(d @ z)
    if c < -1 + 1e-9:
        return np.diag([1.0, -1.0, -1.0])
    k = cross3(z, d)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + kx + kx @ kx / (1.0 + c)


def surface_samples(mesh: Mesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points (n, 3) uniform on the mesh surface (area-weighted triangles, uniform barycentric)."""
    v, f = mesh
    a, b, c = v[f[:, 0]].astype(np.float64), v[f[:, 1]].astype(np.float64), v[f[:, 2]].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)  # (F, 3) rows: vectorised
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return w[:, :1] * a[tri] + w[:, 1:2] * b[tri] + w[:, 2:] * c[tri]
