"""`run_pipeline`: dataset -> shards -> dask graph of stage tasks -> finalize -> store.

Order of a run (nothing is computed before every check has passed):
1. `_checked_config`: load and validate the pipeline; check backends and model/data files
   (config.py), the run options and what is at the output path (`_check_output`);
2. `_open_frames`: open the dataset (structural errors stop here) and list its frames (`limit`:
   the first N);
3. `_make_shards`: under the work directory's and the output's lock (lock.py; the output is
   checked again there), cut the frames into shards, give a windowed
   backend's stage its frames' windows (`frames.frame_windows` over all the frames, so windows
   reach into neighbouring shards) and compute every cache key (a windowed stage's also hashes the
   identity of every neighbour it reads);
4. `execute`: run the missing stage tasks on dask (graph.py, tasks.py), one progress bar per task kind;
5. `finalize`: write the store from the cache (finalize.py); `_summarize` returns a RunSummary.
   Cache entries found damaged on the way (`Cache.load` removes them) are computed again and
   finalize runs again, in the same run (`REPAIR_PASSES`).

The work directory (default `<out>.work/`) holds the lock, the cache and finalize's scratch; keep it
to make later runs with changed parameters recompute only what changed, or delete it to free space.
`--out` and `--work` may be URLs of object storage (location.py): a remote store with its work
directory beside it (the cache on object storage, for workers without a shared filesystem) or a
local one, and a local store with its work directory anywhere (finalize.scratch_dir). A write the
machine refuses (a full disk, a permission, a read-only or lost filesystem) stops the run with one
line naming the place, what the run needs there and what is kept (`_write_problem`).
"""
from __future__ import annotations

import itertools
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ConfigError, DatasetFormatError, EnvironmentProblem, StoreError, environment_problem
from ..files import file_sha256
from ..frames import FrameRef, Window, frame_windows
from ..stages import STAGES, backend_class, dependency_order
from ..store import SCHEMA_VERSION, SOURCE_STAGES, UNFINISHED, validate_store_attrs
from ..synthetic.truth import world_provenance
from .cache import Cache, file_identity, stable_hash
from .config import PipelineConfig, load_pipeline
from .finalize import FinalizeCounts, LostEntries, finalize
from .graph import execute
from .location import Location, absolute, filesystem, is_remote, join
from .lock import RunLock
from .tasks import Shard, StageReport, TaskEnv

FINALIZE_VERSION = "2"  # 2: attrs["summary"] holds FinalizeCounts under its field names
REPAIR_PASSES = 3  # execute + finalize rounds: damaged entries found by finalize are computed in the next
ZARR_MARKERS = ("zarr.json", ".zgroup", ".zarray")  # a directory holding one of these is a Zarr store (v3, v2)

log = logging.getLogger("ga3ce_prep.pipeline")


@dataclass
class RunSummary:
    """What a run did. `counts` come from the store; per stage, `seconds_by_stage` is compute time
    summed over the shards computed in this run, `computed_frames` their frames, `cached_shards`
    those found in the cache; `compute_seconds` is the graph's wall time once the workers are ready."""

    store: str
    pipeline: str
    counts: FinalizeCounts
    objects_per_frame: dict[str, float]
    seconds_by_stage: dict[str, float]
    computed_shards: dict[str, int]
    cached_shards: dict[str, int]
    computed_frames: dict[str, int]
    n_shards: int
    wall_seconds: float
    compute_seconds: float
    store_written: bool

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def format(self) -> str:
        """The end-of-run summary as text."""
        c, o = self.counts, self.objects_per_frame
        lines = [
            f"store      {self.store}{'' if self.store_written else ' (already up to date)'}",
            f"pipeline   {self.pipeline}",
            f"frames     {c.frames_kept} kept of {c.frames_total} ({c.frames_dropped} dropped) "
            f"in {self.n_shards} shards",
            f"objects    {c.objects} (per frame: mean {o['mean']:.1f}, median {o['median']:.0f}, "
            f"min {o['min']:.0f}, max {o['max']:.0f}; "
            f"{c.masks_dropped_few_points} masks dropped for too few depth points)",
        ]
        if c.failures:
            lines.append("failures   stage     dropped degraded  by error")
            for stage in STAGES:
                if stage in c.failures:
                    errs = ", ".join(f"{k} {v}" for k, v in sorted(c.failures[stage].items()))
                    lines.append(f"           {stage:<9} {c.dropped_by_stage.get(stage, 0):>7} "
                                 f"{c.degraded_by_stage.get(stage, 0):>8}  {errs}")
        else:
            lines.append("failures   none")
        lines.append("time       stage     computed  cached  seconds  ms/frame")
        for stage in STAGES:
            n, k, s = (self.computed_shards.get(stage, 0), self.cached_shards.get(stage, 0),
                       self.seconds_by_stage.get(stage, 0.0))
            nf = self.computed_frames.get(stage, 0)
            per = f"{1000 * s / nf:8.2f}" if nf else "       -"
            lines.append(f"           {stage:<9} {n:>8} {k:>7} {s:>8.2f}  {per}")
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
    version = cls.cache_version(sc.p)
    return {"stage": stage, "backend": sc.backend, "version": version, "params": params,
            "data_files": {k: file_identity(p) for k, p in sorted(sc.data_files.items())},
            "models": {k: file_sha256(p) for k, p in sorted(sc.model_files.items())}}


def shard_keys(conf: PipelineConfig, frames: list[FrameRef], data_root: Path,
               idents: dict[str, dict[str, Any]], windows: dict[str, str] | None = None) -> dict[str, str]:
    """The cache key of every stage for one shard of frames. windows: windowed stage -> the hash
    of the shard's windows (`_window_hashes`), which its key also covers."""
    windows = windows or {}
    keys: dict[str, str] = {}
    shard_id = stable_hash([_frame_identity(f) for f in frames])
    for stage in dependency_order(conf.upstream):
        up = [keys[u] for u in conf.upstream[stage]]
        window = {"window": windows[stage]} if stage in windows else {}
        keys[stage] = stable_hash({"ident": idents[stage], "upstream": up,
                                   "frames": shard_id if stage == "input" else None,
                                   "data_root": str(data_root) if stage == "input" else None, **window})
    return keys


def run_pipeline(pipeline: str | Path | dict[str, Any], data: str | Path, out: str | Path, *,
                 workers: int | None = None, scheduler: str | None = None, shard_size: int | None = None,
                 limit: int | None = None, work_dir: str | Path | None = None,
                 overrides: list[str] | dict[str, Any] | None = None, models: str | Path | None = None,
                 overwrite: bool = False, progress: bool = True) -> RunSummary:
    """Preprocess the dataset at `data` with `pipeline` into the store `out` (module docstring).

    pipeline: a pipeline file, a bundled name ("synthetic", "gfie", ...), or a parsed dict.
    workers: N worker processes (distributed.LocalCluster); scheduler: a dask scheduler address;
    neither: the local threaded scheduler. shard_size overrides run.shard_size; limit keeps the
    first N frames; overrides: "stages.view.params.mean_error_deg=30"-style settings; overwrite:
    replace a store at `out` that is not ours or is of another pipeline or dataset (`_check_output`).
    Raises ConfigError / ModelFileError / DatasetFormatError / StoreError before any work.
    """
    t0 = time.perf_counter()
    data_root = Path(data).resolve()
    conf, out_path = _checked_config(pipeline, data_root, out, overrides, shard_size, workers, models, overwrite)
    work = _work_dir(work_dir, out_path)
    frames, read_as = _open_frames(conf, data_root, limit)
    cache, shards, phase = Cache(join(work, "cache")), [], "work"
    try:
        with RunLock(work, str(out_path)) as lock:
            _check_output(out_path, conf, data_root, overwrite)  # again: another run may have written it since
            cache.remove_temporaries()  # left by a killed run; we hold the lock
            shards = _make_shards(conf, frames, data_root)
            env = TaskEnv(cache.root, data_root, conf.stages, conf.upstream, conf.cache_depth_maps)
            attrs = provenance(conf, data_root, shard_size=conf.shard_size, n_shards=len(shards), limit=limit)
            attrs["dataset"].update(read_as)  # the units the adapter assumed, and how they were decided
            world = world_provenance(data_root)  # a synthetic world: its seed, rooms, sessions, protocol
            if world is not None:
                attrs["dataset"]["synthetic"] = world
            sources = {st: backend_class(st, conf.stages[st].backend).sources or (conf.stages[st].backend,)
                       for st in SOURCE_STAGES}
            reports: list[StageReport] = []
            compute_seconds = fin_seconds = 0.0
            for attempt in range(1, REPAIR_PASSES + 1):
                phase = "cache"
                done, seconds = execute(env, shards, workers=workers, scheduler=scheduler, progress=progress)
                reports, compute_seconds = reports + done, compute_seconds + seconds
                t_fin, phase = time.perf_counter(), "finalize"
                try:
                    lock.check()
                    counts, written = finalize(shards, cache, out_path, work, attrs,
                                               _run_key(conf, data_root, shards), sources, progress=progress)
                    break
                except LostEntries as e:
                    if attempt == REPAIR_PASSES:
                        raise StoreError(f"{e}; they were computed again {attempt - 1} times and are still "
                                         f"unreadable: check the disk of {cache.root}") from None
                    log.warning("%s: computing them again", e)
                finally:
                    fin_seconds += time.perf_counter() - t_fin
    except OSError as e:
        problem = _write_problem(e, phase, work, out_path, cache, shards)
        if problem is None:
            raise
        raise problem from e
    return _summarize(str(out_path), conf, len(shards), reports, counts, written, compute_seconds=compute_seconds,
                      finalize_seconds=fin_seconds, wall_seconds=time.perf_counter() - t0)


def _checked_config(pipeline: str | Path | dict[str, Any], data_root: Path, out: str | Path,
                    overrides: list[str] | dict[str, Any] | None, shard_size: int | None,
                    workers: int | None, models: str | Path | None = None,
                    overwrite: bool = False) -> tuple[PipelineConfig, Location]:
    """The validated pipeline (run options applied) and the output's absolute path or URL, checked
    by `_check_output`."""
    conf = load_pipeline(pipeline, data_root, overrides, models=models)
    if shard_size is not None:
        if shard_size < 1:
            raise ConfigError(f"--shard-size must be at least 1, not {shard_size}")
        conf.shard_size = int(shard_size)
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be at least 1, not {workers}")
    out_path = absolute(out)
    _check_output(out_path, conf, data_root, overwrite)
    return conf, out_path


def _check_output(out: Location, conf: PipelineConfig, data_root: Path, overwrite: bool) -> None:
    """Refuse to replace what a run must not: anything at `out` but a Zarr store; with `overwrite`
    false, also a Zarr store that is not a ga3ce-prep store (root attributes valid against
    ga3ce_prep/schemas/store.schema.json), or one of another pipeline (name) or dataset (format and root).
    StoreError saying what is there and how to proceed."""
    if is_remote(out):
        exists, is_store = _probe(str(out))
    else:
        local = Path(out)
        exists, is_store = local.exists(), any((local / m).is_file() for m in ZARR_MARKERS)
    if not exists:
        return
    if not is_store:
        raise StoreError(f"--out {out} exists and is not a Zarr store: ga3ce-prep replaces only its own stores; "
                         "choose another --out, or move it away yourself")
    found = _other_store(out, conf, data_root)
    if found and not overwrite:
        raise StoreError(f"--out {out} holds {found}; to replace it pass --overwrite, to keep it choose another --out")


def _other_store(out: Location, conf: PipelineConfig, data_root: Path) -> str | None:
    """What the Zarr store at `out` is, when it is not a ga3ce-prep store of this pipeline and
    dataset (None: it is, so a run may replace it)."""
    import zarr

    try:
        attrs: dict[str, Any] = dict(zarr.open_group(str(out), mode="r").attrs)  # JSON
    except Exception as e:  # a damaged or unknown root: not known to be ours
        return f"a Zarr store whose root metadata cannot be read ({type(e).__name__}: {e})"
    if attrs == UNFINISHED:
        return None  # ours, killed before its commit (store.StoreWriter, finalize._uncommit)
    try:
        validate_store_attrs(attrs)
    except StoreError as e:
        keys = ", ".join(sorted(attrs)[:8]) or "none"
        return f"a Zarr store that ga3ce-prep did not write (root attributes: {keys}; {e})"
    pipe, ds = attrs["pipeline"].get("name", attrs["pipeline"]["file"]), attrs["dataset"]
    if pipe == conf.name and (ds["name"], ds["root"]) == (conf.dataset_format, str(data_root)):
        return None
    kept = (attrs.get("summary") or {}).get("frames_kept")
    frames = "" if kept is None else f"{kept} frames, "
    return (f"the ga3ce-prep store of pipeline {pipe!r} on the {ds['name']} dataset at {ds['root']} ({frames}"
            f"schema {attrs['schema_version']}), not this run's pipeline {conf.name!r} on the "
            f"{conf.dataset_format} dataset at {data_root}")


def _probe(url: str) -> tuple[bool, bool]:
    """(something is at the URL, a store's root metadata is), after checking that its bucket (the
    URL's first component) is there and these credentials can read it."""
    fs = filesystem(url)
    bucket = fs._strip_protocol(url).lstrip("/").split("/")[0]
    try:
        if not fs.exists(bucket):
            raise ConfigError(f"--out {url}: bucket {bucket} does not exist (or these credentials cannot see it); "
                              "create it first")
        return fs.exists(url), any(fs.exists(f"{url}/{m}") for m in ZARR_MARKERS)
    except ConfigError:
        raise
    except Exception as e:  # credentials, endpoint, network: say which and stop
        raise ConfigError(f"--out {url}: cannot reach it ({type(e).__name__}: {e}); check the credentials and "
                          "endpoint (docs/pipeline.md, \"Object storage\")") from None


def _work_dir(work_dir: str | Path | None, out: Location) -> Location:
    """The work directory: --work (any filesystem or URL, whatever --out is), else `<out>.work` (on
    object storage too, beside the store)."""
    return absolute(work_dir or f"{out}.work")


def _write_problem(e: OSError, phase: str, work: Location, out: Location, cache: Cache,
                   shards: list[Shard]) -> EnvironmentProblem | None:
    """A write the machine refused (errors.environment_problem; None: a bug) as one line: the place
    (the stage cache, the work directory, the output's lock, or where finalize builds the store),
    what the run needs there (for a full disk about how much: the entries still to write at the
    mean size of those written, or the store at the size of the entries it is made of), the fix,
    and what is kept. The place is the path in the exception, else the phase the run was in
    ("work", "cache", "finalize")."""
    at = str(e.filename) if e.filename is not None else ""
    sizes, total = _entry_sizes(cache, shards)
    per = sum(sizes.values()) / len(sizes) if sizes else 0
    store = [n for (stage, _), n in sizes.items() if stage != "depth"]  # depth maps stay out of the store
    store_need = int(sum(store) / len(store) * (total - len(shards))) if store else None
    def under(root: Location) -> bool:
        return at == str(root) or at.startswith(f"{root}/")

    in_cache = under(cache.root) if at else phase == "cache"
    beside = None if is_remote(out) else Path(f"{out}.finalize")  # finalize.scratch_dir: building beside --out
    by_out = (under(out) or (beside is not None and under(beside)) if at
              else phase == "finalize" and (beside is None or beside.exists()))
    if at == f"{out}.lock":
        place, need, fix = f"the output's lock file beside --out {out}", None, "choose another --out"
    elif in_cache:
        place, need = f"the stage cache in --work {work}: {total - len(sizes)} entries still to write", \
            int(per * (total - len(sizes))) or None
        fix = "give --work on another filesystem"
    elif by_out:
        place, need, fix = f"finalize writes the new store for --out {out}", store_need, "choose another --out"
    elif phase == "finalize":
        place, need = f"finalize builds the new store in --work {work} before renaming it over --out", store_need
        fix = "give --work on another filesystem"
    else:
        place, need, fix = f"the work directory --work {work} (its lock and the stage cache)", None, \
            "give --work elsewhere"
    where = at or (cache.root if in_cache else (beside or out) if by_out else work)
    if not total:
        kept = "rerun the same command once this is fixed"
    elif len(sizes) == total:
        kept = f"all {total} cache entries are finished and kept in {cache.root}: rerun the same command to write " \
               "the store from them"
    else:
        kept = f"{len(sizes)} of {total} cache entries are finished and kept in {cache.root}: rerun the same " \
               "command to resume"
    return environment_problem(e, where, place, need, fix, kept)


def _entry_sizes(cache: Cache, shards: list[Shard]) -> tuple[dict[tuple[str, str], int], int]:
    """The finished cache entries of the run's shards, (stage, key) -> bytes (0 when the cache is
    remote), and how many entries the run needs in all; none found when the cache cannot be read."""
    want = {(stage, key) for s in shards for stage, key in s.keys.items()}
    try:
        present = cache.entries() & want
        if cache.remote:
            return {k: 0 for k in present}, len(want)
        return {k: Path(cache.path(*k)).stat().st_size for k in present}, len(want)
    except OSError:
        return {}, len(want)


def _open_frames(conf: PipelineConfig, data_root: Path, limit: int | None) -> tuple[list[FrameRef], dict[str, Any]]:
    """The dataset's frames (the first `limit`), in the adapter's order, ids checked unique; and what
    the adapter says of how it read them (`DatasetAdapter.provenance`: the units assumed)."""
    from ..datasets import open_dataset

    try:
        adapter = open_dataset(conf.dataset_format, data_root, **conf.dataset_options)
    except TypeError as e:
        raise ConfigError(
            f"dataset.options: {e} (see docs/datasets.md for the {conf.dataset_format} options)") from None
    frames = list(itertools.islice(adapter.frames(), None if limit is None else max(limit, 0)))
    if not frames:
        raise DatasetFormatError(f"{data_root}: the {conf.dataset_format} adapter found no frames")
    if len({f.id for f in frames}) != len(frames):
        raise DatasetFormatError(f"{data_root}: frame ids are not unique (adapter bug)")
    return frames, adapter.provenance()


def _make_shards(conf: PipelineConfig, frames: list[FrameRef], data_root: Path) -> list[Shard]:
    """Consecutive shards of run.shard_size frames, each with every stage's cache key and, for a
    windowed backend (`Backend.window`), its frames' windows (`frames.frame_windows` over all the
    run's frames, so a window reaches into the neighbouring shards)."""
    idents = {s: stage_identity(conf, s) for s in STAGES}
    sizes = {s: backend_class(s, conf.stages[s].backend).window for s in STAGES}
    try:
        windows = {s: frame_windows(frames, n) for s, n in sizes.items() if n}
    except ValueError as e:
        raise DatasetFormatError(f"{data_root}: {e} (adapter bug)") from None
    frame_hash = {f: stable_hash(_frame_identity(f)) for f in frames} if windows else {}
    k = conf.shard_size
    shards = [Shard(i, frames[j:j + k], windows={s: w[j:j + k] for s, w in windows.items()})
              for i, j in enumerate(range(0, len(frames), k))]
    for s in shards:
        s.keys = shard_keys(conf, s.frames, data_root, idents, _window_hashes(s.windows, frame_hash))
    return shards


def _window_hashes(windows: dict[str, list[Window]], frame_hash: dict[FrameRef, str]) -> dict[str, str]:
    """Per windowed stage, the hash of a shard's windows: each neighbour's identity (None where it
    is missing) and the previous frame's, in order."""
    return {s: stable_hash([[[frame_hash[f] if f is not None else None for f in w.frames], frame_hash[w.previous]]
                            for w in ws]) for s, ws in windows.items()}


def _run_key(conf: PipelineConfig, data_root: Path, shards: list[Shard]) -> str:
    """What the store depends on: every cache key, the configuration, the dataset, the store layout."""
    return stable_hash({"finalize": FINALIZE_VERSION, "schema": SCHEMA_VERSION,
                        "keys": [s.keys for s in shards], "config": conf.config,
                        "dataset": [conf.dataset_format, str(data_root)]})


def provenance(conf: PipelineConfig, data_root: Path, **run: Any) -> dict[str, Any]:
    """The store's root attributes (ga3ce_prep/schemas/store.schema.json): dataset, pipeline, per-stage backend,
    parameters, model SHA-256 and what the backend adds (`Backend.provenance`), package version,
    run settings."""
    stages = {}
    for stage, sc in conf.stages.items():
        extra = sc.make(data_root).provenance()
        models = {str(p): file_sha256(p) for p in sc.model_files.values()} | extra.pop("models", {})
        stages[stage] = {"backend": sc.backend,
                         "params": {k: (str(v) if isinstance(v, Path) else v) for k, v in sc.params.items()},
                         "models": models, "oracle": sc.backend == "oracle", **extra}
    return {"package_version": __version__,
            "dataset": {"name": conf.dataset_format, "root": str(data_root), "options": conf.dataset_options},
            "pipeline": {"file": conf.file, "sha256": conf.sha256, "name": conf.name, "config": conf.config},
            "stages": stages, "run": {k: v for k, v in run.items()}}


def _summarize(store: str, conf: PipelineConfig, n_shards: int, reports: list[StageReport], counts: FinalizeCounts,
               written: bool, compute_seconds: float, finalize_seconds: float, wall_seconds: float) -> RunSummary:
    """The RunSummary of the tasks' reports and finalize's counts."""
    seconds = {s: 0.0 for s in STAGES}
    computed = {s: 0 for s in STAGES}
    computed_frames = {s: 0 for s in STAGES}
    for r in reports:
        seconds[r.stage] += r.seconds
        if r.computed:
            computed[r.stage] += 1
            computed_frames[r.stage] += r.frames
    return RunSummary(
        store=store, pipeline=conf.file, counts=counts, objects_per_frame=_objects_per_frame(counts.obj_count_hist),
        seconds_by_stage={**seconds, "finalize": finalize_seconds}, computed_shards=computed,
        cached_shards={s: n_shards - computed[s] for s in STAGES}, computed_frames=computed_frames,
        n_shards=n_shards, wall_seconds=wall_seconds, compute_seconds=compute_seconds, store_written=written)


def _objects_per_frame(hist: dict[str, int]) -> dict[str, float]:
    """Mean, median (the lower middle value), min and max objects per frame, from the histogram
    (objects per frame -> frames)."""
    if not hist:
        return {"mean": 0.0, "median": 0.0, "min": 0.0, "max": 0.0}
    k = np.array(sorted(int(c) for c in hist))
    n = np.array([hist[str(c)] for c in k])
    median = k[np.searchsorted(np.cumsum(n) * 2, n.sum())]
    return {"mean": float((k * n).sum() / n.sum()), "median": float(median), "min": float(k[0]), "max": float(k[-1])}
