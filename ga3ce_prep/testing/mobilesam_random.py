"""MobileSAM's official architecture with random weights (seed 0), exported to ONNX the official way:
the files the MobileSAM tests and `make bench-objects` run, built here from registry packages.

The trained MobileSAM weights cannot be fetched from a package registry, so the tests check the
generator, the fast decoder and the pipeline against files that have the real model's graphs,
interfaces, shapes and costs, with meaningless masks:

- `mobile_sam_encoder.onnx`: the TinyViT image encoder, opset 17; `image` f32 (1, 3, 1024, 1024),
  normalised and zero-padded -> `image_embeddings` (1, 256, 64, 64).
- `mobile_sam_decoder.onnx`: the prompt encoder and mask decoder as the official
  `scripts/export_onnx_model.py` exports them (`return_single_mask=False`, dynamic point count),
  opset 17; `image_embeddings`, `point_coords` (1, N, 2), `point_labels` (1, N), `mask_input`,
  `has_mask_input`, `orig_im_size` -> `masks` (1, 4, H, W) logits, `iou_predictions` (1, 4),
  `low_res_masks` (1, 4, 256, 256).
- `mobile_sam.pt`: the same weights as the official checkpoint holds them (the model's
  `state_dict`), which the torch runtime (`runtime: torch`, estimators/segment/mobilesam_torch.py)
  reads.

How they are built (`ensure`, once; `make test-models` runs it and `make test` calls that):
1. `timm` and `mobilesam-mirror` (the official MobileSAM code), pinned by version and SHA-256,
   are installed without their dependencies into a folder of their own (a few MB;
   `estimators/segment/mobilesam_code.py`, which the torch runtime shares); the export runs in a
   subprocess of this virtual environment's Python and torch, which imports that folder's
   `mobile_sam` (`mobilesam_code.import_mobile_sam`). Nothing is added to the environment itself.
2. `mobile_sam` and `timm` import torchvision at package import for their image utilities, and
   PyPI's torchvision does not load beside the CPU build of torch. The export never calls it, so
   an empty stand-in serves the `torchvision` modules while they import
   (`mobilesam_code.absent_torchvision`).
3. `torch.manual_seed(0)`, the `vit_t` model built without a checkpoint, its attention-bias tables
   drawn from N(0, 0.5) (so the encoder graph exercises them), `eval()`, then `torch.onnx.export`
   of the encoder and of `SamOnnxModel` (TorchScript exporter, opset 17), and `torch.save` of the
   model's `state_dict` (after the exports, which it does not change).
4. The result is checked, not trusted: the decoder's graph and weights must have `DECODER_DIGEST`
   (the SHA-256 of the model with its `producer_version` field cleared: with torch 2.13 and with
   2.14.1 + torchvision 0.29.1 the files differ only there), the encoder's output on a fixed
   input must match `ENCODER_FINGERPRINT` (exports from those two torch versions agree to 3.6e-6;
   their constant-folded weights differ in the last bits), and the checkpoint's tensors must have
   `CHECKPOINT_DIGEST`. A build that fails a check is removed and the error says which.

The folder is `$GA3CE_TEST_MODELS/mobilesam-random`, else `~/.cache/ga3ce-prep/test-models/...`;
the code folder `mobilesam_code.site_dir()`.
Building takes about 20 s and a few MB of downloads.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ..estimators.segment import mobilesam_code

ENCODER = "mobile_sam_encoder.onnx"
DECODER = "mobile_sam_decoder.onnx"
CHECKPOINT = "mobile_sam.pt"
STAMP = "verified"
DECODER_DIGEST = "86cd692af82520da4b3e2f2284a2234db89f593061dea8fa0ec46a151f4a0405"
# The encoder's image_embeddings[0, ::64, ::32, ::32] (4 x 2 x 2) on `fingerprint_input()`, and
# the mean of |e| and of e^2 over the whole output.
ENCODER_FINGERPRINT: dict[str, Any] = {
    "samples": [-1.8475067615509033, -2.2048611640930176, 1.0399658679962158, -0.47132137417793274,
                0.5610381364822388, -0.002746355254203081, 0.1810426115989685, 0.8652708530426025,
                3.6112923622131348, 1.304365634918213, 1.4991906881332397, -1.6895084381103516,
                -0.15137962996959686, -0.5653195381164551, 0.5901634693145752, 0.637775182723999],
    "mean_abs": 0.7785188054907628,
    "mean_square": 0.9999965542911761,
}
ENCODER_ATOL = 5e-5
# SHA-256 over the checkpoint's tensors (`checkpoint_digest`)
CHECKPOINT_DIGEST = "945c6360fc99e4d5f1b3964c77a3ea741823b0a4410e47e50a3afae825a9bf6a"
# The stamp of a verified folder
STAMP_TEXT = f"{DECODER_DIGEST}\n{CHECKPOINT_DIGEST}\n"


def model_dir() -> Path:
    """Where the files live: $GA3CE_TEST_MODELS/mobilesam-random, else
    ~/.cache/ga3ce-prep/test-models/mobilesam-random."""
    root = os.environ.get("GA3CE_TEST_MODELS")
    base = Path(root) if root else Path.home() / ".cache" / "ga3ce-prep" / "test-models"
    return base / "mobilesam-random"


def decoder_digest(path: Path) -> str:
    """SHA-256 of the ONNX model at `path` with its `producer_version` (the torch version) cleared."""
    import onnx

    m = onnx.load(str(path))
    m.producer_version = ""
    return hashlib.sha256(m.SerializeToString()).hexdigest()


def checkpoint_digest(path: Path) -> str:
    """SHA-256 over a state dict's entries in key order: name, dtype, shape and bytes of each tensor
    (independent of torch.save's container format)."""
    import torch

    h = hashlib.sha256()
    for name, t in sorted(torch.load(str(path), map_location="cpu", weights_only=True).items()):
        h.update(f"{name}|{t.dtype}|{list(t.shape)}|".encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


def fingerprint_input() -> np.ndarray:
    """The fixed encoder input: (1, 3, 1024, 1024) float32 standard normal, numpy seed 0."""
    return np.random.default_rng(0).standard_normal((1, 3, 1024, 1024)).astype(np.float32)


def encoder_fingerprint(path: Path) -> dict:
    """The encoder's output statistics on `fingerprint_input()` (see ENCODER_FINGERPRINT)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    e = sess.run(None, {"image": fingerprint_input()})[0].astype(np.float64)
    return {"samples": e[0, ::64, ::32, ::32].ravel().tolist(), "mean_abs": float(np.abs(e).mean()),
            "mean_square": float((e ** 2).mean())}


def verify(folder: Path) -> None:
    """Raise RuntimeError unless `folder` holds the expected encoder, decoder and checkpoint (module
    docstring)."""
    got = decoder_digest(folder / DECODER)
    if got != DECODER_DIGEST:
        raise RuntimeError(f"{folder / DECODER}: graph digest {got}, expected {DECODER_DIGEST}")
    fp = encoder_fingerprint(folder / ENCODER)
    worst = max(float(np.abs(np.subtract(fp["samples"], ENCODER_FINGERPRINT["samples"])).max()),
                abs(fp["mean_abs"] - ENCODER_FINGERPRINT["mean_abs"]),
                abs(fp["mean_square"] - ENCODER_FINGERPRINT["mean_square"]))
    if worst > ENCODER_ATOL:
        raise RuntimeError(f"{folder / ENCODER}: outputs differ from the reference export by {worst:.2e} "
                           f"(tolerance {ENCODER_ATOL:.0e})")
    got = checkpoint_digest(folder / CHECKPOINT)
    if got != CHECKPOINT_DIGEST:
        raise RuntimeError(f"{folder / CHECKPOINT}: tensor digest {got}, expected {CHECKPOINT_DIGEST}")


def build(folder: Path | None = None) -> Path:
    """Build the three files into `folder` (default `model_dir()`), verify them and stamp the folder.
    Writes into a temporary sibling and renames it into place, so no half-built folder is left."""
    folder = folder or model_dir()
    folder.parent.mkdir(parents=True, exist_ok=True)
    mobilesam_code.install()
    tmp = Path(tempfile.mkdtemp(prefix=".mobilesam-random-", dir=folder.parent))
    tmp.chmod(0o755)
    try:
        print(f"[mobilesam-random] exporting the seed-0 random-weight MobileSAM to {folder}")
        subprocess.run([sys.executable, "-W", "ignore", "-m", "ga3ce_prep.testing.mobilesam_random",
                        "--export", str(tmp)], check=True, stdout=subprocess.DEVNULL)
        verify(tmp)
        (tmp / STAMP).write_text(STAMP_TEXT)
        if folder.exists():
            shutil.rmtree(folder)
        tmp.rename(folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def ensure() -> tuple[Path, Path]:
    """(encoder, decoder) paths, building them first if the verified folder is not there (or was
    verified before the checkpoint was part of it)."""
    folder = model_dir()
    stamp = folder / STAMP
    if not (stamp.is_file() and stamp.read_text() == STAMP_TEXT):
        build(folder)
    return folder / ENCODER, folder / DECODER


def checkpoint() -> Path:
    """The `mobile_sam.pt` of the same random weights (built first if needed)."""
    return ensure()[0].parent / CHECKPOINT


def _export(out: Path) -> None:
    """The export itself (module docstring, step 3), in the subprocess `build` starts."""
    import torch

    sam_model_registry = mobilesam_code.import_mobile_sam().sam_model_registry
    from mobile_sam.utils.onnx import SamOnnxModel  # imports torch only

    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    sam = sam_model_registry["vit_t"](checkpoint=None)
    with torch.no_grad():
        for name, p in sam.named_parameters():
            if name.endswith("attention_biases"):
                p.normal_(0.0, 0.5)
    sam.train()
    sam.eval()  # TinyViT caches its attention biases in eval(), so after the weights are final
    image = torch.randn(1, 3, 1024, 1024)
    torch.onnx.export(sam.image_encoder, (image,), str(out / ENCODER), opset_version=17, dynamo=False,
                      input_names=["image"], output_names=["image_embeddings"], do_constant_folding=True)
    side = sam.prompt_encoder.image_embedding_size
    example = {
        "image_embeddings": torch.randn(1, sam.prompt_encoder.embed_dim, *side),
        "point_coords": torch.randint(0, 1024, (1, 5, 2), dtype=torch.float),
        "point_labels": torch.randint(0, 4, (1, 5), dtype=torch.float),
        "mask_input": torch.randn(1, 1, 4 * side[0], 4 * side[1]),
        "has_mask_input": torch.tensor([1], dtype=torch.float),
        "orig_im_size": torch.tensor([1500, 2250], dtype=torch.float),
    }
    torch.onnx.export(SamOnnxModel(sam, return_single_mask=False), tuple(example.values()), str(out / DECODER),
                      export_params=True, opset_version=17, do_constant_folding=True, dynamo=False,
                      input_names=list(example), output_names=["masks", "iou_predictions", "low_res_masks"],
                      dynamic_axes={"point_coords": {1: "num_points"}, "point_labels": {1: "num_points"}})
    torch.save(sam.state_dict(), str(out / CHECKPOINT))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="Build (once) and verify the random-weight MobileSAM test models.")
    ap.add_argument("--export", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--rebuild", action="store_true", help="build again even if a verified folder exists")
    args = ap.parse_args(argv)
    if args.export:
        _export(args.export)
        return
    build() if args.rebuild else ensure()
    print(f"[mobilesam-random] ok: {model_dir()}")


if __name__ == "__main__":
    main()
