"""`ga3ce-prep train`, `ga3ce-prep eval`, `ga3ce-prep ablate` and `ga3ce-prep report`.

The training options of train and ablate are made from `TrainConfig`'s fields (name, type, default,
and the field's comment as help); `train --ablation` and `ablate --rows` read `ABLATIONS`.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import typing
from collections.abc import Callable
from typing import Any, Literal

import click
from click.core import ParameterSource

from ..errors import ConfigError
from ..model import ALIASES, DEFAULT_METHOD, ENCODINGS, METHODS, ROTATIONS, ModelConfig, resolve
from ..params import field_docs
from ..store import ContextStore, open_store
from .ablate import ABLATIONS, BY_NAME
from .ablate import ablate as run_ablate
from .dataset import ContextDataset
from .distributed import Ranks
from .evaluate import evaluate as run_eval
from .evaluate import format_eval_table
from .frameset import PROTOCOLS
from .profiles import PROFILES, DatasetProfile
from .report import report as run_report
from .trainer import TrainConfig
from .trainer import train as run_train

NOT_RECIPE = ("store", "out", "model")  # each command's own options; the model: --model-set (and train's choices)


def _n_max(value: str, store: str) -> int | None:
    if value == "batch":
        return None
    if value == "auto":
        return DatasetProfile.for_store(open_store(store)).n_max
    try:
        return int(value)
    except ValueError as e:
        raise click.BadParameter(f"{value!r}: use batch, auto or a number of object slots", param_hint="--n-max") from e


def _model_sets(items: tuple[str, ...]) -> dict[str, Any]:
    known = {f.name: f for f in dataclasses.fields(ModelConfig)}
    out: dict[str, Any] = {}
    for item in items:
        key, _, raw = item.partition("=")
        if key not in known or not raw:
            raise click.BadParameter(f"{item!r}: expected KEY=VALUE with KEY one of {sorted(known)}",
                                     param_hint="--model-set")
        try:
            out[key] = json.loads(raw)
        except json.JSONDecodeError:
            out[key] = raw
    return out


def _checked_split(store: str, split: str) -> ContextStore:
    """The store, verified against its integrity record (StoreError naming the damaged array and
    chunk: whatever --force says), once `--split` is known to it and has frames to evaluate (a view
    prior and ground-truth gaze); ConfigError naming the store, the split and the splits it has otherwise."""
    st = open_store(store, verify=True)
    there = f"its splits: {', '.join(st.split_names) or 'none'}"
    if split not in st.split_names:
        raise ConfigError(f"--split {split}: store {st.path} has no split {split!r}; {there}")
    if not len(ContextDataset(st, split)):
        raise ConfigError(f"--split {split}: store {st.path} has no {split} frame with a view prior and ground-truth "
                          f"gaze to evaluate; choose another split ({there}) or a store whose dataset annotates gaze")
    return st


def model_option(f: Callable) -> Callable:
    """--model NAME: the design to train by its fixed name, or an alias of one (model/methods.py),
    the paper's GA3CE by default."""
    return click.option("--model", "model_name", type=click.Choice([*METHODS, *ALIASES]), default=DEFAULT_METHOD,
                        show_default=True,
                        help="The design: " + "; ".join(f"{m.name} = {m.label}: {m.summary}" for m in METHODS.values())
                        + "; " + "; ".join(f"{a} = {d} today" for a, d in ALIASES.items())
                        + ". A design's name never changes meaning; the checkpoint records the design "
                        "(an alias resolved) and its full config.")(f)


def _help(cls: type, name: str) -> str:
    doc = field_docs(cls)[name]
    return doc[:1].upper() + doc[1:] + "."


def _recipe_option(f: dataclasses.Field, hint: Any) -> Callable:
    """The click option of one TrainConfig field: --name (--name/--no-name for a flag)."""
    opt, default = "--" + f.name.replace("_", "-"), f.default
    if f.name == "n_max":  # the store is needed to resolve auto: see _n_max
        auto = ", ".join(f"{p.name} {p.n_max}" for p in PROFILES.values())
        return click.option(opt, default="batch", show_default=True, metavar="batch|auto|N",
                            help=f"Object slots per frame: batch (the batch's largest count), auto (the dataset's "
                            f"N_max: {auto}) or a number; frames with more keep their largest masks.")
    if hint is bool:
        return click.option(f"{opt}/--no-{opt[2:]}", default=default, show_default=True,
                            help=_help(TrainConfig, f.name))
    if typing.get_origin(hint) is Literal:
        hint = click.Choice(typing.get_args(hint))
    elif default is None:  # X | None
        hint = next(t for t in typing.get_args(hint) if t is not type(None))
    return click.option(opt, type=hint, default=default, show_default=default is not None,
                        help=_help(TrainConfig, f.name))


def recipe_options(f: Callable) -> Callable:
    """The training recipe's options, shared by train and ablate: one per TrainConfig field, and
    --model-set for any ModelConfig field."""
    hints = typing.get_type_hints(TrainConfig)
    opts = [_recipe_option(fld, hints[fld.name]) for fld in dataclasses.fields(TrainConfig)
            if fld.name not in NOT_RECIPE]
    opts.append(click.option("--model-set", multiple=True, metavar="KEY=VALUE",
                             help="Set any ModelConfig field, e.g. --model-set object_distance_scale=0.5 "
                                  "(repeatable)."))
    for o in reversed(opts):
        f = o(f)
    return f


def _train_config(store: str, out: str, model: ModelConfig, n_max: str, **recipe: Any) -> TrainConfig:
    return TrainConfig(store=store, out=out, n_max=_n_max(n_max, store), model=model, **recipe)


def _log_setup() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")


@click.command()
@click.option("--store", required=True, help="The 3D context store (from `ga3ce-prep run`).")
@click.option("--out", required=True, help="Run folder: checkpoints, config.json, history.csv, curves.png.")
@model_option
@click.option("--ablation", type=click.Choice(list(BY_NAME)), default="full", show_default=True,
              help="Train one row of the paper's ablations (train/ablate.py::ABLATIONS): "
              + "; ".join(f"{a.name} = {a.label}" for a in ABLATIONS) + ".")
@click.option("--rotation", type=click.Choice(ROTATIONS), default=ModelConfig().rotation, show_default=True,
              help=_help(ModelConfig, "rotation"))
@click.option("--encoding", type=click.Choice(ENCODINGS), default=ModelConfig().encoding, show_default=True,
              help=_help(ModelConfig, "encoding"))
@recipe_options
@click.option("--resume", is_flag=True,
              help="Continue the run in --out from last.pt (refused if the store or options changed).")
@click.option("--force", is_flag=True, help="Overwrite an existing run, or resume despite a store/config mismatch.")
@click.pass_context
def train(ctx, store, out, model_name, ablation, rotation, encoding, resume, force, model_set, **recipe):
    """Train a gaze model on a store with the paper's recipe: the paper's GA3CE unless --model says.

    \b
    Models: ga3ce (the paper's), pointer-joint, pointer-frozen (our designs; docs/training.md "The
    output"); ours = the design we think best today, recorded by its fixed name; --ablation switches
    one part of it off, as in the paper's Tables 4 and 5.
    Defaults: the paper's recipe (AdamW, weight decay 0.1, 4 warm-up epochs then cosine per step,
    gradient clip 0.1, batch 32 on GFIE and 64 on GAFA, 20 epochs) at lr 3e-4 (docs/training.md "Learning rate"); seeded
    and deterministic on CPU.
    Example: ga3ce-prep train --store synth.zarr --out runs/ours --model ours
    Example: ga3ce-prep train --store synth.zarr --out runs/no-d3 --ablation no-d3
    Data-parallel: torchrun --nproc-per-node 2 --no-python ga3ce-prep train ... (docs/training.md).
    """
    _log_setup()
    chosen = {k: v for k, v in (("rotation", rotation), ("encoding", encoding))
              if ctx.get_parameter_source(k) is not ParameterSource.DEFAULT} | _model_sets(model_set)
    overrides = BY_NAME[ablation].overrides
    design = BY_NAME[ablation].design
    if (design is not None and design != resolve(model_name)
            and ctx.get_parameter_source("model_name") is not ParameterSource.DEFAULT):
        raise click.UsageError(f"--ablation {ablation} trains the model {ablation}; drop --model {model_name}")
    clash = [k for k in overrides if k in chosen and chosen[k] != overrides[k]]
    if clash:
        raise click.UsageError(f"--ablation {ablation} sets {', '.join(f'{k}={overrides[k]}' for k in clash)} itself; "
                               f"drop the options that set {', '.join(clash)}")
    try:
        model = dataclasses.replace(ModelConfig.for_method(model_name, rotation=rotation, encoding=encoding),
                                    **overrides, **chosen)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"model options: {e}") from None
    run = run_train(_train_config(store, out, model, **recipe), resume=resume, force=force)
    if Ranks.from_env().main:  # under torchrun: once
        click.echo(f"run folder: {run} (best.pt, last.pt, history.csv, curves.png)")
        click.echo(f"next: ga3ce-prep eval --store {store} --checkpoint {run / 'best.pt'}")


@click.command()
@click.option("--store", required=True, help="The store to evaluate on.")
@click.option("--checkpoint", required=True, help="A checkpoint (run folder's best.pt or last.pt).")
@click.option("--split", default="test", show_default=True, help="Split to evaluate: train, val or test.")
@click.option("--json", "json_path", default=None, help="Also write every number as JSON to this file.")
@click.option("--cdf", default="auto", show_default=True,
              help="PNG of the angular-error CDF (model vs v prior); auto = eval_<split>_cdf.png beside the "
              "checkpoint; 'none' for no plot.")
@click.option("--snap-cone", type=float, default=None,
              help="Cone half-angle (degrees) of the snap-to-object baseline; default: chosen on the val split.")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True,
              help="Where to run the model.")
@click.option("--batch-size", default=256, show_default=True, help="Frames per inference batch.")
@click.option("--threads", default=2, show_default=True, help="torch CPU threads.")
@click.option("--no-scenes", is_flag=True, help="Leave out the per-scene table.")
@click.option("--frames", type=click.Choice(["auto", *PROTOCOLS]), default="auto", show_default=True,
              help="Frames scored: auto = the dataset's protocol (GAFA: windows; else all); windows = GAFA's "
              "non-overlapping 7-frame windows of raw-consecutive frames; all = every frame of the split.")
@click.option("--data", default=None, type=click.Path(file_okay=False),
              help="The dataset's root, when it is no longer where the store's provenance says (the split's rows, "
              "and with --gfm the images and depth, are read from it).")
@click.option("--force", is_flag=True,
              help="Evaluate on a store other than the one the checkpoint was trained on. Not needed for a store "
              "without a train split (CAD-120, `synth --preset transfer`): that is the paper's Table 2 transfer. "
              "That is all it does: a damaged store is refused even so.")
@click.option("--gfm", "gfm", default=None, metavar="CHECKPOINT",
              help="GFIE's checkpoint (gfiemodel.pt.tar): also print GFIE's Table 1 columns "
              "(AUC, L2, 3D distance, 3D angle) for GFIE, Ours and Ours + GFM, from the frames' images and depth "
              "(GFIE or CAD-120 stores).")
@click.option("--gfm-batch-size", default=16, show_default=True, help="With --gfm: frames per pass of GFIE's network.")
@click.option("--no-objects", "no_objects", default="auto", show_default=True, metavar="auto|none|CHECKPOINT",
              help="A checkpoint of the model without objects to score beside this one (what the objects add); auto = "
              "OUT/no-objects/seed<k>/best.pt when --checkpoint is an ablate folder's OUT/full/seed<k>/best.pt.")
def evaluate(store, checkpoint, split, json_path, cdf, snap_cone, device, batch_size, threads, no_scenes, frames, data,
             force, gfm, gfm_batch_size, no_objects):
    """Evaluate a checkpoint: 3D/2D MAE, front/back, per scene, and the baselines on the same frames.

    \b
    Frames: the dataset's own rows for the split (re-read from the dataset the store was built
    from), every one accounted for: "scored N of M" and the reasons for the rest (the JSON lists
    their ids). Baselines: the view prior v, the head direction from the pose keypoints, and v
    snapped to the nearest object within a cone; and, in an ablate folder (or with --no-objects), the
    model trained without objects. The table says whether the model beats each.
    With --gfm, GFIE's gaze-following network adds GFIE's Table 1 (docs/training.md, "GFIE's
    gaze-following modules").
    """
    _log_setup()
    r = run_eval(_checked_split(store, split), checkpoint, split=split, force=force, device=device,
                 batch_size=batch_size, snap_cone_deg=snap_cone, cdf_path=None if cdf == "none" else cdf,
                 json_path=json_path, threads=threads, frames=frames, data=data, gfm=gfm, gfm_batch_size=gfm_batch_size,
                 **_beside(checkpoint, no_objects))
    click.echo(format_eval_table(r, per_scene=not no_scenes))
    if r.cdf_png is not None:
        click.echo(f"\nCDF plot: {r.cdf_png}")
    if json_path:
        click.echo(f"JSON: {json_path}")


@click.command()
@click.option("--store", required=True, help="The store every ablation trains and tests on.")
@click.option("--out", required=True, help="Folder for the runs (OUT/<row>/seed<k>) and ablation.{json,csv,png}.")
@click.option("--rows", default=None, help="Comma-separated rows to run (default all): " + ", ".join(BY_NAME) + ".")
@click.option("--seeds", default="0", show_default=True,
              help="Comma-separated seeds; the table shows mean +- std over them.")
@click.option("--split", default="test", show_default=True, help="Split the rows are evaluated on.")
@model_option
@recipe_options
@click.option("--force", is_flag=True, help="Retrain every row even if its run folder is complete.")
def ablate(store, out, rows, seeds, split, model_name, force, model_set, **recipe):
    """Train the paper's ablations of --model and print Tables 4 and 5 beside the paper's numbers.

    The rows switch parts of the model off (the paper's GA3CE by default); the rows ga3ce, ours
    (by default) and pointer-joint, pointer-frozen (by name) train that design with the same recipe,
    beside them; each row's output names the fixed design it trained.

    Finished rows are reused and unfinished ones resumed, so rerunning the command continues.
    Writes OUT/ablation.json, OUT/ablation.csv and OUT/ablation.png (bar chart).
    """
    _log_setup()
    try:
        model = ModelConfig.for_method(model_name, **_model_sets(model_set))
        seed_list = [int(s) for s in seeds.split(",") if s.strip()]
    except (TypeError, ValueError) as e:
        raise ConfigError(f"ablate options: {e}") from None
    _checked_split(store, split)
    base = _train_config(store, out, model, **recipe)
    summary = run_ablate(base, out, rows=[r.strip() for r in rows.split(",")] if rows else None,
                         seeds=seed_list, split=split, force=force)
    click.echo(summary["table"])
    click.echo(f"\nbar chart: {summary['png']}\ntable: {out}/ablation.json, {out}/ablation.csv")


@click.command()
@click.argument("run_dir")
@click.option("--store", default=None,
              help="The store to evaluate and draw on; default: the one RUN_DIR/config.json names.")
@click.option("--split", default="test", show_default=True, help="Split to evaluate and draw frames from.")
@click.option("--out", default=None, help="Folder of the page (index.html) and its PNGs; default: RUN_DIR/report.")
@click.option("--frames", default=8, show_default=True, help="Frames in the qualitative grid and the attention figure.")
@click.option("--data", default=None,
              help="The dataset folder with the frames' images; default: the one the store records.")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True,
              help="Where to run the model.")
@click.option("--threads", default=2, show_default=True, help="torch CPU threads.")
@click.option("--force", is_flag=True, help="Report on a store other than the one the checkpoint was trained on "
              "(a damaged store is refused even so).")
def report(run_dir, store, split, out, frames, data, device, threads, force):
    """One HTML page of a trained run: evaluation, curves, error CDF, per-scene and ablation bars, figures.

    \b
    RUN_DIR: a run folder of `ga3ce-prep train` (config.json, history.csv, best.pt), or a folder of
    `ga3ce-prep ablate` (its full row is shown). An ablation.json in RUN_DIR adds the ablation bars.
    Every image is embedded in the page (and written beside it as a PNG).
    Example: ga3ce-prep report runs/full && chromium runs/full/report/index.html
    """
    _log_setup()
    page = run_report(run_dir, store=store, split=split, out=out, frames=frames, data=data, device=device,
                      threads=threads, force=force)
    click.echo(f"report: {page}")


def _beside(checkpoint: str, no_objects: str) -> dict[str, Any]:
    """evaluate's no_objects and compare for `eval`: an ablate folder's other rows (`beside`), the
    no-objects one as --no-objects says (auto: the folder's, none, or a checkpoint)."""
    from .evaluate import beside

    found = beside(checkpoint)
    if no_objects != "auto":
        found["no_objects"] = None if no_objects == "none" else no_objects
    return found
