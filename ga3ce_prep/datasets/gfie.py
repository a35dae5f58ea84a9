"""GFIE (nkuhzx/GFIE): layout and annotation columns in research/gfie.md §1.1.

    GFIE_dataset/rgb/{train,valid,test}/scene<N>/<frame:04d>.jpg
    GFIE_dataset/depth/{train,valid,test}/scene<N>/<frame:04d>.npy   float, NaN holes, metres
    GFIE_dataset/CameraKinect.npy                                      [fx, fy, cx, cy]
    GFIE_dataset/{train,valid,test}_annotation.txt                    CSV with a header
"""
from __future__ import annotations

SPLIT_FOLDERS: dict[str, str] = {"train": "train", "valid": "val", "test": "test"}  # folder -> split
# Columns the adapter reads (by name; other columns are ignored). Boxes and 2D points in pixels.
COLUMNS: tuple[str, ...] = (
    "scene_id", "frame_id", "h_x_min", "h_y_min", "h_x_max", "h_y_max", "eye_u", "eye_v",
    "eye_X", "eye_Y", "eye_Z", "gaze_u", "gaze_v", "gaze_X", "gaze_Y", "gaze_Z",
)


def frame_id(split_folder: str, scene_id: int, frame: int) -> str:
    """Stable frame id, e.g. "train/scene3/0012" (scene numbers are namespaced by split folder)."""
    return f"{split_folder}/scene{int(scene_id)}/{int(frame):04d}"
