"""The 3D gaze transformer and the MLP head (docs/paper.md).

An nn.Transformer (d_model 256, 2 heads, feed-forward 512, 3 encoder and 3 decoder layers, PyTorch
defaults otherwise) whose encoder reads the object tokens and whose decoder reads one target
token, the subject embedding E_subject, against the encoded objects. Cross-attention gets an
additive per-object bias, the gaze-cone bias: cos(v, direction of the object from the head).

A learned null object token sits first in the encoder input and is never masked: a frame with no
objects (or the "no objects" ablation) attends to it alone, and no attention row is ever fully
masked (which would give NaN through the softmax).

`GazeTransformer.record_cross_attention()` exposes the decoder's cross-attention weights through
forward hooks that leave every output unchanged.
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn


def gaze_cone_bias(view: torch.Tensor, objects_rel: torch.Tensor, mask: torch.Tensor,
                   n_heads: int, scale: float = 1.0, relative: bool = False) -> torch.Tensor:
    """The cross-attention bias of the decoder's single query over [null token, objects].

    view: (B, 3) unit axis of the cone (the view prior v in the paper). objects_rel: (B, S, 3)
    objects minus the head position (any frame in which `view` is expressed). mask: (B, S) bool,
    True = real object. Returns a float memory_mask (B * n_heads, 1, 1 + S): `scale` * cos(axis,
    object direction) for real objects (the paper), or with `relative` `scale` * (cos - 1), 0 on
    the axis (a von Mises kernel whose sharpness `scale` does not push the null token out); 0 for
    the null token, -inf for padding.
    """
    B, S, _ = objects_rel.shape
    cos = torch.einsum("bsk,bk->bs", nn.functional.normalize(objects_rel, dim=-1, eps=1e-9), view)
    bias = torch.where(mask, scale * (cos - 1.0 if relative else cos), torch.full_like(cos, float("-inf")))
    bias = torch.cat([bias.new_zeros(B, 1), bias], dim=1)             # null token: 0
    return bias.repeat_interleave(n_heads, dim=0)[:, None, :]


class MLPHead(nn.Module):
    """GA3CE's output head: d_model -> hidden -> 3 with ReLU, giving g' in the egocentric frame."""

    def __init__(self, d_model: int = 256, hidden: int = 512):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(d_model, hidden), nn.ReLU(), nn.Linear(hidden, 3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (B, d_model) -> g' (B, 3), unnormalised."""
        return self.net(x)


class GazeTransformer(nn.Module):
    """Encoder over [null token, objects], decoder with E_subject as its only target token.

    forward(subject (B, d), objects (B, S, d), mask (B, S) bool True = real, bias (B*heads, 1, 1+S)
    float or None) -> (B, d), the decoder output for the subject token.
    """

    def __init__(self, d_model: int = 256, n_heads: int = 2, dim_feedforward: int = 512,
                 num_encoder_layers: int = 3, num_decoder_layers: int = 3, dropout: float = 0.1,
                 norm_first: bool = False):
        super().__init__()
        self.n_heads = n_heads
        self.null_token = nn.Parameter(torch.zeros(1, 1, d_model))
        nn.init.normal_(self.null_token, std=0.02)
        self.transformer = nn.Transformer(
            d_model=d_model, nhead=n_heads, num_encoder_layers=num_encoder_layers,
            num_decoder_layers=num_decoder_layers, dim_feedforward=dim_feedforward,
            dropout=dropout, batch_first=True, norm_first=norm_first)
        # plain padded tensors: the prototype nested-tensor path changes nothing but speed and warns
        self.transformer.encoder.use_nested_tensor = False

    @contextmanager
    def record_cross_attention(self) -> Iterator[list[torch.Tensor]]:
        """Record the decoder's cross-attention weights of the forward passes run in the block.

        Yields a list that receives, per decoder layer and forward pass in order, the weights
        (B, heads, 1 + S) of the subject token over [null token, objects] (each row sums to 1,
        padding gets 0). A forward hook on each layer's attention recomputes them from the layer's
        own inputs with torch's attention (need_weights=True) and returns nothing, so the model's
        outputs are unchanged. Eval mode only: in training the recomputation would draw dropout.
        """
        if self.training:
            raise RuntimeError("record_cross_attention needs eval mode (model.eval()): in training "
                               "its recomputation would draw dropout and change the outputs")
        record: list[torch.Tensor] = []

        def hook(module: nn.MultiheadAttention, args: tuple, kwargs: dict, output: tuple) -> None:
            query, key, value = args[:3]
            _, w = module.forward(query, key, value, attn_mask=kwargs.get("attn_mask"),
                                  key_padding_mask=kwargs.get("key_padding_mask"),
                                  need_weights=True, average_attn_weights=False)
            assert w is not None  # need_weights=True
            record.append(w[:, :, 0].detach())                       # (B, heads, 1 query, 1 + S) -> (B, heads, 1 + S)

        handles = [layer.multihead_attn.register_forward_hook(hook, with_kwargs=True)
                   for layer in self.transformer.decoder.layers]
        try:
            yield record
        finally:
            for h in handles:
                h.remove()

    def forward(self, subject: torch.Tensor, objects: torch.Tensor, mask: torch.Tensor,
                bias: torch.Tensor | None) -> torch.Tensor:
        B = subject.shape[0]
        src = torch.cat([self.null_token.expand(B, 1, -1), objects], dim=1)
        pad = torch.cat([mask.new_zeros(B, 1), ~mask], dim=1)           # True = ignore
        if bias is None:  # padding still has to be masked in cross-attention
            bias = torch.zeros(pad.shape, dtype=src.dtype, device=src.device).masked_fill(pad, float("-inf"))
            bias = bias.repeat_interleave(self.n_heads, dim=0)[:, None, :]
        out = self.transformer(src, subject[:, None, :], src_key_padding_mask=pad, memory_mask=bias)
        return out[:, 0]


class ObjectPointer(nn.Module):
    """The pointer output (designs pointer-joint and pointer-frozen; ModelConfig.output "pointer",
    docs/training.md "The output"): g is a convex combination of the first pass's estimate g0 and
    the unit directions u_i of the objects from the head,

        p = softmax(q(E_subject) . k([null token, F_object]) / sqrt(d) + kappa (cos(g0, u_i) - 1)),
        g = normalise(p_null g0 + sum_i p_i u_i).

    Each object's score sees the subject and that object alone (no encoder mixing the room's
    layout into it), so the model can say "g0" or "that object near g0", but cannot learn a room's
    gaze targets by heart from its object layout (which is what the paper's regressing decoder
    did on our worlds).
    """

    def __init__(self, d_model: int = 256):
        super().__init__()
        self.q, self.k = nn.Linear(d_model, d_model), nn.Linear(d_model, d_model)

    def forward(self, query: torch.Tensor, keys: torch.Tensor, axis: torch.Tensor, objects_rel: torch.Tensor,
                bias: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """query (B, d) E_subject, keys (B, 1+S, d) [null token, F_object], axis (B, 3) unit g0,
        objects_rel (B, S, 3) objects minus the head (the frame of `axis`), bias (B, 1+S): the
        gaze-cone bias (-inf = padding). Returns g (B, 3) unit in the frame of `axis`, and p (B, 1+S)."""
        logits = torch.einsum("bd,bsd->bs", self.q(query), self.k(keys)) / keys.shape[-1] ** 0.5 + bias
        p = torch.softmax(logits, dim=-1)
        dirs = torch.cat([axis[:, None], nn.functional.normalize(objects_rel, dim=-1, eps=1e-9)], dim=1)
        return nn.functional.normalize(torch.einsum("bs,bsk->bk", p, dirs), dim=-1, eps=1e-9), p
