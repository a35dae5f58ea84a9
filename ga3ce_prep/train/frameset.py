"""Which frames of a split are scored, and what became of every other frame the dataset has for it.

The official evaluations score the dataset's own rows: GFIE and CAD-120 every row of the test
annotation file, GAFA the frames of its non-overlapping 7-frame windows (`dataloader/gafa.py` with
interval 7 in `eval.py`; `datasets.gafa.window_starts`). `scored_frames` re-opens the dataset the
store was built from (its provenance names the adapter, the root and the options; `data`
overrides the root when the dataset has moved), takes the split's rows under the protocol, and
matches them with the store: a row is scored when the store holds it with a view prior and
ground truth; otherwise its reason is the failure record that dropped it (stage and error class),
a frame the run never read (`--limit`), a frame left out of the store's split for want of a view
prior or ground truth, or a frame the store does not know at all.

Without the dataset (moved, or a store built from generated data) the store's own frames of the
split stand for the rows, and the result says so (the frames the pipeline dropped are counted from
the failure table, whose split is not recorded).
"""
from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError, Ga3ceError
from ..frames import FrameRef
from ..store import ContextStore
from .dataset import ContextDataset

log = logging.getLogger("ga3ce_prep.train")

PROTOCOLS: dict[str, str] = {  # eval --frames: what is scored
    "all": "every frame of the split",
    "windows": "GAFA's 7-frame windows (raw-consecutive frames, interval 7)",
}


@dataclass
class ScoredFrames:
    """The frames a split is scored on under a protocol, and the reasons for the rest.

    rows: (N,) store rows scored, ascending (a ContextDataset's order). expected: M, the dataset's rows for the
    split under the protocol (N of them scored). front: (N,) bool, front (true gaze z <= 0) decided
    per window from its first frame (GAFA), or None: per frame from its own ground truth.
    unscored: reason -> frame ids (M - N in all). split_rows: the split's rows before the protocol
    chose among them. source: where the rows came from.
    """

    protocol: str
    source: str
    rows: np.ndarray
    expected: int
    split_rows: int
    unscored: dict[str, list[str]] = field(default_factory=dict)
    front: np.ndarray | None = None

    @property
    def scored(self) -> int:
        """N, the frames scored."""
        return int(len(self.rows))

    def as_dict(self) -> dict:
        """The JSON form: protocol, its description, source, expected, scored, split_rows, and
        unscored {reason: [ids]}."""
        return {"protocol": self.protocol, "description": PROTOCOLS[self.protocol], "source": self.source,
                "expected": self.expected, "scored": self.scored, "split_rows": self.split_rows,
                "unscored": self.unscored}


def gafa_windows(frames: list[FrameRef], interval: int = 7) -> tuple[list[FrameRef], np.ndarray]:
    """The frames of GAFA's windows over `frames` (each camera `sequence` on its own, by raw frame
    number `index`; `datasets.gafa.window_starts`) and, per frame (k,) bool, whether its window is
    "front": the window's first frame's ground-truth gaze has z <= 0 (GAFA's `test_step`)."""
    from ..datasets.gafa import WINDOW, window_starts

    seqs: dict[str, list[FrameRef]] = defaultdict(list)
    for f in frames:
        seqs[f.sequence or f.id].append(f)
    out: list[FrameRef] = []
    front: list[bool] = []
    for seq in seqs.values():
        seq.sort(key=lambda f: f.index)
        for i in window_starts(np.array([f.index for f in seq]), interval).tolist():
            out += seq[i:i + WINDOW]
            front += [bool(seq[i].gaze[2] <= 0)] * WINDOW
    return out, np.array(front, bool)


def _dataset_frames(store: ContextStore, data: str | Path | None) -> tuple[list[FrameRef] | None, str]:
    """The frames the run read (its adapter's, the first --limit of them), or None and why not."""
    from ..datasets import open_store_dataset

    ds = store.attrs.get("dataset", {})
    where = f"the {ds.get('name')} dataset at {data or ds.get('root')}"
    try:
        frames = list(open_store_dataset(ds, data).frames())
    except (Ga3ceError, KeyError, TypeError, ValueError, OSError) as e:
        return None, f"{where} cannot be read ({e})"
    return frames, where


def scored_frames(store: ContextStore, split: str, protocol: str = "all", data: str | Path | None = None,
                  ds: ContextDataset | None = None) -> ScoredFrames:
    """The frames of `split` to score under `protocol` ("all" or "windows", PROTOCOLS) and the
    reasons for the dataset's other rows (module docstring). data: the dataset's root, when not
    where the store's provenance says. ds: the split's ContextDataset, if already built.
    ConfigError for "windows" without the dataset (the windows need its every frame)."""
    if protocol not in PROTOCOLS:
        raise ConfigError(f"frames {protocol!r}: choose one of {', '.join(PROTOCOLS)}")
    ds = ds if ds is not None else ContextDataset(store, split)
    ids = store.frames["id"]
    row_of = {str(fid): r for r, fid in enumerate(ids.tolist())}
    frames, source = _dataset_frames(store, data)
    left = {int(r): reason for reason, rows in ds.left_out.items() for r in rows.tolist()}
    fail = store.failures
    dropped: dict[str, str] = {}  # frame id -> its first dropping failure (records come in stage order)
    for fid, stage, err, action in zip(*(np.asarray(fail.get(k, [])).tolist()
                                         for k in ("frame_id", "stage", "error", "action"))):
        if action == "dropped":
            dropped.setdefault(fid, f"dropped by the {stage} stage ({err})")
    scored: list[int] = []
    unscored: dict[str, list[str]] = defaultdict(list)
    if frames is None:
        if protocol == "windows":
            raise ConfigError(f"GAFA's windows need the dataset's frames, but {source}; pass --data ROOT "
                              f"(the dataset's root) or --frames all")
        log.warning("%s: %s; the store's frames of the split stand for its rows", store.path, source)
        rows = store.indices(split)
        for r in rows.tolist():
            if r in left:
                unscored[left[r]].append(str(ids[r]))
            else:
                scored.append(r)
        return ScoredFrames(protocol, f"the store's frames ({source}); the pipeline dropped {len(dropped)} frames "
                            "of all splits (failures table)", np.array(scored, np.int64), len(rows), len(rows),
                            dict(unscored))
    limit = (store.attrs.get("run") or {}).get("limit")
    run_ids = {f.id for f in (frames if limit is None else frames[:max(int(limit), 0)])}
    split_frames = [f for f in frames if f.split == split]
    front = None
    chosen = split_frames
    if protocol == "windows":
        chosen, window_front = gafa_windows(split_frames)
    keep = []
    for k, f in enumerate(chosen):
        r = row_of.get(f.id)
        if r is not None and r not in left and store.split_names[store.frames["split"][r]] == split:
            scored.append(r)
            keep.append(k)
        elif r is not None:
            unscored[left.get(r, f"in the store's {store.split_names[store.frames['split'][r]]} split")].append(f.id)
        elif f.id in dropped:
            unscored[dropped[f.id]].append(f.id)
        elif f.id not in run_ids:
            unscored[f"not read by the run (--limit {limit})"].append(f.id)
        else:
            unscored["not in the store"].append(f.id)
    order = np.argsort(np.array(scored, np.int64), kind="stable")
    if protocol == "windows":
        front = window_front[np.array(keep, np.int64)][order]
    return ScoredFrames(protocol, source, np.array(scored, np.int64)[order], len(chosen), len(split_frames),
                        dict(sorted(unscored.items(), key=lambda kv: -len(kv[1]))), front)
