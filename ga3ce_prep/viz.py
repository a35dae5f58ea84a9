"""`ga3ce-prep show`: one frame's 3D context drawn on its image (PNG) or as a point set (PLY).

PNG (OpenCV drawing): the head box (green), the stored object positions projected into the image
(dots coloured near = warm, far = cool, size by mask area), the head position t_object (yellow
cross), the view prior v (blue arrow), the ground-truth gaze (red arrow) and, when given, a
predicted gaze (orange arrow), all drawn from the head position over `arrow_m` metres, and the pose
joints (magenta dots) when present.

PLY (Open3D): the frame's back-projected depth (coloured by the image when readable, grey
otherwise), each object position as a small red cube of points, the head position (yellow), v and
the ground-truth gaze as lines of points (blue, red), and the pose joints (magenta). Opens in
MeshLab, CloudCompare or Open3D's viewer.
"""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from .errors import FrameError, Ga3ceError, StoreError
from .frames import FrameRef, load_depth, load_rgb
from .geometry import depth_to_points, normalize, project
from .store import ContextStore, LazyStore

BLUE, RED, GREEN, YELLOW, MAGENTA, ORANGE = ((255, 120, 0), (40, 40, 230), (60, 200, 60), (0, 230, 255),
                                             (230, 60, 230), (0, 150, 255))  # BGR


def frame_index(store: ContextStore, frame_id: str) -> int:
    """Index of a frame id in the store; StoreError with close matches if absent."""
    hits = np.flatnonzero(store.frames["id"] == frame_id)
    if len(hits):
        return int(hits[0])
    dropped = frame_id in set(store.failures.get("frame_id", np.array([], str)).tolist())
    near = [i for i in store.frames["id"][:2000].tolist() if frame_id.split("/")[-1] in i][:5]
    why = " (it was dropped: see `ga3ce-prep info` failures)" if dropped else ""
    raise StoreError(f"frame {frame_id!r} is not in {store.path}{why}; e.g. {near or store.frames['id'][:3].tolist()}")


def find_frame_refs(store: ContextStore | LazyStore, frame_ids: Iterable[str],
                    data: str | Path | None = None) -> dict[str, FrameRef]:
    """id -> the dataset's FrameRef for each of frame_ids the dataset has, re-opening the dataset
    the store was made from (`datasets.open_store_dataset`: its provenance, or the one at `data`);
    one pass over the adapter's frames, stopping once every id is found. Raises what opening the
    dataset raises (Ga3ceError, KeyError for an unknown format, OSError)."""
    from .datasets import open_store_dataset

    wanted, out = set(frame_ids), {}
    for f in open_store_dataset(store.attrs.get("dataset", {}), data).frames():
        if f.id in wanted:
            out[f.id] = f
            if len(out) == len(wanted):
                break
    return out


def find_frame_ref(store: ContextStore, frame_id: str, data: str | Path | None = None) -> FrameRef | None:
    """The dataset's FrameRef for frame_id (`find_frame_refs`), or None if the dataset cannot be
    opened or has no such frame."""
    try:
        return find_frame_refs(store, [frame_id], data).get(frame_id)
    except (Ga3ceError, KeyError, OSError, TypeError):
        return None


def _ray(p0: np.ndarray, d: np.ndarray, length: float) -> np.ndarray:
    return np.stack([p0, p0 + length * normalize(d)])


def frame_canvas(store: ContextStore, i: int, ref: FrameRef | None) -> tuple[np.ndarray, float]:
    """Frame i's image (H', W', 3) uint8 BGR (grey where it cannot be read), upscaled so the
    shorter side is at least 480 px, and that scale s (pixel coordinates times s)."""
    W, H = (int(x) for x in store.frames["image_size"][i])
    img = None
    if ref is not None:
        try:
            img = load_rgb(ref.image_path)[..., ::-1].copy()
        except FrameError:
            img = None
    if img is None:
        img = np.full((max(H, 1), max(W, 1), 3), 90, np.uint8)
    H, W = img.shape[:2]
    s = max(1.0, 480.0 / min(H, W))
    img = cv2.resize(img, (int(round(W * s)), int(round(H * s))), interpolation=cv2.INTER_LINEAR) if s > 1 else img
    return img, s


def draw_png(store: ContextStore, i: int, ref: FrameRef | None, arrow_m: float = 0.6,
             gaze_label: str = "ground-truth gaze", pred: np.ndarray | None = None,
             pred_label: str = "ours g") -> np.ndarray:
    """The drawing (H', W', 3) uint8 BGR on frame_canvas; the red arrow is frames/gaze, named
    `gaze_label` in the legend; `pred` (3,), when given, is the orange arrow `pred_label`."""
    fr = store.frames
    K = fr["K"][i].astype(np.float64)
    img, s = frame_canvas(store, i, ref)

    def px(pts: np.ndarray) -> np.ndarray:
        return project(np.atleast_2d(pts), K) * s

    def pt(p) -> tuple[int, int]:
        return int(round(p[0])), int(round(p[1]))

    x1, y1, x2, y2 = fr["head_box"][i] * s
    cv2.rectangle(img, pt((x1, y1)), pt((x2, y2)), GREEN, 2)
    xyz = store.objects_of(i)
    if len(xyz):
        area = store.objects["area"][store.object_slice(i)]
        uv = px(xyz)
        z = xyz[:, 2]
        zn = np.clip((z - z.min()) / max(np.ptp(z), 1e-6), 0, 1)
        colours = cv2.applyColorMap((255 * (1 - zn)).astype(np.uint8)[:, None], cv2.COLORMAP_JET)[:, 0]
        for (u, v), c, a in zip(uv, colours, area):
            if np.all(np.isfinite((u, v))):
                r = int(np.clip(np.sqrt(a) * s / 6, 3, 12))
                cv2.circle(img, pt((u, v)), r, tuple(int(x) for x in c), -1)
                cv2.circle(img, pt((u, v)), r, (0, 0, 0), 1)
    pose = fr["pose"][i]
    for u, v in px(pose[np.isfinite(pose).all(1)]) if np.isfinite(pose).any() else []:
        if np.isfinite(u) and np.isfinite(v):
            cv2.circle(img, pt((u, v)), 3, MAGENTA, -1)
    head = fr["head_pos"][i].astype(np.float64)
    arrows = [(fr["view"][i], BLUE), (fr["gaze"][i], RED)] + ([] if pred is None else [(pred, ORANGE)])
    for vec, colour in arrows:
        if np.all(np.isfinite(vec)) and np.all(np.isfinite(head)):
            a, b = px(_ray(head, np.asarray(vec, np.float64), arrow_m))
            if np.all(np.isfinite(a)) and np.all(np.isfinite(b)):
                cv2.arrowedLine(img, pt(a), pt(b), colour, 3, tipLength=0.15)
    hc = px(head)[0]
    if np.all(np.isfinite(hc)):
        cv2.drawMarker(img, pt(hc), YELLOW, cv2.MARKER_CROSS, 18, 3)
    lines = [(f"{fr['id'][i]}  objects {len(xyz)}", (255, 255, 255)), ("head box", GREEN), ("t_object", YELLOW),
             ("view prior v", BLUE), (gaze_label, RED)] + ([] if pred is None else [(pred_label, ORANGE)])
    lines.append(("objects: warm near, cool far", (255, 255, 255)))
    panel_w = 12 + max(cv2.getTextSize(t, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)[0][0] for t, _ in lines)
    region = img[4:10 + 20 * len(lines), 4:4 + panel_w]
    region[...] = (0.35 * region).astype(np.uint8)  # darken behind the legend
    for k, (text, colour) in enumerate(lines):
        cv2.putText(img, text, (10, 22 + 20 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
    return img


def context_points(store: ContextStore, i: int, ref: FrameRef | None, arrow_m: float = 0.8,
                   max_scene_points: int = 200_000, depth: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The PLY's points (P, 3) metres and colours (P, 3) in [0, 1] (module docstring). depth: the
    frame's (H, W) depth in metres, else read from the frame's depth file."""
    fr = store.frames
    K = fr["K"][i].astype(np.float64)
    pts, cols = [], []
    if ref is not None and (depth is not None or ref.depth_path is not None):
        try:
            if depth is not None:
                d = depth
            else:
                assert ref.depth_path is not None  # the condition above
                d = load_depth(ref.depth_path, ref.depth_scale)
            P = depth_to_points(d, K).reshape(-1, 3)
            ok = d.reshape(-1) > 0
            try:
                rgb = load_rgb(ref.image_path).reshape(-1, 3) / 255.0
                c = rgb if len(rgb) == len(P) else np.full_like(P, 0.6)
            except FrameError:
                c = np.full_like(P, 0.6)
            idx = np.flatnonzero(ok)[:: max(1, int(ok.sum()) // max_scene_points)]
            pts.append(P[idx])
            cols.append(c[idx])
        except FrameError:
            pass

    def add(p: np.ndarray, colour) -> None:
        p = np.atleast_2d(p)
        p = p[np.isfinite(p).all(1)]
        pts.append(p)
        cols.append(np.tile(np.asarray(colour, np.float64), (len(p), 1)))

    cube = np.stack(np.meshgrid(*[np.linspace(-0.02, 0.02, 4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    for x in store.objects_of(i):
        add(x + cube, (1.0, 0.1, 0.1))
    head = fr["head_pos"][i].astype(np.float64)
    add(head + cube * 1.5, (1.0, 0.9, 0.0))
    t = np.linspace(0, 1, 80)[:, None]
    for vec, colour in ((fr["view"][i], (0.0, 0.4, 1.0)), (fr["gaze"][i], (1.0, 0.0, 0.0))):
        if np.all(np.isfinite(vec)) and np.all(np.isfinite(head)):
            add(head + t * arrow_m * normalize(vec.astype(np.float64)), colour)
    pose = fr["pose"][i]
    if np.isfinite(pose).any():
        for j in pose[np.isfinite(pose).all(1)]:
            add(j + cube * 0.75, (0.9, 0.2, 0.9))
    return np.concatenate(pts), np.concatenate(cols)


def show(store: ContextStore, frame_id: str, out: str | Path, data: str | Path | None = None) -> Path:
    """Write frame_id's drawing to out (.png) or its 3D context to out (.ply); returns out."""
    i = frame_index(store, frame_id)
    return write_context(store, i, find_frame_ref(store, frame_id, data), out)


def write_context(store: ContextStore, i: int, ref: FrameRef | None, out: str | Path,
                  gaze_label: str = "ground-truth gaze", depth: np.ndarray | None = None) -> Path:
    """Frame i's drawing as out (.png) or its 3D context as out (.ply); returns out."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".png":
        if not cv2.imwrite(str(out), draw_png(store, i, ref, gaze_label=gaze_label)):
            raise StoreError(f"cannot write {out}")
    elif out.suffix.lower() == ".ply":
        import open3d as o3d

        P, C = context_points(store, i, ref, depth=depth)
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P.astype(np.float64)))
        pc.colors = o3d.utility.Vector3dVector(np.clip(C, 0, 1))
        if not o3d.io.write_point_cloud(out, pc):
            raise StoreError(f"cannot write {out}")
    else:
        raise StoreError(f"--out {out}: use a .png (drawing) or .ply (3D point set) file name")
    return out
