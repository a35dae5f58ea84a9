"""CAD-120 gaze evaluation set (nkuhzx/GFIE's CAD-120 release: `README.md`, `config/cad120evaluation.yaml`).

An evaluation set: every frame is in the "test" split (GA3CE trains on GFIE and tests here).
Boxes and the 2D gaze point are stored normalised to [0, 1]; the adapter converts them to pixels
with each sequence's image size. eye_x/eye_y are never used (their convention is unknown). The
ground-truth gaze is GFIE's normalise(gaze_XYZ - eye_XYZ).
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..frames import SPLITS, FrameRef
from .base import (
    DatasetAdapter,
    check_boxes,
    check_depth_units,
    check_distances,
    check_rows,
    first_image_size,
    gaze_direction,
    intrinsics_from_fxfycxcy,
    one_of,
    read_csv_columns,
)

COLUMNS: tuple[str, ...] = (
    "dataset_id", "frame_index", "x_initial", "y_initial", "w", "h", "eye_x", "eye_y",
    "eye_X", "eye_Y", "eye_Z", "gaze_x", "gaze_y", "gaze_X", "gaze_Y", "gaze_Z",
)
REQUIRED = tuple(c for c in COLUMNS if c not in ("eye_x", "eye_y"))
DEPTH_SCALE = 0.001  # PNG millimetres -> metres
LAYOUT = """    CAD120_dataset/rgb/<dataset_id>/RGB_<n>.png      n not zero-padded
    CAD120_dataset/depth/<dataset_id>/Depth_<n>.png  uint16 millimetres, 0 = invalid
    CAD120_dataset/CameraKinect.npy                  [fx, fy, cx, cy]
    CAD120_dataset/annotation.txt                    CSV with a header; boxes and 2D gaze normalised"""


def frame_id(dataset_id: str, frame_index: int) -> str:
    """Stable frame id, e.g. "D1S1A001/17"."""
    return f"{dataset_id}/{int(frame_index)}"


class CAD120Adapter(DatasetAdapter):
    """CAD-120: one CSV, one K, uint16 millimetre PNG depth."""

    name = "cad120"
    layout = LAYOUT

    def __init__(self, root: str | Path, split: str = "test"):
        super().__init__(root)
        self.split = one_of("split", split, SPLITS)
        self.K = intrinsics_from_fxfycxcy(self.require("CameraKinect.npy", "camera intrinsics"))
        self.require("rgb", "RGB frames")
        self.require("depth", "depth maps")
        self.annotation = self.require("annotation.txt", "annotations")
        t = self._table = read_csv_columns(self.annotation, REQUIRED)
        check_rows([t])
        self._f = f = {c: t.floats(c) for c in REQUIRED if c != "dataset_id"}
        t.check_unique([frame_id(d, n) for d, n in zip(t.cols["dataset_id"], f["frame_index"])], "frame")
        x, y = f["x_initial"], f["y_initial"]
        check_boxes(np.stack([x, y, x + f["w"], y + f["h"]], 1), t, "x_initial, y_initial, w, h", normalised=True)
        check_depth_units([self._depth_path(d, n) for d, n in list(zip(t.cols["dataset_id"], f["frame_index"]))[:5]],
                          DEPTH_SCALE, "the maps' export to uint16 millimetres (CAD-120's depth format)")
        check_distances(f["eye_Z"], f"{self.annotation} eye_Z", "the columns eye_X..gaze_Z to metres (CAD-120's unit)",
                        "eye distance")
        self.units = {"depth": "mm", "eye_gaze_xyz": "m", "boxes": "normalised x, y, w, h (converted to pixels)",
                      "decided_by": "the format"}

    def _depth_path(self, dataset_id: str, n: float) -> Path:
        return self.root / "depth" / dataset_id / f"Depth_{int(n)}.png"

    def frames(self) -> Iterator[FrameRef]:
        t, f = self._table, self._f
        eye = np.stack([f["eye_X"], f["eye_Y"], f["eye_Z"]], 1)
        target = np.stack([f["gaze_X"], f["gaze_Y"], f["gaze_Z"]], 1)
        gaze = gaze_direction(eye, target)
        sizes: dict[str, tuple[int, int]] = {}
        for i in range(len(t)):
            did, n = t.cols["dataset_id"][i], int(f["frame_index"][i])
            rgb = self.root / "rgb" / did / f"RGB_{n}.png"
            if did not in sizes:
                sizes[did] = first_image_size([rgb, *sorted(rgb.parent.glob("RGB_*.png"))[:3]])
            W, H = sizes[did]
            x, y, w, h = f["x_initial"][i], f["y_initial"][i], f["w"][i], f["h"][i]
            yield FrameRef(
                id=frame_id(did, n), split=self.split, scene=did, image_path=rgb, K=self.K,
                image_size=(W, H),
                head_box=(np.array([x, y, x + w, y + h]) * [W, H, W, H]).astype(np.float32),
                depth_path=self._depth_path(did, n), depth_scale=DEPTH_SCALE,
                eye=eye[i].astype(np.float32), gaze_target=target[i].astype(np.float32),
                gaze=gaze[i].astype(np.float32),
                gaze_2d=np.array([f["gaze_x"][i] * W, f["gaze_y"][i] * H], np.float32),
                sequence=did, index=n, annotation=t.where(i),
            )
