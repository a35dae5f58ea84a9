"""`ga3ce-prep synth`: write a synthetic RGB-D dataset in a real dataset's on-disk format."""
from __future__ import annotations

import os

import click


@click.command("synth")
@click.option("--format", "fmt", type=click.Choice(["gfie", "cad120", "gafa"]), default="gfie", show_default=True,
              help="On-disk format: GFIE (jpg + npy metres + pixel CSV), CAD-120 (png + mm png + normalised CSV) "
                   "or GAFA raw (jpg per camera + pkl + intrinsics.npz; no depth).")
@click.option("--out", "out", type=click.Path(file_okay=False), required=True,
              help="Dataset root to write (created); the truth side-car goes to OUT/truth.h5.")
@click.option("--scenes", type=click.IntRange(1), default=10, show_default=True,
              help="Number of scenes (rooms, each with one person and its own camera(s)); splits are made by scene.")
@click.option("--frames-per-scene", type=click.IntRange(1), default=20, show_default=True,
              help="Time steps per scene (GAFA writes one image per camera per step).")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Master seed: the same seed, size and config give byte-identical annotation files.")
@click.option("--width", type=click.IntRange(16), default=640, show_default=True, help="Image width (px).")
@click.option("--height", type=click.IntRange(16), default=None,
              help="Image height (px); default keeps the format's aspect ratio (480 at 640 wide for GFIE/CAD-120).")
@click.option("--config", "config", type=click.Path(dir_okay=False, exists=True), default=None,
              help="YAML file overriding the world's knobs (sections room, objects, person, gaze, camera, render, "
                   "depth, keypoints; see docs/synthetic.md).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def synth(fmt, out, scenes, frames_per_scene, seed, width, height, config, quiet):
    """Write a synthetic RGB-D dataset with exact ground truth in the GFIE, CAD-120 or GAFA format.

    The dataset adapters read it as they would the real dataset; OUT/truth.h5 holds the exact
    pose, eye, gaze target, head direction, depth and instance maps keyed by the adapters' frame
    ids (read it with ga3ce_prep.synthetic.truth.TruthReader).
    """
    os.environ.setdefault("OMP_NUM_THREADS", "2")
    from .generation import generate

    rep = generate(fmt, out, scenes, frames_per_scene, seed=seed, width=width, height=height, config=config,
                   progress=not quiet)
    secs = rep.total_seconds
    click.echo(f"wrote {rep.frames} {fmt} frames ({rep.steps} time steps, {scenes} scenes) to {rep.out} "
               f"in {secs:.1f} s ({rep.frames / max(secs, 1e-9):.1f} frames/s)")
    from .stats import format_statistics, object_snap, world_statistics
    from .truth import TruthReader

    with TruthReader(rep.out) as tr:
        click.echo("world statistics:\n" + format_statistics(world_statistics(tr)))
        click.echo("objects as gaze evidence (v = truth + 20 deg noise; snap v to the nearest visible object):\n"
                   + format_statistics(object_snap(tr)))
