"""Sensor noise: RGB read noise, and Kinect-like depth noise and holes.

Depth noise std grows with z^2: sigma(z) = sigma0 + sigma_z2 * (z - z0)^2 (Nguyen et al. 2012's
Kinect model). Holes, each with its own rate: out of range (and no return), depth edges (a band
where neighbouring depths jump by more than `edge_threshold` relative), dark surfaces (albedo
luminance below `dark_threshold`), shiny surfaces, and random dropout blobs; and, in a fraction
`head_hole_prob` of the frames, the whole head box (`blank_box`: no measured depth near the head,
the case the head stage's fallbacks handle).

Gaussian fields are drawn once per scene into a `NoiseBank` and cropped at a random offset per
frame: drawing 900k normals per frame would cost more than rendering.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .config import DepthConfig, RenderConfig

PAD = 24


class NoiseBank:
    """Standard normal fields for one image size, cropped at a random offset per frame."""

    def __init__(self, rng: np.random.Generator, height: int, width: int):
        self.h, self.w = height, width
        self.rgb = rng.standard_normal((height + PAD, width + PAD, 3), dtype=np.float32)
        self.depth = rng.standard_normal((height + PAD, width + PAD), dtype=np.float32)

    def crop(self, field: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        dy, dx = (int(x) for x in rng.integers(0, PAD, 2))
        out = field[dy:dy + self.h, dx:dx + self.w]
        return -out if rng.random() < 0.5 else out


def rgb_sensor(rgb: np.ndarray, cfg: RenderConfig, bank: NoiseBank, rng: np.random.Generator) -> np.ndarray:
    """Shaded colour (H, W, 3) float in [0, 1] to a noisy (H, W, 3) uint8 RGB image."""
    img = bank.crop(bank.rgb, rng) * np.float32(cfg.rgb_noise)
    img += rgb * np.float32(255.0)
    img += np.float32(0.5)
    np.clip(img, 0, 255, out=img)
    return img.astype(np.uint8)


@dataclass
class DepthHoles:
    """Why each pixel lost its depth, (H, W) bool per cause (a pixel may have several)."""

    out_of_range: np.ndarray
    edge: np.ndarray
    dark: np.ndarray
    shiny: np.ndarray
    blob: np.ndarray

    @property
    def any(self) -> np.ndarray:
        return self.out_of_range | self.edge | self.dark | self.shiny | self.blob


def depth_sigma(z: np.ndarray, cfg: DepthConfig) -> np.ndarray:
    """Noise std (m) at depth z (m)."""
    return cfg.sigma0 + cfg.sigma_z2 * (z - cfg.z0) ** 2


def edge_band(z: np.ndarray, threshold: float, width: int) -> np.ndarray:
    """(H, W) bool: pixels next to a relative depth jump above `threshold` (misses count as
    jumps), dilated to a band `width` px wide on each side."""
    e = np.zeros(z.shape, bool)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        za, zb = z[a], z[b]
        with np.errstate(divide="ignore", invalid="ignore"):
            jump = np.abs(za - zb) > threshold * np.maximum(za, zb)
        e[a] |= jump
        e[b] |= jump
    if width > 1:
        k = 2 * width - 1
        e = cv2.dilate(e.view(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    return e


def depth_sensor(depth: np.ndarray, albedo_lum: np.ndarray, shiny: np.ndarray, cfg: DepthConfig,
                 bank: NoiseBank, rng: np.random.Generator) -> tuple[np.ndarray, DepthHoles]:
    """Exact depth (H, W) metres (0 = no hit) to sensor depth (H, W) float32 metres with 0 at holes
    (quantised to mm when cfg.quantize_mm), and the hole causes."""
    H, W = depth.shape
    px = W / 640.0  # pixel sizes in the config are at 640 wide
    noisy = depth + depth_sigma(depth, cfg) * bank.crop(bank.depth, rng)
    if cfg.quantize_mm:
        noisy = np.round(noisy * 1000.0) / 1000.0
    u = rng.random((H, W), dtype=np.float32)
    out_of_range = (depth <= 0) | (depth < cfg.min_range) | (depth > cfg.max_range)
    edge = edge_band(depth, cfg.edge_threshold, max(1, int(round(cfg.edge_width * px)))) & (u < cfg.edge_hole_prob)
    u2 = rng.random((H, W), dtype=np.float32)  # dark and shiny (a separate draw from edges)
    dark = (albedo_lum < cfg.dark_threshold) & (u2 < cfg.dark_hole_prob)
    shiny_h = shiny & (u2 < cfg.shiny_hole_prob)
    blob = np.zeros((H, W), np.uint8)
    for _ in range(int(rng.poisson(cfg.blob_rate))):
        c = (int(rng.integers(0, W)), int(rng.integers(0, H)))
        ax = (max(1, int(rng.uniform(*cfg.blob_radius) * px)), max(1, int(rng.uniform(*cfg.blob_radius) * px)))
        cv2.ellipse(blob, c, ax, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    holes = DepthHoles(out_of_range, edge, dark, shiny_h, blob.astype(bool))
    noisy = np.where(holes.any | (noisy <= 0), 0.0, noisy).astype(np.float32)
    return noisy, holes


def blank_box(depth: np.ndarray, box: np.ndarray) -> None:
    """Set depth (H, W) to 0 (a hole) in place over every pixel the box x1, y1, x2, y2 (4,) px
    touches; a non-finite box changes nothing."""
    if not np.isfinite(box).all():
        return
    H, W = depth.shape
    x1, y1 = (max(0, int(np.floor(c))) for c in box[:2])
    x2, y2 = min(W, int(np.ceil(box[2])) + 1), min(H, int(np.ceil(box[3])) + 1)
    depth[y1:y2, x1:x2] = 0.0
