"""`Arm` and `Experiment`: worlds x arms x seeds, trained unless done, scored on a split and on
transfer worlds, and one results file that carries the conditions of every figure in it.

Layout under an output folder OUT (the demo's is `out/`):

    OUT/<world>/              the world's dataset (World.ensure_data; `World.data` names another
                              world's folder for worlds that differ in their pipeline only)
    OUT/<world>.zarr          its store
    OUT/runs/<experiment>/<world>/<arm>/seed<k>/   a run (train/trainer.py's run folder)
    OUT/runs/<experiment>/results.json             the results (`run_experiment`)

A run is trained unless it is done (`trainer.ensure_trained`: finished, same store, same
configuration); a score is computed unless the run folder holds one for the same checkpoint, store
and split (`ensure_scored`). Rerunning an experiment is so a check, and an interrupted one goes on.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..files import file_sha256
from .conditions import code, describe, machine
from .world import World


@dataclass(frozen=True)
class Arm:
    """One arm of an experiment: a row of the paper's ablations or one of our designs
    (train/ablate.py `ABLATIONS`: full, no-objects, no-d3, ..., ga3ce, pointer-frozen, ours), with
    training-recipe fields changed for it alone (TrainConfig's names: batching, lr, epochs, ...) and
    model fields changed on top of the row's (a design under study: ModelConfig's names)."""

    row: str                                                # the ablation row or design
    recipe: dict[str, Any] = field(default_factory=dict)    # TrainConfig fields this arm changes
    model: dict[str, Any] = field(default_factory=dict)     # ModelConfig fields changed on top of the row's
    name: str = ""                                          # its run folder; "" = the row's name

    @property
    def folder(self) -> str:
        return self.name or self.row


@dataclass(frozen=True)
class Experiment:
    """Arms trained on each training world with each seed, scored on `split` of that world and on
    the test split of every transfer world (the paper's Table 2: unseen rooms, another camera)."""

    name: str                                               # its name: `ga3ce-prep experiment run NAME`
    question: str                                           # what it asks, one sentence
    worlds: dict[str, World]                                # training worlds by name (their folders)
    arms: tuple[Arm, ...]                                   # the arms, trained in this order
    seeds: tuple[int, ...] = (0,)                           # training seeds of every arm
    split: str = "test"                                     # the split scored ("val" while choosing a design)
    transfer: dict[str, World] = field(default_factory=dict)  # worlds only scored on, by name
    recipe: dict[str, Any] = field(default_factory=dict)   # TrainConfig fields of every arm
    base: str = "ga3ce"                                     # the design the ablation switches apply to
    # the checkpoint scored: "best" (the epoch of the lowest validation 3D MAE) or "last" (the end of
    # the schedule: no arm gains from a noisier validation curve)
    checkpoint: str = "best"
    runs: str = ""                                          # whose run folders it trains in ("": its own)

    def __post_init__(self) -> None:
        from ..train.ablate import BY_NAME

        if unknown := [a.row for a in self.arms if a.row not in BY_NAME]:
            raise ConfigError(f"experiment {self.name}: unknown rows {unknown}; choose from {list(BY_NAME)}")
        folders = [a.folder for a in self.arms]
        if len(set(folders)) != len(folders):
            raise ConfigError(f"experiment {self.name}: two arms share a folder ({folders}); name them")
        if set(self.worlds) & set(self.transfer):
            raise ConfigError(f"experiment {self.name}: a world is both trained on and transfer")
        if self.checkpoint not in ("best", "last"):
            raise ConfigError(f"experiment {self.name}: checkpoint must be best or last, got {self.checkpoint!r}")

    def with_seeds(self, seeds: tuple[int, ...]) -> Experiment:
        return dataclasses.replace(self, seeds=tuple(seeds))

    def with_worlds(self, names: tuple[str, ...]) -> Experiment:
        """The experiment on these of its training worlds alone (the transfer worlds kept)."""
        if unknown := [n for n in names if n not in self.worlds]:
            raise ConfigError(f"experiment {self.name}: no training worlds {unknown}; it has {list(self.worlds)}")
        return dataclasses.replace(self, worlds={n: self.worlds[n] for n in names})

    def data_dirs(self, out: Path) -> dict[str, Path]:
        """Each world's dataset folder: OUT/<its `data`, else its name> (worlds that differ in their
        pipeline only name one dataset)."""
        return {name: Path(out) / (w.data or name) for name, w in {**self.worlds, **self.transfer}.items()}

    def stores(self, out: Path, workers: int | None = None, progress: bool = True) -> dict[str, Path]:
        """Every world's store, OUT/<name>.zarr, made or checked (`World.ensure`)."""
        data = self.data_dirs(out)
        return {name: w.ensure(data[name], self.store_path(out, name), workers=workers, progress=progress)
                for name, w in {**self.worlds, **self.transfer}.items()}

    def store_path(self, out: Path, world: str) -> Path:
        return Path(out) / f"{world}.zarr"

    def run_dir(self, out: Path, world: str, arm: Arm, seed: int) -> Path:
        return Path(out) / "runs" / (self.runs or self.name) / world / arm.folder / f"seed{seed}"

    def results_path(self, out: Path) -> Path:
        return Path(out) / "runs" / self.name / "results.json"

    def train_config(self, out: Path, world: str, arm: Arm, seed: int, progress: bool = True) -> Any:
        """The TrainConfig of one run: the base design with the row's switches, the experiment's
        recipe, then the arm's."""
        from ..model import ModelConfig
        from ..train import TrainConfig
        from ..train.ablate import BY_NAME

        model = dataclasses.replace(ModelConfig.for_method(self.base), **{**BY_NAME[arm.row].overrides, **arm.model})
        frames = {"train_frames": self.worlds[world].train_frames} if self.worlds[world].train_frames else {}
        return TrainConfig(store=str(self.store_path(out, world)), out=str(self.run_dir(out, world, arm, seed)),
                           seed=seed, progress=progress, model=model, **{**frames, **self.recipe, **arm.recipe})


def ensure_scored(store: Path, checkpoint: Path, split: str, threads: int = 2) -> dict[str, Any]:
    """The checkpoint's model scored on `split` of `store` (train/evaluate.py, without siblings or
    plots): 3D and 2D MAE, median, scored N of M, and the v prior on the same frames. Kept in the
    run folder as scored-<split>-<key>.json, the key naming the checkpoint's bytes, the store's
    fingerprint and the split, and read back while they hold. Per scored session: its frames and
    both 3D MAEs (`sessions`), for intervals over sessions (intervals.py); the same for the frames
    whose gaze target is at a stored object and for the others (`target`); the weight the model
    gives the null token, the objects and the gazed object (`attention`, evaluate.object_attention)."""
    import hashlib

    from ..store import open_store
    from ..train import evaluate
    from ..train.dataset import store_fingerprint

    fingerprint = store_fingerprint(open_store(store))
    key = hashlib.sha256(f"{file_sha256(checkpoint)}|{fingerprint}|{split}".encode()).hexdigest()[:16]
    path = Path(checkpoint).parent / f"scored-{split}-{key}.json"
    if path.is_file() and "attention" in (kept := json.loads(path.read_text())):
        return kept
    r = evaluate(str(store), checkpoint, split=split, cdf_path=None, no_objects=None, compare={}, threads=threads)
    m = r.methods["model"]
    score = {"mae3d": m.mae3d, "mae2d": m.mae2d, "median3d": m.median3d, "scored": r.n_frames,
             "expected": r.frames.expected, "protocol": r.frames.protocol, "epoch": r.epoch,
             "v_prior_mae3d": r.methods["view_prior"].mae3d, "label": r.labels["model"],
             "store_fingerprint": fingerprint,
             # per scored session (the store's scene): [frames, the model's 3D MAE, v's], for intervals
             "sessions": {name: [g.n, g.mae3d, r.methods["view_prior"].per_scene[name].mae3d]
                          for name, g in m.per_scene.items()},
             # [frames, the model's 3D MAE, v's] where the gaze target is at a stored object, and elsewhere
             "target": {k: [getattr(m, k).n, getattr(m, k).mae3d, getattr(r.methods["view_prior"], k).mae3d]
                        for k in ("at_object", "elsewhere")},
             # where the model's weight goes: null token, objects, the gazed object (None without objects)
             "attention": r.attention}
    path.write_text(json.dumps(score, indent=2, default=float))
    return score


def training_curve(run: Path) -> dict[str, float]:
    """A finished run's training against validation 3D MAE (its history.csv): at the epoch best.pt
    holds (lowest validation MAE) and at the last; a model that memorises its training frames errs
    far less on them than on validation."""
    from ..train.report import read_history

    rows = read_history(Path(run) / "history.csv")
    best = min(rows, key=lambda r: r["val_mae"])
    return {"epochs": len(rows), "best_epoch": best["epoch"] + 1, "train_best": best["train_mae"],
            "val_best": best["val_mae"], "train_last": rows[-1]["train_mae"], "val_last": rows[-1]["val_mae"]}


def portable(value: Any, out: Path) -> Any:
    """`value` (a results record) with every absolute path (values and keys) under `out` written
    relative to it, every one inside this package relative to the package's folder
    ("ga3ce_prep/pipelines/..."), and every one in the registry's model cache as "{models
    cache}/...", so a results file reads the same on any machine and can be kept beside a study."""
    from ..weights.registry import cache_dir

    if isinstance(value, dict):
        return {portable(k, out): portable(v, out) for k, v in value.items()}
    if isinstance(value, list):
        return [portable(v, out) for v in value]
    if isinstance(value, str) and value.startswith("/"):
        for root, prefix in ((Path(out).resolve(), ""), (Path(__file__).resolve().parents[2], ""),
                             (cache_dir().resolve(), "{models cache}/")):
            if value == str(root) or value.startswith(str(root) + "/"):
                return prefix + os.path.relpath(value, root)
    return value


def _world_record(world: World, store: Path) -> dict[str, Any]:
    """A world's declaration and what its store says it was made with (pipeline, stage backends
    and parameters: the segmenter and the cues' noise)."""
    from ..store import open_store

    attrs = open_store(store).attrs
    return {**world.to_json(), "store": str(store), "pipeline_file": attrs.get("pipeline"),
            "stages": attrs.get("stages")}


def run_experiment(exp: Experiment, out: str | Path, progress: bool = True, workers: int | None = None,
                   echo: Any = print, stores: dict[str, Path] | None = None) -> dict[str, Any]:
    """Make every world's store, train every run unless done, score each, and write the results
    (returned, and at `exp.results_path(out)`): the experiment, its worlds as declared and as their
    stores record them, each arm's resolved training config, the machine and the code, and one row
    per (world, arm, seed, scored-on world) with its 3D MAE and "scored N of M". stores: the
    worlds' stores when the caller made them already (else `World.ensure` makes or checks them)."""
    from ..model import ModelConfig
    from ..train.ablate import BY_NAME, check_row_design, row_label
    from ..train.trainer import ensure_trained

    out = Path(out)
    conditions = {"code": code(), "machine": machine()}   # of the call's start: what trains is this code
    stores = stores or exp.stores(out, workers=workers, progress=progress)
    scores: list[dict[str, Any]] = []
    arms: dict[str, dict[str, Any]] = {}
    t0 = time.perf_counter()
    for world in exp.worlds:
        for arm in exp.arms:
            ab = BY_NAME[arm.row]
            for seed in exp.seeds:
                cfg = exp.train_config(out, world, arm, seed, progress=progress)
                run = Path(cfg.out)
                if ab.design is not None:
                    check_row_design(run, ab, cfg.model.method)
                twin = exp.run_dir(out, world, Arm("no-objects"), seed)
                echo(f"  {world} / {arm.folder} / seed {seed}: {run}")
                best = ensure_trained(cfg, twin=twin)
                scored = best if exp.checkpoint == "best" else run / "last.pt"
                curve = training_curve(run)
                recipe = {k: v for k, v in cfg.to_dict().items() if k not in ("store", "out", "seed", "progress")}
                arms[arm.folder] = {"row": arm.row, "design": cfg.model.method,
                                    "label": row_label(ab, ModelConfig.for_method(exp.base)), "config": recipe}
                for on, split in [(world, exp.split), *((t, "test") for t in exp.transfer)]:
                    s = ensure_scored(stores[on], scored, split, threads=cfg.threads)
                    scores.append({"world": world, "arm": arm.folder, "seed": seed, "scored_on": on, "split": split,
                                   "run": str(run), **s, "curve": curve})
    results = {"experiment": exp.name, "question": exp.question, "split": exp.split, "seeds": list(exp.seeds),
               "checkpoint": exp.checkpoint,
               "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "seconds": round(time.perf_counter() - t0, 1),
               **conditions,
               "worlds": {n: _world_record(w, stores[n]) for n, w in exp.worlds.items()},
               "transfer": {n: _world_record(w, stores[n]) for n, w in exp.transfer.items()},
               "arms": arms, "scores": scores}
    results = portable(results, out)   # paths relative to OUT: the file reads the same anywhere
    path = exp.results_path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=2, default=float))
    return results


def mae_table(results: dict[str, Any]) -> dict[tuple[str, str], dict[str, list[float]]]:
    """{(training world, scored-on world): {arm: [3D MAE per seed, in seed order]}}, arms in the
    experiment's order, then the v prior as the arm "v prior" (one value: no seed changes it)."""
    table: dict[tuple[str, str], dict[str, list[float]]] = {}
    prior: dict[tuple[str, str], float] = {}
    for s in sorted(results["scores"], key=lambda s: s["seed"]):
        table.setdefault((s["world"], s["scored_on"]), {}).setdefault(s["arm"], []).append(s["mae3d"])
        prior[(s["world"], s["scored_on"])] = s["v_prior_mae3d"]
    for key, v in prior.items():
        table[key]["v prior"] = [v]
    return table


def format_results(results: dict[str, Any]) -> str:
    """Any results file as text: per training world and scored-on world, each arm's 3D MAE (mean +-
    std over seeds, its ratio to v's, and each seed's), scored N of M; each arm's gain over no
    objects with its interval; then the machine and the code."""
    arms = results["arms"]
    lines = [f"{results['experiment']}: {results['question']}"]
    if results.get("checkpoint", "best") == "last":
        lines.append("(each run's last epoch scored, not its best validation epoch)")
    for (world, on), cell in mae_table(results).items():
        w = results["worlds"][world] if on == world else results["transfer"][on]
        first = next(s for s in results["scores"] if s["world"] == world and s["scored_on"] == on)
        what = w["protocol"] if on == world else f"transfer (trained on {world})"
        lines += ["", f"{on}: {what}, {first['split']} split, scored {first['scored']} of {first['expected']}; "
                      f"{_describe_world(w)}",
                  f"  {'3D MAE (deg)':30s} {'mean +- std':>14s}  {'of v':>5s}  seeds"]
        prior = cell["v prior"][0]
        for arm, maes in cell.items():
            label = arms[arm]["label"] if arm in arms else arm
            mean = f"{np.mean(maes):.2f}" + (f" +- {np.std(maes):.2f}" if len(maes) > 1 else "")
            seeds = " / ".join(f"{x:.2f}" for x in maes) if len(maes) > 1 else ""
            lines.append(f"  {label:30s} {mean:>14s}  {np.mean(maes) / prior:5.3f}  {seeds}".rstrip())
        if on == world:
            lines += _curve_lines(results, world) + _attention_lines(results, world)
    lines += _gain_lines(results)
    c = results["code"]
    lines += ["", f"machine: {describe(results['machine'])}; code {c['version']}"
              + (f" at {c['commit'][:7]}{' (uncommitted changes)' if c['dirty'] else ''}" if c.get("commit") else "")]
    return "\n".join(lines)


def _curve_lines(results: dict[str, Any], world: str) -> list[str]:
    """Per arm, training against validation 3D MAE at the best and the last epoch, mean over seeds."""
    curves: dict[str, list[dict[str, float]]] = {}
    for s in results["scores"]:
        if s["world"] == world and s["scored_on"] == world and "curve" in s:
            curves.setdefault(s["arm"], []).append(s["curve"])
    if not curves:
        return []
    lines = [f"  {'train / val 3D MAE (deg)':30s} {'best epoch':>14s}  {'last epoch':>12s}  best epochs"]
    for arm, cs in curves.items():
        m = {k: np.mean([c[k] for c in cs]) for k in ("train_best", "val_best", "train_last", "val_last")}
        label = results["arms"][arm]["label"]
        lines.append(f"  {label:30s} {m['train_best']:6.2f} / {m['val_best']:5.2f}  {m['train_last']:5.2f} / "
                     f"{m['val_last']:5.2f}  " + " / ".join(str(int(c["best_epoch"])) for c in cs))
    return lines


def _attention_lines(results: dict[str, Any], world: str) -> list[str]:
    """Per arm with objects, where its weight goes on the scored split (evaluate.object_attention),
    mean over seeds: the null token (g0), the gazed object against each other one, and the share of
    frames where the gazed object gets the most weight against uniform weights' share."""
    by_arm: dict[str, list[dict[str, float]]] = {}
    for s in results["scores"]:
        if s["world"] == world and s["scored_on"] == world and s.get("attention"):
            by_arm.setdefault(s["arm"], []).append(s["attention"])
    if not by_arm:
        return []
    lines = [f"  {'weight (target at an object)':30s} {'null':>5s} {'gazed':>6s} {'other':>6s}  gazed most (uniform)"]
    for arm, rows in by_arm.items():
        m = {k: np.mean([r[k] for r in rows]) for k in ("null", "on_target", "per_other", "target_top", "chance_top")}
        if not any(r["at_object_frames"] for r in rows):   # no gaze target points (GAFA's annotation)
            lines.append(f"  {results['arms'][arm]['label']:30s} {m['null']:5.2f}  (no target at an object: "
                         "the annotation gives no target point)")
            continue
        lines.append(f"  {results['arms'][arm]['label']:30s} {m['null']:5.2f} {m['on_target']:6.3f} "
                     f"{m['per_other']:6.3f}  {m['target_top']:.0%} ({m['chance_top']:.0%})")
    return lines


def _gain_lines(results: dict[str, Any], base: str = "no-objects") -> list[str]:
    """Each arm's gain over `base` with its session interval (intervals.py), pooled over the
    training worlds that differ in their seed alone, scored on themselves; none without sessions."""
    from .intervals import format_gain, gain, target_gains

    if base not in results["arms"] or len(results["arms"]) < 2 or not all("sessions" in s for s in results["scores"]):
        return []
    groups: dict[str, list[str]] = {}
    for name, w in results["worlds"].items():
        like = {k: v for k, v in w.items() if k not in ("seed", "data", "store", "stages")}
        groups.setdefault(json.dumps(like, sort_keys=True, default=str), []).append(name)
    lines = ["", f"gain over {base} (1 - MAE ratio), 95% interval over the scored sessions:"]
    for worlds in groups.values():
        lines.append(f"  {', '.join(worlds)}:")
        for arm in (a for a in results["arms"] if a != base):
            lines.append(f"    {format_gain(gain(results, worlds, arm, base))}")
            if split := target_gains(results, worlds, arm, base):
                lines.append("      where the target is " + "; ".join(
                    f"{'at an object' if k == 'at_object' else 'elsewhere'}: {100 * g:+.1f}% ({n} frames)"
                    for k, (g, n) in split.items()))
    return lines


def _describe_world(w: dict[str, Any]) -> str:
    return World.from_json(w).describe() + f", pipeline {w['pipeline']}"
