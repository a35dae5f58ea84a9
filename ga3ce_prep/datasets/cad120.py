"""CAD-120 gaze evaluation set (nkuhzx/GFIE's CAD-120 release): research/gfie.md §1.2.

    CAD120_dataset/rgb/<dataset_id>/RGB_<n>.png      n not zero-padded
    CAD120_dataset/depth/<dataset_id>/Depth_<n>.png  uint16 millimetres, 0 = invalid
    CAD120_dataset/CameraKinect.npy                  [fx, fy, cx, cy]
    CAD120_dataset/annotation.txt                    CSV with a header; boxes and 2D gaze normalised
"""
from __future__ import annotations

COLUMNS: tuple[str, ...] = (
    "dataset_id", "frame_index", "x_initial", "y_initial", "w", "h", "eye_x", "eye_y",
    "eye_X", "eye_Y", "eye_Z", "gaze_x", "gaze_y", "gaze_X", "gaze_Y", "gaze_Z",
)
DEPTH_SCALE = 0.001  # PNG millimetres -> metres


def frame_id(dataset_id: str, frame_index: int) -> str:
    """Stable frame id, e.g. "D1S1A001/17"."""
    return f"{dataset_id}/{int(frame_index)}"
