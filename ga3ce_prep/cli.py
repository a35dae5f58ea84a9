"""`ga3ce-prep`: the command line. Each command lives in the module of its concept and is imported
only when it runs, so `ga3ce-prep --help` is instant and never imports torch or Open3D."""
from __future__ import annotations

import importlib
import os
import sys

import click

from . import __version__
from .errors import DEBUG_HINT, Ga3ceError, environment_problem, where_raised

# name -> (module:attribute, one-line help). Order is the order `--help` lists them in.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("ga3ce_prep.demo:demo", "Run the whole chain on the embedded synthetic world."),
    "synth": ("ga3ce_prep.synthetic.cli:synth", "Write a synthetic RGB-D dataset in GFIE, CAD-120 or GAFA format."),
    "run": ("ga3ce_prep.pipeline.cli:run", "Preprocess a dataset into a 3D context store (staged, cached, resumable)."),
    "info": ("ga3ce_prep.store_cli:info", "Print what a store holds: splits, scenes, objects, provenance, failures."),
    "show": ("ga3ce_prep.store_cli:show", "Draw one frame's 3D context as a PNG, or write it as a PLY point set."),
    "view": ("ga3ce_prep.view:view",
             "Show a store's 3D context over time, and a checkpoint's gaze, in Rerun (the extra [view])."),
    "export": ("ga3ce_prep.store_cli:export", "Export a store's arrays to HDF5 for other trainers."),
    "train": ("ga3ce_prep.train.cli:train", "Train the GA3CE 3D gaze transformer on a store."),
    "eval": ("ga3ce_prep.train.cli:evaluate",
             "Evaluate a checkpoint: 3D/2D MAE, baselines, per-scene table, CDF plot."),
    "ablate": ("ga3ce_prep.train.cli:ablate",
               "Train the paper's ablations and print Tables 4/5 beside the paper's numbers."),
    "experiment": ("ga3ce_prep.experiments.cli:experiment",
                   "Run a named experiment (worlds x arms x seeds) into one results file; list them; show one."),
    "report": ("ga3ce_prep.train.cli:report",
               "One HTML page of a trained run: curves, error CDF, per-scene and ablation bars, the paper's figures."),
    "predict": ("ga3ce_prep.predict:predict",
                "Run the stages (and a checkpoint) on one RGB(-D) frame: v, g, objects; a drawing."),
    "models": ("ga3ce_prep.weights.cli:models",
               "Fetch and list the registry models; check your folder of the paper's models."),
    "export-mobilesam": ("ga3ce_prep.estimators.cli:export_mobilesam",
                         "Export a trained MobileSAM checkpoint to the ONNX files the mobilesam backend reads."),
    "export-gfie-view": ("ga3ce_prep.estimators.cli:export_gfie_view",
                         "Export GFIE's head network from its checkpoint to an ONNX file for the onnx view backend."),
}

# What each command writes, for the machine's refusals (a full disk, a permission:
# errors.environment_problem): the option (or positional argument, by its index) naming the place,
# for an OSError that names none (a full disk's write(2) does not); what it is; what is kept and
# how to go on once that is fixed. `run` says it all itself, with the figures of its cache.
WRITES: dict[str, tuple[str | int, str, str]] = {
    "run": ("--out", "the store", "what is finished is kept: rerun the same command once this is fixed"),
    "train": ("--out", "the run folder's checkpoints and history.csv", "the epochs finished so far are kept in "
              "the run folder (last.pt, history.csv): rerun with --resume to continue"),
    "ablate": ("--out", "the ablation's run folders", "finished rows are kept: rerun the same command to continue"),
    "eval": ("--json", "the evaluation's JSON", ""),
    "report": ("--out", "the report's page and figures", ""),
    "export": (1, "the HDF5 file", ""),
    "predict": ("--out", "the drawing", ""),
    "show": ("--out", "the drawing", ""),
    "view": ("--save", "the recording", ""),
}
RERUN = "nothing it finished is lost: rerun the command"


class LazyGroup(click.Group):
    """A click group whose commands are imported on first use."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        target, _ = COMMANDS[name]
        module, attr = target.split(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except (ModuleNotFoundError, AttributeError) as e:
            if isinstance(e, ModuleNotFoundError) and e.name and not module.startswith(e.name):
                raise  # a real missing dependency: let it show
            raise click.ClickException(f"command {name!r} is not available in this build ({target})") from e

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        with formatter.section("Commands"):
            formatter.write_dl([(name, help_) for name, (_, help_) in COMMANDS.items()])


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="ga3ce-prep")
def cli() -> None:
    """Offline 3D-context preprocessing and a GA3CE trainer for unconstrained 3D gaze estimation.

    \b
    Typical use:
      ga3ce-prep synth --format gfie --out data/synth        # or bring GFIE, CAD-120, GAFA
      ga3ce-prep run --pipeline synthetic --data data/synth --out synth.zarr   # or a YAML file
      ga3ce-prep train --store synth.zarr --out runs/full
      ga3ce-prep eval --store synth.zarr --checkpoint runs/full/best.pt

    Units: metres; camera frame x right, y down, z forward. Run `ga3ce-prep COMMAND --help` for
    each command's options.
    """


def main() -> None:
    """Entry point: runs the CLI and prints ga3ce-prep's own errors and the machine's (a full disk, a
    permission: `environment_problem`) as one clear `error:` line (exit 2), anything else as one line
    saying it is a bug (exit 1); GA3CE_DEBUG=1 raises instead, for the traceback."""
    try:
        cli.main(standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as e:
        e.show()
        sys.exit(e.exit_code)
    except Ga3ceError as e:
        if os.environ.get("GA3CE_DEBUG"):
            raise
        click.secho(f"error: {e}", fg="red", err=True)
        sys.exit(2)
    except Exception as e:  # the machine's problem (errors.environment_problem), else a bug: one line
        if os.environ.get("GA3CE_DEBUG"):
            raise
        problem = _refused(e, sys.argv[1:])
        if problem is not None:
            click.secho(f"error: {problem}", fg="red", err=True)
            sys.exit(2)
        click.secho(f"error: unexpected {type(e).__name__}: {e} (at {where_raised(e)}); a bug in ga3ce-prep: "
                    f"{DEBUG_HINT} and report it", fg="red", err=True)
        sys.exit(1)


def _refused(e: Exception, args: list[str]):
    """errors.environment_problem for command line `args` (WRITES: the place, what, what is kept)."""
    name = next((a for a in args if a in COMMANDS), "")
    where, what, kept = WRITES.get(name, ("", "", ""))
    rest = args[args.index(name) + 1:] if name else []
    if isinstance(where, int):
        plain = [a for a in rest if not a.startswith("-")]
        path = plain[where] if len(plain) > where else None
    else:
        aliases = {where, {"--out": "-o"}.get(where, where)}
        path = next((rest[i + 1] for i, a in enumerate(rest[:-1]) if a in aliases), None)
        path = path or next((a.split("=", 1)[1] for a in rest if a.split("=", 1)[0] in aliases and "=" in a), None)
    return environment_problem(e, path, what if path else "", kept=kept or RERUN)


if __name__ == "__main__":
    main()
