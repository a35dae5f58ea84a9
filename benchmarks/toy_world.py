"""Write the toy 3D-context world (ga3ce_prep/testing/toy_store.py) as a store, for iterating on the model
before (or beside) the rendered synthetic world: people with 30 joints, 10-60 objects 0.5-4 m from
the head, gaze at an object most of the time, the head turning part of the way, v = truth + 20 deg
noise partly pulled toward the head direction.

    python benchmarks/toy_world.py --frames 20000 --out out/toy.zarr [--view-noise 20 --face-noise 0.03 ...]
"""
from __future__ import annotations

import click

from ga3ce_prep.testing.toy_store import ToyKnobs, write_toy_store


@click.command()
@click.option("--frames", default=20000, show_default=True, help="Frames to generate (70/15/15 split by scene).")
@click.option("--out", default="out/toy.zarr", show_default=True, help="Store path (overwritten).")
@click.option("--seed", default=0, show_default=True, help="Generator seed.")
@click.option("--frames-per-scene", default=40, show_default=True, help="Frames per scene (splits are by scene).")
@click.option("--view-noise", default=20.0, show_default=True, help="Mean angular error of v, degrees.")
@click.option("--view-head-pull", default=0.4, show_default=True,
              help="How far v's mean sits from the gaze toward the head direction (0-1).")
@click.option("--face-noise", default=0.03, show_default=True, help="Face keypoint noise, metres per axis.")
@click.option("--p-object", default=0.8, show_default=True, help="Fraction of frames gazing at an object.")
def main(frames, out, seed, frames_per_scene, view_noise, view_head_pull, face_noise, p_object):
    knobs = ToyKnobs(view_noise_deg=view_noise, view_head_pull=view_head_pull, face_noise=face_noise, p_object=p_object)
    path = write_toy_store(out, frames, seed, frames_per_scene, knobs)
    click.echo(f"wrote {path} ({frames} frames)")


if __name__ == "__main__":
    main()
