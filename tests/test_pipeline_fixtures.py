"""A tiny analytic RGB-D world in GFIE's on-disk layout, for the pipeline tests (no tests here).

Rooms of planes (floor, walls, ceiling), a table (box), small objects (boxes and spheres) and a
person (head sphere on a body box), ray-cast exactly per pixel with numpy. Written as GFIE:
rgb/<split>/scene<N>/<frame>.jpg, depth/.../<frame>.npy (float metres, NaN holes),
CameraKinect.npy, <split>_annotation.txt; plus precomputed pose.h5 / view.h5 (the layout of
docs/pipeline.md) and a fixture-only truth.npz (exact depth, instance ids, kinds, head centre).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np

from ga3ce_prep.geometry import normalize
from ga3ce_prep.skeleton import N_JOINTS

W, H = 160, 120
FX = FY = 140.0
CX, CY = 80.0, 60.0
K = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1]], np.float64)
KINDS = ("structure", "furniture", "object", "person")
COLUMNS = ("scene_id", "frame_id", "h_x_min", "h_y_min", "h_x_max", "h_y_max", "eye_u", "eye_v",
           "eye_X", "eye_Y", "eye_Z", "gaze_u", "gaze_v", "gaze_X", "gaze_Y", "gaze_Z")


@dataclass
class Prim:
    kind: str        # plane | sphere | box
    a: np.ndarray    # plane normal / sphere centre / box min
    b: object        # plane offset / sphere radius / box max
    inst: int
    label: str       # structure | furniture | object | person


def _rays() -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.stack([(u - CX) / FX, (v - CY) / FY, np.ones_like(u)], -1)


def _hit(p: Prim, r: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        if p.kind == "plane":
            t = -p.b / (r @ p.a)
        elif p.kind == "sphere":
            a = np.sum(r * r, -1)
            b = -2 * (r @ p.a)
            c = p.a @ p.a - p.b ** 2
            disc = b * b - 4 * a * c
            t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        else:
            t1, t2 = p.a / r, np.asarray(p.b) / r
            tmin = np.max(np.minimum(t1, t2), -1)
            tmax = np.min(np.maximum(t1, t2), -1)
            t = np.where((tmax >= tmin) & (tmin > 0), tmin, np.inf)
    return np.where(np.isfinite(t) & (t > 0.05), t, np.inf)


def render(prims: list[Prim]) -> tuple[np.ndarray, np.ndarray]:
    """Exact depth (H, W) float32 metres (ray z = 1, so t is depth) and instance ids (H, W) int16."""
    r = _rays()
    best = np.full((H, W), np.inf)
    inst = np.full((H, W), -1, np.int16)
    for p in prims:
        t = _hit(p, r)
        closer = t < best
        best[closer] = t[closer]
        inst[closer] = p.inst
    depth = np.where(np.isfinite(best), best, 0).astype(np.float32)
    return depth, inst


def make_scene(rng: np.random.Generator, n_objects: int = 8) -> tuple[list[Prim], dict]:
    prims = [
        Prim("plane", np.array([0, 1.0, 0]), -1.3, 0, "structure"),    # floor y = 1.3
        Prim("plane", np.array([0, 0, 1.0]), -5.0, 1, "structure"),    # back wall z = 5
        Prim("plane", np.array([1.0, 0, 0]), 2.6, 2, "structure"),     # left wall x = -2.6
        Prim("plane", np.array([1.0, 0, 0]), -2.6, 3, "structure"),    # right wall x = 2.6
        Prim("plane", np.array([0, 1.0, 0]), 1.6, 4, "structure"),     # ceiling y = -1.6
    ]
    tx = rng.uniform(-0.8, 0.2)
    table_lo, table_hi = np.array([tx, 0.55, 3.0]), np.array([tx + 1.4, 1.3, 3.9])
    prims.append(Prim("box", table_lo, table_hi, 5, "furniture"))
    inst = 6
    for k in range(n_objects):
        on_table = k % 2 == 0
        if on_table:
            cx, cz = rng.uniform(tx + 0.15, tx + 1.25), rng.uniform(3.1, 3.8)
            base = 0.55
        else:
            cx, cz = rng.uniform(-2.2, 2.2), rng.uniform(4.0, 4.8)
            base = 1.3
        s = rng.uniform(0.08, 0.16)
        if k % 3 == 0:
            prims.append(Prim("sphere", np.array([cx, base - s, cz]), s, inst, "object"))
        else:
            prims.append(Prim("box", np.array([cx - s, base - 2 * s, cz - s]), np.array([cx + s, base, cz + s]), inst, "object"))
        inst += 1
    hx = rng.uniform(-1.4, -0.9)
    hz = rng.uniform(2.2, 2.6)
    head_c = np.array([hx, -0.1, hz])
    prims.append(Prim("sphere", head_c, 0.11, inst, "person"))
    prims.append(Prim("box", np.array([hx - 0.2, 0.02, hz - 0.12]), np.array([hx + 0.2, 1.3, hz + 0.12]), inst, "person"))
    return prims, {"head_centre": head_c, "person": inst}


def object_centre(p: Prim) -> np.ndarray:
    return p.a if p.kind == "sphere" else 0.5 * (p.a + np.asarray(p.b))


def head_box(c: np.ndarray, r: float = 0.11) -> np.ndarray:
    pts = c + r * np.array([[sx, sy, 0] for sx in (-1, 1) for sy in (-1, 1)])
    uv = np.stack([FX * pts[:, 0] / pts[:, 2] + CX, FY * pts[:, 1] / pts[:, 2] + CY], 1)
    return np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()], np.float32)


def sensor(depth: np.ndarray, rng: np.random.Generator, hole_frac: float = 0.05) -> np.ndarray:
    """Kinect-like: a little noise, random dropouts, a few blobs, holes at depth edges; NaN holes."""
    d = depth + rng.normal(0, 0.002, depth.shape).astype(np.float32) * depth ** 2
    holes = rng.random(depth.shape) < hole_frac
    for _ in range(4):
        y, x, s = rng.integers(0, H), rng.integers(0, W), rng.integers(2, 6)
        holes[max(0, y - s):y + s, max(0, x - s):x + s] = True
    gy, gx = np.gradient(depth)
    holes |= np.hypot(gx, gy) > 0.3
    d = d.astype(np.float32)
    d[holes | (depth <= 0)] = np.nan
    return d


def synth_pose(head_c: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A crude standing skeleton (30, 3) under the head: enough for shapes and NaN handling."""
    ys = np.linspace(1.25, -0.05, N_JOINTS)
    pose = np.stack([np.full(N_JOINTS, head_c[0]), ys, np.full(N_JOINTS, head_c[2])], 1)
    pose[24:30] = head_c + rng.normal(0, 0.05, (6, 3))
    return pose.astype(np.float32)


def write_gfie(root: Path, seed: int = 0, frames_per_split: dict[str, int] | None = None,
               n_objects: int = 8) -> dict:
    """Write the world at root; returns the fixture truth {frame_id: {...}}."""
    rng = np.random.default_rng(seed)
    frames_per_split = frames_per_split or {"train": 4, "valid": 2, "test": 2}
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "CameraKinect.npy", np.array([FX, FY, CX, CY]))
    truth: dict[str, dict] = {}
    ids, poses, views = [], [], []
    for split, n in frames_per_split.items():
        rows = []
        for k in range(n):
            scene = 1 + k // 2
            prims, info = make_scene(np.random.default_rng(seed * 1000 + scene * 10 + ("train", "valid", "test").index(split)))
            # the person moves a little between frames of a scene
            shift = np.array([0.05 * (k % 2), 0, 0])
            for p in prims:
                if p.label == "person":
                    p.a = p.a + shift
                    if p.kind == "box":
                        p.b = np.asarray(p.b) + shift
            head_c = info["head_centre"] + shift
            depth, inst = render(prims)
            rgb_dir = root / "rgb" / split / f"scene{scene}"
            dep_dir = root / "depth" / split / f"scene{scene}"
            rgb_dir.mkdir(parents=True, exist_ok=True)
            dep_dir.mkdir(parents=True, exist_ok=True)
            colours = np.random.default_rng(7).integers(40, 255, (64, 3))
            img = colours[np.maximum(inst, 0) % 64].astype(np.float32)
            img *= (1.0 - 0.1 * np.clip(depth, 0, 5) / 5)[..., None]
            img += rng.normal(0, 4, img.shape)
            cv2.imwrite(str(rgb_dir / f"{k:04d}.jpg"), np.clip(img, 0, 255).astype(np.uint8)[..., ::-1])
            np.save(dep_dir / f"{k:04d}.npy", sensor(depth, rng))
            objs = [p for p in prims if p.label == "object"]
            target = object_centre(objs[int(rng.integers(len(objs)))])
            eye = head_c + np.array([0, 0.02, -0.09])
            box = head_box(head_c)
            tu, tv = FX * target[0] / target[2] + CX, FY * target[1] / target[2] + CY
            eu, ev = FX * eye[0] / eye[2] + CX, FY * eye[1] / eye[2] + CY
            rows.append([scene, k, *box.tolist(), eu, ev, *eye.tolist(), tu, tv, *target.tolist()])
            fid = f"{split}/scene{scene}/{k:04d}"
            gaze = normalize(target - eye)
            truth[fid] = {"depth": depth, "instance": inst, "head_centre": head_c, "eye": eye, "gaze": gaze,
                          "head_box": box, "prims": prims}
            ids.append(fid)
            poses.append(synth_pose(head_c, rng))
            views.append(normalize(gaze + rng.normal(0, 0.2, 3)))
        with open(root / f"{split}_annotation.txt", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(COLUMNS)
            w.writerows(rows)
    with h5py.File(root / "pose.h5", "w") as f:
        f["frame_id"] = np.array(ids, dtype=h5py.string_dtype())
        f["pose"] = np.stack(poses)
    np.savez(root / "view.npz", frame_id=np.array(ids), view=np.stack(views).astype(np.float32))
    return truth


def pipeline_dict(**stage_params) -> dict:
    """The fixture's pipeline: sensor depth, geometric objects, precomputed pose and view."""
    p = {
        "name": "fixture", "dataset": {"format": "gfie"},
        "stages": {
            "depth": {"backend": "sensor"},
            "objects": {"backend": "geometric", "params": {"stride": 2}},
            "head": {"backend": "depth"},
            "pose": {"backend": "precomputed", "params": {"file": "{data}/pose.h5"}},
            "view": {"backend": "precomputed", "params": {"file": "{data}/view.npz"}},
        },
        "run": {"shard_size": 3},
    }
    for stage, params in stage_params.items():
        p["stages"][stage].setdefault("params", {}).update(params)
    return p


# --- the synthetic world (ga3ce_prep.synthetic), small, shared by the pipeline tests -------------
import pytest  # noqa: E402

SYNTH_W = 160  # small frames keep the tests fast


@pytest.fixture(scope="session")
def synth_world(tmp_path_factory) -> Path:
    """A 160x120 synthetic GFIE-format world (3 scenes x 4 frames) with its truth.h5."""
    from ga3ce_prep.synthetic.generate import generate

    root = tmp_path_factory.mktemp("synth") / "gfie"
    generate("gfie", root, scenes=3, frames_per_scene=4, seed=5, width=SYNTH_W, progress=False)
    return root


@pytest.fixture(scope="session")
def synth_world_640(tmp_path_factory) -> Path:
    """A 640x480 synthetic GFIE-format world (4 scenes x 2 frames), the benchmark's resolution,
    where heads span 15-40 px (at 160x120 a head is 5-8 px and its window 3x3)."""
    from ga3ce_prep.synthetic.generate import generate

    root = tmp_path_factory.mktemp("synth640") / "gfie"
    generate("gfie", root, scenes=4, frames_per_scene=2, seed=6, width=640, progress=False)
    return root


# the bundled pipelines, with the geometric segmenter's grid scaled to 160x120 frames
SMALL = ["stages.objects.params.stride=1"]
