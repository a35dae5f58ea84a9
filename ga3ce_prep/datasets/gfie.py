"""GFIE (nkuhzx/GFIE): layout and annotation columns as its `README.md` and `dataset/gfie.py` read them.

The 3D annotations (eye_X.., gaze_X..) share the depth maps' units. The repository never states
them (probably metres); `units="auto"` reads the first depth maps and the annotated eye distances
and takes, for each, the one unit (m, cm or mm) in which the median is a room-scale distance,
refusing when none or several fit (then say `units`); an explicit unit is checked the same way.
The ground-truth gaze (`FrameRef.gaze`) is normalise(gaze_XYZ - eye_XYZ), NaN where the two
points coincide or are missing.
"""
from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from ..errors import DatasetFormatError
from ..frames import FrameRef
from ..units import LENGTH_UNITS, METRES_PER_UNIT
from .base import (
    BOXES_XYXY,
    DatasetAdapter,
    check_boxes,
    check_option,
    check_rows,
    decide_units,
    first_depth_values,
    first_image_size,
    gaze_direction,
    intrinsics_from_fxfycxcy,
    one_of,
    read_csv_columns,
)

log = logging.getLogger("ga3ce_prep.datasets")

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
SPLIT_FOLDERS: dict[str, str] = {"train": "train", "valid": "val", "test": "test"}  # folder -> split
# Columns the adapter reads (by name; other columns are ignored). Boxes and 2D points in pixels.
COLUMNS: tuple[str, ...] = (
    "scene_id", "frame_id", "h_x_min", "h_y_min", "h_x_max", "h_y_max", "eye_u", "eye_v",
    "eye_X", "eye_Y", "eye_Z", "gaze_u", "gaze_v", "gaze_X", "gaze_Y", "gaze_Z",
)
BOX_COLUMNS: tuple[str, ...] = ("h_x_min", "h_y_min", "h_x_max", "h_y_max")
LAYOUT = """    GFIE_dataset/rgb/{train,valid,test}/scene<N>/<frame:04d>.jpg
    GFIE_dataset/depth/{train,valid,test}/scene<N>/<frame:04d>.npy   float, NaN holes, metres (units: auto)
    GFIE_dataset/CameraKinect.npy                                      [fx, fy, cx, cy]
    GFIE_dataset/{train,valid,test}_annotation.txt                    CSV with a header"""


def frame_id(split_folder: str, scene_id: int, frame: int) -> str:
    """Stable frame id, e.g. "train/scene3/0012" (scene numbers are namespaced by split folder)."""
    return f"{split_folder}/scene{int(scene_id)}/{int(frame):04d}"


class GFIEAdapter(DatasetAdapter):
    """GFIE: one CSV per split, one K for the dataset, float .npy depth with NaN holes."""

    name = "gfie"
    layout = LAYOUT

    def __init__(self, root: str | Path, units: str = "auto", splits: Sequence[str] = ("train", "valid", "test")):
        super().__init__(root)
        one_of("units", units, ("auto", *LENGTH_UNITS))
        check_option("splits", splits,
                     isinstance(splits, (list, tuple))
                     and all(isinstance(s, str) and s in SPLIT_FOLDERS for s in splits),
                     f"a list of {', '.join(SPLIT_FOLDERS)}")
        self.K = intrinsics_from_fxfycxcy(self.require("CameraKinect.npy", "camera intrinsics"))
        self.require("rgb", "RGB frames")
        self.require("depth", "depth maps")
        self.annotations = {s: self.root / f"{s}_annotation.txt" for s in splits
                            if (self.root / f"{s}_annotation.txt").is_file()}
        if not self.annotations:
            raise DatasetFormatError(f"gfie: no {{train,valid,test}}_annotation.txt in {self.root}. "
                                     f"Expected layout:\n{LAYOUT}")
        self._tables = {s: read_csv_columns(p, COLUMNS) for s, p in self.annotations.items()}
        check_rows(list(self._tables.values()))
        for folder, t in self._tables.items():
            if not len(t):
                self._warn_empty_split(folder, t.path)
        self._values = {s: {c: t.floats(c) for c in COLUMNS} for s, t in self._tables.items()}
        for folder, t in self._tables.items():
            f = self._values[folder]
            t.check_unique([frame_id(folder, s, n) for s, n in zip(f["scene_id"], f["frame_id"])], "frame")
            check_boxes(np.stack([f[c] for c in BOX_COLUMNS], 1), t, ", ".join(BOX_COLUMNS))
        fix = "dataset.options.units"
        depth = first_depth_values([self._depth_path(folder, s, n) for folder, f in self._values.items()
                                    for s, n in list(zip(f["scene_id"], f["frame_id"]))[:5]])
        depth_units = (decide_units(depth[0], units, f"GFIE depth {depth[1]} (and the next maps)", fix, "depth")
                       if depth is not None else "m" if units == "auto" else units)
        eye_z = np.concatenate([f["eye_Z"] for f in self._values.values()])
        xyz_units = (decide_units(np.abs(eye_z), units,
                                  f"GFIE eye_Z in {', '.join(map(str, self.annotations.values()))}",
                                  fix, "eye distance")
                     if np.isfinite(eye_z).any() else "m" if units == "auto" else units)
        self.units = {"depth": depth_units, "eye_gaze_xyz": xyz_units, "boxes": BOXES_XYXY,
                      "decided_by": "the data (units: auto)" if units == "auto" else f"units: {units}"}

    def _warn_empty_split(self, folder: str, annotation: Path) -> None:
        """Warn when a split's annotation file has a header and no rows while rgb/<folder>/ holds
        images: the split is empty, which is rarely what the images mean."""
        images = self.root / "rgb" / folder
        n = sum(1 for p in images.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES) if images.is_dir() else 0
        if n:
            log.warning("gfie: %s has a header and no rows, but %s holds %d images: the %s split is empty; write "
                        "its rows, or leave it out with dataset.options.splits", annotation, images, n,
                        SPLIT_FOLDERS[folder])

    def _depth_path(self, folder: str, scene_id: float, frame: float) -> Path:
        return self.root / "depth" / folder / f"scene{int(scene_id)}" / f"{int(frame):04d}.npy"

    def frames(self) -> Iterator[FrameRef]:
        depth_scale = METRES_PER_UNIT[self.units["depth"]]
        xyz_scale = METRES_PER_UNIT[self.units["eye_gaze_xyz"]]
        for folder, t in self._tables.items():
            f = self._values[folder]
            scene_ids = f["scene_id"].astype(np.int64)
            frame_nums = f["frame_id"].astype(np.int64)
            sizes: dict[int, tuple[int, int]] = {}
            eye = np.stack([f["eye_X"], f["eye_Y"], f["eye_Z"]], 1) * xyz_scale
            target = np.stack([f["gaze_X"], f["gaze_Y"], f["gaze_Z"]], 1) * xyz_scale
            gaze = gaze_direction(eye, target)
            for i in range(len(t)):
                sid, fnum = int(scene_ids[i]), int(frame_nums[i])
                rgb = self.root / "rgb" / folder / f"scene{sid}" / f"{fnum:04d}.jpg"
                if sid not in sizes:
                    sizes[sid] = first_image_size([rgb, *sorted(rgb.parent.glob("*.jpg"))[:3]])
                yield FrameRef(
                    id=frame_id(folder, sid, fnum), split=SPLIT_FOLDERS[folder], scene=f"{folder}/scene{sid}",
                    image_path=rgb, K=self.K, image_size=sizes[sid],
                    head_box=np.array([f[c][i] for c in BOX_COLUMNS], np.float32),
                    depth_path=self._depth_path(folder, sid, fnum), depth_scale=depth_scale,
                    eye=eye[i].astype(np.float32), gaze_target=target[i].astype(np.float32),
                    gaze=gaze[i].astype(np.float32),
                    gaze_2d=np.array([f["gaze_u"][i], f["gaze_v"][i]], np.float32),
                    sequence=f"{folder}/scene{sid}", index=fnum, annotation=t.where(i),
                )
