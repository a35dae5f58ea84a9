"""GFIE's head-image gaze network (the EGD module of Hu et al., CVPR 2023; github nkuhzx/GFIE,
gfiemodel/gfiemodule.py) in torch, loading its weights from GFIE's released checkpoint.

Network (`GFIEHeadNet`): (N, 3, 224, 224) head crop (estimators/view/head_crop.py, GFIE's recipe) ->
ResNet-50 without its fc (`backbone`: GFIE keeps torchvision's children but the fc in an
nn.Sequential, so its keys are indices: 0 conv1, 1 bn1, 4-7 layer1-4) -> flatten (N, 2048) ->
Linear(2048, 256), ReLU, Linear(256, 3) (`fc`: indices 0 and 2) -> L2-normalised (N, 3).

Checkpoint (`load_gfie_head`): GFIE's `save_checkpoint` (utils/model_utils.py) writes a dict with
"state_dict" (the whole GFIENet's), "epoch", "best_dist_err", "best_cosine_err" (numpy float64)
and "optimizer". The head network's keys in it are `egd_module.` + ours, e.g.
`egd_module.backbone.4.0.conv1.weight`, `egd_module.fc.2.bias`: GFIENet names the branch
`egd_module`, and GFIE never wraps the model in DataParallel (main.py, utils/model_utils.py), so
there is no `module.` prefix; its inference.py loads the file strictly into a plain GFIENet. The
other branch with weights, `ggh_module.` (the heatmap generator, estimators/view/gfie_net.py), is left
unread; any other key, a missing one or one of another shape refuses the file.

Output convention: GFIE trains the vector against normalize(gaze_XYZ - eye_XYZ), the 3D points
of its annotations in the RGB camera frame whose pinhole back-projection is X = (u - cx) Z / fx,
Y = (v - cy) Z / fy, Z = depth (dataset/gfie.py, utils/infer_engine.py): x right, y down, z
forward, ours; the horizontal-flip augmentation negates x with the image. So the output is v as
it is, pointing from the eye toward the target.
"""
from __future__ import annotations

import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ...errors import FrameError, ModelFileError
from .head_crop import CropParams, head_input
from .resnet import ResNet50

PREFIX = "egd_module."  # the head network's keys inside GFIENet's state dict
OTHER_BRANCHES = ("ggh_module.",)  # GFIENet's other branch with weights (PSFoV has none): not read
NetT = TypeVar("NetT", bound=nn.Module)


class GFIEHeadNet(nn.Module):
    """GFIE's EGD module: (N, 3, 224, 224) normalised head crops -> (N, 3) unit gaze vectors in
    the camera frame (x right, y down, z forward)."""

    def __init__(self):
        super().__init__()
        self.backbone = nn.Sequential(*ResNet50(num_classes=None).children())  # conv1 .. avgpool, GFIE's indices
        self.fc = nn.Sequential(nn.Linear(2048, 256), nn.ReLU(), nn.Linear(256, 3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.fc(torch.flatten(self.backbone(x), 1)), dim=1)


def _numpy_scalar_globals() -> list[Any]:
    """What a pickled numpy scalar needs under weights_only=True (GFIE's best_*_err): the
    reconstructor, under numpy 1.x's and 2.x's module names, np.dtype and the dtypes' classes."""
    try:
        from numpy._core.multiarray import scalar
    except ImportError:  # numpy 1.x
        from numpy.core import multiarray as numpy1_multiarray

        scalar = numpy1_multiarray.scalar
    dtypes = {type(np.dtype(c)) for c in ("b1", "i4", "i8", "f2", "f4", "f8")}
    return [(scalar, "numpy.core.multiarray.scalar"), (scalar, "numpy._core.multiarray.scalar"), np.dtype, *dtypes]


def _names(keys: list[str], most: int = 5) -> str:
    return ", ".join(keys[:most]) + (f" (and {len(keys) - most} more)" if len(keys) > most else "")


def matched_state(state: Mapping[str, Any], net: nn.Module, path: str | Path, prefix: str = "",
                  ignore: tuple[str, ...] = (), what: str = "GFIE's network") -> dict[str, torch.Tensor]:
    """`net`'s weights from a GFIENet state dict, strictly: every key prefix + (a key of net) there
    with net's shape, every other key starting with one of `ignore`; returned without the prefix.
    ModelFileError naming the file, `what` and the missing, unexpected and misshapen keys."""
    expected = {prefix + k: v.shape for k, v in net.state_dict().items()}
    missing = [k for k in expected if k not in state]
    extra = [k for k in state if k not in expected and not k.startswith(ignore)]
    wrong = [f"{k} {tuple(getattr(state[k], 'shape', ()))} (expected {tuple(s)})" for k, s in expected.items()
             if k in state and (not torch.is_tensor(state[k]) or state[k].shape != s)]
    problems = [f"{kind}: {_names(keys)}" for kind, keys in
                (("missing keys", missing), ("unexpected keys", extra), ("wrong shapes", wrong)) if keys]
    if problems:
        hint = (" (saved from nn.DataParallel? GFIE's own checkpoints have no 'module.' prefix)"
                if any(k.startswith("module.") for k in state) else "")
        raise ModelFileError(f"GFIE checkpoint {path} does not hold {what}: " + "; ".join(problems) + hint)
    return {k[len(prefix):]: state[k] for k in expected}


def load_gfie_weights(path: str | Path, net: NetT, prefix: str = "", ignore: tuple[str, ...] = (),
                      what: str = "GFIE's network") -> NetT:
    """`net` (eval mode, CPU) with its weights from GFIE's checkpoint at `path` (`matched_state`),
    read with weights_only=True (numpy scalars allowed, nothing else runs) and memory-mapped so the
    tensors not asked for (the optimiser, an ignored branch) are not read. ModelFileError naming
    the file."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"GFIE checkpoint not found: {path}")
    try:
        with torch.serialization.safe_globals(_numpy_scalar_globals()):
            ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=zipfile.is_zipfile(path))
    except Exception as e:  # any unpickling failure means "not a GFIE checkpoint"
        # the first line of torch's message, without its advice (not ours)
        why = str(e).split("WeightsUnpickler error: ")[-1].split("\n")[0].split(". Please use")[0]
        raise ModelFileError(f"cannot read GFIE checkpoint {path} with weights_only=True (tensors, containers "
                             f"and numpy scalars only): {why}") from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), Mapping):
        raise ModelFileError(f"{path} is not a GFIE checkpoint: expected a dict with a 'state_dict' "
                             "(GFIE's save_checkpoint, e.g. its released gfiemodel.pt.tar)")
    net.load_state_dict(matched_state(ckpt["state_dict"], net, path, prefix, ignore, what))
    return net.eval()


def load_gfie_head(path: str | Path) -> GFIEHeadNet:
    """GFIEHeadNet with the `egd_module.*` weights of GFIE's checkpoint at `path`; the heatmap
    branch's keys (`ggh_module.*`) are allowed and not read (`load_gfie_weights`)."""
    return load_gfie_weights(path, GFIEHeadNet(), PREFIX, OTHER_BRANCHES, f"GFIE's head network ({PREFIX}*)")


class GFIEHeadEstimator:
    """GFIE's head network on one device: `estimate(rgb, box)` -> (3,) float32 unit v."""

    def __init__(self, checkpoint: str | Path, device: str = "cpu", threads: int = 1):
        torch.set_num_threads(threads)
        self.device = torch.device(device)
        self.net = load_gfie_head(checkpoint).to(self.device)

    def estimate(self, rgb: np.ndarray, box: np.ndarray) -> np.ndarray:
        """v for the head in box (4,) x1, y1, x2, y2 pixels of an (H, W, 3) uint8 RGB image:
        (3,) float32 unit, camera frame. FrameError if the network gives no direction (a zero or
        non-finite vector)."""
        v = self.estimate_batch([head_input(rgb, box, CropParams())])[0]
        if isinstance(v, Exception):
            raise v
        return v

    def estimate_batch(self, inputs: list[np.ndarray]) -> list[np.ndarray | FrameError]:
        """v for N network inputs (`head_input`, each (1, 3, 224, 224)) in one forward pass: per
        input (3,) float32 unit, or the FrameError of an output that is not a direction."""
        x = torch.from_numpy(np.concatenate(inputs)).to(self.device)
        with torch.inference_mode():
            vs = self.net(x).cpu().numpy().astype(np.float32)
        return [v if abs(float(np.linalg.norm(v)) - 1) < 1e-3 else
                FrameError(f"GFIE's head network gave {v.tolist()}, not a direction") for v in vs]


def export_onnx(checkpoint: str | Path, out: str | Path, opset: int = 17) -> Path:
    """GFIE's head network from its checkpoint -> an ONNX file for `view/onnx` with its default
    recipe: input "image" (N, 3, 224, 224), output "gaze" (N, 3) unit, camera frame."""
    net, out = load_gfie_head(checkpoint), Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        torch.onnx.export(net, (torch.zeros(1, 3, 224, 224),), str(out), dynamo=False, opset_version=opset,
                          input_names=["image"], output_names=["gaze"],
                          dynamic_axes={"image": {0: "batch"}, "gaze": {0: "batch"}})
    return out


__all__ = ["OTHER_BRANCHES", "PREFIX", "GFIEHeadEstimator", "GFIEHeadNet", "export_onnx", "load_gfie_head",
           "load_gfie_weights", "matched_state"]
