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
3. The `vit_t` model is built without a checkpoint, and every tensor torch's initialisers draw at
   random is drawn again from numpy's PCG64 (`random_state`: uniform, with torch's default bounds;
   TinyViT's attention-bias tables, zero in torch's init, get a standard deviation of 0.5 so the
   encoder graph exercises them). torch's own draws (`manual_seed`, `normal_`, `kaiming_uniform_`)
   run kernels picked for the CPU's vector unit, so one seed gave other last bits on an AVX2 CPU
   than on an AVX-512 one; numpy's generator and one float32 rounding give the same bytes on every
   CPU. Then `eval()`, `torch.onnx.export` of the encoder and of `SamOnnxModel` (TorchScript
   exporter, opset 17; tracing inputs from numpy too), and `torch.save` of the model's `state_dict`.
4. The result is checked, not trusted: the decoder's graph and weights must have `DECODER_DIGEST`
   (the SHA-256 of the model with its `producer_version` field cleared), the checkpoint's tensors
   `CHECKPOINT_DIGEST`, and the encoder's output on a fixed input must match `ENCODER_FINGERPRINT`
   within `ENCODER_ATOL`. The two digests and the encoder file's bytes are the same under
   `ATEN_CPU_CAPABILITY=default`, `avx2` and `avx512`, and with MKL and oneDNN held to AVX2
   (tests/test_cpu_independence.py builds under each capability the CPU offers). The
   fingerprint runs ONNX Runtime, whose kernels also follow the CPU: its output moved by at most
   1.3e-6 between graph optimisation levels and thread counts, and torch's encoder on the same
   weights under each capability by 1.9e-6, 26x inside the tolerance. A build that fails a
   check is removed and the error says which.

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
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ..estimators.segment import mobilesam_code

ENCODER = "mobile_sam_encoder.onnx"
DECODER = "mobile_sam_decoder.onnx"
CHECKPOINT = "mobile_sam.pt"
STAMP = "verified"
SEED = 0
DECODER_DIGEST = "77d27d97a09189ab2aa92443516d7972654e7770249920782c5719269e66b2a0"
# The encoder's image_embeddings[0, ::64, ::32, ::32] (4 x 2 x 2) on `fingerprint_input()`, and
# the mean of |e| and of e^2 over the whole output.
ENCODER_FINGERPRINT: dict[str, Any] = {
    "samples": [-0.7090657949447632, -0.6424496173858643, -0.48645883798599243, -0.5037955641746521,
                -0.3097301125526428, 0.7120973467826843, 0.13895584642887115, 0.3962644040584564,
                0.6688147783279419, 0.606624186038971, 0.9793685674667358, 0.04302418231964111,
                -0.29685524106025696, -0.0659899115562439, 0.15877048671245575, 0.4988658130168915],
    "mean_abs": 0.7804528525188643,
    "mean_square": 0.9999970439869053,
}
ENCODER_ATOL = 5e-5
# SHA-256 over the checkpoint's tensors (`checkpoint_digest`)
CHECKPOINT_DIGEST = "b574eecf0e784ca64fecf3ea7c90a40c78c13b3cffd0bfeffc113a058c201734"
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


def _draw(name: str, shape: tuple[int, ...], bound: float) -> np.ndarray:
    """U(-bound, bound) of `shape` as float32, from numpy's PCG64 seeded by (SEED, CRC-32 of `name`).
    Only IEEE basic operations turn the generator's integers into values (a multiply and an add
    per value, then one rounding to float32), so the bytes are the same on every CPU, whatever
    vector unit torch's or numpy's kernels would pick."""
    rng = np.random.default_rng([SEED, zlib.crc32(name.encode())])
    return rng.uniform(-bound, bound, shape).astype(np.float32)


def random_state(sam: Any) -> dict[str, np.ndarray]:
    """Every tensor of `sam`'s state dict that torch's initialisers draw at random, drawn again with
    `_draw` (the module docstring's step 3 gives the rule); the constant ones (norms' ones and
    zeros, zero biases, BatchNorm statistics) are left out, and stay as torch sets them, exactly.

    - Linear, Conv2d, ConvTranspose2d weights and their non-zero biases: U(±1/sqrt(fan_in)), the
      bound of torch's default initialiser (fan_in as `torch.nn.init` computes it from the weight);
    - Embedding weights and the prompt encoder's Gaussian positional matrix: unit variance, U(±√3),
      as torch's N(0, 1);
    - TinyViT's attention biases: standard deviation 0.5, U(±0.5·√3), so the encoder's graph
      exercises them (torch's init leaves them at zero).
    Raises ValueError on a randomly initialised tensor the rule does not cover."""
    import torch

    owner = {}
    for mod_name, mod in sam.named_modules():
        for kind in (mod.named_parameters(recurse=False), mod.named_buffers(recurse=False)):
            for t_name, _ in kind:
                owner[f"{mod_name}.{t_name}" if mod_name else t_name] = (mod, t_name)
    unit = float(np.sqrt(3.0))
    out = {}
    for name, t in sam.state_dict().items():
        mod, leaf = owner[name]
        if leaf == "attention_biases":
            out[name] = _draw(name, tuple(t.shape), 0.5 * unit)
            continue
        if not t.is_floating_point() or bool((t == t.reshape(-1)[0]).all()):
            continue  # constants: exact on every CPU
        if isinstance(mod, (torch.nn.Linear, torch.nn.Conv2d, torch.nn.ConvTranspose2d)):
            fan_in = int(np.prod(mod.weight.shape[1:]))   # as torch.nn.init counts it
            out[name] = _draw(name, tuple(t.shape), 1.0 / float(np.sqrt(fan_in)))
        elif isinstance(mod, torch.nn.Embedding) or leaf == "positional_encoding_gaussian_matrix":
            out[name] = _draw(name, tuple(t.shape), unit)
        else:
            raise ValueError(f"{name} ({type(mod).__name__}.{leaf}): randomly initialised, no rule draws it")
    return out


def _export(out: Path) -> None:
    """The export itself (module docstring, step 3), in the subprocess `build` starts."""
    import torch

    sam_model_registry = mobilesam_code.import_mobile_sam().sam_model_registry
    from mobile_sam.utils.onnx import SamOnnxModel  # imports torch only

    out.mkdir(parents=True, exist_ok=True)
    sam = sam_model_registry["vit_t"](checkpoint=None)
    state = {k: torch.from_numpy(v) for k, v in random_state(sam).items()}
    unexpected = sam.load_state_dict(state, strict=False).unexpected_keys
    assert not unexpected, unexpected
    sam.train()
    sam.eval()  # TinyViT caches its attention biases in eval(), so after the weights are final
    # example inputs for tracing only (they fix shapes, not values); numpy's, like the weights
    ex = np.random.default_rng(SEED)
    image = torch.from_numpy(ex.uniform(-1, 1, (1, 3, 1024, 1024)).astype(np.float32))
    torch.onnx.export(sam.image_encoder, (image,), str(out / ENCODER), opset_version=17, dynamo=False,
                      input_names=["image"], output_names=["image_embeddings"], do_constant_folding=True)
    side = sam.prompt_encoder.image_embedding_size
    example = {
        "image_embeddings": torch.from_numpy(ex.uniform(-1, 1, (1, sam.prompt_encoder.embed_dim, *side))
                                             .astype(np.float32)),
        "point_coords": torch.from_numpy(ex.integers(0, 1024, (1, 5, 2)).astype(np.float32)),
        "point_labels": torch.from_numpy(ex.integers(0, 4, (1, 5)).astype(np.float32)),
        "mask_input": torch.from_numpy(ex.uniform(-1, 1, (1, 1, 4 * side[0], 4 * side[1])).astype(np.float32)),
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
