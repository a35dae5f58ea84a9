#!/usr/bin/env python
"""Write your MeTRAbs (or NLF) crop model as the files `pose: torchscript` and `pose: onnx` read.

    python scripts/export_crop_pose.py metrabs --model-dir metrabs_eff2l_384px_800k_28ds_pytorch --out models
    # -> models/metrabs.pt, models/metrabs.onnx (where it exports), models/metrabs.joints.txt

The written model takes image [1, S, S, 3] float32 RGB in [0, 1] (gamma as the runner makes it) and
the crop camera's intrinsics [1, 3, 3], and returns the smpl+head_30 joints [1, 30, 3] in
millimetres in the crop camera; the joint names, in that order, go to `<name>.joints.txt` beside
it (docs/models/pose.md, "The contract"). The names are the ones the paper's pipelines read from the
model folder (`{models}/metrabs.pt`, `metrabs.onnx`: docs/models/README.md); NLF's are `nlf.*`.
This script imports the authors' code from your install (MeTRAbs's `metrabs_pytorch` with
`posepile`, `simplepyutils` and hydra; or NLF's TorchScript file and torchvision): none of it is
part of ga3ce-prep.

Not run here: the weights cannot be downloaded on the machines this project is built on. What the
tests check is the shared part (`ga3ce_prep.estimators.pose.crop_export.save_crop_model`: tracing,
the files, the loaders, the comparison) on tiny models. Unchecked without the weights: that the
authors' classes load as called below; that MeTRAbs's crop model traces (and whether it exports to
ONNX: its absolute-pose step solves a least-squares system, `torch.linalg.lstsq`, which the
ONNX exporter may refuse; the TorchScript file then serves); the NLF route entirely (the
attribute and method names of NLF's TorchScript model, the units of its output, where its
smpl+head_30 canonical points live: you pass them in).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

WEIGHTS = """where to get the weights (read their licences: MeTRAbs's README allows non-commercial use only):
  MeTRAbs, PyTorch port (github.com/isarandi/metrabs, README "PyTorch"): the archive at
    https://bit.ly/metrabs_l_pt  ->  metrabs_eff2l_384px_800k_28ds_pytorch/ (config.yaml, ckpt.pt,
    joint_info.npz, skeleton_infos.pkl, joint_transform_matrix.npy); its code: pip install the
    metrabs repository with posepile and simplepyutils.
  NLF (github.com/isarandi/nlf, Releases): nlf_l_multi_<version>.torchscript; import torchvision
    first (it registers the operators the file uses).
Written without the weights: the loading of the authors' models is unverified (docs/models/pose.md,
"What was checked, and what was not"); the writing and checking of the files is tested."""
SKELETON = "smpl+head_30"


class MetrabsCrop(torch.nn.Module):
    """MeTRAbs's crop model behind the file interface: NHWC -> NCHW, its joints -> the skeleton's
    (the joint transform, then the skeleton's indices), millimetres in the crop camera."""

    def __init__(self, crop_model: torch.nn.Module, transform: np.ndarray, indices: np.ndarray):
        super().__init__()
        self.crop_model = crop_model
        self.register_buffer("transform", torch.as_tensor(transform, dtype=torch.float32))
        self.register_buffer("indices", torch.as_tensor(indices, dtype=torch.int64))

    def forward(self, image: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        joints = self.crop_model((image.permute(0, 3, 1, 2), intrinsics))
        return torch.einsum("bnc,nm->bmc", joints, self.transform)[:, self.indices]


class NlfCrop(torch.nn.Module):
    """NLF's crop model behind the file interface, at fixed canonical points (unverified)."""

    def __init__(self, crop_model: torch.nn.Module, canonical_points: np.ndarray):
        super().__init__()
        self.crop_model = crop_model
        self.register_buffer("canonical", torch.as_tensor(canonical_points, dtype=torch.float32))

    def forward(self, image: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        out = self.crop_model.predict_multi_same_canonicals(image.permute(0, 3, 1, 2), intrinsics, self.canonical)
        return out[0] if isinstance(out, (tuple, list)) else out


def load_metrabs(model_dir: Path) -> tuple[torch.nn.Module, int, list[str]]:
    """The wrapped crop model, its crop side and the skeleton's joint names, from the PyTorch port's
    model folder."""
    try:
        import posepile.joint_info
        import simplepyutils as spu
        from metrabs_pytorch.backbones import efficientnet
        from metrabs_pytorch.models import metrabs
        from metrabs_pytorch.util import get_config
    except ImportError as e:
        sys.exit(f"cannot import MeTRAbs's PyTorch code ({e}): install the metrabs repository, posepile and "
                 f"simplepyutils.\n{WEIGHTS}")
    cfg = get_config(str((model_dir / "config.yaml").resolve()))
    info = np.load(model_dir / "joint_info.npz")
    joint_info = posepile.joint_info.JointInfo(info["joint_names"], info["joint_edges"])
    features = getattr(efficientnet, f"efficientnet_v2_{cfg.efficientnet_size}")().features
    model = metrabs.Metrabs(torch.nn.Sequential(efficientnet.PreprocLayer(), features), joint_info).eval()
    side = int(cfg.proc_side)
    with torch.no_grad():  # a first call sizes the lazy head before the weights go in
        model((torch.zeros(1, 3, side, side), torch.eye(3)[None]))
    model.load_state_dict(torch.load(model_dir / "ckpt.pt", map_location="cpu"))
    skeleton = spu.load_pickle(str(model_dir / "skeleton_infos.pkl"))[SKELETON]
    transform = np.load(model_dir / "joint_transform_matrix.npy")
    return MetrabsCrop(model, transform, np.asarray(skeleton["indices"])), side, [str(n) for n in skeleton["names"]]


def load_nlf(model: Path, canonical: Path, names: Path,
             resolution: int | None) -> tuple[torch.nn.Module, int, list[str]]:
    """The wrapped crop model of NLF's multi-person TorchScript file (its `crop_model`), at your
    canonical points (J, 3) for the joints named in `names` (one per line)."""
    import torchvision  # noqa: F401 - registers the operators NLF's TorchScript file uses

    crop = torch.jit.load(str(model), map_location="cpu").crop_model
    side = resolution or int(getattr(crop, "input_resolution", 0))
    if not side:
        sys.exit("NLF's crop model has no input_resolution: pass --resolution")
    joint_names = [n.strip() for n in names.read_text().splitlines() if n.strip()]
    points = np.load(canonical)
    if points.shape != (len(joint_names), 3):
        sys.exit(f"--canonical-points {canonical} is {points.shape}; expected ({len(joint_names)}, 3), one per name")
    return NlfCrop(crop, points), side, joint_names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=WEIGHTS,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="family", required=True)
    m = sub.add_parser("metrabs", help="MeTRAbs's PyTorch port (the 28-dataset models)", epilog=WEIGHTS,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    m.add_argument("--model-dir", type=Path, required=True,
                   help="the unpacked model folder (config.yaml, ckpt.pt, ...)")
    n = sub.add_parser("nlf", help="NLF's multi-person TorchScript file (unverified route)", epilog=WEIGHTS,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    n.add_argument("--model", type=Path, required=True, help="nlf_*_multi_*.torchscript")
    n.add_argument("--canonical-points", type=Path, required=True,
                   help=".npy (J, 3): NLF's canonical points of the joints")
    n.add_argument("--joint-names", type=Path, required=True, help="text file: the J joint names, one per line")
    n.add_argument("--resolution", type=int, help="crop side S when the crop model does not say it")
    for p, name in ((m, "metrabs"), (n, "nlf")):
        p.add_argument("--out", type=Path, required=True,
                       help="the model folder (created): writes NAME.pt, NAME.onnx, NAME.joints.txt into it")
        p.add_argument("--name", default=name, help=f"the files' stem (default: {name}, as the pipelines read it)")
        p.add_argument("--no-onnx", action="store_true", help="write the TorchScript file only")
    args = ap.parse_args(argv)

    from ga3ce_prep.estimators.pose.crop import select_joints
    from ga3ce_prep.estimators.pose.crop_export import save_crop_model

    if args.family == "metrabs":
        module, side, names = load_metrabs(args.model_dir)
    else:
        module, side, names = load_nlf(args.model, args.canonical_points, args.joint_names, args.resolution)
    select_joints(names, "the model's joint names")  # all 30 smpl+head_30 names present, before the work
    args.out.mkdir(parents=True, exist_ok=True)
    out = save_crop_model(module, side, names, args.out / args.name, onnx=not args.no_onnx)
    print(f"wrote {out.torchscript} (S = {side}) and {out.joints} ({len(names)} joints)")
    print(f"wrote {out.onnx}" if out.onnx else f"no ONNX file ({out.onnx_error}); use pose: torchscript")
    print("largest difference from the module on a random crop, mm: "
          + ", ".join(f"{k} {v:.3g}" for k, v in out.max_diff_mm.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
