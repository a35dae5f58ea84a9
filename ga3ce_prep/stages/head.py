"""The head stage: t_object, the head box centre back-projected at the median measured depth of a
small window (`geometry.head_position`). No measured depth near the head (or a head box outside
the image) raises FrameError, which drops the frame."""
from __future__ import annotations

import numpy as np

from ..frames import FrameRef
from ..geometry import head_position
from .base import DepthMap, HeadBackend


class DepthHead(HeadBackend):
    """t_object from the depth map: windows of `window_fracs` x the box's shorter side around the
    box centre, tried in order until one holds `min_points` measured pixels."""

    name = "depth"

    def head(self, frame: FrameRef, depth: DepthMap) -> np.ndarray:
        return head_position(depth.depth, frame.K, frame.head_box, valid=depth.valid,
                             window_fracs=tuple(self.params["window_fracs"]),
                             min_points=int(self.params["min_points"]))
