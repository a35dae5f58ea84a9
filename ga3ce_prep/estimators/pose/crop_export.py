"""Writing a crop pose model in the files `pose/torchscript` and `pose/onnx` read
(estimators/pose/crop.py): `<stem>.pt` (TorchScript), `<stem>.onnx` where the model exports, and
`<stem>.joints.txt`, then checking them with the backends' own loaders.

The model-specific part (importing the user's MeTRAbs or NLF and wrapping its crop model as
`forward(image [N,S,S,3], intrinsics [N,3,3]) -> [N,J,3] mm`) is scripts/export_crop_pose.py; this
module is what that script shares with the tests, which run it on tiny models. Imports torch.
"""
from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch


class WithResolution(torch.nn.Module):
    """A traced crop model with its crop side S as the attribute the loader reads
    (`TorchScriptCropModel`: `input_resolution`)."""

    def __init__(self, inner: torch.nn.Module, resolution: int):
        super().__init__()
        self.inner = inner
        self.input_resolution = int(resolution)

    def forward(self, image: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        return self.inner(image, intrinsics)


@dataclass
class Exported:
    """What `save_crop_model` wrote: the files (onnx None when the export failed, with the reason in
    onnx_error) and each file's largest difference from the module on a random crop, millimetres."""

    torchscript: Path
    joints: Path
    onnx: Path | None
    onnx_error: str | None
    max_diff_mm: dict[str, float]


def example_inputs(resolution: int, dtype: torch.dtype = torch.float32,
                   seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """One random crop [1, S, S, 3] in [0, 1] (in `dtype`) and a plausible K' [1, 3, 3]
    (focal length 2 S, principal point (S/2, S/2))."""
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(1, resolution, resolution, 3, generator=g).to(dtype)
    K = torch.tensor([[[2.0 * resolution, 0, resolution / 2], [0, 2.0 * resolution, resolution / 2], [0, 0, 1]]])
    return image, K


def save_crop_model(module: torch.nn.Module, resolution: int, joint_names: Sequence[str], stem: str | Path, *,
                    onnx: bool = True, opset: int = 17, dtype: torch.dtype = torch.float32) -> Exported:
    """Trace `module` (forward(image [1,S,S,3] dtype, intrinsics [1,3,3] float32) -> [1,J,3] mm, on
    the CPU, eval mode) on one crop and write `<stem>.pt` with its `input_resolution`, `<stem>.onnx`
    (torch.onnx.export, dynamo=False; batch 1 as traced) when `onnx`, and `<stem>.joints.txt` (one
    name per line). Then load them with the pipeline's loaders and compare with the module on
    another crop. A failed ONNX export is reported in `onnx_error`, not raised."""
    from .crop import OnnxCropModel, TorchScriptCropModel, ignore_torchscript_deprecation

    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    module = module.eval()
    example = example_inputs(resolution, dtype)
    with torch.inference_mode():
        reference = module(*example)
    if tuple(reference.shape) != (1, len(joint_names), 3):
        raise ValueError(f"the module returns {list(reference.shape)} for one crop; "
                         f"expected [1, {len(joint_names)}, 3] (one row per joint name)")
    joints = stem.with_suffix(".joints.txt")
    joints.write_text("".join(f"{n}\n" for n in joint_names))
    ts = stem.with_suffix(".pt")
    with torch.no_grad(), warnings.catch_warnings():
        ignore_torchscript_deprecation()
        traced = torch.jit.trace(module, example, check_trace=False)
        torch.jit.save(torch.jit.script(WithResolution(traced, resolution)), str(ts))

    test = example_inputs(resolution, dtype, seed=1)
    with torch.inference_mode():
        want = module(*test).double().numpy()
    args = (test[0].numpy(), test[1].numpy())
    diffs = {"torchscript": float(np.abs(TorchScriptCropModel(ts, "cpu", 1, None)(*args) - want).max())}
    path, error = None, None
    if onnx:
        path = stem.with_suffix(".onnx")
        try:
            with torch.no_grad(), warnings.catch_warnings():
                warnings.filterwarnings("ignore", category=DeprecationWarning)  # the legacy exporter's own
                torch.onnx.export(module, example, str(path), dynamo=False, opset_version=opset,
                                  do_constant_folding=True, input_names=["image", "intrinsics"],
                                  output_names=["poses3d"])
            dt = {torch.float32: "float32", torch.float16: "float16", torch.uint8: "uint8"}[dtype]
            diffs["onnx"] = float(np.abs(OnnxCropModel(path, ["CPUExecutionProvider"], 1, dt, None)(*args)
                                         - want).max())
        except Exception as e:  # the exporter raises many types; TorchScript still serves
            path.unlink(missing_ok=True)
            path, error = None, f"{type(e).__name__}: {e}"
    return Exported(ts, joints, path, error, diffs)


__all__ = ["Exported", "WithResolution", "example_inputs", "save_crop_model"]
