"""Positional encodings: Fourier features (Tancik et al. 2020) and GA3CE's D3 encoding.

    gamma(x) = [cos(2 pi x B^T), sin(2 pi x B^T)],  B (m, d) fixed, entries ~ N(0, scale^2)
    D3:        enc(p) = gamma_dir(p / ||p||) ++ gamma_dist(||p||)
    standard:  enc(p) = gamma(p)     (the "no D3" ablation; same width)

The paper does not give the Gaussian scales; they are named parameters (docs/paper.md §2: a unit scale
aliases pose distances of up to ~15 head widths, so distances use small scales). Scales are in
cycles per unit of the encoded quantity: per unit direction component, per head width (pose), per
metre (objects). B is drawn once from a seeded generator and kept as a buffer (saved with the
model), so the encoding is a fixed function of the configuration.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import nn

ENCODINGS: tuple[str, ...] = ("d3", "standard")


def fourier_features(x: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """gamma(x): x (..., d), B (m, d) -> (..., 2m) = [cos(2 pi x B^T), sin(2 pi x B^T)]."""
    proj = (2.0 * math.pi) * (x @ B.T)
    return torch.cat([torch.cos(proj), torch.sin(proj)], dim=-1)


def d3_encoding(p: torch.Tensor, B_dir: torch.Tensor, B_dist: torch.Tensor) -> torch.Tensor:
    """GA3CE's D3 encoding of points p (..., 3): gamma(p / ||p||) ++ gamma(||p||).

    B_dir (m1, 3), B_dist (m2, 1). Returns (..., 2 m1 + 2 m2). A zero point has direction 0.
    """
    dist = torch.linalg.vector_norm(p, dim=-1, keepdim=True)
    direction = p / dist.clamp_min(1e-9)
    return torch.cat([fourier_features(direction, B_dir), fourier_features(dist, B_dist)], dim=-1)


def gaussian_matrix(m: int, d: int, scale: float, generator: torch.Generator) -> torch.Tensor:
    """B (m, d) float32 with entries ~ N(0, scale^2), drawn from `generator`."""
    return torch.randn(m, d, generator=generator, dtype=torch.float64).mul_(scale).float()


class PointEncoding(nn.Module):
    """Encode 3D points of one kind (view, pose joint or object) to `width` features.

    kind "d3": `dir_width` of the width goes to gamma(p/||p||) (scale `dir_scale`), the rest to
    gamma(||p||) (scale `dist_scale`). kind "standard": gamma(p) over the whole width (scale
    `pos_scale`). Widths must be even. forward: (..., 3) -> (..., width).
    """

    if TYPE_CHECKING:  # not at run time: TorchScript cannot read a string annotation
        B_dir: torch.Tensor  # buffers of kind "d3"
        B_dist: torch.Tensor
        B_pos: torch.Tensor  # the buffer of kind "standard"

    def __init__(self, kind: str, width: int, dir_width: int, dir_scale: float, dist_scale: float,
                 pos_scale: float, generator: torch.Generator):
        super().__init__()
        if kind not in ENCODINGS:
            raise ValueError(f"unknown encoding {kind!r}; choose one of {ENCODINGS}")
        if width % 2 or dir_width % 2:
            raise ValueError(f"encoding widths must be even, got {width} and {dir_width}")
        self.kind, self.width = kind, width
        if kind == "d3":
            self.register_buffer("B_dir", gaussian_matrix(dir_width // 2, 3, dir_scale, generator))
            self.register_buffer("B_dist", gaussian_matrix((width - dir_width) // 2, 1, dist_scale, generator))
        else:
            self.register_buffer("B_pos", gaussian_matrix(width // 2, 3, pos_scale, generator))

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        if self.kind == "d3":
            return d3_encoding(p, self.B_dir, self.B_dist)
        return fourier_features(p, self.B_pos)
