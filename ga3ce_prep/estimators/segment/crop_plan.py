"""The seam through which reuse plugs into the MobileSAM generator: `CropPlan`, the layer around the
generator's steps on one crop (`mobilesam.MobileSamSegmenter._process_crop`), and `EXACT`, the
exact generator's plan. The other plan is reuse.SequenceReuse (reuse across the frames of a static
camera)."""
from __future__ import annotations

from typing import Protocol

import numpy as np

from . import amg
from .prompts import Prompts


class CropPlan(Protocol):
    """A layer around the generator's steps on one crop (`MobileSamSegmenter._process_crop`), called
    in this order: `plan` the prompts to decode, decode them with the filters' thresholds
    lowered by `margin`, `merge` their candidates with the layer's own, NMS, `settle` the winners.
    The exact generator's `EXACT` decodes every prompt and adds nothing; reuse.SequenceReuse reuses
    a key frame's candidates (full-image crop only)."""

    @property
    def step(self) -> str | None:
        """amg.StepTimer step of plan and merge (None: not timed)."""

    def plan(self, embedding: np.ndarray, prompts: Prompts) -> tuple[Prompts, np.ndarray | None]:
        """embedding (1, 256, 64, 64), the crop's prompts (n in its pixels: the grid, or the caller's)
        -> the prompts whose candidates the crop gathers (these, or the layer's own) and (m,) bool
        those to decode, None for all."""

    @property
    def margin(self) -> float:
        """Lower the IoU and stability thresholds by this when decoding the planned prompts."""

    def merge(self, decoded: amg.MaskRecords, options: amg.AmgOptions) -> amg.MaskRecords:
        """The planned prompts' candidates, in prompt order -> the crop's candidates before NMS."""

    def settle(self, keep: np.ndarray) -> None:
        """keep: the rows of `merge`'s result that won the crop's NMS, in NMS order."""


class _Exact:
    """The exact generator's CropPlan: every prompt, the filters' own thresholds, nothing merged."""

    step = None
    margin = 0.0

    def plan(self, embedding: np.ndarray, prompts: Prompts) -> tuple[Prompts, None]:
        return prompts, None

    def merge(self, decoded: amg.MaskRecords, options: amg.AmgOptions) -> amg.MaskRecords:
        return decoded

    def settle(self, keep: np.ndarray) -> None:
        pass


EXACT: CropPlan = _Exact()
