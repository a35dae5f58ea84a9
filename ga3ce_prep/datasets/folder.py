"""Your own RGB-D recordings: a folder of frames, a K and a CSV of head boxes.

    my_recording/rgb/<name>.jpg|png
    my_recording/depth/<name>.png|npy      same stem as the RGB frame; PNG uint16 millimetres
                                           (0 = invalid) or .npy float metres (0/NaN = invalid);
                                           depth_scale: metres per stored unit, for both
    my_recording/intrinsics.json           {"fx": .., "fy": .., "cx": .., "cy": ..} or {"K": [[..]]}
    my_recording/heads.csv                 name,x1,y1,x2,y2 [,split] [,scene]
                                           [,eye_X,eye_Y,eye_Z] [,gaze_X,gaze_Y,gaze_Z]

One CSV row per person and frame (`name` is the RGB file's stem); boxes in pixels; optional 3D
eye and gaze target in metres, camera frame (x right, y down, z forward). Without a `split` column
every frame is "test"; without `scene`, the scene is the folder name. A frame with several people
has one row each; their ids are "<name>/<k>".
"""
from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import DatasetFormatError
from ..frames import SPLITS, FrameRef
from ..units import units_name
from .base import (
    BOXES_XYXY,
    DatasetAdapter,
    check_boxes,
    check_depth_units,
    check_distances,
    check_intrinsics,
    check_option,
    check_rows,
    image_size,
    read_csv_columns,
)

LAYOUT = "\n".join(line for line in __doc__.splitlines() if line.startswith("    "))
REQUIRED = ("name", "x1", "y1", "x2", "y2")
DEFAULT_DEPTH_SCALE = {".png": 0.001, ".npy": 1.0}  # metres per stored unit by file type


def read_intrinsics_json(path: Path) -> np.ndarray:
    """K (3, 3) from {"fx", "fy", "cx", "cy"} or {"K": 3x3}."""
    try:
        d = json.loads(path.read_text())
        K = np.asarray(d["K"], np.float64) if "K" in d else np.array(
            [[d["fx"], 0, d["cx"]], [0, d["fy"], d["cy"]], [0, 0, 1]], np.float64)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DatasetFormatError(f"{path}: cannot read intrinsics ({e!r}); expected "
                                 '{"fx": .., "fy": .., "cx": .., "cy": ..} or {"K": [[..], [..], [..]]}') from e
    return check_intrinsics(K, path)


class FolderAdapter(DatasetAdapter):
    """A user's RGB-D folder (layout in the module docstring)."""

    name = "folder"
    layout = LAYOUT

    def __init__(self, root: str | Path, depth_scale: float | None = None):
        super().__init__(root)
        check_option("depth_scale", depth_scale, depth_scale is None or (
            isinstance(depth_scale, (int, float)) and not isinstance(depth_scale, bool) and depth_scale > 0),
            "a positive number (metres per stored unit) or null")
        self.K = read_intrinsics_json(self.require("intrinsics.json", "camera intrinsics"))
        self.require("rgb", "RGB frames")
        self.csv = self.require("heads.csv", "head boxes")
        self.depth_scale = depth_scale
        t = self._table = read_csv_columns(self.csv, REQUIRED)
        check_rows([t])
        bad = sorted({s for s in t.cols.get("split", []) if s not in SPLITS})
        if bad:
            raise DatasetFormatError(f"{self.csv}: split values {bad} are not among {list(SPLITS)}")
        numeric = [c for c in t.cols if c not in ("name", "split", "scene")]
        self._f = f = {c: t.floats(c) for c in numeric}
        boxes = np.stack([f[c] for c in REQUIRED[1:]], 1)
        t.check_unique([f"{n} {b.tolist()}" for n, b in zip(t.cols["name"], boxes)], "frame and head box")
        check_boxes(boxes, t, ", ".join(REQUIRED[1:]))
        if "eye_Z" in f:
            check_distances(f["eye_Z"], f"{self.csv} eye_Z", "the columns eye_X..gaze_Z to metres", "eye distance")
        self._rgb = {p.stem: p for p in sorted((self.root / "rgb").iterdir())
                     if p.suffix.lower() in (".jpg", ".jpeg", ".png")}
        depth_dir = self.root / "depth"
        self._depth = ({p.stem: p for p in sorted(depth_dir.iterdir()) if p.suffix.lower() in DEFAULT_DEPTH_SCALE}
                       if depth_dir.is_dir() else {})
        suffixes = sorted({p.suffix.lower() for p in self._depth.values()})
        # a frame without its depth file: the path it should have (the usual suffix), to fail on that frame
        self._depth_suffix = max(suffixes, key=lambda x: sum(p.suffix.lower() == x for p in self._depth.values()),
                                 default=None)
        for suffix in suffixes:
            scale = self._scale(suffix)
            check_depth_units([p for p in self._depth.values() if p.suffix.lower() == suffix], scale,
                              f"dataset.options.depth_scale (metres per stored unit, now {scale:g}; "
                              "0.001 for millimetres, 0.01 for centimetres)")
        self.units = {"depth": {sfx: units_name(self._scale(sfx)) for sfx in suffixes}, "eye_gaze_xyz": "m",
                      "boxes": BOXES_XYXY,
                      "decided_by": "the files' type" if depth_scale is None else f"depth_scale: {depth_scale:g}"}

    def _scale(self, suffix: str) -> float:
        """Metres per stored depth unit for a depth file of this type."""
        return self.depth_scale if self.depth_scale is not None else DEFAULT_DEPTH_SCALE[suffix]

    def _vec(self, f: dict[str, np.ndarray], prefix: str, i: int) -> np.ndarray:
        names = [f"{prefix}_{a}" for a in "XYZ"]
        if all(n in f for n in names):
            return np.array([f[n][i] for n in names], np.float32)
        return np.full(3, np.nan, np.float32)

    def frames(self) -> Iterator[FrameRef]:
        t, f = self._table, self._f
        counts = Counter(t.cols["name"])
        seen: Counter[str] = Counter()
        for i in range(len(t)):
            name = t.cols["name"][i]
            rgb = self._rgb.get(name, self.root / "rgb" / f"{name}.jpg")  # a missing file fails per frame
            depth = self._depth.get(name) or (self.root / "depth" / f"{name}{self._depth_suffix}"
                                              if self._depth_suffix else None)
            fid = name if counts[name] == 1 else f"{name}/{seen[name]}"
            seen[name] += 1
            eye, target = self._vec(f, "eye", i), self._vec(f, "gaze", i)
            d = target - eye
            n = float(np.linalg.norm(d)) if np.isfinite(d).all() else 0.0
            yield FrameRef(
                id=fid, split=t.cols["split"][i] if "split" in t.cols else "test",
                scene=t.cols["scene"][i] if "scene" in t.cols else self.root.name,
                image_path=rgb, K=self.K, image_size=image_size(rgb) or (0, 0),
                head_box=np.array([f["x1"][i], f["y1"][i], f["x2"][i], f["y2"][i]], np.float32),
                depth_path=depth, depth_scale=self._scale(depth.suffix.lower()) if depth is not None else 1.0,
                eye=eye, gaze_target=target,
                gaze=(d / n).astype(np.float32) if n > 0 else np.full(3, np.nan, np.float32),
                sequence=self.root.name, index=i, annotation=t.where(i),
            )
