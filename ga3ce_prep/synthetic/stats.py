"""Summary statistics of a generated world, from its truth side-car (printed by `synth`)."""
from __future__ import annotations

import numpy as np

from ..geometry import angular_error_deg
from .truth import TruthReader


def world_statistics(truth: TruthReader) -> dict[str, float]:
    """Objects per frame (instances of kind object in the room, and those with visible pixels),
    target mix, eye-in-head offset (= angle between gaze and head direction), head turn (head vs
    chest direction), gaze vs chest angle, share of frames whose eye offset exceeds the head turn,
    reaching share, target visibility; angles in degrees."""
    kinds = truth.object_kinds
    obj = kinds.index("object")
    counts = truth.obj_count
    okind, opix = truth._objects["kind"], truth._objects["pixels"]
    is_obj = okind == obj
    frame_of = np.repeat(np.arange(len(truth)), counts)
    n_obj = np.bincount(frame_of[is_obj], minlength=len(truth))
    n_vis = np.bincount(frame_of[is_obj & (opix > 0)], minlength=len(truth))
    offset = angular_error_deg(truth.gaze, truth.head_dir)
    turn = angular_error_deg(truth.head_dir, truth.chest_dir)
    tk = truth.target_kind
    out = {"frames": float(len(truth)), "objects_per_frame": float(n_obj.mean()),
           "visible_objects_per_frame": float(n_vis.mean())}
    for i, name in enumerate(truth.target_kinds):
        out[f"target_{name}"] = float(np.mean(tk == i))
    out.update({
        "eye_in_head_offset_mean_deg": float(offset.mean()),
        "eye_in_head_offset_max_deg": float(offset.max()),
        "head_turn_mean_deg": float(turn.mean()),
        "gaze_chest_mean_deg": float(angular_error_deg(truth.gaze, truth.chest_dir).mean()),
        "offset_exceeds_head_turn": float(np.mean(offset > turn)),
        "reaching": float(np.mean(truth.reaching)),
        "object_target_visible": float(np.mean(truth.target_visible[tk == 0])) if np.any(tk == 0) else float("nan"),
        "eye_distance_mean_m": float(np.linalg.norm(truth.eye, axis=1).mean()),
        "head_box_height_mean_px": float(np.mean(truth.head_box[:, 3] - truth.head_box[:, 1])),
    })
    return out


def format_statistics(s: dict[str, float]) -> str:
    """One line per statistic."""
    return "\n".join(f"  {k:30s} {v:8.3f}" for k, v in s.items())


def object_snap(truth: TruthReader, view_error_deg: float = 20.0, max_snap_deg: float = 30.0,
                seed: int = 0) -> dict[str, float]:
    """How much the objects can tell about the gaze, without any learning: v = the truth gaze
    plus isotropic noise of mean angle `view_error_deg`; "snap" replaces v by the direction from
    the eye to the visible object centroid nearest to v (within max_snap_deg). Returns the mean
    angular errors (deg) of v and of the snap against the truth, over all frames and over frames
    with object targets. A snap error below v's means the objects carry gaze signal."""
    rng = np.random.default_rng(seed)
    n = len(truth)
    g = truth.gaze
    # per-axis Gaussian noise: the angle is ~ Rayleigh, mean sigma * sqrt(pi / 2)
    sigma = np.radians(view_error_deg) / np.sqrt(np.pi / 2)
    v = g + rng.normal(0.0, sigma, (n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    kinds = truth.object_kinds
    obj = kinds.index("object")
    ok, pix, cen = truth._objects["kind"] == obj, truth._objects["pixels"] > 0, truth._objects["centroid"]
    snap = v.copy()
    cos_max = np.cos(np.radians(max_snap_deg))
    for i in range(n):
        s, c = int(truth.obj_start[i]), int(truth.obj_count[i])
        sel = ok[s:s + c] & pix[s:s + c]
        if not sel.any():
            continue
        d = cen[s:s + c][sel] - truth.eye[i]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        cs = d @ v[i]
        k = int(np.argmax(cs))
        if cs[k] >= cos_max:
            snap[i] = d[k]
    ev, es = angular_error_deg(v, g), angular_error_deg(snap, g)
    is_obj = truth.target_kind == 0
    return {"v_error_deg": float(ev.mean()), "snap_error_deg": float(es.mean()),
            "v_error_object_targets_deg": float(ev[is_obj].mean()) if is_obj.any() else float("nan"),
            "snap_error_object_targets_deg": float(es[is_obj].mean()) if is_obj.any() else float("nan")}


def split_recordings(truth: TruthReader) -> dict[str, dict[str, int]]:
    """Per split ("train", "val", "test", those present): sessions (distinct room, session pairs),
    rooms, and rooms that also have a training session (all of them under the seen-rooms
    protocol, none under unseen-rooms)."""
    room, session, split = truth.room.astype(np.int64), truth.session.astype(np.int64), truth.split
    train_rooms = set(room[split == "train"].tolist())
    out = {}
    for name in ("train", "val", "test"):
        m = split == name
        if m.any():
            rooms = set(room[m].tolist())
            out[name] = {"sessions": len(set(zip(room[m].tolist(), session[m].tolist()))), "rooms": len(rooms),
                         "rooms_seen_in_training": len(rooms & train_rooms)}
    return out
