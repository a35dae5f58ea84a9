"""The paper's experiments on synthetic worlds built like its datasets (`make bench-paper`).

The paper's GFIE and GAFA tables test on rooms seen in training (other recordings of them); its
CAD-120 table (Table 2) tests a GFIE-trained model on unseen scenes with another camera. Here:

- seen-rooms worlds: `ga3ce-prep synth --format gfie --sessions-per-room R`, split by session, so
  every val and test room has training sessions (docs/synthetic.md);
- an unseen-rooms world (R = 1, split by room: the world every figure before 2026-12-05 used);
- the transfer world: `ga3ce-prep synth --preset transfer` (CAD-120 format, new rooms, another
  camera), on which the models trained on a seen-rooms world are evaluated (Table 2).

Each world is made, prepared (`ga3ce_prep/pipelines/synthetic.yaml`) and trained with `ablate` (the rows of
Tables 4 and 5, or a few of them) under OUT/<phase>-<world>/runs-<batching>[-lr<lr>]/<row>/seed<k>;
every step is cached, so rerunning continues. `--phase choose` reports the validation split of the
choosing worlds (where batching and the learning rate are compared); `--phase report` the test split
of worlds whose seeds were drawn after those choices, and the transfer world.

  choose worlds: seen (32 rooms x 4 sessions x 12 frames, seed 201), unseen (48 rooms x 60 frames,
                 seed 0: the demo's world until 2026-12-05)
  report worlds: demo (48 x 4 x 15, seed 0: make demo's world), large (60 x 5 x 20 = 6,000 frames, seed 8002)
  transfer:      16 rooms x 40 frames, seed 8102 (--phase report only; 8101 until the pose noise of
                 2026-12-05 was set, so the figures after that choice are on a fresh world)

Usage:
  python benchmarks/paper_tables.py --phase choose --worlds seen,unseen --rows full,no-objects \\
      --batching sorted,mixed,shuffled
  python benchmarks/paper_tables.py --phase report --worlds demo --rows full,no-objects,ours
  python benchmarks/paper_tables.py --phase report --worlds large --rows paper,ours    # Tables 4, 5 and 2

Prints per world and batching: each row's 3D MAE (mean +- std over seeds, worst seed), full - no
objects per seed, and the ratio to the v prior beside the paper's; then Table 2 on the transfer
world. Writes OUT/paper_tables_<phase>.json. Heavy steps take the CPU lock (cpu_lock.py), 2 threads.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np

from ga3ce_prep.model import ModelConfig
from ga3ce_prep.train import TrainConfig, ablate, evaluate
from ga3ce_prep.train.ablate import ABLATIONS, BY_NAME

from cpu_lock import CLI, cpu_lock, run_locked
from objects_value import paired

SEEDS = (0, 1, 2)
PAPER_ROWS = [a.name for a in ABLATIONS if a.table4 or a.table5]   # Tables 4 and 5
TRANSFER_ROWS = ("full", "ours", "no-objects")                     # Table 2: trained on GFIE, tested on CAD-120


@dataclass(frozen=True)
class World:
    """A synthetic world: rooms x sessions per room x frames per session, its seed, its format or preset."""

    rooms: int
    sessions: int
    frames: int
    seed: int
    preset: str | None = None      # `synth --preset` (the transfer world); None: GFIE format, default knobs

    def synth_args(self) -> list[str]:
        which = ["--preset", self.preset] if self.preset else ["--format", "gfie"]
        return [*which, "--scenes", str(self.rooms), "--sessions-per-room", str(self.sessions),
                "--frames-per-scene", str(self.frames), "--seed", str(self.seed)]


WORLDS = {
    "choose": {"seen": World(32, 4, 12, 201), "unseen": World(48, 1, 60, 0)},
    "report": {"demo": World(48, 4, 15, 0), "large": World(60, 5, 20, 8002)},
}
TRANSFER = World(16, 1, 40, 8102, preset="transfer")


def prepare(root: Path, world: World) -> Path:
    """The world's dataset and store under root (cached); returns the store."""
    data, store = root / "data", root / "synthetic.zarr"
    if (store / "zarr.json").exists():
        return store
    if not (data / "truth.h5").exists():
        run_locked([*CLI, "synth", "--out", str(data), *world.synth_args(), "--quiet"])
    fmt = ["--set", "dataset.format=cad120"] if world.preset == "transfer" else []
    run_locked([*CLI, "run", "--pipeline", "synthetic", "--data", str(data), "--out", str(store), "--quiet", *fmt])
    return store


def transfer_table(store: Path, runs: Path, rows: list[str]) -> dict[str, list[float]]:
    """Table 2: each row's seeds, trained on a seen-rooms world, evaluated on the transfer store."""
    out: dict[str, list[float]] = {}
    for name in rows:
        maes = []
        for k in SEEDS:
            with cpu_lock():
                r = evaluate(store, runs / name / f"seed{k}" / "best.pt", split="test", cdf_path=None,
                             no_objects=None, compare={})
            maes.append(r.methods["model"].mae3d)
            out["v prior"] = [r.methods["view_prior"].mae3d]
        out[name] = maes
    return out


def ms(x: list[float]) -> str:
    return f"{np.mean(x):5.2f} +- {np.std(x):4.2f}"


def format_world(label: str, summary: dict) -> str:
    """One world's rows: test (or val) 3D MAE, worst seed, ratio to the v prior beside the paper's."""
    prior = summary["v_prior_mae3d"]
    lines = [f"{label}: {summary['split']} split, v prior {prior:.2f} deg, seeds {summary['seeds']}",
             f"  {'row':34s} {'3D MAE':>13s} {'worst':>6s} {'ratio':>6s} {'paper GFIE':>10s} {'ratio':>6s}"]
    for r in summary["rows"]:
        paper = f"{r['paper_gfie']:10.1f} {r['paper_ratio_gfie']:6.3f}" if r["paper_gfie"] else f"{'-':>10s} {'-':>6s}"
        lines.append(f"  {r['label']:34s} {ms(r['mae3d_seeds']):>13s} {max(r['mae3d_seeds']):6.2f} {r['ratio']:6.3f} "
                     f"{paper}")
    by = {r["name"]: r["mae3d_seeds"] for r in summary["rows"]}
    if "full" in by and "no-objects" in by:
        d, se = paired(by["full"], by["no-objects"])
        worst = max(np.subtract(by["full"], by["no-objects"]))
        lines.append(f"  full - no objects: {d:+.2f} +- {se:.2f} deg (per-seed differences, mean +- s.e.), worst seed "
                     f"{worst:+.2f}; the paper on GFIE: 11.1 - 13.1 = -2.0")
    return "\n".join(lines)


@click.command(help=__doc__)
@click.option("--out", default="out/paper_tables", show_default=True, help="Folder of the worlds and runs.")
@click.option("--phase", type=click.Choice(list(WORLDS)), default="report", show_default=True)
@click.option("--worlds", default=None, help="Comma-separated world names (default: all of the phase).")
@click.option("--rows", "rows_arg", default="paper", show_default=True,
              help="Comma-separated ablation rows (ga3ce-prep ablate --rows); `paper` stands for the rows of "
              "Tables 4 and 5.")
@click.option("--batching", "batchings", default="shuffled", show_default=True,
              help="Comma-separated TrainConfig.batching values, each a set of runs (mixed, sorted, shuffled).")
@click.option("--lr", default=None, type=float,
              help="Peak learning rate (default: TrainConfig's); its runs get their own folder.")
@click.option("--epochs", default=20, show_default=True,
              help="Training epochs; other than 20, the runs go to runs-<batching>[-lr<lr>]-e<epochs> (a longer "
                   "schedule gives a small world more optimiser steps).")
@click.option("--no-transfer", is_flag=True, help="--phase report: skip Table 2 on the transfer world.")
def main(out: str, phase: str, worlds: str | None, rows_arg: str, batchings: str, lr: float | None, epochs: int,
         no_transfer: bool) -> None:
    rows = [r for token in rows_arg.split(",") for r in (PAPER_ROWS if token == "paper" else [token])]
    if unknown := [r for r in rows if r not in BY_NAME]:
        raise click.BadParameter(f"unknown rows {unknown}; choose from {list(BY_NAME)}", param_hint="--rows")
    split = "val" if phase == "choose" else "test"
    names = worlds.split(",") if worlds else list(WORLDS[phase])
    transfer = None
    if phase == "report" and not no_transfer:
        transfer = prepare(Path(out) / "transfer", TRANSFER)
    report: dict[str, dict] = {}
    texts = []
    for name in names:
        world = WORLDS[phase][name]
        root = Path(out) / f"{phase}-{name}"
        store = prepare(root, world)
        for batching in batchings.split(","):
            base = TrainConfig(store=str(store), epochs=epochs, batching=batching, progress=False,
                               model=ModelConfig.for_method("ga3ce"), **({"lr": lr} if lr else {}))
            recipe = ([f"lr{lr:g}"] if lr else []) + ([f"e{epochs}"] if epochs != 20 else [])   # the default's: none
            runs = root / "-".join([f"runs-{batching}", *recipe])
            with cpu_lock():
                summary = ablate(base, runs, rows=rows, seeds=list(SEEDS), split=split)
            label = f"{name} ({world.rooms} rooms x {world.sessions} sessions x {world.frames} frames, seed "\
                    f"{world.seed}), batching {batching}" + (f", lr {lr:g}" if lr else "") + \
                    (f", {epochs} epochs" if epochs != 20 else "")
            entry = {"world": dataclasses.asdict(world), "batching": batching, "lr": base.lr, "epochs": epochs,
                     "summary": {k: v for k, v in summary.items() if k not in ("table", "png")}}
            if transfer is not None:
                entry["transfer"] = transfer_table(transfer, runs, [r for r in TRANSFER_ROWS if r in rows])
                t = entry["transfer"]
                label_t = "\n  Table 2, transfer world (CAD-120 format, unseen rooms, another camera), 3D MAE: " + \
                    ", ".join(f"{k} {ms(v)}" for k, v in t.items())
            else:
                label_t = ""
            text = format_world(label, summary) + label_t
            click.echo(text)
            texts.append(text)
            report["/".join([name, batching, *recipe])] = entry
    Path(out).mkdir(parents=True, exist_ok=True)
    path = Path(out) / f"paper_tables_{phase}.json"
    old = json.loads(path.read_text()) if path.exists() else {}
    path.write_text(json.dumps({**old, **report}, indent=2, default=float))
    click.echo("\n\n".join(texts) + f"\nwrote {path}")


if __name__ == "__main__":
    main()
