"""The input stage: per-frame checks before any geometry, so a broken frame fails once, early,
with a clear message (and is dropped) instead of giving NaN positions downstream.

Checks: K finite with positive focal lengths; the head box finite, not inverted and not empty; the
image file present and decodable (a full decode, so truncated JPEG/PNG files and headers declaring
huge sizes are caught) at the size the adapter reported.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FrameError
from ..frames import FrameRef, box_fault, load_rgb
from .base import CheckInputBackend


class CheckInput(CheckInputBackend):
    """Per-frame checks of K, the head box and the image file."""

    name = "check"
    version = "2"  # 2: inverted and empty head boxes fail here, with the reason

    @dataclass(frozen=True, kw_only=True)
    class Params:
        decode_image: bool = (
            # decode every image to catch truncated files (about 3 ms per 640x480 JPEG); false: only check it exists
            True)

    def check_frame(self, frame: FrameRef) -> None:
        K = np.asarray(frame.K, np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise FrameError(f"intrinsics K of frame {frame.id} are invalid ({np.asarray(frame.K).tolist()}): "
                             "need a finite 3x3 matrix with fx, fy > 0; check the dataset's intrinsics file")
        fault = box_fault(frame.head_box)
        if fault:
            raise FrameError(f"head box of frame {frame.id} {fault}: a box is x1 < x2, y1 < y2 in pixels; fix "
                             f"{frame.annotation or 'its annotation row'}")
        if self.p.decode_image:
            rgb = load_rgb(frame.image_path)
            H, W = rgb.shape[:2]
            fw, fh = frame.image_size
            if fw and fh and (W, H) != (fw, fh):
                raise FrameError(f"image {frame.image_path} is {W}x{H} but its sequence is {fw}x{fh}; "
                                 "re-export the frame at the sequence's resolution")
        elif not frame.image_path.is_file():
            raise FrameError(f"image file not found: {frame.image_path}")
