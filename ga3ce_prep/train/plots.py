"""PNG figures of a run: training curves, angular-error CDFs, per-scene bars, the ablation bar chart
(matplotlib, Agg backend; nothing is shown on screen). The paper's qualitative figures: figures.py."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from .results import MethodMetrics


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_curves(history: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """Training loss (degrees) and validation 3D MAE per epoch, from the run's history rows."""
    plt = _pyplot()
    ep = [h["epoch"] + 1 for h in history]
    fig, ax = plt.subplots(figsize=(6, 3.6), dpi=110)
    ax.plot(ep, [h["train_mae"] for h in history], "o-", label="train loss (3D MAE)")
    if any(np.isfinite(h.get("val_mae", np.nan)) for h in history):
        ax.plot(ep, [h.get("val_mae", np.nan) for h in history], "s-", label="val 3D MAE")
    if history and np.isfinite(history[0].get("val_prior_mae", np.nan)):
        ax.axhline(history[0]["val_prior_mae"], color="grey", ls="--", label="val: v prior")
    ax.set_xlabel("epoch")
    ax.set_ylabel("degrees")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def plot_cdf(errors: dict[str, np.ndarray], path: str | Path, title: str = "") -> Path:
    """Cumulative distribution of per-frame 3D angular errors (degrees), one line per method."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    for name, e in errors.items():
        e = np.sort(np.asarray(e)[np.isfinite(e)])
        if len(e):
            ax.plot(e, np.arange(1, len(e) + 1) / len(e), label=f"{name} (mean {e.mean():.1f})")
    ax.set_xlim(0, 90)
    ax.set_ylim(0, 1)
    ax.set_xlabel("3D angular error (degrees)")
    ax.set_ylabel("fraction of frames")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def plot_per_scene(methods: dict[str, MethodMetrics], labels: dict[str, str], path: str | Path) -> Path:
    """Bars of the 3D MAE per scene (and over all frames), one bar per method: `methods` is an
    evaluation's {key: MethodMetrics}, `labels` {key: legend label} (the evaluation's labels)."""
    plt = _pyplot()
    first = next(iter(methods.values()))
    scenes = list(first.per_scene)
    ticks = [f"{s}\n({first.per_scene[s].n} frames)" for s in scenes] + [f"all\n({first.n} frames)"]
    x, width = np.arange(len(ticks)), 0.8 / len(methods)
    fig, ax = plt.subplots(figsize=(max(6.0, 0.3 * len(ticks) * len(methods) + 2), 4), dpi=110)
    for k, (key, m) in enumerate(methods.items()):
        mae = [m.per_scene[s].mae3d for s in scenes] + [m.mae3d]
        ax.bar(x - 0.4 + (k + 0.5) * width, mae, width, label=labels.get(key, key))
    tilt = len(ticks) > 6
    ax.set_xticks(x, ticks, rotation=30 if tilt else 0, ha="right" if tilt else "center", fontsize=8)
    ax.set_ylabel("3D MAE (degrees, lower is better)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1))
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def plot_ablation(rows: Sequence[dict[str, Any]], path: str | Path, paper_column: str,
                  appearance_is_v: bool = True) -> Path:
    """Bars of our 3D MAE / v prior per ablation row beside the paper's ratio (paper MAE / its
    appearance-only MAE), so a synthetic store and the paper's dataset compare on one axis.
    appearance_is_v False: the paper's appearance row is another network (GAFA's), labelled so."""
    plt = _pyplot()
    names = [r["label"] for r in rows]

    def values(key: str) -> np.ndarray:  # None (e.g. no paper figure for a row) -> NaN, no bar
        return np.array([np.nan if r.get(key) is None else r[key] for r in rows], dtype=float)

    ours, paper = values("ratio"), values(f"paper_ratio_{paper_column}")
    err = np.nan_to_num(values("ratio_std"))
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(max(6, 1.1 * len(rows)), 4), dpi=110)
    ax.bar(x - 0.2, ours, 0.4, yerr=err, label="ours (3D MAE / v prior)")
    base = "appearance only" if appearance_is_v else "GAFA's gaze module, not v"
    ax.bar(x + 0.2, paper, 0.4, label=f"paper {paper_column.upper()} (3D MAE / {base})")
    ax.set_xticks(x, names, rotation=30, ha="right")
    ax.set_ylabel("relative 3D MAE (lower is better)")
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.grid(axis="y", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)
