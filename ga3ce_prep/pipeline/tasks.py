"""The work of one shard, as dask tasks: each task computes the stage entries of its shard that are
not in the cache yet, writes them atomically, and returns small `StageReport`s (never the arrays).

Tasks per shard (their dependencies are the stage dependencies):

    input     -> its entry (ok flags, failures)
    geometry  -> depth, objects, head entries (one task: the depth map is computed once and used by
                 both consumers; it is kept in the cache only with run.cache_depth_maps)
    pose      -> its entry
    view      -> its entry

Entry arrays (n = frames in the shard, ids for a sanity check; `new_entry` builds each layout):
    all:      ids (n,) str, ok (n,) bool, fail_idx (k,) int, fail_error (k,) str, fail_message (k,) str,
              seconds () float
    depth:    valid_frac, filled_frac (n,) float32 [, map_<i> (H, W) float32, valid_<i> (H, W) bool]
    objects:  count (n,) int32, n_dropped (n,) int32, xyz (m, 3) float32, area (m,) int32, score (m,) float32
    head:     head_pos (n, 3) float32
    pose:     pose (n, 30, 3) float32 (NaN where failed)
    view:     view (n, 3) float32
A frame whose upstream stage failed is skipped (ok False, no second failure record).
"""
from __future__ import annotations

import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import Ga3ceError
from ..frames import FrameRef
from ..skeleton import N_JOINTS
from ..stages.base import DepthMap
from .cache import Cache
from .config import StageConfig

GEOMETRY: tuple[str, ...] = ("depth", "objects", "head")  # the stages of the geometry task

_backends: dict[tuple, Any] = {}


@dataclass
class Shard:
    """One shard's frames and the cache key of every stage for it."""

    index: int
    frames: list[FrameRef]
    keys: dict[str, str] = field(default_factory=dict)

    @property
    def ids(self) -> np.ndarray:
        return np.array([f.id for f in self.frames], dtype=str)


@dataclass
class TaskEnv:
    """What every task needs besides its shard (sent to workers once per task, small)."""

    cache_root: Path
    data_root: Path
    stages: dict[str, StageConfig]
    cache_depth_maps: bool = False


@dataclass
class StageReport:
    """What a task did for one stage of one shard: computed it (False: found in the cache) and the
    seconds spent in the stage's backend."""

    stage: str
    frames: int
    computed: bool = False
    seconds: float = 0.0


def _single_threaded() -> None:
    """One thread per task: parallelism comes from dask workers, not from inside a frame."""
    import cv2

    if cv2.getNumThreads() != 1:
        cv2.setNumThreads(1)


def backend(env: TaskEnv, stage: str):
    """The stage's backend instance, built once per process."""
    sc = env.stages[stage]
    key = (stage, sc.backend, repr(sorted((k, str(v)) for k, v in sc.params.items())), str(env.data_root))
    b = _backends.get(key)
    if b is None:
        b = _backends[key] = sc.make(env.data_root)
    return b


def warm(env: TaskEnv) -> None:
    """Build every backend of the run in this process and let it import what it needs."""
    _single_threaded()
    for stage in env.stages:
        backend(env, stage).warm()


class StageEntry:
    """One stage's cache entry for one shard, filled frame by frame.

    columns: name -> (n, ...) array, row i set when frame i succeeds (the initial 0 or NaN stays
    where it did not); ragged: name -> empty (0, ...) array, each frame adds its (m_i, ...) rows,
    concatenated at save; arrays: whole arrays stored as they are (the cached depth maps).
    values: the backend's result for a frame -> its column values.
    """

    def __init__(self, stage: str, shard: Shard, values: Callable[[Any], dict[str, Any]] = lambda _: {},
                 ragged: dict[str, np.ndarray] | None = None, **columns: np.ndarray):
        self.stage, self.shard, self.values = stage, shard, values
        self.mask = np.zeros(len(shard.frames), bool)
        self.fail_idx: list[int] = []
        self.fail_error: list[str] = []
        self.fail_message: list[str] = []
        self.columns = columns
        self.empty = ragged or {}
        self.parts: dict[str, list[np.ndarray]] = {k: [] for k in self.empty}
        self.arrays: dict[str, np.ndarray] = {}
        self.seconds = 0.0

    def ok(self, i: int, **values: Any) -> None:
        """Frame i succeeded with these column values."""
        for k, v in values.items():
            if k in self.parts:
                self.parts[k].append(v)
            else:
                self.columns[k][i] = v
        self.mask[i] = True

    def fail(self, i: int, e: BaseException) -> None:
        """Frame i failed with `e`: one failure record (error class, message; for an unexpected error
        also where it happened). GA3CE_DEBUG=1 raises it instead."""
        if os.environ.get("GA3CE_DEBUG"):
            raise e
        msg = str(e) or type(e).__name__
        if not isinstance(e, Ga3ceError):  # an unexpected error: keep where it happened
            tb = traceback.extract_tb(e.__traceback__)
            if tb:
                msg += f" (at {Path(tb[-1].filename).name}:{tb[-1].lineno}; rerun with GA3CE_DEBUG=1 for the traceback)"
        self.fail_idx.append(i)
        self.fail_error.append(type(e).__name__)
        self.fail_message.append(msg)

    def attempt(self, i: int, fn: Callable[..., Any], *args: Any) -> Any:
        """fn(*args) for frame i, timed: its result (frame i ok with its values), or None after a
        failure record."""
        t = time.perf_counter()
        try:
            out = fn(*args)
            self.ok(i, **self.values(out))
            return out
        except Exception as e:  # noqa: BLE001 - every per-frame problem becomes a record
            self.fail(i, e)
            return None
        finally:
            self.seconds += time.perf_counter() - t

    def report(self, computed: bool) -> StageReport:
        return StageReport(self.stage, len(self.shard.frames), computed, self.seconds)

    def save(self, cache: Cache) -> StageReport:
        """Write the entry under the shard's key for this stage."""
        ragged = {k: np.concatenate(p).astype(self.empty[k].dtype) if p else self.empty[k]
                  for k, p in self.parts.items()}
        cache.save(self.stage, self.shard.keys[self.stage], {
            "ids": self.shard.ids, "ok": self.mask, "seconds": np.float64(self.seconds),
            "fail_idx": np.array(self.fail_idx, np.int64), "fail_error": np.array(self.fail_error, dtype=str),
            "fail_message": np.array(self.fail_message, dtype=str), **self.columns, **ragged, **self.arrays})
        return self.report(True)


def _shaped(v: Any, shape: tuple[int, ...], stage: str) -> np.ndarray:
    v = np.asarray(v, np.float32)
    if v.shape != shape:
        raise ValueError(f"{stage} backend returned shape {v.shape}, expected {shape}")
    return v


def new_entry(stage: str, shard: Shard) -> StageEntry:
    """An empty entry of `stage` for `shard`, with its columns (module docstring)."""
    n = len(shard.frames)
    if stage == "depth":  # DepthMap
        return StageEntry(stage, shard,
                          lambda dm: {"valid_frac": dm.valid.mean(), "filled_frac": (dm.depth > 0).mean()},
                          valid_frac=np.zeros(n, np.float32), filled_frac=np.zeros(n, np.float32))
    if stage == "objects":  # FrameObjects
        return StageEntry(stage, shard, lambda fo: {"count": len(fo.xyz), "n_dropped": fo.n_dropped, "xyz": fo.xyz,
                                                    "area": fo.area, "score": fo.score},
                          ragged={"xyz": np.zeros((0, 3), np.float32), "area": np.zeros(0, np.int32),
                                  "score": np.zeros(0, np.float32)},
                          count=np.zeros(n, np.int32), n_dropped=np.zeros(n, np.int32))
    if stage == "head":  # (3,) t_object
        return StageEntry(stage, shard, lambda hp: {"head_pos": hp}, head_pos=np.full((n, 3), np.nan, np.float32))
    if stage in ("pose", "view"):  # (N_JOINTS, 3) or (3,)
        shape = {"pose": (N_JOINTS, 3), "view": (3,)}[stage]
        return StageEntry(stage, shard, lambda v: {stage: _shaped(v, shape, stage)},
                          **{stage: np.full((n, *shape), np.nan, np.float32)})
    return StageEntry(stage, shard)  # input: ok flags and failures only


def run_frames(shard: Shard, fn: Callable[[FrameRef], Any], entry: StageEntry, only: np.ndarray | None = None) -> None:
    """entry.attempt(i, fn, frame) for every frame i of the shard (where `only` (n,) bool is True)."""
    for i, f in enumerate(shard.frames):
        if only is None or only[i]:
            entry.attempt(i, fn, f)


def _load_ok(cache: Cache, stage: str, shard: Shard) -> np.ndarray:
    e = cache.load(stage, shard.keys[stage])
    if e is None:
        raise RuntimeError(f"cache entry {stage}/{shard.keys[stage]} vanished: was the cache directory "
                           f"{cache.root} changed during the run? Rerun to recompute it")
    return e["ok"]


def input_task(env: TaskEnv, shard: Shard) -> list[StageReport]:
    """Check each frame (stages/input.py) and write the input entry."""
    cache = Cache(env.cache_root)
    if cache.has("input", shard.keys["input"]):
        return [StageReport("input", len(shard.frames))]
    _single_threaded()
    entry = new_entry("input", shard)
    run_frames(shard, backend(env, "input").check_frame, entry)
    return [entry.save(cache)]


def stage_task(env: TaskEnv, stage: str, shard: Shard, _upstream: Any = None) -> list[StageReport]:
    """A per-frame stage without depth: pose (N_JOINTS, 3) or view (3,)."""
    cache = Cache(env.cache_root)
    if cache.has(stage, shard.keys[stage]):
        return [StageReport(stage, len(shard.frames))]
    _single_threaded()
    entry = new_entry(stage, shard)
    run_frames(shard, getattr(backend(env, stage), stage), entry, only=_load_ok(cache, "input", shard))
    return [entry.save(cache)]


def _reusable_depth(cache: Cache, shard: Shard, cache_maps: bool) -> dict[str, np.ndarray] | None:
    """The shard's cached depth entry, or None when it must be computed and written again: it is
    unreadable, or run.cache_depth_maps is on and it lacks the maps of its ok frames."""
    e = cache.load("depth", shard.keys["depth"])
    if e is None or (cache_maps and not all(f"map_{i}" in e for i in np.flatnonzero(e["ok"]))):
        return None
    return e


def _depth_for(i: int, frame: FrameRef, depth: StageEntry, compute: Callable[[FrameRef], DepthMap],
               cached: dict[str, np.ndarray] | None, cache_maps: bool) -> DepthMap | None:
    """Frame i's depth map, None if it failed. With run.cache_depth_maps: the cached entry's map, or
    one computed and recorded with its map in `depth`; without: computed (recorded in `depth`, which
    is written only when no entry was cached)."""
    if cache_maps and cached is not None:
        return DepthMap(cached[f"map_{i}"], cached[f"valid_{i}"])
    dm = depth.attempt(i, compute, frame)
    if dm is not None and cache_maps:
        depth.arrays[f"map_{i}"], depth.arrays[f"valid_{i}"] = dm.depth, dm.valid
    return dm


def geometry_task(env: TaskEnv, shard: Shard, _upstream: Any = None) -> list[StageReport]:
    """Depth, then objects and head from it, for the frames that passed the input checks."""
    cache = Cache(env.cache_root)
    todo = {s for s in GEOMETRY if not cache.has(s, shard.keys[s])}
    if not todo:
        return [StageReport(s, len(shard.frames)) for s in GEOMETRY]
    _single_threaded()
    cached = None if "depth" in todo else _reusable_depth(cache, shard, env.cache_depth_maps)
    if cached is None:
        todo.add("depth")
    entries = {s: new_entry(s, shard) for s in GEOMETRY}
    compute = {s: getattr(backend(env, s), s) for s in GEOMETRY if s == "depth" or s in todo}
    ok = _load_ok(cache, "input", shard)
    if cached is not None:
        ok = ok & cached["ok"]  # a frame whose depth failed has no objects or head either
    for i in np.flatnonzero(ok):
        f = shard.frames[i]
        dm = _depth_for(i, f, entries["depth"], compute["depth"], cached, env.cache_depth_maps)
        if dm is None:
            continue
        for s in ("objects", "head"):
            if s in todo:
                entries[s].attempt(i, compute[s], f, dm)
    return [entries[s].save(cache) if s in todo else entries[s].report(False) for s in GEOMETRY]
