"""Export GAFA's GazeNet (kyotovision-public/dynamic-3d-gaze-from-afar) to the ONNX file that the
pipeline's `view: gafa` backend reads (docs/models/view.md, "GAFA's view network").

    python scripts/export_gafa_view.py --gafa dynamic-3d-gaze-from-afar --out models
    # -> models/gafa_view.onnx, the name the gafa pipeline reads (docs/models/README.md)

Run it in the environment GAFA's code runs in (its conda.yaml: torch, efficientnet_pytorch,
pytorch_lightning); it imports `models.gazenet` from the --gafa folder and copies none of it. The
weights default to the folder's `models/weights/gazenet_GAFA.pth` (GAFA's README links them).

The file maps image (B, 7, 3, 256, 192), head_mask (B, 7, 1, 256, 192) and body_dv (B, 7, 2),
float32, to gaze (B, 7, 3): GazeNet's gaze direction for each frame of the window (the first
output of its forward, `["direction"]`), with B a dynamic axis. EfficientNet's memory-efficient
swish (a custom autograd function the exporter cannot trace) is switched to the plain swish,
which computes the same values. The script then runs the file with ONNX Runtime, when installed,
on one random window and prints the largest difference from PyTorch.
"""
from __future__ import annotations

import argparse
import inspect
import sys
from pathlib import Path

import numpy as np
import torch

WINDOW, CROP_H, CROP_W = 7, 256, 192
INPUTS = ("image", "head_mask", "body_dv")
NAME = "gafa_view.onnx"  # as the gafa pipeline reads it: {models}/gafa_view.onnx


class GazeOnly(torch.nn.Module):
    """GazeNet's forward (image, head_mask, body_dv) -> its per-frame gaze direction (B, 7, 3)."""

    def __init__(self, net: torch.nn.Module):
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor, head_mask: torch.Tensor, body_dv: torch.Tensor) -> torch.Tensor:
        return self.net(image, head_mask, body_dv)[0]["direction"]


def load_gazenet(gafa: Path, checkpoint: Path, unsafe_load: bool = False) -> torch.nn.Module:
    """GAFA's GazeNet(n_frames=7) from the --gafa folder with the checkpoint's `state_dict`, in eval
    mode, with plain swish activations."""
    sys.path.insert(0, str(gafa))
    from models.gazenet import GazeNet  # GAFA's code, from the user's folder

    safe = "weights_only" in inspect.signature(torch.load).parameters and not unsafe_load
    try:
        state = torch.load(checkpoint, map_location="cpu", **({"weights_only": True} if safe else {}))
    except Exception as e:  # torch raises its own unpickling errors
        sys.exit(f"cannot load {checkpoint} with weights_only=True ({e}); if you trust the file, rerun with "
                 "--unsafe-load")
    net = GazeNet(n_frames=WINDOW)
    net.load_state_dict(state["state_dict"])
    for m in net.modules():
        if hasattr(m, "set_swish"):  # efficientnet_pytorch's EfficientNet and its blocks
            m.set_swish(memory_efficient=False)
    return GazeOnly(net).eval()


def example_window(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A random window of the network's inputs (batch 1): normalised images, a head box mask, a
    small body velocity."""
    g = torch.Generator().manual_seed(seed)
    image = torch.randn(1, WINDOW, 3, CROP_H, CROP_W, generator=g)
    mask = torch.zeros(1, WINDOW, 1, CROP_H, CROP_W)
    mask[..., 10:70, 60:130] = 1
    return image, mask, 0.01 * torch.randn(1, WINDOW, 2, generator=g)


def export(model: torch.nn.Module, out: Path, opset: int = 13) -> float | None:
    """Write the ONNX file; the largest |ONNX - PyTorch| on example_window(), None without
    onnxruntime."""
    out.parent.mkdir(parents=True, exist_ok=True)
    args = example_window()
    axes = {name: {0: "batch"} for name in (*INPUTS, "gaze")}
    extra = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}
    with torch.no_grad():
        torch.onnx.export(model, args, str(out), input_names=list(INPUTS), output_names=["gaze"],
                          dynamic_axes=axes, opset_version=opset, **extra)
        expected = model(*args).numpy()
    try:
        import onnxruntime as ort
    except ImportError:
        return None
    sess = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    got = sess.run(["gaze"], {n: a.numpy() for n, a in zip(INPUTS, args)})[0]
    return float(np.abs(got - expected).max())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gafa", type=Path, required=True, help="your clone of dynamic-3d-gaze-from-afar")
    ap.add_argument("--checkpoint", type=Path, help="default: GAFA/models/weights/gazenet_GAFA.pth")
    ap.add_argument("--out", type=Path, default=Path("models"),
                    help=f"the model folder (created): writes {NAME} into it")
    ap.add_argument("--opset", type=int, default=13)
    ap.add_argument("--unsafe-load", action="store_true", help="torch.load the checkpoint without weights_only")
    a = ap.parse_args(argv)
    ckpt = a.checkpoint or a.gafa / "models" / "weights" / "gazenet_GAFA.pth"
    out = a.out / NAME
    diff = export(load_gazenet(a.gafa.resolve(), ckpt, a.unsafe_load), out, a.opset)
    check = "onnxruntime not installed: not checked" if diff is None else f"max |ONNX - PyTorch| = {diff:.2e}"
    print(f"wrote {out} ({check})")


if __name__ == "__main__":
    main()
