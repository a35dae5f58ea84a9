"""The adapter contract and the helpers every adapter shares (CSV columns, intrinsics, image sizes)."""
from __future__ import annotations

import csv
import logging
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import DatasetFormatError
from ..frames import FrameRef

log = logging.getLogger("ga3ce_prep.datasets")


class DatasetAdapter(ABC):
    """Reads one dataset format. `frames()` yields FrameRefs in a stable order (same dataset, same
    order and ids); structural problems raise DatasetFormatError when the adapter is built."""

    name: str = ""
    layout: str = ""  # the expected on-disk layout, shown in structural errors

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetFormatError(f"dataset root {self.root} is not a directory")

    @abstractmethod
    def frames(self) -> Iterator[FrameRef]:
        """All frames of the dataset, every split."""

    def __iter__(self) -> Iterator[FrameRef]:
        return self.frames()

    def require(self, rel: str, what: str) -> Path:
        """root/rel, or DatasetFormatError saying what is missing and what the layout should be."""
        p = self.root / rel
        if not p.exists():
            raise DatasetFormatError(f"{self.name}: {p} not found ({what}). Expected layout:\n{self.layout}")
        return p


def read_csv_columns(path: Path, required: Sequence[str]) -> tuple[dict[str, list[str]], int]:
    """Read a CSV with a header into columns (by name). Raises DatasetFormatError naming the file
    and the missing columns. Returns (columns, number of rows)."""
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            header = [h.strip() for h in next(reader, [])]
            rows = [r for r in reader if any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetFormatError(f"cannot read annotation file {path}: {e}") from e
    missing = [c for c in required if c not in header]
    if missing:
        raise DatasetFormatError(
            f"{path}: missing column(s) {missing}; found {header}. The file must be a CSV with a "
            f"header naming at least {list(required)}")
    cols: dict[str, list[str]] = {h: [] for h in header}
    for lineno, r in enumerate(rows, start=2):
        if len(r) != len(header):
            raise DatasetFormatError(f"{path}:{lineno}: {len(r)} fields, the header has {len(header)}")
        for h, c in zip(header, r):
            cols[h].append(c.strip())
    return cols, len(rows)


def float_column(cols: dict[str, list[str]], name: str, path: Path) -> np.ndarray:
    """A column as float64; empty cells become NaN; anything else unparsable names file and line."""
    out = np.empty(len(cols[name]), np.float64)
    for i, c in enumerate(cols[name]):
        try:
            out[i] = float(c) if c != "" else np.nan
        except ValueError:
            raise DatasetFormatError(f"{path}:{i + 2}: column {name!r} has {c!r}, not a number") from None
    return out


def gaze_direction(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(N, 3) float64 unit ground-truth gaze normalise(target - eye) (GFIE's definition) from (N, 3)
    3D eye and target points; NaN where they coincide or are unknown."""
    d = target - eye
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, d / norm, np.nan)


def intrinsics_from_fxfycxcy(path: Path) -> np.ndarray:
    """K (3, 3) float64 from a .npy holding [fx, fy, cx, cy] (GFIE's and CAD-120's CameraKinect.npy)."""
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise DatasetFormatError(f"cannot read intrinsics {path}: {e}") from e
    a = np.asarray(a, np.float64).ravel()
    if a.shape != (4,):
        raise DatasetFormatError(f"{path}: expected 4 values [fx, fy, cx, cy], found shape {a.shape}")
    fx, fy, cx, cy = a
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)


def image_size(path: Path) -> tuple[int, int] | None:
    """(W, H) of an image from its header only, or None if it cannot be read."""
    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, SyntaxError, ValueError):
        return None


def first_image_size(paths: Sequence[Path]) -> tuple[int, int]:
    """(W, H) of the first readable image among paths (a sequence shares one size), else (0, 0)."""
    for p in paths:
        s = image_size(p)
        if s is not None:
            return s
    return (0, 0)
