"""Any head-crop gaze network exported to ONNX (`view/onnx`): the head crop of `CropParams`
(GFIE's recipe by default, estimators/view/head_crop.py), one forward pass, and its 3-vector output
mapped to our camera frame (x right, y down, z forward) by `axes` and normalised.

Contract: one float32 input of shape (1, 3, S, S) ("nchw") or (1, S, S, 3) ("nhwc"), S =
input_size (a dynamic batch axis is fed 1); the output (1, 3): the one output of that shape, or
the one named by `output`. `axes` says what each output component is in our frame: ("x", "y",
"z") as it is; ("-x", "-y", "z") for a network whose x points left and y up; ("-x", "-y", "-z")
for one that reports the direction toward the eye rather than away from it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import ConfigError, ModelFileError
from ...geometry import unit_direction
from ...params import param
from ..runtime.onnx_runtime import RuntimeParams, TensorSpec, check_contract, create_session, resolve_providers
from .head_crop import CropParams, head_input

AXES = ("x", "-x", "y", "-y", "z", "-z")


@dataclass(frozen=True, kw_only=True)
class HeadOnnxOptions(CropParams, RuntimeParams):
    """The crop recipe (GFIE's by default), the output and its axes, and the ONNX Runtime options."""

    output: str | None = None  # the output holding the (1, 3) vector; null: the model's one output of that shape
    axes: tuple[str, ...] = param(
        # our camera axis (x right, y down, z forward) each output component points along,
        # with its sign: ["x", "y", "z"] as it is, ["-x", "-y", "z"] for x left and y up
        ("x", "y", "z"), minItems=3, maxItems=3, items={"enum": list(AXES)})


def axes_matrix(axes: tuple[str, ...]) -> np.ndarray:
    """(3, 3) float64 signed permutation M with v = M @ output, from `HeadOnnxOptions.axes`;
    ConfigError unless each of x, y, z appears once."""
    if len(axes) != 3 or any(a not in AXES for a in axes) or sorted(a[-1] for a in axes) != ["x", "y", "z"]:
        raise ConfigError(f"stages.view.params.axes: {list(axes)} must name each of x, y, z once, "
                          "optionally with a minus sign, e.g. [x, y, z] or [-x, -y, z]")
    M = np.zeros((3, 3))
    for i, a in enumerate(axes):
        M["xyz".index(a[-1]), i] = -1.0 if a.startswith("-") else 1.0
    return M


class HeadOnnxEstimator:
    """A head-crop network on one ONNX file; its contract is checked on load (ModelFileError)."""

    def __init__(self, path: str | Path, p: HeadOnnxOptions = HeadOnnxOptions()):
        self.path, self.p, self.M = Path(path), p, axes_matrix(p.axes)
        self.session = create_session(self.path, resolve_providers(p.providers), p.threads, "view")
        names = [o.name for o in self.session.get_outputs()]
        if p.output is not None and p.output not in names:
            raise ModelFileError(f"view ONNX {self.path}: no output named {p.output!r}; its outputs: {names}")
        S = p.input_size
        shape = (1, 3, S, S) if p.layout == "nchw" else (1, S, S, 3)
        roles = check_contract(self.session, [TensorSpec("image", shape)], [TensorSpec(p.output or "gaze", (1, 3))],
                               self.path, "view")
        self.input, self.output = roles["image"], roles[p.output or "gaze"]

    def estimate(self, rgb: np.ndarray, box: np.ndarray) -> np.ndarray:
        """v for the head in box (4,) x1, y1, x2, y2 pixels of an (H, W, 3) uint8 RGB image:
        (3,) float32 unit, camera frame. FrameError for a zero or non-finite output."""
        out = self.session.run([self.output], {self.input: head_input(rgb, box, self.p)})[0]
        return unit_direction(self.M @ np.asarray(out, np.float64).reshape(3), f"view ONNX {self.path}'s output",
                              min_norm=1e-9)


__all__ = ["AXES", "HeadOnnxEstimator", "HeadOnnxOptions", "axes_matrix"]
