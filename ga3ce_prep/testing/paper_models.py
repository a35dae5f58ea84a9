"""Tiny models with the interfaces of the paper's models, for the tests and benchmarks: a model
folder that `ga3ce_prep/pipelines/gfie.yaml`, `cad120.yaml` and `gafa.yaml` run end to end with (`{models}`).

Each model's output is a known function of its input, so a test can check what the pipeline did:
- MobileSAM: `scripted.pooling_encoder` + `scripted.scripted_decoder` on a quadrant label image;
- MeTRAbs-family crop model (`Constant`): fixed joints in the crop camera, millimetres;
- GFIE's network (head branch and GFM): random weights saved as GFIE saves its checkpoint;
- metric monocular depth (`linear_depth_model`): depth = a * channel 0 + b, any input size;
- GAFA's view network: `scripted.centroid_gazenet`.

And stand-ins for the authors' networks that scripts/export_*.py import (`Constant`, `StandInDepth`,
`StandInGazeNet`), with which tests/test_model_folder.py follows the recipes of docs/models/README.md.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch


def linear_depth_model(path: Path, outputs: dict[str, tuple[float, float]], *, layout: str = "nchw",
                       size: tuple[int | str, int | str] = ("h", "w"), n_inputs: int = 1) -> Path:
    """An ONNX file: one float input (1, 3, H, W) or (1, H, W, 3) (int: fixed, str: dynamic), and per
    output name -> (a, b) an output a * channel0 + b of shape (1, 1, H, W) (nhwc: (1, H, W, 1))."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    caxis = 1 if layout == "nchw" else 3
    shape = [1, 3, *size] if layout == "nchw" else [1, *size, 3]
    oshape = [1, 1, *size] if layout == "nchw" else [1, *size, 1]
    inits = [numpy_helper.from_array(np.array(v, np.int64), n) for n, v in
             (("starts", [0]), ("ends", [1]), ("axes", [caxis]))]
    nodes = [helper.make_node("Slice", ["image", "starts", "ends", "axes"], ["c0"])]
    outs = []
    for name, (a, b) in outputs.items():
        inits += [numpy_helper.from_array(np.array(a, np.float32), f"a_{name}"),
                  numpy_helper.from_array(np.array(b, np.float32), f"b_{name}")]
        nodes += [helper.make_node("Mul", ["c0", f"a_{name}"], [f"m_{name}"]),
                  helper.make_node("Add", [f"m_{name}", f"b_{name}"], [name])]
        outs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, oshape))
    ins = [helper.make_tensor_value_info(f"in{i}" if i else "image", TensorProto.FLOAT, shape) for i in range(n_inputs)]
    graph = helper.make_graph(nodes, "linear_depth", ins, outs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


class Constant(torch.nn.Module):
    """A crop model returning fixed joints (J, 3) mm in the crop camera; the inputs enter with
    weight 0 (so an ONNX export keeps them)."""

    if TYPE_CHECKING:  # not at run time: TorchScript cannot read a string annotation
        joints: torch.Tensor  # a buffer

    def __init__(self, joints_mm: np.ndarray):
        super().__init__()
        self.register_buffer("joints", torch.as_tensor(joints_mm, dtype=torch.float32))

    def forward(self, image: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        zero = 0.0 * (image.float().mean() + intrinsics.sum())
        return self.joints[None].expand(image.shape[0], -1, -1) + zero


class StandInGazeNet(torch.nn.Module):
    """GAFA's GazeNet's call convention, forward(image (B, 7, 3, H, W), head_mask (B, 7, 1, H, W),
    body_dv (B, 7, 2)) -> ({"direction": (B, 7, 3) unit}, {}, {}), with a few random weights: what
    scripts/export_gafa_view.py wraps and exports, for the tests that follow its recipe."""

    def __init__(self, seed: int = 0):
        super().__init__()
        torch.manual_seed(seed)
        self.fc = torch.nn.Linear(2, 3)

    def forward(self, image: torch.Tensor, head_mask: torch.Tensor, body_dv: torch.Tensor):
        d = self.fc(body_dv) + image.mean((2, 3, 4))[..., None] + head_mask.mean((2, 3, 4))[..., None] + 0.5
        return {"direction": d / d.norm(dim=-1, keepdim=True)}, {}, {}


class StandInDepth(torch.nn.Module):
    """A metric depth network's call convention (image (1, 3, H, W) -> (1, 1, H, W) metres):
    depth = 1.5 m + the red channel, for the tests that follow scripts/export_monodepth.py's recipe."""

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return 1.5 + image[:, :1]


def constant_joints() -> np.ndarray:
    """The joints of the crop models written here: every joint at CROP_DEPTH_MM on the crop axis plus
    a small per-joint offset, millimetres (one per skeleton joint)."""
    from ..skeleton import JOINT_NAMES

    offsets = np.linspace(-300.0, 300.0, len(JOINT_NAMES))
    return np.stack([0.3 * offsets, offsets, CROP_DEPTH_MM + 0.1 * offsets], 1)


def random_gfie_net(seed: int = 0):
    """GFIE's whole network (`estimators/view/gfie_net.py::GFIENet`) with random weights and random BN
    statistics (so a load that skipped any tensor would change the output)."""
    from ..estimators.view.gfie_net import GFIENet

    torch.manual_seed(seed)
    net = GFIENet()
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            assert m.running_mean is not None and m.running_var is not None  # GFIE's BatchNorms track them
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
            m.weight.data.uniform_(0.5, 1.5)
    return net.eval()


def gfie_state(net) -> dict:
    """The state dict of GFIE's whole network as its checkpoint holds it (GFIE's key names)."""
    return dict(net.state_dict())


def gfie_checkpoint(state: dict) -> dict:
    """What GFIE's save_checkpoint writes (utils/model_utils.py): the whole network's state dict, the
    epoch, the validation errors as numpy float64 and the optimiser's state."""
    return {"epoch": 12, "state_dict": state, "best_dist_err": np.float64(0.0697), "best_cosine_err": np.float64(0.82),
            "optimizer": {"state": {}, "param_groups": [{"lr": 1e-4, "betas": (0.9, 0.999), "eps": 1e-8,
                                                         "weight_decay": 1e-4, "amsgrad": False, "params": [0, 1]}]}}


# joints of the Constant crop model: a standing person 3 m down the crop's axis, millimetres
CROP_DEPTH_MM = 3000.0


def write_paper_models(folder: Path, depth_m: float = 2.0, crop_size: int = 64) -> dict[str, Path]:
    """Write the paper pipelines' model files into `folder` under the names the bundled pipelines
    use; returns name -> path. Depth model: depth_m metres everywhere; crop model: every joint at
    CROP_DEPTH_MM on the crop axis plus a small per-joint offset."""
    import onnx

    from ..estimators.pose.crop_export import save_crop_model
    from ..skeleton import JOINT_NAMES
    from . import scripted

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {"mobile_sam_encoder": folder / "mobile_sam_encoder.onnx",
             "mobile_sam_decoder": folder / "mobile_sam_decoder.onnx",
             "metrabs": folder / "metrabs.pt", "gfiemodel": folder / "gfiemodel.pt.tar",
             "zoedepth": folder / "zoedepth.onnx", "gafa_view": folder / "gafa_view.onnx"}
    labels = np.zeros((480, 640), np.int64)
    labels[:240, :320], labels[:240, 320:], labels[240:, :320], labels[240:, 320:] = 1, 2, 3, 4
    onnx.save(scripted.pooling_encoder(), str(paths["mobile_sam_encoder"]))
    onnx.save(scripted.scripted_decoder(labels), str(paths["mobile_sam_decoder"]))
    save_crop_model(Constant(constant_joints()), crop_size, JOINT_NAMES, folder / "metrabs")
    torch.save(gfie_checkpoint(gfie_state(random_gfie_net())), paths["gfiemodel"])
    linear_depth_model(paths["zoedepth"], {"depth": (0.0, depth_m)})
    onnx.save(scripted.centroid_gazenet(), str(paths["gafa_view"]))
    paths["metrabs_onnx"] = folder / "metrabs.onnx"
    return paths
