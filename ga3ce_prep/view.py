"""`ga3ce-prep view`: a store's 3D context over time, a trained model's gaze beside the truth's, or one
photo's prediction (`predict --view`), as a Rerun recording (`--save f.rrd`) or in Rerun's viewer
(`--spawn`: the native viewer; `--serve`: the web viewer). Rerun is the optional extra `[view]`
(`pip install 'ga3ce-prep[view]'`), imported only here and only when a command asks for it.

Each frame is logged on the timeline of its session (named as the store names it, frames/scene:
the frame's place in its session, 0, 1, ...) and on `row` (its row in the store), under these
entities, every quantity in metres in the store's camera frame (x right, y down, z forward: the
root declares Rerun's RDF view coordinates) and under its store name:

    camera                    Pinhole: frames/K at frames/image_size (the camera at the origin)
    camera/image              the frame's image (the dataset's file), JPEG (`jpeg_quality`)
    camera/frames/head_box    frames/head_box, px
    camera/masks              with masks=True: the store's objects backend's masks, class k + 1 = object k
    depth/image               the completed depth the store's depth backend makes, every `depth_step(...)`-th
                              pixel (at most DEPTH_SIDE on its longer side), PNG in mm
    depth/points              the completed depth back-projected on a grid of at most `budget` pixels,
                              coloured by the image
    objects/xyz               objects/xyz, labelled with their index k, radius 0.3 sqrt(area / pi) z / fx
                              (0.3 of the mask's extent at its depth; 2-15 cm)
    frames/head_pos           t_object
    frames/pose, .../bones    the 30 joints (keypoint id = joint index) and skeleton.BONES
    frames/view, frames/gaze  v and the truth's gaze: arrows of `arrow_m` from t_object
    frames/id                 the frame id (text)
    model/gaze                with a checkpoint: the model's g, the same arrow
    error_deg/model, /view    angle (degrees) between g, and v, and the truth's gaze

A quantity a frame does not have (a NaN, no image, no depth) is cleared on that frame, so the
viewer never shows the previous frame's in its place. A store is read a block of frames at a time
(store.open_lazy): any size streams in bounded memory. docs/store.md "Look at a run".
"""
from __future__ import annotations

import importlib.util
import math
import signal
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import click
import cv2
import numpy as np

from .errors import ConfigError, FrameError, Ga3ceError
from .frames import DepthMap, FrameRef, load_rgb
from .geometry import angular_error_deg, depth_to_points, normalize
from .skeleton import BONES
from .store import ContextStore, LazyStore, open_lazy

INSTALL = "pip install 'ga3ce-prep[view]'"
BLOCK = 64                # frames read from the store, and through the model, at a time
POINT_BUDGET = 5_000      # depth/points per frame, at most
DEPTH_SIDE = 320          # depth/image's longer side, at most, px (a picture of the completion; the points are 3D)
JPEG_QUALITY = 85
ARROW_M = 0.8             # length of the gaze arrows, metres
RADIUS = (0.3, 0.02, 0.15)  # objects' radius: this share of the mask's extent, clipped to these metres
COLOURS = {"view": (40, 120, 255), "gaze": (230, 40, 40), "model": (255, 150, 0), "head": (255, 230, 0),
           "pose": (230, 60, 230), "box": (60, 200, 60)}  # RGB


def import_rerun() -> Any:
    """The rerun module; Ga3ceError saying how to install it when it is missing."""
    try:
        import rerun
    except ImportError as e:
        raise Ga3ceError(f"viewing needs Rerun, the optional extra [view], which this install lacks ({e}): "
                         f"install it with  {INSTALL}") from None
    return rerun


# --- one frame's content, numpy only --------------------------------------------------------------------------

@dataclass
class FrameView:
    """What one frame shows (module docstring): rgb (H, W, 3) uint8, depth (H, W) float32 metres and
    masks (H, W) uint16 (0 none, k + 1 object k), each None when unknown; points (P, 3) metres with
    colours (P, 3) uint8; K (3, 3), size (W, H), head_box (4,) px; objects (M, 3) metres and their
    radii (M,); head_pos (3,), pose (30, 3), view, gaze, model (3,) unit, NaN when unknown (model:
    None without a checkpoint)."""

    frame_id: str
    K: np.ndarray
    size: tuple[int, int]
    head_box: np.ndarray
    objects: np.ndarray
    radii: np.ndarray
    head_pos: np.ndarray
    pose: np.ndarray
    view: np.ndarray
    gaze: np.ndarray
    model: np.ndarray | None = None
    rgb: np.ndarray | None = None
    depth: np.ndarray | None = None
    masks: np.ndarray | None = None
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    colours: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))


def grid_step(shape: tuple[int, int], budget: int) -> int:
    """The pixel step s of the grid (every s-th row and column) that holds at most `budget` of an
    (H, W) image's pixels."""
    H, W = shape
    s = max(1, math.ceil(math.sqrt(H * W / max(budget, 1))))
    while -(-H // s) * -(-W // s) > budget:
        s += 1
    return s


def depth_step(shape: tuple[int, int], side: int = DEPTH_SIDE) -> int:
    """The step s (every s-th row and column) that brings an (H, W) image's longer side to at most `side`."""
    return max(1, -(-max(shape) // side))


def cloud(depth: np.ndarray, K: np.ndarray, rgb: np.ndarray | None, budget: int) -> tuple[np.ndarray, np.ndarray]:
    """The depth map (H, W) metres back-projected (geometry.depth_to_points) at the pixels of a grid of
    at most `budget` pixels (`grid_step`) that have depth: points (P, 3) float32 metres and their
    colours (P, 3) uint8 from rgb (H, W, 3) (grey without it, or at another size)."""
    s = grid_step(depth.shape, budget)
    d = depth[::s, ::s]
    pts = depth_to_points(depth, K)[::s, ::s]
    ok = d > 0
    if rgb is not None and rgb.shape[:2] == depth.shape:
        cols = rgb[::s, ::s][ok]
    else:
        cols = np.full((int(ok.sum()), 3), 150, np.uint8)
    return pts[ok], cols.astype(np.uint8)


def object_radii(xyz: np.ndarray, area: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(M,) metres: RADIUS[0] of the radius of a disc of each mask's area (px) at its object's depth,
    RADIUS[0] * sqrt(area / pi) * z / fx, clipped to RADIUS[1:]."""
    share, lo, hi = RADIUS
    r = share * np.sqrt(np.asarray(area, np.float64) / np.pi) * np.abs(xyz[:, 2]) / float(K[0, 0])
    return np.clip(r, lo, hi).astype(np.float32)


def bone_segments(pose: np.ndarray) -> np.ndarray:
    """(B, 2, 3) metres: the skeleton's bones (skeleton.BONES: joint, parent) whose two joints of
    pose (30, 3) are finite."""
    j, p = np.array(BONES).T
    seg = np.stack([pose[j], pose[p]], axis=1)
    return seg[np.isfinite(seg).all((1, 2))]


def mask_labels(masks: np.ndarray, index: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) uint16 label image of the kept masks: 0 none, k + 1 where mask index[k] (the k-th
    object) lies. masks: (M, H, W) bool (drawn largest first, so a smaller mask over a larger one
    stays visible) or an (H, W) int label image (negative = none)."""
    out = np.zeros(shape, np.uint16)
    if masks.ndim == 2:
        lut = np.zeros(int(max(masks.max(initial=-1), index.max(initial=-1))) + 2, np.uint16)
        lut[index] = np.arange(1, len(index) + 1)
        return lut[np.where(masks >= 0, masks, -1)]  # lut[-1] (the last entry) is never an object's
    kept = masks[index]
    for k in np.argsort(-kept.reshape(len(kept), -1).sum(1), kind="stable"):
        out[kept[k]] = k + 1
    return out


def frame_view(store: ContextStore, i: int, rgb: np.ndarray | None = None, depth: np.ndarray | None = None,
               masks: np.ndarray | None = None, model: np.ndarray | None = None,
               budget: int = POINT_BUDGET) -> FrameView:
    """Frame i of `store` (a block of `LazyStore.rows`, or `predict`'s one-frame store) as it is shown."""
    f = store.frames
    K = f["K"][i].astype(np.float64)
    xyz = store.objects_of(i).astype(np.float32)
    area = store.objects["area"][store.object_slice(i)]
    fv = FrameView(frame_id=str(f["id"][i]), K=K, size=(int(f["image_size"][i][0]), int(f["image_size"][i][1])),
                   head_box=f["head_box"][i].astype(np.float32), objects=xyz, radii=object_radii(xyz, area, K),
                   head_pos=f["head_pos"][i].astype(np.float32), pose=f["pose"][i].astype(np.float32),
                   view=f["view"][i].astype(np.float32), gaze=f["gaze"][i].astype(np.float32),
                   model=model, rgb=rgb, depth=depth, masks=masks)
    if depth is not None:
        fv.points, fv.colours = cloud(depth, K, rgb, budget)
    return fv


# --- Rerun -------------------------------------------------------------------------------------------------

def blueprint(rr: Any) -> Any:
    """The layout: the 3D context, beside it the image (head box, masks), the depth and the errors."""
    rrb = rr.blueprint
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/", name="3D context (camera frame, m)", contents=["/**", "- /depth/image"],
                              eye_controls=rrb.EyeControls3D(position=(0.0, -1.2, -1.0), look_target=(0.0, 0.3, 3.0),
                                                             eye_up=(0.0, -1.0, 0.0))),
            rrb.Vertical(
                rrb.Spatial2DView(origin="camera", name="image",
                                  contents=["$origin/image", "$origin/frames/**", "$origin/masks"]),
                rrb.Spatial2DView(origin="depth/image", name="completed depth"),
                rrb.TimeSeriesView(origin="error_deg", name="angular error (deg)"),
            ),
            column_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


def arrow(rr: Any, origin: np.ndarray, direction: np.ndarray | None, length: float, label: str,
          colour: tuple[int, int, int]) -> Any:
    """An Arrows3D of `length` metres from origin (3,) along the unit direction, or a Clear when
    either is unknown."""
    if direction is None or not (np.isfinite(direction).all() and np.isfinite(origin).all()):
        return rr.Clear(recursive=False)
    return rr.Arrows3D(origins=[origin], vectors=[length * normalize(direction.astype(np.float64))],
                       labels=[label], colors=[colour], show_labels=True)


def log_frame(rr: Any, rec: Any, fv: FrameView, times: dict[str, int], arrow_m: float = ARROW_M,
              jpeg_quality: int = JPEG_QUALITY, masks: bool = False) -> None:
    """Log one frame (module docstring) at `times` (timeline -> sequence number); its masks when asked
    (`masks`: a recording that shows them, cleared on a frame without)."""
    clear = rr.Clear(recursive=False)
    rec.reset_time()
    for timeline, t in times.items():
        rec.set_time(timeline, sequence=int(t))
    W, H = fv.size
    rec.log("camera", rr.Pinhole(image_from_camera=fv.K, resolution=[W, H], camera_xyz=rr.ViewCoordinates.RDF))
    if fv.rgb is not None:
        ok, jpg = cv2.imencode(".jpg", fv.rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        rec.log("camera/image", rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg") if ok else clear)
    else:
        rec.log("camera/image", clear)
    box = fv.head_box
    rec.log("camera/frames/head_box", rr.Boxes2D(array=box, array_format=rr.Box2DFormat.XYXY, labels=["head box"],
                                                 colors=[COLOURS["box"]]) if np.isfinite(box).all() else clear)
    if fv.depth is not None:
        step = depth_step(fv.depth.shape)
        mm = np.clip(np.round(fv.depth[::step, ::step] * np.float32(1000)), 0, 65535).astype(np.uint16)
        ok, png = cv2.imencode(".png", mm)
        rec.log("depth/image", rr.EncodedDepthImage(png.tobytes(), media_type="image/png", meter=1000.0)
                if ok else clear)
    else:
        rec.log("depth/image", clear)
    if masks:
        rec.log("camera/masks", rr.SegmentationImage(fv.masks) if fv.masks is not None else clear)
    rec.log("depth/points", rr.Points3D(fv.points, colors=fv.colours, radii=rr.components.Radius.ui_points(2.0))
            if len(fv.points) else clear)
    ok = np.isfinite(fv.objects).all(1)
    rec.log("objects/xyz", rr.Points3D(fv.objects[ok], radii=fv.radii[ok],
                                       labels=[str(k) for k in np.flatnonzero(ok)]) if ok.any() else clear)
    head = fv.head_pos
    rec.log("frames/head_pos", rr.Points3D([head], radii=0.05, labels=["t_object"], colors=[COLOURS["head"]])
            if np.isfinite(head).all() else clear)
    joints = np.flatnonzero(np.isfinite(fv.pose).all(1))
    rec.log("frames/pose", rr.Points3D(fv.pose[joints], keypoint_ids=joints, radii=0.02, colors=[COLOURS["pose"]])
            if len(joints) else clear)
    bones = bone_segments(fv.pose)
    rec.log("frames/pose/bones", rr.LineStrips3D(bones, radii=0.008, colors=[COLOURS["pose"]]) if len(bones) else clear)
    rec.log("frames/view", arrow(rr, head, fv.view, arrow_m, "v", COLOURS["view"]))
    rec.log("frames/gaze", arrow(rr, head, fv.gaze, arrow_m, "truth", COLOURS["gaze"]))
    rec.log("frames/id", rr.TextDocument(fv.frame_id))
    if fv.model is not None:
        rec.log("model/gaze", arrow(rr, head, fv.model, arrow_m, "model g", COLOURS["model"]))
    for name, d in (("model", fv.model), ("view", fv.view)):
        if d is not None and np.isfinite(d).all() and np.isfinite(fv.gaze).all():
            rec.log(f"error_deg/{name}", rr.Scalars(float(angular_error_deg(d, fv.gaze))))


@dataclass
class Sink:
    """Where a recording goes: a file (`save`), the native viewer (`spawn`) or the web viewer
    (`serve`, on web_port, its data on grpc_port)."""

    save: str | Path | None = None
    spawn: bool = False
    serve: bool = False
    web_port: int = 9090
    grpc_port: int = 9876

    def check(self) -> None:
        if sum([self.save is not None, self.spawn, self.serve]) != 1:
            raise ConfigError("say where the recording goes: --save FILE.rrd, --spawn (Rerun's viewer) or --serve "
                              "(its web viewer), one of them")
        if self.save is not None and Path(self.save).suffix != ".rrd":
            raise ConfigError(f"--save {self.save}: a recording is an .rrd file")

    def open(self, name: str) -> tuple[Any, Any, str]:
        """(rerun, the recording stream, the web viewer's address or "")."""
        self.check()
        rr = import_rerun()
        rec = rr.RecordingStream("ga3ce-prep", recording_id=name)
        rr.set_log_time_enabled(False, recording=rec)  # the frames' own timelines only, no wall-clock one
        bp = blueprint(rr)
        url = ""
        if self.save is not None:
            Path(self.save).parent.mkdir(parents=True, exist_ok=True)
            rec.save(self.save, default_blueprint=bp)
        elif self.spawn:  # the extra's own viewer (package rerun_cli), whether or not its bin/ is on PATH
            spec = importlib.util.find_spec("rerun_cli")
            viewer = Path(next(iter(spec.submodule_search_locations or ()), "")) / "rerun" if spec else None
            rr.spawn(recording=rec, default_blueprint=bp,
                     executable_path=str(viewer) if viewer is not None and viewer.is_file() else None)
        else:
            grpc = rec.serve_grpc(grpc_port=self.grpc_port, default_blueprint=bp)
            rr.serve_web_viewer(web_port=self.web_port, open_browser=False, connect_to=grpc)
            url = f"http://127.0.0.1:{self.web_port}/?url={quote(grpc, safe='')}"
        rec.log("/", rr.ViewCoordinates.RDF, static=True)
        return rr, rec, url

    def close(self, rec: Any, url: str) -> None:
        """Flush the recording; with `serve`, keep serving it until interrupted (Ctrl-C)."""
        try:
            rec.flush()
        except RuntimeError as e:  # Rerun's: its viewer, spawned, never listened
            raise Ga3ceError(f"Rerun's viewer did not take the recording ({str(e).splitlines()[0]}): no display? "
                             "write it with --save FILE.rrd and open it where there is one, or use --serve") from None
        if self.serve:
            click.echo(f"serving the web viewer at {url} (Ctrl-C stops it)", err=True)
            # Ctrl-C stops it also where the process started with SIGINT ignored (a background job of a
            # script, a test runner's worker): Python then installs no handler of its own
            signal.signal(signal.SIGINT, signal.default_int_handler)
            try:
                while True:
                    time.sleep(1)
            except KeyboardInterrupt:
                click.echo("stopped", err=True)
        rec.disconnect()


# --- a store ------------------------------------------------------------------------------------------------

def select_rows(store: LazyStore, frames: tuple[str, ...] = (), sessions: tuple[str, ...] = (),
                splits: tuple[str, ...] = ()) -> np.ndarray:
    """Store rows (k,) int64, ascending, of the frames chosen: those of the given frame ids, sessions
    (frames/scene's names) and splits, each kind that is given (any of its names) applying; every
    frame when none is. ConfigError naming an unknown one, with known ones."""
    ix = store.index
    keep = np.ones(len(store), bool)
    for given, names, column, what in ((sessions, store.scene_names, ix["scene"], "session"),
                                       (splits, store.split_names, ix["split"], "split")):
        if given:
            unknown = [g for g in given if g not in names]
            if unknown:
                raise ConfigError(f"no {what} {unknown[0]!r} in {store.path}; its {what}s: {', '.join(names[:12])}"
                                  f"{' ...' if len(names) > 12 else ''} (`ga3ce-prep info` lists them)")
            keep &= np.isin(column, [names.index(g) for g in given])
    if frames:
        ids = ix["id"]
        unknown = sorted(set(frames) - set(ids.tolist()))
        if unknown:
            raise ConfigError(f"no frame {unknown[0]!r} in {store.path} (a dropped frame? `ga3ce-prep info`); "
                              f"e.g. {', '.join(ids[:3].tolist())}")
        keep &= np.isin(ids, list(frames))
    rows = np.flatnonzero(keep)
    if not len(rows):
        raise ConfigError(f"{store.path}: no frame is in all of what was chosen ({len(frames)} frame ids, "
                          f"sessions {list(sessions)}, splits {list(splits)})")
    return rows


def session_positions(scene: np.ndarray) -> np.ndarray:
    """(N,) int64: each row's place among its session's rows (frames/scene codes (N,)), in store order."""
    order = np.argsort(scene, kind="stable")
    first = np.r_[0, np.flatnonzero(np.diff(scene[order])) + 1]
    sizes = np.diff(np.r_[first, len(scene)])
    pos = np.empty(len(scene), np.int64)
    pos[order] = np.arange(len(scene)) - np.repeat(first, sizes)
    return pos


class StoreStages:
    """The store's own depth and (for masks) objects backends, rebuilt from its provenance (the
    pipeline's effective configuration) against the dataset at data_root; what each could not do,
    counted (`missing`)."""

    def __init__(self, attrs: dict[str, Any], data_root: Path, depth: bool = True, masks: bool = False):
        from .stages.objects import MaskObjects

        self.missing: Counter[str] = Counter()
        self.depth_backend: Any = None
        self.objects_backend: MaskObjects | None = None
        want = [s for s, on in (("depth", depth or masks), ("objects", masks)) if on]
        try:
            from .pipeline.config import load_pipeline

            conf = load_pipeline(attrs["pipeline"]["config"], data_root, check_files=False)
            for stage in want:
                b = conf.stages[stage].make(data_root)
                b.check()
                b.warm()
                if stage == "depth":
                    self.depth_backend = b
                elif isinstance(b, MaskObjects):
                    self.objects_backend = b
                else:
                    self.missing[f"masks: the objects backend {conf.stages[stage].backend} makes none"] += 1
        except (Ga3ceError, KeyError, OSError) as e:
            self.missing[f"the store's {' and '.join(want)} backend cannot run here ({e})"] += 1

    def depth(self, ref: FrameRef | None) -> DepthMap | None:
        """The frame's completed depth as the store's run made it, None when it cannot be had."""
        if ref is None or self.depth_backend is None:
            return None
        try:
            return self.depth_backend.depth(ref)
        except (Ga3ceError, OSError) as e:
            self.missing[f"depth: {type(e).__name__}"] += 1
            return None

    def masks(self, ref: FrameRef | None, depth: DepthMap | None, xyz: np.ndarray) -> np.ndarray | None:
        """The label image (`mask_labels`) of the frame's objects as the objects backend finds them
        again, None when it cannot, or when what it finds is not the store's objects xyz (M, 3)."""
        if ref is None or depth is None or self.objects_backend is None:
            return None
        try:
            masks, _, pos = self.objects_backend.placed(ref, depth)
        except (Ga3ceError, OSError) as e:
            self.missing[f"masks: {type(e).__name__}"] += 1
            return None
        if pos.xyz.shape != xyz.shape or not np.allclose(pos.xyz, xyz, atol=1e-4, equal_nan=True):
            self.missing["masks: the objects backend finds other objects than the store's here"] += 1
            return None
        return mask_labels(masks, pos.index, depth.depth.shape)


def read_rgb(ref: FrameRef | None, missing: Counter[str]) -> np.ndarray | None:
    """The frame's image (H, W, 3) uint8 RGB, None (counted in `missing`) when it cannot be read."""
    if ref is None:
        return None
    try:
        return load_rgb(ref.image_path)
    except FrameError as e:
        missing[f"image: {type(e).__name__}"] += 1
        return None


class Gaze:
    """A checkpoint's model, predicting g for a block of frames as `eval` does (train/evaluate.predict)."""

    def __init__(self, checkpoint: str | Path, threads: int = 2):
        import torch

        from .train.checkpoint import build_model, load_checkpoint

        torch.set_num_threads(threads)
        ckpt = load_checkpoint(checkpoint)
        self.model = build_model(ckpt)
        self.n_max = ckpt["config"].get("n_max")

    def __call__(self, block: ContextStore) -> np.ndarray:
        """g (k, 3) for the block's k frames, NaN where a frame has no view prior."""
        from .train.dataset import ContextDataset
        from .train.evaluate import predict

        ds = ContextDataset(block, require_gaze=False)
        g = np.full((len(block), 3), np.nan, np.float32)
        if len(ds):
            g[ds.rows] = predict(self.model, ds, n_max=self.n_max)
        return g


@dataclass
class Recorded:
    """What a recording holds: frames and sessions, how many frames had an image, depth and masks, the
    model's angular error (degrees) on each frame with a truth, and what could not be shown, counted."""

    frames: int = 0
    sessions: int = 0
    images: int = 0
    depth: int = 0
    masks: int = 0
    model_error: list[float] = field(default_factory=list)
    missing: Counter[str] = field(default_factory=Counter)

    def line(self) -> str:
        mean = f"; model g: mean error {np.mean(self.model_error):.2f} deg" if self.model_error else ""
        miss = "; ".join(f"{k} ({v})" for k, v in self.missing.items())
        return (f"{self.frames} frames of {self.sessions} session(s): image {self.images}, depth {self.depth}, "
                f"masks {self.masks}{mean}" + (f"; not shown: {miss}" if miss else ""))


def blocks(rows: np.ndarray, size: int | None = None) -> Iterator[np.ndarray]:
    """rows (k,) in consecutive pieces of `size` (default BLOCK)."""
    size = size or BLOCK
    for k in range(0, len(rows), size):
        yield rows[k:k + size]


def record_store(rr: Any, rec: Any, store: LazyStore, rows: np.ndarray, *, data: str | Path | None = None,
                 checkpoint: str | Path | None = None, depth: bool = True, masks: bool = False,
                 budget: int = POINT_BUDGET, arrow_m: float = ARROW_M, jpeg_quality: int = JPEG_QUALITY,
                 progress: bool = False) -> Recorded:
    """Log the store's frames `rows` (ascending store rows), BLOCK at a time, into `rec`."""
    from .viz import find_frame_refs

    out = Recorded(sessions=len(np.unique(store.index["scene"][rows])))
    ids = [str(i) for i in store.index["id"][rows].tolist()]
    try:
        refs = find_frame_refs(store, ids, data)
    except (Ga3ceError, KeyError, OSError, TypeError) as e:
        refs = {}
        out.missing[f"the dataset cannot be opened ({e}): no image or depth"] += 1
    root = Path(data or store.attrs.get("dataset", {}).get("root", "."))
    stages = StoreStages(store.attrs, root, depth=depth, masks=masks)
    gaze = Gaze(checkpoint) if checkpoint is not None else None
    where = session_positions(store.index["scene"])
    names = store.scene_names
    if masks:  # the masks' class k + 1 is object k
        most = int(store.index["obj_count"][rows].max(initial=0))
        rec.log("camera/masks", rr.AnnotationContext([(k + 1, str(k)) for k in range(most)]), static=True)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(rows), unit="frame", desc="view")
    for chunk in blocks(rows):
        block = store.rows(chunk)
        g = gaze(block) if gaze is not None else None
        for k, row in enumerate(chunk.tolist()):
            ref = refs.get(str(block.frames["id"][k]))
            rgb = read_rgb(ref, out.missing)
            dm = stages.depth(ref)
            labels = stages.masks(ref, dm, block.objects_of(k)) if masks else None
            fv = frame_view(block, k, rgb, None if dm is None else dm.depth, labels,
                            None if g is None else g[k], budget)
            scene = int(store.index["scene"][row])
            log_frame(rr, rec, fv, {names[scene] if scene < len(names) else str(scene): int(where[row]), "row": row},
                      arrow_m, jpeg_quality, masks)
            out.frames += 1
            out.images += rgb is not None
            out.depth += dm is not None
            out.masks += labels is not None
            if fv.model is not None and np.isfinite(fv.model).all() and np.isfinite(fv.gaze).all():
                out.model_error.append(float(angular_error_deg(fv.model, fv.gaze)))
        if bar is not None:
            bar.update(len(chunk))
    if bar is not None:
        bar.close()
    if refs and len(refs) < len(ids):
        out.missing["frames the dataset no longer has"] += len(ids) - len(refs)
    out.missing.update(stages.missing)
    return out


# --- command line -------------------------------------------------------------------------------------------

@click.command("view")
@click.argument("store", type=click.Path())
@click.option("--frame", "frames", multiple=True, help="A frame id (repeatable).")
@click.option("--session", "sessions", multiple=True,
              help="A session, as frames/scene names it (repeatable; `ga3ce-prep info` lists them).")
@click.option("--split", "splits", multiple=True, type=click.Choice(["train", "val", "test"]),
              help="A split (repeatable). Frame ids, sessions and splits given each narrow the choice; none: "
                   "every frame.")
@click.option("--checkpoint", "-c", type=click.Path(dir_okay=False, exists=True), default=None,
              help="A checkpoint of `ga3ce-prep train` (best.pt): its gaze g beside the truth's, and the angular "
                   "error per frame as a series.")
@click.option("--data", type=click.Path(file_okay=False), default=None,
              help="Dataset root, if it moved since the store was made (for the images and depth).")
@click.option("--points", "budget", type=click.IntRange(min=0), default=POINT_BUDGET, show_default=True,
              help="Most back-projected depth points per frame (a regular pixel grid).")
@click.option("--masks", is_flag=True,
              help="Also show the objects' masks, found again by the store's objects backend (the cache keeps "
                   "only their positions): as long as the objects stage took, a frame (segment-everything: seconds).")
@click.option("--no-depth", is_flag=True, help="Leave out the completed depth and its points (no depth backend runs).")
@click.option("--jpeg-quality", type=click.IntRange(1, 100), default=JPEG_QUALITY, show_default=True,
              help="The images' JPEG quality in the recording.")
@click.option("--arrow", "arrow_m", type=float, default=ARROW_M, show_default=True,
              help="Length of the gaze arrows, metres.")
@click.option("--verify/--no-verify", default=True, show_default=True,
              help="First check the store against its integrity record (SHA-256 of every file).")
@click.option("--save", type=click.Path(dir_okay=False), default=None,
              help="Write the recording to this .rrd file (open it with `rerun FILE.rrd`).")
@click.option("--spawn", is_flag=True, help="Open Rerun's native viewer (needs a display) and stream to it.")
@click.option("--serve", is_flag=True,
              help="Serve Rerun's web viewer on --web-port and keep serving until Ctrl-C (up to 1 GiB of the "
                   "recording in memory, Rerun's default: --save for more).")
@click.option("--web-port", type=int, default=9090, show_default=True, help="The web viewer's port (--serve).")
@click.option("--grpc-port", type=int, default=9876, show_default=True,
              help="The port the web viewer reads the recording from (--serve).")
def view(store, frames, sessions, splits, checkpoint, data, budget, masks, no_depth, jpeg_quality, arrow_m, verify,
         save, spawn, serve, web_port, grpc_port) -> None:
    """Show a store's 3D context over time in Rerun: per frame the image with its head box, the completed
    depth and its points, the objects, t_object, the pose, v, the truth's gaze and a checkpoint's g.

    Each session is a timeline (frames/scene's name; `row`: the store's rows). Metres, the store's camera
    frame (x right, y down, z forward). Needs the extra [view]: pip install 'ga3ce-prep[view]'.

    \b
    Example: ga3ce-prep view out/synthetic.zarr --session test/scene1 -c out/runs/x/best.pt --save s.rrd
    """
    sink = Sink(save, spawn, serve, web_port, grpc_port)
    sink.check()
    import_rerun()
    st = open_lazy(store, verify=verify)
    rows = select_rows(st, frames, sessions, splits)
    t = time.perf_counter()
    rr, rec, url = sink.open(f"{Path(st.path).name}:{','.join(sessions or splits) or 'all'}")
    done = record_store(rr, rec, st, rows, data=data, checkpoint=checkpoint, depth=not no_depth, masks=masks,
                        budget=budget, arrow_m=arrow_m, jpeg_quality=jpeg_quality, progress=len(rows) > BLOCK)
    if save is None:
        click.echo(f"logged {done.line()}")
    sink.close(rec, url)
    if save is not None:
        size = Path(save).stat().st_size / 1e6
        click.echo(f"wrote {save} ({size:.1f} MB, {time.perf_counter() - t:.1f} s): {done.line()}")


def record_frame(sink: Sink, store: ContextStore, name: str, rgb: np.ndarray | None = None,
                 depth: np.ndarray | None = None, model: np.ndarray | None = None, budget: int = POINT_BUDGET) -> None:
    """One frame (store's frame 0, e.g. `predict --view`'s photo) with its image, depth and a model's g,
    into `sink`, on the timeline `photo` (0)."""
    rr, rec, url = sink.open(name)
    log_frame(rr, rec, frame_view(store, 0, rgb, depth, None, model, budget), {"photo": 0})
    sink.close(rec, url)
