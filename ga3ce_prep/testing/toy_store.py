"""A toy 3D-context world written straight into the store format (StoreWriter), for the trainer's
tests and for iterating on the model before the rendered synthetic world and the pipeline exist:
`python -c "from ga3ce_prep.testing.toy_store import write_toy_store; write_toy_store('out/toy.zarr', 20000)"`.

Each frame: a person (smpl+head_30 joints, huge8 order) standing or sitting 2-5 m from the camera,
10-60 objects within 0.5-4 m of the head (half of them clustered on "tables"), a gaze target that
is one of the objects in most frames, a head that turns only part of the way from the body's rest
direction toward the target, an arm that sometimes reaches toward it, and a view prior
v = truth + calibrated noise (mean angular error `view_noise_deg`) partly pulled toward the head
direction. Camera frame (x right, y down, z forward), metres; a random camera pitch per frame.
Scenes are groups of consecutive frames; splits are made by scene. Vectorised numpy throughout.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ga3ce_prep.geometry import angular_error_deg, normalize
from ga3ce_prep.skeleton import N_JOINTS
from ga3ce_prep.store import StoreWriter

ATTRS = {"package_version": "0.1.0", "dataset": {"name": "toy", "root": "(generated)"},
         "pipeline": {"file": "ga3ce_prep/testing/toy_store.py", "sha256": "0" * 64},
         "stages": {"objects": {"backend": "toy"}, "pose": {"backend": "toy"}, "view": {"backend": "toy"}}}

# Body joints 0..23 relative to the pelvis, person frame (x = person's right, y down, z = facing),
# metres for a 1.75 m person. Head joints 15, 24..29 are placed from the head frame below.
_STAND = np.array([
    [0, 0, 0], [-.09, .07, 0], [.09, .07, 0], [0, -.11, .01], [-.10, .47, .02], [.10, .47, .02],
    [0, -.24, .01], [-.10, .87, -.02], [.10, .87, -.02], [0, -.30, 0], [-.11, .93, .12], [.11, .93, .12],
    [0, -.52, -.01], [-.08, -.46, 0], [.08, -.46, 0], [0, 0, 0], [-.18, -.45, -.01], [.18, -.45, -.01],
    [-.24, -.20, -.02], [.24, -.20, -.02], [-.26, .04, .03], [.26, .04, .03], [-.27, .12, .04], [.27, .12, .04],
])
_SIT = _STAND.copy()
_SIT[[4, 5]] = [[-.10, .05, .45], [.10, .05, .45]]
_SIT[[7, 8]] = [[-.10, .50, .45], [.10, .50, .45]]
_SIT[[10, 11]] = [[-.11, .55, .58], [.11, .55, .58]]
_NECK_TO_HEAD = np.array([0, -.12, .03])
# head joints in the head frame (forward, right, down) offsets from the head centre, metres
_HEAD = {15: (0, 0, .03), 24: (.10, 0, .02), 25: (.075, -.03, -.02), 26: (0, -.075, 0),
         27: (.075, .03, -.02), 28: (0, .075, 0), 29: (0, 0, -.11)}


@dataclass
class ToyKnobs:
    """The toy world's knobs (the signal each input carries)."""

    view_noise_deg: float = 20.0   # mean angular error of v
    view_head_pull: float = 0.4    # v's mean lies this far from the gaze toward the head direction
    head_fraction: tuple[float, float] = (0.4, 0.85)  # how far the head turns from rest toward the target
    body_yaw_deg: float = 50.0     # body rest direction: the gaze's yaw +- this
    p_object: float = 0.8          # gaze at an object (else at a random point)
    n_objects: tuple[int, int] = (10, 60)
    face_noise: float = 0.03       # keypoint noise on the face joints, metres (per axis)
    body_noise: float = 0.015      # keypoint noise on the other joints, metres
    reach_prob: float = 0.25       # the right arm reaches toward the target
    p_missing_pose: float = 0.0    # frames whose pose is entirely NaN
    p_no_objects: float = 0.0      # frames with zero objects


def _rotate_toward(a: np.ndarray, b: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """Slerp from unit a toward unit b by frac (..., ) of the angle."""
    cos = np.clip(np.sum(a * b, -1), -1, 1)
    ang = np.arccos(cos)
    perp = normalize(b - cos[..., None] * a)
    t = (frac * ang)[..., None]
    return np.cos(t) * a + np.sin(t) * perp


def _random_tangent_rotation(d: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Rotate unit d by a 2D Gaussian step (std sigma radians per axis) in its tangent plane."""
    a = normalize(np.cross(d, rng.normal(size=d.shape)))
    b = np.cross(d, a)
    step = rng.normal(size=(len(d), 2)) * sigma
    ang = np.linalg.norm(step, axis=1, keepdims=True)
    t = normalize(step[:, :1] * a + step[:, 1:] * b)
    return np.cos(ang) * d + np.sin(ang) * t


def toy_world(n_frames: int, seed: int = 0, frames_per_scene: int = 40, knobs: ToyKnobs | None = None):
    """Generate n_frames frames. Returns (frames, objects, scene_names) in StoreWriter's layout."""
    k = knobs or ToyKnobs()
    rng = np.random.default_rng(seed)
    n = n_frames
    cam_h = rng.uniform(1.4, 2.4, n)
    sitting = rng.random(n) < 0.3
    height = rng.uniform(1.5, 1.9, n)
    scale = height / 1.75
    head_y = cam_h - np.where(sitting, 1.25, 1.62) * scale  # y down: floor at y = cam_h
    H = np.stack([rng.uniform(-1.6, 1.6, n), head_y, rng.uniform(2.0, 5.0, n)], -1)

    # objects: candidates in the room (half clustered on tables), keep those 0.5-4 m from the head
    C = 240
    n_tab = 3
    tables = np.stack([rng.uniform(-3, 3, (n, n_tab)), cam_h[:, None] - rng.uniform(0.4, 1.1, (n, n_tab)),
                       rng.uniform(1.0, 6.5, (n, n_tab))], -1)
    pick = rng.integers(0, n_tab, (n, C // 2))
    clustered = np.take_along_axis(tables, pick[..., None], 1) + rng.normal(0, [0.35, 0.06, 0.3], (n, C // 2, 3))
    uniform = np.stack([rng.uniform(-3.5, 3.5, (n, C // 2)), cam_h[:, None] - rng.uniform(0, 2.6, (n, C // 2)),
                        rng.uniform(0.5, 7.0, (n, C // 2))], -1)
    cand = np.concatenate([clustered, uniform], 1)
    cand = cand[:, rng.permutation(C)]
    dist = np.linalg.norm(cand - H[:, None], axis=-1)
    ok = (dist > 0.5) & (dist < 4.0) & (cand[..., 2] > 0.4)
    ok &= (np.abs(cand[..., 0] / cand[..., 2]) < 0.6) & (np.abs((cand[..., 1] - 0.0) / cand[..., 2]) < 0.45)
    want = rng.integers(k.n_objects[0], k.n_objects[1] + 1, n)
    want[rng.random(n) < k.p_no_objects] = 0
    order = np.argsort(~ok, axis=1, kind="stable")
    count = np.minimum(want, ok.sum(1))
    obj = np.take_along_axis(cand, order[..., None], 1)  # valid first

    # gaze target: an object, or a random point 1-4 m away
    has_obj = (rng.random(n) < k.p_object) & (count > 0)
    which = (rng.random(n) * np.maximum(count, 1)).astype(int)
    free = H + normalize(rng.normal(size=(n, 3)) * [1, 0.5, 1]) * rng.uniform(1, 4, (n, 1))
    target = np.where(has_obj[:, None], obj[np.arange(n), which], free)

    g0 = normalize(target - H)
    yaw = np.arctan2(g0[:, 0], g0[:, 2]) + np.radians(rng.uniform(-k.body_yaw_deg, k.body_yaw_deg, n))
    rest = np.stack([np.sin(yaw), np.zeros(n), np.cos(yaw)], -1)
    head_dir = _rotate_toward(rest, g0, rng.uniform(*k.head_fraction, n))
    eye = H + 0.08 * head_dir
    gaze = normalize(target - eye)

    # pose: body by yaw, head joints in the head frame
    cy, sy = np.cos(yaw), np.sin(yaw)
    Rb = np.zeros((n, 3, 3))
    Rb[:, 0, 0], Rb[:, 0, 2], Rb[:, 1, 1], Rb[:, 2, 0], Rb[:, 2, 2] = cy, sy, 1, -sy, cy
    local = np.where(sitting[:, None, None], _SIT, _STAND) * scale[:, None, None]
    neck_to_head = np.einsum("nij,j->ni", Rb, _NECK_TO_HEAD) * scale[:, None]
    pelvis = H - neck_to_head - np.einsum("nij,nj->ni", Rb, local[:, 12])
    pose = pelvis[:, None] + np.einsum("nij,nkj->nki", Rb, local)
    fwd = head_dir
    right = normalize(np.cross([0, 1, 0], fwd))
    down = np.cross(fwd, right)
    head_joints = {j: H + o[0] * fwd + o[1] * right + o[2] * down for j, o in _HEAD.items()}
    pose = np.concatenate([pose, np.zeros((n, N_JOINTS - 24, 3))], 1)
    for j, p in head_joints.items():
        pose[:, j] = p
    reach = rng.random(n) < k.reach_prob
    sho = pose[:, 17]
    to_t = normalize(target - sho)
    pose[reach, 19] = (sho + 0.27 * scale[:, None] * to_t)[reach]
    pose[reach, 21] = (sho + 0.52 * scale[:, None] * to_t)[reach]
    pose[reach, 23] = (sho + 0.60 * scale[:, None] * to_t)[reach]
    face = np.zeros(N_JOINTS, bool)
    face[24:30] = True
    pose += rng.normal(size=pose.shape) * np.where(face, k.face_noise, k.body_noise)[None, :, None]

    # view prior: pulled toward the head direction, then tangent noise calibrated to the mean error
    v_mean = _rotate_toward(gaze, head_dir, np.full(n, k.view_head_pull))
    sigma = np.radians(k.view_noise_deg) / np.sqrt(np.pi / 2)
    state = rng.bit_generator.state
    for _ in range(4):  # fixed-point calibration of sigma so the mean error hits view_noise_deg
        rng.bit_generator.state = state
        view = _random_tangent_rotation(v_mean, sigma, rng)
        sigma *= k.view_noise_deg / max(float(angular_error_deg(view, gaze).mean()), 1e-6)

    # camera pitch: world (gravity-aligned) -> camera
    pitch = np.radians(rng.uniform(-15, 15, n))
    Rx = np.zeros((n, 3, 3))
    Rx[:, 0, 0] = 1
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = np.cos(pitch), -np.sin(pitch), np.sin(pitch), np.cos(pitch)
    rot = lambda p: np.einsum("nij,n...j->n...i", Rx, p)  # noqa: E731
    pose, obj, H, eye, target, gaze, view = (rot(a) for a in (pose, obj, H, eye, target, gaze, view))
    missing = rng.random(n) < k.p_missing_pose
    pose[missing] = np.nan

    head_pos = H - 0.08 * normalize(H) + rng.normal(0, 0.02, (n, 3))
    Kmat = np.array([[530.0, 0, 320], [0, 530.0, 240], [0, 0, 1]])
    uv = H[:, :2] / H[:, 2:] * 530 + [320, 240]
    r = 0.12 * 530 / H[:, 2]
    head_box = np.stack([uv[:, 0] - r, uv[:, 1] - r, uv[:, 0] + r, uv[:, 1] + r], -1)
    body_box = np.stack([uv[:, 0] - 3 * r, uv[:, 1] - r, uv[:, 0] + 3 * r, uv[:, 1] + 14 * r], -1)

    scene = np.arange(n) // frames_per_scene
    n_scenes = int(scene.max()) + 1
    split_of_scene = np.zeros(n_scenes, np.int8)  # 70/15/15 by scene, each split non-empty
    perm = np.random.default_rng(seed + 1).permutation(n_scenes)
    n_val = max(1, round(0.15 * n_scenes))
    n_test = max(1, round(0.15 * n_scenes))
    split_of_scene[perm[:n_val]] = 1
    split_of_scene[perm[n_val:n_val + n_test]] = 2
    sel = np.arange(C)[None, :] < count[:, None]
    frames = {
        "id": [f"toy/{seed}/{i:06d}" for i in range(n)], "split": split_of_scene[scene], "scene": scene,
        "K": np.broadcast_to(Kmat, (n, 3, 3)), "image_size": np.tile([640, 480], (n, 1)),
        "head_box": head_box, "body_box": body_box, "head_pos": head_pos, "pose": pose,
        "view": view, "view_source": np.zeros(n, np.int8), "head_source": np.zeros(n, np.int8),
        "gaze": gaze, "eye": eye, "gaze_target": target,
        "obj_count": count,
    }
    m = int(count.sum())
    objects = {"xyz": obj[sel], "area": rng.integers(200, 20000, m), "score": rng.uniform(0.5, 1, m)}
    return frames, objects, [f"scene{s:03d}" for s in range(n_scenes)]


def write_toy_store(path: str | Path, n_frames: int = 400, seed: int = 0, frames_per_scene: int = 40,
                    knobs: ToyKnobs | None = None, dataset: str = "toy") -> Path:
    """Write a toy store at `path` (overwritten) and return the path."""
    frames, objects, scenes = toy_world(n_frames, seed, frames_per_scene, knobs)
    w = StoreWriter(path, scene_names=scenes, overwrite=True)
    w.append_frames(frames, objects)
    w.close({**ATTRS, "dataset": {"name": dataset, "root": "(generated)"}})
    return Path(path)
