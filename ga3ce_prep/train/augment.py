"""GA3CE's training augmentations.

view_noise (the paper's GFIE recipe): v_noise = normalise(v + eps), eps ~ U[-a, a]^3 (a = 0.5
shifts a unit v by about 22 degrees on average).
object_dropout and object_jitter (ours, off by default): regularisers of the object pathway against
memorising rooms from their object layouts, tried in docs/studies/2026-11-29-what-the-objects-add.md.
"""
from __future__ import annotations

import torch


def view_noise(view: torch.Tensor, generator: torch.Generator, amplitude: float = 0.5) -> torch.Tensor:
    """view (B, 3) unit -> (B, 3) unit, perturbed by uniform noise in [-amplitude, amplitude]^3."""
    eps = (torch.rand(view.shape, generator=generator, dtype=view.dtype) * 2.0 - 1.0) * amplitude
    return torch.nn.functional.normalize(view + eps.to(view.device), dim=-1, eps=1e-9)


def object_dropout(mask: torch.Tensor, generator: torch.Generator, p: float, frame_p: float = 0.0) -> torch.Tensor:
    """mask (B, S) bool, True = real object -> (B, S): each real object independently dropped
    (set False, i.e. treated as padding) with probability p, and all objects of a frame with
    probability frame_p (the frame then sees the null token alone); padding stays padding."""
    keep = torch.rand(mask.shape, generator=generator) >= p
    if frame_p > 0:
        keep &= torch.rand(mask.shape[0], 1, generator=generator) >= frame_p
    return mask & keep.to(mask.device)


def object_jitter(objects: torch.Tensor, generator: torch.Generator, sigma: float) -> torch.Tensor:
    """objects (B, S, 3) metres -> (B, S, 3) + N(0, sigma^2) per coordinate (sigma in metres)."""
    eps = torch.randn(objects.shape, generator=generator, dtype=objects.dtype) * sigma
    return objects + eps.to(objects.device)
