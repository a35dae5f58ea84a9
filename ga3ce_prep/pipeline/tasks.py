"""The work of one shard, as dask tasks: each task computes the stage entries of its shard that are
not in the cache yet, writes them atomically, and returns small `StageReport`s (never the arrays).

Tasks per shard (`task_stages`; their dependencies are the stages' effective upstream):

    input     -> its entry (ok flags, failures)
    geometry  -> depth and every stage that reads the depth map: objects, head, and pose when its
                 backend refines with depth (one task: the depth map is computed once and used by
                 every consumer; it is kept in the cache only with run.cache_depth_maps)
    pose      -> its entry (when it does not read the depth map)
    view      -> its entry
A stage reading another stage's output (`Backend.needs`, e.g. a view falling back to the pose)
gets it from that stage's cache entry, or from the same task when both run there.
A windowed backend (`Backend.window`) gets each frame's `frames.Window` from `Shard.windows`:
FrameRefs of neighbouring frames, possibly of other shards, whose pixels it reads itself.

Entry arrays (n = frames in the shard, ids for a sanity check; `new_entry` builds each layout):
    all:      ids (n,) str, ok (n,) bool, fail_idx (k,) int, fail_error (k,) str, fail_message (k,) str,
              seconds () float
    depth:    valid_frac, filled_frac (n,) float32 [, map_<i> (H, W) float32, valid_<i> (H, W) bool]
    objects:  count (n,) int32, n_dropped (n,) int32, xyz (m, 3) float32, area (m,) int32, score (m,) float32
    head:     head_pos (n, 3) float32
    pose:     pose (n, 30, 3) float32 (NaN where failed)
    view:     view (n, 3) float32
    + with a backend that declares `sources`: source (n,) int8 (index into them, -1 where failed)
A frame whose dropping upstream stage (input, depth) failed is skipped (ok False, no second
failure record); an optional upstream that failed for a frame (pose) is passed as NaN.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DEBUG_HINT, FrameError, Ga3ceError, StoreError, where_raised
from ..frames import FrameRef, Window
from ..skeleton import N_JOINTS
from ..stages import call_backend, dependency_order
from ..stages.base import DepthMap, Sourced
from .cache import Cache
from .config import StageConfig
from .faults import fault

VALUE_COLUMN = {"pose": "pose", "view": "view", "head": "head_pos"}  # a stage's per-frame value in its entry

_backends: dict[tuple, Any] = {}


@dataclass
class Shard:
    """One shard's frames, the cache key of every stage for it, and per windowed stage its frames'
    windows (`frames.Window`: FrameRefs, possibly of other shards)."""

    index: int
    frames: list[FrameRef]
    keys: dict[str, str] = field(default_factory=dict)
    windows: dict[str, list[Window]] = field(default_factory=dict)

    @property
    def ids(self) -> np.ndarray:
        return np.array([f.id for f in self.frames], dtype=str)


@dataclass
class TaskEnv:
    """What every task needs besides its shard (sent to workers once per task, small)."""

    cache_root: Path | str  # a local directory or a URL
    data_root: Path
    stages: dict[str, StageConfig]
    upstream: dict[str, tuple[str, ...]]  # each stage's effective upstream (stages.upstream_of)
    cache_depth_maps: bool = False


def task_stages(upstream: dict[str, tuple[str, ...]]) -> dict[str, tuple[str, ...]]:
    """The stages each task kind computes, in dependency order (module docstring)."""
    order = dependency_order(upstream)
    geometry = tuple(s for s in order if s == "depth" or "depth" in upstream[s])
    # in an order where every kind comes after the kinds it waits for (pose never reads the view)
    kinds: dict[str, tuple[str, ...]] = {"input": ("input",)}
    if "pose" not in geometry:
        kinds["pose"] = ("pose",)
    kinds["geometry"] = geometry
    if "view" not in geometry:
        kinds["view"] = ("view",)
    return kinds


def task_upstream(upstream: dict[str, tuple[str, ...]]) -> dict[str, tuple[str, ...]]:
    """The task kinds each task kind waits for."""
    kinds = task_stages(upstream)
    home = {s: k for k, stages in kinds.items() for s in stages}
    return {k: tuple(dict.fromkeys(home[u] for s in stages for u in upstream[s] if home[u] != k))
            for k, stages in kinds.items()}


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
                 ragged: dict[str, np.ndarray] | None = None, sources: tuple[str, ...] = (), **columns: np.ndarray):
        self.stage, self.shard, self.values, self.sources = stage, shard, values, sources
        if sources:
            columns["source"] = np.full(len(shard.frames), -1, np.int8)
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
        if not isinstance(e, Ga3ceError) and where_raised(e):  # an unexpected error: keep where it happened
            msg += f" (at {where_raised(e)}; {DEBUG_HINT})"
        self.fail_idx.append(i)
        self.fail_error.append(type(e).__name__)
        self.fail_message.append(msg)

    def attempt(self, i: int, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """fn(*args, **kwargs) for frame i, timed: its result (frame i ok with its values, and its
        source when the backend declares sources), or None after a failure record."""
        t = time.perf_counter()
        try:
            out = fn(*args, **kwargs)
            if self.sources:
                if not isinstance(out, Sourced) or out.source not in self.sources:
                    raise ValueError(f"{self.stage} backend must return Sourced(value, source in {self.sources}), "
                                     f"got {type(out).__name__}")
                out, source = out.value, {"source": self.sources.index(out.source)}
            else:
                source = {}
            self.ok(i, **self.values(out), **source)
            return out
        except Exception as e:  # every per-frame problem becomes a record
            self.fail(i, e)
            return None
        finally:
            self.seconds += time.perf_counter() - t
            fault("stage.frame")

    def attempt_batch(self, rows: list[int], fn: Callable[..., list], frames: list[FrameRef],
                      needs: dict[str, list[Any]]) -> None:
        """fn(frames, **needs) -> one result or Exception per frame, for frames `rows` of the shard
        in one call, each recorded on its frame. If the call itself raises, the frames are tried one
        by one, so the failure lands on the frame that caused it."""
        t = time.perf_counter()
        try:
            results = fn(frames, **needs)
        except Exception:  # a frame's problem: found frame by frame below
            results = None
        self.seconds += time.perf_counter() - t
        for k, i in enumerate(rows):
            if results is None:
                self.attempt(i, lambda k=k: _first(fn([frames[k]], **{n: v[k:k + 1] for n, v in needs.items()})))
            else:
                self.attempt(i, _first, [results[k]])

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


def _first(results: list[Any]) -> Any:
    """The first of a batched call's per-frame results; raises it when it is an exception."""
    if isinstance(results[0], Exception):
        raise results[0]
    return results[0]


def _shaped(v: Any, shape: tuple[int, ...], stage: str) -> np.ndarray:
    """A backend's per-frame value as float32 of `shape`, finite: a pose may have NaN joints (not
    found) but not only those, nor an infinite value. Otherwise a failure record, never a value
    stored as if it were one."""
    v = np.asarray(v, np.float32)
    if v.shape != shape:
        raise ValueError(f"{stage} backend returned shape {v.shape}, expected {shape}")
    bad = np.isinf(v).any() or (np.isnan(v).all() if stage == "pose" else np.isnan(v).any())
    if bad:
        what = "no finite joint" if stage == "pose" and np.isnan(v).all() else "non-finite values"
        raise FrameError(f"the {stage} backend returned {what} ({np.count_nonzero(~np.isfinite(v))} of {v.size}): "
                         f"not stored as a {stage}; a backend raises FrameError when it finds none")
    return v


def new_entry(stage: str, shard: Shard, sources: tuple[str, ...] = ()) -> StageEntry:
    """An empty entry of `stage` for `shard`, with its columns (module docstring); `sources`: the
    backend's."""
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
        return StageEntry(stage, shard, lambda hp: {"head_pos": _shaped(hp, (3,), stage)}, sources=sources,
                          head_pos=np.full((n, 3), np.nan, np.float32))
    if stage in ("pose", "view"):  # (N_JOINTS, 3) or (3,)
        shape = {"pose": (N_JOINTS, 3), "view": (3,)}[stage]
        return StageEntry(stage, shard, lambda v: {stage: _shaped(v, shape, stage)}, ragged=None, sources=sources,
                          **{stage: np.full((n, *shape), np.nan, np.float32)})
    return StageEntry(stage, shard)  # input: ok flags and failures only


def _load_ok(cache: Cache, stage: str, shard: Shard) -> np.ndarray:
    return _load(cache, stage, shard)["ok"]


def _load(cache: Cache, stage: str, shard: Shard) -> dict[str, np.ndarray]:
    e = cache.load(stage, shard.keys[stage])
    if e is None:
        raise StoreError(f"cache entry {cache.path(stage, shard.keys[stage])} (stage {stage}, shard {shard.index}) "
                         "vanished or was damaged (then removed); rerun the same command to recompute it")
    return e


def _values(cache: Cache, stage: str, shard: Shard) -> np.ndarray:
    """A finished stage's per-frame values (n, ...) from its cache entry, NaN where it failed."""
    e = _load(cache, stage, shard)
    v = np.array(e[VALUE_COLUMN[stage]], np.float32)
    v[~e["ok"]] = np.nan
    return v


def _sources(env: TaskEnv, stage: str) -> tuple[str, ...]:
    return backend(env, stage).sources


def _call(env: TaskEnv, entry: StageEntry, i: int, frame: FrameRef, inputs: dict[str, Any]) -> Any:
    """Frame i through its stage's backend (`stages.call_backend`, with its window when the backend
    is windowed), recorded in `entry`."""
    windows = entry.shard.windows.get(entry.stage)
    return entry.attempt(i, call_backend, backend(env, entry.stage), frame, inputs,
                         None if windows is None else windows[i])


def input_task(env: TaskEnv, shard: Shard) -> list[StageReport]:
    """Check each frame (stages/input.py) and write the input entry."""
    cache = Cache(env.cache_root)
    if cache.has("input", shard.keys["input"]):
        return [StageReport("input", len(shard.frames))]
    _single_threaded()
    entry = new_entry("input", shard)
    for i, f in enumerate(shard.frames):
        _call(env, entry, i, f, {})
    return [entry.save(cache)]


def stage_task(env: TaskEnv, stage: str, shard: Shard, *_upstream: Any) -> list[StageReport]:
    """A per-frame stage without the depth map: pose (N_JOINTS, 3) or view (3,), reading the values
    of the stages it needs from their cache entries."""
    cache = Cache(env.cache_root)
    if cache.has(stage, shard.keys[stage]):
        return [StageReport(stage, len(shard.frames))]
    _single_threaded()
    entry = new_entry(stage, shard, _sources(env, stage))
    loaded = {u: _values(cache, u, shard) for u in env.upstream[stage] if u != "input"}
    b = backend(env, stage)
    rows = np.flatnonzero(_load_ok(cache, "input", shard)).tolist()
    if b.batch_size() > 1:  # the backend's network runs on several frames at once
        for k in range(0, len(rows), b.batch_size()):
            chunk = rows[k:k + b.batch_size()]
            entry.attempt_batch(chunk, b.batch, [shard.frames[i] for i in chunk],
                                {n: [loaded[n][i] for i in chunk] for n in b.needs})
        return [entry.save(cache)]
    for i in rows:
        _call(env, entry, i, shard.frames[i], {u: v[i] for u, v in loaded.items()})
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


def geometry_task(env: TaskEnv, shard: Shard, *_upstream: Any) -> list[StageReport]:
    """Depth, then every stage that reads it (objects, head, and a depth-refined pose), in
    dependency order, for the frames that passed the input checks."""
    geometry = task_stages(env.upstream)["geometry"]
    cache = Cache(env.cache_root)
    todo = {s for s in geometry if not cache.has(s, shard.keys[s])}
    if not todo:
        return [StageReport(s, len(shard.frames)) for s in geometry]
    _single_threaded()
    cached = None if "depth" in todo else _reusable_depth(cache, shard, env.cache_depth_maps)
    if cached is None:
        todo.add("depth")
    entries = {s: new_entry(s, shard, _sources(env, s)) for s in geometry}
    # values of the stages read here that are not computed here: other tasks' or already cached
    read = {u for s in geometry if s in todo for u in env.upstream[s]} - {"input", "depth"}
    loaded = {u: _values(cache, u, shard) for u in read if u not in todo}
    ok = _load_ok(cache, "input", shard)
    if cached is not None:
        ok = ok & cached["ok"]  # a frame whose depth failed has nothing that reads it either
    depth_fn = backend(env, "depth").depth
    for s in todo:
        backend(env, s).start_shard()
    for i in np.flatnonzero(ok).tolist():
        f = shard.frames[i]
        dm = _depth_for(i, f, entries["depth"], depth_fn, cached, env.cache_depth_maps)
        if dm is None:
            continue
        inputs = {"depth": dm, **{u: v[i] for u, v in loaded.items()}}
        for s in geometry[1:]:
            if s in todo:
                out = _call(env, entries[s], i, f, inputs)
                if s in VALUE_COLUMN:
                    inputs[s] = entries[s].columns[VALUE_COLUMN[s]][i] if out is not None else \
                        np.full(entries[s].columns[VALUE_COLUMN[s]].shape[1:], np.nan, np.float32)
    return [entries[s].save(cache) if s in todo else entries[s].report(False) for s in geometry]
