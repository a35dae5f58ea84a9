"""`FrameRef`: one frame as a dataset adapter describes it, and the loaders of its image and depth.

Adapters yield FrameRefs (paths and annotations, nothing computed); the pipeline's stages load
pixels through `load_rgb` / `load_depth` so every format's quirks (NaN holes, millimetre PNGs,
truncated files, 8-bit depth, headers declaring huge sizes) are handled in one place.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from .errors import FrameError

# Pillow warns, then refuses, on headers declaring more pixels than Image.MAX_IMAGE_PIXELS
# (179 Mpx, beyond any camera frame): a corrupt file or a decompression bomb. Here both refuse.
warnings.filterwarnings("error", category=Image.DecompressionBombWarning)

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
    annotation: str = ""         # where the frame's annotation is, for messages: "<file>:<line>", "<pkl> row <i>"


def box_fault(box: np.ndarray) -> str:
    """Why an x1, y1, x2, y2 box cannot be a head box, "" if it can: not finite, inverted (x2 < x1
    or y2 < y1) or empty (zero width or height)."""
    x1, y1, x2, y2 = (float(v) for v in box)
    if not np.all(np.isfinite([x1, y1, x2, y2])):
        return "is not finite"
    for a, lo, hi in (("x", x1, x2), ("y", y1, y2)):
        if hi < lo:
            return f"is inverted ({a}2 {hi:g} < {a}1 {lo:g})"
        if hi == lo:
            return f"is empty (zero {'width' if a == 'x' else 'height'}: {a}1 = {a}2 = {lo:g})"
    return ""


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
    out: dict[int, Window] = {}
    offsets = np.arange(-h, h + 1)
    for seq, members_pos in members.items():
        pos = np.asarray(members_pos)
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
            out[int(i)] = Window(tuple(frames[pos[a]] if ok else None for a, ok in zip(at[r], found[r])),
                                 frames[pos[prev[r]]])
    return [out[i] for i in range(len(frames))]  # every frame is in one sequence


@dataclass
class DepthMap:
    """One frame's depth as the geometry stages use it.

    depth: (H, W) float32 metres, completed (holes filled), 0 = still unknown.
    valid: (H, W) bool, the raw sensor validity: the pixels whose depth was measured. Object
    medians and the head position use only these; the completed depth serves the segmenter.
    """

    depth: np.ndarray
    valid: np.ndarray


def _open_checked(path: Path) -> Image.Image:
    """The image at `path` with only its header read. FrameError when the header declares more
    pixels than Image.MAX_IMAGE_PIXELS (a corrupt file or a decompression bomb); Pillow's own
    errors (OSError, SyntaxError, ValueError) for a file it cannot read."""
    try:
        im = Image.open(path)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise FrameError(f"image {path}: its header declares a size beyond any camera frame ({e}); the file is "
                         "corrupt or hostile: replace it") from None
    limit = Image.MAX_IMAGE_PIXELS  # None: lifted (Pillow's own setting), nothing to refuse
    if limit is not None and im.width * im.height > limit:  # when the warning filter above was reset
        im.close()
        raise FrameError(f"image {path}: its header declares {im.width}x{im.height} pixels, beyond any camera "
                         "frame; the file is corrupt or hostile: replace it")
    return im


def _open_image(path: Path) -> Image.Image:
    """`_open_checked` for an RGB frame: FrameError naming the file for any problem."""
    if not path.is_file():
        raise FrameError(f"image file not found: {path}")
    try:
        return _open_checked(path)
    except (OSError, SyntaxError, ValueError) as e:
        raise FrameError(f"cannot decode image {path}: {e}; re-extract or replace the file") from e


def image_header_size(path: str | Path) -> tuple[int, int]:
    """(W, H) from an image's header only; FrameError as `load_rgb` gives it."""
    with _open_image(Path(path)) as im:
        return im.size


def load_rgb(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB. Raises FrameError naming the file if it is
    missing, unreadable, truncated (Pillow refuses truncated JPEG/PNG data) or declares a huge size."""
    path = Path(path)
    with _open_image(path) as im:
        try:
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


def depth_type_fault(d: np.ndarray) -> str:
    """Why stored depth values cannot be a depth map in any unit ("" if they can): not a single
    channel, not numeric, or 8 bits (256 levels: a visualisation, not a measurement)."""
    if d.ndim != 2:
        return f"has shape {d.shape}; expected a single-channel (H, W) map"
    if d.dtype.kind not in "fiu":
        return f"holds {d.dtype} values; expected numbers (float metres or uint16 millimetres)"
    if d.dtype.itemsize == 1:
        return (f"is 8-bit ({d.dtype}, values 0-{int(d.max()) if d.size else 0}): a depth map needs 16 bits "
                "(uint16 millimetres) or floats; this looks like a depth visualisation, export the raw depth")
    return ""


NPY_MAGIC = b"\x93NUMPY"
PICKLED = "pickled objects are never loaded"


def _what_it_is(head: bytes) -> str:
    """What a file that is not a .npy array holds, from its first bytes."""
    if not head:
        return "nothing (an empty file)"
    if head.startswith(b"PK"):
        return "a zip archive (an .npz?)"
    if head[:1] == b"\x80":
        return "a Python pickle"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return f"binary data starting {head[:8]!r}"
    line = text.splitlines()[0] if text.strip() else text
    return f"text ({line[:40]!r}{'...' if len(line) > 40 else ''})"


def load_npy(path: str | Path) -> np.ndarray:
    """The array of a .npy file, read without ever unpickling (allow_pickle=False). ValueError
    saying what the file holds instead when it is not a numeric .npy array: another format (text,
    a pickle, an archive), or an array of Python objects."""
    with open(path, "rb") as f:
        head = f.read(64)
    if not head.startswith(NPY_MAGIC):
        raise ValueError(f"not a numeric .npy array: it holds {_what_it_is(head)}; {PICKLED}")
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as e:
        if "allow_pickle" in str(e):  # an array of Python objects: only a pickle could read it
            raise ValueError(f"not a numeric .npy array: it holds Python objects (dtype object); {PICKLED}") from None
        raise


def read_depth(path: str | Path, check: bool = True) -> np.ndarray:
    """A depth file's stored values as (H, W), unscaled: `.npy` arrays read by `load_npy`, never
    unpickled (GFIE: float metres, NaN holes), images with OpenCV (CAD-120: 16-bit PNG millimetres, 0
    invalid). FrameError naming the file if it is missing, unreadable, or (check) not a depth map
    in any unit (`depth_type_fault`)."""
    path = Path(path)
    if not path.is_file():
        raise FrameError(f"depth file not found: {path}")
    d: np.ndarray | None
    if path.suffix == ".npy":
        try:
            d = load_npy(path)
        except (OSError, ValueError, EOFError) as e:
            raise FrameError(f"cannot read depth {path}: {e}") from e
    else:
        try:  # a header declaring a huge size is refused before OpenCV allocates it
            _open_checked(path).close()
        except (OSError, SyntaxError, ValueError):
            pass  # a format Pillow does not read: OpenCV decides
        d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if d is None:
            raise FrameError(f"cannot decode depth image {path}: missing, truncated or not an image")
    fault = depth_type_fault(d) if check else ""
    if fault:
        raise FrameError(f"depth {path} {fault}")
    return d


def load_depth(path: str | Path, scale: float = 1.0) -> np.ndarray:
    """Read a depth map (`read_depth`) as (H, W) float32 metres, 0 = unknown: `scale` converts
    stored units to metres; non-finite and negative values become 0."""
    d = read_depth(path).astype(np.float32) * np.float32(scale)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d
