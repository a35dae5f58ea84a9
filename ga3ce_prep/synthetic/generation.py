"""Generate a synthetic dataset in one format: rooms -> sessions -> time steps -> camera images,
written by the format's writer, with the truth side-car beside them.

Each room has its own generator, spawned from `numpy.random.SeedSequence(seed)`, so a room's
content depends only on (seed, room index, config, size) and rooms are independent. With one
session per room (the default) that generator draws the whole scene (room, person, cameras,
timeline), as it always has. With R sessions per room the room's seed sequence spawns 1 + R
children: the first builds the room (with a seat, so any session may sit), session j's draws the
person, cameras, timeline and sensor noise of that session.
"""
from __future__ import annotations

import json
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import ConfigError
from .camera import default_height, intrinsics
from .config import SynthConfig, load_config, load_preset
from .noise import blank_box, depth_sensor, rgb_sensor
from .room import build_room
from .truth import FILENAME, TruthWriter, protocol_line
from .world import Scene, SceneError
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
             progress: bool = True, sessions_per_room: int = 1, preset: str | None = None) -> GenerationReport:
    """Write `scenes` rooms, each recorded in `sessions_per_room` sessions of `frames_per_scene`
    time steps, in format `fmt` ("gfie", "cad120", "gafa") under `out`, plus `out/truth.h5`. GAFA
    sessions have several cameras, so they write more images than time steps. One session per room
    splits by room (val/test rooms unseen in training); several split by session (val/test rooms
    have training sessions: `writers.assign_session_splits`). `preset` names a world of
    `config.preset_names()` (its format must be `fmt`; its seed offset is added to `seed`; a
    `config` file applies on top of it). Returns timing per step of the work."""
    if sessions_per_room < 1:
        raise ConfigError(f"sessions_per_room must be at least 1, got {sessions_per_room}")
    if preset is not None:
        if isinstance(config, SynthConfig):
            raise ConfigError("give a preset's overrides as a YAML path, not a SynthConfig")
        seed = int(seed) + load_preset(preset).seed_offset
    cfg = config if isinstance(config, SynthConfig) else load_config(fmt, config, preset=preset)
    if height is None:
        height = default_height(cfg.camera, width)
    K = intrinsics(cfg.camera, width, height)
    out = Path(out)
    R = sessions_per_room
    writer = WRITERS[fmt](out, K, width, height, cfg, scenes, seed, R)
    report = GenerationReport(out=out, fmt=fmt)
    attrs = {"format": fmt, "seed": int(seed), "scenes": int(scenes), "frames_per_scene": int(frames_per_scene),
             "sessions_per_room": int(R), "protocol": protocol_line(R), "preset": preset or "",
             "config": json.dumps(cfg.to_dict(), sort_keys=True)}
    seqs = np.random.SeedSequence(seed).spawn(scenes)
    with TruthWriter(out / FILENAME, width, height, attrs) as truth, \
            tqdm(total=scenes * R * frames_per_scene, unit="frame", desc=f"synth {fmt}", disable=not progress) as bar:
        for i in range(scenes):
            timer = _Timer(report)
            if R == 1:
                rngs, room = [np.random.default_rng(seqs[i])], None
            else:
                children = seqs[i].spawn(1 + R)
                room = build_room(cfg, np.random.default_rng(children[0]), sitting=True)
                rngs = [np.random.default_rng(c) for c in children[1:]]
            for j, rng in enumerate(rngs):
                k = i * R + j
                try:
                    scene = Scene(fmt, cfg, K, width, height, rng, room=room)
                except SceneError as e:
                    raise SceneError(f"room {i}, session {j}: {e}") from None
                split, scene_name, cams = writer.scene_names(k, len(scene.cameras))
                timer.lap("scene (room, cameras, static render)")
                steps = scene.steps(frames_per_scene)
                for t in range(frames_per_scene):
                    step = next(steps)
                    timer.lap("pose + person render")
                    for c in range(len(scene.cameras)):
                        tr = scene.truth(step, c, writer.frame_id(k, c, t), split, scene_name, cams[c], i, j)
                        timer.lap("truth")
                        rgb = rgb_sensor(step.views[c].rgb, cfg.render, scene.banks[c], rng)
                        depth = None
                        if writer.has_depth:
                            v = step.views[c]
                            depth, _ = depth_sensor(v.depth, v.albedo_lum, v.shiny, cfg.depth, scene.banks[c], rng)
                            if cfg.depth.head_hole_prob > 0 and rng.random() < cfg.depth.head_hole_prob:
                                blank_box(depth, tr.head_box)
                        timer.lap("sensor noise")
                        writer.write(FrameContext(k, c, t, tr, rgb, depth, rng))
                        timer.lap("write images + annotations")
                        truth.add(tr)
                        timer.lap("write truth.h5")
                        report.frames += 1
                    report.steps += 1
                    bar.update(1)
                writer.end_scene(k)
                timer.lap("write images + annotations")
        writer.close()
    return report
