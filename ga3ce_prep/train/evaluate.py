"""Evaluate a checkpoint on a store split: the model and three honest baselines on the same frames.

Reported per method: 3D MAE, 2D MAE (GAFA style), front/back (true gaze z <= 0 is front), median,
and a per-scene table. Methods: GA3CE (the checkpoint), the view prior v, the head direction from
the pose keypoints, and snap-to-object (v snapped to the nearest object within a cone whose
half-angle is chosen on the validation split). The summary says plainly whether the model beats
each baseline. Python API: `evaluate(store, checkpoint, split) -> metrics dict`.
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..geometry import angular_error_deg
from ..model import GA3CE
from ..skeleton import head_direction_from_pose
from ..store import ContextStore, open_store
from .baselines import choose_snap_cone, snap_to_object
from .checkpoint import build_model, check_checkpoint, load_checkpoint
from .dataset import BucketBatchSampler, ContextDataset, store_fingerprint
from .gfm import evaluate_gfm, format_gfm_table
from .metrics import summarize
from .plots import plot_cdf

log = logging.getLogger("ga3ce_prep.train")

METHODS = {"model": "GA3CE (model)", "view_prior": "v prior (appearance only)",
           "head_from_pose": "head direction from pose", "snap_to_object": "snap v to object"}
DEFAULT_SNAP_CONE_DEG = 15.0


@torch.no_grad()
def predict(model: GA3CE, ds: ContextDataset, batch_size: int = 256, device: str | torch.device = "cpu",
            n_max: int | None = None) -> np.ndarray:
    """g (len(ds), 3) for every frame of `ds` in dataset order (eval mode, batches by object count)."""
    was_training = model.training
    model.eval()
    out = np.zeros((len(ds), 3), np.float32)
    for idx in BucketBatchSampler(ds.obj_count, batch_size, shuffle=False).batches():
        b = ds.batch(idx, n_max).to(device)
        out[idx] = model(b.view, b.pose, b.head_pos, b.objects, b.mask).cpu().numpy()
    model.train(was_training)
    return out


def _padded_objects(ds: ContextDataset) -> tuple[np.ndarray, np.ndarray]:
    b = ds.batch(np.arange(len(ds)))
    return b.objects.numpy(), b.mask.numpy()


def evaluate(store: ContextStore | str | Path, checkpoint: str | Path, split: str = "test",
             force: bool = False, device: str = "cpu", batch_size: int = 256,
             snap_cone_deg: float | None = None, cdf_path: str | Path | None = "auto",
             json_path: str | Path | None = None, threads: int = 2, gfm: str | Path | None = None,
             data: str | Path | None = None, gfm_batch_size: int = 16) -> dict[str, Any]:
    """Metrics of a checkpoint and the baselines on `split` of `store`.

    force: evaluate even if the checkpoint was trained on another store (e.g. cross-dataset).
    snap_cone_deg: the snap baseline's cone; None chooses it on the validation split (else 15).
    cdf_path: PNG of the angular-error CDFs ("auto": eval_<split>_cdf.png beside the checkpoint;
    None: no plot). json_path: also write the result as JSON. gfm: GFIE's checkpoint, to add GFIE's
    Table 1 columns (train/gfm.py: GFIE's network on the frames' images and depth, from the dataset
    the store was made from or the one at `data`, gfm_batch_size frames per pass). Returns a dict:
    store, split, checkpoint, epoch, n_frames, snap_cone_deg, methods {name: summarize(...)}, beats
    {baseline: bool}, ratio_to_prior, cdf_png, and gfm (`evaluate_gfm`) when asked.
    """
    torch.set_num_threads(threads)
    st = store if isinstance(store, ContextStore) else open_store(store, verify=True)
    ckpt = load_checkpoint(checkpoint)
    problems = check_checkpoint(ckpt, checkpoint, store_fingerprint(st), None, force=force)
    for p in problems:
        log.warning("evaluating despite a mismatch (--force): %s", p)
    ds = ContextDataset(st, split)
    if len(ds) == 0:
        raise ValueError(f"{st.path}: split {split!r} has no frames with a view prior and ground-truth gaze")
    model = build_model(ckpt).to(device)
    preds = {"model": predict(model, ds, batch_size, device, ckpt["config"].get("n_max"))}
    preds["view_prior"] = ds.view
    preds["head_from_pose"], pose_ok = head_direction_from_pose(ds.pose, ds.view)
    if snap_cone_deg is None:
        val = ContextDataset(st, "val") if "val" in st.split_names else None
        if val is not None and len(val):
            vo, vm = _padded_objects(val)
            snap_cone_deg = choose_snap_cone(val.view, val.head_pos, vo, vm, val.gaze)
        else:
            snap_cone_deg = DEFAULT_SNAP_CONE_DEG
    objects, mask = _padded_objects(ds)
    preds["snap_to_object"], snapped = snap_to_object(ds.view, ds.head_pos, objects, mask, snap_cone_deg)

    methods = {name: summarize(p, ds.gaze, ds.scene, st.scene_names) for name, p in preds.items()}
    model_mae = methods["model"]["mae3d"]
    result: dict[str, Any] = {
        "store": str(st.path), "split": split, "checkpoint": str(checkpoint), "epoch": int(ckpt["epoch"]) + 1,
        "config": ckpt["config"], "n_frames": len(ds), "snap_cone_deg": snap_cone_deg,
        "head_from_pose_frames": int(pose_ok.sum()), "snapped_frames": int(snapped.sum()),
        "methods": methods,
        "beats": {k: bool(model_mae < m["mae3d"]) for k, m in methods.items() if k != "model"},
        "ratio_to_prior": model_mae / methods["view_prior"]["mae3d"],
    }
    if gfm is not None:
        result["gfm"] = evaluate_gfm(st, ds.rows, preds["model"], gfm, data, device, gfm_batch_size)
    if cdf_path is not None:
        path = Path(checkpoint).with_name(f"eval_{split}_cdf.png") if cdf_path == "auto" else Path(cdf_path)
        errors = {METHODS["model"]: angular_error_deg(preds["model"], ds.gaze),
                  METHODS["view_prior"]: angular_error_deg(ds.view, ds.gaze)}
        result["cdf_png"] = str(plot_cdf(errors, path, f"{Path(st.path).name}: {split}, {len(ds)} frames"))
    if json_path is not None:
        Path(json_path).write_text(json.dumps(result, indent=2, default=float))
        result["json"] = str(json_path)
    return result


def _f(x: float) -> str:
    return "   n/a" if x is None or not math.isfinite(x) else f"{x:6.2f}"


def format_eval_table(result: dict[str, Any], per_scene: bool = True) -> str:
    """The evaluation as plain-text tables: methods, per scene, and the verdict on each baseline."""
    m = result["methods"]
    lines = [f"{result['store']} | split {result['split']} | {result['n_frames']} frames | "
             f"{result['checkpoint']} (epoch {result['epoch']})", ""]
    lines.append(f"{'method':34s} {'3D MAE':>7s} {'2D MAE':>7s} {'median':>7s} {'front3D':>7s} {'back3D':>7s}")
    for key, label in METHODS.items():
        if key == "snap_to_object":
            label = f"{label} (cone {result['snap_cone_deg']:g} deg)"
        r = m[key]
        lines.append(f"{label:34s} {_f(r['mae3d']):>7s} {_f(r['mae2d']):>7s} {_f(r['median3d']):>7s} "
                     f"{_f(r['front']['mae3d']):>7s} {_f(r['back']['mae3d']):>7s}")
    lines.append(f"{'frames':34s} {'':>7s} {'':>7s} {'':>7s} {m['model']['front']['n']:>7d} {m['model']['back']['n']:>7d}")
    lines.append("")
    lines.append(f"model / v prior = {result['ratio_to_prior']:.3f} (3D MAE); the paper on GFIE: 11.1 / 19.4 = 0.572")
    for key, beats in result["beats"].items():
        d = m[key]["mae3d"] - m["model"]["mae3d"]
        lines.append(f"  {'beats' if beats else 'does NOT beat'} {METHODS[key]}: "
                     f"{m['model']['mae3d']:.2f} vs {m[key]['mae3d']:.2f} deg ({d:+.2f})")
    if per_scene and len(m["model"]["per_scene"]) > 1:
        lines += ["", f"{'scene':24s} {'frames':>7s} {'model':>7s} {'v prior':>7s} {'pose':>7s} {'snap':>7s}"]
        for name, r in m["model"]["per_scene"].items():
            row = [m[k]["per_scene"][name]["mae3d"] for k in ("view_prior", "head_from_pose", "snap_to_object")]
            lines.append(f"{name[:24]:24s} {r['n']:>7d} {_f(r['mae3d']):>7s} " + " ".join(f"{_f(x):>7s}" for x in row))
    if "gfm" in result:
        lines += ["", format_gfm_table(result["gfm"])]
    return "\n".join(lines)
