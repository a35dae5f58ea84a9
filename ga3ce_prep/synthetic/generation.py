"""Generate a synthetic dataset in one format: scenes -> time steps -> camera images, written by
the format's writer, with the truth side-car beside them.

Each scene has its own generator, spawned from `numpy.random.SeedSequence(seed)`, so a scene's
content depends only on (seed, scene index, config, size) and scenes are independent.
"""
from __future__ import annotations

import json
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .camera import default_height, intrinsics
from .config import SynthConfig, load_config
from .noise import blank_box, depth_sensor, rgb_sensor
from .truth import FILENAME, TruthWriter
from .world import Scene
from .writers import WRITERS, FrameContext


@dataclass
class GenerationReport:
    """What was written and where the time went."""

    out: Path
    fmt: str
    frames: int = 0              # camera images written
    steps: int = 0               # time steps
    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))

    @property
    def total_seconds(self) -> float:
        return float(sum(self.seconds.values()))


class _Timer:
    def __init__(self, report: GenerationReport):
        self.r, self.t = report, time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.r.seconds[name] += now - self.t
        self.t = now


def generate(fmt: str, out: str | Path, scenes: int, frames_per_scene: int, seed: int = 0,
             width: int = 640, height: int | None = None, config: SynthConfig | str | Path | None = None,
             progress: bool = True) -> GenerationReport:
    """Write `scenes` scenes of `frames_per_scene` time steps in format `fmt` ("gfie", "cad120",
    "gafa") under `out`, plus `out/truth.h5`. GAFA scenes have several cameras, so they write
    more images than time steps. Returns timing per step of the work."""
    cfg = config if isinstance(config, SynthConfig) else load_config(fmt, config)
    if height is None:
        height = default_height(cfg.camera, width)
    K = intrinsics(cfg.camera, width, height)
    out = Path(out)
    writer = WRITERS[fmt](out, K, width, height, cfg, scenes, seed)
    report = GenerationReport(out=out, fmt=fmt)
    attrs = {"format": fmt, "seed": int(seed), "scenes": int(scenes), "frames_per_scene": int(frames_per_scene),
             "config": json.dumps(cfg.to_dict(), sort_keys=True)}
    seqs = np.random.SeedSequence(seed).spawn(scenes)
    with TruthWriter(out / FILENAME, width, height, attrs) as truth, \
            tqdm(total=scenes * frames_per_scene, unit="frame", desc=f"synth {fmt}", disable=not progress) as bar:
        for i in range(scenes):
            rng = np.random.default_rng(seqs[i])
            timer = _Timer(report)
            scene = Scene(fmt, cfg, K, width, height, rng)
            split, scene_name, cams = writer.scene_names(i, len(scene.cameras))
            timer.lap("scene (room, cameras, static render)")
            steps = scene.steps(frames_per_scene)
            for t in range(frames_per_scene):
                step = next(steps)
                timer.lap("pose + person render")
                for c in range(len(scene.cameras)):
                    tr = scene.truth(step, c, writer.frame_id(i, c, t), split, scene_name, cams[c])
                    timer.lap("truth")
                    rgb = rgb_sensor(step.views[c].rgb, cfg.render, scene.banks[c], rng)
                    depth = None
                    if writer.has_depth:
                        v = step.views[c]
                        depth, _ = depth_sensor(v.depth, v.albedo_lum, v.shiny, cfg.depth, scene.banks[c], rng)
                        if cfg.depth.head_hole_prob > 0 and rng.random() < cfg.depth.head_hole_prob:
                            blank_box(depth, tr.head_box)
                    timer.lap("sensor noise")
                    writer.write(FrameContext(i, c, t, tr, rgb, depth, rng))
                    timer.lap("write images + annotations")
                    truth.add(tr)
                    timer.lap("write truth.h5")
                    report.frames += 1
                report.steps += 1
                bar.update(1)
            writer.end_scene(i)
            timer.lap("write images + annotations")
        writer.close()
    return report
