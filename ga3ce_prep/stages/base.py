"""The stage contract: what each stage returns per frame, and the backend base classes.

A stage is a pure function of one frame and its upstream outputs (docs/pipeline.md). Each stage
has named backends, chosen in the pipeline file; a backend is a small class with one per-frame
method and its parameters as a typed dataclass:

    input    CheckInputBackend.check_frame(frame)              -> None   (raises FrameError)
    depth    DepthBackend.depth(frame)                        -> DepthMap
    objects  ObjectsBackend.objects(frame, depth: DepthMap)   -> FrameObjects
    head     HeadBackend.head(frame, depth: DepthMap)         -> (3,) float32 t_object, metres
                                                                 (head/depth: Sourced, and it reads the pose)
    pose     PoseBackend.pose(frame)                          -> (30, 3) float32 smpl+head_30, metres
    view     ViewBackend.view(frame)                          -> (3,) float32 unit v, camera frame

A backend may read more upstream stages (`needs`: `view(frame, pose=...)`) and a temporal window
of the adapter's frames (`window = 7`: `view(frame, window=Window)`, see `Backend.window`).

A per-frame problem raises FrameError (or any exception): the pipeline turns it into a failure
record (stage, error class, message) and goes on. Units: metres; camera frame x right, y down,
z forward.

Adding a backend (e.g. `depth/onnx`):
1. In the stage's module (or a module of its own), a class with `name`, a nested `Params`
   dataclass (`@dataclass(frozen=True, kw_only=True)`, one field per line: type, default,
   `param(..., minimum=...)` for JSON Schema limits, `param(file="model", hint=...)` for model
   files, and its unit and reason in a trailing comment; inherit shared groups such as
   `RuntimeParams` or `TruthParams`), and its per-frame method reading `self.p.<name>`.
2. Register "stage/name" -> "module:Class" in `ga3ce_prep.stages.BACKENDS`.
3. `make schema` regenerates ga3ce_prep/schemas/pipeline.schema.json from the dataclasses (a test fails
   until it is current). The dataclass is the one home of each parameter and its default: the
   loader fills defaults in from it and the backend reads `self.p` only.

Cache versions, one rule. `version` is a counter in the cache key of the backend's stage: raise it
by one whenever the backend's outputs for the same written parameters change (a changed default
included), and say why on its line, one entry per raise, so the line is the backend's changelog:

    version = "3"  # 2: units, and the size check; 3: depth-refined placement

A layer that only some settings switch on (objects/mobilesam's `reuse`) keeps a counter of its own
in the same form, appended to the key while it is on (`cache_version`: "1+reuse3"), so changing
the layer moves only its runs' keys. A test reads every declaration and fails on a missing entry.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..frames import DepthMap, FrameRef
from ..params import from_dict


@dataclass
class FrameObjects:
    """One frame's P_object: per-mask median 3D points.

    xyz: (M, 3) float32 metres; area: (M,) int32 mask pixels; score: (M,) float32 (predicted IoU,
    or for weight-free backends the fraction of the mask backed by measured depth);
    n_dropped: masks dropped for having too few valid depth points.
    """

    xyz: np.ndarray
    area: np.ndarray
    score: np.ndarray
    n_dropped: int = 0

    @staticmethod
    def empty() -> FrameObjects:
        return FrameObjects(np.zeros((0, 3), np.float32), np.zeros(0, np.int32), np.zeros(0, np.float32), 0)


@dataclass
class BackendContext:
    """What a backend may know about the run besides its parameters."""

    data_root: Path


@dataclass
class Sourced:
    """A per-frame result and the name of the way it came about (one of its backend's `sources`),
    e.g. a view prior from the face mesh or, when no face is visible, from the pose."""

    value: Any
    source: str


@dataclass(frozen=True, kw_only=True)
class NoParams:
    """The parameters of a backend that has none."""


class Backend:
    """Base of every backend. `self.p` is an instance of the backend's `Params` dataclass; file
    parameters are already resolved to absolute paths by the pipeline loader."""

    stage: ClassVar[str] = ""
    name: ClassVar[str] = ""
    version: ClassVar[str] = "1"  # the cache-version rule: module docstring
    Params: ClassVar[type] = NoParams
    # Upstream stages the per-frame method also reads, passed by keyword (`view(frame, pose=...)`):
    # allowed ones are stages.OPTIONAL_UPSTREAM. A failed upstream frame passes NaN.
    needs: ClassVar[tuple[str, ...]] = ()
    # The ways a frame's result can come about; when set, the per-frame method returns `Sourced`
    # and the store records the source of every frame (frames/<stage>_source).
    sources: ClassVar[tuple[str, ...]] = ()
    # A temporal window (odd number of frames, 0: none): the per-frame method also gets
    # `window=Window` (frames.Window), the frame's neighbours in its sequence by consecutive raw
    # frame numbers, None where a number is missing; FrameRefs only, the backend reads their pixels
    # itself. The pipeline finds them across shards and hashes them into the stage's cache key.
    window: ClassVar[int] = 0

    @classmethod
    def cache_version(cls, p: Any) -> str:
        """The version in the cache key of this backend run with parameters `p` (a `Params`):
        `version`, plus the counter of each layer that `p` switches on (module docstring)."""
        return cls.version

    def __init__(self, params: Any, ctx: BackendContext):
        """params: this backend's `Params` (what a loaded pipeline's StageConfig holds), or a mapping
        of them (checked and converted here, each error naming its `stages.<stage>.params` key)."""
        typed = isinstance(params, self.Params)
        self.p: Any = params if typed else from_dict(self.Params, params, f"stages.{self.stage}.params")
        self.ctx = ctx

    def start_shard(self) -> None:
        """Called in the thread about to run this backend on one shard's frames (in the adapter's
        order). A backend that carries state from frame to frame (objects/mobilesam's `reuse:
        sequence`) starts afresh here, so that a shard's results depend on its frames only, not on
        what the process ran before. Default: nothing."""

    def batch_size(self) -> int:
        """Frames per `batch` call; 1 (the default): the backend has no batched method and runs
        frame by frame."""
        return 1

    def batch(self, frames: list[FrameRef], *args: Any, **needs: Any) -> list[Any]:
        """The per-frame method on several frames in one call, for a backend whose network runs them
        together: one result or Exception per frame, in order; each of `needs` as a list, one value
        per frame. The pose and view tasks call it on up to batch_size() frames of a shard at a time
        when batch_size() > 1, so a backend that returns more than 1 overrides it (naming the needs
        it reads: `*args, **needs` leaves its signature free)."""
        raise NotImplementedError(f"{type(self).__name__}: batch_size() is {self.batch_size()}, but it has no "
                                  f"batch method")

    def registry_keys(self) -> tuple[str, ...]:
        """The registry models (`weights.registry` keys) this backend runs: `check()` verifies their
        SHA-256 and `provenance()` records it. Default: none."""
        return ()

    def side_files(self) -> dict[str, Path]:
        """Model files the backend reads that are not file parameters (a list beside its model), by
        what they are; the run checks that they exist before any work, and `ga3ce-prep models check`
        lists them. Default: none."""
        return {}

    def check(self) -> None:
        """Validate once before any work (files readable, keys present); raise ConfigError or
        ModelFileError naming the pipeline key and the fix. Default: the registry models are
        fetched and have their pinned SHA-256."""
        if self.registry_keys():
            from ..weights.registry import require

            for key in self.registry_keys():
                require(key, f"stages.{self.stage}.backend {self.name}")

    def warm(self) -> None:
        """Import heavy libraries / load models ahead of the first frame (dask workers call it once
        before the graph runs). Default: nothing."""

    def provenance(self) -> dict[str, Any]:
        """What the backend adds to its stage's store provenance (run on the driver, after check()):
        "models" {path: SHA-256} of model files that are not file parameters (e.g. the registry's),
        and anything it derives from its files (objects/mobilesam's "mask_mode"). Default: the
        registry models' pinned SHA-256."""
        if not self.registry_keys():
            return {}
        from ..weights.registry import MODELS, file_path

        return {"models": {str(file_path(k)): MODELS[k][1].sha256 for k in self.registry_keys()}}


class ProcessEstimator:
    """Mixin for a backend whose model runs in a native session (ONNX Runtime, LiteRT): one
    estimator per process, built by `build_estimator()` on first use or by `warm()`, and never
    pickled (dask workers rebuild theirs)."""

    def build_estimator(self) -> Any:
        raise NotImplementedError

    def estimator(self) -> Any:
        """The process's estimator (built once, on first use)."""
        if getattr(self, "_estimator", None) is None:
            self._estimator = self.build_estimator()
        return self._estimator

    def warm(self) -> None:
        self.estimator()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.pop("_estimator", None)
        return state


class CheckInputBackend(Backend):
    stage = "input"

    def check_frame(self, frame: FrameRef) -> None:
        raise NotImplementedError


class DepthBackend(Backend):
    stage = "depth"

    def depth(self, frame: FrameRef) -> DepthMap:
        raise NotImplementedError


class ObjectsBackend(Backend):
    stage = "objects"

    def objects(self, frame: FrameRef, depth: DepthMap) -> FrameObjects:
        raise NotImplementedError


# The per-frame methods of the stages whose backends may read more (`needs`, by keyword; `window`):
# `*args, **needs` leaves each backend's signature free to name what it reads (stages.call_backend
# passes exactly that); `Sourced` when the backend has `sources`.
class HeadBackend(Backend):
    stage = "head"

    def head(self, frame: FrameRef, depth: DepthMap, *args: Any, **needs: Any) -> np.ndarray | Sourced:
        raise NotImplementedError


class PoseBackend(Backend):
    stage = "pose"

    def pose(self, frame: FrameRef, *args: Any, **needs: Any) -> np.ndarray | Sourced:
        raise NotImplementedError


class ViewBackend(Backend):
    stage = "view"

    def view(self, frame: FrameRef, *args: Any, **needs: Any) -> np.ndarray | Sourced:
        raise NotImplementedError
