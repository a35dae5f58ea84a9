"""Your own RGB-D recordings: a folder of frames, a K and a CSV of head boxes.

    my_recording/rgb/<name>.jpg|png
    my_recording/depth/<name>.png|npy      same stem as the RGB frame; PNG uint16 millimetres
                                           (0 = invalid) or .npy float metres (0/NaN = invalid)
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
from .base import DatasetAdapter, float_column, image_size, read_csv_columns

LAYOUT = "\n".join(line for line in __doc__.splitlines() if line.startswith("    "))
REQUIRED = ("name", "x1", "y1", "x2", "y2")


def read_intrinsics_json(path: Path) -> np.ndarray:
    """K (3, 3) from {"fx", "fy", "cx", "cy"} or {"K": 3x3}."""
    try:
        d = json.loads(path.read_text())
        K = np.asarray(d["K"], np.float64) if "K" in d else np.array(
            [[d["fx"], 0, d["cx"]], [0, d["fy"], d["cy"]], [0, 0, 1]], np.float64)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DatasetFormatError(f"{path}: cannot read intrinsics ({e!r}); expected "
                                 '{"fx": .., "fy": .., "cx": .., "cy": ..} or {"K": [[..], [..], [..]]}') from e
    if K.shape != (3, 3):
        raise DatasetFormatError(f"{path}: K has shape {K.shape}, expected (3, 3)")
    return K


class FolderAdapter(DatasetAdapter):
    """A user's RGB-D folder (layout in the module docstring)."""

    name = "folder"
    layout = LAYOUT

    def __init__(self, root: str | Path, depth_scale: float | None = None):
        super().__init__(root)
        self.K = read_intrinsics_json(self.require("intrinsics.json", "camera intrinsics"))
        self.require("rgb", "RGB frames")
        self.csv = self.require("heads.csv", "head boxes")
        self.depth_scale = depth_scale
        self._cols, self._n = read_csv_columns(self.csv, REQUIRED)
        bad = sorted({s for s in self._cols.get("split", []) if s not in SPLITS})
        if bad:
            raise DatasetFormatError(f"{self.csv}: split values {bad} are not among {list(SPLITS)}")
        self._rgb = {p.stem: p for p in sorted((self.root / "rgb").iterdir()) if p.suffix.lower() in (".jpg", ".jpeg", ".png")}
        depth_dir = self.root / "depth"
        self._depth = ({p.stem: p for p in sorted(depth_dir.iterdir()) if p.suffix.lower() in (".png", ".npy")}
                       if depth_dir.is_dir() else {})

    def _vec(self, f: dict[str, np.ndarray], prefix: str, i: int) -> np.ndarray:
        names = [f"{prefix}_{a}" for a in "XYZ"]
        if all(n in f for n in names):
            return np.array([f[n][i] for n in names], np.float32)
        return np.full(3, np.nan, np.float32)

    def frames(self) -> Iterator[FrameRef]:
        cols, path = self._cols, self.csv
        numeric = [c for c in cols if c not in ("name", "split", "scene")]
        f = {c: float_column(cols, c, path) for c in numeric}
        counts = Counter(cols["name"])
        seen: Counter[str] = Counter()
        for i in range(self._n):
            name = cols["name"][i]
            rgb = self._rgb.get(name, self.root / "rgb" / f"{name}.jpg")  # a missing file fails per frame
            depth = self._depth.get(name)
            scale = self.depth_scale if self.depth_scale is not None else (
                0.001 if depth is not None and depth.suffix.lower() == ".png" else 1.0)
            fid = name if counts[name] == 1 else f"{name}/{seen[name]}"
            seen[name] += 1
            eye, target = self._vec(f, "eye", i), self._vec(f, "gaze", i)
            d = target - eye
            n = float(np.linalg.norm(d)) if np.isfinite(d).all() else 0.0
            yield FrameRef(
                id=fid, split=cols["split"][i] if "split" in cols else "test",
                scene=cols["scene"][i] if "scene" in cols else self.root.name,
                image_path=rgb, K=self.K, image_size=image_size(rgb) or (0, 0),
                head_box=np.array([f["x1"][i], f["y1"][i], f["x2"][i], f["y2"][i]], np.float32),
                depth_path=depth, depth_scale=scale, eye=eye, gaze_target=target,
                gaze=(d / n).astype(np.float32) if n > 0 else np.full(3, np.nan, np.float32),
                sequence=self.root.name, index=i,
            )
