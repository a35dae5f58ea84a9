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

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402

from ga3ce_prep.synthetic import generate  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--formats", default="gfie,cad120,gafa")
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--frames-per-scene", type=int, default=25)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480, help="GFIE/CAD-120 height (GAFA keeps its aspect ratio)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"synthetic world generation, {args.width} wide, {args.scenes} scenes x {args.frames_per_scene} steps, "
          f"one core")
    rows = []
    for fmt in args.formats.split(","):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            rep = generate(fmt, Path(tmp) / fmt, args.scenes, args.frames_per_scene, seed=0, width=args.width,
                           height=None if fmt == "gafa" else args.height, progress=False)
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
