"""The pose stage: P_pose, 30 smpl+head_30 joints (huge8 order, ga3ce_prep/skeleton.py) in metres,
camera frame. A failure degrades the frame (NaN pose); GA3CE then runs without the pose tokens.

Backends: `precomputed` (an offline estimator's output, stages/precomputed.py layout) and `oracle`
(the synthetic truth plus estimator-like seeded noise, stages/noise.py `noisy_pose`).
"""
from __future__ import annotations

import numpy as np

from ..frames import FrameRef
from ..skeleton import N_JOINTS
from .base import PoseBackend
from .noise import frame_rng, noisy_pose
from .precomputed import precomputed_table
from .truth import truth_record


class PrecomputedPose(PoseBackend):
    """Poses from `file` (HDF5/npz: frame_id (N,), pose (N, 30, 3) metres)."""

    name = "precomputed"

    def check(self) -> None:
        precomputed_table(self.params["file"], "pose", (N_JOINTS, 3), "stages.pose.params.file")

    def pose(self, frame: FrameRef) -> np.ndarray:
        return precomputed_table(self.params["file"], "pose", (N_JOINTS, 3), "stages.pose.params.file").get(frame.id)


class OraclePose(PoseBackend):
    """Truth pose + per-joint Gaussian noise (sigma_face on the 6 face joints, sigma_body on the
    rest), per-frame scale about the camera centre and offset; seeded by (seed, frame id)."""

    name = "oracle"

    def check(self) -> None:
        truth_record.check(self.params["truth"])

    def pose(self, frame: FrameRef) -> np.ndarray:
        p = self.params
        truth = np.asarray(truth_record(p["truth"], frame.id, maps=False).pose, np.float64)
        return noisy_pose(truth, frame_rng(p["seed"], "pose/oracle", frame.id), p["sigma_body"], p["sigma_face"],
                          p["scale_sigma"], p["scale_bias"], p["offset_sigma"])
