"""GAFA raw data (kyotovision-public/dynamic-3d-gaze-from-afar: `README.md`,
`data/preprocessed/preprocess.py`, `dataloader/gafa.py`).

The split is by session and fixed (eval.py / train.py). Validation, `val`: "gafa" (default) is
GAFA's own rule (train.py), seeded: the training sessions shuffled (`val_seed`), their cameras'
7-frame windows of consecutive raw frames (interval 1, `window_starts`) concatenated, and the last
10% of the windows are val: the frames from the first val window's first frame on (the cut falls
inside one camera sequence; GAFA's own run is unseeded). "sessions": the two whole sessions in
VAL_SESSIONS (our earlier choice). GAFA has no depth: a pipeline over it needs a depth estimator
(or, for the synthetic world, the oracle).

Per frame the adapter gives: the head box and body box computed from the OpenPose keypoints the way
GAFA's preprocessing does (head: joints nose, neck, eyes, ears expanded up by 85% and squared;
body: all joints expanded and cut to 3:4), the gaze direction (`gaze.direction`), and as `eye` the
annotated 3D head position (`head.position`; GAFA has no eye point). Frames whose six head joints
are all undetected are skipped, as GAFA's preprocessing skips them.

Intrinsics: one K for every camera (`intrinsics.npz` cam_mat). For portrait-stored cameras the
repository does not say how K applies; with `k_mode="auto"` the adapter reprojects each camera's
head positions with K and with K transposed (fx<->fy, cx<->cy) and keeps the one that lands on
the head keypoints. Distortion coefficients are not applied (GAFA's own code never applies them).
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import DatasetFormatError
from ..frames import FrameRef
from ..geometry import normalize, project
from ..skeleton import BODY25_HEAD
from .base import (
    BOXES_XYXY,
    DatasetAdapter,
    check_distances,
    check_intrinsics,
    check_option,
    first_image_size,
    log,
    one_of,
)
from .safe_pickle import load_pickle

SCENES: tuple[str, ...] = ("library", "lab", "kitchen", "living_room", "courtyard")
TEST_SESSIONS: tuple[str, ...] = (
    "library/1029_2", "lab/1013_2", "kitchen/1022_2", "living_room/006", "courtyard/002", "courtyard/003",
)
TRAIN_SESSIONS: tuple[str, ...] = (
    "library/1026_3", "library/1028_2", "library/1028_5", "lab/1013_1", "lab/1014_1", "kitchen/1022_4",
    "kitchen/1015_4", "living_room/004", "living_room/005", "courtyard/004", "courtyard/005",
)
VAL_SESSIONS: tuple[str, ...] = ("kitchen/1015_4", "courtyard/005")  # val="sessions": two whole training sessions
VAL_FRACTION = 0.1  # val="gafa": the last 10% of the training windows (GAFA's train.py)
# The 17 sessions in an order whose every prefix of 3+ covers train, val and test (for small
# synthetic datasets).
SESSION_ORDER: tuple[str, ...] = (
    "library/1026_3", "library/1029_2", "kitchen/1015_4", "lab/1013_1", "lab/1013_2", "kitchen/1022_4",
    "kitchen/1022_2", "living_room/004", "living_room/006", "courtyard/004", "courtyard/002",
    "courtyard/005", "library/1028_2", "courtyard/003", "library/1028_5", "lab/1014_1", "living_room/005",
)
WINDOW = 7  # GAFA's temporal window (frames)
PKL_KEYS: tuple[str, ...] = ("keypoints2d", "gaze", "head", "chest", "R_cam2w", "t_cam2w")
LAYOUT = """    raw_data/<scene>/<session>/<camera>/<frame:06d>.jpg
    raw_data/<scene>/<session>/<camera>.pkl   keypoints2d (N,25,>=2) BODY_25 px; gaze/head/chest
                                              {direction (N,3), position (N,3)}; R_cam2w; t_cam2w
    raw_data/intrinsics.npz                   cam_mat (3,3), dist_coeffs (1,12)
    scenes: library, lab, kitchen, living_room, courtyard"""


def session_split(session: str, val_sessions: tuple[str, ...] = ()) -> str:
    """"train" or "test" (GAFA's published split) for a "<scene>/<session>" name, "val" for one of
    `val_sessions`; KeyError for an unknown session."""
    if session in TEST_SESSIONS:
        return "test"
    if session in val_sessions:
        return "val"
    if session in TRAIN_SESSIONS:
        return "train"
    raise KeyError(session)


def window_starts(index: np.ndarray, interval: int, size: int = WINDOW) -> np.ndarray:
    """GAFA's windows over one camera sequence (`dataloader/gafa.py`): the positions i (k,) int64
    in range(0, n - size, interval) of the sequence's frames whose raw frame numbers `index` (n,)
    (increasing) run consecutively, index[i] + size - 1 == index[i + size - 1]. As in GAFA's code
    the window ending on the last frame is never used; a sequence of fewer than `size` frames has
    none. Training uses interval 1 (overlapping windows), evaluation interval 7 (disjoint)."""
    index = np.asarray(index, np.int64)
    i = np.arange(0, max(len(index) - size, 0), interval)
    return i[index[i] + size - 1 == index[i + size - 1]]


def gafa_val_starts(numbers: dict[str, np.ndarray], seed: int) -> dict[str, int]:
    """GAFA's validation cut, seeded: per camera sequence of a training session, the position of
    its frames from which they are val (0: all; len: none).

    numbers: "<scene>/<session>/<camera>" -> raw frame numbers (n,) of its frames, every
    training camera (others are ignored). The sessions are shuffled in TRAIN_SESSIONS order with
    np.random.default_rng(seed), their cameras taken in name order, and windows counted with
    interval 1 (`window_starts`); the last VAL_FRACTION of them (int() of the count, as GAFA) are
    val, and so is every frame from the first one's first frame on. No window at all: no val."""
    order = [TRAIN_SESSIONS[k] for k in np.random.default_rng(seed).permutation(len(TRAIN_SESSIONS))]
    cams = [(c, numbers[c]) for s in order for c in sorted(numbers) if c.rsplit("/", 1)[0] == s]
    starts = [window_starts(idx, 1) for _, idx in cams]
    counts = np.array([len(w) for w in starts], np.int64)
    out = {c: len(idx) for c, idx in cams}
    if not counts.sum():
        return out
    cut = int(counts.sum() * (1 - VAL_FRACTION))
    before = 0
    for (c, idx), w, n in zip(cams, starts, counts):
        k = cut - before  # windows of this camera that stay train
        out[c] = len(idx) if k >= n else (0 if k <= 0 else int(w[k]))
        before += n
    return out


def frame_id(session: str, camera: str, frame: int) -> str:
    """Stable frame id, e.g. "library/1029_2/Camera1_0/000123"."""
    return f"{session}/{camera}/{int(frame):06d}"


def keypoint_box(kp: np.ndarray, joints: slice | tuple[int, ...]) -> np.ndarray:
    """GAFA's KeypointsToBB (data/preprocessed/transforms.py) on each frame: (N, 4) u, v, w, h from
    the min/max of the frame's detected `joints`, NaN where none is detected. kp: (N, 25, >=2)
    pixels. As GAFA's: a joint counts when both its coordinates are non-zero (OpenPose writes 0, 0
    for an undetected one), and its coordinates are truncated to integers (`astype(int)`) before
    the min/max. The one box rule of the adapter's boxes and of view/gafa's inputs."""
    uv = np.asarray(kp, np.float64)[:, joints, :2]
    det = np.all(uv != 0, axis=-1)
    uv = np.trunc(uv)
    lo = np.where(det[..., None], uv, np.inf).min(axis=1)
    hi = np.where(det[..., None], uv, -np.inf).max(axis=1)
    box = np.concatenate([lo, hi - lo], axis=1)
    box[~det.any(axis=1)] = np.nan
    return box


def _expand(box: np.ndarray, top: float, bottom: float, left: float, right: float) -> np.ndarray:
    """GAFA's ExpandBB on (N, 4) u, v, w, h: pads int(frac * w) left/right, int(frac * h) top/bottom."""
    u, v, w, h = box.T
    pl, pr = np.trunc(left * w), np.trunc(right * w)
    pt, pb = np.trunc(top * h), np.trunc(bottom * h)
    return np.stack([u - pl, v - pt, w + pl + pr, h + pt + pb], axis=1)


def _square(box: np.ndarray) -> np.ndarray:
    """GAFA's ExpandBBRect: a square of side max(w, h), centred on the shorter axis."""
    u, v, w, h = box.T
    side = np.maximum(w, h)
    return np.stack([u - np.floor((side - w) / 2), v - np.floor((side - h) / 2), side, side], axis=1)


def keypoint_squares(kp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GAFA's head box and body square, each (N, 4) u, v, w, h pixels, from BODY_25 keypoints
    (N, 25, >=2): head_transform (`keypoint_box` of nose, neck, eyes, ears; ExpandBB(0.85, -0.2,
    0.1, 0.1); ExpandBBRect) and body_transform's first three steps (all joints; ExpandBB(0.15, 0.05,
    0.2, 0.2); ExpandBBRect), before its ReshapeBBRect to 3:4 (data/preprocessed/preprocess.py)."""
    head = _square(_expand(keypoint_box(kp, BODY25_HEAD), top=0.85, bottom=-0.2, left=0.1, right=0.1))
    body = _square(_expand(keypoint_box(kp, slice(None)), top=0.15, bottom=0.05, left=0.2, right=0.2))
    return head, body


def head_boxes(kp: np.ndarray) -> np.ndarray:
    """(N, 4) x1, y1, x2, y2 head boxes from BODY_25 keypoints as GAFA's head_transform builds them."""
    box = keypoint_squares(kp)[0]
    return np.concatenate([box[:, :2], box[:, :2] + box[:, 2:]], axis=1)


def body_boxes(kp: np.ndarray) -> np.ndarray:
    """(N, 4) x1, y1, x2, y2 body boxes as GAFA's body_transform builds them (square, then 3:4)."""
    u, v, side, _ = keypoint_squares(kp)[1].T
    w = np.trunc(side * 192 / 256)
    u = u + np.floor((side - w) / 2)
    return np.stack([u, v, u + w, v + side], axis=1)


def _numeric(pkl: Path, field: str, value: object, shape: str) -> np.ndarray:
    """`value` as a float64 array; DatasetFormatError naming the file and the field when it does not
    hold numbers (strings, None, ragged lists)."""
    try:
        a = np.asarray(value, np.float64)
    except (TypeError, ValueError) as e:
        raise DatasetFormatError(
            f"{pkl}: {field} does not hold numbers ({e}); expected a float array {shape}") from None
    return a


def _pick_k(K: np.ndarray, head_pos: np.ndarray, kp: np.ndarray, where: Path) -> np.ndarray:
    """K or its transpose, whichever projects the head positions closer to the head keypoints."""
    KT = np.array([[K[1, 1], 0, K[1, 2]], [0, K[0, 0], K[0, 2]], [0, 0, 1]])
    head_uv = kp[:, BODY25_HEAD, :2].astype(np.float64)
    det = np.any(head_uv != 0, axis=-1)
    centre = (head_uv * det[..., None]).sum(1) / np.maximum(det.sum(1, keepdims=True), 1)
    ok = det.any(1) & np.isfinite(head_pos).all(1)
    if not ok.any():
        return K
    errs = [float(np.nanmedian(np.linalg.norm(project(head_pos[ok], k) - centre[ok], axis=1))) for k in (K, KT)]
    if errs[1] < errs[0]:
        log.info("GAFA %s: K transposed reprojects the head %.0f px closer; using it", where, errs[0] - errs[1])
        return KT
    return K


def _valid(kp: np.ndarray) -> np.ndarray:
    """(N,) bool: the frames GAFA's preprocessing keeps, those with a detected head joint
    (keypoints (N, 25, >=2) px, 0 = undetected)."""
    return np.any(kp[:, BODY25_HEAD, :2] != 0, axis=(1, 2))


class GAFAAdapter(DatasetAdapter):
    """GAFA raw: per-camera pickles of BODY_25 keypoints and camera-frame gaze/head/chest vectors."""

    name = "gafa"
    layout = LAYOUT

    def __init__(self, root: str | Path, k_mode: str = "auto", sessions: tuple[str, ...] | None = None,
                 val: str = "gafa", val_seed: int = 0):
        super().__init__(root)
        if (self.root / "raw_data").is_dir():
            self.root = self.root / "raw_data"
        self.k_mode = one_of("k_mode", k_mode, ("auto", "as_is"))
        val = one_of("val", val, ("gafa", "sessions"))
        check_option("val_seed", val_seed, isinstance(val_seed, int) and not isinstance(val_seed, bool), "an integer")
        check_option("sessions", sessions, sessions is None or (
            isinstance(sessions, (list, tuple)) and all(isinstance(s, str) for s in sessions)),
            "a list of \"<scene>/<session>\" names or null")
        intr = self.require("intrinsics.npz", "shared camera intrinsics")
        try:
            with np.load(intr, allow_pickle=False) as z:
                K = np.asarray(z["cam_mat"], np.float64)
        except (KeyError, OSError, ValueError, TypeError) as e:
            raise DatasetFormatError(f"{intr}: cannot read cam_mat ({e}); expected a (3, 3) float array") from e
        self.K = check_intrinsics(K, intr)
        self.units = {"eye_xyz": "m", "boxes": BOXES_XYXY + " (from the keypoints)", "decided_by": "the format"}
        self.val_sessions = VAL_SESSIONS if val == "sessions" else ()
        self.cameras: list[tuple[str, Path]] = []  # (session, pkl path)
        unknown = []
        for scene in SCENES:
            for sdir in sorted(p for p in (self.root / scene).glob("*") if p.is_dir()):
                session = f"{scene}/{sdir.name}"
                if sessions is not None and session not in sessions:
                    continue
                try:
                    session_split(session)
                except KeyError:
                    unknown.append(session)
                    continue
                self.cameras += [(session, p) for p in sorted(sdir.glob("*.pkl"))]
        if unknown:
            log.warning("GAFA: skipping sessions outside the published split: %s", ", ".join(unknown))
        if not self.cameras:
            raise DatasetFormatError(f"gafa: no <scene>/<session>/<camera>.pkl under {self.root}. "
                                     f"Expected layout:\n{LAYOUT}")
        self.val_start: dict[str, int] = {}  # val="gafa": camera sequence -> first val position
        if val == "gafa":
            train = [(f"{s}/{p.stem}", p) for s, p in self.cameras if session_split(s) == "train"]
            self.val_start = gafa_val_starts({c: np.flatnonzero(_valid(self._load_camera(p)["keypoints2d"]))
                                              for c, p in train}, val_seed)

    def _load_camera(self, pkl: Path) -> dict[str, np.ndarray]:
        """The camera pickle's arrays, checked: a dict with PKL_KEYS, numeric arrays of the expected
        shapes, head positions in metres. DatasetFormatError naming the file and the field."""
        d = load_pickle(pkl)
        if not isinstance(d, dict):
            raise DatasetFormatError(f"{pkl}: holds a {type(d).__name__}, not a dict; a GAFA camera pickle is a dict "
                                     f"with keys {list(PKL_KEYS)}")
        missing = [k for k in PKL_KEYS if k not in d]
        if missing:
            raise DatasetFormatError(f"{pkl}: missing key(s) {missing}; found {sorted(map(str, d))}")
        kp = _numeric(pkl, "keypoints2d", d["keypoints2d"], "(N, 25, >=2) pixels")
        if kp.ndim != 3 or kp.shape[1] != 25 or kp.shape[2] < 2:
            raise DatasetFormatError(f"{pkl}: keypoints2d has shape {kp.shape}, expected (N, 25, >=2)")
        kp = kp.astype(np.float32)
        if kp.shape[2] == 2:  # no confidence column: detected joints get confidence 1
            kp = np.concatenate([kp, np.any(kp != 0, axis=-1, keepdims=True).astype(np.float32)], axis=-1)
        n = len(kp)
        out = {"keypoints2d": kp[:, :, :3]}
        for key, sub in (("gaze", "direction"), ("head", "direction"), ("head", "position")):
            if not isinstance(d[key], dict) or sub not in d[key]:
                raise DatasetFormatError(f"{pkl}: {key}[{sub!r}] missing; {key} must be a dict with {sub!r} ({n}, 3)")
            a = _numeric(pkl, f"{key}[{sub!r}]", d[key][sub], f"({n}, 3)")
            if a.shape != (n, 3):
                raise DatasetFormatError(f"{pkl}: {key}[{sub!r}] has shape {a.shape}, expected ({n}, 3)")
            out[f"{key}_{sub}"] = a
        check_distances(np.linalg.norm(out["head_position"], axis=1), f"{pkl} head['position']",
                        "the pickle's positions to metres (GAFA's unit)", "head distance")
        return out

    def frames(self) -> Iterator[FrameRef]:
        for session, pkl in self.cameras:
            camera = pkl.stem
            cam = self._load_camera(pkl)
            kp = cam["keypoints2d"]
            valid = _valid(kp)
            hb, bb = head_boxes(kp), body_boxes(kp)
            gaze = normalize(cam["gaze_direction"])
            folder = pkl.with_suffix("")
            K = _pick_k(self.K, cam["head_position"], kp, pkl) if self.k_mode == "auto" else self.K
            size = first_image_size([folder / f"{i:06d}.jpg" for i in np.flatnonzero(valid)[:3]])
            split = session_split(session, self.val_sessions)
            val_from = self.val_start.get(f"{session}/{camera}", -1)
            for pos, i in enumerate(np.flatnonzero(valid).tolist()):
                yield FrameRef(
                    id=frame_id(session, camera, i), split="val" if 0 <= val_from <= pos else split, scene=session,
                    image_path=folder / f"{i:06d}.jpg", K=K, image_size=size,
                    head_box=hb[i].astype(np.float32), body_box=bb[i].astype(np.float32),
                    eye=cam["head_position"][i].astype(np.float32), gaze=gaze[i].astype(np.float32),
                    sequence=f"{session}/{camera}", index=i, keypoints_2d=kp[i], annotation=f"{pkl} row {i}",
                )
