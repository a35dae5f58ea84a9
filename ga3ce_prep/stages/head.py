"""The head stage: t_object, the head box centre back-projected at the median measured depth of a
small window (`geometry.head_position`). When no window near the head holds measured depth (dark
hair, a shiny or too-near face, a sensor hole), the depth along the same ray comes from the
stage's fallbacks, and the store records per frame which source gave it (`frames/head_source`).
Only a head box that is invalid or centred outside the image, or a frame where no source knows
anything, raises FrameError, which drops the frame. Design and measured errors: docs/pipeline.md,
"Head position"."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import FrameError
from ..estimators.pose.placement import pose_depth_translation
from ..frames import FrameRef
from ..geometry import back_project, head_box_centre, window_median_depth
from ..params import param
from ..skeleton import HEAD_JOINTS, J
from .base import DepthMap, HeadBackend, Sourced

Fallback = Literal["pose_depth", "pose", "completed"]
FALLBACKS: tuple[str, ...] = ("pose_depth", "pose", "completed")


def pose_head_depth(pose: np.ndarray, K: np.ndarray, depth: DepthMap | None, joint_depth_offset: float) -> float | None:
    """The depth (metres) of the near surface of the pose's head, which is what a measured depth
    at the head box centre sees: the ears' midpoint (the head's centre) minus half the ears'
    distance (its radius), from a camera-frame smpl+head_30 pose (30, 3) metres, NaN = missing;
    without both ears, the mean depth of the finite head joints (`skeleton.HEAD_JOINTS`).

    depth given: after the pose is moved to the distance the measured depth gives at its joints'
    pixels (`placement.pose_depth_translation`; the head's own pixels usually have none, the body's
    do); None when too few joints have a reading. depth None: as the pose stage placed it.
    None when the pose has no finite head joint."""
    pose = np.asarray(pose, np.float64)
    ears = pose[[J["lear"], J["rear"]]]
    head = pose[list(HEAD_JOINTS)]
    head = head[np.isfinite(head).all(1)]
    if np.isfinite(ears).all():
        z = float(ears[:, 2].mean() - 0.5 * np.linalg.norm(ears[0] - ears[1]))
    elif len(head):
        z = float(head[:, 2].mean())
    else:
        return None
    if depth is not None:
        T, used = pose_depth_translation(pose, K, depth.depth, depth.valid, joint_depth_offset)
        if not used:
            return None
        z += float(T[2])
    return z if z > 0 else None


class DepthHead(HeadBackend):
    """t_object from the depth map: windows of `window_fracs` x the box's shorter side around the
    box centre, tried in order until one holds `min_points` measured pixels (source "measured").
    Otherwise the box centre's depth comes from the first of `fallbacks` that knows it (the default
    order is that of their measured errors, docs/pipeline.md "Head position"):

    pose_depth  the near surface of the pose's head (`pose_head_depth`), the pose first moved to the
                measured depth at its other joints (body joints `joint_depth_offset` behind the
                surface: the refinement the pose backends use, `placement.refine_with_depth`);
    pose        the same where the pose stage placed the pose (a monocular estimator's distance is
                off by its size error);
    completed   the median of the depth stage's completed map (its hole filling) in the same
                windows: a last resort, since a hole that wide is filled mostly from what lies
                around the head.

    Each is the depth of the box centre's ray, so t_object stays on the ray a measured depth would
    give. With none, FrameError (the frame is dropped)."""

    name = "depth"
    version = "2"  # 2: fallbacks, Sourced
    needs = ("pose",)
    sources = ("measured", *FALLBACKS)

    @dataclass(frozen=True, kw_only=True)
    class Params:
        window_fracs: tuple[float, ...] = param(
            # window sides as fractions of the box's shorter side, tried in order
            (0.2, 0.5, 1.0), minItems=1, items={"exclusiveMinimum": 0})
        min_points: int = param(3, minimum=1)  # measured pixels a window needs
        fallbacks: tuple[Fallback, ...] = (
            # no measured depth near the head: where the depth comes from, tried
            # in order (docs/pipeline.md, "Head position"); [] drops the frame
            ("pose_depth", "pose", "completed"))
        joint_depth_offset: float = param(
            # pose_depth: metres a body joint lies behind the surface
            # the depth map measures (the 6 face joints lie on it)
            0.05, minimum=0)

    def head(self, frame: FrameRef, depth: DepthMap, pose: np.ndarray) -> Sourced:
        """pose: (30, 3) the pose stage's output for the frame (NaN where it failed)."""
        p = self.p
        H, W = depth.depth.shape
        cu, cv, side = head_box_centre(frame.head_box, W, H)
        K = np.asarray(frame.K, np.float64)
        win = {"window_fracs": p.window_fracs, "min_points": p.min_points}
        z = window_median_depth(depth.depth, depth.valid & (depth.depth > 0), cu, cv, side, **win)
        source = "measured"
        for fb in p.fallbacks:
            if z is not None:
                break
            source = fb
            if fb == "completed":
                z = window_median_depth(depth.depth, depth.depth > 0, cu, cv, side, **win)
            else:
                z = pose_head_depth(pose, K, depth if fb == "pose_depth" else None, p.joint_depth_offset)
        if z is None:
            tried = ", ".join(("measured depth", *p.fallbacks))
            raise FrameError(f"no depth for the head box {[round(float(c), 1) for c in frame.head_box]} "
                             f"(tried {tried})")
        return Sourced(back_project(cu, cv, z, K).astype(np.float32), source)
