"""The weights of MobileSAM's official decoder ONNX (prompt encoder + mask decoder), read back from
its initializers for the fast decoder (fast_decoder.py), keyed by segment-anything's module paths
(`layers.0.cross_attn_token_to_image.q_proj.w`, `hyper.2.1.b`, ...).

The nodes are found by the scope names torch.onnx.export gives them (`/transformer/layers.0/...`),
which MobileSAM's `scripts/export_onnx_model.py` (and SAM's) produce with `dynamo=False`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from ...errors import ModelFileError

P = 4096      # image tokens (64 x 64)
C = 256       # embedding width
H = 8         # attention heads
D = 16        # per-head width of the cross attentions (256 / 2 / 8)
N_OUT = 5     # output tokens: IoU + 4 mask tokens

_ATTN = ("self_attn", "cross_attn_token_to_image", "cross_attn_image_to_token")
_PROJ = ("q_proj", "k_proj", "v_proj", "out_proj")


class _OnnxParams:
    """Finds the official decoder's parameters by the (stable) scope names of the nodes using them."""

    def __init__(self, path: Path):
        try:
            model = onnx.load(str(path))
        except Exception as e:  # onnx raises several types for bad files
            raise ModelFileError(f"cannot read decoder ONNX {path}: {e}") from e
        self.path = path
        g = model.graph
        self.values: dict[str, np.ndarray] = {t.name: numpy_helper.to_array(t) for t in g.initializer}
        for n in g.node:
            if n.op_type == "Constant" and n.attribute and n.attribute[0].type == onnx.AttributeProto.TENSOR:
                self.values[n.output[0]] = numpy_helper.to_array(n.attribute[0].t)
        for n in g.node:  # the exporter shares equal initializers through Identity nodes
            if n.op_type == "Identity" and n.input[0] in self.values:
                self.values[n.output[0]] = self.values[n.input[0]]
        self.nodes = {n.name: n for n in g.node}

    def node(self, suffix: str) -> onnx.NodeProto:
        hits = [n for name, n in self.nodes.items() if name.endswith(suffix)]
        if len(hits) != 1:
            raise ModelFileError(
                f"decoder ONNX {self.path}: expected one node named '*{suffix}', found {len(hits)}; the fast "
                "decoder reads the weights of MobileSAM's scripts/export_onnx_model.py graph exported with "
                "torch.onnx.export(dynamo=False) (docs/models/segment-everything.md, \"Exporting from a "
                "trained `mobile_sam.pt`\"); use decoder='official' for other graphs")
        return hits[0]

    def param(self, suffix: str, position: int | None = None) -> np.ndarray:
        """The constant input of node '*suffix' (the only constant one, or the one at `position`)."""
        n = self.node(suffix)
        idx = [position] if position is not None else [i for i, x in enumerate(n.input) if x in self.values]
        if len(idx) != 1 or n.input[idx[0]] not in self.values:
            raise ModelFileError(f"decoder ONNX {self.path}: node {n.name} has no single constant input")
        return self.values[n.input[idx[0]]].astype(np.float32)

    def attr(self, suffix: str, name: str):
        n = self.node(suffix)
        for a in n.attribute:
            if a.name == name:
                return onnx.helper.get_attribute_value(a)
        raise ModelFileError(f"decoder ONNX {self.path}: node {n.name} has no attribute {name}")

    def named(self, name: str) -> np.ndarray:
        if name not in self.values:
            raise ModelFileError(f"decoder ONNX {self.path}: initializer {name!r} not found")
        return self.values[name].astype(np.float32)


def decoder_weights(path: str | Path) -> dict[str, np.ndarray]:
    """The official decoder's weights, keyed by module path (linear weights stored (in, out)).

    Read from a decoder ONNX exported by MobileSAM's scripts/export_onnx_model.py (or SAM's); raises
    ModelFileError naming the missing node otherwise.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"decoder ONNX not found: {path}")
    p = _OnnxParams(path)
    w = {**_prompt_encoder(p), **_transformer(p), **_mask_decoder(p)}
    _check_shapes(w, path)
    return w


def _prompt_encoder(p: _OnnxParams) -> dict[str, np.ndarray]:
    """PromptEncoder: the points' random Fourier features, the label embeddings, the no-mask embedding."""
    pe = "model.prompt_encoder."
    w = {"pe_gaussian": p.named(pe + "pe_layer.positional_encoding_gaussian_matrix"),
         "not_a_point": p.named(pe + "not_a_point_embed.weight").reshape(C),
         "no_mask_embed": p.param("/Mul_9").reshape(C)}
    for i in range(4):
        w[f"point_embed.{i}"] = p.named(pe + f"point_embeddings.{i}.weight").reshape(C)
    return w


def _linear(p: _OnnxParams, scope: str, key: str) -> dict[str, np.ndarray]:
    return {key + ".w": p.param(scope + "/MatMul"), key + ".b": p.param(scope + "/Add")}


def _layer_norm(p: _OnnxParams, scope: str, key: str) -> dict[str, np.ndarray]:
    node = scope + "/LayerNormalization"
    return {key + ".g": p.param(node, 1), key + ".b": p.param(node, 2)}


def _transformer(p: _OnnxParams) -> dict[str, np.ndarray]:
    """TwoWayTransformer: both TwoWayAttentionBlocks, the final attention and its LayerNorm."""
    w: dict[str, np.ndarray] = {}
    for layer in ("layers.0", "layers.1"):
        scope = f"/transformer/{layer}"
        for att in _ATTN:
            for proj in _PROJ:
                w |= _linear(p, f"{scope}/{att}/{proj}", f"{layer}.{att}.{proj}")
        for lin in ("lin1", "lin2"):
            w |= _linear(p, f"{scope}/mlp/{lin}", f"{layer}.mlp.{lin}")
        for k in range(1, 5):
            w |= _layer_norm(p, f"{scope}/norm{k}", f"{layer}.norm{k}")
    for proj in _PROJ:
        w |= _linear(p, f"/transformer/final_attn_token_to_image/{proj}", f"final.{proj}")
    w |= _layer_norm(p, "/transformer/norm_final_attn", "norm_final")
    w["ln_eps"] = np.array(p.attr("/transformer/norm_final_attn/LayerNormalization", "epsilon"), np.float32)
    return w


def _mask_decoder(p: _OnnxParams) -> dict[str, np.ndarray]:
    """MaskDecoder's own weights: the IoU and mask tokens, output_upscaling (ConvTranspose,
    LayerNorm2d, GELU, ConvTranspose), the IoU head and the 4 hypernetwork MLPs."""
    up = "/output_upscaling/output_upscaling"
    w = {"output_tokens": p.param("/Expand_1").reshape(N_OUT, C),
         "up0.w": p.param(f"{up}.0/ConvTranspose", 1), "up0.b": p.param(f"{up}.0/ConvTranspose", 2),
         "up1.g": p.param(f"{up}.1/Mul").reshape(-1), "up1.b": p.param(f"{up}.1/Add_1").reshape(-1),
         "up1.eps": p.param(f"{up}.1/Add").reshape(()),
         "up3.w": p.param(f"{up}.3/ConvTranspose", 1), "up3.b": p.param(f"{up}.3/ConvTranspose", 2)}
    heads = [("iou", 0, "/iou_prediction_head")] + [("hyper", i, f"/output_hypernetworks_mlps.{i}") for i in range(4)]
    for name, i, scope in heads:
        for j in range(3):
            gemm = f"{scope}/layers.{j}/Gemm"
            wt = p.param(gemm, 1)
            w[f"{name}.{i}.{j}.w"] = wt.T if p.attr(gemm, "transB") else wt   # stored (in, out)
            w[f"{name}.{i}.{j}.b"] = p.param(gemm, 2)
    return w


def _check_shapes(w: dict[str, np.ndarray], path: Path) -> None:
    expect = {"layers.0.cross_attn_token_to_image.k_proj.w": (C, H * D), "layers.0.self_attn.q_proj.w": (C, C),
              "up0.w": (C, 64, 2, 2), "up3.w": (64, 32, 2, 2), "hyper.0.2.w": (C, 32), "iou.0.2.w": (C, 4),
              "pe_gaussian": (2, C // 2)}
    for k, shape in expect.items():
        if w[k].shape != shape:
            raise ModelFileError(f"decoder ONNX {path}: {k} has shape {w[k].shape}, expected {shape} "
                                 "(the SAM/MobileSAM mask decoder: 256 wide, 8 heads, 4 mask tokens)")
