"""GFIE (nkuhzx/GFIE): layout and annotation columns as its `README.md` and `dataset/gfie.py` read them.

The 3D annotations (eye_X.., gaze_X..) share the depth maps' units. The repository never states
them (probably metres); `units="auto"` checks the first depth map and the annotations and converts
millimetres to metres if that is what they hold. The ground-truth gaze (`FrameRef.gaze`) is
normalise(gaze_XYZ - eye_XYZ), NaN where the two points coincide or are missing.
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import DatasetFormatError
from ..frames import FrameRef
from .base import (DatasetAdapter, first_image_size, float_column, gaze_direction, intrinsics_from_fxfycxcy,
                   log, read_csv_columns)

SPLIT_FOLDERS: dict[str, str] = {"train": "train", "valid": "val", "test": "test"}  # folder -> split
# Columns the adapter reads (by name; other columns are ignored). Boxes and 2D points in pixels.
COLUMNS: tuple[str, ...] = (
    "scene_id", "frame_id", "h_x_min", "h_y_min", "h_x_max", "h_y_max", "eye_u", "eye_v",
    "eye_X", "eye_Y", "eye_Z", "gaze_u", "gaze_v", "gaze_X", "gaze_Y", "gaze_Z",
)
LAYOUT = """    GFIE_dataset/rgb/{train,valid,test}/scene<N>/<frame:04d>.jpg
    GFIE_dataset/depth/{train,valid,test}/scene<N>/<frame:04d>.npy   float, NaN holes, metres
    GFIE_dataset/CameraKinect.npy                                      [fx, fy, cx, cy]
    GFIE_dataset/{train,valid,test}_annotation.txt                    CSV with a header"""


def frame_id(split_folder: str, scene_id: int, frame: int) -> str:
    """Stable frame id, e.g. "train/scene3/0012" (scene numbers are namespaced by split folder)."""
    return f"{split_folder}/scene{int(scene_id)}/{int(frame):04d}"


def _unit_scale(values: np.ndarray, what: str, units: str) -> float:
    """1.0 for metres, 0.001 for millimetres; "auto" decides from the median magnitude."""
    if units == "m":
        return 1.0
    if units == "mm":
        return 0.001
    med = float(np.nanmedian(np.abs(values))) if np.isfinite(values).any() else np.nan
    if np.isfinite(med) and med > 50.0:
        log.warning("GFIE %s: median %.0f looks like millimetres; converting to metres "
                    "(pass units='m' or 'mm' to decide yourself)", what, med)
        return 0.001
    return 1.0


class GFIEAdapter(DatasetAdapter):
    """GFIE: one CSV per split, one K for the dataset, float .npy depth with NaN holes."""

    name = "gfie"
    layout = LAYOUT

    def __init__(self, root: str | Path, units: str = "auto", splits: tuple[str, ...] = ("train", "valid", "test")):
        super().__init__(root)
        if units not in ("auto", "m", "mm"):
            raise ValueError(f"units must be auto, m or mm, not {units!r}")
        self.units = units
        self.K = intrinsics_from_fxfycxcy(self.require("CameraKinect.npy", "camera intrinsics"))
        self.require("rgb", "RGB frames")
        self.require("depth", "depth maps")
        self.annotations = {s: self.root / f"{s}_annotation.txt" for s in splits
                            if (self.root / f"{s}_annotation.txt").is_file()}
        if not self.annotations:
            raise DatasetFormatError(f"gfie: no {{train,valid,test}}_annotation.txt in {self.root}. "
                                     f"Expected layout:\n{LAYOUT}")
        self._tables = {s: read_csv_columns(p, COLUMNS) for s, p in self.annotations.items()}

    def _depth_scale(self) -> float:
        """Metres per stored depth unit, checked on the first readable depth maps when units=auto."""
        if self.units != "auto":
            return _unit_scale(np.array([]), "depth", self.units)
        for folder, (cols, n) in self._tables.items():
            for sid, fnum in list(zip(cols["scene_id"], cols["frame_id"]))[:5]:
                path = self.root / "depth" / folder / f"scene{int(float(sid))}" / f"{int(float(fnum)):04d}.npy"
                try:
                    d = np.load(path, allow_pickle=False)
                except (OSError, ValueError):
                    continue
                d = d[np.isfinite(d) & (d > 0)]
                if d.size:
                    return _unit_scale(d, f"depth ({path})", "auto")
        return 1.0

    def frames(self) -> Iterator[FrameRef]:
        depth_scale = self._depth_scale()
        for folder, (cols, n) in self._tables.items():
            path = self.annotations[folder]
            f = {c: float_column(cols, c, path) for c in COLUMNS}
            xyz_scale = _unit_scale(np.concatenate([f["eye_Z"], f["gaze_Z"]]), f"{path.name} 3D", self.units)
            scene_ids = f["scene_id"].astype(np.int64)
            frame_nums = f["frame_id"].astype(np.int64)
            sizes: dict[int, tuple[int, int]] = {}
            eye = np.stack([f["eye_X"], f["eye_Y"], f["eye_Z"]], 1) * xyz_scale
            target = np.stack([f["gaze_X"], f["gaze_Y"], f["gaze_Z"]], 1) * xyz_scale
            gaze = gaze_direction(eye, target)
            for i in range(n):
                sid, fnum = int(scene_ids[i]), int(frame_nums[i])
                rgb = self.root / "rgb" / folder / f"scene{sid}" / f"{fnum:04d}.jpg"
                if sid not in sizes:
                    sizes[sid] = first_image_size([rgb, *sorted(rgb.parent.glob("*.jpg"))[:3]])
                yield FrameRef(
                    id=frame_id(folder, sid, fnum), split=SPLIT_FOLDERS[folder], scene=f"{folder}/scene{sid}",
                    image_path=rgb, K=self.K, image_size=sizes[sid],
                    head_box=np.array([f["h_x_min"][i], f["h_y_min"][i], f["h_x_max"][i], f["h_y_max"][i]], np.float32),
                    depth_path=self.root / "depth" / folder / f"scene{sid}" / f"{fnum:04d}.npy",
                    depth_scale=depth_scale,
                    eye=eye[i].astype(np.float32), gaze_target=target[i].astype(np.float32),
                    gaze=gaze[i].astype(np.float32),
                    gaze_2d=np.array([f["gaze_u"][i], f["gaze_v"][i]], np.float32),
                    sequence=f"{folder}/scene{sid}", index=fnum,
                )
