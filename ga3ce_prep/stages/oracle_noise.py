"""Seeded, calibrated noise for the `oracle` backends (the synthetic world only).

Every random draw comes from `frame_rng(seed, stream, frame_id)`: a generator seeded by the run's
seed, the backend's stream name and the frame id alone, so a frame gets the same noise whatever
the sharding, the order, the worker or a kill-and-resume in between.

View noise (`noisy_view`). The view prior v of an appearance network is the truth gaze g, pulled
partly toward the head direction h, plus random error. In the tangent plane of g (coordinates in
radians; the exponential map sends a tangent vector e to the unit vector at angle |e| from g in
e's direction) we set

    e = d + sigma * n,   d = head_weight * log_g(h),   n ~ N(0, I_2),   v = exp_g(e)

so angle(v, g) = |e| exactly. |e| is Rice-distributed; its mean is sigma * f(|d| / sigma) with
f(r) = E|r e_1 + n|. Per frame, sigma is solved so that E angle(v, g) equals the requested mean
error m; with head_weight = 0 this is sigma = m / sqrt(pi / 2) (a Rayleigh angle). A frame whose
pull alone exceeds m (|d| >= m) gets sigma = 0 and angle |d| > m, so the mean error is exact only
while head_weight * angle(g, h) < m for every frame (about 25 degrees of eye-in-head offset times
head_weight 0.5 stays well inside the default m = 20 degrees).

Pose noise (`noisy_pose`): per joint isotropic Gaussian offsets (sigma_face on the six face
joints, as RGB pose estimators are least accurate there, sigma_body elsewhere), then a per-frame
scale about the camera centre, exp(N(log scale_bias, scale_sigma)), which is how an RGB-only
estimator's depth ambiguity shows, and a per-frame offset N(0, offset_sigma^2 I).

Articulated pose noise (`articulated_pose`): the errors of a 3D pose estimator are a skeleton's, not
independent per joint. Every joint's bone (from its parent, skeleton.PARENTS) turns by a small
random rotation, axis-angle N(0, bone_sigma^2 I) radians, the root's turning the whole body; the
rotations compose down the chains (forward kinematics), so bone lengths are kept and a limb's error
grows along it; the six face joints turn together by one head rotation N(0, head_sigma^2 I) about
the head joint, so the face moves as one. The root then moves by N(0, ray_sigma^2) along the camera
ray (the depth ambiguity) plus N(0, lateral_sigma^2 I). Each draw is sqrt(persistence) x the
session's draw + sqrt(1 - persistence) x the frame's, so a share `persistence` of the error
variance stays the same over a recording.
"""
from __future__ import annotations

import hashlib
from functools import lru_cache

import numpy as np

from ..geometry import normalize
from ..skeleton import HEAD_JOINTS, N_JOINTS


def frame_rng(seed: int, stream: str, frame_id: str) -> np.random.Generator:
    """A generator that depends only on (seed, stream, frame id)."""
    digest = hashlib.sha256(f"{stream}\0{frame_id}".encode()).digest()
    words = np.frombuffer(digest[:16], dtype=np.uint32).tolist()
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, *words]))


def tangent_basis(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (3,) orthogonal to the unit vector g and to each other (right-handed)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(g[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = normalize(np.cross(g, a))
    e2 = np.cross(g, e1)
    return e1, e2


def log_map(g: np.ndarray, h: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Tangent coordinates (2,) at unit g of unit h: direction of h from g, length angle(g, h)."""
    c = float(np.clip(np.dot(g, h), -1.0, 1.0))
    t = h - c * g
    n = float(np.linalg.norm(t))
    if n < 1e-12:
        return np.zeros(2)
    ang = float(np.arccos(c))
    return ang * np.array([np.dot(t, e1), np.dot(t, e2)]) / n


def exp_map(g: np.ndarray, e: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """The unit vector at angle |e| from unit g in the tangent direction e (2,)."""
    a = float(np.hypot(e[0], e[1]))
    if a < 1e-12:
        return g.copy()
    t = (e[0] * e1 + e[1] * e2) / a
    return np.cos(a) * g + np.sin(a) * t


@lru_cache(maxsize=1)
def _rice_table() -> tuple[np.ndarray, np.ndarray]:
    """r and f(r) = E|r e_1 + n|, n ~ N(0, I_2), for r in [0, 8], by quadrature of the Rice density:
    f(r) = int_0^inf rho^2 exp(-(rho - r)^2 / 2) [I0(rho r) exp(-rho r)] d rho."""
    r = np.linspace(0.0, 8.0, 321)
    rho = np.linspace(0.0, 20.0, 2001)
    R, P = np.meshgrid(r, rho, indexing="ij")
    x = P * R
    # exp(-x) I0(x) without overflow: numpy's i0 for x < 50, the asymptotic series beyond
    with np.errstate(over="ignore", invalid="ignore"):
        small = np.exp(-np.minimum(x, 50.0)) * np.i0(np.minimum(x, 50.0))
    xs = np.maximum(x, 1e-9)
    large = (1 + 1 / (8 * xs) + 9 / (128 * xs**2)) / np.sqrt(2 * np.pi * xs)
    i0e = np.where(x < 50.0, small, large)
    f = np.asarray(np.trapezoid(P**2 * np.exp(-0.5 * (P - R) ** 2) * i0e, rho, axis=1))
    return r, f


def rice_sigma(offset: float, mean: float) -> float:
    """The sigma for which E|d + sigma n| = mean, with |d| = offset (radians); 0 if offset >= mean."""
    if offset >= mean:
        return 0.0
    if offset <= 1e-12:
        return mean / np.sqrt(np.pi / 2)
    r, f = _rice_table()
    q = mean / offset  # f(r) / r = q  <=>  h(r) = f(r) - q r = 0, h decreasing (f' <= 1 < q)
    h = f - q * r
    if h[-1] > 0:
        rr = 1.0 / np.sqrt(max(q * q - 1.0, 1e-12))  # beyond the table: f(r) ~ sqrt(r^2 + 1)
    else:
        k = int(np.argmax(h <= 0))  # first node past the root (h[0] = f(0) > 0)
        rr = float(r[k - 1] + (r[k] - r[k - 1]) * h[k - 1] / (h[k - 1] - h[k]))
    return offset / rr


def noisy_view(gaze: np.ndarray, head_dir: np.ndarray | None, rng: np.random.Generator,
               mean_error_deg: float, head_weight: float = 0.0) -> np.ndarray:
    """The view prior v (3,) float32 unit: truth gaze pulled toward head_dir by head_weight, plus
    calibrated noise (module docstring). gaze, head_dir: (3,) camera-frame directions."""
    g = normalize(np.asarray(gaze, np.float64))
    e1, e2 = tangent_basis(g)
    d = np.zeros(2)
    if head_weight > 0 and head_dir is not None and np.all(np.isfinite(head_dir)):
        d = head_weight * log_map(g, normalize(np.asarray(head_dir, np.float64)), e1, e2)
    m = np.radians(mean_error_deg)
    sigma = rice_sigma(float(np.hypot(*d)), float(m))
    n = rng.standard_normal(2)
    return exp_map(g, d + sigma * n, e1, e2).astype(np.float32)


def noisy_pose(pose: np.ndarray, rng: np.random.Generator, sigma_body: float, sigma_face: float,
               scale_sigma: float = 0.0, scale_bias: float = 1.0, offset_sigma: float = 0.0) -> np.ndarray:
    """Truth pose (30, 3) metres plus estimator-like noise (module docstring); (30, 3) float32."""
    pose = np.asarray(pose, np.float64)
    sig = np.full((N_JOINTS, 1), sigma_body)
    sig[list(HEAD_JOINTS)] = sigma_face
    noise = rng.standard_normal((N_JOINTS, 3)) * sig
    scale = scale_bias * np.exp(scale_sigma * rng.standard_normal())
    offset = offset_sigma * rng.standard_normal(3)
    return ((pose + noise) * scale + offset).astype(np.float32)


def rotation_matrices(w: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of axis-angle vectors w (..., 3) radians (Rodrigues)."""
    theta = np.linalg.norm(w, axis=-1, keepdims=True)
    k = np.where(theta > 1e-12, w / np.maximum(theta, 1e-12), 0.0)
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = k[..., 2], -k[..., 1], k[..., 0]
    t = theta[..., None]
    return np.eye(3) + np.sin(t) * K + (1.0 - np.cos(t)) * (K @ K)


def articulated_pose(pose: np.ndarray, frame: np.random.Generator, session: np.random.Generator,
                     bone_sigma_deg: float, head_sigma_deg: float, ray_sigma: float = 0.0,
                     lateral_sigma: float = 0.0, persistence: float = 0.0) -> np.ndarray:
    """Truth pose (30, 3) metres, camera frame, with an articulated estimator's error (module
    docstring); (30, 3) float32. frame, session: the frame's and its recording's generators."""
    from ..skeleton import PARENTS

    a, b = np.sqrt(persistence), np.sqrt(1.0 - persistence)

    def draw(*shape: int) -> np.ndarray:
        return a * session.standard_normal(shape) + b * frame.standard_normal(shape)

    P = np.asarray(pose, np.float64)
    w = draw(N_JOINTS, 3) * np.radians(bone_sigma_deg)
    w[list(HEAD_JOINTS)] = draw(3) * np.radians(head_sigma_deg)
    R = rotation_matrices(w)
    A = np.empty((N_JOINTS, 3, 3))
    out = np.empty_like(P)
    ray = normalize(P[0]) if np.linalg.norm(P[0]) > 0 else np.array([0.0, 0.0, 1.0])
    A[0], out[0] = R[0], P[0] + draw(1)[0] * ray_sigma * ray + draw(3) * lateral_sigma
    for j in range(1, N_JOINTS):   # parents come first (skeleton.PARENTS)
        p = PARENTS[j]
        A[j] = A[p] @ R[j]
        out[j] = out[p] + A[j] @ (P[j] - P[p])
    return out.astype(np.float32)
