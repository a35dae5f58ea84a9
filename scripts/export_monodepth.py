"""Export a metric monocular depth network to ONNX for `depth: onnx` (docs/models/depth.md,
"Exporting ZoeDepth or Depth-Anything-V2-metric").

It imports YOUR install of the network's code and weights; nothing of that code is part of
ga3ce-prep:
  zoedepth                  isl-org/ZoeDepth (a clone on PYTHONPATH, its environment: torch, timm
                            0.6.12) and MiDaS's hub code in the torch hub cache (ZoeDepth's builder
                            calls torch.hub.load("intel-isl/MiDaS", ...) even to load a checkpoint)
  depth-anything-v2-metric  DepthAnything/Depth-Anything-V2's `metric_depth` folder (--repo)

    python scripts/export_monodepth.py zoedepth --variant N --checkpoint ZoeD_M12_N.pt \\
        --image-size 1920x1080 --out models
    # -> models/zoedepth.onnx, the name gfie-monodepth and gafa read (docs/models/README.md)
    python scripts/export_monodepth.py depth-anything-v2-metric --repo Depth-Anything-V2/metric_depth \\
        --encoder vitl --max-depth 20 --checkpoint depth_anything_v2_metric_hypersim_vitl.pth \\
        --image-size 1920x1080 --out models
    # -> models/depth_anything_v2_metric_indoor.onnx (no bundled pipeline reads it: --set its path)

The file's input is fixed at the size `depth/onnx` computes for images of --image-size under the
network's preset (ZoeDepth 1920x1080 -> 384x672, Depth-Anything 1920x1080 -> 518x924), so the file
and the runner agree: one export per image size. The output is the metric depth in metres. The
script then checks the ONNX file against the PyTorch model on a random input (largest absolute
difference) and runs it through the `depth/onnx` runner on a grey image.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ga3ce_prep.estimators.depth.monodepth import (  # noqa: E402
    PRESETS,
    MonoDepthEstimator,
    MonoDepthOptions,
    network_size,
)

# Depth-Anything-V2's model sizes, as its metric_depth README lists them (encoder -> constructor arguments)
DA2_CONFIGS = {
    "vits": {"encoder": "vits", "features": 64, "out_channels": [48, 96, 192, 384]},
    "vitb": {"encoder": "vitb", "features": 128, "out_channels": [96, 192, 384, 768]},
    "vitl": {"encoder": "vitl", "features": 256, "out_channels": [256, 512, 1024, 1024]},
}
# ZoeDepth's variants: get_config(model name, "infer", config_version=...) as its hubconf.py builds them;
# ZoeD_K's config has img_size [384, 768] (N and NK: the preset's [384, 512])
ZOE_VARIANTS = {"N": ("zoedepth", None), "K": ("zoedepth", "kitti"), "NK": ("zoedepth_nk", None)}
ZOE_K_SIZE = (384, 768)


def metric_module(forward):
    """A torch module whose forward(image (1, 3, H, W)) is `forward`'s metric depth."""
    import torch

    class MetricDepth(torch.nn.Module):
        def __init__(self, net):
            super().__init__()
            self.net = net

        def forward(self, image):
            return forward(self.net, image)

    return MetricDepth


def load_zoedepth(variant: str, checkpoint: Path):
    """ZoeD_N / ZoeD_K / ZoeD_NK from a local checkpoint, returning `metric_depth` only. NK picks its
    head per image with Python control flow: the export freezes the head the example input chose."""
    from zoedepth.models.builder import build_model
    from zoedepth.utils.config import get_config

    name, version = ZOE_VARIANTS[variant]
    kw = {"config_version": version} if version else {}
    conf = get_config(name, "infer", pretrained_resource=f"local::{checkpoint}", **kw)
    net = build_model(conf).eval()
    return metric_module(lambda m, x: m(x)["metric_depth"])(net).eval()


def load_depth_anything_v2_metric(repo: Path, encoder: str, max_depth: float, checkpoint: Path):
    """Depth-Anything-V2's metric model (Hypersim: max_depth 20, Virtual KITTI 2: 80) from the
    repository's metric_depth folder."""
    import torch

    sys.path.insert(0, str(repo))
    from depth_anything_v2.dpt import DepthAnythingV2

    net = DepthAnythingV2(**{**DA2_CONFIGS[encoder], "max_depth": max_depth})
    net.load_state_dict(torch.load(checkpoint, map_location="cpu", weights_only=True))
    return metric_module(lambda m, x: m(x))(net.eval()).eval()


def export(module, size: tuple[int, int], out: Path, opset: int = 17) -> Path:
    """Trace `module` on a (1, 3, H, W) input of `size` into `out` (input "image", output "depth")."""
    import torch

    out.parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad(), warnings.catch_warnings():
        # the TorchScript exporter, on purpose: it traces both networks
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(module, (torch.rand(1, 3, *size),), str(out), opset_version=opset, dynamo=False,
                          do_constant_folding=True, input_names=["image"], output_names=["depth"])
    return out


def verify(module, out: Path, opt: MonoDepthOptions, image_size: tuple[int, int]) -> dict:
    """The ONNX file against the module on a random input, and through the runner (options `opt`)
    on a grey image."""
    import onnxruntime as ort
    import torch

    H, W = network_size(*image_size, opt)
    x = np.random.default_rng(0).random((1, 3, H, W), np.float32)
    with torch.no_grad():
        ref = module(torch.from_numpy(x)).numpy()
    got = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]).run(None, {"image": x})[0]
    est = MonoDepthEstimator(out, opt, what="export")
    w, h = image_size
    K = np.array([[w, 0, w / 2], [0, w, h / 2], [0, 0, 1]], np.float64)
    grey = est.predict(np.full((h, w, 3), 128, np.uint8), K)
    return {"input": [H, W], "max_abs_diff_m": float(np.abs(got.reshape(ref.shape) - ref).max()),
            "grey_median_m": float(np.median(grey.depth[grey.valid]))}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="network", required=True)
    zoe = sub.add_parser("zoedepth", help="isl-org/ZoeDepth (preset zoedepth)")
    zoe.add_argument("--variant", choices=list(ZOE_VARIANTS), default="N",
                     help="N: NYU (indoor), K: KITTI, NK: both heads")
    da = sub.add_parser("depth-anything-v2-metric",
                        help="Depth-Anything-V2 metric (presets depth-anything-v2-metric-*)")
    da.add_argument("--repo", type=Path, required=True, help="the repository's metric_depth folder")
    da.add_argument("--encoder", choices=list(DA2_CONFIGS), default="vitl")
    da.add_argument("--max-depth", type=float, default=20.0, help="20 for the Hypersim (indoor) weights, 80 for VKITTI")
    for p in (zoe, da):
        p.add_argument("--checkpoint", type=Path, required=True)
        p.add_argument("--image-size", required=True, help="WxH of the dataset's images, e.g. 1920x1080")
        p.add_argument("--out", type=Path, required=True, help="the model folder (created): writes NAME.onnx into it")
        p.add_argument("--name", help="the file's stem; default: zoedepth, or the Depth-Anything preset's name "
                                      "with underscores")
        p.add_argument("--opset", type=int, default=17)
    a = ap.parse_args(argv)
    image_size = tuple(int(v) for v in a.image_size.lower().split("x"))
    extra = ""
    if a.network == "zoedepth":
        preset, module = "zoedepth", load_zoedepth(a.variant, a.checkpoint)
        opt = PRESETS[preset]
        if a.variant == "K":
            opt, extra = dataclasses.replace(opt, size=ZOE_K_SIZE), f", size: {list(ZOE_K_SIZE)}"
    else:
        preset = "depth-anything-v2-metric-indoor" if a.max_depth <= 20 else "depth-anything-v2-metric-outdoor"
        module, opt = load_depth_anything_v2_metric(a.repo, a.encoder, a.max_depth, a.checkpoint), PRESETS[preset]
    size = network_size(*image_size, opt)
    out = a.out / f"{a.name or preset.replace('-', '_')}.onnx"
    export(module, size, out, a.opset)
    print(f"wrote {out} (input 1x3x{size[0]}x{size[1]}); check: {verify(module, out, opt, image_size)}")
    print(f"pipeline: stages.depth: {{backend: onnx, params: {{model: {out}, preset: {preset}{extra}}}}}")


if __name__ == "__main__":
    main()
