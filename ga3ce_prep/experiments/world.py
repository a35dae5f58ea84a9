"""`World`: a synthetic world and the store a pipeline makes of it, the data every experiment trains
and scores on. One declaration names it; `ensure` makes what is missing and reuses the rest."""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from ..errors import Ga3ceError


@dataclass(frozen=True)
class World:
    """A synthetic world (ga3ce_prep/synthetic; docs/synthetic.md) and its preprocessing.

    Rooms are recorded in `sessions` sessions of `frames` frames each. Splits are by session, so with
    several sessions the val and test rooms have training sessions (the paper's GFIE and GAFA
    protocol, "seen rooms"); with one, by room (every test room unseen). A world with only a test
    split (the transfer preset) is scored, never trained on.
    """

    fmt: str = "gfie"                       # synthetic format: gfie, cad120 or gafa
    rooms: int = 48                         # rooms (the format's scenes)
    sessions: int = 4                       # sessions recorded per room
    frames: int = 15                        # frames per session
    seed: int = 0                           # the world's seed
    preset: str | None = None               # a named world (synthetic/presets: `transfer`); None: the format's defaults
    knobs: str | None = None                # YAML knobs over the preset's (`synth --config`), None: none
    width: int = 640                        # image width, pixels
    pipeline: str = "synthetic"             # the bundled pipeline (or file) that makes its store
    overrides: tuple[str, ...] = field(default=())  # the pipeline's `--set` settings
    train_frames: int | None = None         # train on this many of its training frames, evenly spaced; None: all
    shard_size: int | None = None           # frames per pipeline shard (one camera session each for `reuse: sequence`)
    data: str = ""                          # its dataset's folder under the output folder; "": the world's name

    @property
    def protocol(self) -> str:
        """"seen rooms" (split by session) or "unseen rooms" (split by room)."""
        return "seen rooms" if self.sessions > 1 else "unseen rooms"

    def describe(self) -> str:
        """E.g. "48 rooms x 4 sessions x 15 frames, GFIE format, seed 0"."""
        what = f"preset {self.preset}" if self.preset else f"{self.fmt.upper()} format"
        sessions = f"{self.sessions} session{'s' if self.sessions > 1 else ''}"
        return (f"{self.rooms} rooms x {sessions} x {self.frames} frames, {what}, seed {self.seed}"
                + (", other knobs" if self.knobs else ""))

    def synth_params(self) -> dict[str, Any]:
        """What decides the dataset's files (`synthetic.generate`'s arguments; not the worker count)."""
        return {"fmt": self.fmt, "scenes": self.rooms, "sessions_per_room": self.sessions,
                "frames_per_scene": self.frames, "seed": self.seed, "preset": self.preset, "width": self.width,
                "knobs": self.knobs}

    def ensure_data(self, data: Path, progress: bool = True) -> Path:
        """The dataset at `data`, written unless a dataset of the same parameters is there (its
        `world.json`); refuses a folder holding anything else."""
        from ..synthetic import generate

        stamp = data / "world.json"
        if stamp.is_file() and json.loads(stamp.read_text()) == self.synth_params() and (data / "truth.h5").is_file():
            return data
        if self._written_by_old_demo(data):
            stamp.write_text(json.dumps(self.synth_params()))
            return data
        if data.exists() and any(data.iterdir()):
            raise Ga3ceError(f"{data} exists with other contents than the world {self.describe()}: remove it or "
                             "choose another output folder")
        data.mkdir(parents=True, exist_ok=True)
        config = None
        if self.knobs:
            config = data / "knobs.yaml"
            config.write_text(self.knobs)
        generate(self.fmt, data, scenes=self.rooms, frames_per_scene=self.frames, seed=self.seed, width=self.width,
                 sessions_per_room=self.sessions, preset=self.preset, config=config, progress=progress,
                 workers=os.cpu_count() or 1)   # the same files with any worker count
        stamp.write_text(json.dumps(self.synth_params()))
        return data

    def _written_by_old_demo(self, data: Path) -> bool:
        """Whether `data` is this world as `make demo` wrote it before worlds were objects (its
        demo-params.json: the same format, sizes, seed and preset, at 640 pixels, default knobs)."""
        old = data / "demo-params.json"
        if not (old.is_file() and (data / "truth.h5").is_file()) or self.width != 640 or self.knobs:
            return False
        want = {k: v for k, v in self.synth_params().items() if k not in ("width", "knobs")}
        have = {"preset": None, "sessions_per_room": 1, **json.loads(old.read_text())}
        return have == want

    def ensure(self, data: Path, store: Path, workers: int | None = None, progress: bool = True) -> Path:
        """The store at `store` (the dataset at `data` first, each made unless it is there); returns
        `store`. The pipeline's own cache makes an unchanged rerun a check; worlds of one dataset
        (`data`) share it, in OUT/<data>.work. A finished store without
        its dataset beside it (copied from another machine) is used as it is."""
        import click

        from ..pipeline import run_pipeline

        if (store / "zarr.json").exists() and not data.exists():
            return store
        self.ensure_data(data, progress=progress)
        fmt = [] if self.fmt == "gfie" else [f"dataset.format={self.fmt}"]
        # worlds that name one dataset share one stage cache: what their pipelines share is made once
        work = data.parent / f"{self.data}.work" if self.data else None
        summary = run_pipeline(self.pipeline, data=data, out=store, workers=workers, progress=progress,
                               overrides=[*fmt, *self.overrides], shard_size=self.shard_size, work_dir=work)
        if progress:
            click.echo(summary.format())
        return store

    def to_json(self) -> dict[str, Any]:
        return {**asdict(self), "overrides": list(self.overrides), "protocol": self.protocol}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> World:
        """The World a `to_json` dict (or a results file's world record) declares."""
        known: dict[str, Any] = {f.name: d[f.name] for f in fields(cls) if f.name in d}
        known["overrides"] = tuple(known.get("overrides", ()))
        return cls(**known)
