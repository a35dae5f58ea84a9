"""The fast decoder's token graph: point prompts -> iou_predictions and the per-prompt state of the
mask graph, batched over prompts, in the steps of segment-anything's modules (`SamOnnxModel._embed_points`,
the two `TwoWayAttentionBlock`s, `final_attn_token_to_image`, the mask decoder's heads).

The image stream is never formed per prompt: after layer 0 it is held as the factors of
keys1 = r1 * (s0 + a0c @ m0) * g1 + b1, after layer 1 as those of keys2; every product with it is
re-associated through them. docs/models.md, "How the fast decoder is fast", derives each term under
the names used here.

The attentions a0c, a1c (B, P, HT) are only ever held transposed, as a0cT, a1cT (B, HT, P): a free
reshape of the (B, H, T, P) softmax output, where a0c would cost a transpose of it. Products with
a0c on the right read a0cT through a transposed product (`mm_t`, a FusedMatMul for ONNX Runtime),
those with a0c on the left are taken transposed ((a0c @ X)^T = X^T @ a0cT), and row sums over HT
become column sums (`coldot`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto

from .fast_decoder_graphs import IMAGE_TENSORS, STATE, TOKEN_IMAGE_INPUTS, DecoderGraph, Derived
from .fast_decoder_weights import C, D, H, N_OUT, P


def _heads_T(m: np.ndarray) -> np.ndarray:
    """(P, H*D) -> (H, D, P): a per-position constant of keys or queries, per head, transposed."""
    return m.reshape(P, H, D).transpose(1, 2, 0)


class _TokenGraph(DecoderGraph):
    """The token graph's builder: the image tensors as inputs (`img`), the dynamic H*T (`ht`, set
    once the tokens exist) and the helpers of the factored attentions."""

    def __init__(self, w: dict[str, np.ndarray], d: Derived):
        super().__init__("mobilesam_fast_tokens", w, d)
        self.eps = float(w["ln_eps"])
        self.img = {name: self.input(name, IMAGE_TENSORS[name]) for name in TOKEN_IMAGE_INPUTS}
        self.ht = ""

    def ln(self, x: str, key: str) -> str:
        return self.layer_norm(x, self.w[key + ".g"], self.w[key + ".b"], self.eps)

    def linear_w(self, x: str, key: str) -> str:
        """x @ w[key.w] + w[key.b]."""
        return self.linear(x, self.w[key + ".w"], self.w[key + ".b"])

    def q_heads(self, x: str, key: str) -> str:
        """(B, T, C) -> the cross attention's projection `key`, (B, H, T, D), pre-scaled by 1/sqrt(D)."""
        return self.split_heads(self.linear(x, self.w[key + ".w"] * 0.25, self.w[key + ".b"] * 0.25), [0, 2, 1, 3])

    def self_attn(self, q_in: str, v_in: str, key: str) -> str:
        """segment-anything's Attention at full width (8 heads of 32): q and k from q_in, v from v_in."""
        w, scale = self.w, np.sqrt(32.0)
        q = self.linear(q_in, w[key + ".q_proj.w"] / scale, w[key + ".q_proj.b"] / scale)
        q = self.split_heads(q, [0, 2, 1, 3], 32)
        k = self.split_heads(self.linear_w(q_in, key + ".k_proj"), [0, 2, 3, 1], 32)
        v = self.split_heads(self.linear_w(v_in, key + ".v_proj"), [0, 2, 1, 3], 32)
        o = self.mm(self.softmax(self.mm(q, k)), v)                                    # (B, H, T, 32)
        return self.linear_w(self.merge_heads(o, 32), key + ".out_proj")

    def mlp_block(self, queries: str, layer: str) -> str:
        """The two-way block's MLP block: LN(queries + lin2(relu(lin1(queries))))."""
        h = self.linear_w(self.relu(self.linear_w(queries, layer + ".mlp.lin1")), layer + ".mlp.lin2")
        return self.ln(self.add(queries, h), layer + ".norm3")

    def token_keys_values(self, queries: str, tokens: str, layer: str) -> tuple[str, str]:
        """The tokens' side of the layer's image-to-token attention: keys (B, H, T, D), pre-scaled by
        1/sqrt(D), and values (B, T, 128)."""
        key = layer + ".cross_attn_image_to_token"
        return self.q_heads(self.add(queries, tokens), key + ".k_proj"), self.linear_w(queries, key + ".v_proj")

    def softmax_tokens(self, x: str) -> str:
        """(B, H, T, P) logits -> softmax over the tokens (axis 2), vectorised along P."""
        e = self.op("Exp", self.sub(x, self.op("ReduceMax", x, axes=[2], keepdims=1)))
        return self.div(e, self.reduce_sum(e, [2]))

    def cat_heads_T(self, a: str) -> str:
        """(B, H, T, P) -> (B, H*T, P), the heads stacked: a_c^T, free."""
        return self.reshape(a, [0, -1, P])

    def mm_t(self, a: str, b: str) -> str:
        """a @ b^T over the last two axes: ONNX Runtime fuses the Transpose into its product
        (FusedMatMul with transB), so b^T is never written out."""
        return self.mm(a, self.transpose(b, [0, 2, 1]))

    def r_row(self, r: str) -> str:
        """(B, P, 1) -> (B, 1, 1, P), to scale logits per image position."""
        return self.reshape(r, [0, 1, 1, P])

    def column(self, x: str) -> str:
        """Per-position values (B, 1, P) or (B, 1, 1, P) -> (B, P, 1), free."""
        return self.reshape(x, [0, P, 1])

    def coldot(self, a: str, b: str) -> str:
        """(B, K, P) x (B, K, P) summed over K -> (B, P, 1): the row sums of a^T * b^T."""
        return self.column(self.reduce_sum(self.mul(a, b), [1]))

    def headdot(self, a: str, b: str) -> str:
        """(B, H, T, P) x (B, H, T, P) summed over heads and tokens -> (B, P, 1)."""
        return self.column(self.reduce_sum(self.mul(a, b), [1, 2]))

    def inv_std(self, ssq: str) -> str:
        """(B, P, 1) sums of squares of centred rows -> 1 / sqrt(ssq / C + eps)."""
        var = self.div(ssq, self.const(float(C)))
        return self.op("Reciprocal", self.op("Sqrt", self.add(var, self.const(self.eps))))

    def shape_ht(self, prefix: list[int]) -> str:
        """The int64 shape prefix + [H*T]."""
        return self.concat([self.const(prefix, dtype=np.int64), self.ht], axis=0)

    def through_attention(self, q: str, r: str, a_cT: str, tq: int = -1) -> str:
        """q against the attention part a_c @ r of factored keys: (q @ r) @ a_cT.
        q (B, H, tq, D), r (B, H, D, HT), a_cT (B, HT, P) -> (B, H, tq, P)."""
        qr = self.reshape(self.mm(q, r), self.shape_ht([0, -1]))                       # (B, H*tq, HT)
        return self.reshape(self.mm(qr, a_cT), [0, H, tq, P])

    def attention_through(self, p: str, a_cT: str, tq: int = -1) -> str:
        """Attention weights p (B, H, tq, P) through a_c (held as a_cT (B, HT, P)) -> (B, H, tq, HT):
        p's product with the attention part a_c @ r of factored values is then (p @ a_c) @ r."""
        return self.reshape(self.mm_t(self.reshape(p, [0, -1, P]), a_cT), self.shape_ht([0, H, tq]))

    def factored_logits(self, q: str, r: str, image_T: str, rk: str, a_cT: str, const: np.ndarray) -> str:
        """Logits of q (B, H, T, D) against keys K = r * (S + a_c @ rk) + const (per head):
        r * (q @ image_T + (q @ rk) @ a_cT) + q @ const^T -> (B, H, T, P)."""
        q_a = self.through_attention(q, rk, a_cT)
        return self.add(self.mul(self.r_row(r), self.add(self.mm(q, image_T), q_a)),
                        self.mm(q, self.const(_heads_T(const))))


@dataclass(frozen=True)
class _Keys1:
    """The image stream after layer 0, factored: keys1 = r1 * (s0 + a0c @ m0) * g1 + b1."""

    a0: str  # (B, H, T, P) layer 0's image-to-token attention (softmax over T)
    a0cT: str  # (B, HT, P) its heads stacked: a0c (B, P, HT) transposed
    vt0: str  # (B, T, 128) its token values
    vt0h: str  # (B, H, T, D) per head
    m0: str  # (B, HT, C) blockdiag(vt0) @ wo0
    r1: str  # (B, P, 1) 1 / std of layer 0's norm4 input


@dataclass(frozen=True)
class _Keys2:
    """The image stream after layer 1, factored: keys2 = r2 * (r1 * u0 + u1) * g2 + b2 with
    u0 = s2 + a0c @ n0 and u1 = a1c @ m1 + beta."""

    a1cT: str  # (B, HT, P) layer 1's image-to-token attention, heads stacked: a1c transposed
    n0: str  # (B, HT, C) blockdiag(vt0) @ wn0
    m1: str  # (B, HT, C) blockdiag(vt1) @ wo1
    r2: str  # (B, P, 1) 1 / std of layer 1's norm4 input


def build_token_graph(w: dict[str, np.ndarray], d: Derived) -> onnx.ModelProto:
    """The image tensors (all IMAGE_TENSORS but SC) + point prompts, point_coords (B, N, 2) in the
    1024 frame and point_labels (B, N) -> iou_predictions (B, 4) and the per-prompt STATE."""
    g = _TokenGraph(w, d)
    coords = g.input("point_coords", ["B", "N", 2])
    labels = g.input("point_labels", ["B", "N"])
    tokens = _embed_points(g, coords, labels)                                          # (B, T, C)
    g.ht = g.mul(g.slice(g.op("Shape", tokens), [1], [2], [0]), g.const([H], dtype=np.int64))
    queries, keys1 = _two_way_layer0(g, tokens)
    queries, a1, vt1 = _two_way_layer1(g, queries, tokens, keys1)
    keys2 = _image_stream_stats(g, keys1, a1, vt1)
    out_tokens = _final_attn_token_to_image(g, queries, tokens, keys1, keys2)         # (B, 5, C)
    iou, hyper = _iou_and_hypernetwork_heads(g, out_tokens)
    g.output(iou, "iou_predictions")
    hyper_in = g.concat(hyper, axis=1)                                                 # (B, 4, 32)
    for name, value in zip(STATE, (keys1.a0cT, keys2.a1cT, keys1.r1, keys2.r2, keys1.vt0, vt1, hyper_in)):
        g.output(value, name)
    return g.model()


def _embed_points(g: _TokenGraph, coords: str, labels: str) -> str:
    """SamOnnxModel._embed_points, then the output tokens in front: (B, T = 5 + N, C) tokens, the
    IoU and 4 mask tokens, then each point's positional encoding plus its label's embedding
    (not_a_point for the padding label -1)."""
    w = g.w
    c = g.div(g.add(coords, g.const(0.5)), g.const(1024.0))                           # pixel centres, [0, 1]
    c = g.sub(g.mul(c, g.const(2.0)), g.const(1.0))                                   # [-1, 1]
    proj = g.mul(g.mm(c, g.const(w["pe_gaussian"])), g.const(2.0 * np.pi))            # (B, N, C/2)
    pts = g.concat([g.op("Sin", proj), g.op("Cos", proj)], axis=-1)                   # (B, N, C)
    lab = g.op("Unsqueeze", labels, g.const([-1], dtype=np.int64))                    # (B, N, 1)

    def is_label(v: int) -> str:
        return g.op("Cast", g.op("Equal", lab, g.const(float(v))), to=TensorProto.FLOAT)

    pad = is_label(-1)
    sparse = g.add(g.mul(pts, g.sub(g.const(1.0), pad)), g.mul(pad, g.const(w["not_a_point"])))
    for i in range(4):
        sparse = g.add(sparse, g.mul(is_label(i), g.const(w[f"point_embed.{i}"])))
    b_dim = g.slice(g.op("Shape", coords), [0], [1], [0])
    out_tok = g.op("Expand", g.const(w["output_tokens"][None]),
                   g.concat([b_dim, g.const([N_OUT, C], dtype=np.int64)], axis=0))    # (B, 5, C)
    return g.concat([out_tok, sparse], axis=1)


def _two_way_layer0(g: _TokenGraph, tokens: str) -> tuple[str, _Keys1]:
    """TwoWayAttentionBlock 0 (skip_first_layer_pe) on tokens (B, T, C): the new queries, and the
    image stream after it as the factors of keys1."""
    img = g.img
    # Self attention block (no positional encoding, no residual)
    queries = g.ln(g.self_attn(tokens, tokens, "layers.0.self_attn"), "layers.0.norm1")   # (B, T, C)
    # Cross attention block, tokens attending to image embedding (keys and values per image: K0T, V0)
    T2I = "layers.0.cross_attn_token_to_image"
    q0 = g.q_heads(g.add(queries, tokens), T2I + ".q_proj")                             # (B, H, T, D)
    p0 = g.softmax(g.mm(q0, img["K0T"]))                                               # (B, H, T, P)
    o0 = g.merge_heads(g.mm(p0, img["V0"]))                                            # (B, T, 128)
    queries = g.ln(g.add(queries, g.linear_w(o0, T2I + ".out_proj")), "layers.0.norm2")
    # MLP block
    queries = g.mlp_block(queries, "layers.0")
    # Cross attention block, image embedding attending to tokens: keys1, factored
    kt0, vt0 = g.token_keys_values(queries, tokens, "layers.0")                        # (B, H, T, D), (B, T, 128)
    a0 = g.softmax_tokens(g.mm(kt0, img["Qi0T"]))                                      # (B, H, T, P)
    a0cT = g.cat_heads_T(a0)                                                           # (B, HT, P)
    vt0h = g.split_heads(vt0, [0, 2, 1, 3])                                            # (B, H, T, D)
    m0 = g.blockdiag(vt0h, g.d.wo0)                                                    # (B, HT, C)
    # norm4's statistics: |s0 + a0c @ m0|^2 = ssq + 2 <a0, m0s0> + rowdot(a0c, a0c @ m0m0), the last
    # term as coldot(a0cT, m0m0 @ a0cT) (m0m0 is symmetric)
    m0m0 = g.mm_t(m0, m0)                                                              # (B, HT, HT)
    m0s0 = g.mm(vt0h, img["Sx0T"])                                                     # (B, H, T, P)
    sq1 = g.add(g.add(img["ssq"], g.mul(g.const(2.0), g.headdot(a0, m0s0))), g.coldot(a0cT, g.mm(m0m0, a0cT)))
    return queries, _Keys1(a0=a0, a0cT=a0cT, vt0=vt0, vt0h=vt0h, m0=m0, r1=g.inv_std(sq1))


def _two_way_layer1(g: _TokenGraph, queries: str, tokens: str, keys1: _Keys1) -> tuple[str, str, str]:
    """TwoWayAttentionBlock 1 against keys1 held factored: the new queries (B, T, C), and its
    image-to-token attention a1 (B, H, T, P) and token values vt1 (B, T, 128)."""
    w, d, img = g.w, g.d, g.img
    g1w = d.g1[:, None]
    # Self attention block
    queries = g.ln(g.add(queries, g.self_attn(g.add(queries, tokens), queries, "layers.1.self_attn")),
                   "layers.1.norm1")
    # Cross attention block, tokens attending to keys1: (keys1 + pe) @ Wk + bk = r1 * (SK1 + a0c @ rk1) + k1_const
    T2I = "layers.1.cross_attn_token_to_image"
    q1 = g.q_heads(g.add(queries, tokens), T2I + ".q_proj")                             # (B, H, T, D)
    rk1 = g.split_heads(g.mm(keys1.m0, g.const(g1w * w[T2I + ".k_proj.w"])), [0, 2, 3, 1])   # (B, H, D, HT)
    k1_const = (d.pe + w["layers.0.norm4.b"][None]) @ w[T2I + ".k_proj.w"] + w[T2I + ".k_proj.b"]   # (P, 128)
    p1 = g.softmax(g.factored_logits(q1, keys1.r1, img["SK1T"], rk1, keys1.a0cT, k1_const))  # (B, H, T, P)
    # and values: p1 @ (keys1 @ Wv + bv) = p1r @ SV1 + (p1r @ a0c) @ rv1 + v1_const
    p1r = g.mul(p1, g.r_row(keys1.r1))
    rv1 = g.split_heads(g.mm(keys1.m0, g.const(g1w * w[T2I + ".v_proj.w"])), [0, 2, 1, 3])   # (B, H, HT, D)
    p1_a0 = g.attention_through(p1r, keys1.a0cT)                                        # (B, H, T, HT)
    v1_const = w["layers.0.norm4.b"] @ w[T2I + ".v_proj.w"] + w[T2I + ".v_proj.b"]     # (128,)
    o1 = g.add(g.add(g.mm(p1r, img["SV1"]), g.mm(p1_a0, rv1)), g.const(v1_const.reshape(H, 1, D)))
    queries = g.ln(g.add(queries, g.linear_w(g.merge_heads(o1), T2I + ".out_proj")), "layers.1.norm2")
    # MLP block
    queries = g.mlp_block(queries, "layers.1")
    # Cross attention block, keys1 attending to tokens: (keys1 + pe) @ Wq + bq = r1 * (SQ1 + a0c @ rq1) + q1_const
    I2T = "layers.1.cross_attn_image_to_token"
    kt1, vt1 = g.token_keys_values(queries, tokens, "layers.1")                        # (B, H, T, D), (B, T, 128)
    rq1 = g.split_heads(g.mm(keys1.m0, g.const(g1w * w[I2T + ".q_proj.w"])), [0, 2, 3, 1])   # (B, H, D, HT)
    q1_const = (d.pe + w["layers.0.norm4.b"][None]) @ w[I2T + ".q_proj.w"] + w[I2T + ".q_proj.b"]   # (P, 128)
    a1 = g.softmax_tokens(g.factored_logits(kt1, keys1.r1, img["SQ1T"], rq1, keys1.a0cT, q1_const))
    return queries, a1, vt1


def _image_stream_stats(g: _TokenGraph, keys1: _Keys1, a1: str, vt1: str) -> _Keys2:
    """Layer 1's image-to-token update of the image stream and its norm4 statistics, from Gram
    matrices: |r1 * u0 + u1|^2 = r1^2 u0u0 + 2 r1 u0u1 + u1u1_sq + 2 u1_cross."""
    d, img = g.d, g.img
    a1cT = g.cat_heads_T(a1)                                                           # (B, HT, P)
    vt1h = g.split_heads(vt1, [0, 2, 1, 3])                                            # (B, H, T, D)
    n0 = g.blockdiag(keys1.vt0h, d.wn0)                                                # (B, HT, C)
    m1 = g.blockdiag(vt1h, d.wo1)                                                      # (B, HT, C)
    n0s2 = g.mm(keys1.vt0h, img["Sy0T"])                                               # (B, H, T, P)
    m1s2 = g.mm(vt1h, img["Sy1T"])                                                     # (B, H, T, P)
    beta_row = g.const(d.beta.reshape(1, C))
    # a0c @ n0 n0^T, a0c @ n0 m1^T and a0c @ n0 beta, transposed: (n0 n0^T) @ a0cT, (m1 n0^T) @ a0cT,
    # (beta^T n0^T) @ a0cT
    a0n0n0T = g.mm(g.mm_t(n0, n0), keys1.a0cT)                                         # (B, HT, P)
    a0n0m1T = g.mm(g.mm_t(m1, n0), keys1.a0cT)                                         # (B, HT, P)
    a0n0b = g.column(g.mm(g.mm_t(beta_row, n0), keys1.a0cT))                           # (B, P, 1)
    u0u0 = g.add(g.add(img["S2sq"], g.mul(g.const(2.0), g.headdot(keys1.a0, n0s2))), g.coldot(keys1.a0cT, a0n0n0T))
    u1u1_sq = g.add(g.coldot(a1cT, g.mm(g.mm_t(m1, m1), a1cT)), g.const(float(d.beta @ d.beta)))
    u0u1 = g.add(g.add(g.headdot(a1, m1s2), g.coldot(a1cT, a0n0m1T)), g.add(img["S2b"], a0n0b))
    u1_cross = g.column(g.mm(g.mm_t(beta_row, m1), a1cT))                              # (B, P, 1)
    r1 = keys1.r1
    sq2 = g.add(g.add(g.mul(g.mul(r1, r1), u0u0), u1u1_sq), g.mul(g.const(2.0), g.add(g.mul(r1, u0u1), u1_cross)))
    return _Keys2(a1cT=a1cT, n0=n0, m1=m1, r2=g.inv_std(sq2))


def _final_attn_token_to_image(g: _TokenGraph, queries: str, tokens: str, keys1: _Keys1, keys2: _Keys2) -> str:
    """TwoWayTransformer's final attention of the output tokens 0..4 to keys2 held factored, then
    norm_final_attn -> (B, 5, C)."""
    w, d, img = g.w, g.d, g.img
    F = "final"
    qf = g.q_heads(g.slice(g.add(queries, tokens), [0], [N_OUT], [1]), F + ".q_proj")   # (B, H, 5, D)
    # (keys2 + pe) @ Wk + bk = r2 * (r1 * (SKf + a0c @ rkf0) + a1c @ rkf1 + kf_beta) + kf_const
    g2wk = d.g2[:, None] * w[F + ".k_proj.w"]
    g2wv = d.g2[:, None] * w[F + ".v_proj.w"]
    rkf0 = g.split_heads(g.mm(keys2.n0, g.const(g2wk)), [0, 2, 3, 1])                  # (B, H, D, HT)
    rkf1 = g.split_heads(g.mm(keys2.m1, g.const(g2wk)), [0, 2, 3, 1])
    qf_a0 = g.through_attention(qf, rkf0, keys1.a0cT, N_OUT)                           # (B, H, 5, P)
    qf_a1 = g.through_attention(qf, rkf1, keys2.a1cT, N_OUT)
    kf_beta = (d.beta @ g2wk).reshape(H, D, 1)
    kf_const = (d.pe + w["layers.1.norm4.b"][None]) @ w[F + ".k_proj.w"] + w[F + ".k_proj.b"]   # (P, 128)
    r1_row, r2_row = g.r_row(keys1.r1), g.r_row(keys2.r2)
    inner = g.add(g.add(g.mul(r1_row, g.add(g.mm(qf, img["SKfT"]), qf_a0)), qf_a1), g.mm(qf, g.const(kf_beta)))
    pf = g.softmax(g.add(g.mul(r2_row, inner), g.mm(qf, g.const(_heads_T(kf_const)))))   # (B, H, 5, P)
    # values: pf @ (keys2 @ Wv + bv) = pf_r2r1 @ SVf + (pf_r2r1 @ a0c) @ rvf0 + (pf_r2 @ a1c) @ rvf1
    #                                  + sum(pf_r2) vf_beta + vf_const
    pf_r2 = g.mul(pf, r2_row)
    pf_r2r1 = g.mul(pf_r2, r1_row)
    rvf0 = g.split_heads(g.mm(keys2.n0, g.const(g2wv)), [0, 2, 1, 3])                  # (B, H, HT, D)
    rvf1 = g.split_heads(g.mm(keys2.m1, g.const(g2wv)), [0, 2, 1, 3])
    pf_a0 = g.attention_through(pf_r2r1, keys1.a0cT, N_OUT)                             # (B, H, 5, HT)
    pf_a1 = g.attention_through(pf_r2, keys2.a1cT, N_OUT)
    vf_beta = (d.beta @ g2wv).reshape(H, 1, D)
    vf_const = (w["layers.1.norm4.b"] @ w[F + ".v_proj.w"] + w[F + ".v_proj.b"]).reshape(H, 1, D)
    of = g.add(g.add(g.mm(pf_r2r1, img["SVf"]), g.mm(pf_a0, rvf0)), g.mm(pf_a1, rvf1))
    of = g.add(g.add(of, g.mul(g.reduce_sum(pf_r2, [-1]), g.const(vf_beta))), g.const(vf_const))   # (B, H, 5, D)
    out = g.slice(queries, [0], [N_OUT], [1])
    return g.ln(g.add(out, g.linear_w(g.merge_heads(of), F + ".out_proj")), "norm_final")


def _iou_and_hypernetwork_heads(g: _TokenGraph, out_tokens: str) -> tuple[str, list[str]]:
    """The mask decoder's heads on the output tokens (B, 5, C): iou_prediction_head on token 0 ->
    (B, 4); output_hypernetworks_mlps[i] on mask token i -> (B, 1, 32) each."""

    def head_mlp(x: str, name: str, i: int) -> str:
        for j in range(3):
            x = g.linear_w(x, f"{name}.{i}.{j}")
            if j < 2:
                x = g.relu(x)
        return x

    def token(i: int) -> str:                                                          # (B, C)
        return g.reshape(g.slice(out_tokens, [i], [i + 1], [1]), [0, C])

    iou = head_mlp(token(0), "iou", 0)
    return iou, [g.reshape(head_mlp(token(1 + i), "hyper", i), [0, 1, 32]) for i in range(4)]
