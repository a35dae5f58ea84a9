"""`ga3ce-prep export-mobilesam`: a trained MobileSAM checkpoint -> the two ONNX files the
`objects/mobilesam` backend reads. It imports the MobileSAM code the user has installed (the official
repository, or the `mobilesam-mirror` package), or the private copy of segment/mobilesam_code.py, and
torch; none of that code is part of ga3ce-prep.

`ga3ce-prep export-gfie-view`: GFIE's checkpoint -> its head network as one ONNX file for
`view/onnx` (the network is ours, estimators/view/gfie_head.py; only torch is needed)."""
from __future__ import annotations

import functools
from pathlib import Path

import click

ENCODER_NAME = "mobile_sam_encoder.onnx"
DECODER_NAME = "mobile_sam_decoder.onnx"


def _import_mobile_sam():
    from .segment.mobilesam_code import FIX, import_mobile_sam

    try:
        sam_model_registry = import_mobile_sam().sam_model_registry
        from mobile_sam.utils.onnx import SamOnnxModel
    except ImportError as e:
        raise click.ClickException(
            f"export-mobilesam needs the official MobileSAM code and timm ({e}): {FIX} "
            "(or: pip install timm git+https://github.com/ChaoningZhang/MobileSAM)") from e
    return sam_model_registry, SamOnnxModel


def export_onnx(checkpoint: Path, out_dir: Path, opset: int = 17) -> tuple[Path, Path]:
    """Export the image encoder (normalised [1, 3, 1024, 1024] input) and the prompt encoder + mask
    decoder exactly as MobileSAM's scripts/export_onnx_model.py does (return_single_mask=False,
    dynamic num_points), both with torch.onnx.export(dynamo=False). Returns the two paths."""
    import torch

    sam_model_registry, SamOnnxModel = _import_mobile_sam()
    sam = sam_model_registry["vit_t"](checkpoint=None)
    state = torch.load(str(checkpoint), map_location="cpu", weights_only=True)
    sam.load_state_dict(state, strict=True)
    sam.eval()  # after loading: TinyViT caches its attention biases in eval()
    export = functools.partial(torch.onnx.export, dynamo=False, opset_version=opset, do_constant_folding=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    enc, dec = out_dir / ENCODER_NAME, out_dir / DECODER_NAME
    with torch.no_grad():
        export(sam.image_encoder, (torch.randn(1, 3, 1024, 1024),), str(enc),
               input_names=["image"], output_names=["image_embeddings"])
        model = SamOnnxModel(sam, return_single_mask=False)
        dummy = {
            "image_embeddings": torch.randn(1, 256, 64, 64),
            "point_coords": torch.randint(0, 1024, (1, 5, 2), dtype=torch.float),
            "point_labels": torch.randint(0, 4, (1, 5), dtype=torch.float),
            "mask_input": torch.randn(1, 1, 256, 256),
            "has_mask_input": torch.tensor([1], dtype=torch.float),
            "orig_im_size": torch.tensor([1500, 2250], dtype=torch.float),
        }
        export(model, tuple(dummy.values()), str(dec), export_params=True, input_names=list(dummy),
               output_names=["masks", "iou_predictions", "low_res_masks"],
               dynamic_axes={"point_coords": {1: "num_points"}, "point_labels": {1: "num_points"}})
    return enc, dec


@click.command("export-mobilesam")
@click.option("--checkpoint", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="The trained MobileSAM weights (mobile_sam.pt, a state dict).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help=f"Folder to write {ENCODER_NAME} and {DECODER_NAME} into (created if missing).")
@click.option("--opset", type=int, default=17, show_default=True, help="ONNX opset of both exports.")
@click.option("--check/--no-check", default=True, show_default=True,
              help="Load both files with ONNX Runtime, check their interfaces, and check the fast decoder "
                   "built from the decoder's weights against the exported graph.")
def export_mobilesam(checkpoint: Path, out_dir: Path, opset: int, check: bool) -> None:
    """Export a trained MobileSAM checkpoint to the ONNX files of the `objects/mobilesam` backend.

    \b
    Needs torch, timm and MobileSAM's code installed (pip install timm mobilesam-mirror).
    Then point a pipeline at them:
      stages: {objects: {backend: mobilesam, params: {encoder: DIR/mobile_sam_encoder.onnx,
                                                      decoder: DIR/mobile_sam_decoder.onnx}}}
    """
    enc, dec = export_onnx(checkpoint, out_dir, opset)
    click.echo(f"wrote {enc}\nwrote {dec}")
    if check:
        from ..files import file_sha256
        from .segment.mobilesam import MobileSamSegmenter

        err = MobileSamSegmenter(enc, dec, verify=False).verify()
        click.echo(f"interfaces OK; fast decoder matches the exported decoder to {err:.1e}")
        click.echo(f"sha256 encoder {file_sha256(enc)}\nsha256 decoder {file_sha256(dec)}")


@click.command("export-gfie-view")
@click.option("--checkpoint", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="GFIE's checkpoint (gfiemodel.pt.tar from GFIE's README; a dict with the GFIENet state_dict).")
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The ONNX file to write (its folder is created if missing).")
@click.option("--opset", type=int, default=17, show_default=True, help="ONNX opset of the export.")
def export_gfie_view(checkpoint: Path, out: Path, opset: int) -> None:
    """Export GFIE's head network (its EGD module) to ONNX: input "image" [N, 3, 224, 224], output
    "gaze" [N, 3] unit, camera frame; `view: onnx` reads it with its default parameters.

    \b
      stages: {view: {backend: onnx, params: {model: OUT}}}
    """
    from ..files import file_sha256
    from .view.gfie_head import export_onnx

    click.echo(f"wrote {export_onnx(checkpoint, out, opset)}\nsha256 {file_sha256(out)}")
