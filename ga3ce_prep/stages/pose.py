"""The pose stage: P_pose, 30 smpl+head_30 joints (huge8 order, ga3ce_prep/skeleton.py) in metres,
camera frame. A failure degrades the frame (NaN pose); GA3CE then runs without the pose tokens.

Backends: `precomputed` (an offline estimator's output, stages/precomputed.py layout), `oracle`
(the synthetic truth plus estimator-like seeded noise, stages/oracle_noise.py `noisy_pose`) and
`blazepose` (MediaPipe's BlazePose GHUM from the registry models, estimators/pose/blazepose.py; it
reads the depth stage's map, so it runs in the geometry task). The paper's MeTRAbs-family crop
model from the user's file: `onnx` and `torchscript`, in stages/pose_crop.py.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import FrameError
from ..estimators.pose.blazepose import BlazePoseOptions, place_landmarks
from ..estimators.pose.blazepose_smpl import to_smpl_head30
from ..frames import DepthMap, FrameRef, load_rgb
from ..params import param
from ..skeleton import N_JOINTS
from ..units import BODY_RANGE_M, LENGTH_UNITS, METRES_PER_UNIT, LengthUnits, check_plausible, pose_size, to_metres
from .base import PoseBackend, ProcessEstimator
from .oracle_noise import articulated_pose, frame_rng, noisy_pose
from .precomputed import precomputed_table
from .truth import TruthParams, check_truth_file, truth_frame


class PrecomputedPose(PoseBackend):
    """Poses from `file` (HDF5/npz: frame_id (N,), pose (N, 30, 3) in `units`), converted to metres.
    A pose whose size (largest joint-to-joint distance) is not a person's (`units.BODY_RANGE_M`:
    a file in another unit) is refused: the first one's before any work, each frame's on its own."""

    name = "precomputed"
    version = "2"  # 2: units, and the size check

    @dataclass(frozen=True, kw_only=True)
    class Params:
        file: Path = param(
            # HDF5/npz: frame_id (N,) str, pose (N, 30, 3) in `units`
            file="data", hint="write it with the layout in docs/pipeline.md (frame_id, pose)")
        units: LengthUnits = "m"  # the stored joints' unit: m, cm or mm (converted to metres)

    def _table(self):
        return precomputed_table(self.p.file, "pose", (N_JOINTS, 3), "stages.pose.params.file")

    def _metres(self, frame_id: str, raw: np.ndarray) -> np.ndarray:
        """The frame's pose in metres; FrameError when its size is not a person's."""
        if np.isinf(raw).any():
            raise FrameError(f"pose of frame {frame_id} in {self.p.file} has infinite values; write NaN for a joint "
                             "the estimator did not find")
        size = pose_size(raw)
        if np.isfinite(size):
            check_plausible(np.array([size], np.float32) * np.float32(METRES_PER_UNIT[self.p.units]),
                            np.array([size], np.float32),
                            self.p.units, BODY_RANGE_M, f"pose of frame {frame_id} in {self.p.file}",
                            f"stages.pose.params.units (now {self.p.units})", "person size", candidates=LENGTH_UNITS)
        return to_metres(raw, self.p.units)

    def check(self) -> None:
        """Before any work: the file's layout, and the units on the first pose with two finite joints
        (among the first ten)."""
        self._table().check_first(self._metres, lambda raw: bool(np.isfinite(pose_size(raw))))

    def pose(self, frame: FrameRef) -> np.ndarray:
        return self._metres(frame.id, self._table().get(frame.id))


class OraclePose(PoseBackend):
    """Truth pose + per-joint Gaussian noise (sigma_face on the 6 face joints, sigma_body on the
    rest), per-frame scale about the camera centre and offset; seeded by (seed, frame id)."""

    name = "oracle"

    @dataclass(frozen=True, kw_only=True)
    class Params(TruthParams):
        seed: int = 0  # noise seed (combined with the frame id)
        sigma_body: float = param(0.039, minimum=0)  # metres, per-axis joint noise off the face (MeTRAbs, 3DPW)
        sigma_face: float = param(
            0.039, minimum=0)  # metres, per-axis noise of the 6 face joints (nose, eyes, ears, head top)
        scale_sigma: float = param(0.0, minimum=0)  # log-scale std of a per-frame scale about the camera centre
        scale_bias: float = param(
            1.0, exclusiveMinimum=0)  # mean per-frame scale (an estimator's systematic size error)
        offset_sigma: float = param(0.0, minimum=0)  # metres, per-axis std of a per-frame offset

    def check(self) -> None:
        check_truth_file(self.p.truth)

    def pose(self, frame: FrameRef) -> np.ndarray:
        p = self.p
        truth = np.asarray(truth_frame(p.truth, frame.id, maps=False).pose, np.float64)
        return noisy_pose(truth, frame_rng(p.seed, "pose/oracle", frame.id), p.sigma_body, p.sigma_face,
                          p.scale_sigma, p.scale_bias, p.offset_sigma)


class ArticulatedOraclePose(PoseBackend):
    """Truth pose with an articulated estimator's error (oracle_noise.py `articulated_pose`): small
    rotations of every bone composed down the skeleton, the face turning as one, the root moving
    mostly along the camera ray; a share of the error persisting over each recording. Seeded by
    (seed, frame id) and (seed, the frame's recording)."""

    name = "oracle-articulated"

    @dataclass(frozen=True, kw_only=True)
    class Params(TruthParams):
        seed: int = 0  # noise seed (combined with the frame id, and with its recording for the shared part)
        bone_sigma_deg: float = param(
            # per-axis std of each bone's rotation error, degrees: 2.9 gives a root-relative mean per-joint
            # error of 61.6 mm on 576 poses of the demo's world (3.0: 63.7), MeTRAbs' (eff2l) 61.9 mm on 3DPW
            # (its model zoo); calibrated to that published figure, not to any result of ours
            2.9, minimum=0)
        head_sigma_deg: float = param(
            # per-axis std of the face's one rotation about the head joint, degrees (the bones' until
            # calibrated on its own)
            2.9, minimum=0)
        ray_sigma: float = param(0.0, minimum=0)  # metres, std of the root's move along the camera ray
        lateral_sigma: float = param(0.0, minimum=0)  # metres, per-axis std of the root's other move
        persistence: float = param(
            0.0, minimum=0, maximum=1)  # share of the error variance shared by a recording's frames

    def check(self) -> None:
        check_truth_file(self.p.truth)

    def pose(self, frame: FrameRef) -> np.ndarray:
        p = self.p
        truth = np.asarray(truth_frame(p.truth, frame.id, maps=False).pose, np.float64)
        return articulated_pose(truth, frame_rng(p.seed, "pose/articulated", frame.id),
                                frame_rng(p.seed, "pose/articulated/session", frame.scene), p.bone_sigma_deg,
                                p.head_sigma_deg, p.ray_sigma, p.lateral_sigma, p.persistence)


class BlazePose(ProcessEstimator, PoseBackend):
    """BlazePose GHUM (full or heavy, LiteRT) on the frame's image: the person matching the frame's
    body box (else the one around its head box, else the best detection), world landmarks
    placed in the camera frame by a 2D fit through K, their distance then taken from the depth
    stage's map at the visible landmarks (`depth_refine`; `placement.refine_with_depth`), mapped
    to smpl+head_30 (estimators/pose/blazepose_smpl.py). No person: FrameError (the frame keeps a NaN
    pose)."""

    name = "blazepose"
    version = "2"  # 2: depth-refined placement
    needs = ("depth",)

    @dataclass(frozen=True, kw_only=True)
    class Params(BlazePoseOptions):
        variant: Literal["full", "heavy"] = (
            # landmark model: full (18 ms a frame on 1 thread) or heavy (36 ms;
            # MediaPipe's most accurate); registry keys pose_landmark_<variant>
            "full")
        min_visibility: float = param(
            0.5, minimum=0, maximum=1)  # landmark visibility below which a joint is NaN and left out of the 2D fit
        head_top_height: float = param(
            0.12, minimum=0)  # metres from the ear midpoint up to the head top (BlazePose has no head-top landmark)
        ray_alignment: bool = (
            # turn the world landmarks so their z is the ray through the visible landmarks
            # (the model sees the person along it); false: MediaPipe's image-aligned axes
            True)
        depth_refine: bool = (
            # take the pose's distance (metres) from the depth map at the visible landmarks, body joints 5 cm behind
            # the measured surface: the world landmarks have an average adult's size, so the 2D fit alone is off by the
            # size error times the distance (10% is 30 cm at 3 m); false: the 2D fit only (the map is still passed)
            True)

    def registry_keys(self) -> tuple[str, ...]:
        return "pose_detection", f"pose_landmark_{self.p.variant}"

    def build_estimator(self):
        from ..estimators.pose.blazepose import BlazePoseEstimator
        from ..weights.registry import model_path

        return BlazePoseEstimator(*(model_path(k) for k in self.registry_keys()), self.p)

    def pose(self, frame: FrameRef, depth: DepthMap) -> np.ndarray:
        """depth: the depth stage's map of the frame, at the image's resolution."""
        p = self.p
        lm = self.estimator()(load_rgb(frame.image_path), frame.body_box, frame.head_box)
        measured, valid = (depth.depth, depth.valid) if p.depth_refine else (None, None)
        cam = place_landmarks(lm, np.asarray(frame.K, np.float64), p.min_visibility, p.ray_alignment,
                              depth=measured, valid=valid)
        return to_smpl_head30(cam, lm.visibility, p.min_visibility, p.head_top_height).astype(np.float32)
