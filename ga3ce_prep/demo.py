"""`make demo` / `ga3ce-prep demo`: the whole chain on the embedded synthetic world, run as the
paper runs its experiments: the named experiment `demo` (experiments/named.py), step by step.

synth: a GFIE-format world whose rooms are each recorded in several sessions, split by session, so
the test rooms were seen in training (the paper's GFIE and GAFA protocol), and a small transfer
world (`synth --preset transfer`: CAD-120 format, unseen rooms, another camera: the paper's Table 2)
-> prep (the bundled pipeline `synthetic-calibrated`: sensor depth completion, the weight-free
geometric segmenter, head position; a pose and a v that err as the paper's estimators do: the
calibrated testbed, docs/synthetic.md) -> three short training runs: the paper's GA3CE,
ours, and the model without objects -> evaluation of the three against the v prior and the
learning-free baselines on the seen-room test split and on the transfer world. The results file
(out/runs/demo/results.json) names the machine and the code its figures came from.

Every step is cached: rerunning reuses the datasets, the stage cache, the stores and the finished
runs.
"""
from __future__ import annotations

import time
from pathlib import Path

import click


def _step(n: int, title: str) -> float:
    click.secho(f"\n[{n}/5] {title}", bold=True)
    return time.perf_counter()


def _done(t0: float) -> None:
    click.echo(f"      ({time.perf_counter() - t0:.0f} s)")


@click.command()
@click.option("--out", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Folder for the datasets, the stores and the runs.")
@click.option("--rooms", default=48, show_default=True, help="Rooms of the training world.")
@click.option("--sessions-per-room", default=4, show_default=True,
              help="Sessions recorded in each room; splits are by session, so test rooms are seen in training "
                   "(1: split by room, every test room unseen).")
@click.option("--frames-per-session", default=15, show_default=True, help="Frames per session.")
@click.option("--transfer-rooms", default=8, show_default=True,
              help="Rooms of the transfer world (one session of 30 frames each; 0: none).")
@click.option("--epochs", default=20, show_default=True, help="Training epochs (the default recipe otherwise).")
@click.option("--seed", default=0, show_default=True, help="Seed of the worlds and of training.")
@click.option("--workers", default=None, type=int, help="dask worker processes for prep (default: threads).")
def demo(out: str, rooms: int, sessions_per_room: int, frames_per_session: int, transfer_rooms: int, epochs: int,
         seed: int, workers: int | None) -> None:
    """Run synth -> prep -> train -> eval on the embedded synthetic worlds and print the 3D MAE of
    the paper's GA3CE, of ours, of the model without objects, of the v prior and of the
    learning-free baselines, on test sessions of rooms seen in training and on a transfer world of
    unseen rooms and another camera. 10-16 minutes with set-up on 2 CPU cores (a study:
    docs/studies/2026-12-06-figures-across-cpus.md); rerunning reuses every step. The same
    experiment runs as `ga3ce-prep experiment run demo`."""
    from .experiments import demo_experiment, mae_table, run_experiment
    from .experiments.conditions import describe
    from .model import METHODS, resolve
    from .train import evaluate, format_eval_table
    from .train.evaluate import BASELINE_NOTES

    exp = demo_experiment(rooms, sessions_per_room, frames_per_session, transfer_rooms, epochs, seed)
    root = Path(out)
    seen, = exp.worlds
    transfer_world = next(iter(exp.transfer), "")   # "": no transfer world
    worlds = {**exp.worlds, **exp.transfer}
    t_all = time.perf_counter()

    data = exp.data_dirs(root)
    t0 = _step(1, "synthetic worlds: " + "; ".join(f"{w.describe()} -> {data[n]}" for n, w in worlds.items()))
    for name, w in worlds.items():
        w.ensure_data(data[name])
    _done(t0)

    t0 = _step(2, f"preprocessing (pipeline {exp.worlds[seen].pipeline}) -> "
                  + ", ".join(str(root / f"{n}.zarr") for n in worlds))
    stores = exp.stores(root, workers=workers)
    _done(t0)

    runs = {a.folder: exp.run_dir(root, seen, a, seed) for a in exp.arms}
    t0 = _step(3, f"training the paper's GA3CE, ours and the model without objects ({epochs} epochs each, the "
                  f"default recipe: docs/training.md) -> {runs['full'].parent.parent}/{{{','.join(runs)}}}/seed{seed}")
    results = run_experiment(exp, root, echo=click.echo, stores=stores)
    _done(t0)

    store, ckpt = stores[seen], runs["full"] / "best.pt"
    compare: dict[str, str | Path] = {"ours": runs["ours"] / "best.pt"}   # evaluated beside it, by name
    no_objects = runs["no-objects"] / "best.pt"
    t0 = _step(4, "evaluation on the test sessions (rooms seen in training, other recordings)")
    result = evaluate(str(store), ckpt, split="test", compare=compare, no_objects=no_objects)
    click.echo(format_eval_table(result, per_scene=False))
    _done(t0)
    if exp.transfer:
        t0 = _step(5, "evaluation on the transfer world (unseen rooms, another camera: the paper's Table 2)")
        transfer = evaluate(str(stores[transfer_world]), ckpt, split="test", cdf_path=None, compare=compare,
                            no_objects=no_objects)
        click.echo(format_eval_table(transfer, per_scene=False))
        _done(t0)

    labels = result.labels
    ours = resolve("ours")
    notes = {"model": METHODS["ga3ce"].summary, "ours": f"ours, today the design {ours}: {METHODS[ours].summary}",
             "no_objects": "the same network without the objects (the paper's appearance + pose row)",
             **BASELINE_NOTES}
    click.echo("\nthe rows:")
    for key in result.methods:
        click.echo(f"  {labels[key]:26s} {notes[key]}")
    # the figures from the results file, each arm scored on its own
    table = mae_table(results)
    arm_of = {"model": "full", "ours": "ours", "no_objects": "no-objects", "view_prior": "v prior"}
    click.echo(f"\n3D MAE (deg)               {'seen rooms':>10s} {'transfer':>9s}")
    for key, arm in arm_of.items():
        other = f"{table[(seen, transfer_world)][arm][0]:9.2f}" if exp.transfer else f"{'-':>9s}"
        click.echo(f"  {labels[key]:24s} {table[(seen, seen)][arm][0]:10.2f} {other}")
    m = {k: table[(seen, seen)][arm][0] for k, arm in arm_of.items()}
    click.secho(f"seen rooms = the test sessions of rooms recorded in training (the paper's GFIE protocol: no "
                f"objects 13.1 -> GA3CE 11.1, v prior 19.4); transfer = unseen rooms and another camera "
                f"(its Table 2). The paper's GA3CE {'beats' if m['model'] < m['no_objects'] else 'does NOT beat'} "
                f"its no-objects ablation on the seen rooms here.", bold=True)
    click.echo(f"machine: {describe(results['machine'])}. Training repeats bit for bit on one machine type, vector "
               "unit and thread count; another CPU moves these digits about as much as another seed "
               "(docs/studies/2026-12-06-figures-across-cpus.md).")
    click.echo(f"angular-error CDF: {result.cdf_png}; results: {exp.results_path(root)}")
    click.echo(f"total {time.perf_counter() - t_all:.0f} s. Next: ga3ce-prep info {store} | "
               f"ga3ce-prep show {store} <frame id> --out frame.png")


if __name__ == "__main__":
    import sys

    from .cli import main

    sys.argv = ["ga3ce-prep", "demo", *sys.argv[1:]]
    main()
