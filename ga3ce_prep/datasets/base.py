"""The adapter contract and the checks every adapter shares: annotation CSVs, options, intrinsics,
head boxes, depth units, image sizes.

Dataset-wide faults (a file that cannot be right for any frame: intrinsics NaN or zero, boxes in
another convention, depth or 3D points in another unit, a duplicate row) raise DatasetFormatError
naming the file, the field, the value found and the fix when the adapter is built, before any
work; a fault of one frame is left to the stages, which record it (docs/datasets.md, "What is
checked").
"""
from __future__ import annotations

import csv
import logging
from abc import ABC, abstractmethod
from collections.abc import Hashable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, DatasetFormatError, FrameError
from ..frames import FrameRef, box_fault, depth_type_fault, image_header_size, load_npy, read_depth
from ..units import DISTANCE_RANGE_M, LENGTH_UNITS, METRES_PER_UNIT, check_plausible, infer_units, units_name

log = logging.getLogger("ga3ce_prep.datasets")

BOXES_XYXY = "x1, y1, x2, y2 pixels"


class DatasetAdapter(ABC):
    """Reads one dataset format. `frames()` yields FrameRefs in a stable order (same dataset, same
    order and ids); structural problems raise DatasetFormatError when the adapter is built.
    `units` records the units the adapter read the files in (`provenance()`)."""

    name: str = ""
    layout: str = ""  # the expected on-disk layout, shown in structural errors

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.units: dict[str, Any] = {}
        if not self.root.is_dir():
            raise DatasetFormatError(f"dataset root {self.root} is not a directory")

    @abstractmethod
    def frames(self) -> Iterator[FrameRef]:
        """All frames of the dataset, every split."""

    def __iter__(self) -> Iterator[FrameRef]:
        return self.frames()

    def provenance(self) -> dict[str, Any]:
        """What the store's provenance records about how the dataset was read: the units assumed
        for each quantity (depth, 3D points, boxes) and how they were decided."""
        return {"units": dict(self.units)}

    def require(self, rel: str, what: str) -> Path:
        """root/rel, or DatasetFormatError saying what is missing and what the layout should be."""
        p = self.root / rel
        if not p.exists():
            raise DatasetFormatError(f"{self.name}: {p} not found ({what}). Expected layout:\n{self.layout}")
        return p


def check_option(name: str, value: Any, ok: bool, want: str) -> Any:
    """`value` of dataset option `name` if `ok`; ConfigError naming `dataset.options.<name>`, the
    value and what it may be (`want`) otherwise."""
    if not ok:
        raise ConfigError(f"dataset.options.{name}: {value!r} is not {want}; fix it in the pipeline's dataset.options "
                          "(docs/datasets.md)")
    return value


def one_of(name: str, value: Any, choices: Sequence[Any]) -> Any:
    """`check_option` for an option with a fixed set of values."""
    return check_option(name, value, isinstance(value, Hashable) and value in choices,
                        f"one of {', '.join(map(str, choices))}")


@dataclass
class CsvTable:
    """An annotation CSV read by column name: `cols` name -> the cells (str, stripped) of every row,
    `lines` the file line of each row (for messages)."""

    path: Path
    cols: dict[str, list[str]]
    lines: list[int]

    def __len__(self) -> int:
        return len(self.lines)

    def where(self, i: int) -> str:
        """"<file>:<line>" of row i."""
        return f"{self.path}:{self.lines[i]}"

    def floats(self, name: str) -> np.ndarray:
        """Column `name` as float64; empty cells become NaN; anything else unparsable names file and line."""
        out = np.empty(len(self), np.float64)
        for i, c in enumerate(self.cols[name]):
            try:
                out[i] = float(c) if c != "" else np.nan
            except ValueError:
                raise DatasetFormatError(f"{self.where(i)}: column {name!r} has {c!r}, not a number") from None
        return out

    def check_unique(self, keys: Sequence[str], what: str) -> None:
        """DatasetFormatError naming both lines when two rows have the same key (`what` says what
        the key is, e.g. "frame train/scene1/0003")."""
        first: dict[str, int] = {}
        for i, k in enumerate(keys):
            if k in first:
                raise DatasetFormatError(f"{self.path}: lines {self.lines[first[k]]} and {self.lines[i]} both annotate "
                                         f"{what} {k}; remove the duplicate row")
            first[k] = i


def read_csv_columns(path: Path, required: Sequence[str]) -> CsvTable:
    """Read a CSV with a header (a UTF-8 byte-order mark is allowed) into columns by name.
    DatasetFormatError naming the file for missing columns or a row of the wrong length. A file
    with a header alone is an empty table (an empty split); `check_rows` refuses a dataset of them."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            header = [h.strip() for h in next(reader, [])]
            rows, lines = [], []
            for r in reader:
                if any(c.strip() for c in r):
                    rows.append(r)
                    lines.append(reader.line_num)
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DatasetFormatError(
            f"cannot read annotation file {path}: {e}; it must be a UTF-8 CSV with a header") from e
    missing = [c for c in required if c not in header]
    if missing:
        raise DatasetFormatError(
            f"{path}: missing column(s) {missing}; found {header}. The file must be a CSV with a "
            f"header naming at least {list(required)}")
    cols: dict[str, list[str]] = {h: [] for h in header}
    for lineno, r in zip(lines, rows):
        if len(r) != len(header):
            raise DatasetFormatError(f"{path}:{lineno}: {len(r)} fields, the header has {len(header)}")
        for h, c in zip(header, r):
            cols[h].append(c.strip())
    return CsvTable(path, cols, lines)


def check_rows(tables: Sequence[CsvTable]) -> None:
    """DatasetFormatError naming the files when the dataset's annotation tables have no row at all
    (a header alone annotates no frame)."""
    if not any(len(t) for t in tables):
        raise DatasetFormatError(f"{', '.join(str(t.path) for t in tables)}: a header and no rows: the dataset "
                                 "annotates no frame; write the rows (one per frame and person)")


def gaze_direction(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(N, 3) float64 unit ground-truth gaze normalise(target - eye) (GFIE's definition) from (N, 3)
    3D eye and target points; NaN where they coincide or are unknown."""
    d = target - eye
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, d / norm, np.nan)


def check_intrinsics(K: np.ndarray, path: Path) -> np.ndarray:
    """K (3, 3) itself if it can be a camera's (finite, fx and fy > 0); DatasetFormatError naming
    the file and the values otherwise (every frame would fail: stop before any work)."""
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3):
        raise DatasetFormatError(f"{path}: intrinsics have shape {K.shape}, expected a 3x3 matrix")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    why = ("are not finite" if not np.isfinite(K).all() else
           "have fx or fy <= 0" if fx <= 0 or fy <= 0 else "")
    if why:
        raise DatasetFormatError(f"{path}: intrinsics fx {fx:g}, fy {fy:g}, cx {cx:g}, cy {cy:g} {why}: not a camera; "
                                 "write the camera's calibration in pixels (fx, fy > 0)")
    return K


def intrinsics_from_fxfycxcy(path: Path) -> np.ndarray:
    """K (3, 3) float64 from a .npy holding [fx, fy, cx, cy] (GFIE's and CAD-120's CameraKinect.npy),
    checked (`check_intrinsics`)."""
    expected = "expected a .npy of 4 floats [fx, fy, cx, cy] (np.save(path, np.array([fx, fy, cx, cy])))"
    try:
        a = load_npy(path)
    except (OSError, ValueError, EOFError) as e:
        raise DatasetFormatError(f"cannot read intrinsics {path}: {e}; {expected}") from None
    if a.dtype.kind not in "biuf":
        raise DatasetFormatError(f"cannot read intrinsics {path}: not a numeric .npy array: it holds {a.dtype} "
                                 f"values; {expected}")
    a = np.asarray(a, np.float64).ravel()
    if a.shape != (4,):
        raise DatasetFormatError(f"{path}: expected 4 values [fx, fy, cx, cy], found shape {a.shape}")
    fx, fy, cx, cy = a
    return check_intrinsics(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64), path)


def check_boxes(boxes: np.ndarray, table: CsvTable, columns: str, normalised: bool = False) -> None:
    """Dataset-wide check of the head boxes of `table`, (N, 4) x1, y1, x2, y2 in the file's scale
    (`columns` names the file's columns). DatasetFormatError when the file cannot hold them as
    expected: pixels (`normalised` False) with most boxes inverted or empty (x, y, width, height?)
    or every box within [0, 1.5] (normalised?); normalised, with most boxes reaching beyond 1.5
    (pixels?). A few bad boxes are left to the frames' own checks (failure records)."""
    finite = np.isfinite(boxes).all(1)
    b = boxes[finite]
    if not len(b):
        return
    reach = float(np.median(b[:, 2:].max(1)))
    if normalised:
        if reach > 1.5:
            raise DatasetFormatError(
                f"{table.path}: the head boxes ({columns}) reach {reach:.4g} (median) where the image ends at 1: they "
                "look like pixels; this format stores them normalised to [0, 1] "
                "(divide by the image's width and height)")
        return
    bad = [i for i in np.flatnonzero(finite) if box_fault(boxes[i])]
    if len(bad) > len(b) / 2:
        i = bad[0]
        raise DatasetFormatError(
            f"{table.path}: {len(bad)} of {len(b)} head boxes ({columns}) are inverted or empty "
            f"(line {table.lines[i]}: the box {box_fault(boxes[i])}); they must be {BOXES_XYXY}: "
            "if the file holds x, y, width, height, convert it (x2 = x + width, y2 = y + height)")
    if np.abs(b).max() <= 1.5:
        raise DatasetFormatError(
            f"{table.path}: every head box ({columns}) lies within [0, 1.5]: they look normalised to [0, 1]; they must "
            "be pixels (multiply x by the image's width, y by its height)")


def first_depth_values(paths: Sequence[Path], limit: int = 5) -> tuple[np.ndarray, Path] | None:
    """The positive finite stored values of the first `limit` readable depth files among `paths`,
    and the first of those files; None if none is readable (the frames' own checks will say why).
    An 8-bit or non-numeric depth file raises DatasetFormatError: the dataset's format is wrong."""
    values, first = [], None
    for p in paths:
        if not p.is_file():
            continue
        try:
            d = read_depth(p, check=False)
        except FrameError:
            continue
        fault = depth_type_fault(d)
        if fault:
            raise DatasetFormatError(f"depth {p} {fault}")
        d = d[np.isfinite(d) & (d > 0)].astype(np.float64)
        values.append(d)
        first = first or p
        if len(values) == limit:
            break
    return (np.concatenate(values), first) if first is not None else None


def check_depth_units(paths: Sequence[Path], scale: float, fix: str) -> None:
    """Dataset-wide: the first readable depth files among `paths`, read at `scale` metres per
    stored unit, have a plausible median (`units.DISTANCE_RANGE_M`); DatasetFormatError naming the
    file, the median and the fix (`fix`: the option or the export to change) otherwise."""
    found = first_depth_values(paths)
    if found is not None:
        raw, path = found
        check_plausible(raw * scale, raw, units_name(scale), DISTANCE_RANGE_M, f"depth {path} (and the next maps)",
                        fix, error=DatasetFormatError, candidates=LENGTH_UNITS)


def decide_units(raw: np.ndarray, option: str, what: str, fix: str, quantity: str) -> str:
    """The length unit of a dataset's values: `option` when it names one (m, cm, mm), checked
    plausible; "auto": the one unit in which the median is a room-scale distance
    (`units.infer_units`). DatasetFormatError naming `what` and `fix` otherwise."""
    if option == "auto":
        units = infer_units(raw, what, fix, DatasetFormatError, quantity)
        log.info("%s: %s read as %s (from the median %.4g)", what, quantity, units, float(np.nanmedian(raw)))
        return units
    raw = np.asarray(raw, np.float64)
    raw = raw[np.isfinite(raw)]
    check_plausible(raw * METRES_PER_UNIT[option], raw, option, DISTANCE_RANGE_M, what, f"{fix} (now {option})",
                    quantity, DatasetFormatError, LENGTH_UNITS)
    return option


def check_distances(values: np.ndarray, what: str, fix: str, quantity: str) -> None:
    """Dataset-wide: metres values (e.g. the annotated eyes' distances from the camera) with a
    plausible median (`units.DISTANCE_RANGE_M`); DatasetFormatError naming `what`, the median and
    `fix` otherwise. No finite value: nothing to check."""
    v = np.asarray(values, np.float64)
    v = np.abs(v[np.isfinite(v)])
    if v.size:
        check_plausible(v, v, "m", DISTANCE_RANGE_M, what, fix, quantity, DatasetFormatError, LENGTH_UNITS)


def image_size(path: Path) -> tuple[int, int] | None:
    """(W, H) of an image from its header only, or None if it cannot be read (the frame's own
    checks will say why)."""
    try:
        return image_header_size(path)
    except FrameError:
        return None


def first_image_size(paths: Sequence[Path]) -> tuple[int, int]:
    """(W, H) of the first readable image among paths (a sequence shares one size), else (0, 0)."""
    for p in paths:
        s = image_size(p)
        if s is not None:
            return s
    return (0, 0)
