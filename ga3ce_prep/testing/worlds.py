"""The small synthetic worlds the tests share, the pipeline overrides that fit them, and a world
re-written in the precomputed and `folder` layouts (docs/datasets.md, docs/pipeline.md)."""
from __future__ import annotations

import csv
import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

# 160x120 frames keep the tests fast: 3 scenes x 4 frames.
SMALL_WORLD = dict(scenes=3, frames_per_scene=4, seed=5, width=160)
# 640x480 (the benchmark's resolution), where heads span 15-40 px (at 160x120 a head is 5-8 px
# and its depth window 3x3): 4 scenes x 2 frames.
WORLD_640 = dict(scenes=4, frames_per_scene=2, seed=6, width=640)
# GAFA format for the temporal windows: 2 scenes x 10 frames (6 camera sequences of raw frames
# 0-9; tests/conftest.py removes GAFA_GAP (camera sequence, raw frame) to make a gap).
GAFA_WORLD = dict(scenes=2, frames_per_scene=10, seed=5, width=160)
GAFA_GAP = ("library/1029_2/Camera2_0", 1)
# the bundled pipelines with the geometric segmenter's grid scaled to 160x120 frames
SMALL = ["stages.objects.params.stride=1"]



def truth_file(world: Path, out: Path, name: str, scale: float = 1.0,
               ids: Callable[[str], str] | None = None) -> Path:
    """The world's truth pose (name "pose": (N, J, 3) m) or gaze (name "view": (N, 3)) as a
    precomputed file `out` (.npz: frame_id + the array), times `scale`; `ids` maps the world's
    frame ids to the dataset's. Returns `out`."""
    from ..synthetic.truth import TruthReader

    t = TruthReader(world / "truth.h5")
    values = t.array("pose" if name == "pose" else "gaze").astype(np.float32) * np.float32(scale)
    fids = [ids(f) if ids else f for f in t.frame_ids]
    if name == "pose":
        np.savez(out, frame_id=np.array(fids), pose=values)
    else:
        np.savez(out, frame_id=np.array(fids), view=values)
    return out


def folder_name(frame_id: str) -> str:
    """A GFIE-format world's frame id as a `folder` recording's frame name (<split>_<scene>_<frame>)."""
    return frame_id.replace("/", "_")


def as_folder(world: Path, root: Path) -> Path:
    """The GFIE-format world `world` as a `folder` recording under `root` (rgb/, depth/ .npy,
    intrinsics.json, heads.csv with a split column), with its truth pose and view as `pose.npz` and
    `view.npz` keyed by the recording's frame names. Returns `root`."""
    from ..datasets import open_dataset

    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    fx, fy, cx, cy = np.load(world / "CameraKinect.npy")
    (root / "intrinsics.json").write_text(json.dumps({"fx": fx, "fy": fy, "cx": cx, "cy": cy}))
    rows = []
    for ref in open_dataset("gfie", world).frames():
        assert ref.depth_path is not None, ref.id               # a GFIE-format world has depth files
        shutil.copy(ref.image_path, root / "rgb" / f"{folder_name(ref.id)}.jpg")
        shutil.copy(ref.depth_path, root / "depth" / f"{folder_name(ref.id)}.npy")
        rows.append([folder_name(ref.id), *ref.head_box.tolist(), ref.split])
    with open(root / "heads.csv", "w", newline="") as f:
        csv.writer(f).writerows([["name", "x1", "y1", "x2", "y2", "split"], *rows])
    truth_file(world, root / "pose.npz", "pose", ids=folder_name)
    truth_file(world, root / "view.npz", "view", ids=folder_name)
    return root


# the preprocessing benchmarks' world: 640x480 frames, 4 per scene
BENCH_WIDTH = 640
BENCH_FRAMES_PER_SCENE = 4


def bench_world(base: Path, n_frames: int) -> Path:
    """A GFIE-format synthetic world of n_frames (4 per scene) at 640x480, seed 11, generated once into
    base/world (the preprocessing benchmarks': `make bench-prep`, `make bench-scale`)."""
    from ga3ce_prep.synthetic import generate

    root = base / "world"
    stamp = root / ".bench"
    want = f"{n_frames} {BENCH_WIDTH} {BENCH_FRAMES_PER_SCENE} seed 11"
    if stamp.is_file() and stamp.read_text() == want:
        return root
    shutil.rmtree(root, ignore_errors=True)
    t = time.perf_counter()
    generate("gfie", root, scenes=-(-n_frames // BENCH_FRAMES_PER_SCENE), frames_per_scene=BENCH_FRAMES_PER_SCENE,
             seed=11, width=BENCH_WIDTH, progress=True)
    stamp.write_text(want)
    print(f"generated {n_frames} frames in {time.perf_counter() - t:.0f} s", flush=True)
    return root
