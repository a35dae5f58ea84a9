"""Object medians on measured or completed depth pixels (`objects.params.median_pixels`), measured
against the synthetic truth.

Truth: per true object (kinds object + furniture) the median of its truth mask back-projected with
the exact rendered depth (the `synthetic-oracle` pipeline with `depth: oracle`). Then, for each
choice of median pixels, the sensor-depth pipelines (IP-Basic completion) with
  - the truth masks (`synthetic-oracle`: segmentation is perfect, only the medians differ) and
  - the geometric segmenter (`synthetic`: the demo's pipeline),
and per true object the distance from its truth median to the nearest stored position of the same
frame: recall within 10 cm (as `bench_prep.recall`); then, paired per true object, how many each
choice alone finds, and the position error (median, 90th percentile, mean) of each over the true
objects both find.

    ga3ce-prep synth --format gfie --out out/bench/world --scenes 64 --frames-per-scene 4 --seed 11 --width 640
    OMP_NUM_THREADS=1 python benchmarks/bench_medians.py --data out/bench/world [--frames 256]
"""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import click
import numpy as np

from ga3ce_prep.testing.stores import object_distances

ROOT = Path(__file__).resolve().parent.parent
RUNS = {  # label -> (pipeline, overrides)
    "truth": ("synthetic-oracle", ["stages.depth.backend=oracle", "stages.depth.params={truth: '{data}/truth.h5'}"]),
    "oracle masks": ("synthetic-oracle", []),
    "geometric": ("synthetic", []),
}


def summary(d: np.ndarray, area: np.ndarray, store) -> dict:
    ok = d < 0.10
    small = area < 300
    return {"true_objects": int(len(d)), "within_10cm": int(ok.sum()), "recall": float(ok.mean()),
            "recall_small_lt300px": float(ok[small].mean()), "recall_large_ge300px": float(ok[~small].mean()),
            "stored_per_frame": float(store.frames["obj_count"].mean()),
            "masks_dropped_few_points": int(store.attrs["summary"]["masks_dropped_few_points"])}


def paired(dm: np.ndarray, dc: np.ndarray) -> dict:
    """Measured (dm) vs completed (dc) distances of the same true objects: who finds what, and the
    error of each over the objects both find."""
    om, oc = dm < 0.10, dc < 0.10
    both = om & oc

    def pct(a, q):  # cm
        return float(100 * np.percentile(a, q)) if len(a) else None

    return {"found_by_both": int(both.sum()), "only_measured": int((om & ~oc).sum()),
            "only_completed": int((oc & ~om).sum()),
            "both_error_cm": {"measured": {"median": pct(dm[both], 50), "p90": pct(dm[both], 90),
                                           "mean": float(100 * dm[both].mean())},
                              "completed": {"median": pct(dc[both], 50), "p90": pct(dc[both], 90),
                                            "mean": float(100 * dc[both].mean())}},
            "closer": {"measured": int((dm[both] < dc[both]).sum()), "completed": int((dc[both] < dm[both]).sum())}}


@click.command()
@click.option("--data", required=True, type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="A GFIE-format synthetic world (`ga3ce-prep synth --format gfie`).")
@click.option("--frames", default=256, show_default=True, help="Frames to run (the first N).")
@click.option("--work", default=str(ROOT / "out" / "bench" / "medians"), show_default=True,
              type=click.Path(path_type=Path))
@click.option("--json", "json_out", default=str(ROOT / "out" / "bench" / "bench_medians.json"), show_default=True)
def main(data: Path, frames: int, work: Path, json_out: str) -> None:
    """Measured vs completed median pixels (module docstring)."""
    from ga3ce_prep.pipeline import run_pipeline
    from ga3ce_prep.store import open_store

    work.mkdir(parents=True, exist_ok=True)
    stores = {}
    for label, (pipeline, over) in RUNS.items():
        for choice in (("measured",) if label == "truth" else ("measured", "completed")):
            name = f"{label.replace(' ', '-')}-{choice}"
            out = work / f"{name}.zarr"
            shutil.rmtree(out, ignore_errors=True)
            shutil.rmtree(work / f"{name}.work", ignore_errors=True)
            t = time.perf_counter()
            run_pipeline(pipeline, data, out, limit=frames, progress=False, work_dir=work / f"{name}.work",
                         overrides=[*over, f"stages.objects.params.median_pixels={choice}"])
            print(f"{name}: {time.perf_counter() - t:.0f} s", flush=True)
            stores[(label, choice)] = open_store(out)
    truth = stores[("truth", "measured")]
    res = {"conditions": {"data": str(data), "frames": int(len(truth.frames["id"])),
                          "width": int(truth.frames["image_size"][0][0]) if "image_size" in truth.frames else None,
                          "omp_threads": os.environ.get("OMP_NUM_THREADS")},
           "truth_objects_per_frame": float(truth.frames["obj_count"].mean())}
    dist = {}
    for (label, choice), store in stores.items():
        if label != "truth":
            dist[(label, choice)], area = object_distances(truth, store)
            res[f"{label} / {choice}"] = summary(dist[(label, choice)], area, store)
    for label in ("oracle masks", "geometric"):
        res[f"{label}: measured vs completed"] = paired(dist[(label, "measured")], dist[(label, "completed")])
    Path(json_out).parent.mkdir(parents=True, exist_ok=True)
    Path(json_out).write_text(json.dumps(res, indent=2))
    print(f"\n{res['conditions']['frames']} frames, {res['truth_objects_per_frame']:.1f} true objects per frame")
    print(f"{'masks / median pixels':<26} {'recall@10cm':>11} {'<300px':>7} {'>=300px':>8} {'stored/frame':>13} "
          f"{'dropped':>8}")
    for k, v in res.items():
        if isinstance(v, dict) and "recall" in v:
            print(f"{k:<26} {100 * v['recall']:10.1f}% {100 * v['recall_small_lt300px']:6.1f}% "
                  f"{100 * v['recall_large_ge300px']:7.1f}% {v['stored_per_frame']:13.2f} "
                  f"{v['masks_dropped_few_points']:8d}")
    print(f"\n{'masks':<14} {'found by both':>13} {'only meas.':>10} {'only compl.':>11}   error over both, cm: "
          "measured median/p90/mean | completed median/p90/mean | closer: meas./compl.")
    for label in ("oracle masks", "geometric"):
        v = res[f"{label}: measured vs completed"]
        m, c = v["both_error_cm"]["measured"], v["both_error_cm"]["completed"]
        print(f"{label:<14} {v['found_by_both']:13d} {v['only_measured']:10d} {v['only_completed']:11d}   "
              f"{m['median']:.2f}/{m['p90']:.2f}/{m['mean']:.2f} | {c['median']:.2f}/{c['p90']:.2f}/{c['mean']:.2f} | "
              f"{v['closer']['measured']}/{v['closer']['completed']}")
    print(f"figures: {json_out}")


if __name__ == "__main__":
    main()
