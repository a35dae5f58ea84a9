"""Finalize: consolidate the shards' cache entries into the Zarr store, atomically.

A local store is written to `<scratch>/partial.zarr` shard by shard (memory: one shard's entries
plus the writer's chunk buffers), flushed to disk, then renamed over `--out` (the previous store, if
any, is moved aside to `<scratch>/previous.zarr` first and removed after). The scratch directory is
on the output's filesystem, so the rename never crosses filesystems (`scratch_dir`): the work
directory when a rename from there reaches `--out` (the default `<out>.work`), else `<out>.finalize`
beside `--out` (a work directory on another disk or on object storage), removed after the commit. A
store on object storage, where there is no rename, is committed by its root metadata instead: a
store reads as finished only once its root attributes (schema_version, the run key, the integrity
record) are there (`store.open_store`, `_finished_counts`), so the previous store's root attributes
are removed first (one PUT), then its other objects, then the new arrays are written in place and
the root attributes last (one PUT: the commit). Either way a run killed during finalize leaves no
half store that reads as finished under `--out`; the next run writes it again from the cache. If
`--out` already holds an intact store (`store.store_problems`) of the same run key (same frames,
stages, parameters and inputs), finalize does nothing. A cache entry that is missing or damaged
(`Cache.load` removes it) stops finalize with `LostEntries` once every shard has been looked at: the
run computes them again and finalizes again (run.py).

Which frames are kept (docs/pipeline.md): a failure of input, depth, head or view drops the frame;
a failure of objects keeps it with zero objects; a failure of pose keeps it with a NaN pose.
Every failure is a `failures/*` record (frame id, stage, error class, message, action).
"""
from __future__ import annotations

import errno
import logging
import os
import shutil
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import StoreError
from ..skeleton import N_JOINTS
from ..stages import DROPS_FRAME, STAGES
from ..store import SOURCE_STAGES, UNFINISHED, StoreWriter, store_problems
from .cache import Cache
from .faults import fault
from .location import Location, filesystem, is_remote
from .tasks import Shard

log = logging.getLogger("ga3ce_prep.pipeline")


class LostEntries(StoreError):
    """Cache entries finalize needs are missing or were damaged (and removed): computing them
    again repairs the cache."""

    def __init__(self, lost: list[str]):
        self.lost = lost
        shown = ", ".join(lost[:4]) + (f" and {len(lost) - 4} more" if len(lost) > 4 else "")
        super().__init__(f"{len(lost)} cache entries are missing or were damaged ({shown})")


@dataclass
class FinalizeCounts:
    """What finalize wrote: counts only (deterministic). The store's attrs["summary"] holds them
    under these names."""

    frames_total: int = 0                                              # frames in the dataset (or --limit)
    frames_kept: int = 0                                               # frames in the store
    objects: int = 0
    obj_count_hist: dict[str, int] = field(default_factory=dict)       # objects per frame -> frames
    failures: dict[str, dict[str, int]] = field(default_factory=dict)  # stage -> error class -> n
    dropped_by_stage: dict[str, int] = field(default_factory=dict)
    degraded_by_stage: dict[str, int] = field(default_factory=dict)
    masks_dropped_few_points: int = 0

    @property
    def frames_dropped(self) -> int:
        return self.frames_total - self.frames_kept


def _entries(cache: Cache, shard: Shard, lost: list[str]) -> dict[str, dict[str, np.ndarray]]:
    """The shard's entry of every stage; the missing or damaged ones are added to `lost` instead."""
    out = {}
    for stage in STAGES:
        e = cache.load(stage, shard.keys[stage])
        if e is None:
            lost.append(f"{stage} of shard {shard.index}")
            continue
        if e["ids"].tolist() != shard.ids.tolist():
            raise StoreError(f"cache entry {cache.path(stage, shard.keys[stage])} belongs to other frames; "
                             f"remove {cache.root} and rerun")
        out[stage] = e
    return out


def _fsync_tree(root: Path) -> None:
    for dirpath, _, files in os.walk(root):
        for name in files:
            fd = os.open(os.path.join(dirpath, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


def shard_block(shard: Shard, e: dict[str, dict[str, np.ndarray]], counts: FinalizeCounts):
    """One shard's kept frames (dict of arrays), objects, and failure records."""
    n = len(shard.frames)
    drop = np.zeros(n, bool)
    fail_rows: list[tuple[str, str, str, str, str]] = []
    for stage in STAGES:
        entry = e[stage]
        for i, err, msg in zip(entry["fail_idx"].tolist(), entry["fail_error"].tolist(),
                               entry["fail_message"].tolist()):
            action = "dropped" if DROPS_FRAME[stage] else "degraded"
            if DROPS_FRAME[stage]:
                drop[i] = True
                counts.dropped_by_stage[stage] = counts.dropped_by_stage.get(stage, 0) + 1
            else:
                counts.degraded_by_stage[stage] = counts.degraded_by_stage.get(stage, 0) + 1
            counts.failures.setdefault(stage, {})
            counts.failures[stage][err] = counts.failures[stage].get(err, 0) + 1
            fail_rows.append((shard.frames[i].id, stage, err, msg, action))
    # a frame is kept only if every dropping stage ran and succeeded for it
    for stage in STAGES:
        if DROPS_FRAME[stage]:
            drop |= ~e[stage]["ok"]
    keep = ~drop
    obj = e["objects"]
    obj_count = np.where(obj["ok"], obj["count"], 0).astype(np.int32)
    starts = np.concatenate([[0], np.cumsum(obj["count"])[:-1]]).astype(np.int64)
    sel = np.concatenate([np.arange(starts[i], starts[i] + obj["count"][i]) for i in np.flatnonzero(keep & obj["ok"])]
                         or [np.zeros(0, np.int64)]).astype(np.int64)
    counts.masks_dropped_few_points += int(obj["n_dropped"][keep].sum())
    fr = [shard.frames[i] for i in np.flatnonzero(keep)]

    def stack(attr: str, shape: tuple[int, ...], dtype=np.float32) -> np.ndarray:
        return np.array([np.asarray(getattr(f, attr), dtype) for f in fr], dtype).reshape(len(fr), *shape)

    pose = e["pose"]["pose"][keep]
    pose[~e["pose"]["ok"][keep]] = np.nan
    frames = {
        "id": np.array([f.id for f in fr], dtype=str),
        "split": [f.split for f in fr], "scene": [f.scene for f in fr],
        "K": stack("K", (3, 3)), "image_size": np.array([f.image_size for f in fr], np.int32).reshape(len(fr), 2),
        "head_box": stack("head_box", (4,)), "body_box": stack("body_box", (4,)),
        "head_pos": e["head"]["head_pos"][keep], "pose": pose.reshape(len(fr), N_JOINTS, 3),
        "view": e["view"]["view"][keep],
        **{f"{st}_source": e[st]["source"][keep] if "source" in e[st] else np.zeros(int(keep.sum()), np.int8)
           for st in SOURCE_STAGES},
        "gaze": stack("gaze", (3,)), "eye": stack("eye", (3,)),
        "gaze_target": stack("gaze_target", (3,)),
        "obj_count": obj_count[keep],
    }
    objects = {"xyz": obj["xyz"][sel], "area": obj["area"][sel], "score": obj["score"][sel]}
    counts.frames_total += n
    counts.frames_kept += int(keep.sum())
    counts.objects += len(sel)
    for c, k in Counter(obj_count[keep].tolist()).items():
        counts.obj_count_hist[str(c)] = counts.obj_count_hist.get(str(c), 0) + k
    return frames, objects, fail_rows


def finalize(shards: list[Shard], cache: Cache, out: Location, work: Location, attrs: dict[str, Any],
             run_key: str, sources: dict[str, tuple[str, ...]], progress: bool = True) -> tuple[FinalizeCounts, bool]:
    """Write the store at `out` (a local path or a URL) from the cache (see the module docstring).
    Returns the counts and whether anything was written (False: `out` was already this run's
    store). sources: per stage of store.SOURCE_STAGES the names behind frames/<stage>_source.
    `work` may be anywhere (another filesystem, a URL): a local store is built in `scratch_dir`."""
    done = _finished_counts(out, run_key)
    if done is not None:
        return done, False
    if is_remote(out):
        _uncommit(str(out))
        target: Location = out
    else:
        scratch = scratch_dir(Path(out), work)
        target = scratch / "partial.zarr"
        if target.exists():
            shutil.rmtree(target)
    writer = StoreWriter(target, overwrite=True)
    counts = _write_shards(shards, cache, writer, progress)
    writer.flush(sources)
    attrs = {**attrs, "summary": asdict(counts), "run": {**attrs.get("run", {}), "key": run_key}}
    if is_remote(out):
        fault("finalize.swap")
        writer.commit(attrs)
    else:
        writer.commit(attrs)
        _swap(Path(target), Path(out), scratch)
        if scratch != Path(work):
            shutil.rmtree(scratch)
    return counts, True


def scratch_dir(out: Path, work: Location) -> Path:
    """Where finalize builds the local store `out`: the work directory when a rename from there
    reaches `out`'s directory (one filesystem and mount), else `<out>.finalize` beside `out` (kept
    apart by the output's lock, `<out>.lock`). Asked by trying a rename, since two mounts of one
    filesystem share a device number yet refuse renames between them (EXDEV)."""
    if not is_remote(work):
        probe, landed = Path(work) / "rename-probe", out.with_name(out.name + ".rename-probe")
        probe.touch()
        try:
            os.rename(probe, landed)
            landed.unlink()
            return Path(work)
        except OSError as e:
            probe.unlink(missing_ok=True)
            if e.errno != errno.EXDEV:
                raise
    return out.with_name(out.name + ".finalize")


def _write_shards(shards: list[Shard], cache: Cache, writer: StoreWriter, progress: bool) -> FinalizeCounts:
    """Every shard's kept frames, objects and failure records, appended in order; LostEntries (nothing
    appended past the first) when entries are missing or damaged, once every shard was looked at."""
    from tqdm import tqdm

    counts = FinalizeCounts()
    lost: list[str] = []
    for shard in tqdm(shards, desc="finalize", unit="shard", disable=not progress, leave=False):
        entries = _entries(cache, shard, lost)
        if lost:
            continue  # only look for more: the store is written once every entry is there
        frames, objects, fails = shard_block(shard, entries, counts)
        frames["split"] = np.array([_split_code(s) for s in frames["split"]], np.int8)
        frames["scene"] = np.array([writer.scene_code(s) for s in frames["scene"]], np.int32)
        writer.append_frames(frames, objects)
        if fails:
            cols = list(zip(*fails))
            writer.append_failures({k: np.array(v, dtype=str) for k, v in
                                    zip(("frame_id", "stage", "error", "message", "action"), cols)})
        fault("finalize.shard")
    if lost:
        raise LostEntries(lost)
    counts.obj_count_hist = {k: counts.obj_count_hist[k] for k in sorted(counts.obj_count_hist, key=int)}
    return counts


def _swap(partial: Path, out: Path, scratch: Path) -> None:
    """Rename the finished partial store over `out`, the previous store moved aside (to `scratch`,
    on the output's filesystem) first, and back when the rename is refused."""
    _fsync_tree(partial)
    old = scratch / "previous.zarr"
    if old.exists():
        shutil.rmtree(old)
    fault("finalize.swap")
    if out.exists():
        os.rename(out, old)
        fault("finalize.aside")
    try:
        os.rename(partial, out)
    except OSError:  # refused (a permission, a lost mount): the previous store goes back, if it can
        if old.exists() and not out.exists():
            os.rename(old, out)
        raise
    if old.exists():
        shutil.rmtree(old)


def _uncommit(out: str) -> None:
    """Make the remote store at `out` (if any) read as unfinished, then remove all of it but its
    root metadata (which StoreWriter replaces): first its root attributes go (one PUT), so no
    moment shows a finished store with parts missing, and `out` is a store of ours throughout."""
    import zarr

    fs = filesystem(out)
    root_meta = fs._strip_protocol(f"{out}/zarr.json")
    if not fs.exists(root_meta):
        return
    zarr.open_group(out, mode="r+").attrs.put(dict(UNFINISHED))
    fault("finalize.aside")
    rest = [f for f in fs.find(out) if f != root_meta]
    if rest:
        fs.rm(rest)


def _split_code(split: str) -> int:
    from ..frames import SPLITS

    try:
        return SPLITS.index(split)
    except ValueError:
        raise StoreError(f"split {split!r} is not one of {list(SPLITS)} (adapter bug)") from None


def _finished_counts(out: Location, run_key: str) -> FinalizeCounts | None:
    """The counts of the store at `out` if it is an intact finished store of this run key, else None."""
    try:
        import zarr

        attrs: dict[str, Any] = dict(zarr.open_group(str(out), mode="r").attrs)  # JSON
    except Exception:  # no store, or not a store
        return None
    if (attrs.get("run") or {}).get("key") != run_key:
        return None
    try:
        problems = store_problems(out)
    except StoreError as e:  # no integrity record: a store of schema < 1.3 cannot have this run key
        problems = [str(e)]
    if problems:
        log.warning("%s is damaged (%s): writing it again", out, "; ".join(problems[:3]))
        return None
    return FinalizeCounts(**attrs["summary"])
