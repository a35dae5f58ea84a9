"""Benchmark: synthetic world generation speed at 640x480 on one core, per format, and where the
time goes (`make bench-synth`). Goal: at least 20 frames/s.

One core: OMP/MKL/OpenBLAS threads 1 and Open3D ray casting with nthreads=1 (render.py). Frames
are camera images (GAFA writes one per camera per time step). Figures are provisional on a shared
machine.
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_v] = "1"

import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import click  # noqa: E402
import cv2  # noqa: E402

from ga3ce_prep.synthetic import generate  # noqa: E402


@click.command(help=__doc__)
@click.option("--formats", default="gfie,cad120,gafa", show_default=True)
@click.option("--scenes", default=4, show_default=True)
@click.option("--frames-per-scene", default=25, show_default=True)
@click.option("--width", default=640, show_default=True)
@click.option("--height", default=480, show_default=True, help="GFIE/CAD-120 height (GAFA keeps its aspect ratio)")
def main(formats: str, scenes: int, frames_per_scene: int, width: int, height: int) -> None:
    cv2.setNumThreads(1)
    print(f"synthetic world generation, {width} wide, {scenes} scenes x {frames_per_scene} steps, "
          f"one core")
    rows = []
    for fmt in formats.split(","):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            rep = generate(fmt, Path(tmp) / fmt, scenes, frames_per_scene, seed=0, width=width,
                           height=None if fmt == "gafa" else height, progress=False)
            wall = time.perf_counter() - t0
        fps = rep.frames / wall
        rows.append((fmt, rep.frames, wall, fps))
        print(f"\n{fmt}: {rep.frames} frames in {wall:.2f} s = {fps:.1f} frames/s "
              f"({'meets' if fps >= 20 else 'BELOW'} the 20 frames/s goal)")
        for name, sec in sorted(rep.seconds.items(), key=lambda kv: -kv[1]):
            print(f"  {name:40s} {1000 * sec / rep.frames:7.2f} ms/frame  {100 * sec / rep.total_seconds:5.1f} %")
    print("\nformat   frames   seconds   frames/s")
    for fmt, n, wall, fps in rows:
        print(f"{fmt:8s} {n:6d} {wall:9.2f} {fps:10.1f}")


if __name__ == "__main__":
    main()
