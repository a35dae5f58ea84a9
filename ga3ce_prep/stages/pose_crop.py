"""`pose/onnx` and `pose/torchscript`: the paper's 3D pose (MeTRAbs / NLF, smpl+head_30) from the
user's model file, through the MeTRAbs family's crop contract (estimators/pose/crop.py). The two
backends share the runner and differ only in the session: ONNX Runtime, or `torch.jit.load`.

The person is the frame's body box, or a box grown from its head box; the pose's distance is
taken from the depth stage's map (`depth_refine`), as `pose/blazepose` does, so both read the
depth and run in the geometry task.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..estimators.pose.crop import CropPoseOptions, body_box, joints_file
from ..estimators.runtime.onnx_runtime import RuntimeParams
from ..frames import DepthMap, FrameRef, load_rgb
from ..params import param
from .base import PoseBackend, ProcessEstimator

EXPORT_HINT = ("write it with scripts/export_crop_pose.py from your MeTRAbs (or NLF) model "
               "(docs/models/pose.md, '3D pose from your model files')")


class CropPose(ProcessEstimator, PoseBackend):
    """The shared runner: `load_model()` is the only difference between the backends."""

    version = "2"  # 2: the antialiasing pyramid level and block phase are MeTRAbs's
    needs = ("depth",)

    def load_model(self):
        raise NotImplementedError

    def joints_path(self) -> Path:
        return joints_file(self.p.model, self.p.joints)

    def side_files(self) -> dict[str, Path]:
        """The joint list beside the model when `joints` does not name one."""
        return {} if self.p.joints is not None else {"joint names": self.joints_path()}

    def build_estimator(self):
        from ..estimators.pose.crop import CropPoseEstimator, read_joint_names

        path = self.joints_path()
        names = read_joint_names(path)
        return CropPoseEstimator(self.load_model(), names, self.p, path)

    def check(self) -> None:
        """Before any work: the joint list names all 30 joints, the model loads, takes one crop of
        its declared size and type, and returns [1, J, 3] with J the list's length."""
        self.estimator().verify()

    def provenance(self) -> dict[str, Any]:
        """The joint list's SHA-256 when it is not a parameter (found beside the model)."""
        from ..files import file_sha256

        if self.p.joints is not None:
            return {}
        return {"models": {str(self.joints_path()): file_sha256(self.joints_path())}}

    def pose(self, frame: FrameRef, depth: DepthMap) -> np.ndarray:
        """depth: the depth stage's map of the frame, at the image's resolution."""
        from ..estimators.pose.crop import place_with_depth

        p = self.p
        K = np.asarray(frame.K, np.float64)
        pose = self.estimator()(load_rgb(frame.image_path), K, body_box(frame.body_box, frame.head_box, p))
        if p.depth_refine:
            pose = place_with_depth(pose, K, depth.depth, depth.valid, p.joint_depth_offset)
        return pose.astype(np.float32)


class OnnxPose(CropPose):
    """A MeTRAbs-family crop model exported to ONNX, through ONNX Runtime."""

    name = "onnx"

    @dataclass(frozen=True, kw_only=True)
    class Params(CropPoseOptions, RuntimeParams):
        model: Path = param(
            # the crop model ONNX: image [N,S,S,3], intrinsics [N,3,3] -> poses3d [N,J,3] mm in the crop camera
            file="model", hint=EXPORT_HINT)

    def load_model(self):
        from ..estimators.pose.crop import OnnxCropModel
        from ..estimators.runtime.onnx_runtime import resolve_providers

        p = self.p
        return OnnxCropModel(p.model, resolve_providers(p.providers), p.threads, p.input_dtype, p.resolution)


class TorchScriptPose(CropPose):
    """A MeTRAbs-family crop model saved as TorchScript, through `torch.jit.load`."""

    name = "torchscript"

    @dataclass(frozen=True, kw_only=True)
    class Params(CropPoseOptions):
        model: Path = param(
            # the crop model TorchScript: forward(image [N,S,S,3], intrinsics [N,3,3]) -> [N,J,3] mm in the crop camera
            file="model", hint=EXPORT_HINT)
        device: str = "cpu"  # torch device: cpu, or cuda / cuda:N where this torch build has CUDA
        threads: int = param(2, minimum=1)  # torch intra-op threads (torch.set_num_threads, process-wide)

    def load_model(self):
        from ..estimators.pose.crop import TorchScriptCropModel

        p = self.p
        return TorchScriptCropModel(p.model, p.device, p.threads, p.resolution)
