"""Gaze metrics in degrees (docs/paper.md; GAFA's conventions from its `eval.py` and `models/utils.py`).

3D MAE: mean angle between predicted and true directions. 2D MAE (GAFA): keep the camera-frame x
and y of both vectors, re-normalise, take the angle; frames whose x-y part vanishes are skipped.
Front / back (GAFA): front when the true gaze has z <= 0 (it points toward the camera), per frame,
or per window from its first frame as GAFA's `test_step` decides it (`front` given). All means
are plain per-frame means (GAFA's released code averages per batch in `models/gazenet.py`).
"""
from __future__ import annotations

import numpy as np

from ..geometry import angular_error_deg
from .results import GroupMetrics, MethodMetrics


def angular_errors_2d(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(n,) angle in degrees between the x-y parts of pred and gt (n, 3); NaN where either is ~0."""
    a, b = pred[:, :2], gt[:, :2]
    ok = (np.linalg.norm(a, axis=1) > 1e-9) & (np.linalg.norm(b, axis=1) > 1e-9)
    out = np.full(len(a), np.nan)
    out[ok] = angular_error_deg(a[ok], b[ok])
    return out


def _mean(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else float("nan")


def summarize(pred: np.ndarray, gt: np.ndarray, scene: np.ndarray, scene_names: list[str],
              front: np.ndarray | None = None, at_object: np.ndarray | None = None) -> MethodMetrics:
    """Metrics of one method on n frames: pred, gt (n, 3); scene (n,) int codes into scene_names;
    front (n,) bool (GAFA: per window from its first frame), None: gt z <= 0 per frame; at_object
    (n,) bool: the frames whose gaze target is at a stored object (None: not split).

    Returns MethodMetrics (train/results.py): n, mae3d, mae2d, median3d, front and back
    GroupMetrics (n, mae3d, mae2d), per_scene {name: GroupMetrics} in scene_names' order; degrees.
    """
    e3 = angular_error_deg(pred, gt)
    e2 = angular_errors_2d(pred, gt)
    front = gt[:, 2] <= 0 if front is None else np.asarray(front, bool)

    def group(sel: np.ndarray) -> GroupMetrics:
        return GroupMetrics(n=int(sel.sum()), mae3d=_mean(e3[sel]), mae2d=_mean(e2[sel]))

    per_scene = {}
    for code in np.unique(scene):
        name = scene_names[code] if 0 <= code < len(scene_names) else str(code)
        per_scene[name] = group(scene == code)
    return MethodMetrics(n=int(len(gt)), mae3d=_mean(e3), mae2d=_mean(e2),
                         median3d=float(np.median(e3)) if len(e3) else float("nan"),
                         front=group(front), back=group(~front), per_scene=per_scene,
                         at_object=None if at_object is None else group(at_object),
                         elsewhere=None if at_object is None else group(~at_object))
