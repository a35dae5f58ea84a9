"""The paper's ablations (Tables 4 and 5, docs/paper.md): one switch each, trained from the same
store with the same recipe, evaluated on the same test frames, printed beside the paper's numbers.
The switches apply to the base model (`ablate --model`, the paper's GA3CE by default); the design
rows (`ga3ce`, `pointer-joint`, `pointer-frozen`; model/methods.py) and the alias row `ours` train
that design with the same recipe. Every row records the fixed design it trained ("design"), and
the alias row's label names it ("pointer-frozen (ours)"). The alias row keeps its folder OUT/ours
(a finished run there is reused only while it holds the design `ours` names today).

Because our store's view prior is not the paper's, rows are also compared as ratios: our 3D MAE /
our v prior's, beside the paper's 3D MAE / its appearance-only MAE. That is like for like on GFIE,
where the paper's "appearance only" is v itself (19.4). On GAFA it is not: the paper's row (22.9)
is GAFA's own single-frame gaze module, not a view prior, so there the appearance row is labelled
as ours (v from the store) and the paper's ratios are marked as taken to GAFA's module
(`DatasetProfile.appearance_is_v`).
"""
from __future__ import annotations

import csv
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..model import ALIASES, METHODS, model_label, resolve
from ..store import open_store
from .checkpoint import run_design
from .evaluate import evaluate
from .plots import plot_ablation
from .profiles import DatasetProfile
from .trainer import TrainConfig, ensure_trained


@dataclass(frozen=True)
class Ablation:
    """One row of the paper's Tables 4 and 5."""

    name: str                             # its run folder, and its name for `train --ablation` and `ablate --rows`
    label: str                            # its label in the printed tables
    overrides: dict[str, Any]             # the ModelConfig fields it changes
    table4: tuple[str, str, str] | None   # (appearance, pose, objects) marks; None = not in Table 4
    table5: tuple[str, str, str] | None   # (egocentric, cyclotorsion, D3) marks; None = not in Table 5
    paper_gfie: float | None              # the paper's 3D MAE on GFIE, degrees; None = not reported
    paper_gafa: float | None              # the paper's 3D MAE on GAFA, degrees; None = not reported
    design: str | None = None             # the fixed design a design or alias row trains; None: the base's


ABLATIONS: tuple[Ablation, ...] = (
    Ablation("appearance", "appearance only (v)", {"use_context": False}, ("x", "-", "-"), None, 19.4, 22.9),
    Ablation("no-objects", "appearance + pose", {"use_objects": False}, ("x", "x", "-"), None, 13.1, 20.3),
    Ablation("no-pose", "appearance + objects", {"use_pose": False}, ("x", "-", "x"), None, None, None),
    Ablation("no-ga3ce", "appearance + 3D w/o GA3CE", {"rotation": "none", "encoding": "standard"},
             ("x", "x", "x*"), None, 18.9, 21.2),
    Ablation("full", "full model", {}, ("x", "x", "x"), ("x", "x", "x"), 11.1, 19.9),
    Ablation("no-egocentric", "no egocentric transform", {"rotation": "none"}, None, ("-", "-", "x"), 14.2, 20.8),
    Ablation("no-cyclotorsion", "no cyclotorsion (axis-angle)", {"rotation": "axis_angle"}, None, ("x", "-", "x"),
             12.1, 20.1),
    Ablation("no-d3", "no D3 (standard encoding)", {"encoding": "standard"}, None, ("x", "x", "-"), 12.9, 20.9),
    *(Ablation(m.name, m.label, {"method": m.name, **m.config}, None, None, None, None, m.name)
      for m in METHODS.values()),
    *(Ablation(alias, f"{design} ({alias})", {"method": design, **METHODS[design].config}, None, None, None, None,
               design) for alias, design in ALIASES.items()),
)
BY_NAME = {a.name: a for a in ABLATIONS}


def _paper_ratio(mae: float | None, appearance_mae: float | None) -> float | None:
    """The paper's MAE over its appearance-only row's (None where the paper reports none)."""
    return mae / appearance_mae if mae and appearance_mae else None


def default_rows(method: str) -> list[str]:
    """Every row for base design `method` (or an alias of it): the paper's ablations, the paper's
    GA3CE and `ours`, less the row that would train the base design again."""
    base = resolve(method)
    return [a.name for a in ABLATIONS
            if a.design is None or (a.name in ("ga3ce", *ALIASES) and a.design != base)]


def row_label(ab: Ablation, base_model: Any) -> str:
    """A row's label in the tables: the full row and the design rows are named by their model's
    config ("GA3CE (paper) (full)", "pointer-frozen (ours)", with any design switch set on top)."""
    if ab.name == "full":
        return f"{model_label(base_model)} (full)"
    if ab.design is not None:
        return model_label(dataclasses.replace(base_model, **ab.overrides))
    return ab.label


def check_row_design(run: Path, ab: Ablation, want: str) -> None:
    """ConfigError when the run folder of a design or alias row holds another design than the row
    trains (the alias has moved on since it was trained)."""
    have = run_design(run)
    if have is not None and have != want:
        raise ConfigError(f"{run} holds {have!r}, but the row {ab.name!r} trains {want!r}"
                          + (f" (the design {ab.name!r} names today)" if ab.name in ALIASES else "")
                          + f": move the folder away (to {run.parent.parent / have / run.name} to keep it as a "
                          f"{have} row), or use another --out")


def ablate(base: TrainConfig, out: str | Path, rows: list[str] | None = None, seeds: list[int] | None = None,
           split: str = "test", force: bool = False) -> dict[str, Any]:
    """Train and evaluate each ablation row (out/<row>/seed<k>) with the base recipe.

    Finished runs are reused while their checkpoint matches the store and the row's configuration
    (`trainer.ensure_trained`; else refused, naming the differences), so the command can be rerun
    to resume; unfinished ones are resumed.
    Returns {rows: [...], paper_column, store, seeds, full_best, table} and writes out/ablation.json,
    out/ablation.csv and out/ablation.png.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = rows or default_rows(base.model.method)
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        raise ValueError(f"unknown ablation rows {unknown}; choose from {list(BY_NAME)}")
    designs = [BY_NAME[n].design for n in names if BY_NAME[n].design is not None]
    if len(designs) != len(set(designs)):
        raise ValueError(f"rows {names} train the same design twice (an alias and the design it names: "
                         f"{', '.join(f'{a} = {d}' for a, d in ALIASES.items())}); keep one")
    seeds = seeds or [base.seed]
    results: list[dict[str, Any]] = []
    prior_mae = math.nan
    for name in names:
        ab = BY_NAME[name]
        maes, evals = [], []
        for seed in seeds:
            run = out / name / f"seed{seed}"
            cfg = dataclasses.replace(base, out=str(run), seed=seed,
                                      model=dataclasses.replace(base.model, **ab.overrides))
            if ab.design is not None and not force:
                check_row_design(run, ab, cfg.model.method)
            # a frozen g0 is the no-objects row, weight for weight
            ensure_trained(cfg, force=force, twin=out / "no-objects" / f"seed{seed}")
            r = evaluate(base.store, run / "best.pt", split=split, cdf_path="auto", threads=base.threads,
                         no_objects=None, compare={})
            maes.append(r.model.mae3d)
            prior_mae = r.methods["view_prior"].mae3d
            evals.append(r)
        mae = float(np.mean(maes))
        row: dict[str, Any]  # a JSON row of the summary
        row = {"name": name, "design": dataclasses.replace(base.model, **ab.overrides).method,
               "label": row_label(ab, base.model), "table4": ab.table4, "table5": ab.table5,
               "mae3d": mae, "mae3d_std": float(np.std(maes)) if len(maes) > 1 else None,
               "mae3d_seeds": maes, "ratio": mae / prior_mae,
               "ratio_std": float(np.std(maes)) / prior_mae if len(maes) > 1 else None,
               "mae2d": float(np.mean([e.model.mae2d for e in evals])),
               "paper_gfie": ab.paper_gfie, "paper_gafa": ab.paper_gafa,
               "paper_ratio_gfie": _paper_ratio(ab.paper_gfie, BY_NAME["appearance"].paper_gfie),
               "paper_ratio_gafa": _paper_ratio(ab.paper_gafa, BY_NAME["appearance"].paper_gafa)}
        results.append(row)
    profile = DatasetProfile.for_store(open_store(base.store))
    full = next((r for r in results if r["name"] == "full"), None)
    others = [r for r in results if r["name"] != "full" and (r["table4"] or r["table5"])]  # the paper's rows
    full_best = None if full is None else all(full["mae3d"] < r["mae3d"] for r in others)
    summary = {"store": str(base.store), "dataset": profile.name, "model": base.model.method,
               "split": split, "seeds": seeds,
               "epochs": base.epochs, "train_frames": base.train_frames, "v_prior_mae3d": prior_mae,
               "paper_column": profile.paper_column, "appearance_is_v": profile.appearance_is_v,
               "rows": results, "full_best": full_best}
    summary["table"] = format_ablation_table(summary)
    (out / "ablation.json").write_text(json.dumps(summary, indent=2, default=float))
    with open(out / "ablation.csv", "w", newline="") as f:
        keys = ["name", "design", "label", "mae3d", "mae3d_std", "ratio", "mae2d", "paper_gfie", "paper_gafa",
                "paper_ratio_gfie", "paper_ratio_gafa"]
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        w.writerows(results)
    summary["png"] = str(plot_ablation(results, out / "ablation.png", profile.paper_column, profile.appearance_is_v))
    return summary


def _num(x: float | None, std: float | None = None) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "  -  "
    return f"{x:5.2f}" + (f" +- {std:4.2f}" if std is not None else "")


def _table_lines(rows: dict[str, dict], summary: dict[str, Any], table: str, marks: tuple[str, str, str]) -> list[str]:
    """One of the paper's tables: a header, then per ablation in it its marks, the paper's 3D MAE
    and ratio, ours (mean +- std over seeds) and ratio."""
    col = summary["paper_column"]
    like = summary.get("appearance_is_v", True)
    out = [f"{'':30s} {marks[0]:>5s} {marks[1]:>5s} {marks[2]:>5s} | {'paper ' + col.upper():>9s} "
           f"{'ratio' if like else 'ratio+':>6s} | {'ours':>13s} {'ratio':>6s}"]
    for a in ABLATIONS:
        r, m = rows.get(a.name), getattr(a, table)
        if r is None or m is None:
            continue
        label = r["label"] if like or a.name != "appearance" else "appearance only: v (ours)"
        out.append(f"{label:30s} {m[0]:>5s} {m[1]:>5s} {m[2]:>5s} | "
                   f"{_num(r['paper_' + col]):>9s} {_num(r['paper_ratio_' + col]):>6s} | "
                   f"{_num(r['mae3d'], r['mae3d_std']):>13s} {r['ratio']:6.3f}")
    return out


def format_ablation_table(summary: dict[str, Any]) -> str:
    """Tables 4 and 5 laid out as in the paper, with our 3D MAE and ratio beside the paper's."""
    rows = {r["name"]: r for r in summary["rows"]}
    seeds = summary["seeds"]
    head = (f"{summary['store']} | split {summary['split']} | v prior 3D MAE {summary['v_prior_mae3d']:.2f} deg | "
            f"{summary['epochs']} epochs | seeds {seeds}")
    out = [head, "", "Table 4: input components (x = used)"]
    out += _table_lines(rows, summary, "table4", ("App.", "Pose", "Obj."))
    out += ["  (x* = 3D context fed without the egocentric transform and with standard encoding)", "",
            "Table 5: GA3CE components (x = used)"]
    out += _table_lines(rows, summary, "table5", ("Ego.", "Cyc.", "D3"))
    ours = [(a, rows[a.name]) for a in ABLATIONS if a.table4 is None and a.table5 is None and a.name in rows]
    if ours:
        out += ["", "The other designs, same recipe (ga3ce-prep train --model; docs/training.md \"The output\")"]
        out += [f"{r['label']:30s} {'':17s} | {'':16s} | {_num(r['mae3d'], r['mae3d_std']):>13s} {r['ratio']:6.3f}"
                for a, r in ours]
    out.append("")
    out.append("ratio = 3D MAE / appearance-only 3D MAE (ours: the store's v prior on the same frames)")
    if not summary.get("appearance_is_v", True):
        out.append(f"ratio+ = the paper's 3D MAE / its Appearance row, which on {summary['paper_column'].upper()} is "
                   "GAFA's own gaze module (22.9), not a view prior: not like for like with our ratio to v")
    if summary["full_best"] is True:
        out.append("the full model is best: every ablation row of the paper's tables has a higher 3D MAE")
    elif summary["full_best"] is False:
        worse = [r["label"] for r in summary["rows"] if r["name"] != "full" and (r["table4"] or r["table5"])
                 and r["mae3d"] <= rows["full"]["mae3d"]]
        out.append("the full model is NOT best: " + ", ".join(worse) + " reached a 3D MAE at or below it")
    return "\n".join(out)
