"""A torch Dataset over a 3D context store, its collate, and object-count bucketing.

`ContextDataset` loads the store's arrays once (a few KB per frame) and yields per-frame samples:
view (3,), pose (30, 3) NaN rows = missing, head_pos (3,), gaze (3,), objects (n_i, 3), area (n_i,)
and the store row `index`, all torch tensors (metres, camera frame). `collate` pads a list of
samples into a `Batch` with a boolean object mask: to the batch's largest object count, or to a
fixed N_max (the dataset's `DatasetProfile.n_max`), keeping the largest masks (by pixel area) when a
frame has more. `ContextDataset.batch(indices)` builds the same Batch straight from the arrays
(vectorised gather; what the trainer uses). `BucketBatchSampler` groups frames of similar object
counts so per-batch padding stays small, without gathering a batch from one room ("mixed").

Frames with no finite view prior are left out; frames with unknown gaze are left out when
`require_gaze` (training, evaluation); `left_out` keeps their store rows by reason. Objects with
non-finite positions, and every object of a frame whose head position t_object is not finite, are
dropped at load, so such a frame is a valid sample with zero objects (the model's null token).
Missing pose joints stay NaN (the model's missing-joint policy handles them:
ga3ce_prep/model/egocentric.py).
"""
from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from ..store import ContextStore, open_store
from .profiles import DatasetProfile

log = logging.getLogger("ga3ce_prep.train")


@dataclass
class Batch:
    """A padded batch of B frames with S object slots (torch tensors).

    view, head_pos, gaze: (B, 3); pose: (B, 30, 3) NaN = missing; objects: (B, S, 3) metres, padding
    slots 0; mask: (B, S) bool, True = real object; index: (B,) int64 store rows.
    """

    view: torch.Tensor
    pose: torch.Tensor
    head_pos: torch.Tensor
    gaze: torch.Tensor
    objects: torch.Tensor
    mask: torch.Tensor
    index: torch.Tensor

    def to(self, device: str | torch.device) -> Batch:
        return Batch(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})

    def rows(self, sl: slice) -> Batch:
        """Frames `sl` of the batch, with the same object slots."""
        return Batch(**{f.name: getattr(self, f.name)[sl] for f in fields(self)})

    def __len__(self) -> int:
        return len(self.index)

    def split_by_count(self, parts: int) -> list[tuple[Batch, torch.Tensor]]:
        """The batch as up to `parts` batches of frames of similar object count, each keeping only
        the object slots its frames use (every real object kept), with the rows (int64) each took."""
        S = self.mask.shape[1]
        used = ((self.mask * torch.arange(1, S + 1, device=self.mask.device)).amax(1) if S
                else torch.zeros(len(self), dtype=torch.int64, device=self.mask.device))
        out = []
        for rows in torch.tensor_split(torch.argsort(used, stable=True), min(parts, len(self))):
            k = int(used[rows].max())
            sub = {f.name: getattr(self, f.name)[rows] for f in fields(self)}
            out.append((Batch(**{**sub, "objects": sub["objects"][:, :k], "mask": sub["mask"][:, :k]}), rows))
        return out


def store_fingerprint(store: ContextStore) -> str:
    """SHA-256 over the store's root attributes and every frame and object array: two stores
    with the same fingerprint hold the same data (checkpoints record it)."""
    h = hashlib.sha256(json.dumps(store.attrs, sort_keys=True, default=str).encode())
    for group in (store.frames, store.objects):
        for name in sorted(group):
            a = group[name]
            h.update(name.encode())
            h.update(str(a.shape).encode())
            if a.dtype.kind in "OUT":  # variable-length strings
                h.update("\x00".join(str(x) for x in a.ravel().tolist()).encode())
            else:
                h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


class ContextDataset(Dataset):
    """Per-frame GA3CE inputs of one or more splits of a store (see the module docstring).

    store: a path (opened and verified against its integrity record: `open_store`) or an already
    opened ContextStore (open it once and build one dataset per split).
    split: "train" | "val" | "test", a sequence of them, or None for every frame.
    require_gaze: leave out frames whose ground-truth gaze is unknown.
    max_frames: keep only this many frames (an evenly spaced subset, for short runs).
    only: keep only these store rows (k,) of the split (an evaluation protocol's frames).
    left_out: reason ("no view prior", "no ground-truth gaze") -> store rows of the split left out.
    """

    def __init__(self, store: ContextStore | str | Path, split: str | Sequence[str] | None = None,
                 require_gaze: bool = True, max_frames: int | None = None, only: np.ndarray | None = None):
        self.store = store if isinstance(store, ContextStore) else open_store(store, verify=True)
        s = self.store
        n = len(s)
        if split is None:
            rows = np.arange(n)
        else:
            names = [split] if isinstance(split, str) else list(split)
            rows = np.sort(np.concatenate([s.indices(name) for name in names]))
        if only is not None:
            rows = rows[np.isin(rows, only)]
        f = s.frames
        usable = np.isfinite(f["view"][rows]).all(1) & (np.linalg.norm(f["view"][rows], axis=1) > 0)
        self.left_out = {"no view prior": rows[~usable]}
        if require_gaze:
            gaze_ok = np.isfinite(f["gaze"][rows]).all(1)
            self.left_out["no ground-truth gaze"] = rows[usable & ~gaze_ok]
            usable &= gaze_ok
        self.n_no_view = len(self.left_out["no view prior"])
        self.n_no_gaze = len(self.left_out.get("no ground-truth gaze", ()))
        rows = rows[usable]
        if max_frames is not None and max_frames < len(rows):
            rows = rows[np.linspace(0, len(rows) - 1, max_frames).round().astype(np.int64)]
        if self.n_no_view or self.n_no_gaze:
            log.info("%s: left out %d frames without a view prior and %d without ground-truth gaze",
                     s.path, self.n_no_view, self.n_no_gaze)
        self.rows = rows
        self.xyz, self.area, start, count = s.usable_objects
        self.obj_start, self.obj_count = start[rows], count[rows]
        self.view = np.ascontiguousarray(f["view"][rows], np.float32)
        self.view /= np.linalg.norm(self.view, axis=1, keepdims=True)
        self.pose = np.ascontiguousarray(f["pose"][rows], np.float32)
        self.head_pos = np.ascontiguousarray(f["head_pos"][rows], np.float32)
        self.gaze = np.ascontiguousarray(f["gaze"][rows], np.float32)
        self.scene = np.asarray(f["scene"][rows])

    @property
    def profile(self) -> DatasetProfile:
        """The per-dataset constants of the store's dataset."""
        return DatasetProfile.for_store(self.store)

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        """Frame i of this dataset: view, pose, head_pos, gaze, objects (n_i, 3), area (n_i,), index."""
        sl = slice(int(self.obj_start[i]), int(self.obj_start[i] + self.obj_count[i]))
        return {"view": torch.from_numpy(self.view[i]), "pose": torch.from_numpy(self.pose[i]),
                "head_pos": torch.from_numpy(self.head_pos[i]), "gaze": torch.from_numpy(self.gaze[i]),
                "objects": torch.from_numpy(self.xyz[sl]), "area": torch.from_numpy(self.area[sl]),
                "index": torch.tensor(int(self.rows[i]))}

    def batch(self, indices: np.ndarray | Sequence[int], n_max: int | None = None) -> Batch:
        """The Batch of dataset positions `indices`, gathered in one vectorised step; identical
        to collate([self[i] for i in indices], n_max)."""
        idx = np.asarray(indices, dtype=np.int64)
        count = self.obj_count[idx]
        if n_max is not None:
            count = np.minimum(count, n_max)
        S = int(n_max) if n_max is not None else int(count.max(initial=0))
        slot = np.arange(S)
        mask = slot[None, :] < count[:, None]
        src = np.where(mask, self.obj_start[idx][:, None] + slot[None, :], 0)
        objects = (self.xyz[src.ravel()].reshape(len(idx), S, 3) if len(self.xyz)
                   else np.zeros((len(idx), S, 3), np.float32))
        objects = objects * mask[..., None]
        return Batch(view=torch.from_numpy(self.view[idx]), pose=torch.from_numpy(self.pose[idx]),
                     head_pos=torch.from_numpy(self.head_pos[idx]), gaze=torch.from_numpy(self.gaze[idx]),
                     objects=torch.from_numpy(objects.astype(np.float32, copy=False)),
                     mask=torch.from_numpy(mask), index=torch.from_numpy(self.rows[idx]))


def collate(samples: Sequence[dict[str, torch.Tensor]], n_max: int | None = None) -> Batch:
    """Pad per-frame samples into a Batch (a DataLoader collate_fn: functools.partial(collate,
    n_max=168) for fixed padding). n_max None pads to the batch's largest object count; an int
    pads every frame to exactly n_max slots, keeping each frame's n_max largest masks by area."""
    counts = [len(s["objects"]) for s in samples]
    S = int(n_max) if n_max is not None else max(counts, default=0)
    B = len(samples)
    objects = torch.zeros(B, S, 3)
    mask = torch.zeros(B, S, dtype=torch.bool)
    for b, s in enumerate(samples):
        obj = s["objects"]
        if len(obj) > S:
            obj = obj[torch.argsort(s["area"].to(torch.float64), descending=True, stable=True)[:S]]
        objects[b, :len(obj)] = obj
        mask[b, :len(obj)] = True
    stack = lambda k: torch.stack([s[k] for s in samples])  # noqa: E731
    return Batch(view=stack("view"), pose=stack("pose"), head_pos=stack("head_pos"), gaze=stack("gaze"),
                 objects=objects, mask=mask, index=stack("index"))


BATCHINGS: tuple[str, ...] = ("mixed", "sorted", "shuffled")


class BucketBatchSampler(Sampler[list[int]]):
    """Training batches that keep per-batch object padding small (a DataLoader batch_sampler, or
    iterate it). Seeded by (seed, epoch): call set_epoch(e). `batching`:

    - "shuffled" (the default): plain shuffled batches (padding to nearly the largest count of
      all; `train_step(parts=)` takes most of that padding back).
    - "mixed": frames ranked by object count (ties broken at random) and cut into
      `groups` groups of equal size; each group is shuffled and cut into batches, and the batches
      of all groups shuffled. A batch pads to its group's largest count and draws from a 1/groups
      share of the frames, so it mixes many rooms.
    - "sorted": shuffled, cut into windows of `window` batches and sorted by count inside each
      window: the least padding, but a room's frames have nearly the same count, so each batch
      holds frames of one or two rooms.

    shuffle=False gives batches in count order whatever the batching (evaluation).
    """

    def __init__(self, counts: np.ndarray, batch_size: int, seed: int = 0, batching: str = "shuffled",
                 shuffle: bool = True, groups: int = 4, window: int = 64, drop_last: bool = False):
        if batching not in BATCHINGS:
            raise ValueError(f"batching must be one of {BATCHINGS}, got {batching!r}")
        self.counts = np.asarray(counts)
        self.batch_size, self.seed, self.batching, self.shuffle = batch_size, seed, batching, shuffle
        self.groups, self.window, self.drop_last = groups, window, drop_last
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _cut(self, order: np.ndarray) -> list[np.ndarray]:
        bs, n = self.batch_size, len(order)
        return [order[i:i + bs] for i in range(0, n, bs) if not self.drop_last or i + bs <= n]

    def batches(self) -> list[np.ndarray]:
        n, bs = len(self.counts), self.batch_size
        rng = np.random.default_rng([self.seed, self.epoch])
        if not self.shuffle:
            return self._cut(np.argsort(self.counts, kind="stable"))
        order = rng.permutation(n)
        if self.batching == "mixed":
            ranked = order[np.argsort(self.counts[order], kind="stable")]
            out = [b for g in np.array_split(ranked, self._n_groups()) for b in self._cut(rng.permutation(g))]
        else:
            if self.batching == "sorted" and n:
                w = bs * self.window
                order = np.concatenate([c[np.argsort(self.counts[c], kind="stable")]
                                        for c in np.split(order, range(w, n, w))])
            out = self._cut(order)
        return [out[j] for j in rng.permutation(len(out))]

    def __iter__(self) -> Iterator[list[int]]:
        return (b.tolist() for b in self.batches())

    def _n_groups(self) -> int:
        """Count groups of "mixed": `groups`, fewer when there are not enough frames for a batch each."""
        return max(1, min(self.groups, len(self.counts) // max(self.batch_size, 1)))

    def __len__(self) -> int:
        n, bs = len(self.counts), self.batch_size
        sizes = [len(g) for g in np.array_split(np.arange(n), self._n_groups())] \
            if self.batching == "mixed" and self.shuffle else [n]
        return sum(s // bs if self.drop_last else -(-s // bs) for s in sizes)
