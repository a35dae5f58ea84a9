"""The dask graph over shards and its execution, with one progress bar per task kind.

Per shard, only the tasks whose cache entries are missing enter the graph (`kinds_to_run`: also
those whose entries a task of the graph reads but are damaged), as `dask.delayed` calls named
`<kind>-<shard index>` (`tasks.task_stages`, `tasks.task_upstream`):

    input-i --> geometry-i   depth, objects, head (and pose, when its backend reads the depth)
           \\-> pose-i
           \\-> view-i      (after pose-i or geometry-i when its backend reads the pose)

A task never waits for another shard's: a windowed backend (`Backend.window`) reads its
neighbours' FrameRefs and pixels, not their stage outputs (their identities are in its cache key).

Schedulers: the local threaded scheduler by default (`workers=None`); `workers=N` starts a
`distributed.LocalCluster` of N single-threaded worker processes (parallelism without the GIL:
the stages are partly pure Python); `scheduler=ADDRESS` uses a running dask cluster, whose
workers must see the data at the same path, and the cache at the same path or URL (object
storage needs no shared filesystem). A worker that dies is replaced by dask and its tasks run
again: a task only ever adds complete cache entries, so a rerun task finds or rewrites them.
"""
from __future__ import annotations

import logging
import os
import time
import warnings
from contextlib import ExitStack

from dask import delayed
from dask.delayed import Delayed

from .cache import Cache
from .tasks import Shard, StageReport, TaskEnv, geometry_task, input_task, stage_task, task_stages, task_upstream, warm


def build_graph(env: TaskEnv, shards: list[Shard]) -> tuple[list[Delayed], dict[str, int]]:
    """(the tasks to run, frames already cached per task kind)."""
    cache = Cache(env.cache_root)
    present = cache.entries()
    kinds, after = task_stages(env.upstream), task_upstream(env.upstream)
    tasks: list[Delayed] = []
    cached = {k: 0 for k in kinds}
    for s in shards:
        made: dict[str, Delayed] = {}
        todo = kinds_to_run(cache, present, env.upstream, s)
        for kind in kinds:  # dependency order: a task's upstream tasks come first
            if kind not in todo:
                cached[kind] += len(s.frames)
                continue
            up = [made[k] for k in after[kind] if k in made]
            name = f"{kind}-{s.index}"
            if kind == "input":
                made[kind] = delayed(input_task)(env, s, dask_key_name=name)
            elif kind == "geometry":
                made[kind] = delayed(geometry_task)(env, s, *up, dask_key_name=name)
            else:
                made[kind] = delayed(stage_task)(env, kind, s, *up, dask_key_name=name)
            tasks.append(made[kind])
    return tasks, cached


def kinds_to_run(cache: Cache, present: set[tuple[str, str]], upstream: dict[str, tuple[str, ...]],
                 shard: Shard) -> set[str]:
    """The task kinds of `shard` to run: those with a missing entry (not in `present`, the cache's
    (stage, key) listing: `Cache.entries`), and those whose entries a task to run reads but cannot
    (`Cache.load` removes a damaged entry, which is then computed in this run instead of failing the
    task; the depth entry is the geometry task's own concern)."""
    kinds = task_stages(upstream)
    home = {st: k for k, stages in kinds.items() for st in stages}
    todo = {k for k, stages in kinds.items() if not all((st, shard.keys[st]) in present for st in stages)}
    checked: set[str] = set()
    while True:
        read = {u for k in todo for st in kinds[k] for u in upstream[st]} - {"depth"} - checked
        if not read:
            return todo
        checked |= read
        todo |= {home[u] for u in read if cache.load(u, shard.keys[u]) is None}


def _bar_label(kind: str, stages: tuple[str, ...]) -> str:
    return "+".join(stages) if kind == "geometry" else kind


class _Bars:
    """One tqdm bar per task kind, counting frames."""

    def __init__(self, kinds: dict[str, tuple[str, ...]], shards: list[Shard], cached: dict[str, int],
                 progress: bool):
        from tqdm import tqdm

        total = sum(len(s.frames) for s in shards)
        self.size = {s.index: len(s.frames) for s in shards}
        self.bars = {k: tqdm(total=total, initial=cached[k], desc=f"{_bar_label(k, st):>18}", unit="frame",
                             position=i, disable=not progress, leave=True, dynamic_ncols=True)
                     for i, (k, st) in enumerate(kinds.items())}

    def done(self, key: str) -> None:
        """Task `<kind>-<shard index>` finished."""
        kind, index = key.rsplit("-", 1)
        self.bars[kind].update(self.size[int(index)])

    def close(self) -> None:
        for b in self.bars.values():
            b.close()


def execute(env: TaskEnv, shards: list[Shard], workers: int | None = None, scheduler: str | None = None,
            progress: bool = True) -> tuple[list[StageReport], float]:
    """Run the shards' missing tasks; returns their reports and the compute seconds (wall time from
    the workers being ready, backends built, to the last task)."""
    tasks, cached = build_graph(env, shards)
    bars = _Bars(task_stages(env.upstream), shards, cached, progress)
    try:
        if not tasks:
            return [], 0.0
        if workers is None and scheduler is None:
            return _execute_local(env, tasks, bars)
        return _execute_distributed(env, tasks, bars, workers, scheduler)
    finally:
        bars.close()


def _execute_local(env: TaskEnv, tasks: list[Delayed], bars: _Bars) -> tuple[list[StageReport], float]:
    import dask
    from dask.callbacks import Callback

    def posttask(key, result, dsk, state, worker_id):
        bars.done(key)

    warm(env)
    t0 = time.perf_counter()
    with Callback(posttask=posttask):
        results = dask.compute(*tasks, scheduler="threads", num_workers=os.cpu_count() or 1)
    return [r for task in results for r in task], time.perf_counter() - t0


def _execute_distributed(env: TaskEnv, tasks: list[Delayed], bars: _Bars, workers: int | None,
                         scheduler: str | None) -> tuple[list[StageReport], float]:
    from distributed import Client, LocalCluster, as_completed

    with ExitStack() as stack:
        if scheduler:
            client = stack.enter_context(Client(scheduler))
        else:
            assert workers is not None  # execute() runs locally when neither is given
            with warnings.catch_warnings():  # "port 8787 in use" for the (unused) HTTP server
                warnings.simplefilter("ignore")
                cluster = stack.enter_context(LocalCluster(
                    n_workers=int(workers), threads_per_worker=1, processes=True, dashboard_address=None,
                    silence_logs=logging.CRITICAL))  # a task's exception reaches the driver, which says it once
            client = stack.enter_context(Client(cluster))
        if workers:
            client.wait_for_workers(int(workers))
        client.run(warm, env)  # imports (Open3D) in every worker before the clock starts
        t0 = time.perf_counter()
        reports = []
        for fut, res in as_completed(client.compute(tasks), with_results=True):
            bars.done(fut.key)
            reports += res
        return reports, time.perf_counter() - t0
