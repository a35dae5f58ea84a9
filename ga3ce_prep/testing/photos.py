"""scikit-image's bundled photos as pipeline inputs for the real-model tests: RGB arrays, an
assumed pinhole K, and a frame file with its FrameRef.

`astronaut` (512x512, a person facing the camera), `camera` (grey, a man in 3/4 view),
`chelsea` (a cat), `coffee` (600x400 cup) have no calibration: K is assumed from a horizontal
field of view (60 degrees unless said), principal point at the image centre.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..frames import FrameRef


def photo(name: str) -> np.ndarray:
    """skimage.data's photo `name` as (H, W, 3) uint8 RGB (grey photos repeated to 3 channels)."""
    from skimage import data

    img = getattr(data, name)()
    return np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img


def K_from_hfov(width: int, height: int, hfov_deg: float = 60.0) -> np.ndarray:
    """(3, 3) intrinsics of a horizontal field of view, principal point at the image centre
    (`predict.intrinsics`)."""
    from ..predict import intrinsics

    return intrinsics((width, height), hfov_deg)


def mirrored(img: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    """The horizontally mirrored image and the box (x1, y1, x2, y2) mirrored with it."""
    W = img.shape[1]
    return np.ascontiguousarray(img[:, ::-1]), np.array([W - box[2], box[1], W - box[0], box[3]], np.float64)


def photo_frame(folder: Path, name: str, img: np.ndarray, head_box) -> FrameRef:
    """Write img as folder/name.png and return its FrameRef (K from a 60 degree field of view)."""
    from PIL import Image

    path = Path(folder) / f"{name}.png"
    Image.fromarray(img).save(path)
    H, W = img.shape[:2]
    return FrameRef(name, "test", "photos", path, K_from_hfov(W, H), (W, H), np.asarray(head_box, np.float32))
