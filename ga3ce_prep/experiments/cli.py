"""`ga3ce-prep experiment`: run a named experiment, list them, print a results file."""
from __future__ import annotations

import json
from pathlib import Path

import click


@click.group()
def experiment() -> None:
    """Named experiments (ga3ce_prep/experiments/named.py): worlds x arms x seeds, trained unless done,
    scored, and written to OUT/runs/NAME/results.json with the machine and the code they ran on."""


@experiment.command("list")
def list_() -> None:
    """The named experiments: worlds, arms, seeds."""
    from . import EXPERIMENTS

    for name, e in EXPERIMENTS.items():
        click.echo(f"{name}: {e.question}")
        for w, world in {**e.worlds, **e.transfer}.items():
            click.echo(f"  {'transfer' if w in e.transfer else 'world':8s} {w}: {world.describe()}")
        click.echo(f"  arms     {', '.join(a.folder for a in e.arms)}; seeds {list(e.seeds)}; {e.split} split")


@experiment.command()
@click.argument("name")
@click.option("--out", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Folder of the worlds, stores and runs (OUT/runs/NAME/...).")
@click.option("--seeds", default=None, help="Comma-separated training seeds (default: the experiment's).")
@click.option("--worlds", default=None,
              help="Comma-separated training worlds to run (default: all); the results file then holds these.")
@click.option("--workers", default=None, type=int, help="dask worker processes for preprocessing (default: threads).")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def run(name: str, out: str, seeds: str | None, worlds: str | None, workers: int | None, quiet: bool) -> None:
    """Run the experiment NAME (`ga3ce-prep experiment list`): make each world's store, train every
    arm and seed unless its run is done, score each, print the table and write the results JSON.
    Rerunning reuses everything finished; an interrupted run goes on."""
    from . import EXPERIMENTS, format_results, run_experiment

    if name not in EXPERIMENTS:
        raise click.BadParameter(f"{name!r}; choose from {', '.join(EXPERIMENTS)}", param_hint="NAME")
    exp = EXPERIMENTS[name]
    if seeds:
        exp = exp.with_seeds(tuple(int(s) for s in seeds.split(",")))
    if worlds:
        exp = exp.with_worlds(tuple(worlds.split(",")))
    results = run_experiment(exp, out, progress=not quiet, workers=workers, echo=click.echo)
    click.echo(format_results(results))
    click.echo(f"wrote {exp.results_path(Path(out))}")


@experiment.command()
@click.argument("results", type=click.Path(exists=True, dir_okay=False))
def show(results: str) -> None:
    """Print a results file (OUT/runs/NAME/results.json) as tables, with its conditions."""
    from . import format_results

    click.echo(format_results(json.loads(Path(results).read_text())))
