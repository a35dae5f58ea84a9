"""GFIE's whole gaze-following network (Hu et al., CVPR 2023; github nkuhzx/GFIE at 7590721:
gfiemodel/gfienet.py, gfiemodel/gfiemodule.py), its inputs as GFIE's test loaders make them
(utils/infer_engine.py, `GFIETestDataset` / `CAD120TestDataset.format_model_input`), and its
non-learnable 3D step (`strategy3dGazeFollowing`), in torch and numpy; no GFIE code is copied.

Network (`GFIENet`; the GA3CE paper's "GFM" are its PSFoV and GGH modules):
- `egd_module` (estimators/view/gfie_head.py): head crop (N, 3, 224, 224) -> g (N, 3) unit, camera frame;
- PSFoV (`stereo_fov`, no weights): per pixel of the 224 x 224 scene grid F = ReLU(T . g) and
  F' = F^3, with T (N, 224, 224, 3) the unit directions from the eye to the back-projected depth
  (`matrix_t`; GFIE builds T in its data loader) -> (N, 2, 224, 224);
- `ggh_module`: cat(scene image 3, head mask 1, F, F') (N, 6, 224, 224) -> a ResNet-50 whose conv1
  takes 6 channels (`encoder`, (N, 2048, 7, 7)) -> `decoder`: 1x1 convs 2048 -> 1024 -> 512 (BN,
  ReLU), transposed convs 512 -> 256 (k3 s2, 15 x 15), 256 -> 128 (k3 s2, 31 x 31), 128 -> 1 (k4 s2,
  64 x 64), each with BN and ReLU, and a 1x1 conv 1 -> 1: the raw (N, 64, 64) heatmap (no sigmoid).

Key names in GFIE's checkpoint (`state_dict`, no `module.` prefix): `egd_module.*` (322 tensors,
gfie_head.py), `ggh_module.encoder.{conv1 (64, 6, 7, 7), bn1, layer1..layer4}.*` (torchvision's
ResNet-50 names) and `ggh_module.decoder.{compress_conv1, compress_bn1, compress_conv2,
compress_bn2, deconv1, deconv_bn1, deconv2, deconv_bn2, deconv3, deconv_bn3, conv4}.*`; PSFoV has
none. `load_gfie_net` matches them all strictly.

3D step (`gaze_point_3d`): the 64 x 64 argmax (row-major first) gives the 2D target (col / 64,
row / 64); a window of 0.1 W x 0.1 H full-resolution pixels around it (shifted inside at the
borders, corners truncated) is back-projected with the full-resolution depth; the pixel whose unit
direction from the eye best agrees with g (directions of 0-depth pixels set to 0) is the 3D target,
and that unit direction (or 0) the refined gaze direction.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from PIL import Image
from torch import nn

from ...frames import check_rgb
from ...geometry import back_project, normalize
from .gfie_head import GFIEHeadNet, load_gfie_weights
from .head_crop import CropParams, expand_box, network_input
from .resnet import ResNet50

INPUT_SIZE = 224   # GFIE's TRAIN.input_size: scene image, head mask and T grid
OUTPUT_SIZE = 64   # GFIE's TRAIN.output_size: the heatmap
ALPHA = 3          # PSFoV's exponent: F' = F ** ALPHA
WINDOW_RATIO = 0.1  # the 3D step's window: this fraction of the image's width and height


class GGHEncoder(nn.Module):
    """ResNet-50 without avgpool and fc, conv1 taking 6 channels: (N, 6, 224, 224) -> (N, 2048, 7, 7)."""

    def __init__(self):
        super().__init__()
        r = ResNet50(num_classes=None)
        self.conv1 = nn.Conv2d(6, 64, 7, stride=2, padding=3, bias=False)
        self.bn1, self.relu, self.maxpool = r.bn1, r.relu, r.maxpool
        self.layer1, self.layer2, self.layer3, self.layer4 = r.layer1, r.layer2, r.layer3, r.layer4

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))


class GGHDecoder(nn.Module):
    """(N, 2048, 7, 7) -> (N, 1, 64, 64) raw heatmap (see the module docstring)."""

    def __init__(self):
        super().__init__()
        self.relu = nn.ReLU(inplace=True)
        self.compress_conv1 = nn.Conv2d(2048, 1024, 1, bias=False)
        self.compress_bn1 = nn.BatchNorm2d(1024)
        self.compress_conv2 = nn.Conv2d(1024, 512, 1, bias=False)
        self.compress_bn2 = nn.BatchNorm2d(512)
        self.deconv1 = nn.ConvTranspose2d(512, 256, 3, stride=2)
        self.deconv_bn1 = nn.BatchNorm2d(256)
        self.deconv2 = nn.ConvTranspose2d(256, 128, 3, stride=2)
        self.deconv_bn2 = nn.BatchNorm2d(128)
        self.deconv3 = nn.ConvTranspose2d(128, 1, 4, stride=2)
        self.deconv_bn3 = nn.BatchNorm2d(1)
        self.conv4 = nn.Conv2d(1, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.relu(self.compress_bn1(self.compress_conv1(x)))
        x = self.relu(self.compress_bn2(self.compress_conv2(x)))
        x = self.relu(self.deconv_bn1(self.deconv1(x)))
        x = self.relu(self.deconv_bn2(self.deconv2(x)))
        x = self.relu(self.deconv_bn3(self.deconv3(x)))
        return self.conv4(x)


class GGHModule(nn.Module):
    """GFIE's heatmap generator: (N, 6, 224, 224) -> (N, 1, 64, 64)."""

    def __init__(self):
        super().__init__()
        self.encoder = GGHEncoder()
        self.decoder = GGHDecoder()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder(x))


def stereo_fov(matrix_t: torch.Tensor, gaze: torch.Tensor, alpha: int = ALPHA) -> torch.Tensor:
    """GFIE's PSFoV module: T (N, H, W, 3) unit (or 0) directions, g (N, 3) -> (N, 2, H, W) the
    maps F = ReLU(T . g) and F' = F ** alpha."""
    f = torch.relu(torch.einsum("nhwc,nc->nhw", matrix_t, gaze))[:, None]
    return torch.cat([f, f ** alpha], 1)


class GFIENet(nn.Module):
    """GFIE's network under GFIE's key names (`egd_module`, `ggh_module`)."""

    def __init__(self):
        super().__init__()
        self.egd_module = GFIEHeadNet()
        self.ggh_module = GGHModule()

    def heatmap(self, scene: torch.Tensor, head_loc: torch.Tensor, matrix_t: torch.Tensor,
                gaze: torch.Tensor) -> torch.Tensor:
        """The GFM: scene (N, 3, 224, 224), head mask (N, 1, 224, 224), T (N, 224, 224, 3) and a
        unit gaze g (N, 3) -> (N, 64, 64) raw heatmap."""
        return self.ggh_module(torch.cat([scene, head_loc, stereo_fov(matrix_t, gaze)], 1))[:, 0]

    def forward(self, scene: torch.Tensor, head: torch.Tensor, head_loc: torch.Tensor, matrix_t: torch.Tensor,
                gaze: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(heatmap (N, 64, 64), g (N, 3)): g is the head branch's output on `head` (N, 3, 224,
        224), or `gaze` (N, 3) unit when given ("Ours + GFM": another estimator's g replaces it)."""
        g = self.egd_module(head) if gaze is None else gaze
        return self.heatmap(scene, head_loc, matrix_t, g), g


def load_gfie_net(path: str | Path) -> GFIENet:
    """GFIENet (eval mode, CPU) with every weight of GFIE's checkpoint at `path`: its whole
    `state_dict` must match GFIENet's keys and shapes exactly (`gfie_head.load_gfie_weights`:
    weights_only=True, ModelFileError naming the file and the keys)."""
    return load_gfie_weights(path, GFIENet(), what="GFIE's network (egd_module.*, ggh_module.*)")


# --- inputs --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class DepthRecipe:
    """How a dataset's loader makes T from the depth map (GFIE and CAD-120 differ)."""

    resample: Literal["bicubic", "nearest"]  # Pillow filter resizing the float depth to 224 x 224
    zero_invalid: bool  # T = 0 where the resized depth is 0 (else normalise(-eye) there)


RECIPES: dict[str, DepthRecipe] = {"gfie": DepthRecipe("bicubic", False), "cad120": DepthRecipe("nearest", True)}
_FILTERS = {"bicubic": Image.Resampling.BICUBIC, "nearest": Image.Resampling.NEAREST}


def scene_input(rgb: np.ndarray) -> np.ndarray:
    """The (H, W, 3) uint8 RGB image resized to 224 x 224 (Pillow bilinear, aspect not kept) and
    ImageNet-normalised: (1, 3, 224, 224) float32."""
    small = Image.fromarray(check_rgb(rgb)).resize((INPUT_SIZE, INPUT_SIZE), Image.Resampling.BILINEAR)
    return network_input(np.asarray(small))


def head_location(box: np.ndarray, size: tuple[int, int], k: float = CropParams().box_expand) -> np.ndarray:
    """GFIE's head-position channel: (1, 1, 224, 224) float32, 1 inside the expanded head box (4,)
    x1, y1, x2, y2 pixels of a (W, H) image scaled to 224 and truncated toward zero, corners
    clipped to [0, 223] (end-exclusive, so the last row and column stay 0)."""
    W, H = size
    x1, y1, x2, y2 = np.clip((expand_box(box, k) / [W, H, W, H] * INPUT_SIZE).astype(int), 0, INPUT_SIZE - 1)
    out = np.zeros((1, 1, INPUT_SIZE, INPUT_SIZE), np.float32)
    out[0, 0, y1:y2, x1:x2] = 1
    return out


def matrix_t(depth: np.ndarray, size: tuple[int, int], K: np.ndarray, eye: np.ndarray,
             recipe: DepthRecipe = RECIPES["gfie"]) -> np.ndarray:
    """GFIE's T: (1, 224, 224, 3) float32 unit directions from the eye (3,) to grid point (row j,
    column i) back-projected at pixel (i W / 224, j H / 224) (no half-pixel offset) with the depth
    (H', W') resized to 224 x 224 by `recipe.resample`; a zero-length vector stays 0, and
    `recipe.zero_invalid` zeroes T where the resized depth is 0. Depth and eye in one unit
    (metres); K (3, 3) at the (W, H) image resolution."""
    W, H = size
    d = np.asarray(Image.fromarray(np.asarray(depth, np.float32)).resize((INPUT_SIZE, INPUT_SIZE),
                                                                        _FILTERS[recipe.resample]))
    grid = np.arange(INPUT_SIZE, dtype=np.float64)
    t = normalize(back_project(grid[None, :] * (W / INPUT_SIZE), grid[:, None] * (H / INPUT_SIZE), d, K)
                  - np.asarray(eye, np.float64), eps=np.finfo(np.float64).tiny)
    if recipe.zero_invalid:
        t[d == 0] = 0
    return t.astype(np.float32)[None]


# --- the 3D step ---------------------------------------------------------------------------------

@dataclass
class GazePoint:
    """GFIE's 3D gaze-following output for one frame."""

    target_2d: np.ndarray  # (2,) heatmap argmax (column / w, row / h), normalised image coordinates
    point: np.ndarray      # (3,) float64 the chosen back-projected depth pixel, depth's unit (metres)
    direction: np.ndarray  # (3,) float64 unit eye -> point, or 0 when the chosen pixel has no depth
    window: tuple[int, int, int, int]  # u0, v0, u1, v1 full-resolution pixels (end-exclusive)


def _span(centre: float, n: int, ratio: float) -> tuple[int, int]:
    """The window [lo, hi) of ratio * n pixels around centre, shifted inside [0, n], truncated."""
    lo, hi = centre - n * ratio / 2, centre + n * ratio / 2
    if lo < 0:
        lo, hi = 0, n * ratio
    elif hi > n:
        lo, hi = n - n * ratio, n
    return int(lo), int(hi)


def gaze_point_3d(depth: np.ndarray, heatmap: np.ndarray, gaze: np.ndarray, eye: np.ndarray, K: np.ndarray,
                  ratio: float = WINDOW_RATIO) -> GazePoint:
    """GFIE's `strategy3dGazeFollowing` on one frame: (H, W) full-resolution depth (0 = unknown),
    (h, w) raw heatmap, g (3,), eye (3,) in the depth's unit, K (3, 3) at (W, H).

    When no pixel of the window has depth, every score is 0 and the argmax is the window's first
    pixel: point (0, 0, 0) and a zero direction, as GFIE's. So too when every pixel with depth
    scores below 0 and one without depth is in the window."""
    H, W = depth.shape
    h, w = heatmap.shape
    row, col = np.unravel_index(int(np.argmax(heatmap)), heatmap.shape)
    u0, u1 = _span(col * W / w, W, ratio)
    v0, v1 = _span(row * H / h, H, ratio)
    d = depth[v0:v1, u0:u1]
    u, v = np.arange(u0, u1, dtype=np.float64), np.arange(v0, v1, dtype=np.float64)
    points = back_project(u[None, :], v[:, None], d, K)
    dirs = normalize(points - np.asarray(eye, np.float64), eps=np.finfo(np.float64).tiny)
    dirs[d == 0] = 0
    i, j = np.unravel_index(int(np.argmax(dirs @ np.asarray(gaze, np.float64))), d.shape)
    return GazePoint(np.array([col / w, row / h]), points[i, j], dirs[i, j], (u0, v0, u1, v1))


__all__ = ["ALPHA", "INPUT_SIZE", "OUTPUT_SIZE", "RECIPES", "WINDOW_RATIO", "DepthRecipe", "GFIENet", "GGHDecoder",
           "GGHEncoder", "GGHModule", "GazePoint", "gaze_point_3d", "head_location", "load_gfie_net", "matrix_t",
           "scene_input", "stereo_fov"]
