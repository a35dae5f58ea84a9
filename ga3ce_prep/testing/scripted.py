"""Small ONNX models with the official interfaces of MobileSAM and GAFA's GazeNet, for the tests
and benchmarks.

- `pooling_encoder(form)`: an "encoder" whose embedding is the 16x16 block mean of the normalised,
  padded input (channel c = RGB channel c % 3), in the normalised `[1, 3, 1024, 1024]` form or
  samexporter's `--use-preprocess` `[H, W, 3]` form (normalisation and padding inside the graph).
- `scripted_decoder(labels)`: a "decoder" whose masks come from a label image: the prompt's first
  point picks the label under it; mask tokens 0-2 are that label's region (predicted IoU 0.97,
  0.97, 0.92 for an object, 0.2 for the background label 0) and token 3 the whole frame (IoU 0.6).
  The low-res logits are +-8, postprocessed to `orig_im_size` exactly as the official export does.
  `single_mask=True`: one mask per prompt, as SAM's `--return-single-mask` export of one click
  (the best of tokens 1..3: token 1).
- `renamed(model, names)`: a copy with inputs/outputs renamed (exports that name tensors their own way).
- `centroid_gazenet()`: GAFA's view interface (estimators/view/gafa.py) whose gaze for each frame is
  a known function of its inputs (`centroid_gaze`, the same in numpy): the head mask's centroid,
  the window's summed body velocity and the frame's mean image value.
"""
from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import onnx
from onnx import TensorProto

from ..estimators.runtime.onnx_graph import GraphBuilder
from ..estimators.segment.amg import preprocess_shape
from ..estimators.segment.mobilesam_runners import PIXEL_MEAN, PIXEL_STD


def _pool_to_embedding(g: GraphBuilder, x: str) -> str:
    pooled = g.op("AveragePool", x, kernel_shape=[16, 16], strides=[16, 16])     # (1, 3, 64, 64)
    w = np.zeros((256, 3, 1, 1), np.float32)
    w[np.arange(256), np.arange(256) % 3] = 1.0
    return g.op("Conv", pooled, g.const(w))


def pooling_encoder(form: str = "normalised", input_name: str | None = None, size: int = 1024):
    """An encoder ModelProto. form "normalised": input [1, 3, size, size]; "preprocess": input
    [H, W, 3] RGB 0-255 (samexporter --use-preprocess). `size` != 1024 makes a contract-breaking file."""
    g = GraphBuilder(f"pooling_encoder_{form}")
    if form == "normalised":
        x = g.input(input_name or "image", [1, 3, size, size])
    elif form == "preprocess":
        img = g.input(input_name or "input_image", ["image_height", "image_width", 3])
        x = g.transpose(g.div(g.sub(img, g.const(PIXEL_MEAN)), g.const(PIXEL_STD)), [2, 0, 1])   # (3, H, W)
        hw = g.slice(g.op("Shape", x), [1], [3], [0])
        pad_hw = g.sub(g.const([1024, 1024], dtype=np.int64), hw)
        # begin (0, 0, 0), end (0, ph, pw)
        pads = g.concat([g.const([0, 0, 0], dtype=np.int64), g.const([0], dtype=np.int64), pad_hw], axis=0)
        x = g.op("Unsqueeze", g.op("Pad", x, pads), g.const([0], dtype=np.int64))
    else:
        raise ValueError(f"form must be 'normalised' or 'preprocess', got {form!r}")
    g.output(_pool_to_embedding(g, x), "image_embeddings")
    return g.model()


def low_res_labels(labels: np.ndarray) -> np.ndarray:
    """An (H, W) int label image -> the (256, 256) label map of the padded 1024 frame (nearest, cell
    centres), -1 in the padding."""
    h, w = labels.shape
    newh, neww = preprocess_shape(h, w)
    resized = cv2.resize(labels.astype(np.int32), (neww, newh), interpolation=cv2.INTER_NEAREST)
    canvas = np.full((1024, 1024), -1, np.int64)
    canvas[:newh, :neww] = resized
    return canvas[2::4, 2::4]


def scripted_decoder(labels: np.ndarray, batch_dynamic: bool = False, drop_input: str | None = None,
                     mask_input_size: int = 256, single_mask: bool = False):
    """A decoder ModelProto with the official inputs and outputs whose masks come from `labels`
    ((H, W) int, 0 = background). batch_dynamic: a symbolic batch axis on point_coords/labels (else
    fixed 1 as the official export). drop_input / mask_input_size make contract-breaking files.
    single_mask: outputs [B, 1, ...] (token 1), as a single-mask export answers one click."""
    lab = low_res_labels(labels)
    g = GraphBuilder("scripted_decoder")
    batch = "batch" if batch_dynamic else 1
    specs: list[tuple[str, list[Any]]] = [
        ("image_embeddings", [1, 256, 64, 64]), ("point_coords", [batch, "num_points", 2]),
        ("point_labels", [batch, "num_points"]), ("mask_input", [1, 1, mask_input_size, mask_input_size]),
        ("has_mask_input", [1]), ("orig_im_size", [2])]
    ins = {name: g.input(name, shape) for name, shape in specs if name != drop_input}
    coords = ins["point_coords"]
    first = g.reshape(g.slice(coords, [0], [1], [1]), [-1, 2])                     # (B, 2) first point
    cell = g.op("Floor", g.div(first, g.const(4.0)))
    cell = g.op("Clip", cell, g.const(0.0), g.const(255.0))
    cx = g.reshape(g.slice(cell, [0], [1], [1]), [-1])
    cy = g.reshape(g.slice(cell, [1], [2], [1]), [-1])
    flat = g.op("Cast", g.add(g.mul(cy, g.const(256.0)), cx), to=TensorProto.INT64)
    label = g.op("Gather", g.const(lab.reshape(-1), dtype=np.int64), flat, axis=0)  # (B,)
    label3 = g.reshape(label, [-1, 1, 1])
    same = g.op("Equal", g.const(lab[None], dtype=np.int64), label3)               # (B, 256, 256)
    obj = g.op("Where", same, g.const(8.0), g.const(-8.0))
    whole = g.add(g.mul(obj, g.const(0.0)), g.const(8.0))
    obj4 = g.op("Unsqueeze", obj, g.const([1], dtype=np.int64))
    low = g.concat([obj4, obj4, obj4, g.op("Unsqueeze", whole, g.const([1], dtype=np.int64))], axis=1)
    is_obj = g.op("Cast", g.op("Greater", label, g.const(0, dtype=np.int64)), to=TensorProto.FLOAT)
    q = g.add(g.const(0.2), g.mul(is_obj, g.const(0.77)))                            # 0.97 object, 0.2 background
    q = g.reshape(q, [-1, 1])
    iou = g.concat([q, q, g.sub(q, g.const(0.05)), g.add(g.mul(q, g.const(0.0)), g.const(0.6))], axis=1)
    # the official postprocessing: 1024x1024, crop to the resized image, resize to orig_im_size
    up = g.op("Resize", low, "", g.const([1.0, 1.0, 4.0, 4.0]), mode="linear",
              coordinate_transformation_mode="half_pixel")
    size = ins.get("orig_im_size") or g.const([480.0, 640.0])
    scale = g.div(g.const(1024.0), g.op("ReduceMax", size, keepdims=1))
    pre = g.op("Cast", g.op("Floor", g.add(g.mul(size, scale), g.const(0.5))), to=TensorProto.INT64)
    cropped = g.op("Slice", up, g.const([0, 0], dtype=np.int64), pre, g.const([2, 3], dtype=np.int64))
    sizes = g.concat([g.slice(g.op("Shape", low), [0], [2], [0]), g.op("Cast", size, to=TensorProto.INT64)], axis=0)
    masks = g.op("Resize", cropped, "", "", sizes, mode="linear", coordinate_transformation_mode="half_pixel")
    for value, name in ((masks, "masks"), (iou, "iou_predictions"), (low, "low_res_masks")):
        g.output(g.slice(value, [1], [2], [1]) if single_mask else value, name)
    return g.model()


class LabelDecoder:
    """`scripted_decoder`'s answers as a numpy `MaskDecoder` whose label image can change from frame
    to frame (set `labels` before each image): the reuse tests' decoder of a sequence. Multimask:
    tokens 1..3 are the label's region (IoU 0.97, 0.92 for an object, 0.2, 0.2, 0.15 for the
    background 0), logits +-8 at the low resolution."""

    batch_size = 64
    candidate_tokens = (1, 2, 3)

    def __init__(self, labels: np.ndarray):
        self.labels = labels
        self.calls = 0  # prompts asked for (predict_iou), to count what reuse decodes

    def set_image(self, image_embeddings: np.ndarray) -> None:
        self._low = low_res_labels(self.labels)

    def predict_iou(self, point_coords: np.ndarray, point_labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cell = np.clip(np.floor(np.asarray(point_coords)[:, 0] / 4.0), 0, 255).astype(np.int64)   # (B, 2) x, y
        label = self._low[cell[:, 1], cell[:, 0]]
        q = np.where(label > 0, 0.97, 0.2).astype(np.float32)
        self.calls += len(label)
        return np.stack([q, q, q - 0.05, np.full_like(q, 0.6)], axis=1), label

    def _logits(self, label: np.ndarray, token: np.ndarray) -> np.ndarray:
        obj = np.where(self._low[None] == label[:, None, None], 8.0, -8.0).astype(np.float32)
        return np.where(np.asarray(token)[:, None, None] == 3, np.float32(8.0), obj)

    def low_res_masks(self, state: np.ndarray, index: np.ndarray) -> np.ndarray:
        label = np.repeat(state[np.asarray(index)], 4)
        return self._logits(label, np.tile(np.arange(4), len(index))).reshape(-1, 4, 256, 256)

    def candidate_masks(self, state: np.ndarray, prompt: np.ndarray, token: np.ndarray) -> np.ndarray:
        return self._logits(state[np.asarray(prompt)], token)


def renamed(model: onnx.ModelProto, names: dict[str, str]) -> onnx.ModelProto:
    """A copy of `model` with graph inputs and outputs renamed ({old: new}), every use following."""
    m = onnx.ModelProto()
    m.CopyFrom(model)
    g = m.graph
    for v in [*g.input, *g.output]:
        v.name = names.get(v.name, v.name)
    for n in g.node:
        n.input[:] = [names.get(x, x) for x in n.input]
        n.output[:] = [names.get(x, x) for x in n.output]
    return m


def drawn_frame(h: int = 480, w: int = 640, seed: int = 0) -> np.ndarray:
    """A (h, w, 3) uint8 RGB test frame (the MobileSAM benchmark's): an RGB gradient with filled
    rectangles, an ellipse, a ring, a triangle and a diagonal line, Gaussian noise sigma 4 (like the
    frame the official generator was timed on)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([x * 255.0 / w, y * 255.0 / h, np.full((h, w), 128.0)], -1).astype(np.float32)
    cv2.rectangle(img, (50, 60), (200, 220), (200, 30, 30), -1)
    cv2.rectangle(img, (400, 300), (600, 450), (30, 200, 30), -1)
    cv2.rectangle(img, (480, 40), (600, 120), (90, 60, 160), -1)
    cv2.ellipse(img, (320, 150), (80, 50), 20, 0, 360, (30, 30, 220), -1)
    cv2.circle(img, (150, 380), 70, (240, 240, 0), -1)
    cv2.circle(img, (150, 380), 35, (20, 20, 20), -1)
    cv2.fillPoly(img, [np.array([[300, 420], [380, 300], [460, 420]])], (200, 120, 40))
    cv2.line(img, (0, 0), (w - 1, h - 1), (255, 255, 255), 3)
    img += rng.normal(0.0, 4.0, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def centroid_gaze(image: np.ndarray, head_mask: np.ndarray, body_dv: np.ndarray) -> np.ndarray:
    """(B, 7, 3) float64, what `centroid_gazenet` writes (not normalised) for image (B, 7, 3, H, W),
    head_mask (B, 7, 1, H, W), body_dv (B, 7, 2): per frame (cx - 95.5 + 100 D_x,
    cy - 127.5 + 100 D_y, 40 + 10 mean(image)), with (cx, cy) the head mask's centroid in crop
    pixels and D the body velocity summed over the window (the last frame's box centre minus the
    one before the window's)."""
    m = np.asarray(head_mask, np.float64)[:, :, 0]
    h, w = m.shape[-2:]
    area = m.sum((2, 3)) + 1e-3
    cx, cy = (m * np.arange(w)).sum((2, 3)) / area, (m * np.arange(h)[:, None]).sum((2, 3)) / area
    d = np.asarray(body_dv, np.float64).sum(1)[:, None]
    z = 40 + 10 * np.asarray(image, np.float64).mean((2, 3, 4))
    return np.stack([cx - 95.5 + 100 * d[..., 0], cy - 127.5 + 100 * d[..., 1], z], axis=-1)


def centroid_gazenet(window: int = 7, h: int = 256, w: int = 192) -> onnx.ModelProto:
    """A ModelProto with GAFA's view interface: image (B, window, 3, h, w), head_mask
    (B, window, 1, h, w), body_dv (B, window, 2) -> gaze (B, window, 3) = `centroid_gaze`."""
    g = GraphBuilder("centroid_gazenet")
    image = g.input("image", ["batch", window, 3, h, w])
    mask = g.input("head_mask", ["batch", window, 1, h, w])
    dv = g.input("body_dv", ["batch", window, 2])
    area = g.add(g.reduce_sum(mask, [2, 3, 4], keepdims=False), g.const(1e-3))             # (B, T)
    cx = g.div(g.reduce_sum(g.mul(mask, g.const(np.arange(w).reshape(1, 1, 1, 1, w))), [2, 3, 4], False), area)
    cy = g.div(g.reduce_sum(g.mul(mask, g.const(np.arange(h).reshape(1, 1, 1, h, 1))), [2, 3, 4], False), area)
    d = g.mul(g.reduce_sum(dv, [1], keepdims=False), g.const(100.0))                        # (B, 2)
    dx, dy = (g.op("Gather", d, g.const([k], dtype=np.int64), axis=1) for k in (0, 1))     # (B, 1)
    z = g.add(g.mul(g.op("ReduceMean", image, axes=[2, 3, 4], keepdims=0), g.const(10.0)), g.const(40.0))
    xyz = [g.add(g.sub(cx, g.const(95.5)), dx), g.add(g.sub(cy, g.const(127.5)), dy), z]
    g.output(g.concat([g.op("Unsqueeze", c, g.const([2], dtype=np.int64)) for c in xyz], axis=2), "gaze")
    m = g.model()
    m.graph.output[0].CopyFrom(onnx.helper.make_tensor_value_info("gaze", TensorProto.FLOAT, ["batch", window, 3]))
    return m
