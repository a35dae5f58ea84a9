"""`make demo` / `ga3ce-prep demo`: the whole chain on the embedded synthetic world.

synth (GFIE format, exact truth) -> prep (pipelines/synthetic.yaml: sensor depth completion,
the weight-free geometric segmenter, head position; oracle pose and view at 20 degrees) -> three
short training runs in `ablate`'s layout: the paper's GA3CE, ours, and the model without objects
-> evaluation of the three against the v prior and the learning-free baselines on the test scenes.

Every step is cached: rerunning reuses the dataset, the stage cache and the store, and only
trains again if the run folder is missing.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import click

from .errors import Ga3ceError


def _step(n: int, title: str) -> float:
    click.secho(f"\n[{n}/4] {title}", bold=True)
    return time.perf_counter()


def _done(t0: float) -> None:
    click.echo(f"      ({time.perf_counter() - t0:.0f} s)")


@click.command()
@click.option("--out", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Folder for the dataset, the store and the run.")
@click.option("--scenes", default=48, show_default=True, help="Synthetic scenes (rooms); splits are by scene.")
@click.option("--frames-per-scene", default=60, show_default=True, help="Frames per scene.")
@click.option("--epochs", default=20, show_default=True, help="Training epochs (the default recipe otherwise).")
@click.option("--seed", default=0, show_default=True, help="Seed of the world and of training.")
@click.option("--workers", default=None, type=int, help="dask worker processes for prep (default: threads).")
def demo(out: str, scenes: int, frames_per_scene: int, epochs: int, seed: int, workers: int | None) -> None:
    """Run synth -> prep -> train -> eval on the embedded synthetic world and print the 3D MAE of the
    paper's GA3CE, of ours, of the model without objects, of the v prior and of the learning-free
    baselines. Takes several minutes on 2 CPU cores; rerunning reuses every step."""
    from .model import METHODS, ModelConfig
    from .pipeline import run_pipeline
    from .synthetic import generate
    from .train import TrainConfig, ablate, evaluate, format_eval_table
    from .train.evaluate import BASELINE_NOTES

    root = Path(out)
    data, store, run = root / "synthetic", root / "synthetic.zarr", root / "runs" / "demo"
    t_all = time.perf_counter()

    t0 = _step(1, f"synthetic world: {scenes} scenes x {frames_per_scene} frames, GFIE format -> {data}")
    params = {"format": "gfie", "scenes": scenes, "frames_per_scene": frames_per_scene, "seed": seed, "width": 640}
    stamp = data / "demo-params.json"
    if stamp.is_file() and json.loads(stamp.read_text()) == params and (data / "truth.h5").is_file():
        click.echo("      reusing the dataset written before with the same parameters")
    else:
        if data.exists() and any(data.iterdir()):
            raise Ga3ceError(f"{data} exists with other contents; remove it or pass another --out")
        generate("gfie", data, scenes=scenes, frames_per_scene=frames_per_scene, seed=seed, width=640)
        stamp.write_text(json.dumps(params))
    _done(t0)

    t0 = _step(2, f"preprocessing (pipelines/synthetic.yaml) -> {store}")
    summary = run_pipeline("synthetic", data=data, out=store, workers=workers)
    click.echo(summary.format())
    _done(t0)

    rows = ("full", "no-objects", "ours")   # ours starts from the no-objects model
    t0 = _step(3, f"training the paper's GA3CE, ours and the model without objects ({epochs} epochs each, the "
                  f"default recipe: docs/training.md) -> {run}/{{{','.join(rows)}}}/seed{seed}")
    if all((run / row / f"seed{seed}" / "best.pt").is_file() for row in rows):
        click.echo("      reusing the trained runs (delete them to train again)")
    base = TrainConfig(store=str(store), out=str(run), epochs=epochs, seed=seed, model=ModelConfig.for_method("ga3ce"))
    ablate(base, run, rows=list(rows))
    _done(t0)

    t0 = _step(4, "evaluation on the test scenes")
    result = evaluate(str(store), run / "full" / f"seed{seed}" / "best.pt", split="test")
    click.echo(format_eval_table(result, per_scene=False))
    _done(t0)

    labels = result["labels"]
    notes = {"model": METHODS["ga3ce"].summary, "ours": f"our design: {METHODS['ours'].summary}",
             "no_objects": "the same network without the objects (the paper's appearance + pose row)",
             **BASELINE_NOTES}
    click.echo("\nthe rows:")
    for key in result["methods"]:
        click.echo(f"  {labels[key]:26s} {notes[key]}")
    m = {k: v["mae3d"] for k, v in result["methods"].items()}
    paper, ours, bare, prior = m["model"], m["ours"], m["no_objects"], m["view_prior"]
    click.secho(f"\n3D MAE on the test scenes: GA3CE (paper) {paper:.2f} deg, ours {ours:.2f} deg, no objects "
                f"{bare:.2f} deg, the v prior {prior:.2f} deg (the paper on GFIE: no objects 13.1 -> GA3CE 11.1, "
                f"v prior 19.4)", bold=True)
    click.echo(f"angular-error CDF: {result['cdf_png']}")
    click.echo(f"total {time.perf_counter() - t_all:.0f} s. Next: ga3ce-prep info {store} | "
               f"ga3ce-prep show {store} <frame id> --out frame.png")


if __name__ == "__main__":
    import sys

    from .cli import main

    sys.argv = ["ga3ce-prep", "demo", *sys.argv[1:]]
    main()
