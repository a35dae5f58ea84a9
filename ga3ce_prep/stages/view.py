"""The view stage: the view prior v, a unit camera-frame vector (an appearance network's gaze
estimate). A failure drops the frame: GA3CE has nothing to refine without v.

Backends: `precomputed` (stages/precomputed.py layout), `oracle` (the synthetic truth gaze,
optionally pulled toward the head direction, plus noise calibrated to a mean angular error:
stages/oracle_noise.py `noisy_view`; the paper's robustness protocol uses 20, 30 and 40 degrees),
`oracle-turn` (the same, its mean error growing as the head turns away from the camera),
`facemesh` (the head direction from MediaPipe's face mesh on the registry's models:
estimators/view/facemesh.py; a proxy for the paper's appearance network, not an eye-gaze estimate),
`gfie` (GFIE's head-image gaze network from its released checkpoint: estimators/view/gfie_head.py),
`onnx` (any head-crop network exported to ONNX, GFIE's crop recipe by default:
estimators/view/head_onnx.py) and `gafa` (GAFA's 7-frame head-and-body gaze network on your ONNX
export: estimators/view/gafa.py; a windowed backend, `Backend.window`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..datasets.gafa import WINDOW
from ..errors import ConfigError, FrameError
from ..estimators.runtime.onnx_runtime import RuntimeParams
from ..estimators.view.facemesh import FaceMeshOptions
from ..estimators.view.head_onnx import HeadOnnxOptions
from ..frames import FrameRef, Window, load_rgb
from ..geometry import normalize, unit_direction
from ..params import param
from ..skeleton import head_direction_from_pose
from .base import ProcessEstimator, Sourced, ViewBackend
from .oracle_noise import frame_rng, noisy_view
from .precomputed import precomputed_table
from .truth import TruthParams, check_truth_file, truth_frame


class PrecomputedView(ViewBackend):
    """v from `file` (HDF5/npz: frame_id (N,), view (N, 3)); re-normalised."""

    name = "precomputed"

    @dataclass(frozen=True, kw_only=True)
    class Params:
        file: Path = param(
            # HDF5/npz: frame_id (N,) str, view (N, 3)
            file="data", hint="write it with the layout in docs/pipeline.md (frame_id, view)")

    def _table(self):
        return precomputed_table(self.p.file, "view", (3,), "stages.view.params.file")

    def check(self) -> None:
        self._table()

    def view(self, frame: FrameRef) -> np.ndarray:
        return unit_direction(self._table().get(frame.id), f"view of frame {frame.id} in {self.p.file}")


class OracleView(ViewBackend):
    """Truth gaze, pulled toward the head direction by head_weight, plus noise with mean angular
    error mean_error_deg against the truth gaze; seeded by (seed, frame id)."""

    name = "oracle"

    @dataclass(frozen=True, kw_only=True)
    class Params(TruthParams):
        seed: int = 0  # noise seed (combined with the frame id)
        mean_error_deg: float = param(20.0, minimum=0, maximum=90)  # mean angle between v and the truth gaze, degrees
        head_weight: float = param(
            # pull of v toward the truth head direction before the noise (0: none, 1: centred on it)
            0.0, minimum=0, maximum=1)

    def check(self) -> None:
        check_truth_file(self.p.truth)

    def view(self, frame: FrameRef) -> np.ndarray:
        p = self.p
        rec, gaze = truth_gaze(p.truth, frame)
        head = getattr(rec, "head_dir", None)
        return noisy_view(gaze, None if head is None else np.asarray(head, np.float64),
                          frame_rng(p.seed, "view/oracle", frame.id), p.mean_error_deg, p.head_weight)


def truth_gaze(truth: Path, frame: FrameRef) -> tuple[Any, np.ndarray]:
    """The frame's truth record and its unit gaze (3,); FrameError when the gaze is no direction."""
    rec = truth_frame(truth, frame.id, maps=False)
    gaze = np.asarray(rec.gaze, np.float64)
    if not np.all(np.isfinite(gaze)) or np.linalg.norm(gaze) < 1e-9:
        raise FrameError(f"truth gaze of frame {frame.id} is not a direction")
    return rec, normalize(gaze)


def turn_from_camera(head_dir: np.ndarray, head_center: np.ndarray) -> float:
    """How far the head turns away from the camera, degrees: 0 facing it, 180 the back of the head
    to it. head_dir: (3,) unit facing direction; head_center: (3,) metres, camera frame."""
    to_camera = -normalize(np.asarray(head_center, np.float64))
    return float(np.degrees(np.arccos(np.clip(np.dot(normalize(np.asarray(head_dir, np.float64)), to_camera),
                                              -1.0, 1.0))))


class TurnOracleView(ViewBackend):
    """`oracle` whose mean error grows as the head turns away from the camera, as an appearance
    network's does (it sees less of the eyes, then none): front_error_deg facing the camera,
    back_error_deg with the back of the head to it, in between by (1 - cos turn) / 2."""

    name = "oracle-turn"

    @dataclass(frozen=True, kw_only=True)
    class Params(TruthParams):
        seed: int = 0  # noise seed (combined with the frame id)
        front_error_deg: float = param(
            # mean angle between v and the truth gaze with the face toward the camera, degrees
            12.8, minimum=0, maximum=90)
        back_error_deg: float = param(
            # the same with the back of the head toward it; the defaults (twice the front's) put the
            # mean over the demo's world at 19.4, the paper's appearance-only v on GFIE (its Table 4)
            25.6, minimum=0, maximum=90)
        head_weight: float = param(
            # pull of v toward the truth head direction before the noise (0: none, 1: centred on it)
            0.0, minimum=0, maximum=1)

    def check(self) -> None:
        check_truth_file(self.p.truth)

    def mean_error_deg(self, head_dir: np.ndarray, head_center: np.ndarray) -> float:
        """The frame's mean error, degrees, from how far its head turns from the camera."""
        w = (1.0 - np.cos(np.radians(turn_from_camera(head_dir, head_center)))) / 2.0
        return float(self.p.front_error_deg + w * (self.p.back_error_deg - self.p.front_error_deg))

    def view(self, frame: FrameRef) -> np.ndarray:
        p = self.p
        rec, gaze = truth_gaze(p.truth, frame)
        head = np.asarray(rec.head_dir, np.float64)
        return noisy_view(gaze, head, frame_rng(p.seed, "view/oracle", frame.id),
                          self.mean_error_deg(head, rec.head_center), p.head_weight)


class FaceMeshView(ProcessEstimator, ViewBackend):
    """v = the head direction of the face in the head box: BlazeFace, the face mesh, then the
    facing direction of its landmarks, perspective-corrected with K (estimators/view/facemesh.py).
    The models come from the registry cache (`ga3ce-prep models fetch`), SHA-256 checked.

    Where no face is visible (the subject faces away, an occluded or tiny face), v is the head
    direction of the pose stage's keypoints (`skeleton.head_direction_from_pose`: ears to nose),
    and the store records which source gave each frame's v (frames/view_source: "face" or
    "pose"). With neither, the frame fails with FrameError (and is dropped)."""

    name = "facemesh"
    needs = ("pose",)
    sources = ("face", "pose")

    @dataclass(frozen=True, kw_only=True)
    class Params(FaceMeshOptions):
        pose_fallback: bool = (
            # no face visible: v = the pose's head direction (ears to nose); false: the frame fails
            True)

    def registry_keys(self) -> tuple[str, ...]:
        return "face_detection", "face_landmark"  # BlazeFace short-range, the face mesh

    def build_estimator(self):
        from ..estimators.view.facemesh import FaceMeshEstimator
        from ..weights.registry import model_path

        return FaceMeshEstimator(*(model_path(k) for k in self.registry_keys()), self.p)

    def view(self, frame: FrameRef, pose: np.ndarray) -> Sourced:
        """pose: (30, 3) the pose stage's output for the frame (NaN where it failed)."""
        try:
            res = self.estimator().estimate(load_rgb(frame.image_path), frame.head_box, frame.K)
            return Sourced(res.direction.astype(np.float32), "face")
        except FrameError as no_face:
            if not self.p.pose_fallback:
                raise
            d, ok = head_direction_from_pose(np.asarray(pose, np.float64)[None], np.full((1, 3), np.nan))
            if not ok[0]:
                raise FrameError(f"{no_face}; and the pose has no nose and ears to fall back on") from None
            return Sourced(d[0].astype(np.float32), "pose")


GFIE_HINT = ("GFIE's released checkpoint (gfiemodel.pt.tar, linked from the README of github.com/nkuhzx/GFIE); "
             "docs/models/view.md, GFIE's head network")
ONNX_HINT = ("export your head-crop network to ONNX (docs/models/view.md, Head-crop ONNX networks; "
             "GFIE's: ga3ce-prep export-gfie-view)")


class GFIEView(ProcessEstimator, ViewBackend):
    """v = GFIE's head-image gaze network (its EGD module) on GFIE's head crop of the frame's head
    box, in torch, with the weights of GFIE's released checkpoint (estimators/view/gfie_head.py)."""

    name = "gfie"

    @dataclass(frozen=True, kw_only=True)
    class Params:
        checkpoint: Path = param(
            # GFIE's checkpoint (a dict with the whole GFIENet's
            # state_dict); only its head network, egd_module.*, is read
            file="model", hint=GFIE_HINT)
        device: Literal["cpu", "cuda"] = "cpu"  # torch device of the network
        threads: int = param(1, minimum=1)  # torch intra-op threads per process
        batch_size: int = param(
            # heads per forward pass (a shard's frames in chunks): on a GPU
            # raise it; on a CPU 8 already amortises the per-call overhead
            8, minimum=1)

    def batch_size(self) -> int:
        return self.p.batch_size

    def check(self) -> None:
        """Before any work: the device exists and the checkpoint holds GFIE's head network."""
        import torch

        from ..estimators.view.gfie_head import load_gfie_head

        if self.p.device == "cuda" and not torch.cuda.is_available():
            raise ConfigError("stages.view.params.device: cuda, but this torch build sees no CUDA device (use cpu)")
        load_gfie_head(self.p.checkpoint)

    def build_estimator(self):
        from ..estimators.view.gfie_head import GFIEHeadEstimator

        return GFIEHeadEstimator(self.p.checkpoint, self.p.device, self.p.threads)

    def view(self, frame: FrameRef) -> np.ndarray:
        return self.estimator().estimate(load_rgb(frame.image_path), frame.head_box)

    def batch(self, frames: list[FrameRef]) -> list[np.ndarray | Exception]:
        """v for several frames in one forward pass; a frame whose image cannot be read gets its
        FrameError."""
        from ..estimators.view.head_crop import CropParams, head_input

        inputs: list[np.ndarray] = []
        out: list[FrameError | None] = []
        for f in frames:
            try:
                inputs.append(head_input(load_rgb(f.image_path), f.head_box, CropParams()))
                out.append(None)
            except FrameError as e:
                out.append(e)
        vs = iter(self.estimator().estimate_batch(inputs) if inputs else [])
        return [next(vs) if o is None else o for o in out]


class OnnxView(ProcessEstimator, ViewBackend):
    """v = a head-crop network exported to ONNX: the crop recipe, the output and its axes as
    parameters (GFIE's crop and our camera frame by default), normalised (estimators/view/head_onnx.py)."""

    name = "onnx"

    @dataclass(frozen=True, kw_only=True)
    class Params(HeadOnnxOptions):
        model: Path = param(
            file="model", hint=ONNX_HINT)  # the ONNX file: one float32 image input, a (1, 3) direction output

    def check(self) -> None:
        """Before any work: the axes, the providers and the file's interface."""
        self.build_estimator()

    def build_estimator(self):
        from ..estimators.view.head_onnx import HeadOnnxEstimator

        return HeadOnnxEstimator(self.p.model, self.p)

    def view(self, frame: FrameRef) -> np.ndarray:
        return self.estimator().estimate(load_rgb(frame.image_path), frame.head_box)


class GafaView(ProcessEstimator, ViewBackend):
    """v = the gaze that GAFA's GazeNet gives the centre frame of the 7-frame window centred on the
    frame (estimators/view/gafa.py builds its inputs as GAFA's preprocessing and loader do).

    GAFA's contiguity rule (`dataloader/gafa.py`): a window is 7 consecutive raw frame numbers of
    the camera sequence, all present. A frame within 3 numbers of a gap or of either end of its
    sequence has no such window and fails with FrameError (the frame is dropped). Needs the GAFA
    adapter's BODY_25 keypoints (`FrameRef.keypoints_2d`)."""

    name = "gafa"
    window = WINDOW

    @dataclass(frozen=True, kw_only=True)
    class Params(RuntimeParams):
        model: Path = param(
            # ONNX of GAFA's GazeNet (7 frames): image, head_mask, body_dv -> gaze
            file="model",
            hint="export GAFA's GazeNet with scripts/export_gafa_view.py (docs/models/view.md, GAFA's view network)")

    def check(self) -> None:
        """Before any work: the providers and the file's interface (GazeNet's inputs and output)."""
        self.estimator()

    def build_estimator(self):
        from ..estimators.view.gafa import GafaViewEstimator

        return GafaViewEstimator(self.p.model, self.p)

    def view(self, frame: FrameRef, window: Window) -> np.ndarray:
        from ..estimators.view.gafa import body_velocity, head_masks, normalize_crops, preprocessed_boxes

        if not window.complete:
            missing = [frame.index + k - WINDOW // 2 for k, f in enumerate(window.frames) if f is None]
            raise FrameError(f"no {WINDOW}-frame window around frame {frame.index} of {frame.sequence or frame.id}: "
                             f"raw frame(s) {missing} missing (GAFA uses only runs of {WINDOW} consecutive frames)")
        frames = [f for f in window.frames if f is not None]  # all of them: the window is complete
        seq = [window.previous, *frames]
        keypoints = [f.keypoints_2d for f in seq if f.keypoints_2d is not None]
        if len(keypoints) < len(seq):
            raise FrameError(f"view/gafa needs OpenPose BODY_25 keypoints (the gafa adapter); a frame of "
                             f"the window around {frame.id} has none")
        head, body = preprocessed_boxes(np.stack(keypoints))
        if not (np.isfinite(body).all() and np.isfinite(head).all() and (body[:, 2:] > 0).all()):
            raise FrameError(f"a frame of the window around {frame.id} has no head or body box from its keypoints")
        est = self.estimator()
        crops = np.stack([est.crop(f.image_path, b) for f, b in zip(frames, body[1:])])
        gaze = est.predict(normalize_crops(crops), head_masks(head[1:], body[1:]), body_velocity(body))
        what = f"GAFA's network's output for frame {frame.id}"
        return unit_direction(np.asarray(gaze[WINDOW // 2], np.float64), what)
