"""How far each head-position source lands from the truth when the head box has no measured depth.

On a synthetic GFIE-format world, every frame's sensor depth has its head box blanked
(`synthetic.noise.blank_box`, what `depth.head_hole_prob` does to a fraction of frames), is
completed as the `synthetic` pipeline completes it, and the head stage (`stages/head.py::DepthHead`)
is run with one fallback at a time. Truth: the head box centre back-projected at the median of the
exact rendered depth in the same windows (t_object as the head stage defines it, on perfect
depth). "measured" is the head stage on the untouched sensor depth, for reference. The pose comes
from the `oracle` pose backend's noise model at two settings: an RGB-D-refined pose
(1 cm per joint, no scale error) and a monocular estimator's (2 cm body, 4 cm face, a per-frame
scale about the camera centre with 10% log-std: its distance is off by the size error).

    ga3ce-prep synth --format gfie --out out/bench/world --scenes 64 --frames-per-scene 4 --seed 11 --width 640
    OMP_NUM_THREADS=1 python benchmarks/bench_head_fallback.py --data out/bench/world [--frames 256] [--json out.json]
"""
from __future__ import annotations

import json
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import click
import numpy as np

POSES = {  # label -> noisy_pose keyword arguments
    "RGB-D pose (1 cm)": {"sigma_body": 0.01, "sigma_face": 0.01},
    "monocular pose (2/4 cm, 10% scale)": {"sigma_body": 0.02, "sigma_face": 0.04, "scale_sigma": 0.1},
}


def stats(err: list[float]) -> dict:
    e = 100.0 * np.asarray(err)
    if not len(e):
        return {"frames": 0}
    return {"frames": int(len(e)), "median_cm": float(np.median(e)), "p90_cm": float(np.percentile(e, 90)),
            "max_cm": float(e.max())}


@click.command()
@click.option("--data", required=True, type=click.Path(exists=True, file_okay=False),
              help="A synthetic GFIE-format world.")
@click.option("--frames", default=None, type=int, help="Use the first N frames (default all).")
@click.option("--json", "json_path", default=None, help="Also write the figures as JSON.")
def main(data: str, frames: int | None, json_path: str | None) -> None:
    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.estimators.depth.completion import complete_depth
    from ga3ce_prep.frames import DepthMap, load_depth
    from ga3ce_prep.geometry import head_position
    from ga3ce_prep.params import from_dict
    from ga3ce_prep.pipeline import load_pipeline
    from ga3ce_prep.stages.base import BackendContext
    from ga3ce_prep.stages.depth import SensorDepth
    from ga3ce_prep.stages.head import FALLBACKS, DepthHead
    from ga3ce_prep.stages.oracle_noise import frame_rng, noisy_pose
    from ga3ce_prep.synthetic.noise import blank_box
    from ga3ce_prep.synthetic.truth import TruthReader

    root = Path(data)
    conf = load_pipeline("synthetic", root, check_files=False)
    completion = from_dict(SensorDepth.Params, conf.stages["depth"].params)
    head_params = conf.stages["head"].params
    ctx = BackendContext(root)
    heads = {fb: DepthHead({**head_params, "fallbacks": [fb]}, ctx) for fb in FALLBACKS}
    measured = DepthHead({**head_params, "fallbacks": []}, ctx)
    truth = TruthReader(root / "truth.h5")
    refs = list(open_dataset("gfie", root).frames())[:frames]
    err: dict[str, dict[str, list[float]]] = {p: {s: [] for s in ("measured", *FALLBACKS)} for p in POSES}
    for f in refs:
        t = truth.get(f.id)
        exact = np.asarray(t.depth, np.float32)
        try:
            true_pos = head_position(exact, f.K, f.head_box, valid=exact > 0, window_fracs=measured.p.window_fracs,
                                     min_points=measured.p.min_points)
        except Exception:  # no head in view: nothing to measure
            continue
        raw = load_depth(f.depth_path, f.depth_scale)
        holed = raw.copy()
        blank_box(holed, f.head_box)
        dm_raw, dm_holed = complete_depth(raw, completion), complete_depth(holed, completion)
        for label, kw in POSES.items():
            pose = noisy_pose(np.asarray(t.pose), frame_rng(0, "pose/oracle", f.id), **kw)
            try:
                err[label]["measured"].append(float(np.linalg.norm(measured.head(f, dm_raw, pose).value - true_pos)))
            except Exception:  # the sensor measured nothing there either
                pass
            for fb, backend in heads.items():
                try:
                    r = backend.head(f, DepthMap(dm_holed.depth, dm_holed.valid), pose)
                except Exception:  # this source knows nothing for the frame
                    continue
                if r.source == fb:
                    err[label][fb].append(float(np.linalg.norm(r.value - true_pos)))
    out = {label: {s: stats(e) for s, e in by.items()} for label, by in err.items()}
    n = len(refs)
    click.echo(f"{root}: {n} frames, head box blanked in each; distance from t_object on the exact depth")
    for label, by in out.items():
        click.echo(f"\n{label}")
        click.echo(f"  {'source':12s} {'frames':>7s} {'median':>8s} {'p90':>8s} {'max':>8s}  (cm)")
        for s, r in by.items():
            if r["frames"]:
                click.echo(f"  {s:12s} {r['frames']:7d} {r['median_cm']:8.1f} {r['p90_cm']:8.1f} {r['max_cm']:8.1f}")
            else:
                click.echo(f"  {s:12s} {0:7d}")
    if json_path:
        Path(json_path).write_text(json.dumps({"data": str(root), "frames": n, "poses": POSES, "results": out},
                                              indent=2))


if __name__ == "__main__":
    main()
