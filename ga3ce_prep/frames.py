"""`FrameRef`: one frame as a dataset adapter describes it, and the loaders of its image and depth.

Adapters yield FrameRefs (paths and annotations, nothing computed); the pipeline's stages load
pixels through `load_rgb` / `load_depth` so every format's quirks (NaN holes, millimetre PNGs,
truncated files) are handled in one place.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from .errors import FrameError

SPLITS: tuple[str, ...] = ("train", "val", "test")


def nan3() -> np.ndarray:
    """A (3,) float32 NaN vector: the value of an unknown 3D annotation."""
    return np.full(3, np.nan, np.float32)


@dataclass(eq=False)
class FrameRef:
    """One dataset frame: where its pixels are and what the format annotates.

    Units: pixels for boxes and 2D points; metres, camera frame (x right, y down, z forward) for
    3D points; unknown values are NaN. `id` is stable across runs and unique in the dataset.
    """

    id: str                      # e.g. "train/scene3/0012" (GFIE), "D1S1A001/17" (CAD-120)
    split: str                   # one of SPLITS
    scene: str                   # the unit splits are made by (GFIE scene, GAFA session, ...)
    image_path: Path
    K: np.ndarray                # (3, 3) float64 intrinsics at the image resolution
    image_size: tuple[int, int]  # (W, H) pixels
    head_box: np.ndarray         # (4,) float32 x1, y1, x2, y2 pixels
    depth_path: Path | None = None
    depth_scale: float = 1.0     # metres per stored depth unit (GFIE .npy 1.0, CAD-120 PNG 0.001)
    body_box: np.ndarray = field(default_factory=lambda: np.full(4, np.nan, np.float32))
    eye: np.ndarray = field(default_factory=nan3)          # (3,) 3D gaze origin
    gaze_target: np.ndarray = field(default_factory=nan3)  # (3,) 3D gaze target
    gaze: np.ndarray = field(default_factory=nan3)         # (3,) unit gaze direction
    gaze_2d: np.ndarray = field(default_factory=lambda: np.full(2, np.nan, np.float32))  # (2,) px
    sequence: str = ""           # temporal sequence (GAFA camera folder); "" if none
    index: int = 0               # raw frame number within `sequence`
    keypoints_2d: np.ndarray | None = None  # (25, 3) OpenPose BODY_25 u, v, confidence (GAFA)


@dataclass(frozen=True, eq=False)
class Window:
    """The frames around one frame of its sequence, as a windowed backend receives them
    (`Backend.window`, docs/pipeline.md).

    frames: (size,) the adapter's frames of the same `sequence` at raw frame numbers index - size//2
    ... index + size//2 (the frame itself in the middle); None where the adapter has no frame with
    that number (a gap in the numbering, or beyond either end of the sequence).
    previous: the sequence's frame that comes before raw number index - size//2 in frame-number
    order, cyclically: the sequence's last frame when none comes before (what `np.roll(x, 1)`
    pairs with the window's first frame over the array of the sequence's frames, as GAFA's body
    velocity does).
    """

    frames: tuple[FrameRef | None, ...]
    previous: FrameRef

    @property
    def complete(self) -> bool:
        """Every raw frame number of the window is present."""
        return all(f is not None for f in self.frames)


def frame_windows(frames: list[FrameRef], size: int) -> list[Window]:
    """The `size`-frame window (odd) centred on each frame, in the order of `frames`: neighbours by
    consecutive raw frame numbers (`FrameRef.index`) within each `sequence`, looked up among
    `frames` only. A frame with no sequence ("") is a sequence of its own. ValueError for an even
    size or two frames of one sequence with the same number (an adapter bug)."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"a window has an odd number of frames, not {size}")
    h = size // 2
    members: dict[str | int, list[int]] = {}
    for i, f in enumerate(frames):
        members.setdefault(f.sequence or i, []).append(i)
    out: list[Window | None] = [None] * len(frames)
    offsets = np.arange(-h, h + 1)
    for seq, pos in members.items():
        pos = np.asarray(pos)
        number = np.array([frames[i].index for i in pos], np.int64)
        order = np.argsort(number, kind="stable")
        pos, number = pos[order], number[order]
        if np.any(np.diff(number) == 0):
            dup = int(number[np.flatnonzero(np.diff(number) == 0)[0]])
            raise ValueError(f"sequence {seq!r}: two frames with raw frame number {dup}")
        want = number[:, None] + offsets                                  # (n, size) raw numbers
        at = np.minimum(np.searchsorted(number, want), len(number) - 1)   # where each would sit
        found = number[at] == want
        prev = (np.searchsorted(number, number - h) - 1) % len(number)    # cyclic: -1 -> the last
        for r, i in enumerate(pos):
            out[i] = Window(tuple(frames[pos[a]] if ok else None for a, ok in zip(at[r], found[r])),
                            frames[pos[prev[r]]])
    return out  # type: ignore[return-value]


@dataclass
class DepthMap:
    """One frame's depth as the geometry stages use it.

    depth: (H, W) float32 metres, completed (holes filled), 0 = still unknown.
    valid: (H, W) bool, the raw sensor validity: the pixels whose depth was measured. Object
    medians and the head position use only these; the completed depth serves the segmenter.
    """

    depth: np.ndarray
    valid: np.ndarray


def load_rgb(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB. Raises FrameError naming the file if it is
    missing, unreadable or truncated (Pillow refuses truncated JPEG/PNG data)."""
    path = Path(path)
    if not path.is_file():
        raise FrameError(f"image file not found: {path}")
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im.convert("RGB"))
    except (OSError, SyntaxError, ValueError) as e:
        raise FrameError(f"cannot decode image {path}: {e}; re-extract or replace the file") from e


def check_rgb(rgb: np.ndarray) -> np.ndarray:
    """The array itself if it is an (H, W, 3) uint8 RGB image (what `load_rgb` returns);
    FrameError saying what it is otherwise."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise FrameError(f"expected an (H, W, 3) uint8 RGB image, got {rgb.shape} {rgb.dtype}")
    return rgb


def load_depth(path: str | Path, scale: float = 1.0) -> np.ndarray:
    """Read a depth map as (H, W) float32 metres, 0 = unknown.

    `.npy` float arrays (GFIE: NaN holes) are read with allow_pickle=False; 16-bit PNGs (CAD-120:
    millimetres, 0 invalid) with OpenCV. `scale` converts stored units to metres. Non-finite and
    negative values become 0.
    """
    path = Path(path)
    if not path.is_file():
        raise FrameError(f"depth file not found: {path}")
    if path.suffix == ".npy":
        try:
            d = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            raise FrameError(f"cannot read depth {path}: {e}") from e
    else:
        d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if d is None:
            raise FrameError(f"cannot decode depth image {path}: missing, truncated or not an image")
    if d.ndim != 2:
        raise FrameError(f"depth {path} has shape {d.shape}; expected a single-channel (H, W) map")
    d = d.astype(np.float32) * np.float32(scale)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d
