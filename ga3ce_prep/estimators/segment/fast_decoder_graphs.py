"""What the fast decoder's three ONNX graphs share, and two of them: the image graph (once per image)
and the mask graph (per prompt whose candidates pass the IoU filter). The token graph is in
fast_decoder_tokens.py.

The algebra, and every name used here (`s0`, `s2`, `m0`, `n0`, `wn0`, `beta`, `SC`, ...), is written
out once in docs/models/segment-everything.md, "How the fast decoder is fast".
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto

from ..runtime.onnx_graph import GraphBuilder
from .amg import LOW_RES
from .fast_decoder_weights import C, D, H, P

# The image graph's outputs, in order, and their shapes; the token graph reads all but SC, the mask graph SC
IMAGE_TENSORS: dict[str, list[int]] = {
    "K0T": [H, D, P], "V0": [H, P, D], "Qi0T": [H, D, P], "Sx0T": [H, D, P], "ssq": [P, 1],
    "SK1T": [H, D, P], "SV1": [H, P, D], "SQ1T": [H, D, P], "Sy0T": [H, D, P], "Sy1T": [H, D, P],
    "S2sq": [P, 1], "S2b": [P, 1], "SKfT": [H, D, P], "SVf": [H, P, D], "SC": [P, C]}
TOKEN_IMAGE_INPUTS = tuple(IMAGE_TENSORS)[:-1]
# The token graph's per-prompt outputs that the mask graph gathers (B prompts, T = 5 + N tokens; the
# attentions a0c, a1c transposed, as the token graph holds them)
STATE: dict[str, list] = {"A0cT": ["B", "HT", P], "A1cT": ["B", "HT", P], "r1": ["B", P, 1], "r2": ["B", P, 1],
                          "Vt0": ["B", "T", H * D], "Vt1": ["B", "T", H * D], "hyper_in": ["B", 4, 32]}


def dense_positional_encoding(gauss: np.ndarray) -> np.ndarray:
    """The prompt encoder's `get_dense_pe()` as (4096, 256) float32: random Fourier features of the
    64x64 grid's cell centres in [0, 1], rows in raster order (y, x)."""
    side = int(np.sqrt(P))
    c = (np.arange(side, dtype=np.float64) + 0.5) / side
    xy = np.stack(np.meshgrid(c, c, indexing="xy"), axis=-1).reshape(P, 2)  # (x, y) per row, y-major
    proj = 2.0 * np.pi * ((2.0 * xy - 1.0) @ gauss.astype(np.float64))
    return np.concatenate([np.sin(proj), np.cos(proj)], axis=-1).astype(np.float32)


def _center_rows(m: np.ndarray) -> np.ndarray:
    """m Cc: each row minus its mean over the last axis (LayerNorm's centring, applied on the right)."""
    return m - m.mean(axis=-1, keepdims=True)


@dataclass(frozen=True)
class Derived:
    """The prompt-independent products of the weights that the factored graphs use, float64."""

    pe: np.ndarray  # (P, C) dense positional encoding
    g1: np.ndarray  # (C,) layer 0's norm4 scale
    g2: np.ndarray  # (C,) layer 1's norm4 scale
    wo0: np.ndarray  # (128, C) Wo0 Cc: layer 0's image-to-token out_proj weight, rows centred
    wo1: np.ndarray  # (128, C) Wo1 Cc: the same for layer 1
    wn0: np.ndarray  # (128, C) (wo0 g1) Cc
    beta: np.ndarray  # (C,) (b1 + bo1) Cc: layer 0's norm4 shift plus layer 1's out_proj bias, centred
    wc: np.ndarray  # (C, 256) output_upscaling.0 (2x2 transposed conv) as a matrix, columns (kh, kw, o)
    conv_bias: np.ndarray  # (256,) its bias, columns (kh, kw, o)

    @classmethod
    def from_weights(cls, w: dict[str, np.ndarray]) -> Derived:
        """From `fast_decoder_weights.decoder_weights`."""
        f64 = {k: v.astype(np.float64) for k, v in w.items() if isinstance(v, np.ndarray)}
        g1, b1 = f64["layers.0.norm4.g"], f64["layers.0.norm4.b"]
        wo0 = _center_rows(f64["layers.0.cross_attn_image_to_token.out_proj.w"])
        beta = b1 + f64["layers.1.cross_attn_image_to_token.out_proj.b"]
        return cls(pe=dense_positional_encoding(w["pe_gaussian"]).astype(np.float64), g1=g1,
                   g2=f64["layers.1.norm4.g"], wo0=wo0,
                   wo1=_center_rows(f64["layers.1.cross_attn_image_to_token.out_proj.w"]),
                   wn0=_center_rows(wo0 * g1[None, :]), beta=beta - beta.mean(),
                   wc=f64["up0.w"].transpose(0, 2, 3, 1).reshape(C, 4 * 64), conv_bias=np.tile(f64["up0.b"], 4))


class DecoderGraph(GraphBuilder):
    """A GraphBuilder with the decoder's weights `w`, their derived products `d`, and the head layouts
    of the decoder's attentions (H heads of width D = 16, or 32 in the self attentions)."""

    def __init__(self, name: str, w: dict[str, np.ndarray], d: Derived):
        super().__init__(name)
        self.w, self.d = w, d

    def split_heads(self, x: str, perm: list[int], width: int = D) -> str:
        """(B, T, H*width) -> (B, T, H, width) -> transpose(perm)."""
        return self.transpose(self.reshape(x, [0, 0, H, width]), perm)

    def merge_heads(self, x: str, width: int = D) -> str:
        """(B, H, T, width) -> (B, T, H*width)."""
        return self.reshape(self.transpose(x, [0, 2, 1, 3]), [0, 0, H * width])

    def blockdiag(self, vth: str, mat: np.ndarray) -> str:
        """blockdiag(vt) @ mat: per-head token values vth (B, H, T, D) times each head's D rows of
        mat (H*D, k) -> (B, H*T, k)."""
        return self.reshape(self.mm(vth, self.const(mat.reshape(H, D, -1))), [0, -1, mat.shape[-1]])


def build_image_graph(w: dict[str, np.ndarray], d: Derived) -> onnx.ModelProto:
    """image_embeddings (1, 256, 64, 64) -> IMAGE_TENSORS: every prompt-independent product of the
    image stream that the token and mask graphs need."""
    g = DecoderGraph("mobilesam_fast_image", w, d)
    emb = g.input("image_embeddings", [1, C, 64, 64])
    src = g.add(g.transpose(g.reshape(emb, [C, P]), [1, 0]), g.const(w["no_mask_embed"]))   # (P, C)
    src_pe = g.add(src, g.const(d.pe))
    T2I0, I2T0 = "layers.0.cross_attn_token_to_image", "layers.0.cross_attn_image_to_token"
    T2I1, I2T1 = "layers.1.cross_attn_token_to_image", "layers.1.cross_attn_image_to_token"

    def heads_dp(x):  # (P, 128) -> (H, D, P)
        return g.transpose(g.reshape(x, [P, H, D]), [1, 2, 0])

    def heads_pd(x):  # (P, 128) -> (H, P, D)
        return g.transpose(g.reshape(x, [P, H, D]), [1, 0, 2])

    out = {}
    # Layer 0: keys and values of the token-to-image attention, queries of the image-to-token one
    out["K0T"] = heads_dp(g.linear(src_pe, w[T2I0 + ".k_proj.w"], w[T2I0 + ".k_proj.b"]))
    out["V0"] = heads_pd(g.linear(src, w[T2I0 + ".v_proj.w"], w[T2I0 + ".v_proj.b"]))
    out["Qi0T"] = heads_dp(g.linear(src_pe, w[I2T0 + ".q_proj.w"], w[I2T0 + ".q_proj.b"]))
    # keys1's image part s0 and its LayerNorm terms
    s = g.add(src, g.const(w[I2T0 + ".out_proj.b"]))
    s0 = g.sub(s, g.op("ReduceMean", s, axes=[-1], keepdims=1))                        # (P, C)
    out["Sx0T"] = heads_dp(g.mm(s0, g.const(d.wo0.T)))
    out["ssq"] = g.reduce_sum(g.mul(s0, s0), [-1])                                      # (P, 1)
    # Layer 1: its projections of s0 g1
    s0g1 = g.mul(s0, g.const(d.g1))
    out["SK1T"] = heads_dp(g.mm(s0g1, g.const(w[T2I1 + ".k_proj.w"])))
    out["SV1"] = heads_pd(g.mm(s0g1, g.const(w[T2I1 + ".v_proj.w"])))
    out["SQ1T"] = heads_dp(g.mm(s0g1, g.const(w[I2T1 + ".q_proj.w"])))
    # keys2's image part s2 and its LayerNorm terms
    s2 = g.sub(s0g1, g.op("ReduceMean", s0g1, axes=[-1], keepdims=1))                  # (P, C)
    out["Sy0T"] = heads_dp(g.mm(s2, g.const(d.wn0.T)))
    out["Sy1T"] = heads_dp(g.mm(s2, g.const(d.wo1.T)))
    out["S2sq"] = g.reduce_sum(g.mul(s2, s2), [-1])
    out["S2b"] = g.mm(s2, g.const(d.beta.reshape(C, 1)))
    # The final attention's and the output upscaling's projections of s2 g2
    s2g2 = g.mul(s2, g.const(d.g2))
    out["SKfT"] = heads_dp(g.mm(s2g2, g.const(w["final.k_proj.w"])))
    out["SVf"] = heads_pd(g.mm(s2g2, g.const(w["final.v_proj.w"])))
    out["SC"] = g.mm(s2g2, g.const(d.wc))
    for name in IMAGE_TENSORS:
        g.output(out[name], name)
    return g.model()


def build_mask_graph(w: dict[str, np.ndarray], d: Derived, pixel_chunks: int = 1) -> onnx.ModelProto:
    """SC + the token graph's STATE + prompt indices (K,) -> low_res_raw (K, 4096*16, 4) mask logits
    (pixel order: raw_to_image).

    pixel_chunks: the output upscaling and the hypernetwork product run on this many slices of the
      4096 embedding pixels one after the other (every step of them is per pixel), so that each
      slice's intermediates stay in the core's cache (on CPU; measured in
      docs/studies/2026-11-29-segment-everything-speed.md, "What was tried"); 1 = the whole image in each node (GPU)."""
    if P % pixel_chunks:
        raise ValueError(f"pixel_chunks must divide {P}, got {pixel_chunks}")
    g = DecoderGraph("mobilesam_fast_masks", w, d)
    sc = g.input("SC", IMAGE_TENSORS["SC"])
    idx = g.input("index", ["K"], TensorProto.INT64)
    st = {k: g.op("Gather", g.input(k, shape), idx, axis=0) for k, shape in STATE.items()}
    vt0h = g.split_heads(st["Vt0"], [0, 2, 1, 3])                                      # (K, H, T, D)
    vt1h = g.split_heads(st["Vt1"], [0, 2, 1, 3])
    # keys2 @ wc + conv_bias = r2 r1 SC + [r2 r1 a0c | r2 a1c | r2 | 1] @ [rc0; rc1; c_beta; c_const]:
    # one product (its left side built transposed from A0cT, A1cT, and read through a fused transpose),
    # 2 passes over the (K, P, 256) result
    g2wc = d.g2[:, None] * d.wc
    rc0 = g.blockdiag(vt0h, d.wn0 @ g2wc)                                              # (K, HT, 256)
    rc1 = g.blockdiag(vt1h, d.wo1 @ g2wc)
    c_beta = d.beta @ g2wc                                                              # (256,)
    c_const = w["layers.1.norm4.b"] @ d.wc + d.conv_bias
    r2, r21 = st["r2"], g.mul(st["r2"], st["r1"])                                      # (K, P, 1)
    r2T, r21T = g.reshape(r2, [0, 1, P]), g.reshape(r21, [0, 1, P])                    # (K, 1, P), free
    ones = g.add(g.mul(r2T, g.const(0.0)), g.const(1.0))
    leftT = g.concat([g.mul(st["A0cT"], r21T), g.mul(st["A1cT"], r2T), r2T, ones], axis=1)   # (K, 2HT + 2, P)
    k_dim = g.slice(g.op("Shape", rc0), [0], [1], [0])
    right = g.concat([rc0, rc1, g.op("Expand", g.const(np.stack([c_beta, c_const])[None]),
                                     g.concat([k_dim, g.const([2, C], dtype=np.int64)], axis=0))], axis=1)
    # The second transposed conv's matrix with its bias as a 65th input row against a ones column: a
    # concat of 1/64 of y costs less than an Add over the 2x larger output
    # (docs/studies/2026-11-29-segment-everything-speed.md, "What was tried")
    w2 = w["up3.w"].transpose(0, 2, 3, 1).reshape(64, 4 * 32)                         # cols (kh2, kw2, o2)
    w2b = g.const(np.concatenate([w2, np.tile(w["up3.b"], 4)[None]], axis=0))          # (65, 128)
    # The hypernetwork product with the mask tokens' MLP outputs, per output pixel (kh2, kw2) of the
    # second conv: z @ blockdiag(hyper_in^T x 4), an (128, 16) right side (a 4-column product wastes
    # most of each vector)
    hT = g.reshape(g.transpose(st["hyper_in"], [0, 2, 1]), [0, 1, 32, 1, 4])         # (K, 1, 32, 1, 4)
    hblock = g.reshape(g.mul(hT, g.const(np.eye(4).reshape(4, 1, 4, 1))), [0, 128, 16])   # (K, 128, 16)
    n = P // pixel_chunks
    ones_col = g.op("Expand", g.const(np.ones((1, 1, 1, 1))),
                    g.concat([k_dim, g.const([n, 4, 1], dtype=np.int64)], axis=0))
    outs = []
    for p0 in range(0, P, n):   # the embedding pixels p0 .. p0 + n - 1
        lt, sc_p, r21_p = (g.slice(leftT, [p0], [p0 + n], [2]), g.slice(sc, [p0], [p0 + n], [0]),
                           g.slice(r21, [p0], [p0 + n], [1])) if pixel_chunks > 1 else (leftT, sc, r21)
        y = g.add(g.mul(sc_p, r21_p), g.mm(g.transpose(lt, [0, 2, 1]), right))       # (K, n, 256)
        # The rest of output_upscaling: LayerNorm2d, GELU, the second transposed conv, GELU
        y = g.reshape(y, [0, n, 4, 64])
        y = g.gelu(g.layer_norm(y, w["up1.g"], w["up1.b"], float(w["up1.eps"])))
        z = g.reshape(g.gelu(g.mm(g.concat([y, ones_col], axis=-1), w2b)), [0, n * 4, 128])    # (K, 4n, 128)
        outs.append(g.mm(z, hblock))                                                     # (K, 4n, 16)
    out = outs[0] if len(outs) == 1 else g.concat(outs, axis=1)
    g.output(g.reshape(out, [0, P * 16, 4]), "low_res_raw")                           # (K, P*16, 4)
    return g.model()


def raw_to_image(raw: np.ndarray) -> np.ndarray:
    """The mask graph's (..., 4096*16) logits in (y, x, kh, kw, kh2, kw2) order -> (..., 256, 256):
    pixel row 4y + 2kh + kh2, column 4x + 2kw + kw2 (the two stride-2 transposed convolutions)."""
    lead = raw.shape[:-1]
    r = raw.reshape(-1, 64, 64, 2, 2, 2, 2).transpose(0, 1, 3, 5, 2, 4, 6)
    return r.reshape(*lead, LOW_RES, LOW_RES)
