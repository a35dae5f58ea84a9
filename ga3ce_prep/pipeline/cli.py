"""The pipeline's command: `run` (registered in ga3ce_prep/cli.py; the store commands are in
ga3ce_prep/store_cli.py)."""
from __future__ import annotations

import json
from pathlib import Path

import click

from ..bundled import pipeline_names


@click.command("run", context_settings={"show_default": True})
@click.option("--pipeline", "-p", required=True,
              help="A pipeline file (YAML), or the name of one the package carries (ga3ce_prep/pipelines/): "
                   + ", ".join(pipeline_names()) + ".")
@click.option("--data", "-d", required=True, type=click.Path(file_okay=False),
              help="Dataset root, in the format the pipeline's dataset.format names.")
@click.option("--out", "-o", required=True,
              help="Output store: a directory (out/gfie.zarr) or an fsspec URL (s3://bucket/gfie.zarr, with s3fs "
                   "installed; credentials from the environment). An existing ga3ce-prep store of the same pipeline "
                   "and dataset is replaced; anything else is refused (see --overwrite).")
@click.option("--overwrite", is_flag=True,
              help="Replace a Zarr store at --out that ga3ce-prep did not write, or that another pipeline or dataset "
                   "made. Anything at --out that is not a Zarr store is refused even so.")
@click.option("--workers", "-j", type=int, default=None,
              help="Run on a local dask cluster of N single-threaded worker processes. Default: the local "
                   "threaded scheduler.")
@click.option("--scheduler", default=None,
              help="Address of a running dask scheduler (tcp://host:8786); its workers must see --data at the same "
                   "path, and the work directory at the same path or URL.")
@click.option("--shard-size", type=int, default=None,
              help="Frames per shard (the unit of caching and of tasks). Default: the pipeline's run.shard_size.")
@click.option("--limit", type=int, default=None,
              help="Process only the first N frames (in the dataset's order; N >= 1). Default: every frame.")
@click.option("--work", default=None,
              help="Work directory for its lock, the stage cache and finalize's scratch: any filesystem or URL, "
                   "whatever --out is (the store is then built beside --out). Default: <out>.work (the output's own "
                   "lock is <out>.lock)")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override a pipeline setting, e.g. --set stages.view.params.mean_error_deg=30 (repeatable).")
@click.option("--models", "-m", type=click.Path(file_okay=False), default=None,
              help="Folder of your model files, `{models}` in pipeline files. "
                   "Default: $GA3CE_MODEL_DIR, else ./models.")
@click.option("--summary-json", type=click.Path(dir_okay=False), default=None,
              help="Also write the run summary as JSON to this file.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars.")
def run(pipeline, data, out, overwrite, workers, scheduler, shard_size, limit, work, overrides, models, summary_json,
        quiet):
    """Preprocess a dataset into a 3D context store (staged, cached, resumable).

    Every check (pipeline schema, backends, model and data files, dataset layout, what is at --out,
    the locks on the work directory and the output) runs before any work. Stages run on dask over
    shards of frames; each stage's output per shard is cached atomically, so a killed run resumes
    where it stopped when you rerun the same command, and a changed parameter recomputes only that
    stage and the stages after it.

    \b
    Example:
      ga3ce-prep run --pipeline synthetic --data out/synthetic --out out/synthetic.zarr
    """
    from ..errors import ConfigError
    from .run import run_pipeline

    if limit is not None and limit < 1:
        raise ConfigError(f"--limit {limit}: the number of frames to process must be at least 1; leave --limit out "
                          "to process every frame")
    s = run_pipeline(pipeline, data, out, workers=workers, scheduler=scheduler, shard_size=shard_size,
                     limit=limit, work_dir=work, overrides=list(overrides), models=models, overwrite=overwrite,
                     progress=not quiet)
    click.echo(s.format())
    if summary_json:
        Path(summary_json).write_text(json.dumps(s.as_dict(), indent=2))
