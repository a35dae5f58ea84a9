"""The learning-rate schedule of the recipe: linear warm-up, then cosine decay to 0, per step."""
from __future__ import annotations

import math


def warmup_cosine_lr(step: int, total_steps: int, warmup_steps: int, base_lr: float) -> float:
    """Learning rate of optimiser step `step` (0-based): base_lr * (step + 1) / warmup_steps during
    the warm-up, then base_lr * (1 + cos(pi * t)) / 2 with t going from 0 to 1 over the rest."""
    if step < warmup_steps:
        return base_lr * (step + 1) / warmup_steps
    t = (step - warmup_steps) / max(1, total_steps - warmup_steps)
    return base_lr * 0.5 * (1.0 + math.cos(math.pi * min(t, 1.0)))
