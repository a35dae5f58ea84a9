"""The synthetic-world accuracy benchmark: synth -> `ga3ce-prep run` -> ablate -> the criteria.

Criteria: with the default recipe, the full model's test 3D MAE is at most
60% of the v prior's (v = truth + 20 degrees of noise), and every ablation row is worse than the
full model. The script prints the Tables 4/5 layout with the paper's numbers beside ours and a
PASS/FAIL line per criterion, and writes OUT/accuracy.json.

Each heavy step (synth, the pipeline, each ablation row) runs under the CPU lock (cpu_lock.py) with 2
threads; every step resumes (the dataset and the store are reused when present, finished ablation
runs are reused, unfinished ones resumed), so rerunning the same command continues.

    python benchmarks/accuracy.py --out out/accuracy [--scenes 400 --frames-per-scene 15]
        [--pipeline synthetic] [--set stages.view.params.head_weight=0.5] [--synth-config knobs.yaml]
        [--rows full,no-objects,...] [--seeds 0,1] [--epochs 20 --lr 3e-4 ...]
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from ga3ce_prep.model import ALIASES, METHODS, ModelConfig
from ga3ce_prep.train import TrainConfig
from ga3ce_prep.train.ablate import ablate, default_rows
from ga3ce_prep.train.cli import _model_sets

from cpu_lock import CLI, cpu_lock, run_locked

ROOT = Path(__file__).resolve().parent.parent
RECIPE = TrainConfig()   # the default recipe


@click.command()
@click.option("--out", default=str(ROOT / "out" / "accuracy"), show_default=True,
              help="Folder for the dataset, the store and the runs.")
@click.option("--scenes", default=400, show_default=True, help="Synthetic scenes (splits are by scene).")
@click.option("--frames-per-scene", default=15, show_default=True, help="Frames per scene.")
@click.option("--seed", default=0, show_default=True, help="Synthetic world seed.")
@click.option("--data", default=None, help="Use this synthetic dataset folder (default OUT/data, made if missing).")
@click.option("--store", "store_path", default=None, help="Use/make the store here (default OUT/<pipeline>.zarr).")
@click.option("--work", default=None,
              help="Pipeline work directory (share one to reuse cached stages across --set variants).")
@click.option("--synth-config", default=None, help="YAML overriding the world's knobs (docs/synthetic.md).")
@click.option("--pipeline", default="synthetic", show_default=True,
              help="Pipeline: synthetic (geometric objects, oracle pose and view) or synthetic-oracle.")
@click.option("--set", "sets", multiple=True, metavar="KEY=VALUE",
              help="Pipeline override passed to `ga3ce-prep run --set` (repeatable).")
@click.option("--rows", default=None, help="Ablation rows (default: all).")
@click.option("--seeds", default="0", show_default=True, help="Training seeds (comma-separated): mean +- std.")
@click.option("--epochs", default=RECIPE.epochs, show_default=True, help="Training epochs (the default recipe's).")
@click.option("--lr", default=RECIPE.lr, show_default=True,
              help='Peak learning rate (the default recipe\'s: docs/training.md "Learning rate").')
@click.option("--view-noise", type=click.Choice(["auto", "on", "off"]), default="auto", show_default=True,
              help="View-noise augmentation.")
@click.option("--model", "model_name", type=click.Choice([*METHODS, *ALIASES]), default="ga3ce",
              show_default=True, help="The base design whose ablations are trained (ga3ce: the paper's; "
              "model/methods.py).")
@click.option("--model-set", multiple=True, metavar="KEY=VALUE", help="ModelConfig override (repeatable).")
@click.option("--train-frames", type=int, default=None, help="Train on a subset of this many frames.")
def main(out, scenes, frames_per_scene, seed, data, store_path, work, synth_config, pipeline, sets, rows, seeds, epochs,
         lr, view_noise, model_name, model_set, train_frames):
    out = Path(out)
    data = Path(data) if data else out / "data"
    store = Path(store_path) if store_path else out / f"{pipeline}.zarr"
    if not (data / "truth.h5").exists():
        cmd = CLI + ["synth", "--format", "gfie", "--out", str(data), "--scenes", str(scenes),
                     "--frames-per-scene", str(frames_per_scene), "--seed", str(seed), "--quiet"]
        run_locked(cmd + (["--config", synth_config] if synth_config else []))
    if not (store / "zarr.json").exists():
        cmd = CLI + ["run", "--pipeline", pipeline, "--data", str(data), "--out", str(store), "--quiet"]
        cmd += ["--work", work] if work else []
        for s in sets:
            cmd += ["--set", s]
        run_locked(cmd)

    base = TrainConfig(store=str(store), out=str(out / "runs"), epochs=epochs, lr=lr, view_noise=view_noise,
                       train_frames=train_frames, progress=False,
                       model=ModelConfig.for_method(model_name, **_model_sets(model_set)))
    names = [r.strip() for r in rows.split(",")] if rows else default_rows(model_name)
    seed_list = [int(s) for s in seeds.split(",")]
    runs = out / "runs"
    for name in names:  # one row at a time under the lock, so other heavy jobs can interleave
        click.echo(f"ablation row {name}")
        with cpu_lock():
            ablate(base, runs, rows=[name], seeds=seed_list)
    summary = ablate(base, runs, rows=names, seeds=seed_list)  # finished runs: evaluation only
    rows_by = {r["name"]: r for r in summary["rows"]}
    checks = {}
    if "full" in rows_by:
        checks["full <= 0.60 x v prior"] = rows_by["full"]["ratio"] <= 0.60
        checks["full model best"] = bool(summary["full_best"])
    click.echo("\n" + summary["table"] + "\n")
    for k, ok in checks.items():
        click.echo(f"{'PASS' if ok else 'FAIL'}: {k}"
                   + (f" (ratio {rows_by['full']['ratio']:.3f})" if "0.60" in k else ""))
    result = {**{k: v for k, v in summary.items() if k != "table"}, "checks": checks,
              "world": {"scenes": scenes, "frames_per_scene": frames_per_scene, "seed": seed,
                        "synth_config": synth_config, "pipeline": pipeline, "sets": list(sets)},
              "recipe": base.to_dict(),
              "command": " ".join(sys.argv)}
    (out / "accuracy.json").write_text(json.dumps(result, indent=2, default=float))
    click.echo(f"\nwrote {out / 'accuracy.json'}, {summary.get('png')}")


if __name__ == "__main__":
    main()
