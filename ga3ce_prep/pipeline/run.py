"""`run_pipeline`: dataset -> shards -> dask graph of stage tasks -> finalize -> store.

Order of a run (nothing is computed before every check has passed):
1. load and validate the pipeline; check backends and model/data files (config.py);
2. open the dataset (structural errors stop here) and list its frames (`limit`: the first N);
3. take the output's lock (lock.py), cut the frames into shards and compute every cache key;
4. run the missing stage tasks on dask (graph.py, tasks.py), one progress bar per task kind;
5. finalize the store from the cache (finalize.py) and return a RunSummary.

The work directory (default `<out>.work/`) holds the lock, the cache and finalize's scratch; keep it
to make later runs with changed parameters recompute only what changed, or delete it to free space.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import ConfigError, DatasetFormatError, StoreError
from ..frames import FrameRef
from ..stages import STAGES, UPSTREAM, backend_class
from .cache import Cache, file_identity, file_sha256, stable_hash
from .config import PipelineConfig, load_pipeline
from .finalize import FinalizeCounts, finalize
from .graph import build_graph, execute
from .lock import RunLock
from .tasks import Shard, TaskEnv

FINALIZE_VERSION = "1"


@dataclass
class RunSummary:
    """What a run did. Counts come from the store; seconds are compute time summed over the shards
    computed in this run (per stage), `cached_shards` those found in the cache."""

    store: str
    pipeline: str
    frames_total: int
    frames_kept: int
    objects: int
    objects_per_frame: dict[str, float]
    obj_count_hist: dict[str, int]
    failures: dict[str, dict[str, int]]
    dropped_by_stage: dict[str, int]
    degraded_by_stage: dict[str, int]
    seconds_by_stage: dict[str, float]
    computed_shards: dict[str, int]
    cached_shards: dict[str, int]
    n_shards: int
    wall_seconds: float
    store_written: bool
    masks_dropped_few_points: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def frames_dropped(self) -> int:
        return self.frames_total - self.frames_kept

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def format(self) -> str:
        """The end-of-run summary as text."""
        o = self.objects_per_frame
        lines = [
            f"store      {self.store}{'' if self.store_written else ' (already up to date)'}",
            f"pipeline   {self.pipeline}",
            f"frames     {self.frames_kept} kept of {self.frames_total} ({self.frames_dropped} dropped) in {self.n_shards} shards",
            f"objects    {self.objects} (per frame: mean {o['mean']:.1f}, median {o['median']:.0f}, "
            f"min {o['min']:.0f}, max {o['max']:.0f}; {self.masks_dropped_few_points} masks dropped for too few depth points)",
        ]
        if self.failures:
            lines.append("failures   stage     dropped degraded  by error")
            for stage in STAGES:
                if stage in self.failures:
                    errs = ", ".join(f"{k} {v}" for k, v in sorted(self.failures[stage].items()))
                    lines.append(f"           {stage:<9} {self.dropped_by_stage.get(stage, 0):>7} "
                                 f"{self.degraded_by_stage.get(stage, 0):>8}  {errs}")
        else:
            lines.append("failures   none")
        lines.append("time       stage     computed  cached  seconds  ms/frame")
        for stage in STAGES:
            c, k, s = self.computed_shards.get(stage, 0), self.cached_shards.get(stage, 0), self.seconds_by_stage.get(stage, 0.0)
            nf = self.extra.get("computed_frames", {}).get(stage, 0)
            per = f"{1000 * s / nf:8.2f}" if nf else "       -"
            lines.append(f"           {stage:<9} {c:>8} {k:>7} {s:>8.2f}  {per}")
        lines.append(f"wall       {self.wall_seconds:.1f} s")
        return "\n".join(lines)


def _frame_identity(f: FrameRef) -> list[Any]:
    return [f.id, f.split, f.scene, file_identity(f.image_path), file_identity(f.depth_path), f.depth_scale,
            f.K, list(f.image_size), f.head_box, f.body_box, f.eye, f.gaze_target, f.gaze, f.gaze_2d,
            f.sequence, f.index, f.keypoints_2d]


def stage_identity(conf: PipelineConfig, stage: str) -> dict[str, Any]:
    """Everything about a stage's configuration that its outputs depend on (for its cache key)."""
    sc = conf.stages[stage]
    cls = backend_class(stage, sc.backend)
    params = {k: v for k, v in conf.config["stages"][stage].get("params", {}).items()}
    return {"stage": stage, "backend": sc.backend, "version": cls.version, "params": params,
            "data_files": {k: file_identity(p) for k, p in sorted(sc.data_files.items())},
            "models": {k: file_sha256(p) for k, p in sorted(sc.model_files.items())}}


def shard_keys(conf: PipelineConfig, frames: list[FrameRef], data_root: Path,
               idents: dict[str, dict[str, Any]]) -> dict[str, str]:
    """The cache key of every stage for one shard of frames."""
    keys: dict[str, str] = {}
    shard_id = stable_hash([_frame_identity(f) for f in frames])
    for stage in STAGES:
        up = [keys[u] for u in UPSTREAM[stage]]
        keys[stage] = stable_hash({"ident": idents[stage], "upstream": up,
                                   "frames": shard_id if stage == "input" else None,
                                   "data_root": str(data_root) if stage == "input" else None})
    return keys


def default_work_dir(out: str) -> Path:
    if "://" in out:
        return Path.cwd() / ".ga3ce-work" / stable_hash(out)[:16]
    return Path(out.rstrip("/") + ".work")


def run_pipeline(pipeline: str | Path | dict[str, Any], data: str | Path, out: str | Path, *,
                 workers: int | None = None, scheduler: str | None = None, shard_size: int | None = None,
                 limit: int | None = None, work_dir: str | Path | None = None,
                 overrides: list[str] | dict[str, Any] | None = None, progress: bool = True) -> RunSummary:
    """Preprocess the dataset at `data` with `pipeline` into the store `out` (module docstring).

    pipeline: a pipeline file, a bundled name ("synthetic", "gfie", ...), or a parsed dict.
    workers: N worker processes (distributed.LocalCluster); scheduler: a dask scheduler address;
    neither: the local threaded scheduler. shard_size overrides run.shard_size; limit keeps the
    first N frames; overrides: "stages.view.params.mean_error_deg=30"-style settings.
    Raises ConfigError / ModelFileError / DatasetFormatError / StoreError before any work.
    """
    t0 = time.perf_counter()
    data_root = Path(data).resolve()
    out_s = str(out)
    if "://" not in out_s:
        out_s = str(Path(out_s).resolve())
    conf = load_pipeline(pipeline, data_root, overrides)
    if shard_size is not None:
        if shard_size < 1:
            raise ConfigError(f"--shard-size must be at least 1, not {shard_size}")
        conf.shard_size = int(shard_size)
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be at least 1, not {workers}")
    if "://" in out_s:
        raise ConfigError(f"--out {out_s}: remote stores are not supported by `run` yet (finalize renames a "
                          "local directory into place); write locally and copy the store")
    out_path = Path(out_s)
    if out_path.exists() and not (out_path / "zarr.json").is_file():
        raise StoreError(f"--out {out_path} exists and is not a ga3ce-prep store; choose another path or remove it")

    from ..datasets import open_dataset

    try:
        adapter = open_dataset(conf.dataset_format, data_root, **conf.dataset_options)
    except TypeError as e:
        raise ConfigError(f"dataset.options: {e} (see docs/datasets.md for the {conf.dataset_format} options)") from None
    frames: list[FrameRef] = []
    for f in adapter.frames():
        if limit is not None and len(frames) >= limit:
            break
        frames.append(f)
    if not frames:
        raise DatasetFormatError(f"{data_root}: the {conf.dataset_format} adapter found no frames")
    ids = [f.id for f in frames]
    if len(set(ids)) != len(ids):
        raise DatasetFormatError(f"{data_root}: frame ids are not unique (adapter bug)")

    work = Path(work_dir) if work_dir else default_work_dir(out_s)
    with RunLock(work, out_s):
        cache = Cache(work / "cache")
        for tmp in cache.root.glob("*/*/.*.tmp") if cache.root.exists() else []:
            tmp.unlink(missing_ok=True)  # left by a killed run; we hold the lock
        idents = {s: stage_identity(conf, s) for s in STAGES}
        k = conf.shard_size
        shards = [Shard(i, frames[j:j + k]) for i, j in enumerate(range(0, len(frames), k))]
        for s in shards:
            s.keys = shard_keys(conf, s.frames, data_root, idents)
        env = TaskEnv(cache.root, data_root, conf.stages, conf.cache_depth_maps)
        tasks, cached = build_graph(env, shards)
        reports, compute_seconds = execute(env, tasks, shards, cached, workers=workers, scheduler=scheduler,
                                           progress=progress)

        seconds = {s: 0.0 for s in STAGES}
        computed = {s: 0 for s in STAGES}
        computed_frames = {s: 0 for s in STAGES}
        for r in reports:
            seconds[r.stage] += r.seconds
            if r.computed:
                computed[r.stage] += 1
                computed_frames[r.stage] += r.frames
        cached_shards = {s: len(shards) - computed[s] for s in STAGES}

        run_key = stable_hash({"finalize": FINALIZE_VERSION, "schema": _schema_version(),
                               "keys": [s.keys for s in shards], "config": conf.config,
                               "dataset": [conf.dataset_format, str(data_root)]})
        attrs = provenance(conf, data_root, shard_size=k, n_shards=len(shards), limit=limit)
        t_fin = time.perf_counter()
        counts, written = finalize(shards, cache, out_path, work, attrs, run_key, progress=progress)
        fin_seconds = time.perf_counter() - t_fin
    summary = _summary(out_s, conf, counts, seconds, computed, cached_shards, computed_frames, len(shards),
                       time.perf_counter() - t0, written, fin_seconds)
    summary.extra["compute_seconds"] = compute_seconds  # graph wall time, workers ready
    return summary


def _schema_version() -> str:
    from ..store import SCHEMA_VERSION

    return SCHEMA_VERSION


def provenance(conf: PipelineConfig, data_root: Path, **run: Any) -> dict[str, Any]:
    """The store's root attributes (schemas/store.schema.json): dataset, pipeline, per-stage backend,
    parameters and model SHA-256, package version, run settings."""
    stages = {}
    for stage, sc in conf.stages.items():
        stages[stage] = {"backend": sc.backend,
                         "params": {k: (str(v) if isinstance(v, Path) else v) for k, v in sc.params.items()},
                         "models": {str(p): file_sha256(p) for p in sc.model_files.values()},
                         "oracle": sc.backend == "oracle"}
    return {"package_version": __version__,
            "dataset": {"name": conf.dataset_format, "root": str(data_root), "options": conf.dataset_options},
            "pipeline": {"file": conf.file, "sha256": conf.sha256, "name": conf.name, "config": conf.config},
            "stages": stages, "run": {k: v for k, v in run.items()}}


def _summary(out: str, conf: PipelineConfig, counts: FinalizeCounts, seconds, computed, cached, computed_frames,
             n_shards: int, wall: float, written: bool, fin_seconds: float) -> RunSummary:
    hist = {int(k): v for k, v in counts.obj_count_hist.items()}
    n = sum(hist.values())
    if n:
        vals = sorted(hist)
        mean = sum(k * v for k, v in hist.items()) / n
        cum, median = 0, 0
        for k in vals:
            cum += hist[k]
            if cum * 2 >= n:
                median = k
                break
        opf = {"mean": mean, "median": float(median), "min": float(vals[0]), "max": float(vals[-1])}
    else:
        opf = {"mean": 0.0, "median": 0.0, "min": 0.0, "max": 0.0}
    return RunSummary(
        store=out, pipeline=conf.file, frames_total=counts.frames_total, frames_kept=counts.frames_kept,
        objects=counts.objects, objects_per_frame=opf, obj_count_hist=counts.obj_count_hist,
        failures=counts.failures, dropped_by_stage=counts.dropped_by_stage, degraded_by_stage=counts.degraded_by_stage,
        seconds_by_stage={**seconds, "finalize": fin_seconds}, computed_shards=computed, cached_shards=cached,
        n_shards=n_shards, wall_seconds=wall, store_written=written,
        masks_dropped_few_points=counts.masks_dropped_few_points, extra={"computed_frames": computed_frames})
