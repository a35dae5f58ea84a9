"""The demo's synthetic worlds (48 rooms x 4 sessions x 15 frames, GFIE format, and the 8-room
transfer world, 640x480: demo.py's step 1) written by 1 and by 2 processes (`generate(...,
workers=N)`), twice each in turn, in one run: wall seconds and a digest of every file but
truth.h5 (the same bytes with any count).

Usage: python benchmarks/synth_workers.py OUT_FOLDER   (about 8 minutes on 2 cores)
"""
import hashlib
import shutil
import time
from pathlib import Path

import click

from ga3ce_prep.synthetic import generate


def world(out: Path, workers: int) -> float:
    """Write the demo's two worlds under `out`; returns wall seconds."""
    t = time.perf_counter()
    generate("gfie", out / "synthetic", scenes=48, frames_per_scene=15, seed=0, sessions_per_room=4,
             width=640, progress=False, workers=workers)
    generate("cad120", out / "transfer", scenes=8, frames_per_scene=30, seed=0, preset="transfer",
             width=640, progress=False, workers=workers)
    return time.perf_counter() - t


def digest(folder: Path) -> str:
    """SHA-256 (first 16 hex digits) over every file's relative path and bytes, truth.h5 aside."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != "truth.h5":
            h.update(str(p.relative_to(folder)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()[:16]


@click.command(help=__doc__)
@click.argument("out_folder", type=click.Path(file_okay=False, path_type=Path))
def main(out_folder: Path) -> None:
    for rep in range(2):
        for w in (1, 2):
            out = out_folder / f"w{w}"
            shutil.rmtree(out, ignore_errors=True)
            s = world(out, w)
            print(f"round {rep} workers {w}: {s:.1f} s  files {digest(out)}", flush=True)


if __name__ == "__main__":   # the worker processes are spawned: they import this file
    main()
