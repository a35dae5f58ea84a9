"""`ga3ce-prep report RUN_DIR`: one self-contained HTML page of a trained run.

The page (OUT/index.html, default OUT = RUN_DIR/report) holds the evaluation table, the training
curves, the angular-error CDF, per-scene bars, the ablation bars and Tables 4/5 (when RUN_DIR holds
an ablation), the qualitative grid, the decoder's attention and the egocentric space. Every image is
embedded in the page as a data URI, and also written beside it as a PNG.

RUN_DIR is a run folder (`ga3ce-prep train --out RUN_DIR`: config.json, history.csv, best.pt), or
an ablation folder (`ga3ce-prep ablate --out RUN_DIR`: ablation.json), whose full row's first seed
is then the run shown. The test split is evaluated afresh (`evaluate`, on the store the run's
config.json names, or --store), so the page always matches the checkpoint.
"""
from __future__ import annotations

import base64
import csv
import html
import json
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import Ga3ceError
from ..store import open_store
from .checkpoint import build_model, load_checkpoint
from .dataset import ContextDataset
from .evaluate import beside, evaluate, format_eval_table
from .figures import make_figures
from .plots import plot_ablation, plot_curves, plot_per_scene

RUN_FILES = ("config.json", "history.csv", "best.pt")


class ReportError(Ga3ceError):
    """RUN_DIR lacks what the report needs; the message names it and the command that makes it."""


def find_run(run_dir: str | Path) -> tuple[Path, dict[str, Any] | None]:
    """The run folder to report on and RUN_DIR's ablation summary (ablation.json) or None.
    Raises ReportError naming what is missing and how to make it."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ReportError(f"{run_dir} is not a folder: give the run folder of `ga3ce-prep train --store STORE "
                          f"--out {run_dir}` (or the folder of `ga3ce-prep ablate --out`)")
    ablation = json.loads((run_dir / "ablation.json").read_text()) if (run_dir / "ablation.json").is_file() else None
    run = run_dir
    if ablation is not None and not (run_dir / "history.csv").exists():
        run = run_dir / "full" / f"seed{ablation['seeds'][0]}"
        if not run.is_dir():
            raise ReportError(f"{run_dir} holds an ablation without its full row ({run}): add it with "
                              f"`ga3ce-prep ablate --store {ablation['store']} --out {run_dir} --rows full`, "
                              "or give a run folder of `ga3ce-prep train`")
    missing = [name for name in RUN_FILES if not (run / name).is_file()]
    if missing:
        how = ("`ga3ce-prep train --resume ...` to finish the run" if (run / "last.pt").is_file() else
               f"`ga3ce-prep train --store STORE --out {run}` (every file appears after its first epoch)")
        raise ReportError(f"{run} is not a finished run folder: it lacks {', '.join(missing)}. Make them with {how}; "
                          "an ablation folder of `ga3ce-prep ablate --out` works too")
    return run, ablation


def read_history(path: str | Path) -> list[dict[str, float]]:
    """The rows of a run's history.csv as numbers (epoch an int)."""
    with open(path) as f:
        return [{k: int(v) if k == "epoch" else float(v) for k, v in row.items()} for row in csv.DictReader(f)]


def _img(path: Path, caption: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(path.name)}">'
            f"<figcaption>{html.escape(caption)} ({html.escape(path.name)})</figcaption></figure>")


def _section(title: str, *parts: str) -> str:
    return f"<section><h2>{html.escape(title)}</h2>{''.join(parts)}</section>"


def _pre(text: str) -> str:
    return f"<pre>{html.escape(text)}</pre>"


def _note(text: str) -> str:
    return f'<p class="note">{html.escape(text)}</p>'


STYLE = """body{font-family:sans-serif;max-width:1500px;margin:1.5em auto;padding:0 1em;color:#222}
h1{font-size:1.4em}h2{font-size:1.15em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
img{max-width:100%;height:auto;border:1px solid #ddd}figure{margin:.6em 0}figcaption{color:#555;font-size:.9em}
pre{background:#f6f6f6;padding:.7em;overflow-x:auto;font-size:.85em}.note{color:#555}
table{border-collapse:collapse}td{padding:.15em .8em .15em 0;vertical-align:top}"""


def report(run_dir: str | Path, store: str | Path | None = None, split: str = "test", out: str | Path | None = None,
           frames: int = 8, data: str | Path | None = None, device: str = "cpu", threads: int = 2,
           force: bool = False) -> Path:
    """Write the report page of RUN_DIR (module docstring); returns OUT/index.html.

    store: the store to evaluate and draw on (default: the one RUN_DIR's config.json names).
    frames: frames in the qualitative grid and the attention figure. data: the dataset folder
    holding the frames' images (default: the one the store records; grey canvases without it).
    force: report on a store other than the one the checkpoint was trained on (as `eval --force`).
    """
    run, ablation = find_run(run_dir)
    config = json.loads((run / "config.json").read_text())
    store_path = Path(store or config["store"])
    if not store_path.exists():
        raise ReportError(f"the store {store_path} that {run / 'config.json'} names is not there: pass "
                          "--store PATH (the store the run was trained on, or rebuild it with `ga3ce-prep run`)")
    st = open_store(store_path)
    if split not in st.split_names:
        raise ReportError(f"{store_path} has no split {split!r} (splits: {st.split_names}): pass --split")
    out = Path(out) if out is not None else Path(run_dir) / "report"
    out.mkdir(parents=True, exist_ok=True)

    checkpoint = run / "best.pt"
    result = evaluate(st, checkpoint, split=split, force=force, device=device, cdf_path=out / "cdf.png",
                      json_path=out / "eval.json", threads=threads, **beside(checkpoint))
    history = read_history(run / "history.csv")
    ckpt = load_checkpoint(checkpoint)
    figs = make_figures(build_model(ckpt).to(device), ContextDataset(st, split), out, frames,
                        ckpt["config"].get("n_max"), data, device)

    model_keys = ("output", "rotation", "encoding", "use_pose", "use_objects", "use_context", "cone_bias")
    summary = {"run": str(run), "store": str(store_path), "split": f"{split}, {result.n_frames} frames",
               "checkpoint": f"{checkpoint} (epoch {result.epoch} of {config.get('epochs')})",
               "model": result.labels["model"] + " ("
               + ", ".join(f"{k}={config['model'][k]}" for k in model_keys if k in config["model"]) + ")",
               "ga3ce-prep": __version__}
    rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in summary.items())
    curves = plot_curves(history, out / "curves.png")
    per_scene = plot_per_scene(result.methods, result.labels, out / "per_scene.png")
    parts = [f"<h1>Run report, {html.escape(result.labels['model'])}: {html.escape(str(run))}</h1>"
             f"<table>{rows}</table>",
             _section("Evaluation", _pre(format_eval_table(result))),
             _section("Training curves", _img(curves, "training loss and validation 3D MAE per epoch; "
                                                      "the dashed line is the validation v prior")),
             _section("Angular error CDF", _img(Path(str(result.cdf_png)),
                                                        f"per-frame 3D angular error, {split} split")),
             _section("Per scene", _img(per_scene, "3D MAE per scene and over all frames, "
                                                   "the model beside the baselines"))]
    if ablation is not None:
        png = plot_ablation(ablation["rows"], out / "ablation.png", ablation["paper_column"])
        parts.append(_section("Ablations (Tables 4 and 5)", _pre(ablation["table"]),
                              _img(png, "3D MAE relative to the v prior, ours beside the paper's ratio")))
    else:
        parts.append(_section("Ablations", _note(f"{run_dir} holds no ablation (ablation.json): add one with "
                                                 f"`ga3ce-prep ablate --store {store_path} --out {run_dir}`")))
    parts.append(_section("Qualitative results",
                          _img(figs["qualitative"], "frames from the model's best to its worst error")))
    parts.append(_section("Decoder attention", _img(figs["attention"], "cross-attention of the subject token over the "
                                                    "objects; red rings: above the frame's 95th percentile; "
                                                    "star: gaze target")
                          if "attention" in figs else _note("the appearance-only model (g = v) has no attention")))
    parts.append(_section("Egocentric space",
                          _img(figs["egocentric"], "the 3D context after the egocentric transform")))
    page = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f"<title>GA3CE report: {html.escape(run.name)}</title><style>{STYLE}</style></head>"
            f"<body>{''.join(parts)}</body></html>\n")
    index = out / "index.html"
    index.write_text(page, encoding="utf-8")
    return index
