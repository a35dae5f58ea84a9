"""The rotations of GA3CE's egocentric transform: R maps the view prior v onto z = (0, 0, 1).

Both functions take numpy arrays or torch tensors (the same code runs on either; results agree to
float precision) and are batched over leading axes: v (..., 3) -> R (..., 3, 3), with R v = z.
Camera frame: x right, y down, z forward. v need not be unit length (it is normalised here).
"""
from __future__ import annotations

from types import ModuleType
from typing import TypeVar

import numpy as np
import torch

Array = TypeVar("Array", np.ndarray, torch.Tensor)

ROTATIONS: tuple[str, ...] = ("cyclotorsion", "axis_angle", "none")


def _xp(a: np.ndarray | torch.Tensor) -> ModuleType:
    """The array namespace of `a`: torch for tensors, numpy otherwise."""
    return torch if isinstance(a, torch.Tensor) else np


def _unit(v: Array) -> Array:
    if isinstance(v, torch.Tensor):
        return v / torch.sqrt((v * v).sum(-1, keepdim=True)).clamp_min(1e-30)
    return v / (np.sqrt((v * v).sum(-1, keepdims=True)) + 1e-30)


def _matrix(rows: list[list[Array]]) -> Array:
    """Stack a 3x3 nested list of (...,) arrays into (..., 3, 3)."""
    xp = _xp(rows[0][0])
    return xp.stack([xp.stack(r, -1) for r in rows], -2)


def cyclotorsion_rotation(v: Array) -> Array:
    """GA3CE's cyclotorsion-free rotation R = Rx(theta) Ry(phi) with R v = z.

    phi = atan2(-v_x, v_z) turns v about the y axis into the y-z plane, then
    theta = atan2(v_y, v_z cos(phi) - v_x sin(phi)) tilts it about x onto z. The first row of R is
    (cos phi, 0, sin phi): the rotated x axis stays in the camera's horizontal plane, so the
    egocentric frame has no roll (no cyclotorsion about the gaze axis).

    v: (..., 3) direction (any length). Returns R: (..., 3, 3), same type and dtype as v.
    Defined everywhere: at v = +-y, phi = 0 and theta = +-pi/2; at v = -z, phi = pi.
    """
    xp = _xp(v)
    v = _unit(v)
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    phi = xp.arctan2(-vx, vz)
    cp, sp = xp.cos(phi), xp.sin(phi)
    theta = xp.arctan2(vy, vz * cp - vx * sp)
    ct, st = xp.cos(theta), xp.sin(theta)
    zero = xp.zeros_like(vx)
    # Rx(theta) @ Ry(phi), written out
    return _matrix([[cp, zero, sp],
                    [st * sp, ct, -st * cp],
                    [-ct * sp, st, ct * cp]])


def axis_angle_rotation(v: Array) -> Array:
    """The "no cyclotorsion" ablation: the shortest rotation taking v to z, about the axis v x z by
    the angle arccos(v . z) (Rodrigues). It rolls the frame about the gaze axis for generic v.

    v: (..., 3) direction (any length). Returns R: (..., 3, 3), R v = z. At v = z exactly R = I;
    at v = -z exactly (axis undefined) it is the half turn about x, diag(1, -1, -1).
    """
    xp = _xp(v)
    v = _unit(v)
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    # axis w = v x z = (v_y, -v_x, 0); sin = |w|, cos = v_z (sin^2 + cos^2 = 1 exactly for unit v)
    s = xp.sqrt(vx * vx + vy * vy)
    c = vz
    degenerate = s < 1e-30
    safe = xp.where(degenerate, xp.ones_like(s), s)
    kx = xp.where(degenerate, xp.ones_like(s), vy / safe)
    ky = xp.where(degenerate, xp.zeros_like(s), -vx / safe)
    t = 1.0 - c
    # R = c I + s [k]x + (1 - c) k k^T with k = (kx, ky, 0)
    return _matrix([[c + t * kx * kx, t * kx * ky, s * ky],
                    [t * kx * ky, c + t * ky * ky, -s * kx],
                    [-s * ky, s * kx, c]])


def identity_rotation(v: Array) -> Array:
    """The "no egocentric transform" ablation: R = I for every frame. v: (..., 3) -> (..., 3, 3)."""
    if isinstance(v, torch.Tensor):
        return torch.eye(3, dtype=v.dtype, device=v.device).expand(*v.shape[:-1], 3, 3).clone()
    return np.broadcast_to(np.eye(3, dtype=v.dtype), (*v.shape[:-1], 3, 3)).copy()


def rotation(name: str, v: Array) -> Array:
    """R for the named variant: "cyclotorsion" (GA3CE), "axis_angle" or "none" (identity)."""
    fns = {"cyclotorsion": cyclotorsion_rotation, "axis_angle": axis_angle_rotation,
           "none": identity_rotation}
    if name not in fns:
        raise ValueError(f"unknown rotation {name!r}; choose one of {ROTATIONS}")
    return fns[name](v)
