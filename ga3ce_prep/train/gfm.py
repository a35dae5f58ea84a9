"""GFIE's gaze-following evaluation: the columns of GFIE's Table 1 (AUC, L2 distance, 3D distance,
3D angle) for "GFIE", "Ours" and "Ours + GFM" (`ga3ce-prep eval --gfm CHECKPOINT`).

- GFIE: GFIE's whole network (estimators/view/gfie_net.py) as GFIE's `inference.py` runs it: its head
  branch's g feeds the stereo-FoV maps, the heatmap and the 3D step.
- Ours: GA3CE's g; only the 3D angle (the angle between g and the ground truth).
- Ours + GFM: GA3CE's g replaces the head branch's g in the stereo-FoV maps and in the 3D step
  (the paper's "Ours + GFM"), everything else as GFIE.

Metrics per frame, exactly as GFIE's `inference.py` and `utils/utils.py` compute them, then the
plain mean over frames (GFIE's batch-size-weighted means of batch means are the same thing):
- AUC (`heatmap_auc`): the raw 64 x 64 heatmap resized to the full (W, H) depth resolution with
  Pillow's nearest filter, scored against a map with one positive pixel (int(x W), int(y H)),
  clipped to (W - 1, H - 1): sklearn's ROC AUC, which with one positive is the fraction of the other
  pixels scored below it, ties counting half.
- L2: || heatmap argmax (column / 64, row / 64) - (gaze_u / W, gaze_v / H) ||, normalised image
  coordinates, no cell-centre offset.
- 3D distance: || the 3D step's point - gaze_XYZ ||, metres.
- 3D angle: arccos(direction . normalise(gaze_XYZ - eye_XYZ)) in degrees, with the 3D step's
  refined direction (a zero vector when the chosen pixel has no depth: 90 degrees).

Where GFIE's code has no answer we say so: a 2D target left of or above the image (x < 0 or y < 0)
gets no AUC (GFIE's `roc_auc_score` raises with no positive pixel for x < 0, and a y < 0 gives row
int(y H), which numpy counts from the bottom when negative); the cosine is clipped to [-1, 1]
before arccos (GFIE's unclipped arccos gives NaN when rounding takes it past 1).
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from ..errors import ConfigError, FrameError, Ga3ceError
from ..frames import FrameRef, load_depth, load_rgb
from ..geometry import angular_error_deg, normalize
from ..store import ContextStore

log = logging.getLogger("ga3ce_prep.train")

# name -> label, in GFIE's Table 1 order
GFM_METHODS = {"gfie": "GFIE", "ours": "Ours", "ours_gfm": "Ours + GFM"}   # "Ours": the evaluated model
METRICS = ("auc", "l2", "dist3d", "angle3d")


def heatmap_auc(heatmap: np.ndarray, target_2d: np.ndarray, size: tuple[int, int]) -> float:
    """GFIE's AUC of one (h, w) raw heatmap against the 2D target (2,) in normalised image
    coordinates, at the full (W, H) resolution (see the module docstring); NaN for a non-finite
    target or one with x < 0 or y < 0."""
    W, H = size
    gx, gy = (float(c) for c in target_2d)
    if not (math.isfinite(gx) and math.isfinite(gy)) or gx < 0 or gy < 0:
        return float("nan")
    score = np.asarray(Image.fromarray(np.asarray(heatmap, np.float32)).resize((W, H), Image.Resampling.NEAREST))
    pos = score[min(int(gy * H), H - 1), min(int(gx * W), W - 1)]
    below, ties = int(np.count_nonzero(score < pos)), int(np.count_nonzero(score == pos)) - 1
    return (below + 0.5 * ties) / (W * H - 1)


def _mean(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else float("nan")


def _gfm_frame(ref: FrameRef, recipe, g: np.ndarray) -> dict[str, Any]:
    """One frame's network inputs and what its scoring needs; FrameError when it cannot be read."""
    from ..estimators.view.gfie_net import head_location, matrix_t, scene_input
    from ..estimators.view.head_crop import head_input

    if not (np.all(np.isfinite(ref.eye)) and np.all(np.isfinite(ref.gaze_target))):
        raise FrameError("no annotated 3D eye and target")
    if ref.depth_path is None:
        raise FrameError("no depth map")
    rgb = load_rgb(ref.image_path)
    depth = load_depth(ref.depth_path, ref.depth_scale)
    H, W = rgb.shape[:2]
    eye = np.asarray(ref.eye, np.float64)
    return {"scene": scene_input(rgb), "head": head_input(rgb, ref.head_box),
            "head_loc": head_location(ref.head_box, (W, H)), "matrix_t": matrix_t(depth, (W, H), ref.K, eye, recipe),
            "depth": depth, "K": ref.K, "eye": eye, "g": g, "target_3d": np.asarray(ref.gaze_target, np.float64),
            "target_2d": np.asarray(ref.gaze_2d, np.float64) / [W, H]}


def _score(net, chunk: list[dict[str, Any]], device: str, per: dict[str, dict[str, list[float]]]) -> None:
    """Run GFIE's network on a batch of frames (`_gfm_frame`) with GFIE's g and with ours, and
    append each method's per-frame metrics to `per`."""
    from ..estimators.view.gfie_net import gaze_point_3d

    x = {key: torch.from_numpy(np.concatenate([f[key] for f in chunk])).to(device)
         for key in ("scene", "head", "head_loc", "matrix_t")}
    g_ours = torch.from_numpy(np.stack([f["g"] for f in chunk]).astype(np.float32)).to(device)
    with torch.inference_mode():  # GFIE's g, then ours, through one GFM pass of 2 x len(chunk)
        gs = torch.cat([net.egd_module(x["head"]), g_ours])
        heat = net.heatmap(*(torch.cat([x[k], x[k]]) for k in ("scene", "head_loc", "matrix_t")), gs).cpu().numpy()
    g_np = gs.cpu().numpy()
    for i, f in enumerate(chunk):
        gt_dir = normalize(f["target_3d"] - f["eye"])
        H, W = f["depth"].shape
        for m, j in (("gfie", i), ("ours_gfm", len(chunk) + i)):
            p = gaze_point_3d(f["depth"], heat[j], g_np[j], f["eye"], f["K"])
            per[m]["auc"].append(heatmap_auc(heat[j], f["target_2d"], (W, H)))
            per[m]["l2"].append(float(np.linalg.norm(p.target_2d - f["target_2d"])))
            per[m]["dist3d"].append(float(np.linalg.norm(p.point - f["target_3d"])))
            per[m]["angle3d"].append(float(angular_error_deg(p.direction, gt_dir)))
        per["ours"]["angle3d"].append(float(angular_error_deg(f["g"], gt_dir)))
        for k in ("auc", "l2", "dist3d"):
            per["ours"][k].append(float("nan"))


def evaluate_gfm(store: ContextStore, rows: np.ndarray, g: np.ndarray, checkpoint: str | Path,
                 data: str | Path | None = None, device: str = "cpu", batch_size: int = 16) -> dict[str, Any]:
    """GFIE's Table 1 columns on the store rows `rows` (n,), with GA3CE's g (n, 3) for them.

    The frames' images and depth come from the dataset the store was made from (its provenance),
    or the one at `data`. A frame that cannot be scored (not in the dataset, unreadable, no 3D
    annotation) is left out of every column and listed. Returns {checkpoint, n_frames, n_scored,
    skipped {frame id: reason}, methods {gfie, ours, ours_gfm: {n, auc, n_auc, l2, dist3d,
    angle3d}} (NaN where a method has no such column)}.
    """
    from ..estimators.view.gfie_net import RECIPES, load_gfie_net
    from ..viz import find_frame_refs

    name = str(store.attrs.get("dataset", {}).get("name", ""))
    if name not in RECIPES:
        raise ConfigError(f"--gfm runs GFIE's network on GFIE or CAD-120 frames (depth and 3D annotations); "
                          f"{store.path} was made from {name or 'an unknown dataset'!r}")
    ids = [str(i) for i in np.asarray(store.frames["id"])[rows]]
    root = data or store.attrs.get("dataset", {}).get("root")
    try:
        refs = find_frame_refs(store, ids, data)
    except (Ga3ceError, KeyError, OSError, TypeError) as e:
        raise ConfigError(f"--gfm needs the frames' images and depth, but the dataset at {root} (the store's "
                          f"provenance, or --data) cannot be opened: {e}") from None
    net = load_gfie_net(checkpoint).to(device)
    skipped: dict[str, str] = {}
    per: dict[str, dict[str, list[float]]] = {m: {k: [] for k in METRICS} for m in GFM_METHODS}
    for start in range(0, len(ids), batch_size):  # frames are read a batch at a time: full-size depth is large
        chunk = []
        for k in range(start, min(start + batch_size, len(ids))):
            try:
                if ids[k] not in refs:
                    raise FrameError(f"not in the dataset at {root}")
                chunk.append(_gfm_frame(refs[ids[k]], RECIPES[name], g[k]))
            except FrameError as e:
                skipped[ids[k]] = str(e)
        if chunk:
            _score(net, chunk, device, per)
    if skipped:
        log.warning("--gfm: %d of %d frames cannot be scored (listed in the JSON's gfm.skipped), e.g. %s: %s",
                    len(skipped), len(ids), *next(iter(skipped.items())))
    methods = {}
    for m, vals in per.items():
        a = {k: np.asarray(x, np.float64) for k, x in vals.items()}
        methods[m] = {"n": len(a["angle3d"]), **{k: _mean(a[k]) for k in METRICS},
                      "n_auc": int(np.isfinite(a["auc"]).sum())}
    return {"checkpoint": str(checkpoint), "n_frames": len(ids), "n_scored": len(ids) - len(skipped),
            "skipped": skipped, "methods": methods}


def format_gfm_table(r: dict[str, Any]) -> str:
    """GFIE's Table 1 columns as plain text ("-": no such column for the method)."""
    f = lambda x, spec: "      -" if not math.isfinite(x) else format(x, spec)  # noqa: E731
    lines = [f"GFIE's Table 1 columns (GFIE's metrics; {r['checkpoint']}): {r['n_scored']} of {r['n_frames']} frames",
             f"{'method':12s} {'AUC':>7s} {'L2 dist':>7s} {'3D dist':>7s} {'3D angle':>8s}"]
    for key, label in GFM_METHODS.items():
        m = r["methods"][key]
        lines.append(f"{label:12s} {f(m['auc'], '7.3f')} {f(m['l2'], '7.3f')} {f(m['dist3d'], '7.3f')} "
                     f"{f(m['angle3d'], '8.2f')}")
    lines.append("L2: normalised image coordinates; 3D dist: metres; 3D angle: degrees, the depth-refined "
                 "direction for GFIE and Ours + GFM")
    n_auc = r["methods"]["gfie"]["n_auc"]
    if n_auc < r["n_scored"]:
        lines.append(f"AUC over {n_auc} frames: {r['n_scored'] - n_auc} have their 2D target left of or above "
                     "the image (GFIE's AUC is undefined there)")
    if r["skipped"]:
        lines.append(f"not scored: {len(r['skipped'])} frames (reasons in the JSON)")
    return "\n".join(lines)


__all__ = ["GFM_METHODS", "METRICS", "evaluate_gfm", "format_gfm_table", "heatmap_auc"]
