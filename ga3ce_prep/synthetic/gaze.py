"""How head and body follow the gaze.

The gaze goes from the eye midpoint to the target. The torso turns `body_follow` of the yaw from
the person's heading to the gaze; the head turns `head_follow` of the angle from the torso's
forward direction to the gaze (a slerp), then a small random error is added; the eyes do the rest,
but never more than `eye_offset_max` degrees: beyond it the head catches up. With head_follow
below 0.5 the eye-in-head offset is larger than the head turn, as in natural gaze shifts.
"""
from __future__ import annotations

import numpy as np

from .meshes import cross3
from .person import from_rotvec


def unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (rad) between two directions."""
    return float(np.arccos(np.clip(unit(a) @ unit(b), -1.0, 1.0)))


def slerp(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """The unit direction t of the way from a to b along the great circle (t may exceed 1)."""
    a, b = unit(a), unit(b)
    th = np.arccos(np.clip(a @ b, -1.0, 1.0))
    if th < 1e-9:
        return a
    if np.pi - th < 1e-6:  # opposite: turn about z (or any axis orthogonal to a)
        ax = unit(cross3(a, [0.0, 0.0, 1.0])) if abs(a[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
        return unit(np.cos(t * np.pi) * a + np.sin(t * np.pi) * ax)
    return unit((np.sin((1 - t) * th) * a + np.sin(t * th) * b) / np.sin(th))


def yaw_of(v: np.ndarray) -> float:
    return float(np.arctan2(v[1], v[0]))


def wrap(a: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def head_direction(gaze: np.ndarray, torso_forward: np.ndarray, head_follow: float, eye_offset_max: float,
                   jitter: np.ndarray | None = None, previous: np.ndarray | None = None,
                   smoothing: float = 1.0) -> np.ndarray:
    """The head's forward direction (3,) for a gaze direction (3,).

    head_follow: share of the torso-to-gaze angle the head turns; eye_offset_max: cap (rad) on the
    angle between head and gaze; jitter: (3,) rotation vector of the head's random error;
    previous + smoothing (0..1, share of the way toward the new direction per frame): temporal
    smoothing for continuous sequences.
    """
    h = slerp(torso_forward, gaze, head_follow)
    if jitter is not None:
        h = from_rotvec(jitter) @ h
    if previous is not None and smoothing < 1.0:
        h = slerp(previous, h, smoothing)
    off = angle(h, gaze)
    if off > eye_offset_max:
        h = slerp(gaze, h, eye_offset_max / off)
    return unit(h)

