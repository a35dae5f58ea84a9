"""Exact vs reuse (`reuse: sequence`) segment-everything over one synthetic camera sequence, for
the torch runtime's rows of `make bench-objects DEVICE=...` (benchmarks/bench_objects.py): seconds
per frame of each (mean over the sequence, key frame included), the share of prompts decoded per
frame in reuse mode, the key frames, and the agreement of P_object (per-mask median 3D points of
the masks, measured depth): the share of exact objects with a reuse object within 2 cm and the
reverse, pooled over the frames.

What agreement to expect: the exact generator against itself on every `noise_every`-th frame with
fresh sensor noise added (Gaussian, std sqrt(2) x the world's RGB noise: the size of the noise
difference between two frames), on the same depth. Which of a surface's near-tied duplicate prompts
wins NMS moves with such noise (docs/models/segment-everything.md, "Reuse across frames").

The world: GFIE format, one scene of `frames` 640x480 frames (seed 6 or another), generated once
into out/bench_objects_world_<frames>_seed<seed>/. Cues as the pipeline gives them: the measured
depth and the frame's head box (GFIE has no body box).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

AGREE_M = 0.02   # metres: an object agrees when the other run has one this close
NOISE_EVERY = 3  # the exact generator against itself on every third frame, re-noised


def sequence(out_dir: Path, frames: int, seed: int = 6) -> list:
    """The FrameRefs of the world's one camera sequence, in frame order (generated if missing); each
    seed draws another room, objects, person and path."""
    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.synthetic import generate

    root = out_dir / f"bench_objects_world_{frames}_seed{seed}"
    if not (root / "truth.h5").is_file():
        generate("gfie", root, scenes=1, frames_per_scene=frames, seed=seed, width=640, progress=False)
    refs = sorted(open_dataset("gfie", root), key=lambda f: (f.sequence, f.index))
    return [f for f in refs if f.sequence == refs[0].sequence]


def within(a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    """(n,) bool: each point of a (n, 3) has a point of b (m, 3) within r."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(len(a), bool)
    return np.linalg.norm(a[:, None] - b[None], axis=-1).min(axis=1) <= r


def compare(seg, frames: list, settings: dict, noise_every: int = NOISE_EVERY) -> dict:
    """Run the segmenter over the frames exactly, then with reuse once per setting ({name:
    ReuseParams}) -> {name: row}; with objects, also exactly on every `noise_every`-th frame
    re-noised (0: not)."""
    from ga3ce_prep.frames import load_depth, load_rgb
    from ga3ce_prep.geometry import object_positions
    from ga3ce_prep.synthetic.config import RenderConfig

    data = [(f, load_rgb(f.image_path), load_depth(f.depth_path, f.depth_scale)) for f in frames]

    def objects(r, f, depth):
        return object_positions(depth, f.K, r.masks, valid=depth > 0, min_points=10).xyz

    seg.segment(data[0][1])                                                   # warm-up
    exact, exact_s = [], []
    for f, rgb, depth in data:
        t = time.perf_counter()
        r = seg.segment(rgb, out_size=depth.shape)
        exact_s.append(time.perf_counter() - t)
        exact.append(objects(r, f, depth))
    floor = {}
    if noise_every and any(len(e) for e in exact):
        rng, std = np.random.default_rng(0), np.sqrt(2.0) * RenderConfig().rgb_noise
        e_parts, n_parts = [], []
        for i in range(0, len(data), noise_every):
            f, rgb, depth = data[i]
            noisy = np.clip(np.rint(rgb + rng.normal(0.0, std, rgb.shape)), 0, 255).astype(np.uint8)
            x = objects(seg.segment(noisy, out_size=depth.shape), f, depth)
            e_parts.append(within(exact[i], x, AGREE_M))
            n_parts.append(within(x, exact[i], AGREE_M))
        e_in_n, n_in_e = np.concatenate(e_parts), np.concatenate(n_parts)
        floor = {"noise_objects": int(len(e_in_n)), "noisy_objects": int(len(n_in_e)),
                 "exact_with_noisy_within_2cm": round(float(e_in_n.mean()), 4) if len(e_in_n) else None,
                 "noisy_with_exact_within_2cm": round(float(n_in_e.mean()), 4) if len(n_in_e) else None}
    return {name: {**_reuse_row(seg, data, objects, params, exact, exact_s), **floor}
            for name, params in settings.items()}


def _reuse_row(seg, data: list, objects, params, exact: list, exact_s: list) -> dict:
    """The reuse run with `params` over `data` against the exact run's objects and seconds."""
    from ga3ce_prep.estimators.segment.reuse import FrameCues, SequenceReuse

    state = SequenceReuse(params)
    reuse, reuse_s, steps = [], [], []
    for f, rgb, depth in data:
        t = time.perf_counter()
        state.start(FrameCues(f.index, rgb.shape[:2], depth, np.stack([f.head_box, f.body_box])))
        r = seg.segment(rgb, out_size=depth.shape, reuse=state)
        reuse_s.append(time.perf_counter() - t)
        steps.append(r.reuse)
        reuse.append(objects(r, f, depth))
    e_in_r = np.concatenate([within(e, r, AGREE_M) for e, r in zip(exact, reuse)])
    r_in_e = np.concatenate([within(r, e, AGREE_M) for e, r in zip(exact, reuse)])
    share = np.array([s.decoded_share for s in steps])
    return {"frames": len(data), "exact_s": round(float(np.mean(exact_s)), 3),
            "reuse_s": round(float(np.mean(reuse_s)), 3),
            "speedup": round(float(np.sum(exact_s) / np.sum(reuse_s)), 2),
            "key_frames": [i for i, s in enumerate(steps) if s.key], "key_reasons": [s.reason for s in steps if s.key],
            "decoded_share_mean": round(float(share.mean()), 3),
            "decoded_share_reuse_frames": round(float(share[[not s.key for s in steps]].mean()), 3)
            if not all(s.key for s in steps) else None,
            "exact_objects": int(len(e_in_r)), "reuse_objects": int(len(r_in_e)),
            "exact_with_reuse_within_2cm": round(float(e_in_r.mean()), 4) if len(e_in_r) else None,
            "reuse_with_exact_within_2cm": round(float(r_in_e.mean()), 4) if len(r_in_e) else None}


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.1%}"


def print_row(name: str, row: dict) -> None:
    print(f"{name}: {row['frames']} frames | exact {row['exact_s']:.2f} s/frame | reuse {row['reuse_s']:.2f} s/frame "
          f"| {row['speedup']:.1f}x | prompts decoded {_pct(row['decoded_share_mean'])} per frame "
          f"({_pct(row['decoded_share_reuse_frames'])} on reuse frames), key frames {row['key_frames']} "
          f"{row['key_reasons']} | agreement within 2 cm: exact->reuse {_pct(row['exact_with_reuse_within_2cm'])} "
          f"of {row['exact_objects']}, reuse->exact {_pct(row['reuse_with_exact_within_2cm'])} "
          f"of {row['reuse_objects']}"
          + (f" | exact vs exact re-noised (one frame in {NOISE_EVERY}): {_pct(row['exact_with_noisy_within_2cm'])} of "
             f"{row['noise_objects']} / {_pct(row['noisy_with_exact_within_2cm'])} of {row['noisy_objects']}"
             if "noise_objects" in row else ""), flush=True)
