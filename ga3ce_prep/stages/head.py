"""The head stage: t_object, the head box centre back-projected at the median measured depth of a
small window (`geometry.head_position`). No measured depth near the head (or a head box outside
the image) raises FrameError, which drops the frame."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..frames import FrameRef
from ..geometry import head_position
from ..params import param
from .base import DepthMap, HeadBackend


class DepthHead(HeadBackend):
    """t_object from the depth map: windows of `window_fracs` x the box's shorter side around the
    box centre, tried in order until one holds `min_points` measured pixels."""

    name = "depth"

    @dataclass(frozen=True, kw_only=True)
    class Params:
        window_fracs: tuple[float, ...] = param((0.2, 0.5, 1.0), minItems=1, items={"exclusiveMinimum": 0})  # window sides as fractions of the box's shorter side, tried in order
        min_points: int = param(3, minimum=1)  # measured pixels a window needs

    def head(self, frame: FrameRef, depth: DepthMap) -> np.ndarray:
        return head_position(depth.depth, frame.K, frame.head_box, valid=depth.valid,
                             window_fracs=self.p.window_fracs, min_points=self.p.min_points)
