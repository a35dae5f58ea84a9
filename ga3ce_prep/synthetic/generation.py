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
import multiprocessing
import time
from collections import defaultdict
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..errors import ConfigError
from .camera import default_height, intrinsics
from .config import SynthConfig, load_config, load_preset
from .noise import blank_box, depth_sensor, rgb_sensor
from .room import build_room
from .truth import FILENAME, TruthFrame, TruthWriter, protocol_line
from .world import Scene, SceneError
from .writers import WRITERS, FormatWriter, FrameContext


@dataclass
class GenerationReport:
    """What was written and where the time went."""

    out: Path
    fmt: str
    frames: int = 0              # camera images written
    steps: int = 0               # time steps
    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))   # per step, summed over processes
    wall_seconds: float = 0.0

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


@dataclass(frozen=True)
class _World:
    """What every room of one world is made with (sent to worker processes)."""

    fmt: str
    out: Path
    K: np.ndarray
    width: int
    height: int
    cfg: SynthConfig
    scenes: int
    seed: int
    sessions_per_room: int
    frames_per_scene: int

    def writer(self) -> FormatWriter:
        return WRITERS[self.fmt](self.out, self.K, self.width, self.height, self.cfg, self.scenes, self.seed,
                                 self.sessions_per_room)


@dataclass
class _Room:
    """One room's sessions as written: its truth frames, the writer's kept rows, the time per step."""

    frames: list[TruthFrame]
    kept: Any
    steps: int
    seconds: dict[str, float]


def _room(world: _World, i: int, seq: np.random.SeedSequence) -> _Room:
    """Render room i's sessions and write their images (and GAFA's per-session files) with a writer
    of its own; the truth frames and annotation rows go back to the caller, which keeps the order."""
    report = GenerationReport(out=world.out, fmt=world.fmt)
    timer = _Timer(report)
    writer, cfg, R = world.writer(), world.cfg, world.sessions_per_room
    K, width, height = world.K, world.width, world.height
    if R == 1:
        rngs, room = [np.random.default_rng(seq)], None
    else:
        children = seq.spawn(1 + R)
        room = build_room(cfg, np.random.default_rng(children[0]), sitting=True)
        rngs = [np.random.default_rng(c) for c in children[1:]]
    frames: list[TruthFrame] = []
    for j, rng in enumerate(rngs):
        k = i * R + j
        try:
            scene = Scene(world.fmt, cfg, K, width, height, rng, room=room)
        except SceneError as e:
            raise SceneError(f"room {i}, session {j}: {e}") from None
        split, scene_name, cams = writer.scene_names(k, len(scene.cameras))
        timer.lap("scene (room, cameras, static render)")
        steps = scene.steps(world.frames_per_scene)
        for t in range(world.frames_per_scene):
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
                frames.append(tr)
            report.steps += 1
        writer.end_scene(k)
        timer.lap("write images + annotations")
    return _Room(frames, writer.take(), report.steps, dict(report.seconds))


def _rooms(world: _World, seqs: list[np.random.SeedSequence], workers: int) -> Iterator[_Room]:
    """Each room in order, rendered here (workers = 1) or by a pool of worker processes."""
    if workers <= 1:
        yield from (_room(world, i, s) for i, s in enumerate(seqs))
        return
    # spawned, not forked: the caller may hold threads (torch's, dask's) that a fork would copy mid-work
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        yield from pool.map(_room, [world] * len(seqs), range(len(seqs)), seqs)


def generate(fmt: str, out: str | Path, scenes: int, frames_per_scene: int, seed: int = 0,
             width: int = 640, height: int | None = None, config: SynthConfig | str | Path | None = None,
             progress: bool = True, sessions_per_room: int = 1, preset: str | None = None,
             workers: int = 1) -> GenerationReport:
    """Write `scenes` rooms, each recorded in `sessions_per_room` sessions of `frames_per_scene`
    time steps, in format `fmt` ("gfie", "cad120", "gafa") under `out`, plus `out/truth.h5`. GAFA
    sessions have several cameras, so they write more images than time steps. One session per room
    splits by room (val/test rooms unseen in training); several split by session (val/test rooms
    have training sessions: `writers.assign_session_splits`). `preset` names a world of
    `config.preset_names()` (its format must be `fmt`; its seed offset is added to `seed`; a
    `config` file applies on top of it). `workers` > 1 renders rooms in that many spawned processes
    (the same bytes as with one; a script that calls this must do so under `if __name__ ==
    "__main__":`, since spawned processes import it). Returns the frames written, the time per step
    of the work (summed over the processes) and the wall time."""
    if sessions_per_room < 1:
        raise ConfigError(f"sessions_per_room must be at least 1, got {sessions_per_room}")
    if preset is not None:
        if isinstance(config, SynthConfig):
            raise ConfigError("give a preset's overrides as a YAML path, not a SynthConfig")
        seed = int(seed) + load_preset(preset).seed_offset
    cfg = config if isinstance(config, SynthConfig) else load_config(fmt, config, preset=preset)
    if height is None:
        height = default_height(cfg.camera, width)
    t0 = time.perf_counter()
    out = Path(out)
    R = sessions_per_room
    world = _World(fmt, out, intrinsics(cfg.camera, width, height), width, height, cfg, scenes, seed, R,
                   frames_per_scene)
    writer = world.writer()
    writer.begin()
    report = GenerationReport(out=out, fmt=fmt)
    attrs = {"format": fmt, "seed": int(seed), "scenes": int(scenes), "frames_per_scene": int(frames_per_scene),
             "sessions_per_room": int(R), "protocol": protocol_line(R), "preset": preset or "",
             "config": json.dumps(cfg.to_dict(), sort_keys=True)}
    seqs = np.random.SeedSequence(seed).spawn(scenes)
    with TruthWriter(out / FILENAME, width, height, attrs) as truth, \
            tqdm(total=scenes * R * frames_per_scene, unit="frame", desc=f"synth {fmt}", disable=not progress) as bar:
        for room in _rooms(world, seqs, min(workers, scenes)):
            timer = _Timer(report)
            writer.absorb(room.kept)
            for tr in room.frames:
                truth.add(tr)
            timer.lap("write truth.h5")
            for name, s in room.seconds.items():
                report.seconds[name] += s
            report.frames += len(room.frames)
            report.steps += room.steps
            bar.update(room.steps)
        writer.close()
    report.wall_seconds = time.perf_counter() - t0
    return report
