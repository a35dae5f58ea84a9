"""GAFA's 7-frame head-and-body gaze network (GazeNet, kyotovision-public/dynamic-3d-gaze-from-afar)
through ONNX Runtime, with its inputs built the way GAFA's preprocessing and loader build them.

Per frame of a window, from the raw frame and its OpenPose BODY_25 keypoints:

- boxes (`preprocessed_boxes`, GAFA's `data/preprocessed/preprocess.py` with `transforms.py`; the
  rules shared with the gafa adapter, `datasets.gafa.keypoint_squares`): the min/max of the
  detected joints (both coordinates non-zero), truncated to integers; head: joints nose, neck,
  eyes, ears expanded by (top 0.85, bottom -0.2, left 0.1, right 0.1) of its height and width
  (each pad truncated to an integer), then squared on its longer side; body: all joints,
  expanded by (0.15, 0.05, 0.2, 0.2), squared, then narrowed to 3:4 (width 0.75 x side, a float,
  shifted right by floor(side / 8)). Boxes are u, v, w, h full-image pixels;
- the body crop (`pre_blur`, `body_crop`): the whole frame resized to width 720 and back (bicubic,
  Pillow's default filter), the body box cut out (Pillow rounds the box to whole pixels, half to
  even; outside the image is black) and resized to 192 x 256 (bilinear, torchvision's Resize on a
  PIL image); then ImageNet mean/std on RGB / 255 (`normalize_crops`, GAFA's loader);
- the head mask (`head_masks`, GAFA's `dataloader/gafa.py`): the head box relative to the body box,
  scaled to the 192 x 256 crop, truncated to integers, negatives clamped to 0: ones inside;
- the body velocity (`body_velocity`, same loader): the body box centre divided by the box's size,
  minus the same for the previous frame of the camera sequence (`Window.previous` for the window's
  first frame, which GAFA's `np.roll` takes across a gap, and from the sequence's last frame at
  its start).

The network reads image (B, 7, 3, 256, 192), head_mask (B, 7, 1, 256, 192), body_dv (B, 7, 2) and
writes gaze (B, 7, 3): GazeNet's gaze direction per frame (`gaze_res["direction"]`, its final
output), unit vectors in GAFA's camera frame (x right, y down, z forward, the frame of its labels).
scripts/export_gafa_view.py exports it from a GAFA install.
"""
from __future__ import annotations

import os
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np
from PIL import Image

from ...datasets.gafa import WINDOW, keypoint_squares
from ...frames import load_rgb
from ..runtime.onnx_runtime import RuntimeParams, TensorSpec, check_contract, create_session, resolve_providers

CROP_H, CROP_W = 256, 192  # GAFA's body crop, pixels
BLUR_WIDTH = 720           # GAFA's pre-blur: frames are resized to this width and back before cropping
MEAN = np.array([0.485, 0.456, 0.406], np.float32) * np.float32(255)  # ImageNet on 0-255 RGB (albumentations Normalize)
INV_STD = np.reciprocal(np.array([0.229, 0.224, 0.225], np.float32) * np.float32(255))
INPUTS = [TensorSpec("image", (1, WINDOW, 3, CROP_H, CROP_W)), TensorSpec("head_mask", (1, WINDOW, 1, CROP_H, CROP_W)),
          TensorSpec("body_dv", (1, WINDOW, 2))]
OUTPUTS = [TensorSpec("gaze", (1, WINDOW, 3))]


def preprocessed_boxes(kp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The head and body boxes (T, 4) u, v, w, h float64 full-image pixels that GAFA's preprocessing
    stores for BODY_25 keypoints kp (T, 25, >=2) pixels (0 = undetected); module docstring."""
    head, body = keypoint_squares(kp)
    u, v, side, _ = body.T
    diff = side - side * (CROP_W / CROP_H)
    body = np.stack([u + np.floor(diff / 2), v, side - diff, side], axis=1)
    return head, body


def pre_blur(image: Image.Image) -> Image.Image:
    """GAFA's pre-blur: resized to width 720 (height int(H * 720 / W)) and back, bicubic."""
    W, H = image.size
    small = image.resize((BLUR_WIDTH, int(H * (BLUR_WIDTH / W))), Image.Resampling.BICUBIC)
    return small.resize((W, H), Image.Resampling.BICUBIC)


def body_crop(image: Image.Image, body: np.ndarray) -> np.ndarray:
    """(256, 192, 3) uint8: the body box (4,) u, v, w, h of a (pre-blurred) image, Pillow-rounded to
    whole pixels, black outside the image, resized bilinearly."""
    u, v, w, h = (float(x) for x in body)
    return np.asarray(image.crop((u, v, u + w, v + h)).resize((CROP_W, CROP_H), Image.Resampling.BILINEAR))


def normalize_crops(crops: np.ndarray) -> np.ndarray:
    """(T, 3, 256, 192) float32 network images from (T, 256, 192, 3) uint8 RGB crops."""
    return ((crops.astype(np.float32) - MEAN) * INV_STD).transpose(0, 3, 1, 2)


def head_masks(head: np.ndarray, body: np.ndarray) -> np.ndarray:
    """(T, 1, 256, 192) float32 head masks from head and body boxes (T, 4) u, v, w, h (float32 math
    as GAFA's loader: the head box relative to the body box, scaled to the crop, truncated)."""
    head, body = np.asarray(head, np.float32), np.asarray(body, np.float32)
    x, y = (head[:, 0] - body[:, 0]) / body[:, 2] * CROP_W, (head[:, 1] - body[:, 1]) / body[:, 3] * CROP_H
    w, h = head[:, 2] / body[:, 2] * CROP_W, head[:, 3] / body[:, 3] * CROP_H
    x1, y1, x2, y2 = np.maximum(np.stack([x, y, x + w, y + h]).astype(np.int64), 0)
    cols, rows = np.arange(CROP_W), np.arange(CROP_H)
    inside = (((rows >= y1[:, None]) & (rows < y2[:, None]))[:, :, None]
              & ((cols >= x1[:, None]) & (cols < x2[:, None]))[:, None, :])
    return inside[:, None].astype(np.float32)


def body_velocity(body: np.ndarray) -> np.ndarray:
    """(T, 2) float32 body velocity (per frame, in box sizes) from body boxes (T + 1, 4) u, v, w, h:
    row 0 is the frame before the window (GAFA's np.roll predecessor), rows 1.. the window's."""
    b = np.asarray(body, np.float32)
    centre = (b[:, :2] + b[:, 2:] / 2) / b[:, 2:]
    return np.diff(centre, axis=0)


class GafaViewEstimator:
    """GazeNet on one ONNX file (contract above, checked on load: ModelFileError), with a small
    per-process cache of body crops: consecutive windows share 6 of their 7 frames."""

    def __init__(self, path: str | Path,
                 options: RuntimeParams = RuntimeParams(),  # noqa: B008 - frozen dataclass: safe to share
                 cached_crops: int = 32):
        self.path = Path(path)
        self.session = create_session(self.path, resolve_providers(options.providers), options.threads,
                                      "GAFA view")
        self.names = check_contract(self.session, INPUTS, OUTPUTS, self.path, "GAFA view")
        self._crops: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._size = cached_crops
        self._lock = threading.Lock()

    def crop(self, image_path: Path, body: np.ndarray) -> np.ndarray:
        """(256, 192, 3) uint8 body crop of a raw frame (pre-blurred; module docstring). FrameError
        for a missing or undecodable image."""
        st = os.stat(image_path) if Path(image_path).is_file() else None
        key = (str(image_path), st and (st.st_size, st.st_mtime_ns), tuple(np.asarray(body, np.float64).tolist()))
        with self._lock:
            if key in self._crops:
                self._crops.move_to_end(key)
                return self._crops[key]
        out = body_crop(pre_blur(Image.fromarray(load_rgb(image_path))), body)
        with self._lock:
            self._crops[key] = out
            while len(self._crops) > self._size:
                self._crops.popitem(last=False)
        return out

    def predict(self, image: np.ndarray, head_mask: np.ndarray, body_dv: np.ndarray) -> np.ndarray:
        """(7, 3) the network's gaze per frame of one window: image (7, 3, 256, 192), head_mask
        (7, 1, 256, 192), body_dv (7, 2), all float32."""
        n = self.names
        feed = {n["image"]: image[None], n["head_mask"]: head_mask[None], n["body_dv"]: body_dv[None]}
        return self.session.run([n["gaze"]], feed)[0][0]


__all__ = ["BLUR_WIDTH", "CROP_H", "CROP_W", "INPUTS", "OUTPUTS", "GafaViewEstimator", "body_crop", "body_velocity",
           "head_masks", "normalize_crops", "pre_blur", "preprocessed_boxes"]
