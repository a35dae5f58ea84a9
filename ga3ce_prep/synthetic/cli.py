"""`ga3ce-prep synth`: write a synthetic RGB-D dataset in a real dataset's on-disk format."""
from __future__ import annotations

import os

import click

from .config import FORMATS, load_preset, preset_names


@click.command("synth")
@click.option("--format", "fmt", type=click.Choice(list(FORMATS)), default=None,
              help="On-disk format: GFIE (jpg + npy metres + pixel CSV), CAD-120 (png + mm png + normalised CSV) "
                   "or GAFA raw (jpg per camera + pkl + intrinsics.npz; no depth). Default: the preset's, else gfie.")
@click.option("--preset", type=click.Choice(preset_names()), default=None,
              help="A named world shipped with the package (ga3ce_prep/synthetic/presets/): its format, a seed offset "
                   "and config sections; --config applies on top (docs/synthetic.md). "
                   + "; ".join(f"{n}: {load_preset(n).description}" for n in preset_names()) + ".")
@click.option("--out", "out", type=click.Path(file_okay=False), required=True,
              help="Dataset root to write (created); the truth side-car goes to OUT/truth.h5.")
@click.option("--scenes", type=click.IntRange(1), default=10, show_default=True,
              help="Number of rooms (furniture, objects, light), each recorded in --sessions-per-room sessions.")
@click.option("--sessions-per-room", type=click.IntRange(1), default=1, show_default=True,
              help="Sessions recorded in each room, each with its own person, camera placement and timeline. "
                   "1: splits by room, val/test rooms unseen in training (CAD-120-like transfer). R > 1: splits by "
                   "session, every room keeps a training session and val/test (about 15% of the sessions each) are "
                   "rooms seen in training, as in the paper's GFIE and GAFA experiments (GAFA: its own session "
                   "split). CAD-120 is all test either way.")
@click.option("--frames-per-scene", type=click.IntRange(1), default=20, show_default=True,
              help="Time steps per session (GAFA writes one image per camera per step).")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Master seed: the same seed, size and config give byte-identical annotation files (a preset adds "
                   "its seed offset).")
@click.option("--width", type=click.IntRange(16), default=640, show_default=True, help="Image width (px).")
@click.option("--height", type=click.IntRange(16), default=None,
              help="Image height (px); default keeps the format's aspect ratio (480 at 640 wide for GFIE/CAD-120).")
@click.option("--config", "config", type=click.Path(dir_okay=False, exists=True), default=None,
              help="YAML file overriding the world's knobs (sections room, objects, person, gaze, camera, render, "
                   "depth, keypoints; see docs/synthetic.md), on top of the preset if one is given.")
@click.option("--workers", type=click.IntRange(1), default=None,
              help="Processes rendering rooms (default: the machine's cores, at most one per room); the files are "
                   "the same bytes with any number.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def synth(fmt, preset, out, scenes, sessions_per_room, frames_per_scene, seed, width, height, config, workers, quiet):
    """Write a synthetic RGB-D dataset with exact ground truth in the GFIE, CAD-120 or GAFA format.

    The dataset adapters read it as they would the real dataset; OUT/truth.h5 holds the exact
    pose, eye, gaze target, head direction, depth and instance maps keyed by the adapters' frame
    ids (read it with ga3ce_prep.synthetic.truth.TruthReader).
    """
    if preset is not None:
        pfmt = load_preset(preset).format
        if fmt is not None and fmt != pfmt:
            raise click.UsageError(f"--preset {preset} writes the {pfmt} format; drop --format {fmt}")
        fmt = pfmt
    fmt = fmt or "gfie"
    os.environ.setdefault("OMP_NUM_THREADS", "2")
    from .generation import generate

    workers = workers or os.cpu_count() or 1
    rep = generate(fmt, out, scenes, frames_per_scene, seed=seed, width=width, height=height, config=config,
                   progress=not quiet, sessions_per_room=sessions_per_room, preset=preset, workers=workers)
    secs = rep.wall_seconds
    click.echo(f"wrote {rep.frames} {fmt} frames ({rep.steps} time steps, {scenes} rooms x {sessions_per_room} "
               f"sessions) to {rep.out} in {secs:.1f} s ({rep.frames / max(secs, 1e-9):.1f} frames/s, "
               f"{min(workers, scenes)} process{'es' if min(workers, scenes) > 1 else ''})")
    from .stats import format_statistics, object_snap, split_recordings, world_statistics
    from .truth import TruthReader

    with TruthReader(rep.out) as tr:
        click.echo("world statistics:\n" + format_statistics(world_statistics(tr)))
        click.echo("objects as gaze evidence (v = truth + 20 deg noise; snap v to the nearest visible object):\n"
                   + format_statistics(object_snap(tr)))
        preset_txt = f", preset {preset}" if preset else ""
        click.echo(f"protocol: {tr.protocol} (seed {tr.attrs['seed']}{preset_txt})")
        for name, c in split_recordings(tr).items():
            click.echo(f"  {name:5s} {c['sessions']:4d} sessions in {c['rooms']:4d} rooms "
                       f"({c['rooms_seen_in_training']} with training sessions)")
