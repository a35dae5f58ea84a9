"""`make bench-objects`: MobileSAM segment-everything, every row in one run, then a summary.

(a) One 640x480 frame, random-weight MobileSAM files: the reference order (testing/amg_reference.py,
a port of segment-anything's generator onto the official ONNX files, one official-decoder call per
grid point, filters on full-resolution logits, box NMS) against the `mobilesam` backend (fast
decoder), with the IoU threshold at the quantiles of the predicted IoUs that let 10%, 30% and 100%
of the candidates pass (random weights pass almost none at 0.88). Seconds per frame (backend: median
of --repeat; reference: one run, ~40 s), their ratio (target >= 5x at 30%), the time per step, and
whether both keep the same masks (count, scores within 1e-4, boxes within 1 px, at most 0.1% of a
mask's pixels differing).

(b) The GPU batch path (`io_binding`: a frame's prompts in one batch, state bound on the device)
against plain batches on the CUDA provider, frame (a) at 30%; "skipped" without one (`--only gpu
--gpu-provider cpu` checks the script on CPU, where binding gains nothing).

(c) `--device cpu|cuda`, only these rows: the torch runtime (`runtime: torch`, the random-weight
`mobile_sam.pt`) against MobileSAM's own `SamAutomaticMaskGenerator` on the same checkpoint and
device (testing/official_amg.py; without torchvision its four functions come from numpy and
Pillow): frame (a) at 30%, seconds (median of --repeat) and same masks, also with many kept; then
exact vs reuse on the torch runtime over a synthetic camera sequence (testing/reuse_sequence.py,
--sequence-frames). Tiny check: `--device cpu --points-per-side 4 --repeat 1 --sequence-frames 3`.

Writes out/bench_objects.json. Models: the random-weight files testing/mobilesam_random.py builds
and checks. Takes the CPU lock itself (benchmarks/cpu_lock.py; --no-lock if the caller holds it).
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from types import SimpleNamespace

import click
import cv2
import numpy as np

from ga3ce_prep.testing import mobilesam_random

from cpu_lock import LOCK, cpu_lock

REPO = Path(__file__).resolve().parents[1]
TARGET_RATIO = 5.0   # the goal: the backend >= 5x the reference-order port at 30%


def model_dir() -> Path:
    """The random-weight MobileSAM files, built and checked first if they are not there."""
    return mobilesam_random.ensure()[0].parent


def shares(timings: dict) -> dict:
    total = sum(timings.values())
    return {k: round(v / total, 3) for k, v in sorted(timings.items(), key=lambda kv: -kv[1])}


@click.command(help=__doc__)
@click.option("--fractions", default="0.1,0.3,1.0", show_default=True,
              help="fractions of candidates passing the IoU filter")
@click.option("--no-reference", is_flag=True, help="time only the backend")
@click.option("--threads", default=2, show_default=True, help="intra-op threads")
@click.option("--repeat", default=3, show_default=True, help="backend runs per fraction (the median is reported)")
@click.option("--points-per-side", default=32, show_default=True)
@click.option("--only", type=click.Choice(["random", "gpu"]), default=None,
              help="run only the random-weight rows or the GPU rows")
@click.option("--sequence-frames", default=30, show_default=True,
              help="frames of the torch runtime's reuse sequence (0: no reuse rows)")
@click.option("--sequence-seed", default=6, show_default=True, help="world seed of that sequence")
@click.option("--gpu-provider", default="cuda", show_default=True,
              help="provider of the GPU rows (cpu: check the script on CPU)")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default=None,
              help="run only the torch runtime's rows (c) on this device, against the official generator")
@click.option("--no-lock", is_flag=True, help=f"do not take {LOCK} (the caller holds it)")
@click.option("--out", default=str(REPO / "out" / "bench_objects.json"), show_default=True)
def main(**options) -> None:
    args = SimpleNamespace(**options)   # the row functions below read the options as attributes
    cv2.setNumThreads(args.threads)

    onnx = args.device is None
    with cpu_lock(not args.no_lock):
        results = random_weight_rows(args) if onnx and args.only in (None, "random") else []
        gpu = gpu_rows(args) if onnx and args.only in (None, "gpu") else None
        torch_runtime = None if onnx else torch_rows(args)
    if onnx:
        print_summary(args, results, gpu)
    else:
        print_torch_summary(args, torch_runtime)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"threads": args.threads, "target_ratio_at_30pct": TARGET_RATIO, "rows": results,
                               "gpu": gpu, "torch": torch_runtime}, indent=2))
    print("wrote", out)


def print_summary(args, rows: list[dict], gpu: dict | None) -> None:
    """Every row of this run side by side."""
    print(f"\n== summary: {args.threads} threads, {args.points_per_side}x{args.points_per_side} grid ==")
    for r in rows:
        if r["fraction"] is None:
            print(f"random weights, same masks with many kept ({r['setting']}): "
                  f"{'yes' if r['same_masks'] else 'NO'} ({r['masks_compared']})")
            continue
        line = f"random weights, 640x480, {r['fraction']:>4.0%} pass: backend {r['fast_s']:6.2f} s"
        if "reference_s" in r:
            line += (f" | reference-order port {r['reference_s']:6.2f} s | ratio {r['ratio']:4.1f}x"
                     + (f" (target >= {TARGET_RATIO:.0f}x)" if r["fraction"] == 0.3 else "")
                     + f" | same masks {'yes' if r['same_masks'] else 'NO'} ({r['masks_compared']})")
        print(line)
    if gpu:
        print(f"GPU ({gpu['provider']}), 640x480 at 30%: io_binding {gpu['io_binding_s']:.2f} s | plain batches "
              f"{gpu['plain_s']:.2f} s | same masks as the plain path {'yes' if gpu['same_masks'] else 'NO'} "
              f"({gpu['masks_compared']})")
    elif args.only in (None, "gpu"):
        print("GPU batch path: no CUDA provider: skipped")


def print_torch_summary(args, row: dict) -> None:
    """The torch runtime's rows (c) side by side."""
    print(f"\n== summary: torch runtime on {row['device']} ({row['device_name']}), {args.points_per_side}x"
          f"{args.points_per_side} grid, {args.threads} threads ==")
    print(f"random weights, 640x480, 30% pass: torch runtime {row['exact_s']:6.2f} s | official "
          f"SamAutomaticMaskGenerator {row['official_s']:6.2f} s | ratio {row['ratio']:4.1f}x | same masks "
          f"{'yes' if row['same_masks'] else 'NO'} ({row['masks_compared']})")
    many = row["many_kept"]
    print(f"random weights, same masks with many kept ({many['setting']}): "
          f"{'yes' if many['same_masks'] else 'NO'} ({many['masks_compared']})")
    if row.get("reuse"):
        from ga3ce_prep.testing import reuse_sequence as rs

        for name, r in row["reuse"].items():
            rs.print_row(f"   {name}", r)
            print(f"   against the official generator's {row['official_s']:.2f} s on frame (a): exact "
                  f"{row['official_s'] / r['exact_s']:.1f}x, reuse {row['official_s'] / r['reuse_s']:.1f}x")


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


def same_masks(fast, ref) -> dict:
    """Whether the backend's Segmentation and the reference's result keep the same masks in the same
    order: same count, predicted IoUs within 1e-4, boxes within 1 px, at most 0.1% of a mask's pixels
    differing (logits within float noise of 0), with the figures."""
    n = len(ref.masks)
    if len(fast.masks) != n:
        return {"same_masks": False, "masks_compared": f"{len(fast.masks)} vs {n} masks"}
    if n == 0:
        return {"same_masks": True, "masks_compared": "0 masks"}
    score = float(np.abs(fast.scores - ref.scores).max())
    box = int(np.abs(fast.boxes - ref.boxes).max())
    pixels = float(((fast.masks != ref.masks).reshape(n, -1).mean(axis=1)).max())
    return {"same_masks": bool(score <= 1e-4 and box <= 1 and pixels <= 1e-3),
            "masks_compared": f"{n} masks, scores within {score:.1e}, boxes within {box} px, "
                              f"at most {pixels:.3%} of a mask's pixels differ"}


def gpu_rows(args) -> dict | None:
    """Frame (a) at 30% on the GPU provider: the I/O binding batch path (all prompts in one batch)
    against plain batches of FastDecoder.GPU_BATCH_SIZE, masks compared; None without the provider."""
    import onnxruntime as ort

    from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
    from ga3ce_prep.estimators.segment.mobilesam_runners import SegmenterOptions
    from ga3ce_prep.testing.scripted import drawn_frame

    provider = args.gpu_provider
    wanted = {"cuda": "CUDAExecutionProvider", "cpu": "CPUExecutionProvider"}.get(provider, provider)
    if wanted not in ort.get_available_providers():
        print(f"GPU batch path: no {'CUDA' if wanted == 'CUDAExecutionProvider' else wanted} provider: skipped")
        return None
    d = model_dir()
    enc, dec = d / "mobile_sam_encoder.onnx", d / "mobile_sam_decoder.onnx"
    rgb = drawn_frame()
    base = SegmenterOptions(points_per_side=args.points_per_side, threads=args.threads, providers=provider)
    thr = iou_thresholds(enc, dec, rgb, base, [0.3])[0]
    runs, segs = {}, {}
    for io in ("on", "off"):
        seg = MobileSamSegmenter(enc, dec, dataclasses.replace(base, pred_iou_thresh=thr, io_binding=io))
        segs[io] = seg
        r, t = timed_segment(seg, rgb, args.repeat)
        runs[io] = float(np.median(t))
        print(f"GPU rows ({provider}, 30% pass): io_binding {io}: {runs[io]:.2f} s (median of {len(t)}; "
              f"batch {seg.decoder.batch_size or 'all prompts'}), shares {shares(r.timings)}", flush=True)
    for seg in segs.values():   # random weights keep no mask at 30%: compare with many kept
        seg.options = many_kept(seg.options)
    agree = same_masks(*(seg.segment(rgb) for seg in segs.values()))
    print(f"   same masks, many kept (16x16 grid, no IoU filter, stability 0.3 at offset 0.05, no NMS): "
          f"{'yes' if agree['same_masks'] else 'NO'} ({agree['masks_compared']})")
    return {"provider": provider, "io_binding_s": round(runs["on"], 3), "plain_s": round(runs["off"], 3), **agree}


def iou_thresholds(enc: Path, dec: Path, rgb: np.ndarray, base, fractions: list[float]) -> list[float]:
    """The IoU thresholds that let each fraction of the frame's candidates (tokens 1..3 of every
    grid point) pass the IoU filter."""
    from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter

    probe = MobileSamSegmenter(enc, dec, dataclasses.replace(base, pred_iou_thresh=1e9), verify=False)
    return probe_thresholds(probe, rgb, base, fractions)


def probe_thresholds(probe, rgb: np.ndarray, base, fractions: list[float]) -> list[float]:
    """iou_thresholds with the segmenter `probe`'s encoder and decoder (either runtime)."""
    from ga3ce_prep.estimators.segment.amg import build_point_grid, transform_coords
    from ga3ce_prep.estimators.segment.mobilesam_runners import single_point_prompts

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


def torch_rows(args) -> dict:
    """(c) The torch runtime on args.device against the official generator, same checkpoint and
    device: frame (a) at 30%, the masks with many kept, exact vs reuse over the sequence."""
    import torch

    from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
    from ga3ce_prep.estimators.segment.mobilesam_runners import SegmenterOptions
    from ga3ce_prep.estimators.segment.mobilesam_torch import load_sam
    from ga3ce_prep.estimators.segment.reuse import ReuseParams
    from ga3ce_prep.frames import load_rgb
    from ga3ce_prep.testing import reuse_sequence as rs
    from ga3ce_prep.testing.official_amg import official_generate, official_generator
    from ga3ce_prep.testing.scripted import drawn_frame

    ckpt = mobilesam_random.checkpoint()
    rgb = drawn_frame()
    base = SegmenterOptions(points_per_side=args.points_per_side, threads=args.threads, runtime="torch",
                            device=args.device)
    seg = MobileSamSegmenter.from_checkpoint(ckpt, base)
    sam = load_sam(ckpt, args.device)
    name = torch.cuda.get_device_name() if args.device == "cuda" else "CPU"
    thr = probe_thresholds(seg, rgb, base, [0.3])[0]
    seg.options = dataclasses.replace(base, pred_iou_thresh=thr)
    r, runs = timed_segment(seg, rgb, args.repeat)
    official = official_generator(sam, seg.options)
    ref, ref_runs = None, []
    for i in range(args.repeat + 1):   # a warm-up run first
        t = time.perf_counter()
        ref = official_generate(official, rgb)
        ref_runs += [time.perf_counter() - t] if i else []
    row = {"device": args.device, "device_name": name, "pred_iou_thresh": thr, "candidates_decoded": r.n_candidates,
           "exact_s": round(float(np.median(runs)), 3), "exact_runs_s": [round(x, 3) for x in runs],
           "exact_shares": shares(r.timings), "official_s": round(float(np.median(ref_runs)), 3),
           "official_runs_s": [round(x, 3) for x in ref_runs], "masks": int(len(r.masks)), **same_masks(r, ref)}
    row["ratio"] = round(row["official_s"] / row["exact_s"], 2)
    print(f"torch runtime on {args.device} ({name}), 640x480 at 30% (thr {thr:+.4f}, {r.n_candidates} candidates): "
          f"{row['exact_s']:.2f} s | official SamAutomaticMaskGenerator {row['official_s']:.2f} s | ratio "
          f"{row['ratio']:.1f}x | same masks {'yes' if row['same_masks'] else 'NO'} ({row['masks_compared']})",
          flush=True)
    print("   torch runtime shares:", row["exact_shares"])
    seg.options = many = many_kept(base)
    agree = same_masks(seg.segment(rgb), official_generate(official_generator(sam, many), rgb))
    row["many_kept"] = {"setting": "16x16 grid, no IoU filter, stability 0.3 at offset 0.05, no NMS", **agree}
    print(f"   same masks, many kept: {'yes' if agree['same_masks'] else 'NO'} ({agree['masks_compared']})", flush=True)
    if args.sequence_frames:
        frames = rs.sequence(Path(args.out).parent, args.sequence_frames, args.sequence_seed)
        seg.options = dataclasses.replace(base, pred_iou_thresh=probe_thresholds(
            seg, load_rgb(frames[0].image_path), base, [0.3])[0])
        row["reuse"] = {f"torch runtime on {args.device}, 30% pass, reuse {k}": v for k, v in
                        rs.compare(seg, frames, {"defaults": ReuseParams(reuse="sequence")}).items()}
        for key, v in row["reuse"].items():
            rs.print_row(key, v)
    return row


def random_weight_rows(args) -> list[dict]:
    """The official MobileSAM files with random weights on the drawn 640x480 frame, IoU thresholds at
    the quantiles that let the given fractions of candidates pass."""
    from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
    from ga3ce_prep.estimators.segment.mobilesam_runners import SegmenterOptions
    from ga3ce_prep.testing.amg_reference import reference_generate
    from ga3ce_prep.testing.scripted import drawn_frame

    d = model_dir()
    enc, dec = d / "mobile_sam_encoder.onnx", d / "mobile_sam_decoder.onnx"
    rgb = drawn_frame()
    base = SegmenterOptions(points_per_side=args.points_per_side, threads=args.threads)
    seg = MobileSamSegmenter(enc, dec, dataclasses.replace(base, pred_iou_thresh=0.0))
    results = []
    print(f"MobileSAM segment-everything, 640x480, {args.points_per_side}x{args.points_per_side} grid, "
          f"{args.threads} threads")
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
                       reference_shares=shares(ref.timings), ratio=round(ref_s / fast_s, 2), **same_masks(r, ref))
        results.append(row)
        line = (f"{frac:>5.0%} pass (thr {thr:+.4f}, {r.n_candidates} candidates of {r.n_mask_prompts} prompts): "
                f"backend {fast_s:6.2f} s (median of {len(runs)}: {min(runs):.2f}-{max(runs):.2f})")
        if "reference_s" in row:
            line += (f" | reference-order port {row['reference_s']:6.2f} s | ratio {row['ratio']:5.1f}x | same masks "
                     f"{'yes' if row['same_masks'] else 'NO'} ({row['masks_compared']})")
        print(line)
        print("   backend shares:  ", row["fast_shares"])
        if "reference_shares" in row:
            print("   reference shares:", row["reference_shares"])
    if not args.no_reference:
        results.append(agreement_row(seg, rgb, base))
    return results


def many_kept(base):
    """Options under which random weights keep many masks: every candidate of a 16x16 grid, the
    stability score at offset 0.05 and threshold 0.3, no NMS."""
    return dataclasses.replace(base, points_per_side=16, pred_iou_thresh=0.0, stability_score_thresh=0.3,
                               stability_score_offset=0.05, box_nms_thresh=1.0)


def agreement_row(seg, rgb: np.ndarray, base) -> dict:
    """Random weights keep no mask at the default stability filter (their masks are noise), so the
    timed rows compare 0 masks with 0. Here both keep many: every candidate of a 16x16 grid, the
    stability score at offset 0.05 and threshold 0.3, no NMS (as tests/test_mobilesam_models.py)."""
    from ga3ce_prep.testing.amg_reference import reference_generate

    seg.options = opt = many_kept(base)
    r = seg.segment(rgb)
    ref = reference_generate(seg.encoder, seg.official, rgb, opt)
    row = {"fraction": None, "setting": "16x16 grid, no IoU filter, stability 0.3 at offset 0.05, no NMS",
           "candidates_decoded": r.n_candidates, "reference_candidates": int(len(ref.candidates)), **same_masks(r, ref)}
    print(f"same masks with many kept ({row['setting']}): {'yes' if row['same_masks'] else 'NO'} "
          f"({row['masks_compared']}; {r.n_candidates} and {len(ref.candidates)} candidates decoded)", flush=True)
    return row


if __name__ == "__main__":
    main()
