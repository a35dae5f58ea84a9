"""What an evaluation returns (train/evaluate.py `evaluate`), typed: `EvalResult` for one split,
`MethodMetrics` for each method scored on it, `GroupMetrics` for a subset of its frames (front,
back, a scene). Angles in degrees; NaN where a mean has no frame.

Each has `to_json()`: the JSON form `ga3ce-prep eval --json` writes, with the keys, and their
order, of the dict `evaluate` returned before these types, so readers of those files need no
change. In Python, read the attributes: `r.methods["model"].mae3d`,
`r.methods["view_prior"].per_scene["kitchen"].n`, `r.frames.scored`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .frameset import ScoredFrames


@dataclass(frozen=True)
class GroupMetrics:
    """One method on a group of frames (front, back, or a scene): n frames, 3D and 2D MAE."""

    n: int
    mae3d: float
    mae2d: float

    def to_json(self) -> dict[str, Any]:
        return {"n": self.n, "mae3d": self.mae3d, "mae2d": self.mae2d}


@dataclass(frozen=True)
class MethodMetrics:
    """One method on a split's scored frames (train/metrics.py `summarize`): n, 3D MAE, 2D MAE
    (GAFA style), median 3D error, front / back (GAFA's split of the frames), per scene (in the
    evaluation's column order), and at_object / elsewhere when the frames' gaze targets are known."""

    n: int
    mae3d: float
    mae2d: float
    median3d: float
    front: GroupMetrics
    back: GroupMetrics
    per_scene: dict[str, GroupMetrics] = field(default_factory=dict)
    at_object: GroupMetrics | None = None    # frames whose gaze target is at a stored object (evaluate.py)
    elsewhere: GroupMetrics | None = None    # the others: mid-air targets, and objects the store missed

    def to_json(self) -> dict[str, Any]:
        out = {"n": self.n, "mae3d": self.mae3d, "mae2d": self.mae2d, "median3d": self.median3d,
               "front": self.front.to_json(), "back": self.back.to_json(),
               "per_scene": {name: g.to_json() for name, g in self.per_scene.items()}}
        if self.at_object is not None and self.elsewhere is not None:
            out |= {"at_object": self.at_object.to_json(), "elsewhere": self.elsewhere.to_json()}
        return out


@dataclass
class EvalResult:
    """A checkpoint and the baselines on one split of a store.

    store, split, checkpoint (path), epoch (1-based), dataset (its profile's name), config (the
    checkpoint's training config). labels {method key: its name in tables}: "model" first, then the
    compared checkpoints, then the baselines (evaluate.BASELINES). methods {key: MethodMetrics},
    every key of labels. frames: which frames were scored and why the others were not
    (frameset.ScoredFrames); n_frames scored. head_sources {source: scored frames},
    head_fallback_frames (scored frames whose head position came from a fallback),
    head_from_pose_frames, snapped_frames, snap_cone_deg (the snap baseline's cone).
    scene_columns: the per-scene table's columns; paper_rows {label: {column: (3D, 2D)}} (GAFA's
    windows only). beats {method key: the model's 3D MAE is below it}; ratio_to_prior: the model's
    3D MAE / the view prior's. no_objects_checkpoint, compared_checkpoints {key: path}: the other
    checkpoints scored. gfm: GFIE's Table 1 columns (train/gfm.py `evaluate_gfm`) when asked;
    attention: the model's weight on the null token, on the objects and on the gazed object
    (evaluate.object_attention), None for a model without objects; cdf_png: the CDF plot written;
    json: the JSON file written (neither in the JSON itself unless written before it: cdf_png is,
    json is not).
    """

    store: str
    split: str
    checkpoint: str
    epoch: int
    no_objects_checkpoint: str | None
    compared_checkpoints: dict[str, str]
    labels: dict[str, str]
    config: dict[str, Any]
    dataset: str
    n_frames: int
    frames: ScoredFrames
    head_sources: dict[str, int]
    head_fallback_frames: int
    snap_cone_deg: float
    head_from_pose_frames: int
    snapped_frames: int
    methods: dict[str, MethodMetrics]
    scene_columns: list[str]
    paper_rows: dict[str, dict[str, Any]]
    beats: dict[str, bool]
    ratio_to_prior: float
    attention: dict[str, float] | None = None   # where the model's weight goes (evaluate.object_attention)
    gfm: dict[str, Any] | None = None
    cdf_png: str | None = None
    json: str | None = None

    @property
    def model(self) -> MethodMetrics:
        """The checkpoint's own metrics (methods["model"])."""
        return self.methods["model"]

    def to_json(self) -> dict[str, Any]:
        """The JSON form (`eval --json`): every field but `json`, in this order; attention, gfm
        and cdf_png only when set. Values as they are (numpy scalars included: write with default=float)."""
        out: dict[str, Any] = {
            "store": self.store, "split": self.split, "checkpoint": self.checkpoint, "epoch": self.epoch,
            "no_objects_checkpoint": self.no_objects_checkpoint, "compared_checkpoints": self.compared_checkpoints,
            "labels": self.labels, "config": self.config, "dataset": self.dataset, "n_frames": self.n_frames,
            "frames": self.frames.as_dict(), "head_sources": self.head_sources,
            "head_fallback_frames": self.head_fallback_frames, "snap_cone_deg": self.snap_cone_deg,
            "head_from_pose_frames": self.head_from_pose_frames, "snapped_frames": self.snapped_frames,
            "methods": {key: m.to_json() for key, m in self.methods.items()}, "scene_columns": self.scene_columns,
            "paper_rows": self.paper_rows, "beats": self.beats, "ratio_to_prior": self.ratio_to_prior,
        }
        if self.attention is not None:
            out["attention"] = self.attention
        if self.gfm is not None:
            out["gfm"] = self.gfm
        if self.cdf_png is not None:
            out["cdf_png"] = self.cdf_png
        return out
