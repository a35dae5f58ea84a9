"""The preprocessing stages and the registry of their backends (docs/pipeline.md).

Stages, in dependency order, and what a failure of each does to the frame (docs/pipeline.md):

    input    frame checks (finite K, readable image)   failure drops the frame
    depth    depth map + raw validity                   failure drops the frame (no head position)
    objects  P_object: per-mask median 3D points         failure degrades it: zero objects
    head     t_object (its fallbacks read the pose)      failure drops the frame
    pose     P_pose (30, 3)                              failure degrades it: NaN pose
    view     the view prior v                            failure drops the frame

A backend may read more upstream stages than its stage's own (`Backend.needs`, within
`OPTIONAL_UPSTREAM`): a pose estimator refining with the depth map, a view estimator falling back
to the pose when no face is visible, the head position falling back to the pose's head when the
head has no measured depth. `upstream_of` gives a pipeline's effective dependencies.

Backends are imported only when a pipeline names them (Open3D, h5py stay unloaded otherwise).
"""
from __future__ import annotations

import importlib
from typing import Any

from ..errors import ConfigError
from ..frames import FrameRef, Window, frame_windows
from .base import Backend

STAGES: tuple[str, ...] = ("input", "depth", "objects", "head", "pose", "view")
UPSTREAM: dict[str, tuple[str, ...]] = {
    "input": (), "depth": ("input",), "objects": ("depth",), "head": ("depth",),
    "pose": ("input",), "view": ("input",),
}
# what a backend may add to its stage's upstream (Backend.needs)
OPTIONAL_UPSTREAM: dict[str, tuple[str, ...]] = {"pose": ("depth",), "view": ("pose",), "head": ("pose",)}
# True: a failure of this stage drops the frame from the store; False: the frame is kept, degraded.
DROPS_FRAME: dict[str, bool] = {
    "input": True, "depth": True, "objects": False, "head": True, "pose": False, "view": True,
}


BACKENDS: dict[str, str] = {
    "input/check": "ga3ce_prep.stages.input:CheckInput",
    "depth/sensor": "ga3ce_prep.stages.depth:SensorDepth",
    "depth/oracle": "ga3ce_prep.stages.depth:OracleDepth",
    "depth/fastdepth": "ga3ce_prep.stages.depth:FastDepth",
    "depth/onnx": "ga3ce_prep.stages.depth:OnnxDepth",
    "depth/precomputed": "ga3ce_prep.stages.depth:PrecomputedDepth",
    "objects/geometric": "ga3ce_prep.stages.objects:GeometricObjects",
    "objects/oracle": "ga3ce_prep.stages.objects:OracleObjects",
    "objects/mobilesam": "ga3ce_prep.stages.objects_mobilesam:MobileSAMObjects",
    "head/depth": "ga3ce_prep.stages.head:DepthHead",
    "pose/precomputed": "ga3ce_prep.stages.pose:PrecomputedPose",
    "pose/oracle": "ga3ce_prep.stages.pose:OraclePose",
    "pose/oracle-articulated": "ga3ce_prep.stages.pose:ArticulatedOraclePose",
    "pose/blazepose": "ga3ce_prep.stages.pose:BlazePose",
    "pose/onnx": "ga3ce_prep.stages.pose_crop:OnnxPose",
    "pose/torchscript": "ga3ce_prep.stages.pose_crop:TorchScriptPose",
    "view/precomputed": "ga3ce_prep.stages.view:PrecomputedView",
    "view/oracle": "ga3ce_prep.stages.view:OracleView",
    "view/oracle-turn": "ga3ce_prep.stages.view:TurnOracleView",
    "view/facemesh": "ga3ce_prep.stages.view:FaceMeshView",
    "view/gfie": "ga3ce_prep.stages.view:GFIEView",
    "view/onnx": "ga3ce_prep.stages.view:OnnxView",
    "view/gafa": "ga3ce_prep.stages.view:GafaView",
}


def backend_class(stage: str, name: str) -> type[Backend]:
    """The class registered as "stage/name"; ConfigError for an unknown one."""
    entry = BACKENDS.get(f"{stage}/{name}")
    if entry is None:
        known = sorted(k.split("/")[1] for k in BACKENDS if k.startswith(stage + "/"))
        raise ConfigError(f"stages.{stage}.backend: unknown backend {name!r}; known: {', '.join(known)}")
    module, cls = entry.split(":")
    return getattr(importlib.import_module(module), cls)


def upstream_of(backends: dict[str, str]) -> dict[str, tuple[str, ...]]:
    """Each stage's effective upstream for the chosen backends (stage -> backend name): its own
    plus what the backend `needs`. ConfigError for a need outside OPTIONAL_UPSTREAM."""
    up = {}
    for stage in STAGES:
        needs = backend_class(stage, backends[stage]).needs
        bad = [n for n in needs if n not in OPTIONAL_UPSTREAM.get(stage, ())]
        if bad:
            raise ConfigError(f"stages.{stage}: backend {backends[stage]!r} needs {bad}, which a {stage} backend "
                              f"may not read (allowed: {list(OPTIONAL_UPSTREAM.get(stage, ()))})")
        up[stage] = UPSTREAM[stage] + tuple(n for n in needs if n not in UPSTREAM[stage])
    return up


def call_backend(backend: Backend, frame: FrameRef, inputs: dict[str, Any], window: Window | None = None) -> Any:
    """One frame through a backend's per-frame method: its stage's own upstream output (the depth
    map for objects and head) positionally, and what the backend `needs` by keyword, from `inputs`
    (stage -> that stage's output for this frame); a windowed backend (`Backend.window`) also gets
    `window`, the frame's `frames.Window` (without one, e.g. `predict`'s single frame: the frame alone)."""
    stage = backend.stage
    method = getattr(backend, "check_frame" if stage == "input" else stage)
    args = [inputs[u] for u in UPSTREAM[stage] if u != "input"]
    kwargs = {n: inputs[n] for n in backend.needs}
    if backend.window:
        kwargs["window"] = window if window is not None else frame_windows([frame], backend.window)[0]
    return method(frame, *args, **kwargs)


def dependency_order(upstream: dict[str, tuple[str, ...]]) -> list[str]:
    """The stages in an order where each comes after its upstream (STAGES order breaks ties)."""
    order: list[str] = []
    while len(order) < len(STAGES):
        ready = [s for s in STAGES if s not in order and all(u in order for u in upstream[s])]
        if not ready:
            raise ConfigError(f"the stages' dependencies form a cycle: {upstream}")
        order.append(ready[0])
    return order


__all__ = ["BACKENDS", "DROPS_FRAME", "OPTIONAL_UPSTREAM", "STAGES", "UPSTREAM", "backend_class",
           "call_backend", "dependency_order", "upstream_of"]
