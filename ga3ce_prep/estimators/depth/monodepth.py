"""Metric monocular depth from an ONNX export, through ONNX Runtime: one runner for every network
(`depth/onnx` on the user's file, `depth/fastdepth` on the registry's), configured by
`MonoDepthOptions`, with presets for the common exports (`PRESETS`; their sources: docs/models/depth.md,
"Presets").

`MonoDepthEstimator.predict(rgb, K)`:
1. crop: the largest centred crop of aspect `crop_aspect` (W:H; empty: the whole image);
2. resize to the network input (`network_size`): `stretch` to `size` (H, W) (unset: the file's fixed
   input size), or `keep_aspect`: the smallest scaling that makes both sides at least `size`, each
   side then rounded to the nearest multiple of `multiple`, never below `size` (Depth-Anything's
   "lower_bound" rule; ZoeDepth's "minimal" rule gives the same size for images at least its
   384 x 512); a file with a fixed input size must have the size the rule gives;
3. x = (pixel - mean) / std, pixels in `input_range` (0-1: RGB / 255), `channels` order, `layout`
   NCHW or NHWC, float32, batch 1;
4. the depth output (`output_name`, else output number `output_index`), squeezed to (h, w), to
   metres (`units`: m, cm, mm, or inverse_m = 1 / metres), times the focal rescale
   f_x' / `focal_px` when `focal_px` > 0 (f_x' = the frame's focal length in network-input pixels:
   for networks trained at one focal length, e.g. FastDepth's 199 px);
5. refused (FrameError naming the file and the units that would fit) when the median of the
   positive depths is outside `plausible_depth`;
6. resized back to the crop at the image resolution (bilinear); 0 (unknown) outside the crop and
   where the prediction is not positive or beyond the plausible maximum. `valid` = the predicted
   pixels (depth > 0).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, TypeVar

import cv2
import numpy as np

from ...errors import ConfigError, FrameError, ModelFileError
from ...frames import DepthMap, check_rgb
from ...params import param
from ...units import Units, check_plausible, to_metres
from ..runtime.onnx_runtime import RuntimeParams, create_session, resolve_providers

INTERPOLATION = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
T = TypeVar("T")


@dataclass(frozen=True, kw_only=True)
class MonoDepthOptions:
    """How a metric depth export is run; every field left null takes the preset's value."""

    size: tuple[int, ...] | None = param(
        # network input (H, W) pixels: stretch's exact size (null in
        # the preset: the file's fixed size), keep_aspect's lower bound
        None, minItems=2, maxItems=2, items={"minimum": 1})
    resize: Literal["stretch", "keep_aspect"] | None = (
        # stretch: to size exactly; keep_aspect: the smallest scaling with
        # both sides >= size, sides rounded to a multiple of `multiple`
        None)
    multiple: int | None = param(
        None, minimum=1)  # keep_aspect: each side a multiple of this (ZoeDepth 32, Depth-Anything 14)
    crop_aspect: tuple[int, ...] | None = param(
        # [W, H]: the network sees the largest centred crop of this aspect (FastDepth [4, 3]); []: the whole image
        None, maxItems=2, items={"minimum": 1})
    interpolation: Literal["area", "linear", "cubic"] | None = None  # OpenCV interpolation of the image resize
    channels: Literal["rgb", "bgr"] | None = None  # channel order the network reads
    input_range: Literal["0-1", "0-255"] | None = None  # pixel values before mean and std: RGB / 255, or RGB as is
    mean: tuple[float, ...] | None = param(
        None, minItems=3, maxItems=3)  # per channel, subtracted (in input_range units, channel order as fed)
    std: tuple[float, ...] | None = param(
        None, minItems=3, maxItems=3, items={"exclusiveMinimum": 0})  # per channel, divided by
    layout: Literal["nchw", "nhwc"] | None = None  # the input tensor's layout (batch 1)
    output_name: str | None = None  # the depth output's name; null: the output numbered output_index
    output_index: int | None = param(
        None, minimum=0)  # the depth output's position among the outputs, when output_name is null
    units: Units | None = None  # the output's unit: m, cm, mm, or inverse_m (1 / metres, inverted here)
    focal_px: float | None = param(
        # the focal length (network-input pixels) the network was trained
        # at: depth x (f_x in input pixels) / focal_px; 0: no rescale
        None, minimum=0)
    plausible_depth: tuple[float, ...] | None = param(
        # metres [min, max]: a frame whose median predicted depth is
        # outside is refused (wrong units?); pixels beyond max are unknown
        None, minItems=2, maxItems=2, items={"exclusiveMinimum": 0})


# The presets (docs/models/depth.md, "Presets", says where each value comes from). Changing one
# changes outputs: bump the backends' `version`.
_CUSTOM = MonoDepthOptions(
    size=None, resize="stretch", multiple=1, crop_aspect=(), interpolation="linear", channels="rgb",
    input_range="0-1", mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0), layout="nchw", output_name=None,
    output_index=0, units="m", focal_px=0.0, plausible_depth=(0.1, 100.0))
_DEPTH_ANYTHING_V2_METRIC = dataclasses.replace(
    _CUSTOM, size=(518, 518), resize="keep_aspect", multiple=14, interpolation="cubic", mean=IMAGENET_MEAN,
    std=IMAGENET_STD)
PRESETS: dict[str, MonoDepthOptions] = {
    # isl-org/ZoeDepth: RGB / 255 in, its resize and mean/std 0.5 live inside the exported graph
    # (PrepForMidas), img_size 384 x 512 keep-aspect at multiples of 32, `metric_depth` in metres
    "zoedepth": dataclasses.replace(_CUSTOM, size=(384, 512), resize="keep_aspect", multiple=32),
    # DepthAnything/Depth-Anything-V2 metric_depth `infer_image`: lower-bound 518 keep-aspect at
    # multiples of 14, bicubic, ImageNet mean/std on RGB / 255, metres (Hypersim: max 20 m)
    "depth-anything-v2-metric-indoor": _DEPTH_ANYTHING_V2_METRIC,
    # the same preprocessing; Virtual KITTI 2 weights (max 80 m)
    "depth-anything-v2-metric-outdoor": _DEPTH_ANYTHING_V2_METRIC,
    # FastDepth (NYU-Depth-v2) as estimators/depth/fastdepth.py describes it: 4:3 crop squashed to
    # 224 x 224, RGB / 255, metres at a 199 px focal length
    "fastdepth": dataclasses.replace(_CUSTOM, size=(224, 224), crop_aspect=(4, 3), interpolation="area",
                                     focal_px=199.0),
    # nothing assumed: whole image stretched to the file's fixed size, RGB / 255, NCHW, output 0, metres
    "custom": _CUSTOM,
}
Preset = Literal["zoedepth", "depth-anything-v2-metric-indoor", "depth-anything-v2-metric-outdoor", "fastdepth",
                 "custom"]


def resolve_options(preset: str, overrides: MonoDepthOptions) -> MonoDepthOptions:
    """The preset's options with every field `overrides` sets (not None) replaced."""
    base = PRESETS[preset]
    return dataclasses.replace(base, **{f.name: getattr(overrides, f.name) for f in dataclasses.fields(MonoDepthOptions)
                                        if getattr(overrides, f.name) is not None})


def required(value: T | None, name: str) -> T:
    """A field of resolved options (`resolve_options`: a preset sets every field but size and
    output_name); ConfigError naming the field when it is unset."""
    if value is None:
        raise ConfigError(f"depth options: {name} is unset; take the options from a preset (resolve_options)")
    return value


def centre_crop(width: int, height: int, aspect: tuple[int, ...]) -> tuple[int, int, int, int]:
    """The largest centred crop of aspect W:H = aspect (empty: the whole image) of a width x height
    image: (x0, y0, w, h) pixels."""
    if not aspect:
        return 0, 0, width, height
    aw, ah = aspect
    w, h = (width, int(round(width * ah / aw))) if width * ah <= height * aw else (int(round(height * aw / ah)), height)
    return (width - w) // 2, (height - h) // 2, w, h


def network_size(width: int, height: int, opt: MonoDepthOptions) -> tuple[int, int]:
    """The network input (H, W) for a width x height crop under `opt` (resize, size, multiple)."""
    th, tw = required(opt.size, "size")
    if opt.resize == "stretch":
        return th, tw
    s = max(th / height, tw / width)
    m = required(opt.multiple, "multiple")

    def side(x: float, lo: int) -> int:
        y = int(np.round(x / m) * m)
        return y if y >= lo else int(np.ceil(x / m) * m)

    return side(s * height, th), side(s * width, tw)


def focal_scale(fx: float, net_width: int, crop_width: int, focal_px: float) -> float:
    """The factor on a depth network's output for a camera of horizontal focal fx (image pixels)
    whose crop_width-pixel-wide crop became net_width pixels: (fx * net_width / crop_width) / focal_px."""
    return float(fx) * net_width / crop_width / focal_px


@dataclass(frozen=True)
class CropDepth:
    """A network's depth for one image. depth: (H, W) float32 metres at the image resolution, 0
    where unknown; valid: (H, W) bool, the predicted pixels; crop: (x0, y0, w, h) pixels the network saw."""

    depth: np.ndarray
    valid: np.ndarray
    crop: tuple[int, int, int, int]

    def as_depth_map(self) -> DepthMap:
        return DepthMap(self.depth, self.valid)


class MonoDepthEstimator:
    """One metric depth ONNX file run under `MonoDepthOptions` (fully resolved: no None but
    `size` and `output_name`). The file's interface is checked on load (ModelFileError naming the
    file): one float32 rank-4 image input with 3 channels where the layout puts them, a fixed
    input size if `resize` is stretch and `size` unset, and the depth output present."""

    def __init__(self, path: str | Path, opt: MonoDepthOptions,
                 runtime: RuntimeParams = RuntimeParams(),  # noqa: B008 - frozen dataclass: safe to share
                 what: str = "depth", fix: str = "the depth backend's units"):
        self.path, self.opt, self.what, self.fix = Path(path), opt, what, fix
        crop_aspect = required(opt.crop_aspect, "crop_aspect")
        plausible = required(opt.plausible_depth, "plausible_depth")
        if len(crop_aspect) not in (0, 2) or not plausible[0] < plausible[1]:
            raise ConfigError(f"{what}: crop_aspect {list(crop_aspect)} must be [W, H] or [], and plausible_depth "
                              f"{list(plausible)} [min, max] with min < max")
        self.session = create_session(self.path, resolve_providers(runtime.providers), runtime.threads, what)
        where = f"{what} ONNX {self.path}"
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1:
            raise ModelFileError(
                f"{where}: {len(inputs)} inputs ({[a.name for a in inputs]}); a depth export takes one image")
        inp = inputs[0]
        dims = tuple(d if isinstance(d, int) else None for d in (inp.shape or []))
        if len(dims) != 4 or inp.type != "tensor(float)":
            raise ModelFileError(f"{where}: input {inp.name!r} is {inp.type} {list(inp.shape or [])}; expected a "
                                 f"float32 image of rank 4 ({opt.layout})")
        c, (h, w) = (dims[1], dims[2:]) if opt.layout == "nchw" else (dims[3], dims[1:3])
        if c not in (3, None):
            raise ModelFileError(f"{where}: input {inp.name!r} {list(inp.shape)} has {c} channels where layout "
                                 f"{opt.layout} puts them; expected 3 "
                                 f"(set layout: {'nhwc' if opt.layout == 'nchw' else 'nchw'}?)")
        self.input_name = inp.name
        self.fixed = (h, w) if h is not None and w is not None else None
        if opt.resize == "stretch":
            size = opt.size or self.fixed
            if size is None:
                raise ModelFileError(f"{where}: the input {inp.name!r} {list(inp.shape)} has no fixed height "
                                     "and width; set the depth backend's size [H, W]")
            if opt.size is not None and self.fixed is not None and tuple(opt.size) != self.fixed:
                raise ModelFileError(f"{where}: the input is fixed at {self.fixed[0]}x{self.fixed[1]} (HxW) but size "
                                     f"is {list(opt.size)}")
            self.opt = dataclasses.replace(opt, size=tuple(size))
        elif opt.size is None:
            raise ModelFileError(f"{where}: resize keep_aspect needs a size [H, W] (the lower bound)")
        names = [o.name for o in outputs]
        if opt.output_name is not None:
            if opt.output_name not in names:
                raise ModelFileError(f"{where}: no output named {opt.output_name!r}; the outputs are {names}")
            self.output_name = opt.output_name
        else:
            index = required(opt.output_index, "output_index")
            if index >= len(names):
                raise ModelFileError(f"{where}: output_index {index} but the file has {len(names)} outputs {names}")
            self.output_name = names[index]
        self.mean = np.asarray(opt.mean, np.float32)
        self.std = np.asarray(opt.std, np.float32)

    def network_input(self, crop: np.ndarray) -> np.ndarray:
        """An (h, w, 3) uint8 RGB crop as the network's (1, 3, H, W) or (1, H, W, 3) float32 input."""
        opt = self.opt
        H, W = network_size(crop.shape[1], crop.shape[0], opt)
        if self.fixed is not None and (H, W) != self.fixed:
            raise FrameError(f"{self.what} ONNX {self.path}: a {crop.shape[1]}x{crop.shape[0]} image needs a {H}x{W} "
                             f"(HxW) input under resize {opt.resize}, but the file is fixed at {self.fixed[0]}x"
                             f"{self.fixed[1]}: export it at {H}x{W} (scripts/export_monodepth.py --image-size "
                             f"{crop.shape[1]}x{crop.shape[0]}), or set resize: stretch")
        interpolation = INTERPOLATION[required(opt.interpolation, "interpolation")]
        x = cv2.resize(crop, (W, H), interpolation=interpolation).astype(np.float32)
        if opt.input_range == "0-1":
            x = x / 255.0
        if opt.channels == "bgr":
            x = x[..., ::-1]
        x = (x - self.mean) / self.std
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None] if opt.layout == "nchw" else x[None], np.float32)

    def predict(self, rgb: np.ndarray, K: np.ndarray) -> CropDepth:
        """Depth of an (H, W, 3) uint8 RGB image with intrinsics K (3, 3) at its resolution."""
        opt = self.opt
        H, W = check_rgb(rgb).shape[:2]
        x0, y0, w, h = centre_crop(W, H, required(opt.crop_aspect, "crop_aspect"))
        x = self.network_input(rgb[y0:y0 + h, x0:x0 + w])
        raw = np.asarray(self.session.run([self.output_name], {self.input_name: x})[0])
        out = raw.squeeze()
        if out.ndim != 2:
            raise ModelFileError(f"{self.what} ONNX {self.path}: output {self.output_name!r} "
                                 f"has shape {list(raw.shape)}; "
                                 "expected one (h, w) depth map (with any size-1 batch or channel axes)")
        out = np.where(np.isfinite(out), out, 0).astype(np.float32)
        units, plausible = required(opt.units, "units"), required(opt.plausible_depth, "plausible_depth")
        d = to_metres(out, units)
        if opt.focal_px:
            d = d * focal_scale(K[0, 0], x.shape[3] if opt.layout == "nchw" else x.shape[2], w, opt.focal_px)
        check_plausible(d, out, units, plausible, f"{self.what} ONNX {self.path}", self.fix)
        d = cv2.resize(d, (w, h), interpolation=cv2.INTER_LINEAR)
        depth = np.zeros((H, W), np.float32)
        depth[y0:y0 + h, x0:x0 + w] = np.where(d <= plausible[1], np.maximum(d, 0), 0)
        return CropDepth(depth, depth > 0, (x0, y0, w, h))


__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "PRESETS", "CropDepth", "MonoDepthEstimator", "MonoDepthOptions", "Preset",
           "centre_crop", "check_plausible", "focal_scale", "network_size", "resolve_options", "to_metres"]
