"""The work of one shard, as dask tasks: each task computes the stage entries of its shard that are
not in the cache yet, writes them atomically, and returns a small report (never the arrays).

Tasks per shard (their dependencies are the stage dependencies):

    input     -> its entry (ok flags, failures)
    geometry  -> depth, objects, head entries (one task: the depth map is computed once and used by
                 both consumers; it is kept in the cache only with run.cache_depth_maps)
    pose      -> its entry
    view      -> its entry

Entry arrays (n = frames in the shard, ids for a sanity check):
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
from .cache import Cache
from .config import StageConfig

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


class _Failures:
    def __init__(self) -> None:
        self.idx: list[int] = []
        self.error: list[str] = []
        self.message: list[str] = []

    def add(self, i: int, e: BaseException) -> None:
        if os.environ.get("GA3CE_DEBUG"):
            raise e
        self.idx.append(i)
        self.error.append(type(e).__name__)
        msg = str(e) or type(e).__name__
        if not isinstance(e, Ga3ceError):  # an unexpected error: keep where it happened
            tb = traceback.extract_tb(e.__traceback__)
            if tb:
                msg += f" (at {Path(tb[-1].filename).name}:{tb[-1].lineno}; rerun with GA3CE_DEBUG=1 for the traceback)"
        self.message.append(msg)

    def arrays(self) -> dict[str, np.ndarray]:
        return {"fail_idx": np.array(self.idx, np.int64), "fail_error": np.array(self.error, dtype=str),
                "fail_message": np.array(self.message, dtype=str)}


def _entry(shard: Shard, ok: np.ndarray, fails: _Failures, seconds: float, **arrays) -> dict[str, np.ndarray]:
    return {"ids": shard.ids, "ok": ok, "seconds": np.float64(seconds), **fails.arrays(), **arrays}


def _report(stage: str, shard: Shard, computed: bool, seconds: float = 0.0) -> dict[str, Any]:
    return {stage: {"computed": computed, "seconds": seconds, "frames": len(shard.frames)}}


def _load_ok(cache: Cache, stage: str, shard: Shard) -> np.ndarray:
    e = cache.load(stage, shard.keys[stage])
    if e is None:
        raise RuntimeError(f"cache entry {stage}/{shard.keys[stage]} vanished: was the cache directory "
                           f"{cache.root} changed during the run? Rerun to recompute it")
    return e["ok"]


def input_task(env: TaskEnv, shard: Shard) -> dict[str, Any]:
    """Check each frame (stages/input.py) and write the input entry."""
    cache = Cache(env.cache_root)
    if cache.has("input", shard.keys["input"]):
        return _report("input", shard, False)
    _single_threaded()
    t0 = time.perf_counter()
    b = backend(env, "input")
    ok = np.zeros(len(shard.frames), bool)
    fails = _Failures()
    for i, f in enumerate(shard.frames):
        try:
            b.check_frame(f)
            ok[i] = True
        except Exception as e:  # noqa: BLE001 - every per-frame problem becomes a record
            fails.add(i, e)
    dt = time.perf_counter() - t0
    cache.save("input", shard.keys["input"], _entry(shard, ok, fails, dt))
    return _report("input", shard, True, dt)


def geometry_task(env: TaskEnv, shard: Shard, _upstream: Any = None) -> dict[str, Any]:
    """Depth, then objects and head from it, for the frames that passed the input checks."""
    cache = Cache(env.cache_root)
    need = {s: not cache.has(s, shard.keys[s]) for s in ("depth", "objects", "head")}
    if not any(need.values()):
        return {s: _report(s, shard, False)[s] for s in ("depth", "objects", "head")}
    _single_threaded()
    n = len(shard.frames)
    ok_in = _load_ok(cache, "input", shard)
    cached_depth = None if need["depth"] else cache.load("depth", shard.keys["depth"])
    if cached_depth is None:
        need["depth"] = True
    use_maps = cached_depth is not None and env.cache_depth_maps and (
        all(f"map_{i}" in cached_depth for i in np.flatnonzero(cached_depth["ok"])))
    if env.cache_depth_maps and cached_depth is not None and not use_maps:
        need["depth"] = True  # entry without maps: recompute so the maps get cached
    b_depth = backend(env, "depth")
    b_obj = backend(env, "objects") if need["objects"] else None
    b_head = backend(env, "head") if need["head"] else None
    secs = {"depth": 0.0, "objects": 0.0, "head": 0.0}
    fails = {s: _Failures() for s in secs}
    ok = {s: np.zeros(n, bool) for s in secs}
    valid_frac = np.zeros(n, np.float32)
    filled_frac = np.zeros(n, np.float32)
    maps: dict[str, np.ndarray] = {}
    count = np.zeros(n, np.int32)
    n_dropped = np.zeros(n, np.int32)
    xyz, area, score = [], [], []
    head_pos = np.full((n, 3), np.nan, np.float32)
    depth_ok = ok_in if need["depth"] else (ok_in & cached_depth["ok"])  # recomputing: every input-ok frame

    def timed(stage: str, fn: Callable[[], Any], i: int) -> Any:
        t = time.perf_counter()
        try:
            out = fn()
            ok[stage][i] = True
            return out
        except Exception as e:  # noqa: BLE001
            fails[stage].add(i, e)
            return None
        finally:
            secs[stage] += time.perf_counter() - t

    for i, f in enumerate(shard.frames):
        if not depth_ok[i]:
            continue
        if use_maps:
            from ..stages.base import DepthMap

            dm = DepthMap(cached_depth[f"map_{i}"], cached_depth[f"valid_{i}"])
            ok["depth"][i] = True
        else:
            dm = timed("depth", lambda: b_depth.depth(f), i)
        if dm is None:
            continue
        valid_frac[i] = dm.valid.mean()
        filled_frac[i] = (dm.depth > 0).mean()
        if env.cache_depth_maps and need["depth"]:
            maps[f"map_{i}"], maps[f"valid_{i}"] = dm.depth, dm.valid
        if b_obj is not None:
            fo = timed("objects", lambda: b_obj.objects(f, dm), i)
            if fo is not None:
                count[i], n_dropped[i] = len(fo.xyz), fo.n_dropped
                xyz.append(fo.xyz)
                area.append(fo.area)
                score.append(fo.score)
        if b_head is not None:
            hp = timed("head", lambda: b_head.head(f, dm), i)
            if hp is not None:
                head_pos[i] = hp
    reports: dict[str, Any] = {}
    if need["depth"]:
        cache.save("depth", shard.keys["depth"], _entry(shard, ok["depth"], fails["depth"], secs["depth"],
                                                        valid_frac=valid_frac, filled_frac=filled_frac, **maps))
    reports.update(_report("depth", shard, need["depth"], secs["depth"]))
    if need["objects"]:
        cat = (lambda parts, shape, dt: np.concatenate(parts).astype(dt) if parts else np.zeros(shape, dt))
        cache.save("objects", shard.keys["objects"], _entry(
            shard, ok["objects"], fails["objects"], secs["objects"], count=count, n_dropped=n_dropped,
            xyz=cat(xyz, (0, 3), np.float32), area=cat(area, (0,), np.int32), score=cat(score, (0,), np.float32)))
    reports.update(_report("objects", shard, need["objects"], secs["objects"]))
    if need["head"]:
        cache.save("head", shard.keys["head"], _entry(shard, ok["head"], fails["head"], secs["head"], head_pos=head_pos))
    reports.update(_report("head", shard, need["head"], secs["head"]))
    return reports


def stage_task(env: TaskEnv, stage: str, shard: Shard, _upstream: Any = None) -> dict[str, Any]:
    """A per-frame stage without depth: pose (N_JOINTS, 3) or view (3,)."""
    cache = Cache(env.cache_root)
    if cache.has(stage, shard.keys[stage]):
        return _report(stage, shard, False)
    _single_threaded()
    t0 = time.perf_counter()
    ok_in = _load_ok(cache, "input", shard)
    b = backend(env, stage)
    fn = getattr(b, stage)  # PoseBackend.pose or ViewBackend.view
    shape = {"pose": (N_JOINTS, 3), "view": (3,)}[stage]
    n = len(shard.frames)
    out = np.full((n, *shape), np.nan, np.float32)
    ok = np.zeros(n, bool)
    fails = _Failures()
    for i, f in enumerate(shard.frames):
        if not ok_in[i]:
            continue
        try:
            v = np.asarray(fn(f), np.float32)
            if v.shape != shape:
                raise ValueError(f"{stage} backend returned shape {v.shape}, expected {shape}")
            out[i] = v
            ok[i] = True
        except Exception as e:  # noqa: BLE001
            fails.add(i, e)
    dt = time.perf_counter() - t0
    cache.save(stage, shard.keys[stage], _entry(shard, ok, fails, dt, **{stage: out}))
    return _report(stage, shard, True, dt)
