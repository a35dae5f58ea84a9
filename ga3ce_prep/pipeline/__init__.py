"""The staged preprocessing pipeline: pipeline files, the stage cache, the dask graph, finalize.

    from ga3ce_prep.pipeline import run_pipeline
    summary = run_pipeline("synthetic", data="out/synthetic", out="out/synthetic.zarr")
    print(summary.format())

docs/pipeline.md describes the stages, the cache, resuming and failure handling; docs/store.md the
store it writes and its read API (`ga3ce_prep.store.open_store`).
"""
from .config import PipelineConfig, load_pipeline
from .run import RunSummary, run_pipeline

__all__ = ["PipelineConfig", "RunSummary", "load_pipeline", "run_pipeline"]
