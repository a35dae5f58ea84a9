"""The MeTRAbs family's crop-model contract (MeTRAbs, NLF): one person's 3D pose from a perspective
crop, on the user's ONNX or TorchScript file (`pose/onnx`, `pose/torchscript`).

The model file's interface (docs/models/pose.md, "The contract"):

    image       [N, S, S, 3]  the crop, RGB, dtype and value range as `CropPoseOptions` says
                              (MeTRAbs: float, [0, 1]; the model maps it to [-1, 1] itself)
    intrinsics  [N, 3, 3]     float32, the crop camera's K' (principal point at (S/2, S/2))
    poses3d     [N, J, 3]     millimetres in the crop camera (x right, y down, z forward)

and a joint-name list beside it (`<model stem>.joints.txt`, one name per line, the model's J
joints in its order). The runner warps a square crop around the body box with the homography
K' R K^-1 (`crops.look_at_crop`, `crops.warp_homography`: the camera turned toward the box
centre, as MeTRAbs's `_get_crops` does), in linear light (`gamma`), feeds it with K', turns the
output back to the camera frame (`poses @ R`), converts millimetres to metres and picks the 30
smpl+head_30 joints by name (`skeleton.JOINT_NAMES`): the order differs between model
generations, so a name the list lacks is refused, naming it.
"""
from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

import cv2
import numpy as np

from ...errors import ConfigError, FrameError, ModelFileError
from ...params import param
from ...skeleton import JOINT_NAMES
from ..runtime.crops import LookAtCrop, look_at_crop, warp_homography
from .placement import pose_depth_translation


def ignore_torchscript_deprecation() -> None:
    """Within warnings.catch_warnings(): torch 2.13 deprecates TorchScript (NLF's release format and
    ours), silenced where we call it."""
    warnings.filterwarnings("ignore", message=r"`torch\.jit\.", category=DeprecationWarning)


INPUT_DTYPES = {"float32": np.float32, "float16": np.float16, "uint8": np.uint8}
ORT_TYPES = {"float32": "tensor(float)", "float16": "tensor(float16)", "uint8": "tensor(uint8)"}


@dataclass(frozen=True, kw_only=True)
class CropPoseOptions:
    """The crop contract's parameters, MeTRAbs's values as defaults (both pose backends)."""

    joints: Path | None = param(
        # the model's joint-name list, one name per line in its output
        # order; null: <model stem>.joints.txt beside the model
        None, file="model",
        hint="scripts/export_crop_pose.py writes it beside the model: "
             "one joint name per line, in the model's output order")
    resolution: int | None = param(
        # crop side S, pixels; null: from the model (the ONNX image input's fixed side, or the
        # TorchScript module's `input_resolution`, which scripts/export_crop_pose.py writes)
        None, minimum=1)
    input_dtype: Literal["float32", "float16", "uint8"] = (
        # the image tensor's dtype (MeTRAbs's PyTorch crop model: float32; its TF SavedModel takes float16)
        "float32")
    value_range: tuple[float, ...] = param(
        # what black and white become in the image tensor (MeTRAbs: [0, 1];
        # the model maps it to [-1, 1] itself); uint8 input: (0, 255)
        (0.0, 1.0), minItems=2, maxItems=2)
    gamma: float = param(
        # the warp interpolates in linear light: pixels are decoded as
        # (v / 255)^gamma before it (MeTRAbs: 2.2); 1: plain sRGB interpolation
        2.2, exclusiveMinimum=0)
    gamma_aug: float = param(
        # the crop is encoded back as linear^(gamma_aug / gamma): MeTRAbs's single-augmentation value (its
        # test-time gammas 0.6..1.0, linspace with one sample gives their mean 0.8); 1: exactly undo the decoding
        0.8, exclusiveMinimum=0)
    box_scale: float = param(
        # the crop spans box_scale x the body box's larger (perspective-corrected)
        # side; MeTRAbs crops the detector's box as it is (1)
        1.0, exclusiveMinimum=0)
    head_box_width: float = param(
        # no finite body box: the width of the box grown from the head
        # box, in head-box sides (its larger side), centred on it
        3.0, exclusiveMinimum=0)
    head_box_above: float = param(
        0.25, minimum=0)  # no finite body box: head-box sides the grown box reaches above the head box's top
    head_box_below: float = param(
        # no finite body box: head-box sides the grown box reaches below the head box's bottom
        # (an upright adult is about 7.5 heads tall; a seated one leaves floor in the crop)
        6.5, minimum=0)
    joint_depth_offset: float = param(
        # depth_refine: metres a body joint lies behind the surface the depth map measures (the 6 face joints lie on it)
        0.05, minimum=0)
    depth_refine: bool = (
        # take the pose's distance from the depth stage's map at its joints
        # (placement.refine_with_depth, as pose/blazepose): a monocular pose's distance is off by
        # its size error times the distance; false: the model's distance (the map is still passed)
        True)


class CropModel(Protocol):
    """A loaded crop model: `resolution` S, `where` (its file, for messages), and a call on
    images [N, S, S, 3] (its input dtype) and intrinsics [N, 3, 3] float32 -> [N, J, 3] float64 mm."""

    resolution: int
    where: str

    def __call__(self, images: np.ndarray, intrinsics: np.ndarray) -> np.ndarray: ...


def joints_file(model: Path, joints: Path | None) -> Path:
    """The joint-name list: `joints`, or `<model stem>.joints.txt` beside the model."""
    return Path(joints) if joints is not None else Path(model).with_suffix(".joints.txt")


def read_joint_names(path: Path) -> list[str]:
    """The names in a joint-name list (one per line, blank lines ignored); ModelFileError for a
    missing file or a repeated name."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"joint-name list {path} not found: the model's joint names, one per line in its output "
                             "order (scripts/export_crop_pose.py writes it beside the model), or set `joints`")
    names = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ModelFileError(f"joint-name list {path}: {repeated} appear more than once")
    return names


def select_joints(names: Sequence[str], where: str, wanted: Sequence[str] = JOINT_NAMES) -> np.ndarray:
    """Indices (len(wanted),) int64 of `wanted` in the model's joint names; ModelFileError naming
    the missing names (smpl+head_30's are `skeleton.JOINT_NAMES`)."""
    pos = {n: i for i, n in enumerate(names)}
    missing = [n for n in wanted if n not in pos]
    if missing:
        raise ModelFileError(f"{where}: no joint named {missing[0]!r}"
                             + (f" (nor {missing[1:]})" if missing[1:] else "")
                             + f" among its {len(names)} names; smpl+head_30 needs the {len(wanted)} names of "
                             "skeleton.JOINT_NAMES (a model that spells one otherwise: rename it in the list)")
    return np.array([pos[n] for n in wanted], np.int64)


def crop_to_camera(poses_mm: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Crop-camera points (..., 3) millimetres -> camera-frame points (..., 3) metres: R^T p / 1000
    (`LookAtCrop.R` takes camera to crop)."""
    return (np.asarray(poses_mm, np.float64) @ np.asarray(R, np.float64)) * 1e-3


def body_box(frame_body_box: np.ndarray, head_box: np.ndarray, o: CropPoseOptions) -> np.ndarray:
    """(4,) x1, y1, x2, y2 pixels: the frame's body box when finite and non-empty, else one grown
    from the head box (`head_box_width`, `head_box_above`, `head_box_below`, in head-box sides,
    the side being the head box's larger one). FrameError when neither is usable."""
    b = np.asarray(frame_body_box, np.float64)
    if np.isfinite(b).all() and b[2] > b[0] and b[3] > b[1]:
        return b
    x1, y1, x2, y2 = np.asarray(head_box, np.float64)
    if not np.isfinite([x1, y1, x2, y2]).all() or x2 <= x1 or y2 <= y1:
        raise FrameError(f"no usable body box {list(b)} nor head box {[x1, y1, x2, y2]} to crop the person")
    side, cx = max(x2 - x1, y2 - y1), 0.5 * (x1 + x2)
    half = 0.5 * o.head_box_width * side
    return np.array([cx - half, y1 - o.head_box_above * side, cx + half, y2 + o.head_box_below * side])


def decode_lut(gamma: float) -> np.ndarray:
    """(256,) float32: byte v -> (v / 255)^gamma, linear light."""
    return ((np.arange(256) / 255.0) ** gamma).astype(np.float32)


class CropPoseEstimator:
    """One person's smpl+head_30 pose from a crop model (`CropModel`) and its joint names."""

    def __init__(self, model: CropModel, names: Sequence[str], options: CropPoseOptions,
                 names_file: Path | None = None):
        """names: the model's J joint names in its output order (from `names_file`, for messages)."""
        self.model, self.o = model, options
        self.n_model_joints = len(names)
        self.index = select_joints(names, f"{model.where}: joint-name list {names_file or '(given)'}")
        self.lut = decode_lut(options.gamma)

    def crop(self, rgb: np.ndarray, K: np.ndarray, box: np.ndarray) -> tuple[np.ndarray, LookAtCrop]:
        """The model's image [S, S, 3] (its dtype and value range) for an (H, W, 3) uint8 RGB
        image, K (3, 3) and a body box (4,) pixels, and the crop's geometry."""
        o = self.o
        geo = look_at_crop(K, box, self.model.resolution, o.box_scale)
        linear = warp_homography(cv2.LUT(rgb, self.lut), geo.H, geo.size, geo.zoom)
        lo, hi = o.value_range
        x = lo + (hi - lo) * np.power(np.clip(linear, 0.0, None), o.gamma_aug / o.gamma)
        if o.input_dtype == "uint8":
            x = np.clip(np.rint(x), 0, 255)
        return x.astype(INPUT_DTYPES[o.input_dtype]), geo

    def raw(self, image: np.ndarray, Kc: np.ndarray) -> np.ndarray:
        """The model's output (J, 3) millimetres in the crop camera for one crop [S, S, 3] and its
        K' (3, 3); ModelFileError when it is not [1, J, 3] with J the list's length."""
        out = np.asarray(self.model(image[None], np.asarray(Kc, np.float32)[None]))
        if out.shape != (1, self.n_model_joints, 3):
            raise ModelFileError(f"{self.model.where}: output poses3d has shape {list(out.shape)} for one crop; "
                                 f"expected [1, {self.n_model_joints}, 3] (J = the joint-name list's length)")
        return out[0]

    def __call__(self, rgb: np.ndarray, K: np.ndarray, box: np.ndarray) -> np.ndarray:
        """(30, 3) float64 smpl+head_30 joints, metres, camera frame, for the person in `box`."""
        image, geo = self.crop(rgb, K, box)
        return crop_to_camera(self.raw(image, geo.K), geo.R)[self.index]

    def verify(self) -> None:
        """Run one grey crop through the model (before any work): its input is accepted and its
        output has the list's joint count. ModelFileError naming the file otherwise."""
        S = self.model.resolution
        K = np.array([[S, 0.0, S / 2], [0.0, S, S / 2], [0.0, 0.0, 1.0]])
        lo, hi = self.o.value_range
        image = np.full((S, S, 3), 0.5 * (lo + hi), INPUT_DTYPES[self.o.input_dtype])
        try:
            self.raw(image, K)
        except ModelFileError:
            raise
        except Exception as e:  # the runtimes raise their own types
            lines = [line.strip() for line in str(e).splitlines() if line.strip()]  # TorchScript: the cause comes last
            raise ModelFileError(f"{self.model.where}: refused the input image [1, {S}, {S}, 3] {self.o.input_dtype} "
                                 "with intrinsics [1, 3, 3] float32: "
                                 f"{lines[-1] if lines else type(e).__name__}") from e


def place_with_depth(pose: np.ndarray, K: np.ndarray, depth: np.ndarray, valid: np.ndarray | None,
                     joint_depth_offset: float) -> np.ndarray:
    """The pose (30, 3) metres moved to the distance the depth map (H, W) metres measures at its
    joints' pixels (`placement.refine_with_depth`; body joints `joint_depth_offset` metres behind
    the surface, the 6 face joints on it; too few agreeing readings: unchanged)."""
    return pose + pose_depth_translation(pose, K, depth, valid, joint_depth_offset)[0]


def _shapes(args) -> str:
    return ", ".join(f"{a.name!r} {a.shape} {a.type}" for a in args)


class OnnxCropModel:
    """A crop model in an ONNX file, through ONNX Runtime (`onnx_runtime.check_contract`: each
    tensor by its role, `image`, `intrinsics`, `poses3d`)."""

    def __init__(self, path: Path, providers: Sequence[str], threads: int, dtype: str, resolution: int | None):
        from ..runtime.onnx_runtime import TensorSpec, check_contract, create_session, input_dims

        self.where = f"crop pose ONNX {path}"
        self.sess = create_session(path, providers, threads, "crop pose")
        inputs = [TensorSpec("image", (None, resolution, resolution, 3), ORT_TYPES[dtype]),
                  TensorSpec("intrinsics", (None, 3, 3))]
        self.names = check_contract(self.sess, inputs, [TensorSpec("poses3d", (None, None, 3))], path, "crop pose")
        dims = input_dims(self.sess, self.names["image"])[1:3]
        if isinstance(dims[0], int) and dims[0] != dims[1]:
            raise ModelFileError(f"{self.where}: input {self.names['image']!r} is {list(dims)} pixels; "
                                 f"the crop is square. Inputs: {_shapes(self.sess.get_inputs())}")
        S = resolution or dims[0]
        if not S:
            raise ConfigError(f"{self.where}: input {self.names['image']!r} has a dynamic size: set `resolution` "
                              "(MeTRAbs: 256 or 384, the model's input_resolution)")
        self.resolution = int(S)

    def __call__(self, images: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
        feed = {self.names["image"]: images, self.names["intrinsics"]: intrinsics.astype(np.float32)}
        return np.asarray(self.sess.run([self.names["poses3d"]], feed)[0], np.float64)


class TorchScriptCropModel:
    """A crop model in a TorchScript file: `module(image, intrinsics)` on `device`, in inference mode."""

    def __init__(self, path: Path, device: str, threads: int, resolution: int | None):
        import torch

        self.where = f"crop pose TorchScript {path}"
        if not Path(path).is_file():
            raise ModelFileError(f"{self.where}: file not found")
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise ConfigError(f"device {device!r}: this torch build or machine has no CUDA; use device: cpu")
        torch.set_num_threads(int(threads))
        try:
            with warnings.catch_warnings():
                ignore_torchscript_deprecation()
                self.module = torch.jit.load(str(path), map_location=device).eval()
        except Exception as e:  # torch raises RuntimeError and others
            raise ModelFileError(f"cannot load {self.where}: {e}") from e
        S = resolution or getattr(self.module, "input_resolution", None)
        if not S:
            raise ConfigError(f"{self.where} has no `input_resolution` attribute: set `resolution` "
                              "(MeTRAbs: 256 or 384, the model's input_resolution)")
        self.resolution, self.device = int(S), device

    def __call__(self, images: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
        import torch

        with torch.inference_mode():
            out = self.module(torch.from_numpy(np.ascontiguousarray(images)).to(self.device),
                              torch.from_numpy(intrinsics.astype(np.float32)).to(self.device))
        return out.float().cpu().numpy().astype(np.float64)


__all__ = ["CropModel", "CropPoseEstimator", "CropPoseOptions", "OnnxCropModel", "TorchScriptCropModel", "body_box",
           "crop_to_camera", "decode_lut", "joints_file", "place_with_depth", "read_joint_names", "select_joints"]
