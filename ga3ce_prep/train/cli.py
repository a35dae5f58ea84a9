"""`ga3ce-prep train`, `ga3ce-prep eval` and `ga3ce-prep ablate`."""
from __future__ import annotations

import dataclasses
import json
import logging
from typing import Any

import click

from ..errors import ConfigError
from ..model import ModelConfig


def _n_max(value: str, store: str) -> int | None:
    if value == "batch":
        return None
    if value == "auto":
        from ..store import open_store
        from .profiles import DatasetProfile

        return DatasetProfile.for_store(open_store(store)).n_max
    try:
        return int(value)
    except ValueError:
        raise click.BadParameter(f"{value!r}: use batch, auto or a number of object slots", param_hint="--n-max")


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


def recipe_options(f):
    """The training recipe's options, shared by train and ablate; defaults are TrainConfig's."""
    from .trainer import TrainConfig  # (ga3ce_prep.train has imported it already)

    d = TrainConfig()
    opts = [
        click.option("--epochs", default=d.epochs, show_default=True, help="Training epochs."),
        click.option("--batch-size", default=d.batch_size, show_default=True, help="Frames per batch (paper: 32 GFIE, 64 GAFA)."),
        click.option("--lr", default=d.lr, show_default=True,
                     help='Peak AdamW learning rate, below the paper\'s: docs/training.md "Learning rate".'),
        click.option("--weight-decay", default=d.weight_decay, show_default=True, help="AdamW weight decay."),
        click.option("--warmup-epochs", default=d.warmup_epochs, show_default=True, help="Linear warm-up length in epochs (per-step schedule), then cosine decay to 0."),
        click.option("--grad-clip", default=d.grad_clip, show_default=True, help="Gradient clipping, L2 norm."),
        click.option("--view-noise", type=click.Choice(["auto", "on", "off"]), default=d.view_noise, show_default=True,
                     help="View-noise augmentation v <- normalise(v + U[-0.5,0.5]^3); auto = on for GFIE stores only (the paper's recipe)."),
        click.option("--seed", default=d.seed, show_default=True, help="Seed of every random draw (same seed, same weights on CPU)."),
        click.option("--device", type=click.Choice(["cpu", "cuda"]), default=d.device, show_default=True, help="Where to train."),
        click.option("--threads", default=d.threads, show_default=True, help="torch CPU threads (keep at the number of free cores)."),
        click.option("--n-max", default="batch", show_default=True,
                     help="Object padding: batch (to the batch's largest count), auto (168 GFIE/CAD-120, 278 GAFA) or a number; frames with more keep their largest masks."),
        click.option("--no-bucket", is_flag=True, help="Do not group batches by object count (slower with per-batch padding)."),
        click.option("--train-frames", type=int, default=None, help="Train on an evenly spaced subset of this many frames (short runs)."),
        click.option("--val-frames", type=int, default=None, help="Validate on a subset of this many frames."),
        click.option("--model-set", multiple=True, metavar="KEY=VALUE",
                     help="Set any ModelConfig field, e.g. --model-set object_distance_scale=0.5 (repeatable)."),
        click.option("--no-progress", is_flag=True, help="No progress bars (one log line per epoch)."),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


def _config(store: str, out: str, model: ModelConfig, **kw) -> "TrainConfig":  # noqa: F821
    from .trainer import TrainConfig

    return TrainConfig(
        store=store, out=out, epochs=kw["epochs"], batch_size=kw["batch_size"], lr=kw["lr"],
        weight_decay=kw["weight_decay"], warmup_epochs=kw["warmup_epochs"], grad_clip=kw["grad_clip"],
        view_noise=kw["view_noise"], seed=kw["seed"], device=kw["device"], threads=kw["threads"],
        n_max=_n_max(kw["n_max"], store), bucket=not kw["no_bucket"], train_frames=kw["train_frames"],
        val_frames=kw["val_frames"], progress=not kw["no_progress"], model=model)


def _log_setup() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")


@click.command()
@click.option("--store", required=True, help="The 3D context store (from `ga3ce-prep run`).")
@click.option("--out", required=True, help="Run folder: checkpoints, config.json, history.csv, curves.png.")
@click.option("--rotation", type=click.Choice(["cyclotorsion", "axis_angle", "none"]), default="cyclotorsion",
              show_default=True, help="Egocentric rotation: GA3CE's cyclotorsion-free one, the axis-angle one "
              "(ablation 'no cyclotorsion') or none (ablation 'no egocentric transform').")
@click.option("--encoding", type=click.Choice(["d3", "standard"]), default="d3", show_default=True,
              help="Point encoding: D3 (direction ++ distance) or standard Fourier features of the point (ablation 'no D3').")
@click.option("--no-objects", is_flag=True, help="Ablation 'appearance + pose': objects replaced by the learned null token.")
@click.option("--no-pose", is_flag=True, help="Ablation 'appearance + objects': every joint replaced by its learned missing-joint embedding.")
@click.option("--no-context", is_flag=True, help="Ablation 'appearance only': g = v, nothing to train (writes a checkpoint eval can read).")
@click.option("--no-ga3ce", is_flag=True, help="Ablation '3D without GA3CE': no egocentric rotation and standard encoding.")
@recipe_options
@click.option("--resume", is_flag=True, help="Continue the run in --out from last.pt (refused if the store or options changed).")
@click.option("--force", is_flag=True, help="Overwrite an existing run, or resume despite a store/config mismatch.")
def train(store, out, rotation, encoding, no_objects, no_pose, no_context, no_ga3ce, resume, force, model_set, **kw):
    """Train the GA3CE 3D gaze transformer on a store with the paper's recipe.

    \b
    Defaults: the paper's recipe (AdamW, weight decay 0.1, 4 warm-up epochs then cosine per step,
    gradient clip 0.1, batch 32, 20 epochs) at lr 3e-4 (docs/training.md "Learning rate"); seeded
    and deterministic on CPU.
    Example: ga3ce-prep train --store synth.zarr --out runs/full
    """
    from .trainer import train as run_train

    _log_setup()
    if no_ga3ce:
        if rotation != "cyclotorsion" or encoding != "d3":
            raise click.UsageError("--no-ga3ce sets --rotation none and --encoding standard itself; drop those options")
        rotation, encoding = "none", "standard"
    try:
        model = ModelConfig(**{"rotation": rotation, "encoding": encoding, "use_objects": not no_objects,
                               "use_pose": not no_pose, "use_context": not no_context, **_model_sets(model_set)})
    except (TypeError, ValueError) as e:
        raise ConfigError(f"model options: {e}") from None
    run = run_train(_config(store, out, model, **kw), resume=resume, force=force)
    click.echo(f"run folder: {run} (best.pt, last.pt, history.csv, curves.png)")
    click.echo(f"next: ga3ce-prep eval --store {store} --checkpoint {run / 'best.pt'}")


@click.command()
@click.option("--store", required=True, help="The store to evaluate on.")
@click.option("--checkpoint", required=True, help="A checkpoint (run folder's best.pt or last.pt).")
@click.option("--split", default="test", show_default=True, help="Split to evaluate: train, val or test.")
@click.option("--json", "json_path", default=None, help="Also write every number as JSON to this file.")
@click.option("--cdf", default="auto", show_default=True,
              help="PNG of the angular-error CDF (model vs v prior); auto = eval_<split>_cdf.png beside the checkpoint; 'none' for no plot.")
@click.option("--snap-cone", type=float, default=None, help="Cone half-angle (degrees) of the snap-to-object baseline; default: chosen on the val split.")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True, help="Where to run the model.")
@click.option("--batch-size", default=256, show_default=True, help="Frames per inference batch.")
@click.option("--threads", default=2, show_default=True, help="torch CPU threads.")
@click.option("--no-scenes", is_flag=True, help="Leave out the per-scene table.")
@click.option("--force", is_flag=True, help="Evaluate on a store other than the one the checkpoint was trained on (e.g. cross-dataset).")
def evaluate(store, checkpoint, split, json_path, cdf, snap_cone, device, batch_size, threads, no_scenes, force):
    """Evaluate a checkpoint: 3D/2D MAE, front/back, per scene, and the baselines on the same frames.

    \b
    Baselines: the view prior v, the head direction from the pose keypoints, and v snapped to the
    nearest object within a cone. The table says whether the model beats each of them.
    """
    from .evaluate import evaluate as run_eval, format_eval_table

    _log_setup()
    r = run_eval(store, checkpoint, split=split, force=force, device=device, batch_size=batch_size,
                 snap_cone_deg=snap_cone, cdf_path=None if cdf == "none" else cdf, json_path=json_path,
                 threads=threads)
    click.echo(format_eval_table(r, per_scene=not no_scenes))
    if "cdf_png" in r:
        click.echo(f"\nCDF plot: {r['cdf_png']}")
    if json_path:
        click.echo(f"JSON: {json_path}")


@click.command()
@click.option("--store", required=True, help="The store every ablation trains and tests on.")
@click.option("--out", required=True, help="Folder for the runs (OUT/<row>/seed<k>) and ablation.{json,csv,png}.")
@click.option("--rows", default=None, help="Comma-separated rows to run (default all): appearance, no-objects, "
              "no-pose, no-ga3ce, full, no-egocentric, no-cyclotorsion, no-d3.")
@click.option("--seeds", default="0", show_default=True, help="Comma-separated seeds; the table shows mean +- std over them.")
@click.option("--split", default="test", show_default=True, help="Split the rows are evaluated on.")
@recipe_options
@click.option("--force", is_flag=True, help="Retrain every row even if its run folder is complete.")
def ablate(store, out, rows, seeds, split, force, model_set, **kw):
    """Train the paper's ablations and print Tables 4 and 5 beside the paper's numbers.

    Finished rows are reused and unfinished ones resumed, so rerunning the command continues.
    Writes OUT/ablation.json, OUT/ablation.csv and OUT/ablation.png (bar chart).
    """
    from .ablate import ablate as run_ablate

    _log_setup()
    try:
        model = ModelConfig(**_model_sets(model_set))
        seed_list = [int(s) for s in seeds.split(",") if s.strip()]
    except (TypeError, ValueError) as e:
        raise ConfigError(f"ablate options: {e}") from None
    base = _config(store, out, model, **kw)
    summary = run_ablate(base, out, rows=[r.strip() for r in rows.split(",")] if rows else None,
                         seeds=seed_list, split=split, force=force)
    click.echo(summary["table"])
    click.echo(f"\nbar chart: {summary['png']}\ntable: {out}/ablation.json, {out}/ablation.csv")
