"""MobileSAM's mask decoder restructured for segment-everything, run by ONNX Runtime.

The official decoder export (MobileSAM `scripts/export_onnx_model.py`) costs about 1.8 GMAC per
prompt: its transformer multiplies the 4096x256 image embedding by 256x128 projections again and
again, and it upsamples 4 masks to full resolution for every prompt. This module rebuilds the same
function from the same weights (read from the official decoder ONNX's initializers) as three ONNX
graphs:

- **image graph**, once per image: every projection of the image embedding that does not depend on
  the prompt (layer 0's token-to-image keys/values and image-to-token queries, and the projections
  of the layer-norm-ed residual stream used by the later layers).
- **token graph**, batched over prompts: the 5 + N prompt tokens through both two-way layers and the
  final attention, giving `iou_predictions` (B, 4) without ever forming a 4096x256 tensor per
  prompt. After layer 0 the image stream is `keys1 = LN(src + A0 @ M0)`, where A0 (4096 x 8*T) is
  the image-to-token attention and M0 (8*T x 256) = blockdiag(V_tokens) @ W_out is tiny; layer 1
  adds `A1 @ M1` and another LayerNorm. Every later product with the image stream is re-associated
  through these factors (prompt-independent parts precomputed by the image graph, the LayerNorm
  statistics from Gram matrices of the factors), so the per-prompt work is products with
  4096 x 56 matrices instead of 4096 x 256 x 128 projections (exact up to float rounding).
- **mask graph**, only for the prompts whose candidates pass the IoU filter: the image stream after
  layer 1 through the output upscaling (transposed convolutions, LayerNorm2d, GELU) and the
  hypernetwork product, giving the 256x256 low-resolution mask logits (K, 4, 256, 256).

Tokens are numbered as in the official decoder: 0 = IoU token, 1..4 = mask tokens (1..3 are the
"multimask" outputs), then the prompt points. Mask inputs (`has_mask_input` = 1) are not supported:
segment-everything never uses them.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import onnx
from onnx import TensorProto

from .amg import LOW_RES
from .fast_decoder_weights import C, D, H, N_OUT, P, decoder_weights
from .onnx_graph import GraphBuilder


def dense_positional_encoding(gauss: np.ndarray) -> np.ndarray:
    """The prompt encoder's `get_dense_pe()` as (4096, 256) float32: random Fourier features of the
    64x64 grid's cell centres in [0, 1], rows in raster order (y, x)."""
    side = int(np.sqrt(P))
    c = (np.arange(side, dtype=np.float64) + 0.5) / side
    xy = np.stack(np.meshgrid(c, c, indexing="xy"), axis=-1).reshape(P, 2)  # (x, y) per row, y-major
    proj = 2.0 * np.pi * ((2.0 * xy - 1.0) @ gauss.astype(np.float64))
    return np.concatenate([np.sin(proj), np.cos(proj)], axis=-1).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Graphs
# ---------------------------------------------------------------------------------------------
def _center_rows(m: np.ndarray) -> np.ndarray:
    """Subtract each row's mean over the last axis (the LayerNorm centring C applied on the right)."""
    return m - m.mean(axis=-1, keepdims=True)


def _heads_rows(w: np.ndarray) -> np.ndarray:
    """(H*D, k) weight -> (H, D, k): per-head row blocks."""
    return w.reshape(H, D, -1)


@dataclass
class _Derived:
    """Prompt-independent matrices of the factored form, float64 then cast (see module docstring)."""

    w: dict[str, np.ndarray]

    def __post_init__(self):
        w = {k: v.astype(np.float64) if isinstance(v, np.ndarray) else v for k, v in self.w.items()}
        self.pe = dense_positional_encoding(self.w["pe_gaussian"]).astype(np.float64)
        g1, b1 = w["layers.0.norm4.g"], w["layers.0.norm4.b"]
        g2, b2 = w["layers.1.norm4.g"], w["layers.1.norm4.b"]
        self.g1, self.g2 = g1, g2
        self.wo0 = _center_rows(w["layers.0.cross_attn_image_to_token.out_proj.w"])   # W~o0 (128, C)
        self.wo1 = _center_rows(w["layers.1.cross_attn_image_to_token.out_proj.w"])   # W~o1
        self.wn0 = _center_rows(self.wo0 * g1[None, :])                              # W~o0 G1 Cc
        beta = b1 + w["layers.1.cross_attn_image_to_token.out_proj.b"]
        self.beta_c = beta - beta.mean()                                             # beta'
        wc = w["up0.w"].transpose(0, 2, 3, 1).reshape(C, 4 * 64)                     # cols (kh, kw, o)
        self.wc = wc
        self.conv_bias = np.tile(w["up0.b"], 4)                                      # (256,) in (kh, kw, o)


def _split_heads(g: GraphBuilder, x: str, perm: list[int]) -> str:
    """(B, T, 128) -> (B, T, H, D) -> transpose(perm)."""
    return g.transpose(g.reshape(x, [0, 0, H, D]), perm)


def _merge_heads(g: GraphBuilder, x: str) -> str:
    """(B, H, T, D) -> (B, T, 128)."""
    return g.reshape(g.transpose(x, [0, 2, 1, 3]), [0, 0, H * D])


def build_image_graph(w: dict[str, np.ndarray]) -> onnx.ModelProto:
    """image_embeddings (1, 256, 64, 64) -> the prompt-independent tensors of the token and mask graphs."""
    d = _Derived(w)
    g = GraphBuilder("mobilesam_fast_image")
    emb = g.input("image_embeddings", [1, C, 64, 64])
    src = g.add(g.transpose(g.reshape(emb, [C, P]), [1, 0]), g.const(w["no_mask_embed"]))
    pe = g.const(d.pe)
    src_pe = g.add(src, pe)
    L0 = "layers.0.cross_attn_token_to_image"
    I0 = "layers.0.cross_attn_image_to_token"

    def heads_dp(x):  # (P, 128) -> (H, D, P)
        return g.transpose(g.reshape(x, [P, H, D]), [1, 2, 0])

    def heads_pd(x):  # (P, 128) -> (H, P, D)
        return g.transpose(g.reshape(x, [P, H, D]), [1, 0, 2])

    outs = {}
    outs["K0T"] = heads_dp(g.linear(src_pe, w[L0 + ".k_proj.w"], w[L0 + ".k_proj.b"]))
    outs["V0"] = heads_pd(g.linear(src, w[L0 + ".v_proj.w"], w[L0 + ".v_proj.b"]))
    outs["Qi0T"] = heads_dp(g.linear(src_pe, w[I0 + ".q_proj.w"], w[I0 + ".q_proj.b"]))
    s = g.add(src, g.const(w[I0 + ".out_proj.b"]))
    s_c = g.sub(s, g.op("ReduceMean", s, axes=[-1], keepdims=1))                   # s~ (P, C)
    outs["Sx0T"] = heads_dp(g.mm(s_c, g.const(d.wo0.T)))
    outs["ssq"] = g.reduce_sum(g.mul(s_c, s_c), [-1])                                  # (P, 1)
    sg = g.mul(s_c, g.const(d.g1))
    L1 = "layers.1.cross_attn_token_to_image"
    I1 = "layers.1.cross_attn_image_to_token"
    outs["SK1T"] = heads_dp(g.mm(sg, g.const(w[L1 + ".k_proj.w"])))
    outs["SV1"] = heads_pd(g.mm(sg, g.const(w[L1 + ".v_proj.w"])))
    outs["SQ1T"] = heads_dp(g.mm(sg, g.const(w[I1 + ".q_proj.w"])))
    s2 = g.sub(sg, g.op("ReduceMean", sg, axes=[-1], keepdims=1))                     # S2 (P, C)
    outs["Sy0T"] = heads_dp(g.mm(s2, g.const(d.wn0.T)))
    outs["Sy1T"] = heads_dp(g.mm(s2, g.const(d.wo1.T)))
    outs["S2sq"] = g.reduce_sum(g.mul(s2, s2), [-1])
    outs["S2b"] = g.mm(s2, g.const(d.beta_c.reshape(C, 1)))
    s2g = g.mul(s2, g.const(d.g2))
    outs["SKfT"] = heads_dp(g.mm(s2g, g.const(w["final.k_proj.w"])))
    outs["SVf"] = heads_pd(g.mm(s2g, g.const(w["final.v_proj.w"])))
    outs["SC"] = g.mm(s2g, g.const(d.wc))
    for name, value in outs.items():
        g.output(value, name)
    return g.model()


IMAGE_OUTPUTS = ("K0T", "V0", "Qi0T", "Sx0T", "ssq", "SK1T", "SV1", "SQ1T", "Sy0T", "Sy1T", "S2sq", "S2b",
                 "SKfT", "SVf", "SC")
TOKEN_IMAGE_INPUTS = IMAGE_OUTPUTS[:-1]          # all but SC
STATE = ("A0c", "A1c", "r1", "r2", "Vt0", "Vt1", "hyper_in")


def build_token_graph(w: dict[str, np.ndarray]) -> onnx.ModelProto:
    """Image tensors + point prompts (B, N, 2) (B, N) -> iou_predictions (B, 4) and the per-prompt state
    of the mask graph."""
    d = _Derived(w)
    eps = float(w["ln_eps"])
    g = GraphBuilder("mobilesam_fast_tokens")
    img = {}
    shapes = {"ssq": [P, 1], "S2sq": [P, 1], "S2b": [P, 1]}
    for name in TOKEN_IMAGE_INPUTS:
        shp = shapes.get(name, [H, D, P] if name.endswith("T") else [H, P, D])
        img[name] = g.input(name, shp)
    coords = g.input("point_coords", ["B", "N", 2])
    labels = g.input("point_labels", ["B", "N"])

    # ---- prompt encoder (SamOnnxModel._embed_points) -----------------------------------------
    c = g.div(g.add(coords, g.const(0.5)), g.const(1024.0))
    c = g.sub(g.mul(c, g.const(2.0)), g.const(1.0))
    proj = g.mul(g.mm(c, g.const(w["pe_gaussian"])), g.const(2.0 * np.pi))
    pts = g.concat([g.op("Sin", proj), g.op("Cos", proj)], axis=-1)             # (B, N, C)
    lab = g.op("Unsqueeze", labels, g.const([-1], dtype=np.int64))

    def is_label(v):
        return g.op("Cast", g.op("Equal", lab, g.const(float(v))), to=TensorProto.FLOAT)

    pad = is_label(-1)
    sparse = g.add(g.mul(pts, g.sub(g.const(1.0), pad)), g.mul(pad, g.const(w["not_a_point"])))
    for i in range(4):
        sparse = g.add(sparse, g.mul(is_label(i), g.const(w[f"point_embed.{i}"])))
    shape_c = g.op("Shape", coords)
    b_dim = g.slice(shape_c, [0], [1], [0])
    out_tok = g.op("Expand", g.const(w["output_tokens"][None]),
                   g.concat([b_dim, g.const([N_OUT, C], dtype=np.int64)], axis=0))
    tokens = g.concat([out_tok, sparse], axis=1)                                   # (B, T, C)
    t_dim = g.slice(g.op("Shape", tokens), [1], [2], [0])
    ht = g.mul(t_dim, g.const([H], dtype=np.int64))

    def dyn(*parts):
        return g.concat([p if isinstance(p, str) else g.const(p, dtype=np.int64) for p in parts], axis=0)

    def rowdot(a, b):   # sum over last axis, keepdims -> (B, P, 1)
        return g.reduce_sum(g.mul(a, b), [-1])

    def headdot(a, b):  # (B, H, T, P) x (B, H, T, P) summed over heads and tokens -> (B, P, 1)
        return g.reshape(g.reduce_sum(g.mul(a, b), [1, 2]), [0, P, 1])

    def softmax_tokens(x):  # (B, H, T, P) logits -> softmax over T (axis 2), vectorised along P
        e = g.op("Exp", g.sub(x, g.op("ReduceMax", x, axes=[2], keepdims=1)))
        return g.div(e, g.reduce_sum(e, [2]))

    def cat_of(a):      # (B, H, T, P) -> (B, P, H*T)
        return g.reshape(g.transpose(a, [0, 3, 1, 2]), [0, P, -1])

    def catT_of(a):     # (B, H, T, P) -> (B, H*T, P), free
        return g.reshape(a, [0, -1, P])

    def ln(x, key):
        return g.layer_norm(x, w[key + ".g"], w[key + ".b"], eps)

    def self_attn(q_in, v_in, key):
        q = _split_heads_n(g, g.linear(q_in, w[key + ".q_proj.w"] / np.sqrt(32.0), w[key + ".q_proj.b"] / np.sqrt(32.0)), [0, 2, 1, 3])
        k = _split_heads_n(g, g.linear(q_in, w[key + ".k_proj.w"], w[key + ".k_proj.b"]), [0, 2, 3, 1])
        v = _split_heads_n(g, g.linear(v_in, w[key + ".v_proj.w"], w[key + ".v_proj.b"]), [0, 2, 1, 3])
        o = g.mm(g.softmax(g.mm(q, k)), v)
        o = g.reshape(g.transpose(o, [0, 2, 1, 3]), [0, 0, C])
        return g.linear(o, w[key + ".out_proj.w"], w[key + ".out_proj.b"])

    def mlp(x, key):
        h = g.relu(g.linear(x, w[key + ".lin1.w"], w[key + ".lin1.b"]))
        return g.linear(h, w[key + ".lin2.w"], w[key + ".lin2.b"])

    def q_heads(x, key, scale=0.25):  # (B, T, C) -> (B, H, T, D), pre-scaled by 1/sqrt(D)
        return _split_heads(g, g.linear(x, w[key + ".w"] * scale, w[key + ".b"] * scale), [0, 2, 1, 3])

    def per_head_right(vt_h, mat):  # (B, H, T, D) @ (H, D, k) -> (B, H*T, k)
        return g.reshape(g.mm(vt_h, g.const(mat)), [0, -1, mat.shape[-1]])

    def r_row(r):   # (B, P, 1) -> (B, 1, 1, P)
        return g.reshape(r, [0, 1, 1, P])

    # ---- layer 0 -----------------------------------------------------------------------------
    queries = ln(self_attn(tokens, tokens, "layers.0.self_attn"), "layers.0.norm1")
    L0 = "layers.0.cross_attn_token_to_image"
    q = q_heads(g.add(queries, tokens), L0 + ".q_proj")
    p0 = g.softmax(g.mm(q, img["K0T"]))                                             # (B, H, T, P)
    o = _merge_heads(g, g.mm(p0, img["V0"]))
    queries = ln(g.add(queries, g.linear(o, w[L0 + ".out_proj.w"], w[L0 + ".out_proj.b"])), "layers.0.norm2")
    queries = ln(g.add(queries, mlp(queries, "layers.0.mlp")), "layers.0.norm3")
    I0 = "layers.0.cross_attn_image_to_token"
    kt0 = q_heads(g.add(queries, tokens), I0 + ".k_proj")                           # (B, H, T, D) / 4
    vt0 = g.linear(queries, w[I0 + ".v_proj.w"], w[I0 + ".v_proj.b"])                # (B, T, 128)
    a0 = softmax_tokens(g.mm(kt0, img["Qi0T"]))                                     # (B, H, T, P)
    a0c, a0cT = cat_of(a0), catT_of(a0)
    vt0h = _split_heads(g, vt0, [0, 2, 1, 3])                                       # (B, H, T, D)
    m0 = per_head_right(vt0h, _heads_rows(d.wo0))                                   # M~0 (B, HT, C)
    g0 = g.mm(m0, g.transpose(m0, [0, 2, 1]))
    dx0 = g.mm(vt0h, img["Sx0T"])                                                   # (s~ M~0^T)^T (B, H, T, P)
    var1 = g.add(g.add(img["ssq"], g.mul(g.const(2.0), headdot(a0, dx0))), rowdot(a0c, g.mm(a0c, g0)))
    r1 = g.op("Reciprocal", g.op("Sqrt", g.add(g.div(var1, g.const(float(C))), g.const(eps))))  # (B, P, 1)

    # ---- layer 1 -----------------------------------------------------------------------------
    queries = ln(g.add(queries, self_attn(g.add(queries, tokens), queries, "layers.1.self_attn")), "layers.1.norm1")
    L1 = "layers.1.cross_attn_token_to_image"
    q1 = q_heads(g.add(queries, tokens), L1 + ".q_proj")                            # (B, H, T, D)
    g1w = d.g1[:, None]
    rk1 = _split_heads(g, g.mm(m0, g.const(g1w * w[L1 + ".k_proj.w"])), [0, 2, 3, 1])  # (B, H, D, HT)
    y = g.reshape(g.mm(q1, rk1), dyn([0, -1], ht))                                  # (B, HT', HT)
    low = g.reshape(g.mm(y, a0cT), [0, H, -1, P])                                   # (B, H, T, P)
    ck1 = (d.pe + d.w["layers.0.norm4.b"][None]) @ w[L1 + ".k_proj.w"] + w[L1 + ".k_proj.b"]
    logits = g.add(g.mul(r_row(r1), g.add(g.mm(q1, img["SK1T"]), low)),
                   g.mm(q1, g.const(ck1.reshape(P, H, D).transpose(1, 2, 0))))
    p1 = g.softmax(logits)
    pr = g.mul(p1, r_row(r1))
    rv1 = _split_heads(g, g.mm(m0, g.const(g1w * w[L1 + ".v_proj.w"])), [0, 2, 1, 3])  # (B, H, HT, D)
    prA = g.reshape(g.mm(g.reshape(pr, [0, -1, P]), a0c), dyn([0, H, -1], ht))      # (B, H, T, HT)
    cv1 = d.w["layers.0.norm4.b"] @ w[L1 + ".v_proj.w"] + w[L1 + ".v_proj.b"]
    o = g.add(g.add(g.mm(pr, img["SV1"]), g.mm(prA, rv1)), g.const(cv1.reshape(H, 1, D)))
    queries = ln(g.add(queries, g.linear(_merge_heads(g, o), w[L1 + ".out_proj.w"], w[L1 + ".out_proj.b"])),
                 "layers.1.norm2")
    queries = ln(g.add(queries, mlp(queries, "layers.1.mlp")), "layers.1.norm3")
    I1 = "layers.1.cross_attn_image_to_token"
    kt1 = q_heads(g.add(queries, tokens), I1 + ".k_proj")                           # (B, H, T, D) / 4
    vt1 = g.linear(queries, w[I1 + ".v_proj.w"], w[I1 + ".v_proj.b"])
    rq1 = _split_heads(g, g.mm(m0, g.const(g1w * w[I1 + ".q_proj.w"])), [0, 2, 3, 1])  # (B, H, D, HT)
    zt = g.reshape(g.mm(kt1, rq1), dyn([0, -1], ht))                                # (B, H*T, HT)
    az = g.reshape(g.mm(zt, a0cT), [0, H, -1, P])                                   # (B, H, T, P)
    cq1 = (d.pe + d.w["layers.0.norm4.b"][None]) @ w[I1 + ".q_proj.w"] + w[I1 + ".q_proj.b"]
    l1 = g.add(g.mul(r_row(r1), g.add(g.mm(kt1, img["SQ1T"]), az)),
               g.mm(kt1, g.const(cq1.reshape(P, H, D).transpose(1, 2, 0))))
    a1 = softmax_tokens(l1)                                                         # (B, H, T, P)
    a1c, a1cT = cat_of(a1), catT_of(a1)

    # ---- LayerNorm statistics of the image stream after layer 1 -------------------------------
    vt1h = _split_heads(g, vt1, [0, 2, 1, 3])
    n0 = per_head_right(vt0h, _heads_rows(d.wn0))                                   # N0 (B, HT, C)
    m1 = per_head_right(vt1h, _heads_rows(d.wo1))                                   # M~1 (B, HT, C)
    n0T, m1T = g.transpose(n0, [0, 2, 1]), g.transpose(m1, [0, 2, 1])
    d0 = g.mm(vt0h, img["Sy0T"])                                                    # (B, H, T, P)
    d1 = g.mm(vt1h, img["Sy1T"])
    beta = g.const(d.beta_c.reshape(C, 1))
    a0g = g.mm(a0c, g.concat([g.mm(n0, n0T), g.mm(n0, m1T), g.mm(n0, beta)], axis=-1))   # (B, P, 2HT + 1)
    a0g00 = g.op("Slice", a0g, g.const([0], dtype=np.int64), ht, g.const([2], dtype=np.int64))
    a0g01 = g.op("Slice", a0g, ht, g.mul(ht, g.const([2], dtype=np.int64)), g.const([2], dtype=np.int64))
    a0n0 = g.slice(a0g, [-1], [2 ** 62], [2])
    t00 = g.add(g.add(img["S2sq"], g.mul(g.const(2.0), headdot(a0, d0))), rowdot(a0c, a0g00))
    t11 = g.add(rowdot(a1c, g.mm(a1c, g.mm(m1, m1T))), g.const(float(d.beta_c @ d.beta_c)))
    t01 = g.add(g.add(headdot(a1, d1), rowdot(a1c, a0g01)), g.add(img["S2b"], a0n0))
    t1 = g.mm(a1c, g.mm(m1, beta))
    var2 = g.add(g.add(g.mul(g.mul(r1, r1), t00), t11), g.mul(g.const(2.0), g.add(g.mul(r1, t01), t1)))
    r2 = g.op("Reciprocal", g.op("Sqrt", g.add(g.div(var2, g.const(float(C))), g.const(eps))))

    # ---- final token-to-image attention (tokens 0..4 only) -----------------------------------
    F = "final"
    qtok = g.slice(g.add(queries, tokens), [0], [N_OUT], [1])
    qf = q_heads(qtok, F + ".q_proj")                                               # (B, H, 5, D)
    g2wk = d.g2[:, None] * w[F + ".k_proj.w"]
    g2wv = d.g2[:, None] * w[F + ".v_proj.w"]
    rkf0 = _split_heads(g, g.mm(n0, g.const(g2wk)), [0, 2, 3, 1])                  # (B, H, D, HT)
    rkf1 = _split_heads(g, g.mm(m1, g.const(g2wk)), [0, 2, 3, 1])
    lo0 = g.reshape(g.mm(g.reshape(g.mm(qf, rkf0), dyn([0, -1], ht)), a0cT), [0, H, N_OUT, P])
    lo1 = g.reshape(g.mm(g.reshape(g.mm(qf, rkf1), dyn([0, -1], ht)), a1cT), [0, H, N_OUT, P])
    ckf = (d.beta_c @ g2wk).reshape(H, D, 1)
    cKf = (d.pe + d.w["layers.1.norm4.b"][None]) @ w[F + ".k_proj.w"] + w[F + ".k_proj.b"]
    r1row, r2row = r_row(r1), r_row(r2)
    inner = g.add(g.add(g.mul(r1row, g.add(g.mm(qf, img["SKfT"]), lo0)), lo1), g.mm(qf, g.const(ckf)))
    lf = g.add(g.mul(r2row, inner), g.mm(qf, g.const(cKf.reshape(P, H, D).transpose(1, 2, 0))))
    pf = g.softmax(lf)
    pr2 = g.mul(pf, r2row)
    pr21 = g.mul(pr2, r1row)
    rvf0 = _split_heads(g, g.mm(n0, g.const(g2wv)), [0, 2, 1, 3])                  # (B, H, HT, D)
    rvf1 = _split_heads(g, g.mm(m1, g.const(g2wv)), [0, 2, 1, 3])
    pa0 = g.reshape(g.mm(g.reshape(pr21, [0, -1, P]), a0c), dyn([0, H, N_OUT], ht))
    pa1 = g.reshape(g.mm(g.reshape(pr2, [0, -1, P]), a1c), dyn([0, H, N_OUT], ht))
    cvf = (d.beta_c @ g2wv).reshape(H, 1, D)
    cVf = (d.w["layers.1.norm4.b"] @ w[F + ".v_proj.w"] + w[F + ".v_proj.b"]).reshape(H, 1, D)
    of = g.add(g.add(g.mm(pr21, img["SVf"]), g.mm(pa0, rvf0)), g.mm(pa1, rvf1))
    of = g.add(g.add(of, g.mul(g.reduce_sum(pr2, [-1]), g.const(cvf))), g.const(cVf))
    qout = g.slice(queries, [0], [N_OUT], [1])
    qout = g.layer_norm(g.add(qout, g.linear(_merge_heads(g, of), w[F + ".out_proj.w"], w[F + ".out_proj.b"])),
                        w["norm_final.g"], w["norm_final.b"], eps)

    def head_mlp(x, name, i):
        for j in range(3):
            x = g.linear(x, w[f"{name}.{i}.{j}.w"], w[f"{name}.{i}.{j}.b"])
            if j < 2:
                x = g.relu(x)
        return x

    iou = head_mlp(g.reshape(g.slice(qout, [0], [1], [1]), [0, C]), "iou", 0)
    hyper = [g.reshape(head_mlp(g.reshape(g.slice(qout, [1 + i], [2 + i], [1]), [0, C]), "hyper", i), [0, 1, 32])
             for i in range(4)]
    g.output(iou, "iou_predictions")
    for name, value in zip(STATE, (a0c, a1c, r1, r2, vt0, vt1, g.concat(hyper, axis=1))):
        g.output(value, name)
    return g.model()


def _split_heads_n(g: GraphBuilder, x: str, perm: list[int], heads: int = H, width: int = 32) -> str:
    return g.transpose(g.reshape(x, [0, 0, heads, width]), perm)


def build_mask_graph(w: dict[str, np.ndarray]) -> onnx.ModelProto:
    """SC + token-graph state + prompt indices (K,) -> low_res_masks (K, 4, 256, 256) logits."""
    d = _Derived(w)
    g = GraphBuilder("mobilesam_fast_masks")
    sc = g.input("SC", [P, C])
    idx = g.input("index", ["K"], TensorProto.INT64)
    shapes = {"A0c": ["B", P, "HT"], "A1c": ["B", P, "HT"], "r1": ["B", P, 1], "r2": ["B", P, 1],
              "Vt0": ["B", "T", H * D], "Vt1": ["B", "T", H * D], "hyper_in": ["B", 4, 32]}
    st = {k: g.op("Gather", g.input(k, shp), idx, axis=0) for k, shp in shapes.items()}
    vt0h = _split_heads(g, st["Vt0"], [0, 2, 1, 3])
    vt1h = _split_heads(g, st["Vt1"], [0, 2, 1, 3])
    rc0 = g.reshape(g.mm(vt0h, g.const(_heads_rows(d.wn0 @ (d.g2[:, None] * d.wc)))), [0, -1, C])
    rc1 = g.reshape(g.mm(vt1h, g.const(_heads_rows(d.wo1 @ (d.g2[:, None] * d.wc)))), [0, -1, C])
    cc = d.beta_c @ (d.g2[:, None] * d.wc)
    cb = d.w["layers.1.norm4.b"] @ d.wc + d.conv_bias
    # keys2 @ Wc + b = r2 r1 SC + [r2 r1 A0c | r2 A1c | r2 | 1] @ [RC0; RC1; cc; cb]: one product, 2 passes
    r2, r21 = st["r2"], g.mul(st["r2"], st["r1"])
    ones = g.add(g.mul(r2, g.const(0.0)), g.const(1.0))
    left = g.concat([g.mul(st["A0c"], r21), g.mul(st["A1c"], r2), r2, ones], axis=-1)   # (K, P, 2HT + 2)
    k_dim = g.slice(g.op("Shape", rc0), [0], [1], [0])
    right = g.concat([rc0, rc1, g.op("Expand", g.const(np.stack([cc, cb])[None]),
                                     g.concat([k_dim, g.const([2, C], dtype=np.int64)], axis=0))], axis=1)
    y = g.add(g.mul(sc, r21), g.mm(left, right))                                    # (K, P, 256) = keys2 @ Wc + b
    y = g.reshape(y, [0, P, 4, 64])
    y = g.gelu(g.layer_norm(y, w["up1.g"], w["up1.b"], float(w["up1.eps"])))
    w2 = w["up3.w"].transpose(0, 2, 3, 1).reshape(64, 4 * 32)                      # cols (kh2, kw2, o2)
    z = g.gelu(g.add(g.mm(y, g.const(w2)), g.const(np.tile(w["up3.b"], 4))))       # (K, P, 4, 128)
    z = g.reshape(z, [0, P * 16, 32])
    g.output(g.mm(z, g.transpose(st["hyper_in"], [0, 2, 1])), "low_res_raw")   # (K, P*16, 4)
    return g.model()


def raw_to_image(raw: np.ndarray) -> np.ndarray:
    """The mask graph's (..., 4096*16) logits in (y, x, kh, kw, kh2, kw2) order -> (..., 256, 256):
    pixel row 4y + 2kh + kh2, column 4x + 2kw + kw2 (the two stride-2 transposed convolutions)."""
    lead = raw.shape[:-1]
    r = raw.reshape(-1, 64, 64, 2, 2, 2, 2).transpose(0, 1, 3, 5, 2, 4, 6)
    return r.reshape(*lead, LOW_RES, LOW_RES)


# ---------------------------------------------------------------------------------------------
# Runner
# ---------------------------------------------------------------------------------------------
# ORT would fuse the mask graph's second bias + GELU into BiasGelu, whose CPU kernel is about 4x
# slower per element than Gelu's (onnxruntime 1.32, same outputs; docs/models.md "Speed")
MASK_GRAPH_DISABLED_OPTIMIZERS = ("BiasGeluFusion",)


class FastDecoder:
    """The restructured decoder on ONNX Runtime: `set_image` once per image, then `predict_iou` for a
    batch of prompts and `low_res_masks` for the prompts whose candidates are wanted.

    decoder_path: the official decoder ONNX (its weights are read from it).
    providers: resolved execution providers in preference order (onnx_runtime.resolve_providers).
    threads: intra-op threads of each of the three sessions."""

    # Prompts per token-graph call: 4 on CPU (measured per batch size in docs/models.md, "Speed"),
    # GPU_BATCH_SIZE on other providers.
    CPU_BATCH_SIZE = 4
    GPU_BATCH_SIZE = 64

    def __init__(self, decoder_path: str | Path, providers: Sequence[str], threads: int):
        from .onnx_runtime import create_session

        w = decoder_weights(decoder_path)
        self.path = Path(decoder_path)
        self.batch_size = self.CPU_BATCH_SIZE if providers[0] == "CPUExecutionProvider" else self.GPU_BATCH_SIZE
        self._image = create_session(build_image_graph(w).SerializeToString(), providers, threads, "fast decoder (image)")
        self._tokens = create_session(build_token_graph(w).SerializeToString(), providers, threads, "fast decoder (tokens)")
        self._masks = create_session(build_mask_graph(w).SerializeToString(), providers, threads, "fast decoder (masks)",
                                     disabled_optimizers=MASK_GRAPH_DISABLED_OPTIMIZERS)
        self._token_outputs = [o.name for o in self._tokens.get_outputs()]
        self._img: dict | None = None

    def set_image(self, image_embeddings: np.ndarray) -> None:
        """image_embeddings (1, 256, 64, 64) float32 from the encoder."""
        import onnxruntime as ort

        emb = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(image_embeddings, np.float32))
        vals = self._image.run_with_ort_values(list(IMAGE_OUTPUTS), {"image_embeddings": emb})
        self._img = dict(zip(IMAGE_OUTPUTS, vals))

    def predict_iou(self, point_coords: np.ndarray, point_labels: np.ndarray):
        """point_coords (B, N, 2) in the 1024 input frame, point_labels (B, N) (1 fg, 0 bg, -1 padding).
        Returns (iou_predictions (B, 4) float32, state for `low_res_masks`)."""
        import onnxruntime as ort

        if self._img is None:
            raise RuntimeError("call set_image() before predict_iou()")
        feeds = {k: self._img[k] for k in TOKEN_IMAGE_INPUTS}
        feeds["point_coords"] = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(point_coords, np.float32))
        feeds["point_labels"] = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(point_labels, np.float32))
        vals = dict(zip(self._token_outputs, self._tokens.run_with_ort_values(self._token_outputs, feeds)))
        return vals["iou_predictions"].numpy(), {k: vals[k] for k in STATE}

    def low_res_raw(self, state: dict, index: np.ndarray) -> np.ndarray:
        """(K, 4096*16, 4) float32 mask logits of the prompts `index` of a predict_iou batch, in the
        mask graph's pixel order (see raw_to_image)."""
        import onnxruntime as ort

        feeds = dict(state)
        feeds["SC"] = self._img["SC"]
        feeds["index"] = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(index, np.int64))
        return self._masks.run_with_ort_values(["low_res_raw"], feeds)[0].numpy()

    def low_res_masks(self, state: dict, index: np.ndarray) -> np.ndarray:
        """(K, 4, 256, 256) float32 mask logits of the prompts `index` of a predict_iou batch."""
        return raw_to_image(np.moveaxis(self.low_res_raw(state, index), -1, 1))

    def candidate_masks(self, state: dict, prompt: np.ndarray, token: np.ndarray) -> np.ndarray:
        """(n, 256, 256) logits of candidates (prompt index in the batch, mask token 0..3); each
        prompt's masks are decoded once."""
        uniq, rows = np.unique(prompt, return_inverse=True)
        raw = self.low_res_raw(state, uniq)
        return raw_to_image(raw[rows, :, np.asarray(token)])
