"""The pose stage: P_pose, 30 smpl+head_30 joints (huge8 order, ga3ce_prep/skeleton.py) in metres,
camera frame. A failure degrades the frame (NaN pose); GA3CE then runs without the pose tokens.

Backends: `precomputed` (an offline estimator's output, stages/precomputed.py layout) and `oracle`
(the synthetic truth plus estimator-like seeded noise, stages/oracle_noise.py `noisy_pose`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..frames import FrameRef
from ..params import param
from ..skeleton import N_JOINTS
from .base import PoseBackend
from .oracle_noise import frame_rng, noisy_pose
from .precomputed import precomputed_table
from .truth import TruthParams, check_truth_file, truth_frame


class PrecomputedPose(PoseBackend):
    """Poses from `file` (HDF5/npz: frame_id (N,), pose (N, 30, 3) metres)."""

    name = "precomputed"

    @dataclass(frozen=True, kw_only=True)
    class Params:
        file: Path = param(file="data", hint="write it with the layout in docs/pipeline.md (frame_id, pose)")  # HDF5/npz: frame_id (N,) str, pose (N, 30, 3) metres

    def _table(self):
        return precomputed_table(self.p.file, "pose", (N_JOINTS, 3), "stages.pose.params.file")

    def check(self) -> None:
        self._table()

    def pose(self, frame: FrameRef) -> np.ndarray:
        return self._table().get(frame.id)


class OraclePose(PoseBackend):
    """Truth pose + per-joint Gaussian noise (sigma_face on the 6 face joints, sigma_body on the
    rest), per-frame scale about the camera centre and offset; seeded by (seed, frame id)."""

    name = "oracle"

    @dataclass(frozen=True, kw_only=True)
    class Params(TruthParams):
        seed: int = 0  # noise seed (combined with the frame id)
        sigma_body: float = param(0.02, minimum=0)  # metres, per-axis joint noise off the face
        sigma_face: float = param(0.04, minimum=0)  # metres, per-axis noise of the 6 face joints (nose, eyes, ears, head top)
        scale_sigma: float = param(0.0, minimum=0)  # log-scale std of a per-frame scale about the camera centre
        scale_bias: float = param(1.0, exclusiveMinimum=0)  # mean per-frame scale (an estimator's systematic size error)
        offset_sigma: float = param(0.0, minimum=0)  # metres, per-axis std of a per-frame offset

    def check(self) -> None:
        check_truth_file(self.p.truth)

    def pose(self, frame: FrameRef) -> np.ndarray:
        p = self.p
        truth = np.asarray(truth_frame(p.truth, frame.id, maps=False).pose, np.float64)
        return noisy_pose(truth, frame_rng(p.seed, "pose/oracle", frame.id), p.sigma_body, p.sigma_face,
                          p.scale_sigma, p.scale_bias, p.offset_sigma)
