"""Writers of the three real on-disk formats (docs/datasets.md; sources in docs/paper.md §4).

Ids and split conventions come from the dataset modules (gfie.frame_id, cad120.frame_id,
gafa.SESSION_ORDER, ...) so the adapters' ids and ours agree by construction. Numbers are written
with fixed formats so the same seed gives byte-identical annotation files.

A writer names recordings by their index k = room * sessions_per_room + session (with one session
per room, k is the room): GFIE a `scene<N>` folder per recording, CAD-120 a dataset id per
recording, GAFA a session of the room's environment.
"""
from __future__ import annotations

import csv
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .. import skeleton
from ..datasets import cad120, gafa, gfie
from .config import KeypointConfig, SynthConfig
from .truth import TruthFrame


@dataclass
class FrameContext:
    """What a writer gets for one camera image."""

    scene_index: int             # the recording: room * sessions_per_room + session
    camera_index: int
    t: int                       # time step within the scene
    truth: TruthFrame
    rgb: np.ndarray              # (H, W, 3) uint8
    depth: np.ndarray | None     # (H, W) float32 metres, 0 = hole (sensor-like); None if no depth
    rng: np.random.Generator     # the scene's generator (keypoint noise)


def assign_splits(n: int, seed: int, fractions=(0.70, 0.15, 0.15)) -> list[str]:
    """Deterministic scene -> split ("train", "val", "test") for n scenes, about 70/15/15 with at
    least one of each when n >= 3 (n = 2: train and test; n = 1: train)."""
    if n <= 0:
        return []
    if n == 1:
        return ["train"]
    n_test = max(1, int(round(fractions[2] * n)))
    n_val = max(1, int(round(fractions[1] * n))) if n >= 3 else 0
    perm = np.random.default_rng([int(seed), 0x5911]).permutation(n)
    out = ["train"] * n
    for i in perm[:n_test]:
        out[i] = "test"
    for i in perm[n_test:n_test + n_val]:
        out[i] = "val"
    return out


def assign_session_splits(rooms: int, sessions_per_room: int, seed: int,
                          fractions=(0.70, 0.15, 0.15)) -> list[str]:
    """Deterministic split of each recording (room-major: session j of room i is entry
    i * sessions_per_room + j). One session per room: `assign_splits` by room. Several: session 0
    of every room trains; val and test are about fractions[1] and fractions[2] of all sessions
    (at least one each while there are other sessions to draw), drawn with the seed among the
    rooms' other sessions, so every val and test room has training sessions."""
    R = sessions_per_room
    if R == 1:
        return assign_splits(rooms, seed, fractions)
    n = rooms * R
    candidates = [i * R + j for i in range(rooms) for j in range(1, R)]
    n_test = min(len(candidates), max(1, int(round(fractions[2] * n))))
    n_val = min(len(candidates) - n_test, max(1, int(round(fractions[1] * n))))
    perm = np.random.default_rng([int(seed), 0x5E55]).permutation(len(candidates))
    out = ["train"] * n
    for k in perm[:n_test]:
        out[candidates[k]] = "test"
    for k in perm[n_test:n_test + n_val]:
        out[candidates[k]] = "val"
    return out


# fast lossless PNG: "up" filter + Huffman-only deflate (2-3x faster than zlib level 1 on noisy
# sensor images, files about as small)
PNG_FAST = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP,
            cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]


def _imwrite(path: Path, rgb: np.ndarray, params: list[int]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(path.suffix, np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise OSError(f"cannot encode {path}")
    path.write_bytes(buf.tobytes())


def _save_camera_kinect(out: Path, K: np.ndarray) -> None:
    """GFIE's and CAD-120's intrinsics file: CameraKinect.npy, [fx, fy, cx, cy] float64."""
    np.save(out / "CameraKinect.npy", np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float64))


def _f(x: float, nd: int) -> str:
    return f"{float(x):.{nd}f}"


class FormatWriter:
    """One dataset format: names scenes and frames, writes images, annotations and intrinsics."""

    name = ""
    has_depth = True

    def __init__(self, out: Path, K: np.ndarray, width: int, height: int, cfg: SynthConfig, n_scenes: int, seed: int,
                 sessions_per_room: int = 1):
        self.out, self.K, self.W, self.H, self.cfg = Path(out), K, width, height, cfg
        self.n_scenes, self.seed, self.sessions_per_room = n_scenes, seed, sessions_per_room
        self.n_recordings = n_scenes * sessions_per_room
        self.out.mkdir(parents=True, exist_ok=True)

    def begin(self) -> None:
        """Write the files that no frame changes (the intrinsics); once per dataset, before any frame."""

    def take(self) -> Any:
        """What write() kept for close() since the last take (annotation rows), handed over to
        absorb() of the writer that closes: recordings may be written by writers in other processes."""
        return None

    def absorb(self, kept: Any) -> None:
        """Add what another writer's take() gave, in recording order."""

    def scene_names(self, i: int, n_cameras: int) -> tuple[str, str, list[str]]:
        """(split, scene name, camera names) of recording i."""
        raise NotImplementedError

    def frame_id(self, i: int, c: int, t: int) -> str:
        raise NotImplementedError

    def write(self, ctx: FrameContext) -> None:
        raise NotImplementedError

    def end_scene(self, i: int) -> None:
        """Called after recording i's last frame."""

    def close(self) -> None:
        """Write what is kept until the end (annotation files)."""


class GFIEWriter(FormatWriter):
    """GFIE_dataset/rgb/{train,valid,test}/scene<N>/<frame:04d>.jpg, depth/.../<frame:04d>.npy
    (float32 metres, NaN holes), CameraKinect.npy [fx, fy, cx, cy], {split}_annotation.txt. Each
    recording (a room's session) is a scene<N> folder of its split (`assign_session_splits`)."""

    name = "gfie"
    FOLDER = {v: k for k, v in gfie.SPLIT_FOLDERS.items()}  # split -> folder

    def __init__(self, *a: Any, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.splits = assign_session_splits(self.n_scenes, self.sessions_per_room, self.seed)
        self.number: list[int] = []
        counts: dict[str, int] = {}
        for s in self.splits:  # scenes numbered from 1 within each split folder
            counts[s] = counts.get(s, 0) + 1
            self.number.append(counts[s])
        self.rows: dict[str, list[list[str]]] = {f: [] for f in gfie.SPLIT_FOLDERS}

    def begin(self):
        _save_camera_kinect(self.out, self.K)

    def take(self):
        kept, self.rows = self.rows, {f: [] for f in gfie.SPLIT_FOLDERS}
        return kept

    def absorb(self, kept):
        for folder, rows in kept.items():
            self.rows[folder] += rows

    def scene_names(self, i, n_cameras):
        folder = self.FOLDER[self.splits[i]]
        return self.splits[i], f"{folder}/scene{self.number[i]}", [""] * n_cameras

    def frame_id(self, i, c, t):
        return gfie.frame_id(self.FOLDER[self.splits[i]], self.number[i], t)

    def write(self, ctx):
        i, t, tr = ctx.scene_index, ctx.t, ctx.truth
        folder = self.FOLDER[self.splits[i]]
        rel = Path(folder) / f"scene{self.number[i]}" / f"{t:04d}"
        _imwrite(self.out / "rgb" / rel.with_suffix(".jpg"), ctx.rgb,
                 [cv2.IMWRITE_JPEG_QUALITY, self.cfg.render.jpeg_quality])
        d = np.where(ctx.depth > 0, ctx.depth, np.nan).astype(np.float32)
        p = self.out / "depth" / rel.with_suffix(".npy")
        p.parent.mkdir(parents=True, exist_ok=True)
        np.save(p, d)
        hb = tr.head_box
        self.rows[folder].append(
            [str(self.number[i]), str(t)] + [_f(x, 4) for x in hb] + [_f(x, 4) for x in tr.eye_2d]
            + [_f(x, 6) for x in tr.eye] + [_f(x, 4) for x in tr.gaze_2d] + [_f(x, 6) for x in tr.gaze_target])

    def close(self):
        for folder, rows in self.rows.items():
            with open(self.out / f"{folder}_annotation.txt", "w", newline="") as fh:
                w = csv.writer(fh, lineterminator="\n")
                w.writerow(gfie.COLUMNS)
                w.writerows(rows)


class CAD120Writer(FormatWriter):
    """CAD120_dataset/rgb/<id>/RGB_<n>.png, depth/<id>/Depth_<n>.png (uint16 mm, 0 invalid),
    CameraKinect.npy, annotation.txt (normalised boxes and 2D points). n starts at 1. Every
    recording is test (an evaluation set), one dataset id each."""

    name = "cad120"

    def __init__(self, *a: Any, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.rows: list[list[str]] = []

    def begin(self):
        _save_camera_kinect(self.out, self.K)

    def take(self):
        kept, self.rows = self.rows, []
        return kept

    def absorb(self, kept):
        self.rows += kept

    @staticmethod
    def dataset_id(i: int) -> str:
        """D1S<subject>A<activity>: one id per recording (subjects cycle 1-4)."""
        return f"D1S{i % 4 + 1}A{i + 1:03d}"

    def scene_names(self, i, n_cameras):
        return "test", self.dataset_id(i), [""] * n_cameras

    def frame_id(self, i, c, t):
        return cad120.frame_id(self.dataset_id(i), t + 1)

    def write(self, ctx):
        i, tr = ctx.scene_index, ctx.truth
        did, n = self.dataset_id(i), ctx.t + 1
        _imwrite(self.out / "rgb" / did / f"RGB_{n}.png", ctx.rgb, PNG_FAST)
        mm = np.clip(np.round(ctx.depth * 1000.0), 0, 65535).astype(np.uint16)
        p = self.out / "depth" / did / f"Depth_{n}.png"
        p.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(p), mm, PNG_FAST)
        W, H = self.W, self.H
        x1, y1, x2, y2 = tr.head_box
        self.rows.append(
            [did, str(n), _f(x1 / W, 8), _f(y1 / H, 8), _f((x2 - x1) / W, 8), _f((y2 - y1) / H, 8),
             _f(tr.eye_2d[0] / W, 8), _f(tr.eye_2d[1] / H, 8)] + [_f(x, 6) for x in tr.eye]
            + [_f(tr.gaze_2d[0] / W, 8), _f(tr.gaze_2d[1] / H, 8)] + [_f(x, 6) for x in tr.gaze_target])

    def close(self):
        with open(self.out / "annotation.txt", "w", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(cad120.COLUMNS)
            w.writerows(self.rows)


def body25_keypoints(tr: TruthFrame, cfg: KeypointConfig, rng: np.random.Generator) -> np.ndarray:
    """OpenPose-like BODY_25 keypoints (25, 3) u, v, confidence from the exact pose: pixel noise,
    0 rows for joints out of the image, face points turned away from the camera, or randomly
    missed."""
    W, H = (int(x) for x in tr.image_size)
    pose = tr.pose[list(skeleton.BODY25_FROM_SMPL30)]
    z = pose[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = tr.K[0, 0] * pose[:, 0] / z + tr.K[0, 2]
        v = tr.K[1, 1] * pose[:, 1] / z + tr.K[1, 2]
    noise = rng.normal(0.0, cfg.noise_px * W / 640.0, (25, 2))
    conf = rng.uniform(*cfg.confidence, 25)
    miss = rng.random(25) < cfg.miss_prob
    ok = (z > 0.05) & np.isfinite(u) & np.isfinite(v)
    u, v = u + noise[:, 0], v + noise[:, 1]
    ok &= (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    to_cam = -tr.head_center / np.linalg.norm(tr.head_center)
    facing = tr.head_dir @ to_cam          # > 0: the face is toward the camera
    left = tr.head_R[:, 1] @ to_cam        # > 0: the left side is toward the camera
    face = {0: facing > -0.15, 15: facing > -0.15, 16: facing > -0.15, 17: left < 0.3, 18: left > -0.3}
    for j, seen in face.items():
        ok[j] &= bool(seen)
    # random misses, but a head in view keeps at least one face point (OpenPose finds an ear)
    face_ok = ok[list(face)].copy()
    ok &= ~miss
    if face_ok.any() and not ok[list(face)].any():
        ok[list(face)[int(np.flatnonzero(face_ok)[0])]] = True
    out = np.zeros((25, 3), np.float32)
    out[ok] = np.stack([u[ok], v[ok], conf[ok]], axis=1)
    return out


def environment_sessions(env: str) -> tuple[str, ...]:
    """GAFA's sessions of one environment (gafa.SCENES): a training session, a test one, then the
    rest in gafa.SESSION_ORDER, so two sessions of a room already cover both splits."""
    own = [s for s in gafa.SESSION_ORDER if s.split("/", 1)[0] == env]
    first = [next(s for s in own if gafa.session_split(s) == "train"),
             next(s for s in own if gafa.session_split(s) == "test")]
    return tuple(first + [s for s in own if s not in first])


class GAFAWriter(FormatWriter):
    """raw_data/<scene>/<session>/<camera>/<frame:06d>.jpg, <camera>.pkl (plain dict of arrays),
    intrinsics.npz (cam_mat, dist_coeffs (1, 12) zeros). One session per room: recording i is
    session gafa.SESSION_ORDER[i % 17]. Several: room i is environment gafa.SCENES[i % 5] and its
    session j that environment's `environment_sessions`[j % n]; either way GAFA's split
    (gafa.session_split) applies. Cameras are Camera<c>_<r>, r counting the earlier recordings of
    the same session name."""

    name = "gafa"
    has_depth = False

    def __init__(self, *a: Any, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.acc: dict[int, dict[str, list]] = {}
        R = self.sessions_per_room
        if R == 1:
            names = [gafa.SESSION_ORDER[i % len(gafa.SESSION_ORDER)] for i in range(self.n_recordings)]
        else:
            names = []
            for i in range(self.n_scenes):
                env = environment_sessions(gafa.SCENES[i % len(gafa.SCENES)])
                names += [env[j % len(env)] for j in range(R)]
        self.sessions: list[str] = names
        seen: dict[str, int] = {}
        self.repeats: list[int] = []
        for s in names:
            self.repeats.append(seen.get(s, 0))
            seen[s] = self.repeats[-1] + 1

    def begin(self):
        np.savez(self.out / "intrinsics.npz", cam_mat=np.asarray(self.K, np.float64), dist_coeffs=np.zeros((1, 12)))

    def session(self, i: int) -> str:
        return self.sessions[i]

    def camera(self, i: int, c: int) -> str:
        return f"Camera{c + 1}_{self.repeats[i]}"

    def scene_names(self, i, n_cameras):
        s = self.session(i)
        return gafa.session_split(s), s, [self.camera(i, c) for c in range(n_cameras)]

    def frame_id(self, i, c, t):
        return gafa.frame_id(self.session(i), self.camera(i, c), t)

    def write(self, ctx):
        i, c, t, tr = ctx.scene_index, ctx.camera_index, ctx.t, ctx.truth
        folder = self.out / self.session(i) / self.camera(i, c)
        _imwrite(folder / f"{t:06d}.jpg", ctx.rgb, [cv2.IMWRITE_JPEG_QUALITY, self.cfg.render.jpeg_quality])
        a = self.acc.setdefault(c, {k: [] for k in ("kp", "gaze", "head_d", "head_p", "chest_d", "chest_p")})
        if len(a["kp"]) != t:
            raise RuntimeError(f"GAFA frames of {folder} out of order: got {t} after {len(a['kp'])} frames")
        a["kp"].append(body25_keypoints(tr, self.cfg.keypoints, ctx.rng))
        a["gaze"].append(tr.gaze)
        a["head_d"].append(tr.head_dir)
        a["head_p"].append(tr.head_center)
        a["chest_d"].append(tr.chest_dir)
        a["chest_p"].append(tr.chest_pos)
        a["R"], a["t"] = tr.R_w2c.T.copy(), tr.cam_center.copy()

    def end_scene(self, i):
        for c, a in sorted(self.acc.items()):
            f32 = lambda k, a=a: np.asarray(np.stack(a[k]), np.float32)  # noqa: E731
            d = {"keypoints2d": f32("kp"), "gaze": {"direction": f32("gaze")},
                 "head": {"direction": f32("head_d"), "position": f32("head_p")},
                 "chest": {"direction": f32("chest_d"), "position": f32("chest_p")},
                 "R_cam2w": np.asarray(a["R"], np.float64), "t_cam2w": np.asarray(a["t"], np.float64)}
            p = self.out / self.session(i) / f"{self.camera(i, c)}.pkl"
            with open(p, "wb") as fh:
                pickle.dump(d, fh, protocol=4)
        self.acc = {}


WRITERS: dict[str, type[FormatWriter]] = {"gfie": GFIEWriter, "cad120": CAD120Writer, "gafa": GAFAWriter}
