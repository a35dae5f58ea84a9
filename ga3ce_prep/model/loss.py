"""GA3CE's training loss: the angle between the predicted and the true gaze direction."""
from __future__ import annotations

import torch

COS_MARGIN = 1e-6  # arccos' derivative is infinite at +-1: keep the cosine strictly inside


def angular_loss(g: torch.Tensor, g_gt: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """arccos(g . g_GT) in radians, the cosine clamped to [-1 + 1e-6, 1 - 1e-6] so the gradient
    is finite everywhere (zero where the clamp is active, e.g. at g = g_GT and g = -g_GT).

    g, g_gt: (B, 3) unit vectors. reduction: "mean" -> scalar, "none" -> (B,).
    """
    cos = (g * g_gt).sum(-1).clamp(-1.0 + COS_MARGIN, 1.0 - COS_MARGIN)
    angle = torch.arccos(cos)
    return angle.mean() if reduction == "mean" else angle
