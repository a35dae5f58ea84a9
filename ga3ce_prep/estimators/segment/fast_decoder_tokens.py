"""The fast decoder's token graph: point prompts -> iou_predictions and the per-prompt state of the
mask graph, batched over prompts, in the steps of segment-anything's modules (`SamOnnxModel._embed_points`,
the two `TwoWayAttentionBlock`s, `final_attn_token_to_image`, the mask decoder's heads).

The image stream is never formed per prompt: after layer 0 it is held as the factors of
keys1 = r1 * (s0 + a0c @ m0) * g1 + b1, after layer 1 as those of keys2; every product with it is
re-associated through them. docs/models/segment-everything.md, "How the fast decoder is fast",
derives each term under the names used here.

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
from .fast_decoder_weights import N_OUT, C, D, H, P


def _heads_T(m: np.ndarray) -> np.ndarray:
    """(P, H*D) -> (H, D, P): a per-position constant of keys or queries, per head, transposed."""
    return m.reshape(P, H, D).transpose(1, 2, 0)


class _TokenGraph(DecoderGraph):
    """The token graph's builder: the image tensors as inputs (`img`), the dynamic H*T (`ht`, set
    once the tokens exist), the pixel slices (`slices`) and the helpers of the factored attentions.
    Per-pixel helpers take the slice's width n."""

    def __init__(self, w: dict[str, np.ndarray], d: Derived, pixel_chunks: int):
        super().__init__("mobilesam_fast_tokens", w, d)
        if P % pixel_chunks:
            raise ValueError(f"pixel_chunks must divide {P}, got {pixel_chunks}")
        self.eps = float(w["ln_eps"])
        self.img = {name: self.input(name, IMAGE_TENSORS[name]) for name in TOKEN_IMAGE_INPUTS}
        self.ht = ""
        n = P // pixel_chunks
        self.slices = [_Slice(self, p0, n) for p0 in range(0, P, n)]

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
        """(B, H, T, n) logits -> softmax over the tokens (axis 2), vectorised along the pixels."""
        e = self.op("Exp", self.sub(x, self.op("ReduceMax", x, axes=[2], keepdims=1)))
        return self.div(e, self.reduce_sum(e, [2]))

    def cat_heads_T(self, a: str, n: int) -> str:
        """(B, H, T, n) -> (B, H*T, n), the heads stacked: a_c^T, free."""
        return self.reshape(a, [0, -1, n])

    def mm_t(self, a: str, b: str) -> str:
        """a @ b^T over the last two axes: ONNX Runtime fuses the Transpose into its product
        (FusedMatMul with transB), so b^T is never written out."""
        return self.mm(a, self.transpose(b, [0, 2, 1]))

    def r_row(self, r: str, n: int) -> str:
        """(B, n, 1) -> (B, 1, 1, n), to scale logits per image position."""
        return self.reshape(r, [0, 1, 1, n])

    def column(self, x: str, n: int) -> str:
        """Per-position values (B, 1, n) or (B, 1, 1, n) -> (B, n, 1), free."""
        return self.reshape(x, [0, n, 1])

    def coldot(self, a: str, b: str, n: int) -> str:
        """(B, K, n) x (B, K, n) summed over K -> (B, n, 1): the row sums of a^T * b^T."""
        return self.column(self.reduce_sum(self.mul(a, b), [1]), n)

    def headdot(self, a: str, b: str, n: int) -> str:
        """(B, H, T, n) x (B, H, T, n) summed over heads and tokens -> (B, n, 1)."""
        return self.column(self.reduce_sum(self.mul(a, b), [1, 2]), n)

    def inv_std(self, ssq: str) -> str:
        """(B, n, 1) sums of squares of centred rows -> 1 / sqrt(ssq / C + eps)."""
        var = self.div(ssq, self.const(float(C)))
        return self.op("Reciprocal", self.op("Sqrt", self.add(var, self.const(self.eps))))

    def shape_ht(self, prefix: list[int]) -> str:
        """The int64 shape prefix + [H*T]."""
        return self.concat([self.const(prefix, dtype=np.int64), self.ht], axis=0)

    def q_through(self, q: str, r: str) -> str:
        """q (B, H, tq, D) times the attention part's factor r (B, H, D, HT), heads stacked: (B, H*tq, HT),
        once per graph; `through_attention` then takes it against each slice's attention."""
        return self.reshape(self.mm(q, r), self.shape_ht([0, -1]))

    def through_attention(self, qr: str, a_cT: str, n: int, tq: int = -1) -> str:
        """q against the attention part a_c @ r of factored keys: (q @ r) @ a_cT.
        qr = q_through(q, r) (B, H*tq, HT), a_cT (B, HT, n) -> (B, H, tq, n)."""
        return self.reshape(self.mm(qr, a_cT), [0, H, tq, n])

    def attention_through(self, p: str, a_cT: str, n: int, tq: int = -1) -> str:
        """Attention weights p (B, H, tq, n) through a_c (held as a_cT (B, HT, n)) -> (B, H, tq, HT):
        p's product with the attention part a_c @ r of factored values is then (p @ a_c) @ r."""
        return self.reshape(self.mm_t(self.reshape(p, [0, -1, n]), a_cT), self.shape_ht([0, H, tq]))

    def factored_logits(self, q: str, qr: str, r: str, image_T: str, a_cT: str, const_T: str, n: int) -> str:
        """Logits of q (B, H, T, D) against keys K = r * (S + a_c @ rk) + const (per head) on a slice:
        r * (q @ image_T + (q @ rk) @ a_cT) + q @ const_T -> (B, H, T, n), with qr = q_through(q, rk)
        and const_T the constant's slice as (H, D, n)."""
        q_a = self.through_attention(qr, a_cT, n)
        return self.add(self.mul(self.r_row(r, n), self.add(self.mm(q, image_T), q_a)), self.mm(q, const_T))


class _Slice:
    """The pixels p0 .. p0 + n - 1 of the image: its slices of the image tensors (`img`, made when
    first asked for) and of per-pixel constants (`const_T`)."""

    def __init__(self, g: _TokenGraph, p0: int, n: int):
        self.g, self.p0, self.n = g, p0, n
        self._img: dict[str, str] = {}

    def img(self, name: str) -> str:
        """The slice of image tensor `name` ((H, D, n), (H, n, D) or (n, 1), as IMAGE_TENSORS)."""
        if name not in self._img:
            axis = IMAGE_TENSORS[name].index(P)
            self._img[name] = self.g.img[name] if self.n == P else \
                self.g.slice(self.g.img[name], [self.p0], [self.p0 + self.n], [axis])
        return self._img[name]

    def const_T(self, m: np.ndarray) -> str:
        """A per-position constant (P, H*D) of keys or queries as its slice's (H, D, n) constant."""
        return self.g.const(_heads_T(m)[:, :, self.p0:self.p0 + self.n])


class _PixelSoftmax:
    """Softmax over the pixels of logits given slice by slice, and products of its weights with
    per-pixel values, streamed ("online softmax"): each slice keeps its max m_s over the pixels,
    e_s = exp(x - m_s) and its sum, and the caller's products of e_s; `combine` rescales each slice's
    parts by exp(m_s - M), M the max over the slices, and divides by the total sum. Every product
    must be linear in e_s and indexed (B, H, tq, ...)."""

    def __init__(self, g: _TokenGraph):
        self.g = g
        self.parts: list[tuple[str, str, list[str]]] = []

    def weights(self, logits: str) -> tuple[str, str]:
        """A slice's logits (B, H, tq, n) -> (e_s, m_s); hand e_s's products to `add`."""
        g = self.g
        m = g.op("ReduceMax", logits, axes=[3], keepdims=1)                           # (B, H, tq, 1)
        return g.op("Exp", g.sub(logits, m)), m

    def add(self, e: str, m: str, products: list[str]) -> None:
        self.parts.append((m, self.g.reduce_sum(e, [3]), products))

    def combine(self) -> list[str]:
        """The products of the softmax weights: sum over slices of exp(m_s - M) * product, over
        the sum of exp(m_s - M) * sum(e_s)."""
        g = self.g
        if len(self.parts) == 1:
            _, s, products = self.parts[0]
            return [g.div(x, s) for x in products]
        big = g.op("Max", *[m for m, _, _ in self.parts])
        scale = [g.op("Exp", g.sub(m, big)) for m, _, _ in self.parts]
        total = g.op("Sum", *[g.mul(k, s) for k, (_, s, _) in zip(scale, self.parts)])
        return [g.div(g.op("Sum", *[g.mul(k, part[2][j]) for k, part in zip(scale, self.parts)]), total)
                for j in range(len(self.parts[0][2]))]


@dataclass(frozen=True)
class _Keys1:
    """The image stream after layer 0, factored, per pixel slice: keys1 = r1 * (s0 + a0c @ m0) * g1 + b1."""

    a0: str  # (B, H, T, n) layer 0's image-to-token attention (softmax over T)
    a0cT: str  # (B, HT, n) its heads stacked: a0c (B, n, HT) transposed
    r1: str  # (B, n, 1) 1 / std of layer 0's norm4 input


@dataclass(frozen=True)
class _Keys2:
    """The image stream after layer 1, factored, per pixel slice: keys2 = r2 * (r1 * u0 + u1) * g2 + b2
    with u0 = s2 + a0c @ n0 and u1 = a1c @ m1 + beta."""

    a1cT: str  # (B, HT, n) layer 1's image-to-token attention, heads stacked: a1c transposed
    r2: str  # (B, n, 1) 1 / std of layer 1's norm4 input


def build_token_graph(w: dict[str, np.ndarray], d: Derived, pixel_chunks: int = 1) -> onnx.ModelProto:
    """The image tensors (all IMAGE_TENSORS but SC) + point prompts, point_coords (B, N, 2) in the
    1024 frame and point_labels (B, N) -> iou_predictions (B, 4) and the per-prompt STATE.

    pixel_chunks: every per-pixel step runs on this many slices of the 4096 embedding pixels one
      after the other, and the three softmaxes over the pixels are streamed over them
      (`_PixelSoftmax`), so that a slice's (B, H, T, n) intermediates stay in the core's cache (on
      CPU; measured in docs/studies/2026-11-29-segment-everything-speed.md, "What was tried"); 1 = the
      whole image in each node (GPU)."""
    g = _TokenGraph(w, d, pixel_chunks)
    coords = g.input("point_coords", ["B", "N", 2])
    labels = g.input("point_labels", ["B", "N"])
    tokens = _embed_points(g, coords, labels)                                          # (B, T, C)
    g.ht = g.mul(g.slice(g.op("Shape", tokens), [1], [2], [0]), g.const([H], dtype=np.int64))
    queries, kt0, vt0 = _two_way_layer0(g, tokens)
    vt0h = g.split_heads(vt0, [0, 2, 1, 3])                                            # (B, H, T, D)
    queries, keys1, l1 = _two_way_layer1(g, queries, tokens, kt0, vt0h)
    out_tokens, keys2 = _final_attn_token_to_image(g, queries, tokens, keys1, l1, vt0h)   # (B, 5, C)
    iou, hyper = _iou_and_hypernetwork_heads(g, out_tokens)
    g.output(iou, "iou_predictions")
    hyper_in = g.concat(hyper, axis=1)                                                 # (B, 4, 32)

    def whole(xs: list[str], axis: int) -> str:
        return xs[0] if len(xs) == 1 else g.concat(xs, axis=axis)

    state = (whole([k.a0cT for k in keys1], 2), whole([k.a1cT for k in keys2], 2), whole([k.r1 for k in keys1], 1),
             whole([k.r2 for k in keys2], 1), vt0, l1.vt1, hyper_in)
    for name, value in zip(STATE, state):
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


def _two_way_layer0(g: _TokenGraph, tokens: str) -> tuple[str, str, str]:
    """TwoWayAttentionBlock 0 (skip_first_layer_pe) on tokens (B, T, C) up to its image-to-token
    attention: the new queries, and that attention's token keys kt0 (B, H, T, D) and values vt0
    (B, T, 128). The image side, keys1, is computed per slice (`_keys1`)."""
    # Self attention block (no positional encoding, no residual)
    queries = g.ln(g.self_attn(tokens, tokens, "layers.0.self_attn"), "layers.0.norm1")   # (B, T, C)
    # Cross attention block, tokens attending to image embedding (keys and values per image: K0T, V0)
    T2I = "layers.0.cross_attn_token_to_image"
    q0 = g.q_heads(g.add(queries, tokens), T2I + ".q_proj")                             # (B, H, T, D)
    sm = _PixelSoftmax(g)
    for sl in g.slices:
        e, m = sm.weights(g.mm(q0, sl.img("K0T")))                                     # (B, H, T, n)
        sm.add(e, m, [g.mm(e, sl.img("V0"))])
    o0 = g.merge_heads(sm.combine()[0])                                                # (B, T, 128)
    queries = g.ln(g.add(queries, g.linear_w(o0, T2I + ".out_proj")), "layers.0.norm2")
    # MLP block
    queries = g.mlp_block(queries, "layers.0")
    # Cross attention block, image embedding attending to tokens: the tokens' side
    kt0, vt0 = g.token_keys_values(queries, tokens, "layers.0")                        # (B, H, T, D), (B, T, 128)
    return queries, kt0, vt0


def _keys1(g: _TokenGraph, sl: _Slice, kt0: str, vt0h: str, m0m0: str) -> _Keys1:
    """Layer 0's image-to-token attention on a slice and the factors of keys1 there (m0 =
    blockdiag(vt0) @ wo0, m0m0 = m0 m0^T (B, HT, HT))."""
    n = sl.n
    a0 = g.softmax_tokens(g.mm(kt0, sl.img("Qi0T")))                                  # (B, H, T, n)
    a0cT = g.cat_heads_T(a0, n)                                                        # (B, HT, n)
    # norm4's statistics: |s0 + a0c @ m0|^2 = ssq + 2 <a0, m0s0> + rowdot(a0c, a0c @ m0m0), the last
    # term as coldot(a0cT, m0m0 @ a0cT) (m0m0 is symmetric)
    m0s0 = g.mm(vt0h, sl.img("Sx0T"))                                                  # (B, H, T, n)
    sq1 = g.add(g.add(sl.img("ssq"), g.mul(g.const(2.0), g.headdot(a0, m0s0, n))),
                g.coldot(a0cT, g.mm(m0m0, a0cT), n))
    return _Keys1(a0=a0, a0cT=a0cT, r1=g.inv_std(sq1))


@dataclass(frozen=True)
class _Layer1ToTokens:
    """Layer 1's image-to-token attention, the tokens' side: keys kt1 (B, H, T, D), values vt1
    (B, T, 128), and the queries' factors (keys1 + pe) @ Wq + bq = r1 * (SQ1 + a0c @ rq1) + q1_const:
    kt1_rq1 = q_through(kt1, rq1), q1_const (P, 128)."""

    kt1: str
    vt1: str
    kt1_rq1: str
    q1_const: np.ndarray

    def attention(self, g: _TokenGraph, sl: _Slice, k1: _Keys1) -> str:
        """a1 on a slice (B, H, T, n): keys1's queries against the tokens' keys, softmax over the tokens."""
        return g.softmax_tokens(g.factored_logits(self.kt1, self.kt1_rq1, k1.r1, sl.img("SQ1T"), k1.a0cT,
                                                  sl.const_T(self.q1_const), sl.n))


def _two_way_layer1(g: _TokenGraph, queries: str, tokens: str, kt0: str,
                    vt0h: str) -> tuple[str, list[_Keys1], _Layer1ToTokens]:
    """TwoWayAttentionBlock 1 against keys1, which it computes per slice (`_keys1`): the new queries
    (B, T, C), keys1's factors per slice, and its image-to-token attention's token side."""
    w, d = g.w, g.d
    g1w = d.g1[:, None]
    m0 = g.blockdiag(vt0h, d.wo0)                                                      # (B, HT, C)
    m0m0 = g.mm_t(m0, m0)                                                              # (B, HT, HT)
    # Self attention block
    queries = g.ln(g.add(queries, g.self_attn(g.add(queries, tokens), queries, "layers.1.self_attn")),
                   "layers.1.norm1")
    # Cross attention block, tokens attending to keys1: (keys1 + pe) @ Wk + bk = r1 * (SK1 + a0c @ rk1) + k1_const
    T2I = "layers.1.cross_attn_token_to_image"
    q1 = g.q_heads(g.add(queries, tokens), T2I + ".q_proj")                             # (B, H, T, D)
    rk1 = g.split_heads(g.mm(m0, g.const(g1w * w[T2I + ".k_proj.w"])), [0, 2, 3, 1])   # (B, H, D, HT)
    q1_rk1 = g.q_through(q1, rk1)
    k1_const = (d.pe + w["layers.0.norm4.b"][None]) @ w[T2I + ".k_proj.w"] + w[T2I + ".k_proj.b"]   # (P, 128)
    # and values: p1 @ (keys1 @ Wv + bv) = p1r @ SV1 + (p1r @ a0c) @ rv1 + v1_const, p1r = p1 * r1
    rv1 = g.split_heads(g.mm(m0, g.const(g1w * w[T2I + ".v_proj.w"])), [0, 2, 1, 3])   # (B, H, HT, D)
    sm, keys1 = _PixelSoftmax(g), []
    for sl in g.slices:
        k1 = _keys1(g, sl, kt0, vt0h, m0m0)
        keys1.append(k1)
        e, m = sm.weights(g.factored_logits(q1, q1_rk1, k1.r1, sl.img("SK1T"), k1.a0cT, sl.const_T(k1_const), sl.n))
        er = g.mul(e, g.r_row(k1.r1, sl.n))
        sm.add(e, m, [g.mm(er, sl.img("SV1")), g.attention_through(er, k1.a0cT, sl.n)])
    p1r_sv1, p1_a0 = sm.combine()                                                      # (B, H, T, D), (B, H, T, HT)
    v1_const = w["layers.0.norm4.b"] @ w[T2I + ".v_proj.w"] + w[T2I + ".v_proj.b"]     # (128,)
    o1 = g.add(g.add(p1r_sv1, g.mm(p1_a0, rv1)), g.const(v1_const.reshape(H, 1, D)))
    queries = g.ln(g.add(queries, g.linear_w(g.merge_heads(o1), T2I + ".out_proj")), "layers.1.norm2")
    # MLP block
    queries = g.mlp_block(queries, "layers.1")
    # Cross attention block, keys1 attending to tokens: (keys1 + pe) @ Wq + bq = r1 * (SQ1 + a0c @ rq1) + q1_const
    I2T = "layers.1.cross_attn_image_to_token"
    kt1, vt1 = g.token_keys_values(queries, tokens, "layers.1")                        # (B, H, T, D), (B, T, 128)
    rq1 = g.split_heads(g.mm(m0, g.const(g1w * w[I2T + ".q_proj.w"])), [0, 2, 3, 1])   # (B, H, D, HT)
    q1_const = (d.pe + w["layers.0.norm4.b"][None]) @ w[I2T + ".q_proj.w"] + w[I2T + ".q_proj.b"]   # (P, 128)
    return queries, keys1, _Layer1ToTokens(kt1=kt1, vt1=vt1, kt1_rq1=g.q_through(kt1, rq1), q1_const=q1_const)


@dataclass(frozen=True)
class _Grams:
    """The token-side products of layer 1's norm4 statistics (B prompts): vt0h, vt1h (B, H, T, D), the
    Gram matrices n0n0T = n0 n0^T, m1n0T = m1 n0^T, m1m1T (B, HT, HT) and bn0 = beta n0^T, bm1 =
    beta m1^T (B, 1, HT)."""

    vt0h: str
    vt1h: str
    n0n0T: str
    m1n0T: str
    m1m1T: str
    bn0: str
    bm1: str

    @classmethod
    def of(cls, g: _TokenGraph, vt0h: str, vt1h: str, n0: str, m1: str) -> _Grams:
        beta_row = g.const(g.d.beta.reshape(1, C))
        return cls(vt0h=vt0h, vt1h=vt1h, n0n0T=g.mm_t(n0, n0), m1n0T=g.mm_t(m1, n0), m1m1T=g.mm_t(m1, m1),
                   bn0=g.mm_t(beta_row, n0), bm1=g.mm_t(beta_row, m1))


def _image_stream_stats(g: _TokenGraph, sl: _Slice, keys1: _Keys1, a1: str, gr: _Grams) -> _Keys2:
    """Layer 1's image-to-token update of the image stream on a slice and its norm4 statistics, from
    Gram matrices: |r1 * u0 + u1|^2 = r1^2 u0u0 + 2 r1 u0u1 + u1u1_sq + 2 u1_cross."""
    d, n = g.d, sl.n
    a1cT = g.cat_heads_T(a1, n)                                                        # (B, HT, n)
    n0s2 = g.mm(gr.vt0h, sl.img("Sy0T"))                                               # (B, H, T, n)
    m1s2 = g.mm(gr.vt1h, sl.img("Sy1T"))                                               # (B, H, T, n)
    # a0c @ n0 n0^T, a0c @ n0 m1^T and a0c @ n0 beta, transposed: (n0 n0^T) @ a0cT, (m1 n0^T) @ a0cT,
    # (beta^T n0^T) @ a0cT
    a0n0n0T = g.mm(gr.n0n0T, keys1.a0cT)                                               # (B, HT, n)
    a0n0m1T = g.mm(gr.m1n0T, keys1.a0cT)                                               # (B, HT, n)
    a0n0b = g.column(g.mm(gr.bn0, keys1.a0cT), n)                                      # (B, n, 1)
    u0u0 = g.add(g.add(sl.img("S2sq"), g.mul(g.const(2.0), g.headdot(keys1.a0, n0s2, n))),
                 g.coldot(keys1.a0cT, a0n0n0T, n))
    u1u1_sq = g.add(g.coldot(a1cT, g.mm(gr.m1m1T, a1cT), n), g.const(float(d.beta @ d.beta)))
    u0u1 = g.add(g.add(g.headdot(a1, m1s2, n), g.coldot(a1cT, a0n0m1T, n)), g.add(sl.img("S2b"), a0n0b))
    u1_cross = g.column(g.mm(gr.bm1, a1cT), n)                                         # (B, n, 1)
    r1 = keys1.r1
    sq2 = g.add(g.add(g.mul(g.mul(r1, r1), u0u0), u1u1_sq), g.mul(g.const(2.0), g.add(g.mul(r1, u0u1), u1_cross)))
    return _Keys2(a1cT=a1cT, r2=g.inv_std(sq2))


def _final_attn_token_to_image(g: _TokenGraph, queries: str, tokens: str, keys1: list[_Keys1],
                               l1: _Layer1ToTokens, vt0h: str) -> tuple[str, list[_Keys2]]:
    """Layer 1's image-to-token attention and keys2 per slice (`_image_stream_stats`), and
    TwoWayTransformer's final attention of the output tokens 0..4 to keys2 held factored, then
    norm_final_attn -> (B, 5, C), and keys2's factors per slice."""
    w, d = g.w, g.d
    F = "final"
    vt1h = g.split_heads(l1.vt1, [0, 2, 1, 3])                                         # (B, H, T, D)
    n0 = g.blockdiag(vt0h, d.wn0)                                                      # (B, HT, C)
    m1 = g.blockdiag(vt1h, d.wo1)                                                      # (B, HT, C)
    grams = _Grams.of(g, vt0h, vt1h, n0, m1)
    qf = g.q_heads(g.slice(g.add(queries, tokens), [0], [N_OUT], [1]), F + ".q_proj")   # (B, H, 5, D)
    # (keys2 + pe) @ Wk + bk = r2 * (r1 * (SKf + a0c @ rkf0) + a1c @ rkf1 + kf_beta) + kf_const
    g2wk = d.g2[:, None] * w[F + ".k_proj.w"]
    g2wv = d.g2[:, None] * w[F + ".v_proj.w"]
    qf_rkf0 = g.q_through(qf, g.split_heads(g.mm(n0, g.const(g2wk)), [0, 2, 3, 1]))   # (B, H*5, HT)
    qf_rkf1 = g.q_through(qf, g.split_heads(g.mm(m1, g.const(g2wk)), [0, 2, 3, 1]))
    qf_kf_beta = g.mm(qf, g.const((d.beta @ g2wk).reshape(H, D, 1)))                  # (B, H, 5, 1)
    kf_const = (d.pe + w["layers.1.norm4.b"][None]) @ w[F + ".k_proj.w"] + w[F + ".k_proj.b"]   # (P, 128)
    # values: pf @ (keys2 @ Wv + bv) = pf_r2r1 @ SVf + (pf_r2r1 @ a0c) @ rvf0 + (pf_r2 @ a1c) @ rvf1
    #                                  + sum(pf_r2) vf_beta + vf_const
    sm, keys2 = _PixelSoftmax(g), []
    for sl, k1 in zip(g.slices, keys1):
        n = sl.n
        k2 = _image_stream_stats(g, sl, k1, l1.attention(g, sl, k1), grams)
        keys2.append(k2)
        r1_row, r2_row = g.r_row(k1.r1, n), g.r_row(k2.r2, n)
        qf_a0 = g.through_attention(qf_rkf0, k1.a0cT, n, N_OUT)                        # (B, H, 5, n)
        qf_a1 = g.through_attention(qf_rkf1, k2.a1cT, n, N_OUT)
        inner = g.add(g.add(g.mul(r1_row, g.add(g.mm(qf, sl.img("SKfT")), qf_a0)), qf_a1), qf_kf_beta)
        e, m = sm.weights(g.add(g.mul(r2_row, inner), g.mm(qf, sl.const_T(kf_const))))   # (B, H, 5, n)
        e_r2 = g.mul(e, r2_row)
        e_r2r1 = g.mul(e_r2, r1_row)
        sm.add(e, m, [g.mm(e_r2r1, sl.img("SVf")), g.attention_through(e_r2r1, k1.a0cT, n, N_OUT),
                      g.attention_through(e_r2, k2.a1cT, n, N_OUT), g.reduce_sum(e_r2, [-1])])
    pf_sv, pf_a0, pf_a1, pf_sum = sm.combine()
    rvf0 = g.split_heads(g.mm(n0, g.const(g2wv)), [0, 2, 1, 3])                       # (B, H, HT, D)
    rvf1 = g.split_heads(g.mm(m1, g.const(g2wv)), [0, 2, 1, 3])
    vf_beta = (d.beta @ g2wv).reshape(H, 1, D)
    vf_const = (w["layers.1.norm4.b"] @ w[F + ".v_proj.w"] + w[F + ".v_proj.b"]).reshape(H, 1, D)
    of = g.add(g.add(pf_sv, g.mm(pf_a0, rvf0)), g.mm(pf_a1, rvf1))
    of = g.add(g.add(of, g.mul(pf_sum, g.const(vf_beta))), g.const(vf_const))         # (B, H, 5, D)
    out = g.slice(queries, [0], [N_OUT], [1])
    return g.ln(g.add(out, g.linear_w(g.merge_heads(of), F + ".out_proj")), "norm_final"), keys2


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
