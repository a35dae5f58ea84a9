"""Evaluate a checkpoint on a store split: the model and three honest baselines on the same frames.

Frames: the dataset's own rows for the split under its protocol (train/frameset.py: every row for
GFIE and CAD-120, GAFA's 7-frame windows for GAFA; `frames` chooses), every one accounted for:
"scored N of M" and, per reason, the ids of the others. Reported per method: 3D MAE, 2D MAE (GAFA
style), front/back (true gaze z <= 0 is front; per window from its first frame under GAFA's
windows), median, and per scene 3D and 2D (GAFA: the paper's Table 3 columns, Office = `lab`,
Courtyard = both courtyard sessions by frames, beside the paper's row). Methods: the checkpoint's
model, named by its config's fixed design ("GA3CE (paper)", "pointer-frozen (ours)"; model/methods.py),
the other trained models it is given (`beside`: an `ablate` folder's other designs and its model
without objects), the view prior v, the head direction from the pose keypoints, and
snap-to-object (v snapped to the nearest object within a cone whose half-angle is chosen on the
validation split). The summary says plainly
whether the model beats each. Python API:
`evaluate(store, checkpoint, split) -> EvalResult` (train/results.py; `.to_json()`: what `eval --json` writes).
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import ConfigError
from ..geometry import angular_error_deg
from ..model import ALIASES, GA3CE, METHODS, ModelConfig, model_label
from ..skeleton import head_direction_from_pose
from ..store import ContextStore, open_store
from .baselines import choose_snap_cone, snap_to_object
from .checkpoint import build_model, check_checkpoint, load_checkpoint, run_design
from .dataset import BucketBatchSampler, ContextDataset, store_fingerprint
from .frameset import PROTOCOLS, scored_frames
from .gfm import evaluate_gfm, format_gfm_table
from .metrics import summarize
from .plots import plot_cdf
from .profiles import DatasetProfile
from .results import EvalResult

log = logging.getLogger("ga3ce_prep.train")

BASELINES = {"view_prior": "v prior (appearance only)", "head_from_pose": "head direction from pose",
             "snap_to_object": "snap v to object"}
BASELINE_NOTES = {"view_prior": "the store's view prior v itself (the appearance-only row)",
                  "head_from_pose": "the head's facing direction from the 3D pose keypoints",
                  "snap_to_object": "v turned to the nearest object within the cone"}
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


def sibling_checkpoints(checkpoint: str | Path) -> dict[str, Path]:
    """The other models trained beside a full model in an `ablate` folder (OUT/full/seed<k>/best.pt
    -> OUT/<row>/seed<k>/best.pt for the design rows, the alias rows and no-objects), by row key
    ("ga3ce", "pointer-joint", "pointer-frozen", "ours", "no_objects"); those that are there."""
    p = Path(checkpoint)
    if p.parent.parent.name != "full":
        return {}
    rows = {**{m: m for m in [*METHODS, *ALIASES]}, "no_objects": "no-objects"}
    found = {key: p.parent.parent.parent / row / p.parent.name / p.name for key, row in rows.items()}
    return {key: path for key, path in found.items() if path.is_file()}


def beside(checkpoint: str | Path) -> dict[str, Any]:
    """The models an `ablate` folder trained beside `checkpoint`, as `evaluate`'s arguments:
    {"no_objects": the no-objects row's best.pt or None, "compare": {row key: best.pt}, each other
    design once (an alias row may hold the same design as a design row)}. Empty outside such a
    folder. The command line's `eval` and `report` use it; evaluate itself searches nothing."""
    siblings = sibling_checkpoints(checkpoint)
    seen = {run_design(checkpoint)}
    compare: dict[str, str | Path] = {}
    for key, sibling in siblings.items():
        design = run_design(sibling)
        if key != "no_objects" and design not in seen:
            seen.add(design)
            compare[key] = sibling
    return {"no_objects": siblings.get("no_objects"), "compare": compare}


AT_OBJECT_M = 0.2   # metres: a gaze target this near a stored object position is "at an object"


def target_at_object(target: np.ndarray, objects: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(n,) bool: whether each frame's gaze target (n, 3) lies within AT_OBJECT_M of one of its
    stored object positions (n, k, 3) where mask (n, k) is set; False for an unknown target."""
    d = np.linalg.norm(objects - target[:, None, :], axis=-1)
    d = np.where(mask.astype(bool), d, np.inf)
    with np.errstate(invalid="ignore"):
        return (d.min(axis=1, initial=np.inf) < AT_OBJECT_M) & np.all(np.isfinite(target), axis=1)


@torch.no_grad()
def object_attention(model: GA3CE, ds: ContextDataset, target: np.ndarray, batch_size: int = 256,
                     device: str | torch.device = "cpu", n_max: int | None = None) -> dict[str, float] | None:
    """Where the model's weight goes (GA3CE.object_weights: the regress model's last decoder layer's
    cross-attention over [null token, objects], mean over heads; the pointer's p over [g0,
    objects]), over ds's frames; target (len(ds), 3) their gaze targets, metres.

    Returns None for a model without objects, else: `frames`; `null`, `objects`: the mean weight of
    the null token (g0's) and of all objects together; over the `at_object_frames` whose target is
    within AT_OBJECT_M of a stored object, the one nearest it being the gazed object: `on_target`
    (mean weight on it), `per_other` (mean weight per other object), `target_top` (share of frames
    where it outweighs every other object) and `chance_top` (that share for uniform weights, the
    mean of 1 / objects)."""
    if not (model.config.use_context and model.config.use_objects):
        return None
    was_training = model.training
    model.eval()
    null, objects, on_target, per_other, top, chance = [], [], [], [], [], []
    for idx in BucketBatchSampler(ds.obj_count, batch_size, shuffle=False).batches():
        b = ds.batch(idx, n_max)
        _, weights = model.object_weights(*(t.to(device) for t in (b.view, b.pose, b.head_pos, b.objects, b.mask)))
        w = weights.cpu().numpy().astype(np.float64)                    # (B, 1 + S)
        mask = b.mask.numpy().astype(bool)[:, : w.shape[1] - 1]
        obj = np.where(mask, w[:, 1:], 0.0)
        null.append(w[:, 0])
        objects.append(obj.sum(1))
        d = np.linalg.norm(b.objects.numpy()[:, : w.shape[1] - 1] - target[idx, None, :], axis=-1)
        d = np.where(mask, d, np.inf)
        at = target_at_object(target[idx], b.objects.numpy(), b.mask.numpy())
        if not at.any() or not obj.shape[1]:
            continue
        j = d.argmin(1)[at]
        o, n = obj[at], mask[at].sum(1)
        gazed = o[np.arange(len(o)), j]
        on_target.append(gazed)
        per_other.append(np.where(n > 1, (o.sum(1) - gazed) / np.maximum(n - 1, 1), np.nan))
        top.append(gazed >= np.where(mask[at], o, -np.inf).max(1))
        chance.append(1.0 / n)
    model.train(was_training)
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)  # noqa: E731
    k = len(cat(on_target))
    mean = lambda xs: float(np.nanmean(cat(xs))) if k else float("nan")  # noqa: E731
    return {"frames": len(ds), "null": float(cat(null).mean()), "objects": float(cat(objects).mean()),
            "at_object_frames": k, "on_target": mean(on_target), "per_other": mean(per_other),
            "target_top": mean(top), "chance_top": mean(chance)}


def _padded_objects(ds: ContextDataset) -> tuple[np.ndarray, np.ndarray]:
    b = ds.batch(np.arange(len(ds)))
    return b.objects.numpy(), b.mask.numpy()


def _scene_columns(st: ContextStore, profile: DatasetProfile, scene: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Per frame (n,) the code of its per-scene column, and the columns: the profile's (in the
    paper's order: GAFA's scenes, sessions merged) that have frames, else the store's scenes."""
    of_scene = [profile.scene_column(name) for name in st.scene_names]
    order = [c for c, _ in profile.scene_columns] + [c for c in dict.fromkeys(of_scene) if c not in
                                                      {c for c, _ in profile.scene_columns}]
    code = np.array([order.index(c) for c in of_scene], np.int64)
    return code[scene] if len(code) else scene.astype(np.int64), order


def evaluate(store: ContextStore | str | Path, checkpoint: str | Path, split: str = "test",
             force: bool = False, device: str = "cpu", batch_size: int = 256,
             snap_cone_deg: float | None = None, cdf_path: str | Path | None = "auto",
             json_path: str | Path | None = None, threads: int = 2, frames: str = "auto",
             data: str | Path | None = None, gfm: str | Path | None = None, gfm_batch_size: int = 16,
             no_objects: str | Path | None = None, compare: dict[str, str | Path] | None = None) -> EvalResult:
    """Metrics of a checkpoint and the baselines on `split` of `store`.

    force: evaluate even if the checkpoint was trained on another store; implied when the store has
    no train split (an evaluation-only set such as CAD-120: the paper's Table 2 transfer).
    snap_cone_deg: the snap baseline's cone; None chooses it on the validation split (else 15).
    cdf_path: PNG of the angular-error CDFs ("auto": eval_<split>_cdf.png beside the checkpoint;
    None: no plot). json_path: also write the result as JSON. frames: "auto" (the dataset's
    protocol, DatasetProfile.eval_frames), "windows" (GAFA's) or "all" (every frame). data: the
    dataset's root when it is not where the store's provenance says. gfm: GFIE's checkpoint, to add
    GFIE's Table 1 columns (train/gfm.py: GFIE's network on the frames' images and depth,
    gfm_batch_size frames per pass). no_objects: a checkpoint of the model without objects to score
    beside this one (method "no_objects"), None = none. compare: other checkpoints to score beside
    it, {key: path} ("ours": its label names the design). `beside(checkpoint)` gives both for an
    ablate folder's full row. Returns an EvalResult
    (train/results.py): store, split, checkpoint, epoch, labels {method: its name in tables},
    n_frames (scored), frames (frameset.ScoredFrames: protocol, expected, scored, unscored {reason:
    [ids]}), head_sources, head_fallback_frames, snap_cone_deg, methods {name: MethodMetrics},
    scene_columns, paper_rows, beats {baseline: bool}, ratio_to_prior, attention
    (`object_attention`), cdf_png, and gfm (`evaluate_gfm`) when asked; json_path gets its `to_json()`.
    """
    torch.set_num_threads(threads)
    st = store if isinstance(store, ContextStore) else open_store(store, verify=True)
    ckpt = load_checkpoint(checkpoint)
    if not force and ("train" not in st.split_names or not len(st.indices("train"))):
        # an evaluation-only store (CAD-120, the transfer world): the checkpoint comes from another
        # dataset by design (the paper's Table 2), so its fingerprint is not checked
        log.info("%s has no training frames: evaluating %s across datasets", st.path, checkpoint)
        force = True
    else:
        for p in check_checkpoint(ckpt, checkpoint, store_fingerprint(st), None, force=force):
            log.warning("evaluating despite a mismatch (--force): %s", p)
    profile = DatasetProfile.for_store(st)
    fs = scored_frames(st, split, profile.eval_frames if frames == "auto" else frames, data, ContextDataset(st, split))
    ds = ContextDataset(st, split, only=fs.rows)
    if len(ds) == 0:
        raise ConfigError(f"{st.path}: split {split!r} has no frames to score ({fs.expected} expected under "
                          f"{PROTOCOLS[fs.protocol]}; {sum(map(len, fs.unscored.values()))} left out); "
                          "choose another --split or --frames all")
    model = build_model(ckpt).to(device)
    preds = {"model": predict(model, ds, batch_size, device, ckpt["config"].get("n_max"))}
    config = ModelConfig.from_dict(ckpt["config"]["model"])
    labels = {"model": model_label(config)}
    others: dict[str, str | Path] = dict(compare or {})
    if no_objects is not None:
        others["no_objects"] = no_objects
    for key, path in others.items():
        other = load_checkpoint(path)
        check_checkpoint(other, path, store_fingerprint(st), None, force=force)
        preds[key] = predict(build_model(other).to(device), ds, batch_size, device, other["config"].get("n_max"))
        labels[key] = model_label(ModelConfig.from_dict(other["config"]["model"]))
    labels |= BASELINES
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
    at_object = target_at_object(np.asarray(st.frames["gaze_target"][ds.rows], np.float64), objects, mask)

    attention = object_attention(model, ds, np.asarray(st.frames["gaze_target"][ds.rows], np.float64), batch_size,
                                 device, ckpt["config"].get("n_max"))
    scene, columns = _scene_columns(st, profile, ds.scene)
    methods = {name: summarize(p, ds.gaze, scene, columns, fs.front, at_object) for name, p in preds.items()}
    model_mae = methods["model"].mae3d
    head_sources: dict[str, int] = {}
    head_fallback = 0
    if "head" in st.source_names:  # code 0: the backend's own way (head: depth: measured depth)
        codes = st.frames["head_source"][ds.rows]
        head_sources = {st.source_names["head"][k]: int((codes == k).sum()) for k in np.unique(codes)}
        head_fallback = int((codes != 0).sum())
    result = EvalResult(
        store=str(st.path), split=split, checkpoint=str(checkpoint), epoch=int(ckpt["epoch"]) + 1,
        no_objects_checkpoint=None if no_objects is None else str(no_objects),
        compared_checkpoints={k: str(v) for k, v in others.items()}, labels=labels,
        config={**ckpt["config"], "model": config.to_dict()}, dataset=profile.name, n_frames=len(ds), frames=fs,
        head_sources=head_sources, head_fallback_frames=head_fallback, snap_cone_deg=snap_cone_deg,
        head_from_pose_frames=int(pose_ok.sum()), snapped_frames=int(snapped.sum()),
        methods=methods, scene_columns=[c for c in columns if c in methods["model"].per_scene],
        paper_rows={label: dict(cells) for label, cells in profile.paper_rows} if fs.protocol == "windows" else {},
        beats={k: bool(model_mae < m.mae3d) for k, m in methods.items() if k != "model"},
        ratio_to_prior=model_mae / methods["view_prior"].mae3d, attention=attention,
    )
    if gfm is not None:
        result.gfm = evaluate_gfm(st, ds.rows, preds["model"], gfm, data, device, gfm_batch_size)
    if cdf_path is not None:
        path = Path(checkpoint).with_name(f"eval_{split}_cdf.png") if cdf_path == "auto" else Path(cdf_path)
        errors = {labels[k]: angular_error_deg(p, ds.gaze) for k, p in preds.items()
                  if k not in ("head_from_pose", "snap_to_object")}
        result.cdf_png = str(plot_cdf(errors, path, f"{Path(st.path).name}: {split}, {len(ds)} frames"))
    if json_path is not None:
        Path(json_path).write_text(json.dumps(result.to_json(), indent=2, default=float))
        result.json = str(json_path)
    return result


def _f(x: float | None) -> str:
    return "   n/a" if x is None or not math.isfinite(x) else f"{x:6.2f}"


def _cell(mae3d: float | None, mae2d: float | None) -> str:
    """A per-scene cell "3D / 2D", '-' where a value is unknown."""
    g = lambda x: "  -  " if x is None or not math.isfinite(x) else f"{x:5.1f}"  # noqa: E731
    return f"{g(mae3d)} / {g(mae2d)}"


def format_accounting(result: EvalResult) -> list[str]:
    """"scored N of M" with the protocol, where the rows came from, and a line per reason for the rest."""
    fr = result.frames
    label = PROTOCOLS[fr.protocol]
    if fr.protocol == "all" and result.dataset == "gafa":
        label += ", NOT GAFA's protocol (its 7-frame windows: --frames windows)"
    within = f" ({fr.expected} of the split's {fr.split_rows} frames)" if fr.expected != fr.split_rows else ""
    lines = [f"scored {fr.scored} of {fr.expected} {result.split} frames: {label}{within}; rows from {fr.source}"]
    for reason, ids in fr.unscored.items():
        lines.append(f"  {len(ids):6d} not scored: {reason} (e.g. {ids[0]})")
    hs = result.head_sources
    if result.head_fallback_frames:
        lines.append("head position of the scored frames: " + ", ".join(f"{k} {v}" for k, v in hs.items())
                     + " (docs/pipeline.md, \"Head position\")")
    return lines


def format_scene_table(result: EvalResult) -> list[str]:
    """The per-scene table: 3D / 2D MAE per column and over all frames, for every method, and the
    paper's rows beside them (unknown cells '-')."""
    m, cols = result.methods, result.scene_columns
    w = 13
    lines = ["per scene: 3D / 2D MAE (deg); All over frames",
             f"{'':34s} " + " ".join(f"{c[:w]:>{w}s}" for c in [*cols, "All"])]
    for key, label in result.labels.items():
        if key not in m:
            continue
        ps = m[key].per_scene
        cells = [_cell(ps[c].mae3d, ps[c].mae2d) for c in cols] + [_cell(m[key].mae3d, m[key].mae2d)]
        lines.append(f"{label[:34]:34s} " + " ".join(f"{c:>{w}s}" for c in cells))
    for label, paper in result.paper_rows.items():
        row = [_cell(*paper[c]) if c in paper else _cell(None, None) for c in [*cols, "All"]]
        lines.append(f"{label[:34]:34s} " + " ".join(f"{c:>{w}s}" for c in row))
    model = result.model
    lines.append(f"{'frames':34s} " + " ".join(f"{n:>{w}d}" for n in [*(model.per_scene[c].n for c in cols), model.n]))
    if result.paper_rows:
        lines.append("(GA3CE, the paper's figure: Table 3's per-scene cells are not in our sources, '-'; its "
                     "All 3D is the full model of Tables 4/5. GAFA's README: its released GazeNet, averaged per "
                     "batch of 32 windows; ours are per frame)")
    return lines


def format_attention(a: dict[str, float]) -> str:
    """One line of `object_attention`'s figures."""
    return (f"weight: null token (g0) {a['null']:.2f}, objects {a['objects']:.2f}; where the target is at an "
            f"object ({a['at_object_frames']} frames): the gazed object {a['on_target']:.3f}, each other "
            f"{a['per_other']:.3f}, "
            f"the most of any object {a['target_top']:.0%} (uniform weights: {a['chance_top']:.0%})")


def format_eval_table(result: EvalResult, per_scene: bool = True) -> str:
    """The evaluation as plain-text tables: which frames, methods, per scene, and the verdict on each baseline."""
    m, model = result.methods, result.model
    lines = [f"{result.store} | split {result.split} | {result.n_frames} frames | "
             f"{result.checkpoint} (epoch {result.epoch})", *format_accounting(result), ""]
    per_window = " (front/back per window)" if result.frames.protocol == "windows" else ""
    lines.append(f"{'method':34s} {'3D MAE':>7s} {'2D MAE':>7s} {'median':>7s} "
                 f"{'front3D':>7s} {'back3D':>7s}{per_window}")
    for key, label in result.labels.items():
        if key not in m:
            continue
        if key == "snap_to_object":
            label = f"{label} (cone {result.snap_cone_deg:g} deg)"
        r = m[key]
        lines.append(f"{label:34s} {_f(r.mae3d):>7s} {_f(r.mae2d):>7s} {_f(r.median3d):>7s} "
                     f"{_f(r.front.mae3d):>7s} {_f(r.back.mae3d):>7s}")
    lines.append(f"{'frames':34s} {'':>7s} {'':>7s} {'':>7s} {model.front.n:>7d} {model.back.n:>7d}")
    lines.append("")
    name = result.labels["model"]
    lines.append(f"{name} / v prior = {result.ratio_to_prior:.3f} (3D MAE); the paper on GFIE: 11.1 / 19.4 = 0.572")
    lines.append(f"{name}:")
    for key, beats in result.beats.items():
        d = m[key].mae3d - model.mae3d
        lines.append(f"  {'beats' if beats else 'does NOT beat'} {result.labels[key]}: "
                     f"{model.mae3d:.2f} vs {m[key].mae3d:.2f} deg ({d:+.2f}"
                     + (f", objects {'add' if d > 0 else 'cost'} {abs(d) / m[key].mae3d:.0%})"
                        if key == "no_objects" else ")"))
    if a := result.attention:
        lines.append(format_attention(a))
    if per_scene and (len(result.scene_columns) > 1 or result.paper_rows):
        lines += ["", *format_scene_table(result)]
    if result.gfm is not None:
        lines += ["", format_gfm_table(result.gfm)]
    return "\n".join(lines)
