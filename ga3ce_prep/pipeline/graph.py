"""The dask graph over shards and its execution, with one progress bar per task kind.

Per shard, only the tasks whose cache entries are missing enter the graph:

    ("input", i) --> ("geometry", i)   depth, objects, head
               \\-> ("pose", i)
               \\-> ("view", i)

Schedulers: the local threaded scheduler by default (`workers=None`); `workers=N` starts a
`distributed.LocalCluster` of N single-threaded worker processes (parallelism without the GIL:
the stages are partly pure Python); `scheduler=ADDRESS` uses a running dask cluster, whose
workers must see the same data, cache and output paths.
"""
from __future__ import annotations

import logging
import os
import time
import warnings
from contextlib import ExitStack
from typing import Any

from .cache import Cache
from .tasks import Shard, StageReport, TaskEnv, geometry_task, input_task, stage_task, warm

TASK_STAGES: dict[str, tuple[str, ...]] = {
    "input": ("input",), "geometry": ("depth", "objects", "head"), "pose": ("pose",), "view": ("view",),
}
BAR_LABELS = {"input": "input", "geometry": "depth+objects+head", "pose": "pose", "view": "view"}


def build_graph(env: TaskEnv, shards: list[Shard]) -> tuple[dict, list, dict[str, int]]:
    """(dask graph, its output keys, frames already cached per task kind)."""
    cache = Cache(env.cache_root)
    dsk: dict = {}
    cached = {k: 0 for k in TASK_STAGES}
    for s in shards:
        need = {kind: any(not cache.has(st, s.keys[st]) for st in stages) for kind, stages in TASK_STAGES.items()}
        for kind in TASK_STAGES:
            if not need[kind]:
                cached[kind] += len(s.frames)
        up = ("input", s.index) if need["input"] else None
        if need["input"]:
            dsk[("input", s.index)] = (input_task, env, s)
        if need["geometry"]:
            dsk[("geometry", s.index)] = (geometry_task, env, s, up)
        for kind in ("pose", "view"):
            if need[kind]:
                dsk[(kind, s.index)] = (stage_task, env, kind, s, up)
    return dsk, list(dsk), cached


class _Bars:
    """One tqdm bar per task kind, counting frames."""

    def __init__(self, shards: list[Shard], cached: dict[str, int], progress: bool):
        from tqdm import tqdm

        total = sum(len(s.frames) for s in shards)
        self.size = {s.index: len(s.frames) for s in shards}
        self.bars = {k: tqdm(total=total, initial=cached[k], desc=f"{BAR_LABELS[k]:>18}", unit="frame",
                             position=i, disable=not progress, leave=True, dynamic_ncols=True)
                     for i, k in enumerate(TASK_STAGES)}

    def done(self, key: tuple) -> None:
        kind, index = key
        self.bars[kind].update(self.size[index])

    def close(self) -> None:
        for b in self.bars.values():
            b.close()


def execute(dsk: dict, keys: list, shards: list[Shard], cached: dict[str, int], workers: int | None = None,
            scheduler: str | None = None, progress: bool = True,
            timing: dict[str, float] | None = None) -> list[list[StageReport]]:
    """Run the graph; returns the tasks' reports (a list of StageReport per task). `timing`
    receives "compute_seconds": wall time from the workers being ready to the last task."""
    bars = _Bars(shards, cached, progress)
    timing = {} if timing is None else timing
    try:
        if not keys:
            timing["compute_seconds"] = 0.0
            return []
        if workers is None and scheduler is None:
            return _execute_local(dsk, keys, bars, timing)
        return _execute_distributed(dsk, keys, bars, workers, scheduler, timing)
    finally:
        bars.close()


def _execute_local(dsk: dict, keys: list, bars: _Bars, timing: dict[str, float]) -> list[dict[str, Any]]:
    import dask.threaded
    from dask.callbacks import Callback

    def posttask(key, result, dsk_, state, worker_id):
        bars.done(key)

    env = next((t[1] for t in dsk.values() if isinstance(t[1], TaskEnv)), None)
    if env is not None:
        warm(env)
    t0 = time.perf_counter()
    with Callback(posttask=posttask):
        results = dask.threaded.get(dsk, keys, num_workers=os.cpu_count() or 1)
    timing["compute_seconds"] = time.perf_counter() - t0
    return list(results)


def _execute_distributed(dsk: dict, keys: list, bars: _Bars, workers: int | None,
                         scheduler: str | None, timing: dict[str, float]) -> list[dict[str, Any]]:
    from distributed import Client, LocalCluster, as_completed

    with ExitStack() as stack:
        if scheduler:
            client = stack.enter_context(Client(scheduler))
        else:
            with warnings.catch_warnings():  # "port 8787 in use" for the (unused) HTTP server
                warnings.simplefilter("ignore")
                cluster = stack.enter_context(LocalCluster(
                    n_workers=int(workers), threads_per_worker=1, processes=True, dashboard_address=None,
                    silence_logs=logging.ERROR))
            client = stack.enter_context(Client(cluster))
        if workers:
            client.wait_for_workers(int(workers))
        env = next((t[1] for t in dsk.values() if isinstance(t[1], TaskEnv)), None)
        if env is not None:
            client.run(warm, env)  # imports (Open3D) in every worker before the clock starts
        t0 = time.perf_counter()
        futures = client.get(dsk, keys, sync=False)
        key_of = {f.key: k for f, k in zip(futures, keys)}
        results = []
        for fut, res in as_completed(futures, with_results=True):
            bars.done(key_of.get(fut.key, fut.key))
            results.append(res)
        timing["compute_seconds"] = time.perf_counter() - t0
        return results
