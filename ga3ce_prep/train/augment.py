"""GA3CE's view-noise augmentation (GFIE recipe): v_noise = normalise(v + eps), eps ~ U[-a, a]^3
(a = 0.5 shifts a unit v by about 22 degrees on average)."""
from __future__ import annotations

import torch


def view_noise(view: torch.Tensor, generator: torch.Generator, amplitude: float = 0.5) -> torch.Tensor:
    """view (B, 3) unit -> (B, 3) unit, perturbed by uniform noise in [-amplitude, amplitude]^3."""
    eps = (torch.rand(view.shape, generator=generator, dtype=view.dtype) * 2.0 - 1.0) * amplitude
    return torch.nn.functional.normalize(view + eps.to(view.device), dim=-1, eps=1e-9)
