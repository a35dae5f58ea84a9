"""What `ga3ce-prep view` costs on one long session (docs/store.md "Look at a run"): the recording's size
(MB, and per 1,000 frames), its bytes by entity, the seconds per frame and the command's peak memory, with
the defaults and with the options that trade size (--points, --no-depth, --jpeg-quality), and on the
session's first 100 frames (the peak memory does not grow with the frames); and, with
--screenshot, the web viewer's picture of a session in headless chromium, for the manual (a PNG of 256
colours).

The default store is one session of 1,000 frames at 640x480 (a GFIE-format synthetic world, one room,
seed 7, through the demo's pipeline `synthetic`), written once under --work. Each recording is made by
`ga3ce-prep view` in a process of its own, under the CPU lock (benchmarks/cpu_lock.py).

    python benchmarks/bench_view.py [--store S.zarr --session NAME] [--checkpoint best.pt]
    python benchmarks/bench_view.py --store out/synthetic.zarr --session test/scene1 -c best.pt --only-screenshot \
        --screenshot docs/img/view.png
"""
from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import click

from cpu_lock import CLI, cpu_lock, run_locked

# runs the command line, then prints the process's peak resident memory (KiB) as its last line on stderr
PEAK = ("import resource, sys\nfrom ga3ce_prep.cli import main\nsys.argv = ['ga3ce-prep', *sys.argv[1:]]\n"
        "try:\n    main()\nfinally:\n"
        "    print('peak_kib', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\n")
VARIANTS = {"defaults": [], "--points 20000": ["--points", "20000"], "--jpeg-quality 95": ["--jpeg-quality", "95"],
            "--no-depth": ["--no-depth"]}


def world(work: Path, frames: int) -> tuple[Path, str]:
    """The default store (module docstring), made once under `work`; (its path, its session)."""
    data, store = work / f"world_{frames}", work / f"world_{frames}.zarr"
    if not (data / "truth.h5").is_file():
        shutil.rmtree(data, ignore_errors=True)
        run_locked([*CLI, "synth", "--format", "gfie", "--out", str(data), "--scenes", "1", "--frames-per-scene",
                    str(frames), "--width", "640", "--seed", "7"])
    if not (store / "zarr.json").is_file():
        run_locked([*CLI, "run", "--pipeline", "synthetic", "--data", str(data), "--out", str(store)])
    from ga3ce_prep.store import open_lazy

    return store, open_lazy(store, verify=False).scene_names[0]


def measure(store: Path, session: str, extra: list[str], out: Path) -> dict[str, float]:
    """One recording of the session: MB, MB per 1,000 frames, frames, seconds per frame, peak MiB."""
    cmd = [sys.executable, "-c", PEAK, "view", str(store), "--session", session, "--save", str(out), *extra]
    with cpu_lock():
        t = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True)
        seconds = time.perf_counter() - t
    if p.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{p.stderr[-3000:]}")
    frames = int(re.search(r"(\d+) frames of", p.stdout)[1])
    peak = int(re.findall(r"peak_kib (\d+)", p.stderr)[-1]) / 1024
    mb = out.stat().st_size / 1e6
    return {"MB": mb, "MB per 1,000 frames": 1000 * mb / frames, "frames": frames, "s per frame": seconds / frames,
            "peak MiB": peak}


def by_entity(path: Path) -> dict[str, float]:
    """kB per frame of each entity, as Arrow holds it once read (uncompressed), largest first."""
    from ga3ce_prep.testing.recordings import read_recording

    rec = read_recording(path)
    frames = len(rec.at("/frames/id", "row"))
    return dict(sorted(((e, n / frames / 1e3) for e, n in rec.nbytes.items()), key=lambda kv: -kv[1]))


def screenshot(store: Path, session: str, checkpoint: str | None, out: Path, frames: int) -> None:
    """The web viewer (`view --serve`) showing the session in headless chromium, once every frame
    arrived (the recording it holds, read back), as a PNG of 256 colours at `out`."""
    import io

    from PIL import Image

    from ga3ce_prep.testing.browser import rerun_web_viewer
    from ga3ce_prep.testing.cluster import free_port

    web, grpc = free_port(), free_port()
    cmd = [*CLI, "view", str(store), "--session", session, "--serve", "--web-port", str(web),
           "--grpc-port", str(grpc), *(["-c", checkpoint] if checkpoint else [])]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        url = next(m[1] for line in proc.stderr if (m := re.search(r"viewer at (http://\S+)", line)))
        page = rerun_web_viewer(url, frames, Path(tempfile.mkdtemp()) / "held.rrd", timeout=300, settle=5)
        if not page.ready:
            raise SystemExit(f"the web viewer did not receive every frame: {page.errors[:3]}")
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
    img = Image.open(io.BytesIO(page.png)).convert("RGB").quantize(256)
    out.parent.mkdir(parents=True, exist_ok=True)
    img.save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB, {img.size[0]}x{img.size[1]})")


@click.command()
@click.option("--store", type=click.Path(), default=None, help="A store (default: the 1,000-frame world).")
@click.option("--session", default=None, help="Its session (default: the world's one).")
@click.option("--checkpoint", "-c", default=None, help="A checkpoint for the model's g (recordings and screenshot).")
@click.option("--frames", default=1000, show_default=True, help="Frames of the default world's session.")
@click.option("--work", type=click.Path(file_okay=False), default="out/bench/view", show_default=True)
@click.option("--screenshot", "shot", type=click.Path(dir_okay=False), default=None,
              help="Also write the web viewer's screenshot of the session here.")
@click.option("--only-screenshot", is_flag=True, help="Only the screenshot, no recordings measured.")
def main(store: str | None, session: str | None, checkpoint: str | None, frames: int, work: str, shot: str | None,
         only_screenshot: bool) -> None:
    from ga3ce_prep.store import open_lazy

    work_dir = Path(work)
    work_dir.mkdir(parents=True, exist_ok=True)
    if store is None:
        path, name = world(work_dir, frames)
    else:
        path, name = Path(store), session or ""
    lazy = open_lazy(path, verify=False)
    if not only_screenshot:
        first = [str(i) for i in lazy.index["id"][lazy.index["scene"] == lazy.scene_names.index(name)][:100].tolist()]
        variants = {**VARIANTS, "defaults, its first 100 frames": [a for i in first for a in ("--frame", i)]}
        rows = {}
        for label, extra in variants.items():
            rrd = work_dir / f"{re.sub(r'[^a-z0-9]+', '_', label.strip('-'))}.rrd"
            rows[label] = measure(path, name, [*extra, *(["-c", checkpoint] if checkpoint else [])], rrd)
            print(f"{label:>30}: " + ", ".join(f"{k} {v:.3g}" for k, v in rows[label].items()), flush=True)
        print("kB per frame by entity (uncompressed), defaults:")
        for entity, kb in by_entity(work_dir / "defaults.rrd").items():
            print(f"  {entity:<28} {kb:8.1f}")
        (work_dir / "bench_view.json").write_text(json.dumps(rows, indent=1))
    if shot:
        n = int((lazy.index["scene"] == lazy.scene_names.index(name)).sum())
        with cpu_lock():
            screenshot(path, name, checkpoint, Path(shot), n)


if __name__ == "__main__":
    main()
