"""Non-learned baselines every evaluation reports on the same frames as the model.

- the view prior v itself (GA3CE's "appearance only" row);
- the head direction implied by the pose keypoints (`skeleton.head_direction_from_pose`);
- snap to object: v replaced by the direction from the head (t_object) to the stored object
  closest in angle to v, when that object lies within a cone of half-angle `cone_deg` around v.
All numpy, vectorised; directions are unit (n, 3), camera frame.
"""
from __future__ import annotations

import numpy as np

from ..geometry import angular_error_deg, normalize

SNAP_CONES_DEG: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 40.0)


def snap_to_object(view: np.ndarray, head_pos: np.ndarray, objects: np.ndarray, mask: np.ndarray,
                   cone_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Snap v to the nearest object direction within the cone.

    view (n, 3) unit, head_pos (n, 3), objects (n, S, 3) padded, mask (n, S) True = real.
    Returns (directions (n, 3), snapped (n,) bool)."""
    d = normalize(objects - head_pos[:, None])
    cos = np.where(mask, np.einsum("nsk,nk->ns", d, view), -np.inf)
    if cos.shape[1] == 0:
        return view.copy(), np.zeros(len(view), bool)
    best = np.argmax(cos, axis=1)
    best_cos = cos[np.arange(len(view)), best]
    snapped = best_cos >= np.cos(np.radians(cone_deg))
    out = np.where(snapped[:, None], d[np.arange(len(view)), best], view)
    return out, snapped


def choose_snap_cone(view: np.ndarray, head_pos: np.ndarray, objects: np.ndarray, mask: np.ndarray,
                     gaze: np.ndarray, cones: tuple[float, ...] = SNAP_CONES_DEG) -> float:
    """The cone (degrees) with the lowest 3D MAE on the given (validation) frames."""
    maes = [float(angular_error_deg(snap_to_object(view, head_pos, objects, mask, c)[0], gaze).mean())
            for c in cones]
    return float(cones[int(np.argmin(maes))])
