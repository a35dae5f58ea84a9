"""`make demo` / `ga3ce-prep demo`: the whole chain on the embedded synthetic world, run as the
paper runs its experiments.

synth: a GFIE-format world whose rooms are each recorded in several sessions, split by session, so
the test rooms were seen in training (the paper's GFIE and GAFA protocol), and a small transfer
world (`synth --preset transfer`: CAD-120 format, unseen rooms, another camera: the paper's Table 2)
-> prep (the bundled pipeline `synthetic`: sensor depth completion, the weight-free geometric
segmenter, head position; oracle pose and view) -> three short training runs in `ablate`'s layout: the
paper's GA3CE, ours, and the model without objects -> evaluation of the three against the v prior
and the learning-free baselines on the seen-room test split and on the transfer world.

Every step is cached: rerunning reuses the datasets, the stage cache and the stores, and only
trains again if the run folder is missing.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import click

from .errors import Ga3ceError


def _step(n: int, title: str) -> float:
    click.secho(f"\n[{n}/5] {title}", bold=True)
    return time.perf_counter()


def _done(t0: float) -> None:
    click.echo(f"      ({time.perf_counter() - t0:.0f} s)")


def _world(data: Path, params: dict[str, Any]) -> None:
    """Write the synthetic world `params` (generate's arguments) into `data`, unless it is there."""
    from .synthetic import generate

    stamp = data / "demo-params.json"
    if stamp.is_file() and json.loads(stamp.read_text()) == params and (data / "truth.h5").is_file():
        click.echo(f"      reusing {data}, written before with the same parameters")
        return
    if data.exists() and any(data.iterdir()):
        raise Ga3ceError(f"{data} exists with other contents; remove it or pass another --out")
    generate(**params, out=data, width=640, workers=os.cpu_count() or 1)   # the same files with any count
    stamp.write_text(json.dumps(params))


@click.command()
@click.option("--out", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Folder for the datasets, the stores and the runs.")
@click.option("--rooms", default=48, show_default=True, help="Rooms of the training world.")
@click.option("--sessions-per-room", default=4, show_default=True,
              help="Sessions recorded in each room; splits are by session, so test rooms are seen in training "
                   "(1: split by room, every test room unseen).")
@click.option("--frames-per-session", default=15, show_default=True, help="Frames per session.")
@click.option("--transfer-rooms", default=8, show_default=True,
              help="Rooms of the transfer world (one session of 30 frames each; 0: none).")
@click.option("--epochs", default=20, show_default=True, help="Training epochs (the default recipe otherwise).")
@click.option("--seed", default=0, show_default=True, help="Seed of the worlds and of training.")
@click.option("--workers", default=None, type=int, help="dask worker processes for prep (default: threads).")
def demo(out: str, rooms: int, sessions_per_room: int, frames_per_session: int, transfer_rooms: int, epochs: int,
         seed: int, workers: int | None) -> None:
    """Run synth -> prep -> train -> eval on the embedded synthetic worlds and print the 3D MAE of
    the paper's GA3CE, of ours, of the model without objects, of the v prior and of the
    learning-free baselines, on test sessions of rooms seen in training and on a transfer world of
    unseen rooms and another camera. 9-14 minutes on 2 CPU cores (a study:
    docs/studies/2026-12-05-the-demo-on-a-fresh-clone.md); rerunning reuses every step."""
    from .model import METHODS, ModelConfig, resolve
    from .pipeline import run_pipeline
    from .train import TrainConfig, ablate, evaluate, format_eval_table
    from .train.evaluate import BASELINE_NOTES

    root = Path(out)
    data, store, run = root / "synthetic", root / "synthetic.zarr", root / "runs" / "demo"
    tdata, tstore = root / "transfer", root / "transfer.zarr"
    t_all = time.perf_counter()

    t0 = _step(1, f"synthetic worlds: {rooms} rooms x {sessions_per_room} sessions x {frames_per_session} frames, "
                  f"GFIE format -> {data}; transfer: {transfer_rooms} rooms x 30 frames, CAD-120 format -> {tdata}")
    _world(data, {"fmt": "gfie", "scenes": rooms, "sessions_per_room": sessions_per_room,
                  "frames_per_scene": frames_per_session, "seed": seed})
    if transfer_rooms:
        _world(tdata, {"fmt": "cad120", "preset": "transfer", "scenes": transfer_rooms, "frames_per_scene": 30,
                       "seed": seed})
    _done(t0)

    t0 = _step(2, f"preprocessing (pipeline synthetic) -> {store}" + (f", {tstore}" if transfer_rooms else ""))
    click.echo(run_pipeline("synthetic", data=data, out=store, workers=workers).format())
    if transfer_rooms:
        click.echo(run_pipeline("synthetic", data=tdata, out=tstore, workers=workers,
                                overrides=["dataset.format=cad120"]).format())
    _done(t0)

    rows = ("full", "no-objects", "ours")   # ours starts from the no-objects model
    t0 = _step(3, f"training the paper's GA3CE, ours and the model without objects ({epochs} epochs each, the "
                  f"default recipe: docs/training.md) -> {run}/{{{','.join(rows)}}}/seed{seed}")
    if all((run / row / f"seed{seed}" / "best.pt").is_file() for row in rows):
        click.echo("      reusing the trained runs (delete them to train again)")
    base = TrainConfig(store=str(store), out=str(run), epochs=epochs, seed=seed, model=ModelConfig.for_method("ga3ce"))
    ablate(base, run, rows=list(rows))
    _done(t0)

    ckpt = run / "full" / f"seed{seed}" / "best.pt"
    t0 = _step(4, "evaluation on the test sessions (rooms seen in training, other recordings)")
    result = evaluate(str(store), ckpt, split="test")
    click.echo(format_eval_table(result, per_scene=False))
    _done(t0)
    transfer = None
    if transfer_rooms:
        t0 = _step(5, "evaluation on the transfer world (unseen rooms, another camera: the paper's Table 2)")
        transfer = evaluate(str(tstore), ckpt, split="test", cdf_path=None)
        click.echo(format_eval_table(transfer, per_scene=False))
        _done(t0)

    labels = result.labels
    ours = resolve("ours")
    notes = {"model": METHODS["ga3ce"].summary, "ours": f"ours, today the design {ours}: {METHODS[ours].summary}",
             "no_objects": "the same network without the objects (the paper's appearance + pose row)",
             **BASELINE_NOTES}
    click.echo("\nthe rows:")
    for key in result.methods:
        click.echo(f"  {labels[key]:26s} {notes[key]}")
    click.echo(f"\n3D MAE (deg)               {'seen rooms':>10s} {'transfer':>9s}")
    for key in ("model", "ours", "no_objects", "view_prior"):
        other = f"{transfer.methods[key].mae3d:9.2f}" if transfer is not None else f"{'-':>9s}"
        click.echo(f"  {labels[key]:24s} {result.methods[key].mae3d:10.2f} {other}")
    m = {k: v.mae3d for k, v in result.methods.items()}
    click.secho(f"seen rooms = the test sessions of rooms recorded in training (the paper's GFIE protocol: no "
                f"objects 13.1 -> GA3CE 11.1, v prior 19.4); transfer = unseen rooms and another camera "
                f"(its Table 2). The paper's GA3CE {'beats' if m['model'] < m['no_objects'] else 'does NOT beat'} "
                f"its no-objects ablation on the seen rooms here.", bold=True)
    click.echo(f"angular-error CDF: {result.cdf_png}")
    click.echo(f"total {time.perf_counter() - t_all:.0f} s. Next: ga3ce-prep info {store} | "
               f"ga3ce-prep show {store} <frame id> --out frame.png")


if __name__ == "__main__":
    import sys

    from .cli import main

    sys.argv = ["ga3ce-prep", "demo", *sys.argv[1:]]
    main()
